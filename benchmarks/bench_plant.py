"""Speed and accuracy benchmarks of the pneugym plant: the entry point that runs every section
and writes ``plant.json``. This file holds the first-call and real-time-factor sections and the
report; each other section is a module of its own.

Run from the repository root::

    python benchmarks/bench_plant.py                 # full run (a few minutes)
    python benchmarks/bench_plant.py --quick         # < 1 minute, fewer repeats
    python benchmarks/bench_plant.py --out DIR       # where plant.json goes (default benchmarks/results)
    python benchmarks/bench_plant.py --only rtf,batch

Sections (see ``benchmarks/README.md``), and where they live:

first_call, a. rtf (here): compile / cache-load time in fresh interpreters; real-time factor
   (RTF) of one plant at the default configuration;
b. accuracy (``bench_accuracy.py``): the default configuration against a converged reference
   (4x line cells, dt/4), and the RTF / error trade-off of alternative line grids and orifice
   linear zones; the IMEX stability scan is ``imex_stability.py``;
c. batch (``bench_batch.py``): batched kernel (``PlantBatch``) throughput with 1 and 2 numba threads;
d. scipy (``bench_solve_ivp.py``): the plant's own stepper against ``scipy.integrate.solve_ivp``
   on the same jitted RHS (lumped line, smooth window), wall time at equal accuracy;
d'. fullstroke (``bench_fullstroke.py``): the same comparison over whole strokes (valve commands,
   breakaway, stick-slip, end stop), solve_ivp driven from event to event on the plant's kernels;
e. profile (``bench_profile.py``): cost of one RHS call, one substep, one orifice flow.

Timing, tables, machine information and versions are in ``common.py``. Each section module also
runs alone (``python benchmarks/bench_accuracy.py --quick`` = ``--only accuracy``).

All timings are wall-clock medians of repeats after a warm-up call (numba compilation excluded)
and all ratios are measured within one process, so that load from other processes on the
machine affects both sides of a ratio alike. ``plant.json`` holds every number printed and more.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import bench_accuracy
import bench_batch
import bench_fullstroke
import bench_profile
import bench_solve_ivp
from common import (
    GOAL_RTF, ROOT, fmt_table, g, interleaved, json_default, machine_info, stats, versions,
)
from pneugym import Plant, thesis_rig
from pneugym.physics import system as K


# ------------------------------------------------------------------------------------------
# first call and a. real-time factor
# ------------------------------------------------------------------------------------------
_FIRST_CALL_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from pneugym import Plant, PlantBatch, thesis_rig
t1 = time.perf_counter()
p = Plant(thesis_rig(2.5))
t2 = time.perf_counter()
p.advance(0.01, 1)
t3 = time.perf_counter()
p.reset(); t4 = time.perf_counter(); p.advance(0.01, 1); t5 = time.perf_counter()
b = PlantBatch([thesis_rig(2.5)] * 2)
t6 = time.perf_counter()
b.advance(np.ones(2), 0.005)
t7 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "plant_init_s": t2 - t1, "first_advance_s": t3 - t2,
                  "second_advance_s": t5 - t4, "batch_init_s": t6 - t5,
                  "first_batch_advance_s": t7 - t6}))
"""


def first_call_costs(cold: bool):
    """Import + first-call times in fresh interpreters: with the package's numba cache (cache
    load; run twice so a missing cache is written first) and, if ``cold``, with an empty
    ``NUMBA_CACHE_DIR`` (full compilation)."""
    out = {}
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")

    def one(e):
        r = subprocess.run([sys.executable, "-c", _FIRST_CALL_SCRIPT], env=e, capture_output=True,
                           text=True, cwd=ROOT, timeout=900)
        if r.returncode != 0:
            return {"error": r.stderr[-2000:]}
        return json.loads(r.stdout.strip().splitlines()[-1])

    one(env)  # make sure the on-disk cache exists
    out["cache_load"] = one(env)
    if cold:
        with tempfile.TemporaryDirectory() as td:
            e = dict(env)
            e["NUMBA_CACHE_DIR"] = td
            out["cold_compile"] = one(e)
    return out


