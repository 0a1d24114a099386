"""What an evaluation leaves: the table it prints (:func:`print_table`), and ``results.json``,
``results.csv`` and the plots (:mod:`~agents.evaluation.plots`), replaced as a set
(:func:`write_outputs`)."""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Mapping, Sequence

from pneugym.outputs import atomic_write_json, staged_files

from .plots import plot_results


def outside_reasons(rec: Sequence[Mapping[str, Any]]) -> list[str]:
    """The distinct reasons why episodes of ``rec`` lie outside their policy's training
    conditions (their ``outside_training``), in episode order."""
    return list(dict.fromkeys(r["outside_training"] for r in rec if r.get("outside_training")))


def print_table(results: dict[str, Any]) -> None:
    """The metrics of every policy, one table per suite."""
    for suite, s in results["suites"].items():
        n = next(iter(s["policies"].values()))["episodes"]
        print(f"\n== {suite} suite ({n} episodes per policy)")
        print(f"{'policy':<14}{'saving %':>9}{'time +%':>9}{'stall %':>8}{'stick %':>8}"
              f"{'done %':>8}{'return':>9}{'oracle fr.':>11}")
        for name, p in s["policies"].items():
            def pct(v):
                return f"{100 * v:.1f}" if v is not None else "-"
            of = p["oracle_fraction"]
            print(f"{name:<14}{pct(p['saving_mean']):>9}{pct(p['time_increase_mean']):>9}"
                  f"{pct(p['stall_rate']):>8}{pct(p['stick_slip_rate']):>8}"
                  f"{pct(p['completion_rate']):>8}{p['return_mean']:>9.3f}"
                  f"{(f'{of:.3f}' if of is not None else '-'):>11}")
        for name, p in s["policies"].items():
            if p.get("outside_training_rate"):
                rec = [r for r in s["episodes"] if r["policy"] == name]
                why = outside_reasons(rec)
                print(f"  {name}: {100 * p['outside_training_rate']:.0f} % of the episodes lie "
                      f"outside its training conditions ({'; '.join(why[:2])}"
                      f"{'; ...' if len(why) > 2 else ''})")
    print("(oracle: privileged, knows each episode's conditions; oracle fraction = share of the "
          "oracle's gain over conventional)")


#: the files an evaluation writes into ``--out`` (a new set replaces every one of them: a plot
#: of a suite not run again is removed, not left beside results it does not belong to)
OWNED = ("results.json", "results.csv", "*_saving_vs_time.png", "robustness_heatmaps.png",
         "*_oracle_fraction_per_rig.png", "example_trajectories.png")


def write_outputs(results: dict[str, Any], out: str | Path) -> None:
    """results.json, results.csv and the plots, replacing those in ``out`` only once all are
    written (an error leaves the previous set untouched); the evaluation's files of an earlier
    set that this one does not write (:data:`OWNED`) are removed."""
    with staged_files(out, replaces=OWNED) as stage:
        atomic_write_json(stage / "results.json", results)
        rows = [r for s in results["suites"].values() for r in s["episodes"]]
        if rows:
            keys = list(dict.fromkeys(k for r in rows for k in r))
            with open(stage / "results.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=keys)
                w.writeheader()
                w.writerows(rows)
        plot_results(results, stage)
