"""The operating-life figures: every named scenario under frozen and adapting controllers,
5000 strokes each, one DuckDB record and one report (issue 14's table).

    python benchmarks/bench_operation.py --runs runs --out benchmarks/results/operation
    python benchmarks/bench_operation.py --strokes 1000 --scenarios wear,leak-onset
    python benchmarks/bench_operation.py --rig my_rig.yaml --scenarios wear \
        --controllers gaslaw-rig,esac=RUNS/esac-family,esac-adaptive=RUNS/esac-family
    python benchmarks/bench_operation.py --transfer-rig heldout-3 --scenarios wear \
        --controllers gaslaw,gaslaw-rig,esac=RUNS/esac-family,esac-adaptive=RUNS/esac-family

Scenarios are independent: two processes on disjoint ``--scenarios`` with their own ``--out`` give
the same figures as one (the documented figures were run so, on 2 cores). Start each such
process with ``NUMBA_NUM_THREADS=1``: with numba's default threads, processes sharing the cores
ran 4.7 times slower.

Needs a trained ESAC run (``pneugym train --algo esac --out runs/esac``, or the main job's).
About 40 minutes on one core for the controllers, and 40 more for the condition monitoring
(the discrepancy workflow at 70 checkpoints, 30-60 s each).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.adaptive import is_adaptive  # noqa: E402
from pneugym.operation.report import write_report  # noqa: E402
from pneugym.operation.run import operate  # noqa: E402
from pneugym.operation.scenarios import SCENARIOS  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", default="runs", help="where the trained esac run is")
    p.add_argument("--out", default="benchmarks/results/operation")
    p.add_argument("--strokes", type=int, default=5000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--controllers", default="gaslaw,gaslaw-adaptive,esac=RUNS/esac,"
                                            "esac-adaptive=RUNS/esac")
    p.add_argument("--monitor", default="healthy:500,wear:500,shift:500,leak-onset:250,"
                                        "aging:500,load-change:500",
                   help="SCENARIO:EVERY pairs: condition monitoring of the frozen Gas-Law run")
    p.add_argument("--rollback-after", type=int, default=None,
                   help="esac-adaptive: strokes without a cut before a fine-tuned model gives "
                        "way to the shipped one (default: the controller's, 50; 0: never)")
    p.add_argument("--probation", type=int, default=None,
                   help="esac-adaptive: regular strokes a fine-tuned model is on probation for "
                        "(3 stalls there: the model before it runs again; default the "
                        "controller's, 50; 0: none)")
    p.add_argument("--reference-every", type=int, default=None,
                   help="esac-adaptive: strokes between reference strokes (default 100)")
    p.add_argument("--reference-on-change", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="esac-adaptive: a reference stroke also at each change of the told "
                        "operating point, reference-every then counting from the last one "
                        "(default: off, every reference-every-th stroke; tried: "
                        "--reference-every 500 --reference-on-change)")
    p.add_argument("--reference-cut", choices=("never", "arrival"), default=None,
                   help="esac-adaptive and gaslaw-adaptive: how a reference stroke runs: cut off "
                        "on arrival (arrival, the default) or uncut (never, the earlier default)")
    p.add_argument("--explore-max", type=float, default=None,
                   help="esac-adaptive: the largest time demand its explored range grows to, "
                        "e.g. 1.2 (default: the range, +0 to +30 %%, never grows)")
    p.add_argument("--rig", metavar="FILE", help="the operated rig (a rig file; default the "
                   "thesis rig): runs SCENARIO@RIG at its supply and payload")
    p.add_argument("--rig-name", metavar="NAME", help="its name (default the file's stem)")
    p.add_argument("--transfer-rig", metavar="NAME",
                   help="instead of --rig: a rig of the transfer suite (heldout-1 ... "
                        "heldout-6, edge-..., form-...: agents.evaluation.suites.transfer_rigs), "
                        "named so")
    args = p.parse_args()
    if args.transfer_rig:
        if args.rig:
            p.error("--rig or --transfer-rig, not both")
        from agents.evaluation.suites import transfer_rigs
        from pneugym.envs.conditions import apply_changes
        from pneugym.params import RigParams

        rigs = transfer_rigs()
        if args.transfer_rig not in rigs:
            p.error(f"--transfer-rig {args.transfer_rig!r}: one of {', '.join(rigs)}")
        args.rig = apply_changes(RigParams(), rigs[args.transfer_rig])
        args.rig_name = args.rig_name or args.transfer_rig
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    db = out / "ops.duckdb"
    ctrls = [c.replace("RUNS", args.runs) for c in args.controllers.split(",")]
    ids = {}
    for sc in args.scenarios.split(","):
        for c in ctrls:
            opts = {k: v for k, v in (("rollback_after", args.rollback_after),
                                      ("probation", args.probation),
                                      ("explore_max", args.explore_max),
                                      ("reference_every", args.reference_every),
                                      ("reference_on_change", args.reference_on_change))
                    if v is not None}
            opts = opts if opts and c.startswith("esac-adaptive=") else None
            if args.reference_cut is not None and is_adaptive(c):
                opts = {**(opts or {}), "reference_cut": args.reference_cut}
            ids[sc, c] = operate(sc, c, strokes=args.strokes, db=db, seed=args.seed,
                                 options=opts, rig=args.rig, rig_name=args.rig_name)
    from pneugym.operation.monitor import alarm, monitor

    for item in filter(None, args.monitor.split(",")):
        sc, every = item.split(":")
        if (sc, "gaslaw") in ids:
            pts = monitor(str(db), ids[sc, "gaslaw"], every=int(every))
            print(f"monitor {sc}: {alarm(pts)}", flush=True)
    res = write_report(db, out)
    for rid, s in res["runs"].items():
        print(f"{rid:60s} oracle fraction {s['oracle_fraction']:.3f}  stalls {s['stalls']}  "
              f"stick {s['stick_slip_strokes']}  recovery {s['recovery']}")


if __name__ == "__main__":
    main()
