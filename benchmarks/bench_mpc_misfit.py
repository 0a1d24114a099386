"""Does a commissioning fit's misfit tell when ``mpc-rig``'s plan will fail?

On ``bench_mpc.py``'s fresh family draws (the same ``--seed``, the same draws, the same two
simulated strokes per rig), commissions ``mpc-rig`` on each draw's rig as the benchmark does and
runs its episode; where the fit's misfit (mean square residual over the noise's; about 1 is a
fit to the noise) exceeds ``--refit-above``, fits again from three times the starts (other
draws) with one and a half times the evaluations, and runs the episode planned on that fit too.
The baselines (end-stroke, Gas-Law calibrated per rig) and the oracle run on every draw.

From these it scores, for each misfit limit of ``--limits``, the guards one could put in front
of the plan (oracle fraction over all draws): refit above the limit and plan on the better fit;
then, if that is still above the limit, refuse it and cut on arrival (end-stroke) or with
Gas-Law; or refuse without a refit. And the rank correlation between misfit and the share of the
oracle's gain the plan loses. Writes ``mpc_misfit.json`` (every draw's records) and
``mpc_misfit.png`` (loss against misfit; the guards' oracle fractions).

    python benchmarks/bench_mpc_misfit.py --seed 3000000                # validation draws, 56 min on 2 cores
    python benchmarks/bench_mpc_misfit.py --seed 5000000 --episodes 20  # fresh draws, 19 min
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from common import ROOT, add_commission_args, commission_overrides  # noqa: F401

BASELINES = ("conventional", "endstroke", "gaslaw-rig", "oracle")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--episodes", type=int, default=40, help="family draws (one episode each)")
    ap.add_argument("--seed", type=int, default=3_000_000,
                    help="seed of the draws (bench_mpc.py's; default the validation draws)")
    ap.add_argument("--refit-above", type=float, default=4.0,
                    help="fit again where the misfit exceeds this (default 4)")
    ap.add_argument("--limits", type=float, nargs="+", default=[4.0, 9.0, 25.0, 100.0],
                    help="misfit limits the guards are scored at (each >= --refit-above)")
    ap.add_argument("--out", default="bench/mpc-misfit", help="folder for the results")
    add_commission_args(ap)
    args = ap.parse_args(argv)
    if args.episodes < 1 or min(args.limits) < args.refit_above:
        ap.error("--episodes must be >= 1 and every --limits >= --refit-above")
    import numpy as np
    from scipy.stats import spearmanr
    from tqdm import tqdm

    from agents.evaluation.commissioning import commissioning_runs
    from agents.evaluation.run import oracle_fraction, run_policy
    from agents.evaluation.specs import evaluation_env_config, make_named_policy
    from agents.evaluation.suites import family_draws
    from pneugym.commission import commission
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    cfg = evaluation_env_config({})
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    conds = family_draws(args.seed, args.episodes)  # the draws of bench_mpc.py
    base = {}
    for spec in BASELINES:
        out = run_policy(make_named_policy(spec, probe)[1], conds, cfg, args.seed)
        base[spec] = [float(v) for v in out["objective"]]
    _, policy = make_named_policy("mpc-rig", probe)
    opts = dict(policy.commission_options)
    opts.update(commission_overrides(args))
    refit = {**opts, "starts": 3 * opts["starts"], "max_nfev": int(1.5 * opts["max_nfev"]),
             "seed": opts.get("seed", 0) + 1}
    draws = []
    for g, c in enumerate(tqdm(conds, desc="commissioning", unit="rig")):
        runs = commissioning_runs(c.rig_changes, probe.rig, args.seed, g)
        d = {"draw": g}
        for key, o in (("first", opts), ("refit", refit)):
            if key == "refit" and not d["first"]["misfit"] > args.refit_above:
                break
            policy.set_model(commission(runs, **o))
            ep = run_policy(policy, [c], cfg, args.seed)
            d[key] = {"misfit": policy.model.misfit, "line_model": policy.model.rig.line.model,
                      "objective": float(ep["objective"][0]),
                      "cutoff_time_s": _num(ep["cutoff_time_s"][0]),
                      "stick_slip_events": int(ep["stick_slip_events"][0]),
                      "stalled": bool(ep["stalled"][0])}
        draws.append(d)
    conv, orc = float(np.mean(base["conventional"])), float(np.mean(base["oracle"]))

    def fraction(returns) -> float:
        return oracle_fraction(float(np.mean(returns)), conv, orc)

    guards = {"no guard": fraction([d["first"]["objective"] for d in draws])}
    for lim in args.limits:
        for name, refit_, fallback in (("refit", True, None), ("refit, then end-stroke", True,
                                       "endstroke"), ("refit, then Gas-Law per rig", True,
                                       "gaslaw-rig"), ("end-stroke, no refit", False, "endstroke")):
            guards[f"{name} above {lim:g}"] = fraction(
                [_guarded(d, base, lim, refit_, fallback) for d in draws])
    loss = [(base["oracle"][d["draw"]] - d["first"]["objective"])
            / (base["oracle"][d["draw"]] - base["conventional"][d["draw"]]) for d in draws]
    rho, p = spearmanr([d["first"]["misfit"] for d in draws], loss) if len(draws) > 2 else (
        math.nan, math.nan)
    for name, f in guards.items():
        print(f"{name:40s} oracle fraction {f:.3f}")
    print(f"end-stroke {fraction(base['endstroke']):.3f}, Gas-Law per rig "
          f"{fraction(base['gaslaw-rig']):.3f}; misfit vs loss: Spearman rho {rho:.2f} (p {p:.2g})")
    result = {"guards": guards, "baselines": {k: fraction(v) for k, v in base.items()},
              "spearman": {"rho": _num(rho), "p": _num(p)}, "draws": draws, "returns": base,
              "config": {**vars(args), "commission": opts, "refit": refit},
              "provenance": provenance()}
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "mpc_misfit.json").write_text(json.dumps(result, indent=2))
    _plot(draws, loss, guards, out_dir / "mpc_misfit.png")
    print(f"wrote {out_dir / 'mpc_misfit.json'} and .png")
    return result


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _guarded(d: dict, base: dict, limit: float, refit: bool, fallback: str | None) -> float:
    """A draw's return under a guard: plan on the better fit if the first is above ``limit``
    (``refit``), then cut with ``fallback`` if that is still above it."""
    fit = d["first"]
    if refit and fit["misfit"] > limit and d["refit"]["misfit"] < fit["misfit"]:
        fit = d["refit"]
    if fallback and fit["misfit"] > limit:
        return base[fallback][d["draw"]]
    return fit["objective"]


def _plot(draws: list, loss: list, guards: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    a.scatter([d["first"]["misfit"] for d in draws], loss, s=18)
    for d, y in zip(draws, loss):
        if "refit" in d or y > 0.2:
            a.annotate(str(d["draw"]), (d["first"]["misfit"], y), fontsize=7)
    a.set_xscale("log")
    a.set_xlabel("misfit of the commissioning fit (SSR/N, noise = 1)")
    a.set_ylabel("share of the oracle's gain the plan loses")
    a.set_title("each draw", fontsize=9)
    names = list(guards)
    b.barh(names, [guards[n] for n in names])
    b.axvline(guards["no guard"], color="k", lw=0.8)
    b.set_xlim(min(0.5, min(guards.values()) - 0.05), 1.0)
    b.set_xlabel("oracle fraction over all draws")
    b.tick_params(axis="y", labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
