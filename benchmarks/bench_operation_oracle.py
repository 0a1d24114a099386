"""How the operating figures depend on their yardstick: every run of an operating record scored
against three oracles that know the drift.

- **search**: the record's own truth (``OraclePolicy``'s search: a cut at every fourth control
  step and never cutting, then every step around the three best), what every report uses;
- **every step**: the best cut of every control step up to the conventional stroke's end
  (``OraclePolicy(coarse=1)``), the best single cut there is;
- **slip-robust**: the cut whose worst return within ``--slip`` control periods either side is
  best (``agents.mpc.robust_best``), scored at its own return: an oracle that will not cut where
  a cut one period off stalls or sticks.

Each drift step's conditions are searched once (the truth holds one condition per step). Writes
``oracles.json`` (per run: the oracle fraction against each, over the life and its regular
strokes; per scenario: the drift steps where the search missed a better cut) and
``oracles.png``.

    python benchmarks/bench_operation.py --runs runs --scenarios load-change --monitor "" --out bench/lc
    python benchmarks/bench_operation_oracle.py --db bench/lc/ops.duckdb --out bench/lc

About 6 minutes on one core per scenario of 5000 strokes (500 drift steps, about 250 cuts each).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

YARDSTICKS = ("search", "every step", "slip-robust")


def step_returns(scenario: dict, seed: int, strokes: np.ndarray, slip: int, chunk: int = 20,
                 progress: bool = True, env: dict | None = None) -> dict[int, tuple[float, float]]:
    """``{drift step: (best return of every step, slip-robust return)}`` of a scenario's
    strokes, on the rig the life ran on (``env``: the record's environment configuration,
    its rig included; default the thesis rig's)."""
    from tqdm import tqdm

    from agents.mpc import robust_best
    from agents.oracle import OraclePolicy
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.operation.run import ENV_CONFIG
    from pneugym.operation.scenarios import Scenario

    sc = Scenario(**scenario)
    oracle = OraclePolicy.for_env(CutOffVectorEnv(num_envs=1, **(env or ENV_CONFIG)), coarse=1)
    steps = np.unique(strokes // sc.resolution)
    out: dict[int, tuple[float, float]] = {}
    for i in tqdm(range(0, steps.size, chunk), desc=f"{sc.name} seed {seed}", unit="chunk",
                  disable=not progress):
        part = steps[i:i + chunk]
        conds = [sc.conditions(int(s) * sc.resolution, seed) for s in part]
        for s, js in zip(part, oracle.returns_many(conds)):
            t = robust_best(js, slip * oracle.period)
            out[int(s)] = (max(js.values()), js[t])
    return out


def fraction(j: np.ndarray, jc: np.ndarray, jo: np.ndarray) -> float:
    """The share of the oracle's gain over the conventional controller, summed."""
    return float((j.sum() - jc.sum()) / (jo.sum() - jc.sum()))


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--db", required=True, help="an operating record (DuckDB)")
    p.add_argument("--out", default="benchmarks/results/operation", help="folder for results")
    p.add_argument("--slip", type=int, default=1, help="control periods either side (>= 1)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.slip < 1:
        p.error("--slip must be >= 1")
    from pneugym.operation.record import Record
    from pneugym.provenance import provenance

    res: dict = {"config": {"db": str(args.db), "slip_periods": args.slip},
                 "provenance": provenance(), "runs": {}, "scenarios": {}}
    with Record(args.db, read_only=True) as rec:
        runs = [rec.run(r["run_id"]) for r in rec.runs()]
        lives = {(r["scenario"], r["seed"]): (r["config"]["scenario"], r["config"].get("env"))
                 for r in runs}
        truth, best = {}, {}
        for (name, seed), (spec, env) in lives.items():
            t = rec.truth(name, seed, 0, 10**12)
            st = step_returns(spec, seed, t["stroke"], args.slip, progress=not args.no_progress,
                              env=env)
            k = t["stroke"] // spec["resolution"]
            ex = np.array([st[int(s)][0] for s in k])
            rb = np.array([st[int(s)][1] for s in k])
            truth[name, seed] = t
            best[name, seed] = {"search": t["oracle_objective"], "every step": ex,
                                "slip-robust": rb}
            missed = ex > t["oracle_objective"] + 0.01
            res["scenarios"][f"{name}/seed{seed}"] = {
                "drift_steps": len(st), "strokes_search_missed_by_0.01": int(missed.sum()),
                "mean_gain_every_step_over_search": float(np.mean(ex - t["oracle_objective"])),
                "mean_loss_slip_robust_against_search": float(np.mean(t["oracle_objective"]
                                                                      - rb)),
                "mean_loss_slip_robust_against_every_step": float(np.mean(ex - rb))}
        for r in runs:
            s = rec.strokes(r["run_id"])
            t = truth[r["scenario"], r["seed"]]
            i = np.searchsorted(t["stroke"], s["stroke"])
            j, jc = s["objective"].astype(float), t["conventional_objective"][i]
            reg = ~(s["reference"].astype(bool) | s["explore"].astype(bool))
            res["runs"][r["run_id"]] = {
                y: {"life": fraction(j, jc, jo[i]),
                    "regular": fraction(j[reg], jc[reg], jo[i][reg])}
                for y, jo in best[r["scenario"], r["seed"]].items()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "oracles.json").write_text(json.dumps(res, indent=1))
    plot(res, out / "oracles.png")
    for rid, f in res["runs"].items():
        print(f"{rid:60s} " + "  ".join(f"{y} {f[y]['life']:.3f} ({f[y]['regular']:.3f})"
                                        for y in YARDSTICKS))
    for sc, v in res["scenarios"].items():
        print(f"{sc}: the search missed a better cut (by > 0.01) on "
              f"{v['strokes_search_missed_by_0.01']} strokes")
    return res


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(res["runs"])
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(runs)), 3.6))
    w = 0.8 / len(YARDSTICKS)
    for k, y in enumerate(YARDSTICKS):
        ax.bar(np.arange(len(runs)) + (k - 1) * w, [res["runs"][r][y]["life"] for r in runs], w,
               label=y)
    ax.axhline(0.95, color="k", lw=0.8, ls="--")
    ax.set_xticks(np.arange(len(runs)), [r.split("/", 2)[2].split("=")[0] for r in runs],
                  fontsize=8)
    ax.set_ylabel("oracle fraction over the life")
    ax.set_ylim(min(0.8, min(res["runs"][r][y]["life"] for r in runs for y in YARDSTICKS)), 1.0)
    ax.legend(fontsize=8, title="oracle")
    ax.set_title(", ".join(res["scenarios"]), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
