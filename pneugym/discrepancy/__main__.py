"""``python -m pneugym.discrepancy PATH... --out DIR``: the discrepancy workflow on measured runs.

A PATH is a run (``NAME.csv``, ``NAME.json`` or the stem ``NAME``) or a folder of runs. Writes
``report.json``, ``report.md``, ``updated_model.json`` and PNG plots into ``DIR`` (as a set:
an earlier report there is replaced only once all are written) and prints the decision. Exit
status 0 on success, 2 when ``DIR`` is empty or cannot be a writable folder (checked before
anything else), a run is refused (the message names the file, row or key and the reason) or the
plant cannot simulate a run (a ``SimulationError`` or ``ValueError`` naming the run): never a
traceback for bad input.
"""
from __future__ import annotations

import argparse
import sys
import time

from ..data import MeasurementFormatError
from ..outputs import OutputError, check_output_dir
from ..params import LINE_MODELS, ORIFICE_MODELS
from ..plant import SimulationError
from .candidates import CANDIDATES
from .prepare import MAX_SAMPLES
from .workflow import Discrepancy


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description="Find where simulation and measurement disagree, name the missing effect, "
                    "add it to the model and show the gap shrink.",
        epilog="examples:\n"
               "  pneugym discrepancy runs/ --out report/\n"
               "  pneugym discrepancy runs/a runs/b.csv --out report/ --holdout b --jobs 2\n"
               "  python -m pneugym.discrepancy runs/ --out report/ --no-plots --no-progress",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("paths", nargs="+", metavar="PATH", help="a run (NAME.csv/NAME.json/NAME) or a folder of runs")
    ap.add_argument("--out", required=True, metavar="DIR", help="folder for report.json, report.md, plots")
    ap.add_argument("--holdout", default="auto", metavar="NAME",
                    help="run to hold out: a run name, 'auto' (default: the median run by cut-off "
                         "time) or 'none'")
    ap.add_argument("--candidates", default=",".join(CANDIDATES),
                    help=f"comma-separated candidate effects (default: {','.join(CANDIDATES)}; "
                         "also valve_delay, a valve slower than stated, with --calibrate basic)")
    ap.add_argument("--starts", type=int, default=None,
                    help="least-squares starts per fit (default 4; 2 for --hold)")
    ap.add_argument("--probe", type=int, default=24, help="start points screened per fit (default 24)")
    ap.add_argument("--max-nfev", type=int, default=40, help="iterations per start (default 40)")
    ap.add_argument("--alpha", type=float, default=0.01, help="significance level (default 0.01)")
    ap.add_argument("--min-improvement", type=float, default=None,
                    help="fraction of the calibrated model's misfit an effect must remove (default "
                         "0.1; with --discrepancy-term ar, 0.3 of the misfit above the noise)")
    ap.add_argument("--discrepancy-term", choices=("none", "ar"), default="none",
                    help="model of the structural error the tests read the residuals through: none "
                         "(default: the residuals' autocorrelation deflates their sample size) or "
                         "ar (an autoregressive model fitted on the calibrated nominal model "
                         "whitens every candidate's residuals; an option for rigs whose form the "
                         "model misses, see docs/discrepancy.md)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random starts (default 0)")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: all cores)")
    ap.add_argument("--max-samples", type=int, default=MAX_SAMPLES,
                    help=f"most samples per run after windowing; more are block-averaged "
                         f"(default {MAX_SAMPLES})")
    ap.add_argument("--calibrate", choices=("extended", "basic"), default="extended",
                    help="nominal parameters calibrated first: extended (default: discharge "
                         "coefficient, friction, valve delay, exhaust and port areas, cushion "
                         "length) or basic (discharge coefficient and friction)")
    ap.add_argument("--line-models", nargs="+", default=None, choices=LINE_MODELS, metavar="MODEL",
                    help="supply-line models to run the workflow on (fd, lumped); another than "
                         "the runs' stated one is kept only if its updated model fits clearly "
                         "better (default: the stated one only)")
    ap.add_argument("--orifice-models", nargs="+", default=None, choices=ORIFICE_MODELS,
                    metavar="LAW",
                    help="orifice laws to run the workflow on (thesis, iso6358), with each line "
                         "model tried; as --line-models, another form than the stated one is kept "
                         "only if it fits clearly better (default: the stated law only)")
    ap.add_argument("--hold", action="store_true",
                    help="the PATHs are hold tests of a closed chamber (CSV with columns t [s] and "
                         "p_drive [Pa absolute], or zillen:NAME for a shipped public record): name "
                         "leakage (through an orifice or laminar pores, the law reported), heat_transfer, "
                         "both or none; one report folder per record in --out "
                         "(of the options, only --alpha, --min-improvement, --seed, --starts, "
                         "--leak-laws and --no-plots apply)")
    ap.add_argument("--leak-laws", nargs="+", default=None, choices=("orifice", "laminar"),
                    metavar="LAW",
                    help="with --hold: the laws a leak is fitted with, orifice and/or laminar "
                         "(default both; the better fit stands for leakage, the report says which)")
    ap.add_argument("--rig", default=None, metavar="FILE",
                    help="rig file of the rig the runs were measured on: what their JSON rig "
                         "sections leave out (default the thesis rig's values)")
    ap.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    ap.add_argument("--no-progress", "--quiet", dest="quiet", action="store_true",
                    help="no progress bar")
    return ap


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    if not a.out.strip():  # Path("") is the current folder: never write there by accident
        print(f"error: --out {a.out!r} is empty: give a folder path for the report (an empty "
              f"path would write into the current folder)", file=sys.stderr)
        return 2
    try:
        # the string as given (check_output_dir refuses "" too): before the (long) fit
        out = check_output_dir(a.out, "--out folder")
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if a.hold:
        if a.line_models or a.orifice_models:
            print("error: --line-models and --orifice-models are for extension strokes; a hold "
                  "test has no supply line or valve flow to model (the valve is closed)",
                  file=sys.stderr)
            return 2
        return _hold(a, out)
    if a.leak_laws:
        print("error: --leak-laws is for hold tests (--hold)", file=sys.stderr)
        return 2
    names = [c.strip() for c in a.candidates.split(",") if c.strip()]
    holdout = None if a.holdout.lower() == "none" else a.holdout
    try:
        d = Discrepancy(names, holdout=holdout, n_probe=a.probe, max_nfev=a.max_nfev, alpha=a.alpha,
                        min_improvement=a.min_improvement, seed=a.seed, n_jobs=a.jobs,
                        progress=not a.quiet, max_samples=a.max_samples, calibrate=a.calibrate,
                        discrepancy_term=None if a.discrepancy_term == "none" else a.discrepancy_term,
                        line_models=a.line_models, orifice_models=a.orifice_models, **_starts(a))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        # the workflow reads the runs itself: a long run's full arrays are dropped as soon as
        # it has been cut to its informative window
        from ..rigfile import as_rig

        d.fit(a.paths, as_rig(a.rig, "--rig") if a.rig else None)
    except MeasurementFormatError as exc:  # names the file, row or key
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (SimulationError, ValueError) as exc:  # the plant or a rig, not a traceback
        run_names = [r.name for r in getattr(d, "runs_", [])]
        msg = str(exc)
        if not any(f"run {n!r}" in msg for n in run_names):  # name the runs if it does not
            msg = f"runs {', '.join(run_names) or ', '.join(a.paths)}: {msg}"
        if isinstance(exc, SimulationError):
            msg += " (the plant cannot simulate the run: check its JSON rig and valve column)"
        print(f"error: {msg}", file=sys.stderr)
        return 2
    print(f"{len(d.runs_)} run(s): " + ", ".join(r.name for r in d.runs_), flush=True)
    try:
        path = d.report(out, plots=not a.no_plots)
    except (OSError, ValueError) as exc:  # e.g. the disk filled up: the old report is left as it was
        print(d.summary())
        print(f"error: the report could not be written to {out}: {exc}", file=sys.stderr)
        return 2
    print(d.summary())
    also = "report.md, updated_model.json" + ("" if a.no_plots else ", plots")
    print(f"report: {path} (and {also}) in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def _starts(a: argparse.Namespace) -> dict[str, int]:
    """``--starts`` if given; otherwise each fit keeps its own default."""
    return {} if a.starts is None else {"n_starts": a.starts}


def _hold(a: argparse.Namespace, out) -> int:
    """Every PATH as a hold test; a report folder ``out/NAME`` each."""
    from .hold import HoldDiscrepancy, read_hold, write_hold_report
    try:
        recs = [read_hold(p) for p in a.paths]
        h = HoldDiscrepancy(alpha=a.alpha, seed=a.seed,
                            min_improvement=0.1 if a.min_improvement is None else a.min_improvement,
                            **_starts(a), **({"leak_laws": tuple(a.leak_laws)} if a.leak_laws else {}))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    names = [r.name for r in recs]
    if len(set(names)) < len(names):
        print(f"error: two hold records share a name ({', '.join(names)}): each gets the report "
              f"folder --out/NAME", file=sys.stderr)
        return 2
    for rec in recs:
        try:
            h.fit(rec)
        except (SimulationError, ValueError) as exc:
            print(f"error: hold record {rec.name!r}: {exc} (the plant cannot simulate it)", file=sys.stderr)
            return 2
        try:
            path = write_hold_report(h, out / rec.name, plots=not a.no_plots)
        except (OSError, ValueError) as exc:
            print(f"{rec.name}: {h.decision_}")
            print(f"error: the report could not be written to {out / rec.name}: {exc}", file=sys.stderr)
            return 2
        print(f"{rec.name}: {h.decision_}\n  report: {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
