"""Which commissioning and which plan serve ``mpc-rig`` best: the orifice law tried or not, and
the plausible rigs and rule a plan picks its cut with.

On ``bench_mpc.py``'s fresh family draws (the same ``--seed``, the same draws, the same two
simulated strokes per rig) it commissions each draw's rig as ``mpc-rig`` does, once with the
stated orifice law only (``mpc-rig``'s default) and once trying both laws
(``pneugym commission --orifice-models thesis iso6358``). For each fit it scores every cut-off
time, on every control period, on the rig's truth (what the oracle searches) and on the plausible
rigs of every plan setting: ``--spreads`` (the Laplace draws' standard deviations times this),
with and without the other model forms the strokes cannot rule out (``forms``), ``--members``
plausible rigs each.
Every rule (``worst`` / ``mean`` return within ``--margins`` control periods either side) then
picks its cut, and the truth's return at that cut is the episode's (``mpc-rig`` cuts on the
clock). ``--stick-weights`` prices a stick-slip of the plausible rigs at that many times the
environment's ``w_stick`` (``RigModelPolicy(stick_weight=...)``; the truth's return, the figure,
keeps the environment's), ``--stall-weights`` a stroke not completed so against ``w_stall``;
``--shifts`` moves the plan's cut that many control periods later
(``RigModelPolicy(shift_periods=...)``), ``--min-completions`` lets it take only a cut at least
that share of its plausible rigs complete (``RigModelPolicy(min_completion=...)``). The
plausible rigs are simulated once and every price applied to their figures (the objective is
linear in the weights; tests/test_commission.py checks it against the planner's own returns).
Reports the oracle fraction, stick-slip rate, stalls and strokes not completed of every setting
over all draws, the orifice law found against the truth's, and writes ``mpc_plan.json`` (every
draw's cuts and figures) and ``mpc_plan.png``; ``--fits DIR`` keeps every commissioning fit
there and reuses it.

The plans here search every control period (``RigModelPolicy(coarse=1)``); ``mpc-rig`` searches
every fourth, then every period around its three best and around the cut it takes
(:func:`agents.oracle.settle_windows`), and took the same cuts on all 40 validation draws.

    python benchmarks/bench_mpc_plan.py --seed 3000000    # validation draws, about 2 h on 2 cores
    python benchmarks/bench_mpc_plan.py --seed 3000000 --laws stated --spreads 2 --margins 1 \
        --forms off --stick-weights 1 1.5 2 3 4 --shifts 0 1 2 3 4   # about 50 min
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
from common import ROOT, add_commission_args, commission_overrides  # noqa: F401

LAWS = {"stated law": None, "both laws": ("thesis", "iso6358")}
LAW_CHOICES = {"stated": "stated law", "both": "both laws"}
#: what a cut is scored by (``w_stall`` prices a stroke not completed; a stall is one stuck short)
FIGURES = ("objective", "stick_slip_events", "completed", "stalled")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--episodes", type=int, default=40, help="family draws (one episode each)")
    ap.add_argument("--seed", type=int, default=3_000_000,
                    help="seed of the draws (bench_mpc.py's; default the validation draws)")
    ap.add_argument("--spreads", type=float, nargs="+", default=[1.0, 2.0],
                    help="spreads of the plausible rigs (times the fit's standard deviations)")
    ap.add_argument("--margins", type=int, nargs="+", default=[0, 1, 3],
                    help="half-widths of the rules' windows [control periods]")
    ap.add_argument("--members", type=int, default=8, help="plausible rigs per plan (mpc-rig's 8)")
    ap.add_argument("--laws", nargs="+", choices=list(LAW_CHOICES), default=list(LAW_CHOICES),
                    help="commission with the stated orifice law, trying both, or each")
    ap.add_argument("--forms", nargs="+", choices=["off", "on"], default=["off", "on"],
                    help="plan without / with the other forms the strokes cannot rule out")
    ap.add_argument("--stick-weights", type=float, nargs="+", default=[1.0],
                    help="a plausible rig's stick-slip priced at this many times w_stick")
    ap.add_argument("--stall-weights", type=float, nargs="+", default=[1.0],
                    help="a plausible rig's stall priced at this many times w_stall")
    ap.add_argument("--shifts", type=int, nargs="+", default=[0],
                    help="the plan's cut moved this many control periods later")
    ap.add_argument("--min-completions", type=float, nargs="+", default=[1.0],
                    help="the plan takes only cuts at least this share of its plausible rigs "
                         "complete (mpc-rig's 1; 0: any cut)")
    ap.add_argument("--fits", default=None,
                    help="folder keeping the commissioning fits (reused when there)")
    ap.add_argument("--out", default="bench/mpc-plan", help="folder for the results")
    add_commission_args(ap)
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.members < 1 or min(args.spreads) < 0 or min(args.margins) < 0 \
            or not all(map(math.isfinite, args.spreads)):
        ap.error("--episodes and --members must be >= 1, --spreads (finite) and --margins >= 0")
    for name in ("stick_weights", "stall_weights"):
        v = getattr(args, name)
        if min(v) < 0 or not all(map(math.isfinite, v)):
            ap.error(f"--{name.replace('_', '-')} must be finite and >= 0")
    if min(args.shifts) < 0:
        ap.error("--shifts must be >= 0")
    if not all(0 <= q <= 1 for q in args.min_completions):
        ap.error("--min-completions must be shares in [0, 1]")
    from tqdm import tqdm

    from agents.evaluation.commissioning import commissioning_runs
    from agents.evaluation.run import oracle_fraction, run_policy
    from agents.evaluation.specs import evaluation_env_config, make_named_policy
    from agents.evaluation.suites import family_draws
    from agents.mpc_rig import completing
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    cfg = evaluation_env_config({})
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    conds = family_draws(args.seed, args.episodes)  # the draws of bench_mpc.py
    ref, ref_sticks = {}, {}
    for spec in ("conventional", "oracle"):
        out = run_policy(make_named_policy(spec, probe)[1], conds, cfg, args.seed)
        ref[spec] = [float(v) for v in out["objective"]]
        ref_sticks[spec] = [int(v) for v in out["stick_slip_events"]]
    _, policy = make_named_policy("mpc-rig", probe)
    policy.n_members = args.members
    opts = dict(policy.commission_options)
    opts.update(commission_overrides(args))
    laws = {LAW_CHOICES[k]: LAWS[LAW_CHOICES[k]] for k in args.laws}
    settings = [(law, s, forms) for law in laws for s in args.spreads
                for forms in (f == "on" for f in args.forms)]
    w_stick, w_stall = float(probe.weights["w_stick"]), float(probe.weights["w_stall"])
    draws = []
    for g, c in enumerate(tqdm(conds, desc="commissioning", unit="rig")):
        runs = commissioning_runs(c.rig_changes, probe.rig, args.seed, g)
        truth = {k: v for k, v in c.rig_changes if k in ("line.model", "valve.flow_model")}
        d = {"draw": g, "truth_form": [truth.get("line.model"), truth.get("valve.flow_model")],
             "fits": {}, "returns": {}, "sticks": {}, "stalls": {}, "completed": {},
             "cuts": {}}
        truth_j: dict = {}
        plans: dict = {}  # mean returns by plausible rigs (forms adds none where none is kept)
        for law, law_models in laws.items():
            t0 = time.perf_counter()
            model = _fit(runs, law_models, opts, args.fits and Path(args.fits) / f"{g}-{law}",
                         {"seed": args.seed, "draw": g})
            d["fits"][law] = {"form": [model.rig.line.model, model.rig.valve.flow_model],
                              "misfit": model.misfit, "refitted": model.refitted,
                              "seconds": time.perf_counter() - t0,
                              "alternatives": [[r.line.model, r.valve.flow_model, dv] for r, dv
                                               in zip(model.alternatives,
                                                      model.alternative_deltas)]}
            for _, s, forms in (x for x in settings if x[0] == law):
                policy.spread, policy.forms = s, forms
                policy.set_model(model)
                key = (law, tuple(policy.changes))
                scored = plans[key] = plans.get(key) or _scores(policy, c, probe.rig, truth_j)
                done = {t: f[2] for t, f in scored.items()}
                for w, ws, rule, m, sh, q in ((w, ws, r, m, sh, q) for w in args.stick_weights
                                              for ws in args.stall_weights
                                              for r in ("worst", "mean") for m in args.margins
                                              for sh in args.shifts
                                              for q in args.min_completions):
                    mean = {t: j - (w - 1.0) * w_stick * n - (ws - 1.0) * w_stall * (1.0 - ok)
                            for t, (j, n, ok, _) in scored.items()}
                    t = _later(_pick(mean, policy.period, rule, m, completing(done, q)), sh,
                               policy.period)
                    k = _key(law, s, forms, rule, m, w, sh, ws, q)
                    _truth_at([t], policy, c, truth_j)  # (a shifted cut past the grid)
                    d["cuts"][k] = t
                    d["returns"][k], d["sticks"][k], d["completed"][k], d["stalls"][k] = truth_j[t]
        d["stick_free_window"] = _window(truth_j, policy.period)
        draws.append(d)
    conv, orc = float(np.mean(ref["conventional"])), float(np.mean(ref["oracle"]))
    table = {k: oracle_fraction(float(np.mean([d["returns"][k] for d in draws])), conv, orc)
             for k in draws[0]["returns"]}
    sticks = {k: float(np.mean([d["sticks"][k] > 0 for d in draws])) for k in table}
    for spec in ref_sticks:  # the oracle's, and the conventional stroke's (the rig as it is)
        sticks[spec] = float(np.mean([n > 0 for n in ref_sticks[spec]]))
    stalls = {k: int(sum(d["stalls"][k] > 0 for d in draws)) for k in table}
    undone = {k: int(sum(not d["completed"][k] for d in draws)) for k in table}
    for k, f in sorted(table.items(), key=lambda kv: -kv[1]):
        print(f"{k:62s} oracle fraction {f:.3f}, stick-slip {100 * sticks[k]:.1f} %, "
              f"stalls {stalls[k]}, not completed {undone[k]}")
    for spec in ref_sticks:
        print(f"{spec:62s} stick-slip {100 * sticks[spec]:.1f} %")
    for k in table:  # where a plan sticks and the oracle does not: how narrow was the way out?
        over = [(d, g) for g, d in enumerate(draws) if d["sticks"][k] > 0
                and ref_sticks["oracle"][g] == 0 and d["stick_free_window"]]
        if over:
            w = [d["stick_free_window"] for d, _ in over]
            print(f"{k}: sticks where the oracle does not in {len(over)} draws (the conventional "
                  f"stroke too in {sum(ref_sticks['conventional'][g] > 0 for _, g in over)}); the "
                  f"truth's stick-free cuts there span {sorted(x['periods'] for x in w)} control "
                  f"periods, a stroke not completed before them in "
                  f"{sum(x['before'] == 'not completed' for x in w)}")
    right = {law: sum(d["fits"][law]["form"][1] == d["truth_form"][1] for d in draws)
             for law in laws}
    for law, n in right.items():
        print(f"orifice law as the truth's ({law}): {n} of {len(draws)} draws")
    result = {"fractions": table, "stick_slip_rates": sticks, "stalls": stalls,
              "not_completed": undone, "orifice_law_right": right, "draws": draws,
              "reference": ref, "reference_sticks": ref_sticks,
              "config": {**vars(args), "commission": opts}, "provenance": provenance()}
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "mpc_plan.json").write_text(json.dumps(_finite(result), indent=2, default=_num,
                                                      allow_nan=False))
    _plot(table, out_dir / "mpc_plan.png")
    print(f"wrote {out_dir / 'mpc_plan.json'} and .png")
    return result


def _key(law: str, spread: float, forms: bool, rule: str, margin: int, w: float = 1.0,
         shift: int = 0, ws: float = 1.0, q: float = 1.0) -> str:
    priced = f", stick weight {w:g}" if w != 1.0 else ""
    priced += f", stall weight {ws:g}" if ws != 1.0 else ""
    priced += f", completed by >= {q:g}" if q != 1.0 else ""
    later = f", later by {shift}" if shift else ""
    return (f"{law}, spread {spread:g}{', forms' if forms else ''}, {rule} within {margin}"
            f"{priced}{later}")


def _later(t: float, shift: int, period: float) -> float:
    """Cut-off time ``t`` moved ``shift`` control periods later (never cutting stays)."""
    return round(t + shift * period, 6) if math.isfinite(t) else t


def _truth_at(cuts: list, policy, c, truth_j: dict) -> None:
    """Score the truth's (noise-free) :data:`FIGURES` at those of ``cuts`` not yet in
    ``truth_j`` into it (by cut)."""
    from agents.oracle import OraclePolicy

    missing = [t for t in cuts if t not in truth_j]
    if missing:
        quiet = dataclasses.replace(c, position_noise_m=0.0, pressure_noise_pa=0.0)
        truth_j.update(OraclePolicy(policy.layout, policy.env_config).score_figures(
            {0: quiet}, {0: missing}, FIGURES)[0])


def _fit(runs, law_models, opts: dict, where: Path | None, draw: dict):
    """The commissioning fit of ``runs`` (``law_models``: the orifice laws tried), kept in
    folder ``where`` with what it was fitted for (``draw``: the seed and draw, the laws, the
    options, the fit's procedure :data:`~pneugym.commission.FIT_VERSION`; ``fit_key.json``) and
    read from there when it is already; a kept fit of another draw, other options or an
    earlier procedure is refused (a folder kept before the key was written is taken; a fit
    below the misfit flag is the same with any ``refit_starts``, so a run that refits may reuse
    one fitted without)."""
    from pneugym.commission import FIT_VERSION, MISFIT_FLAG, Commissioned, commission

    key = json.loads(json.dumps({**draw, "fit_version": FIT_VERSION,
                                 "orifice_models": law_models,
                                 "commission": {k: v for k, v in opts.items()
                                                if k != "n_jobs"}}))  # (jobs change nothing)
    if where is not None and (where / "commissioning.json").is_file():
        model = Commissioned.load(where)
        kept = where / "fit_key.json"
        if kept.is_file() and not _same_fit(json.loads(kept.read_text()), key,
                                            model.misfit <= MISFIT_FLAG):
            raise SystemExit(f"--fits: {where} holds a fit for {kept.read_text().strip()}, "
                             f"not {json.dumps(key)}: give another --fits folder")
        return model
    model = commission(runs, orifice_models=law_models, **opts)
    if where is not None:
        model.save(where)
        (where / "fit_key.json").write_text(json.dumps(key))
    return model


def _same_fit(kept: dict, key: dict, unflagged: bool) -> bool:
    """Whether a fit kept for ``kept`` serves ``key`` (:func:`_fit`'s keys); ``unflagged``: the
    kept fit is below the misfit flag, so ``refit_starts`` would not have changed it."""
    if unflagged:
        kept, key = ({**k, "commission": {n: v for n, v in k.get("commission", {}).items()
                                          if n != "refit_starts"}} for k in (kept, key))
    return kept == key


def _window(truth_j: dict, period: float) -> dict | None:
    """The truth's stick-free cuts that complete the stroke around the best of them, on the
    control-period grid of ``truth_j``: the first and last cut [s], their number of periods,
    and what lies either side (``"not completed"``, ``"stick"``: a stick-slip, ``"edge"`` of
    the grid); ``None`` if no such cut."""
    ts = sorted(t for t in truth_j if math.isfinite(t) and abs(t / period - round(t / period))
                < 1e-6)
    free = [truth_j[t][1] == 0 and bool(truth_j[t][2]) for t in ts]
    if not any(free):
        return None
    k = max((i for i, ok in enumerate(free) if ok), key=lambda i: truth_j[ts[i]][0])
    lo, hi = k, k
    while lo > 0 and free[lo - 1]:
        lo -= 1
    while hi < len(ts) - 1 and free[hi + 1]:
        hi += 1

    def side(i: int) -> str:
        return ("edge" if not 0 <= i < len(ts) else "stick" if truth_j[ts[i]][2]
                else "not completed")

    return {"first_s": ts[lo], "last_s": ts[hi], "periods": hi - lo + 1, "before": side(lo - 1),
            "after": side(hi + 1)}


def _num(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _finite(obj):
    """``obj`` with every non-finite float (a cut never taken: ``inf``) as ``None`` (JSON
    has no infinity)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _scores(policy, c, base, truth_j: dict) -> dict:
    """Every cut's mean :data:`FIGURES` over ``policy``'s plausible rigs (a tuple),
    on the control-period grid up to the latest of their and the truth's stroke ends plus the
    decision window (``mpc-rig``'s range); ``truth_j`` (the truth's :data:`FIGURES`, by cut) is
    filled in for every cut of the grid. ``{}`` when no plausible rig completes a stroke
    (``mpc-rig`` then never cuts)."""
    from pneugym.envs import conventional_figures

    point = (round(float(c.supply_pressure_gauge_pa), 0), round(float(c.load_mass_kg), 4))
    quiet = dataclasses.replace(c, position_noise_m=0.0, pressure_noise_pa=0.0)
    members, ends = policy.members_at(*point)
    if not members:
        return {}
    ends.append(conventional_figures(quiet.rig(base), quiet.dip, period_s=policy.period)[0])
    k1 = int(math.ceil((max(ends) + policy.window) / policy.period)) + 1
    grid = [round(k * policy.period, 6) for k in range(k1 + 1)] + [math.inf]
    _truth_at(grid, policy, c, truth_j)
    per = policy.planner.score_figures(members, {j: grid for j in members}, FIGURES)
    return {t: tuple(np.mean([per[j][t] for j in per], axis=0)) for t in grid}


def _pick(mean: dict, period: float, rule: str, margin: int, allowed: list) -> float:
    from agents.mpc_rig import RULES

    return RULES[rule](mean, margin * period, allowed) if mean else math.inf


def _plot(table: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted(table, key=table.get)
    fig, ax = plt.subplots(figsize=(8, 0.22 * len(names) + 1.2))
    ax.barh(names, [table[n] for n in names])
    ax.set_xlim(min(0.5, min(table.values()) - 0.05), 1.0)
    ax.set_xlabel("oracle fraction over all draws")
    ax.tick_params(axis="y", labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
