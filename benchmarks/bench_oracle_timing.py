"""How much of the oracle's gain depends on millisecond-exact timing: the privileged oracle's cut
times, shifted by a few control periods, on evaluate.py's robustness suite.

Run from the repository root::

    python benchmarks/bench_oracle_timing.py               # about 1 minute on 2 cores
    python benchmarks/bench_oracle_timing.py --shifts -2 -1 1 2 --episodes 2 --out DIR

The oracle plans each episode with its conditions known (agents.oracle). A causal policy sees
noisy sensors and can be off by a period or more. ``oracle_timing.json`` (and ``.png``) give, for
each shift of ``k`` control periods (5 ms each), the suite's oracle fraction, saving and stick-slip
rate of the oracle's own cut times moved by ``k`` periods, and the cells that lose most at
``k = ±1``: the ceiling that a causal policy can hope for, next to the oracle's 1.0.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

from agents import make_policy  # noqa: E402
from agents.evaluation import EVAL_SEED, run_policy, suite_episodes  # noqa: E402
from agents.oracle import TimedCutPolicy  # noqa: E402
from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: E402
from pneugym.provenance import provenance  # noqa: E402


def shifted_oracle(shifts: list[int], episodes: int, seed: int) -> dict:
    """Suite figures of the oracle's cut times moved by each of ``shifts`` control periods."""
    eps = suite_episodes("robustness", episodes, seed)
    labels = np.array([label for label, _ in eps])
    conds = [c for _, c in eps]
    probe = CutOffVectorEnv(num_envs=1)
    period = probe.control_period_s
    conv = run_policy(make_policy("conventional", probe), conds, {}, seed)
    orc = run_policy(make_policy("oracle", probe), conds, {}, seed)
    t_cut = np.array([np.inf if t is None else float(t) for t in orc["cutoff_time_s"]])
    j_conv = conv["objective"].astype(float)
    j_orc = orc["objective"].astype(float)
    gap = j_orc.mean() - j_conv.mean()
    rows = []
    for k in sorted(set([0, *shifts])):
        pol = TimedCutPolicy(probe.observation_layout(), np.maximum(t_cut + k * period, 0.0))
        out = orc if k == 0 else run_policy(pol, conds, {}, seed)
        j = out["objective"].astype(float)
        loss = {lab: float(j_orc[labels == lab].mean() - j[labels == lab].mean())
                for lab in dict.fromkeys(labels)}
        worst = sorted(loss.items(), key=lambda kv: -kv[1])[:5]
        rows.append({"shift_periods": k, "shift_s": k * period,
                     "oracle_fraction": float((j.mean() - j_conv.mean()) / gap),
                     "saving": float(np.mean(out["saving_ratio"])),
                     "stick_slip_rate": float(np.mean(out["stick_slip_events"] > 0)),
                     "stall_rate": float(np.mean(out["stalled"])),
                     "cells_losing_most": [{"cell": c, "return_loss": v} for c, v in worst]})
    return {"rows": rows, "episodes": len(conds), "control_period_s": period,
            "conventional_return": float(j_conv.mean()), "oracle_return": float(j_orc.mean())}


def plot(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    k = [1e3 * r["shift_s"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(k, [r["oracle_fraction"] for r in rows], "o-", label="oracle fraction")
    ax.plot(k, [r["stick_slip_rate"] for r in rows], "s--", label="stick-slip rate")
    ax.set_xlabel("oracle cut time shifted by [ms]")
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(f"Oracle with its cut moved, robustness suite ({res['episodes']} episodes)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shifts", type=int, nargs="+", default=[-5, -2, -1, 1, 2, 5],
                    help="shifts in control periods (0 is always run)")
    ap.add_argument("--episodes", type=int, default=2, help="episodes per cell (evaluate.py's 2)")
    ap.add_argument("--seed", type=int, default=EVAL_SEED)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    res = shifted_oracle(args.shifts, args.episodes, args.seed)
    res.update(config=vars(args) | {"out": str(args.out)}, **provenance())
    print(f"{'shift':>8}{'oracle fr.':>12}{'saving %':>10}{'stick %':>9}  cells losing most")
    for r in res["rows"]:
        cells = ", ".join(f"{c['cell']} {c['return_loss']:.2f}" for c in r["cells_losing_most"][:3]
                          if c["return_loss"] > 0.01)
        print(f"{1e3 * r['shift_s']:>+6.0f}ms{r['oracle_fraction']:>12.3f}"
              f"{100 * r['saving']:>10.1f}{100 * r['stick_slip_rate']:>9.1f}  {cells}")
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = args.out / "oracle_timing.json.tmp"
    tmp.write_text(json.dumps(res, indent=1, default=str))
    tmp.replace(args.out / "oracle_timing.json")
    plot(res, args.out / "oracle_timing.png")
    print(f"\nwrote {args.out / 'oracle_timing.json'} and oracle_timing.png")
    return res


if __name__ == "__main__":
    main()