def bench_rtf(reps):
    res = {}
    plants = {}
    cases = []
    for bar in (2.5, 1.5):
        plant = Plant(thesis_rig(bar))
        t_first0 = time.perf_counter()
        plant.advance(0.01, 1)
        first = time.perf_counter() - t_first0

        def adv(p=plant):
            p.advance(2.0, 1)

        def run_rec(p=plant):
            p.run(2.0, record_dt=1e-3)

        def control_loop(p=plant):  # 5 ms control periods, as an environment would call it
            for _ in range(400):
                p.advance(0.005, 1)

        def kernel_loop(p=plant):  # the same periods, the jitted call alone (no checks)
            for _ in range(400):
                K.command_advance(p.y, p.P, p.d, p._work, 1.0, 0.005, False)

        # the same rig with the FD line solved implicitly (SolverParams(line_scheme="implicit"))
        imp = Plant(thesis_rig(bar).with_(solver={"line_scheme": "implicit"}))
        imp.advance(0.01, 1)
        plants[bar] = (plant, first, imp)

        def imp_adv(p=imp):
            p.advance(2.0, 1)

        def imp_loop(p=imp):
            for _ in range(400):
                p.advance(0.005, 1)

        cases += [((bar, "advance"), adv, plant.reset), ((bar, "run"), run_rec, plant.reset),
                  ((bar, "loop"), control_loop, plant.reset),
                  ((bar, "kernel"), kernel_loop, plant.reset),
                  ((bar, "implicit"), imp_adv, imp.reset),
                  ((bar, "implicit loop"), imp_loop, imp.reset)]
    cpu = {}
    times = interleaved(cases, reps, cpu)
    for bar, (plant, first, imp) in plants.items():
        plant.reset()
        plant.advance(2.0, 1)
        imp.reset()
        imp.advance(2.0, 1)
        t_adv, t_run, t_ctl = times[(bar, "advance")], times[(bar, "run")], times[(bar, "loop")]
        n_sub = math.ceil(2.0 / plant.dt_s - 1e-9)
        res[f"{bar}bar"] = {
            "supply_bar_gauge": bar, "dt_s": plant.dt_s, "dt_limited_by": plant.dt_limited_by,
            "n_cells": plant.n_cells, "simulated_s": 2.0, "arrival_time_s": plant.arrival_time_s,
            "first_call_in_process_s": first, "substeps_advance": n_sub,
            "advance": stats(t_adv), "rtf_advance": 2.0 / float(np.median(t_adv)),
            "run_record_1ms": stats(t_run), "rtf_run_record_1ms": 2.0 / float(np.median(t_run)),
            "control_loop_5ms": stats(t_ctl), "rtf_control_loop_5ms": 2.0 / float(np.median(t_ctl)),
            "ns_per_substep_advance": float(np.median(t_adv)) / n_sub * 1e9,
            "cpu_time": {"advance": stats(cpu[(bar, "advance")]),
                         "rtf_advance": 2.0 / float(np.median(cpu[(bar, "advance")])),
                         "control_loop_5ms": stats(cpu[(bar, "loop")]),
                         "rtf_control_loop_5ms": 2.0 / float(np.median(cpu[(bar, "loop")])),
                         "us_per_advance_5ms_call": float(np.median(cpu[(bar, "loop")])) / 400 * 1e6},
            "us_per_advance_5ms_call": float(np.median(t_ctl)) / 400 * 1e6,
            # Plant.advance's 5 ms call against the jitted call alone, CPU time: its checks' cost
            "control_loop_over_kernel": float(np.median(cpu[(bar, "loop")]))
            / float(np.median(cpu[(bar, "kernel")])),
            "implicit_line": {  # CPU time, timed round-robin with the explicit cases above
                "dt_s": imp.dt_s, "dt_limited_by": imp.dt_limited_by,
                "arrival_time_s": imp.arrival_time_s,
                "rtf_advance": 2.0 / float(np.median(cpu[(bar, "implicit")])),
                "rtf_control_loop_5ms": 2.0 / float(np.median(cpu[(bar, "implicit loop")])),
                "advance_speedup_over_explicit": float(np.median(cpu[(bar, "advance")]))
                / float(np.median(cpu[(bar, "implicit")])),
                "loop_speedup_over_explicit": float(np.median(cpu[(bar, "loop")]))
                / float(np.median(cpu[(bar, "implicit loop")])),
            },
        }
    return res


# ------------------------------------------------------------------------------------------
# report: every section's tables, in the order of the sections
# ------------------------------------------------------------------------------------------
def report_rtf(a):
    """Text blocks of section a (rtf) for the report."""
    out = []
    rows = []
    for k, e in a.items():
        rows.append([k, g(e["dt_s"] * 1e6, 4), e["dt_limited_by"], e["substeps_advance"],
                     g(e["advance"]["median_s"] * 1e3, 4), g(e["rtf_advance"], 4),
                     g(e["rtf_run_record_1ms"], 4), g(e["rtf_control_loop_5ms"], 4),
                     g(e["ns_per_substep_advance"], 4), g(e["us_per_advance_5ms_call"], 3),
                     g(e["cpu_time"]["rtf_advance"], 4), g(e["cpu_time"]["us_per_advance_5ms_call"], 3),
                     g(e["control_loop_over_kernel"], 3), g(e["arrival_time_s"], 6)])
    out.append(fmt_table(["supply", "dt[us]", "dt limited by", "substeps", "advance 2s [ms]",
                          "RTF advance", "RTF run(rec 1ms)", "RTF 5ms-loop", "ns/substep",
                          "us / advance(5ms)", "RTF advance (CPU)", "us / advance(5ms) (CPU)",
                          "call / kernel (CPU)", "arrival [s]"], rows,
                         f"a. Real-time factor, one plant, default configuration "
                         f"(goal RTF >= {GOAL_RTF:.0f}); medians of {a['2.5bar']['advance']['n']} repeats; (CPU): "
                         "this thread's CPU time, which does not count waiting for a core on a busy machine"))
    rows = []
    for k, e in a.items():
        m = e["implicit_line"]
        rows.append([k, g(m["dt_s"] * 1e6, 4), m["dt_limited_by"], g(m["rtf_advance"], 4),
                     g(m["advance_speedup_over_explicit"], 3), g(m["rtf_control_loop_5ms"], 4),
                     g(m["loop_speedup_over_explicit"], 3), g(m["arrival_time_s"], 6)])
    out.append(fmt_table(["supply", "dt[us]", "dt limited by", "RTF advance (CPU)",
                          "x explicit", "RTF 5ms-loop (CPU)", "x explicit", "arrival [s]"], rows,
                         "a'. The same with the FD line solved implicitly "
                         "(SolverParams(line_scheme='implicit')), CPU time, timed round-robin "
                         "with the explicit line"))
    inproc = {k: e["first_call_in_process_s"] for k, e in a.items()}
    out.append("   first call in this process (cache load): "
               + ", ".join(f"{k}: {v:.3f} s" for k, v in inproc.items()))
    return out


