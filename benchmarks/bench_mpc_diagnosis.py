"""Why ``mpc-rig`` loses on a family draw: its commissioned model against the rig's truth.

For each chosen draw of ``bench_mpc.py``'s fresh family draws (the same ``--seed``, the same
draw index), commissions ``mpc-rig`` on the draw's rig exactly as the benchmark does (the same
two simulated strokes, the same noise seed), then prints and writes:

- the fit: its misfit (mean square residual in units of the noise's; about 1 is a fit to the
  noise), the line model and extras it chose, and every fitted field against the truth;
- the return of every cut-off time on a grid, noise-free, on the rig's truth (what the oracle
  searches), on the fitted rig and averaged over the plan's plausible rigs (what ``mpc-rig``
  plans on); with the plan's cut and the truth's best.

Writes ``mpc_diagnosis.json`` and ``mpc_diagnosis.png`` (return against cut-off time per draw).

    python benchmarks/bench_mpc_diagnosis.py --draws 5 1 38 34   # 3 min on 2 cores
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

from common import ROOT, add_commission_args, commission_overrides  # noqa: F401


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--draws", type=int, nargs="+", required=True,
                    help="indices of bench_mpc.py's draws (0-based)")
    ap.add_argument("--seed", type=int, default=4_000_000, help="bench_mpc.py's --seed")
    ap.add_argument("--grid", type=float, default=0.025, help="cut-off grid step [s]")
    ap.add_argument("--out", default="bench/mpc-diagnosis", help="folder for the results")
    add_commission_args(ap)
    args = ap.parse_args(argv)
    if min(args.draws) < 0 or not args.grid > 0:
        ap.error("--draws must be >= 0 and --grid > 0")
    import numpy as np

    from agents.evaluation.commissioning import commissioning_runs
    from agents.evaluation.specs import evaluation_env_config, make_named_policy
    from agents.evaluation.suites import family_draws
    from agents.mpc_rig import FORM_FIELDS, MEMBER_FIELDS
    from agents.oracle import OraclePolicy
    from pneugym.envs import Conditions, conventional_figures
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance
    from pneugym.rigfile import rig_fields

    cfg = evaluation_env_config({})
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    conds = family_draws(args.seed, max(args.draws) + 1)  # the draws of bench_mpc.py
    base = probe.rig
    _, policy = make_named_policy("mpc-rig", probe)
    policy.commission_options.update(commission_overrides(args))
    truth_planner = OraclePolicy(probe.observation_layout(), policy.env_config)
    out: dict[str, dict] = {}
    for g in args.draws:
        c = conds[g]
        truth = Conditions(supply_pressure_gauge_pa=base.supply_pressure_gauge_pa,
                           load_mass_kg=base.load_mass_kg, rig_changes=c.rig_changes).rig(base)
        policy.commission(commissioning_runs(c.rig_changes, base, args.seed, g),
                          **policy.commission_options)
        m = policy.model
        point = (round(float(c.supply_pressure_gauge_pa), 0), round(float(c.load_mass_kg), 4))
        plan = policy.plan([point])[point]
        quiet = dataclasses.replace(c, position_noise_m=0.0, pressure_noise_pa=0.0)
        t_conv = conventional_figures(quiet.rig(base), quiet.dip, period_s=policy.period)[0]
        ts = [round(float(t), 4) for t in np.arange(args.grid, t_conv + 2 * args.grid, args.grid)]
        j_truth = truth_planner.score_cuts({0: quiet}, {0: ts})[0]
        members = {j: Conditions(supply_pressure_gauge_pa=point[0], load_mass_kg=point[1],
                                 rig_changes=ch) for j, ch in enumerate(policy.changes)}
        per = policy.planner.score_cuts(members, {j: ts for j in members})
        tf, ff = rig_fields(truth), rig_fields(m.rig)
        best = max(ts, key=j_truth.get)
        near = min(ts, key=lambda t: abs(t - plan)) if math.isfinite(plan) else None
        out[str(g)] = {
            "supply_bar_gauge": c.supply_pressure_gauge_pa / 1e5, "load_kg": c.load_mass_kg,
            "misfit": m.misfit, "extras": list(m.extras),
            "line": [truth.line.model, m.rig.line.model],
            "orifice": [truth.valve.flow_model, m.rig.valve.flow_model],
            "fields": {k: [tf.get(k), ff.get(k)] for k in MEMBER_FIELDS
                       if k not in FORM_FIELDS},
            "plan_s": plan, "truth_best_s": best, "truth_at_best": j_truth[best],
            "truth_at_plan": None if near is None else j_truth[near],
            "cut_s": ts, "truth": [j_truth[t] for t in ts], "fitted": [per[0][t] for t in ts],
            "members": [float(np.mean([per[j][t] for j in per])) for t in ts]}
        _report(g, out[str(g)])
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {"draws": out, "config": vars(args), "provenance": provenance()}
    (out_dir / "mpc_diagnosis.json").write_text(json.dumps(result, indent=2, default=str))
    _plot(out, out_dir / "mpc_diagnosis.png")
    print(f"wrote {out_dir / 'mpc_diagnosis.json'} and .png")
    return result


def _report(g: int, d: dict) -> None:
    print(f"\ndraw {g}: {d['supply_bar_gauge']:.2f} bar g, {d['load_kg']:.1f} kg; misfit "
          f"{d['misfit']:.1f}; line {d['line'][1]} (truth {d['line'][0]}), orifice "
          f"{d['orifice'][1]} (truth {d['orifice'][0]}); extras {', '.join(d['extras']) or '-'}")
    for k, (t, f) in d["fields"].items():
        if t != f:
            print(f"  {k:40s} truth {t:11.4g}  fitted {f:11.4g}")
    at = "-" if d["truth_at_plan"] is None else f"{d['truth_at_plan']:.3f}"
    print(f"  plan {d['plan_s']:.3f} s: return on the truth {at}; the truth's best "
          f"{d['truth_best_s']:.3f} s: {d['truth_at_best']:.3f}")


def _plot(out: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(out), 1, figsize=(8, 2.4 * len(out)), squeeze=False)
    for ax, (g, d) in zip(axes[:, 0], out.items()):
        ax.plot(d["cut_s"], d["truth"], "k.-", label="truth")
        ax.plot(d["cut_s"], d["fitted"], "C0.-", label="fitted rig")
        ax.plot(d["cut_s"], d["members"], "C1--", label="mean of the plausible rigs")
        if math.isfinite(d["plan_s"]):
            ax.axvline(d["plan_s"], color="C1", lw=0.8)
        ax.axvline(d["truth_best_s"], color="k", lw=0.8, ls=":")
        ax.set_ylim(-3.5, 0.1)
        ax.set_title(f"draw {g}: {d['supply_bar_gauge']:.1f} bar g, {d['load_kg']:.0f} kg, "
                     f"misfit {d['misfit']:.0f}", fontsize=9)
        ax.set_ylabel("return")
    axes[-1, 0].set_xlabel("cut-off time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
