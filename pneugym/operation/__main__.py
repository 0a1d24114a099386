"""``python -m pneugym.operation`` (or ``pneugym operate``): run a rig's operating life under one
or more controllers, record every stroke in DuckDB, and report.

    pneugym operate --scenario wear --policy esac=runs/esac --strokes 5000 --db ops.duckdb
    pneugym operate --scenario leak-onset --policy gaslaw --policy gaslaw-adaptive --out ops/
    pneugym operate --rig my_rig.yaml --scenario wear --policy gaslaw-rig --strokes 2000
    pneugym operate --db ops.duckdb --monitor leak-onset/seed0/gaslaw --every 250
    pneugym operate --db ops.duckdb --out ops/               # report what the record holds
    pneugym operate --db ops.duckdb --export-parquet ops/parquet
    pneugym operate --db ops.duckdb --export-runs ops/runs --run healthy/seed0/gaslaw --first 0 --last 5
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

from .scenarios import SCENARIOS

EXAMPLES = __doc__.split("\n\n")[1]
CONTROLLERS = ("a baseline's name (conventional, endstroke, gaslaw, gaslaw-rig, mpc) or "
               "NAME=PATH of a trained model (frozen); gaslaw-adaptive; esac-adaptive=PATH "
               "(an ESAC run or model, fine-tuned from its record)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pneugym operate", description=__doc__.split("\n\n")[0],
        epilog="examples:\n" + "\n".join("  " + ln.strip() for ln in EXAMPLES.splitlines())
               + "\n\nscenarios:\n" + "\n".join(f"  {k}: {v.description}"
                                                for k, v in SCENARIOS.items()),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", choices=sorted(SCENARIOS), help="the operating scenario")
    p.add_argument("--policy", action="append", default=[], metavar="SPEC",
                   help=f"a controller (repeatable): {CONTROLLERS}")
    p.add_argument("--rig", metavar="FILE",
                   help="the operated rig (a rig file; default the thesis rig): the scenario "
                        "runs at its stated supply and payload (the named scenarios' supply "
                        "and load scaled from 2.5 bar and 10 kg), recorded as SCENARIO@NAME")
    p.add_argument("--rig-name", metavar="NAME",
                   help="the rig's name in the record (default the rig file's stem)")
    p.add_argument("--strokes", type=int, default=5000, help="strokes to run (default 5000)")
    p.add_argument("--seed", type=int, default=0, help="the scenario's seed (default 0)")
    p.add_argument("--reference-cut", choices=("never", "arrival"), default=None,
                   help="the adaptive controllers' reference strokes (every 100th, which their "
                        "measured objective counts against): cut off on arrival (arrival, the "
                        "default) or uncut (never, the earlier default)")
    p.add_argument("--block", type=int, default=25,
                   help="strokes per block: a controller learns between blocks (default 25)")
    p.add_argument("--db", default="ops.duckdb", help="the DuckDB record (default ops.duckdb); "
                   "a run already in it resumes")
    p.add_argument("--out", metavar="DIR",
                   help="write the report there: report.md, report.json, one plot per scenario")
    p.add_argument("--export-parquet", metavar="DIR", help="every table as Parquet")
    p.add_argument("--export-runs", metavar="DIR",
                   help="strokes of --run as pneugym-measurement/1 runs")
    p.add_argument("--run", help="the run id for --export-runs (SCENARIO/seedN/CONTROLLER)")
    p.add_argument("--remove", metavar="RUN", action="append", default=[],
                   help="delete a run from the record first (repeatable)")
    p.add_argument("--monitor", metavar="RUN", action="append", default=[],
                   help="run the discrepancy workflow on RUN's record at checkpoints "
                        "(condition monitoring; repeatable)")
    p.add_argument("--every", type=int, default=250,
                   help="strokes between monitoring checkpoints (default 250)")
    p.add_argument("--window", type=int, default=6,
                   help="strokes the workflow reads at each checkpoint (default 6)")
    p.add_argument("--monitor-candidates", metavar="LIST",
                   help="comma-separated changes the monitor tests (default: leakage,"
                        "heat_transfer,stribeck_friction,sensor_lag,dead_volume,valve_delay: "
                        "the five effects and a valve slower than commissioned)")
    p.add_argument("--monitor-passes", type=int, metavar="N",
                   help="passes at each checkpoint: each after the first writes the changes "
                        "named so far into the model and tests the rest (default 2)")
    p.add_argument("--monitor-friction", choices=("stroke", "shared"),
                   help="stroke: fit each stroke's own friction first (default); shared: one "
                        "friction for the window's strokes")
    p.add_argument("--first", type=int, default=0, help="first stroke to export")
    p.add_argument("--last", type=int, default=None, help="last stroke to export")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _monitor_options(args: argparse.Namespace) -> dict:
    """``--monitor-candidates``, ``--monitor-passes`` and ``--monitor-friction`` as the
    monitor's options (absent: its defaults)."""
    from pneugym.discrepancy.candidates import CANDIDATES, MORE_CANDIDATES

    out: dict = {}
    if args.monitor_passes is not None:
        if args.monitor_passes < 1:
            raise ValueError(f"--monitor-passes {args.monitor_passes}: give 1 or more")
        out["passes"] = args.monitor_passes
    if args.monitor_friction is not None:
        out["stroke_friction"] = args.monitor_friction == "stroke"
    if not args.monitor_candidates:
        return out
    names = [c.strip() for c in args.monitor_candidates.split(",") if c.strip()]
    bad = [c for c in names if c not in CANDIDATES and c not in MORE_CANDIDATES]
    if bad or not names:
        raise ValueError(f"--monitor-candidates {args.monitor_candidates!r}: unknown {bad}; "
                         f"choose from {[*CANDIDATES, *MORE_CANDIDATES]}")
    return {**out, "candidates": names}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.policy and not args.scenario:
        parser.error("--policy needs --scenario")
    if args.scenario and not args.policy:
        parser.error("--scenario needs at least one --policy")
    if (args.rig or args.rig_name) and not args.policy:
        parser.error("--rig and --rig-name go with --scenario and --policy")
    if args.rig_name and not args.rig:
        parser.error("--rig-name names the rig of --rig: give --rig FILE")
    try:
        options = _monitor_options(args)
    except ValueError as exc:
        parser.error(str(exc))
    if not (args.policy or args.out or args.export_parquet or args.export_runs
            or args.monitor or args.remove):
        parser.error("nothing to do: give --scenario and --policy, --out, --monitor, "
                     "--export-parquet or --export-runs")
    from ..outputs import OutputError, check_output_dir, check_output_file
    from .record import Record, export_runs
    from .run import operate

    try:  # every place written to, proved writable before any long work
        check_output_file(args.db, "--db")
        for opt in ("out", "export_parquet", "export_runs"):
            if getattr(args, opt):
                check_output_dir(getattr(args, opt), f"--{opt.replace('_', '-')}")
    except OutputError as exc:
        parser.error(str(exc))

    for rid in args.remove:
        with Record(args.db) as rec:
            try:
                n = rec.remove_run(rid)
            except ValueError as exc:
                parser.error(str(exc))
        print(f"removed {rid} ({n} strokes) from {args.db}")
    from agents.adaptive import is_adaptive

    if args.reference_cut and not any(map(is_adaptive, args.policy)):
        parser.error("--reference-cut is an option of the adaptive controllers: give "
                     "--policy gaslaw-adaptive or --policy esac-adaptive=RUN")
    cut = {"reference_cut": args.reference_cut} if args.reference_cut else None
    ids = []
    for spec in args.policy:
        try:
            ids.append(operate(args.scenario, spec, strokes=args.strokes, db=args.db,
                               seed=args.seed, block=args.block,
                               progress=not args.no_progress, rig=args.rig,
                               rig_name=args.rig_name,
                               options=cut if is_adaptive(spec) else None))
        except (ValueError, FileNotFoundError) as exc:
            parser.error(str(exc))
        print(f"recorded {ids[-1]} in {args.db}")
    for rid in args.monitor:
        from .monitor import alarm, monitor

        try:
            pts = monitor(args.db, rid, every=args.every, window=args.window,
                          progress=not args.no_progress, **options)
        except ValueError as exc:
            parser.error(str(exc))
        print(f"{rid}: {alarm(pts)}")
    if args.export_parquet:
        with Record(args.db, read_only=True) as rec:
            files = rec.export_parquet(args.export_parquet)
        print(f"wrote {len(files)} Parquet files to {args.export_parquet}")
    if args.export_runs:
        if not args.run:
            parser.error("--export-runs needs --run")
        with Record(args.db, read_only=True) as rec:
            try:
                files = export_runs(rec, args.run, args.export_runs, args.first, args.last)
            except ValueError as exc:
                parser.error(str(exc))
        print(f"wrote {len(files)} measured runs to {args.export_runs}")
    if args.out:
        from .report import write_report

        res = write_report(args.db, args.out, ids or None)
        for rid, s in res["runs"].items():
            frac = "-" if s["oracle_fraction"] is None else f"{s['oracle_fraction']:.3f}"
            print(f"{rid}: oracle fraction {frac}, stalls {s['stalls']}, "
                  f"stick-slip strokes {s['stick_slip_strokes']}")
        print(f"report: {args.out}/report.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