def report_first_call(fc):
    """Text block of the first_call section for the report (none if it did not run)."""
    out = []
    rows = []
    for k, e in fc.items():
        if "error" in e:
            rows.append([k, "error", "", "", ""])
            continue
        rows.append([k, g(e["import_s"], 3), g(e["plant_init_s"], 3), g(e["first_advance_s"], 3),
                     g(e["second_advance_s"] * 1e3, 3), g(e["first_batch_advance_s"], 3)])
    if rows:
        out.append(fmt_table(["numba cache", "import [s]", "Plant() [s]", "1st Plant.advance [s]",
                              "2nd advance(0.01s) [ms]", "1st PlantBatch.advance [s]"], rows,
                             "   First call (fresh interpreter): cache load vs cold compile"))
    return out


def report(R):
    out = []
    if "rtf" in R:
        out += report_rtf(R["rtf"])
    out += report_first_call(R.get("first_call", {}))
    if "accuracy" in R:
        out += bench_accuracy.report_accuracy(R["accuracy"])
    if "batch" in R:
        out += bench_batch.report_batch(R["batch"])
    if "scipy" in R:
        out += bench_solve_ivp.report_scipy(R["scipy"])
    if "fullstroke" in R:
        out += bench_fullstroke.report_fullstroke(R["fullstroke"])
    if "profile" in R:
        out += bench_profile.report_profile(R["profile"])
    return "\n\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"), help="output directory")
    ap.add_argument("--quick", action="store_true", help="< 1 minute: fewer repeats and cases")
    ap.add_argument("--repeats", type=int, default=None, help="repeats per timing (default 21, quick 5)")
    ap.add_argument("--no-cold-compile", action="store_true",
                    help="skip the cold-compile measurement (fresh NUMBA_CACHE_DIR; ~1 min)")
    ap.add_argument("--only", default=None,
                    help="comma-separated sections to run: first_call,rtf,accuracy,batch,scipy,fullstroke,profile")
    args = ap.parse_args(argv)
    reps = args.repeats or (5 if args.quick else 21)
    t_start = time.perf_counter()
    R = {"benchmark": "pneugym plant", "date_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(),
         "configuration": {"quick": args.quick, "repeats": reps,
                           "default_rig": thesis_rig(2.5).to_dict(),
                           "timing": "wall-clock medians after a warm-up call (time.perf_counter)"},
         "versions": versions(), "machine": machine_info()}
    steps = [("first_call", lambda: first_call_costs(cold=not (args.quick or args.no_cold_compile))),
             ("rtf", lambda: bench_rtf(reps)),
             ("accuracy", lambda: bench_accuracy.bench_accuracy(reps, args.quick)),
             ("batch", lambda: bench_batch.bench_batch(reps, args.quick)),
             ("scipy", lambda: bench_solve_ivp.bench_scipy(reps, args.quick)),
             ("fullstroke", lambda: bench_fullstroke.bench_fullstroke(reps, args.quick)),
             ("profile", lambda: bench_profile.bench_profile(reps, args.quick))]
    if args.only:
        keep = set(args.only.split(","))
        unknown = keep - {s for s, _ in steps}
        if unknown:
            ap.error(f"unknown sections {sorted(unknown)}")
        steps = [s for s in steps if s[0] in keep]
    R["section_wall_s"] = {}
    for name, fn in steps:
        t0 = time.perf_counter()
        print(f"[{name}] ...", file=sys.stderr, flush=True)
        R[name] = fn()
        R["section_wall_s"][name] = time.perf_counter() - t0
    R["machine"]["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    R["total_wall_s"] = time.perf_counter() - t_start
    text = report(R)
    print(text)
    print(f"\n(total {R['total_wall_s']:.1f} s; load average start {R['machine']['loadavg_start']}, "
          f"end {R['machine']['loadavg_end']})")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    R["report_text"] = text
    with open(out / "plant.json", "w") as fh:
        json.dump(R, fh, indent=1, default=json_default)
    print(f"wrote {out / 'plant.json'}")


if __name__ == "__main__":
    main()
