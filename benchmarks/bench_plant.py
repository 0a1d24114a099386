"""Speed and accuracy benchmarks of the pneugym plant.

Run from the repository root::

    python benchmarks/bench_plant.py                 # full run (a few minutes)
    python benchmarks/bench_plant.py --quick         # < 1 minute, fewer repeats
    python benchmarks/bench_plant.py --out DIR       # where plant.json goes (default benchmarks/results)

Sections (see ``benchmarks/README.md``):

a. real-time factor (RTF) of one plant at the default configuration, compile / cache-load time;
b. accuracy of the default configuration against a converged reference (4x line cells, dt/4),
   and the RTF / error trade-off of alternative line grids and orifice linear zones;
c. batched kernel (``PlantBatch``) throughput with 1 and 2 numba threads;
d. the plant's own stepper against ``scipy.integrate.solve_ivp`` on the same jitted RHS
   (lumped line, smooth window), wall time at equal accuracy;
d'. fullstroke: the same comparison over whole strokes (valve commands, breakaway, stick-slip,
   end stop), solve_ivp driven from event to event on the plant's kernels;
e. profile: cost of one RHS call, one substep, one orifice flow.

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
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numba  # noqa: E402
from numba import njit  # noqa: E402

import pneugym  # noqa: E402
from pneugym import Plant, PlantBatch, thesis_rig  # noqa: E402
from pneugym.physics import layout as L  # noqa: E402
from pneugym.physics import system as K  # noqa: E402
from pneugym.physics.cylinder import cushion_factor  # noqa: E402
from pneugym.physics.orifice import NOC, flow_at, mass_flow  # noqa: E402
from pneugym.plant import choose_dt, stability_limits  # noqa: E402

NOREC = np.zeros((0, L.NR))
GOAL_RTF = 1000.0
GOAL_ERR_PCT = 0.5
GOAL_SCIPY_RATIO = 50.0


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
def timeit(fn, setup=None, repeats=11, warmup=1):
    """Wall times [s] of ``fn()`` (``setup()`` before each call, untimed); returns the list."""
    for _ in range(warmup):
        if setup is not None:
            setup()
        fn()
    out = []
    for _ in range(repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def stats(times):
    a = np.asarray(times, float)
    return {"median_s": float(np.median(a)), "min_s": float(a.min()), "max_s": float(a.max()),
            "n": int(a.size)}


def rel_pct(x, ref):
    return 100.0 * (x - ref) / ref


def fmt_table(headers, rows, title=None):
    """Plain-text table (strings are left-aligned, numbers right-aligned)."""
    cells = [[str(h) for h in headers]] + [[c if isinstance(c, str) else f"{c}" for c in r]
                                           for r in rows]
    w = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    if title:
        lines.append(title)
    sep = "  "
    lines.append(sep.join(h.ljust(w[i]) for i, h in enumerate(cells[0])))
    lines.append(sep.join("-" * w[i] for i in range(len(w))))
    for r in cells[1:]:
        lines.append(sep.join(c.rjust(w[i]) if _numeric(c) else c.ljust(w[i])
                              for i, c in enumerate(r)))
    return "\n".join(lines)


def _numeric(s):
    try:
        float(s.replace("%", "").replace("x", "").replace("+", ""))
        return True
    except ValueError:
        return False


def g(x, nd=4):
    """Short number formatting for tables."""
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if not math.isfinite(x):
        return str(x)
    return f"{x:.{nd}g}"


def pct(x, nd=3):
    return "-" if x is None else f"{x:+.{nd}f}%"


def machine_info():
    info = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "loadavg_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "numba_num_threads": numba.config.NUMBA_NUM_THREADS,
    }
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        with open("/proc/meminfo") as fh:
            info["mem_total"] = fh.readline().split(":", 1)[1].strip()
    except OSError:
        pass
    return info


def versions():
    import scipy
    v = {"pneugym": pneugym.__version__, "numpy": np.__version__, "numba": numba.__version__,
         "scipy": scipy.__version__, "llvmlite": __import__("llvmlite").__version__}
    import hashlib
    h = hashlib.sha256()
    for f in sorted((ROOT / "pneugym").rglob("*.py")):
        h.update(str(f.relative_to(ROOT)).encode())
        h.update(f.read_bytes())
    v["pneugym_source_sha256"] = h.hexdigest()[:16]
    v["pneugym_path"] = str(Path(pneugym.__file__).resolve().parent)
    try:
        v["git_commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                         text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "pneugym"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        v["pneugym_dirty"] = bool(dirty)
    except (OSError, subprocess.CalledProcessError):
        pass
    return v


# ------------------------------------------------------------------------------------------
# a. real-time factor and first-call cost
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


def interleaved(cases, reps, cpu=None):
    """Time several ``(name, fn, setup)`` cases round-robin (one call of each per round, after
    one warm-up round), so that load from other processes hits every case alike. If ``cpu`` is
    a dict, it receives the same calls' CPU times of this thread (``time.thread_time``): a
    single-threaded call's CPU time does not count the time the process waits for a core."""
    for _, fn, setup in cases:
        setup()
        fn()
    times = {name: [] for name, _, _ in cases}
    if cpu is not None:
        cpu.update({name: [] for name, _, _ in cases})
    for _ in range(reps):
        for name, fn, setup in cases:
            setup()
            c0 = time.thread_time()
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
            if cpu is not None:
                cpu[name].append(time.thread_time() - c0)
    return times


def bench_rtf(reps):
    res = {}
    plants = {}
    cases = []
    for bar in (2.5, 1.5):
        plant = Plant(thesis_rig(bar))
        t_first0 = time.perf_counter()
        plant.advance(0.01, 1)
        first = time.perf_counter() - t_first0
        plants[bar] = (plant, first)

        def adv(p=plant):
            p.advance(2.0, 1)

        def run_rec(p=plant):
            p.run(2.0, record_dt=1e-3)

        def control_loop(p=plant):  # 5 ms control periods, as an environment would call it
            for _ in range(400):
                p.advance(0.005, 1)

        cases += [((bar, "advance"), adv, plant.reset), ((bar, "run"), run_rec, plant.reset),
                  ((bar, "loop"), control_loop, plant.reset)]
    cpu = {}
    times = interleaved(cases, reps, cpu)
    for bar, (plant, first) in plants.items():
        plant.reset()
        plant.advance(2.0, 1)
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
        }
    return res


# ------------------------------------------------------------------------------------------
# b. accuracy against a converged reference, and the trade-off table
# ------------------------------------------------------------------------------------------
T_END_ACC = 3.0
T_CUT_MID = 0.45  # early cut-off: the piston stops mid-stroke
T_CUT_LATE = {2.5: 1.1, 1.5: 1.25}  # later cut-off: valve closes mid-stroke, the piston still arrives
STOPPED_V = 1e-5  # [m/s] a piston slower than this counts as stopped (it may creep asymptotically)


def refined_rig(rig, factor):
    """``rig`` with ``factor`` x the line cells and dt / ``factor`` (or the stability limit of
    the refined grid times the safety factor if that is smaller)."""
    dt0, _ = choose_dt(rig)
    n = rig.line.n_cells * factor
    fine = rig.with_(line={"n_cells": n})
    lim = stability_limits(fine)
    lim_name = min(lim, key=lim.get)
    dt = dt0 / factor
    note = f"dt = default dt / {factor}"
    if dt > lim[lim_name] * fine.solver.safety:
        dt = lim[lim_name] * fine.solver.safety
        note = (f"dt/{factor} = {dt0 / factor:.3g} s is above the {lim_name} limit x safety "
                f"{lim[lim_name] * fine.solver.safety:.3g} s of the refined grid; used that")
    ref = fine.with_(solver={"dt_s": dt})
    dt_chk, how = choose_dt(ref)  # raises if not accepted
    return ref, {"n_cells": n, "dt_s": dt_chk, "dt_how": how, "note": note,
                 "stability_limit_s": lim[lim_name], "stability_limited_by": lim_name}


def stroke_metrics(rig):
    """Stroke time and wasted energies of one configuration: conventional (closed form),
    end-stroke cut-off, early mid-stroke cut-off (``T_CUT_MID``, piston stops mid-stroke) and a
    later cut-off (``T_CUT_LATE``, valve closed mid-stroke, the piston still arrives)."""
    bar = round(rig.supply_pressure_gauge_pa / 1e5, 3)
    pl = Plant(rig)
    out = {"dt_s": pl.dt_s, "dt_limited_by": pl.dt_limited_by, "n_cells": pl.n_cells}
    pl.reset()
    pl.advance(T_END_ACC, 1)
    out["arrival_time_s"] = pl.arrival_time_s
    out["energy_conventional_j"] = pl.energy_wasted_j  # closed form (filled to supply, x = stroke)

    pl.reset()
    pl.run(T_END_ACC, cut_on_arrival=True)
    out["endcut"] = _after_cut(pl)

    pl.reset()
    pl.run(T_END_ACC, schedule=[(0.0, 1), (T_CUT_MID, 0)])
    out["midcut"] = _after_cut(pl)

    t_late = T_CUT_LATE.get(bar, 1.2)
    pl.reset()
    pl.run(T_END_ACC, schedule=[(0.0, 1), (t_late, 0)])
    out["latecut"] = {**_after_cut(pl), "command_s": t_late}
    return out


def _after_cut(pl):
    stopped = pl.mode != L.MODE_MOVING or abs(pl.velocity_m_s) < STOPPED_V
    return {"energy_wasted_j": pl.energy_wasted_j, "valve_closed": bool(pl.valve_closed),
            "valve_closed_time_s": pl.valve_closed_time_s, "piston_stopped": bool(stopped),
            "velocity_m_s": pl.velocity_m_s, "mode": pl.mode, "position_m": pl.position_m,
            "arrival_time_s": pl.arrival_time_s, "p_drive_pa": pl.p_drive_pa}


QUANTITIES = {  # name -> getter on a stroke_metrics dict
    "stroke_time": lambda m: m["arrival_time_s"],
    "energy_conventional": lambda m: m["energy_conventional_j"],
    "energy_endcut": lambda m: m["endcut"]["energy_wasted_j"],
    "energy_midcut": lambda m: m["midcut"]["energy_wasted_j"],
    "energy_latecut": lambda m: m["latecut"]["energy_wasted_j"],
    "latecut_arrival": lambda m: m["latecut"]["arrival_time_s"],
    "midcut_final_position": lambda m: m["midcut"]["position_m"],
}
GOAL_QUANTITIES = ("stroke_time", "energy_conventional", "energy_endcut", "energy_midcut",
                   "energy_latecut")


def compare(m, ref):
    """Relative errors [%] of ``m`` against ``ref`` (a stroke_metrics dict or a dict of values)."""
    e = {}
    for q, get in QUANTITIES.items():
        a = get(m)
        b = ref[q] if q in ref else get(ref)
        e[q + "_pct"] = None if a is None or b is None else rel_pct(a, b)
    vals = [abs(e[q + "_pct"]) for q in GOAL_QUANTITIES if e[q + "_pct"] is not None]
    e["max_abs_pct"] = max(vals) if vals else None
    return e


def richardson(m4, m16, m32):
    """Extrapolate each quantity to n_cells -> inf from the levels 4x and 8x (grid ratio 2) with
    the order observed from the default (1x), 4x and 8x levels (h ~ 1/n_cells, dt ~ h)."""
    out, orders = {}, {}
    for q, get in QUANTITIES.items():
        x1, x4, x8 = get(m4), get(m16), get(m32)
        if None in (x1, x4, x8) or x4 == x8:
            out[q], orders[q] = x8, None
            continue
        ratio = (x1 - x4) / (x4 - x8)
        p = _observed_order(ratio)
        orders[q] = p
        pp = p if p is not None else 1.0
        out[q] = x8 - (x4 - x8) / (2.0 ** pp - 1.0)
    return out, orders


def _observed_order(ratio):
    """Order p with (1 - 4^-p) / (4^-p - 8^-p) = ratio (levels h, h/4, h/8); None if none."""
    f = lambda p: (1.0 - 4.0 ** -p) / (4.0 ** -p - 8.0 ** -p) - ratio  # noqa: E731
    lo, hi = 0.05, 6.0
    if not (f(lo) < 0 < f(hi)):
        return None
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if f(mid) < 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# -- stability check: IMEX amplification of the linearised plant -------------------------------
def jacobian(plant, y, d, mode):
    """Finite-difference Jacobian of the jitted rhs at state (y, d) with the given mode."""
    n, b = plant.n_cells, plant._b
    dy = np.empty_like(y)
    p = np.empty(n)
    t = float(d[L.D_T])
    K.rhs(t, y, plant.P, d, mode, dy, p)
    f0 = dy.copy()
    floor = np.full(y.size, 1e-12)
    floor[n:b] = 1e-5  # face mass flows [kg/s]
    floor[b + L.Y_X] = floor[b + L.Y_V] = 1e-4
    J = np.empty((y.size, y.size))
    for j in range(y.size):
        h = 1e-7 * max(abs(y[j]), floor[j])
        yy = y.copy()
        yy[j] += h
        K.rhs(t, yy, plant.P, d, mode, dy, p)
        J[:, j] = (dy - f0) / h
    return J


def _implicit_jacobian(plant, y, d):
    """Jacobian of the IMEX substep's implicit part: the port flow (line cell n-1 -> driving
    chamber), with more than one cell the valve flow (supply -> cell 0, and the supply mass),
    and with a lumped line of more than one cell the joints between its cells."""
    n, b = plant.n_cells, plant._b
    P = plant.P
    RT = P[L.P_R] * P[L.P_T]

    def port(yy):
        pc = yy[n - 1] * RT / P[L.NP + n - 1]
        pd, _, _, _ = K.chamber_pressures(yy, P, b)
        fd = cushion_factor(yy[b + L.Y_X], P[L.P_CUSH_LEN], P[L.P_CUSH_FD], P[L.P_CUSH_RAMP])
        return flow_at(pc, pd, fd * P[L.P_CDA_PORT], P[L.P_SQRT_T], math.sqrt(yy[b + L.Y_TD]), P, L.P_OC)

    def valve(yy):
        s, _ = K.valve_opening(d, P, d[L.D_T])
        if s <= 0.0:
            return 0.0
        return flow_at(K.supply_pressure(P, d[L.D_T]), yy[0] * RT / P[L.NP], s * P[L.P_CDA_VALVE],
                       P[L.P_SQRT_T], P[L.P_SQRT_T], P, L.P_OC)

    def joint(j):
        def f(yy):
            return flow_at(yy[j] * RT / P[L.NP + j], yy[j + 1] * RT / P[L.NP + j + 1],
                           P[L.P_CDA_LINE], P[L.P_SQRT_T], P[L.P_SQRT_T], P, L.P_OC)
        return f

    JI = np.zeros((y.size, y.size))
    parts = [(port, [n - 1, b + L.Y_MD], n - 1, b + L.Y_MD)]
    if n > 1:
        parts.append((valve, [0], None, 0))
    if P[L.P_LINE_MODEL] != 0.0 and n > 1:
        parts += [(joint(j), [j, j + 1], j, j + 1) for j in range(n - 1)]
    for f, cols, out_row, in_row in parts:
        f0 = f(y)
        for j in cols:
            h = 1e-7 * max(abs(y[j]), 1e-12)
            yy = y.copy()
            yy[j] += h
            g = (f(yy) - f0) / h
            if out_row is not None:
                JI[out_row, j] -= g
            JI[in_row, j] += g
            if f is valve:
                JI[b + L.Y_MIN, j] += g
    return JI


def imex_amplification(JE, JI, h):
    """Amplification matrix of the plant's IMEX substep for ``y' = (JE + JI) y``."""
    I = np.eye(JE.shape[0])
    FE, FI = [], []
    for i in range(3):
        rhs = I.copy()
        for j in range(i):
            rhs = rhs + h * IMEX_AE[i][j] * FE[j] + h * IMEX_AI[i][j] * FI[j]
        Y = np.linalg.solve(I - h * IMEX_AI[i][i] * JI, rhs)
        FE.append(JE @ Y)
        FI.append(JI @ Y)
    R = I.copy()
    for i in range(3):
        R = R + h * IMEX_B[i] * (FE[i] + FI[i])
    return R


IMEX_AE = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.25, 0.25, 0.0))
IMEX_AI = ((0.0, 0.0, 0.0), (K.IMEX_A21, K.IMEX_A22, 0.0), (K.IMEX_A31, K.IMEX_A32, K.IMEX_A33))
IMEX_B = (1.0 / 6.0, 1.0 / 6.0, 2.0 / 3.0)


def stability_scan(rig, t_end=T_END_ACC, every=0.01, cut_at=None):
    """Spectral radius of the IMEX substep's amplification matrix for the linearised plant at
    states sampled every ``every`` s along an extension (conventional, or cut off at ``cut_at``),
    and the largest substep (from 0.5 to 3 x dt) that keeps every sampled state stable.
    Physical growth (the Jacobian's largest real part) is allowed for: a state counts as
    unstable when rho(R) > exp(dt max Re lambda)."""
    pl = Plant(rig)
    pl.reset()
    pl.command(1)
    worst = {"max_amp": 0.0}
    mats = []
    t = 0.0
    while t < t_end - 1e-12:
        if cut_at is not None and abs(t - cut_at) < 1e-9:
            pl.command(0)
        pl.advance(every)
        t = pl.time_s
        y, d = pl.snapshot()
        J = jacobian(pl, y, d, pl.mode)
        JI = _implicit_jacobian(pl, y, d)
        grow = max(0.0, float(np.max(np.linalg.eigvals(J).real)))
        mats.append((J - JI, JI, grow))
        amp = float(np.max(np.abs(np.linalg.eigvals(imex_amplification(J - JI, JI, pl.dt_s)))))
        amp /= math.exp(pl.dt_s * grow)
        if amp > worst["max_amp"]:
            worst = {"max_amp": amp, "at_t_s": t, "mode": pl.mode}
    h_ok = None
    for f in np.arange(0.5, 3.0001, 0.05):
        h = pl.dt_s * f
        if all(np.max(np.abs(np.linalg.eigvals(imex_amplification(JE, JI, h)))) <= math.exp(h * g) * (1 + 1e-9)
               for JE, JI, g in mats):
            h_ok = h
        else:
            break
    worst["stable"] = worst["max_amp"] <= 1.0 + 1e-6
    worst["dt_s"] = pl.dt_s
    worst["dt_max_stable_s"] = float(h_ok) if h_ok else 0.0
    worst["dt_over_dt_max_stable"] = pl.dt_s / float(h_ok) if h_ok else float("inf")
    return worst


def bench_accuracy(reps, quick):
    res = {"t_end_s": T_END_ACC, "midcut_command_s": T_CUT_MID, "latecut_command_s": T_CUT_LATE,
           "stopped_below_m_s": STOPPED_V, "by_pressure": {}}
    for bar in (2.5, 1.5):
        rig = thesis_rig(bar)
        ref_rig, ref_info = refined_rig(rig, 4)
        m_def = stroke_metrics(rig)
        m_ref = stroke_metrics(ref_rig)
        entry = {"default": m_def, "reference": m_ref, "reference_grid": ref_info,
                 "errors_default_vs_reference": compare(m_def, m_ref)}
        # is the reference converged? compare it with an 8x / dt/8 solution and extrapolate
        ref8_rig, ref8_info = refined_rig(rig, 8)
        m_ref8 = stroke_metrics(ref8_rig)
        entry["reference8"] = m_ref8
        entry["reference8_grid"] = ref8_info
        entry["errors_reference_vs_reference8"] = compare(m_ref, m_ref8)
        extrap, orders = richardson(m_def, m_ref, m_ref8)
        entry["richardson_extrapolated"] = extrap
        entry["observed_order_in_1_over_n_cells"] = orders
        entry["errors_default_vs_extrapolated"] = compare(m_def, extrap)
        entry["errors_reference_vs_extrapolated"] = compare(m_ref, extrap)
        entry["stability_scan_default"] = stability_scan(rig)
        res["by_pressure"][f"{bar}bar"] = entry

    # trade-off: alternative line grids and orifice linear zones, against the same reference
    alts = []
    configs = [(n, lin) for lin in (0.02, 0.05) for n in (2, 3, 4, 6, 8)]
    cases = []
    for n, lin in configs:
        pl = Plant(thesis_rig(2.5, line={"n_cells": n}, valve={"linear_ratio": lin}))
        cases.append(((n, lin), (lambda p=pl: p.advance(2.0, 1)), pl.reset))
    rtf_times = interleaved(cases, reps)
    for n, lin in configs:
        row = {"n_cells": n, "linear_ratio": lin}
        rig25 = thesis_rig(2.5, line={"n_cells": n}, valve={"linear_ratio": lin})
        dt, why = choose_dt(rig25)
        row["dt_s"], row["dt_limited_by"] = dt, why
        row["advance_2s"] = stats(rtf_times[(n, lin)])
        row["rtf_2.5bar"] = 2.0 / row["advance_2s"]["median_s"]
        row["stability_scan_2.5bar"] = stability_scan(rig25, every=0.02 if quick else 0.01)
        for bar in (2.5, 1.5):
            rig = thesis_rig(bar, line={"n_cells": n}, valve={"linear_ratio": lin})
            m = stroke_metrics(rig)
            ref = res["by_pressure"][f"{bar}bar"]
            row[f"{bar}bar"] = {"metrics": m, "errors": compare(m, ref["reference"]),
                                "errors_vs_extrapolated": compare(m, ref["richardson_extrapolated"])}
        alts.append(row)
    res["tradeoff"] = alts
    # how much of the other linear_ratio's error is the model change (at reference resolution)?
    lin_def = thesis_rig(2.5).valve.linear_ratio
    res["default_linear_ratio"] = lin_def
    lin_model = {}
    for lin in (0.02, 0.05):
        if lin == lin_def:
            continue
        for bar in (2.5, 1.5):
            rig_l = thesis_rig(bar, valve={"linear_ratio": lin})
            refl_rig, infol = refined_rig(rig_l, 4)
            ml = stroke_metrics(refl_rig)
            ref = res["by_pressure"][f"{bar}bar"]["reference"]
            lin_model[f"{lin}@{bar}bar"] = {"linear_ratio": lin, "reference_grid": infol, "metrics": ml,
                                            "errors_vs_default_reference": compare(ml, ref)}
    res["linear_ratio_model_change"] = lin_model
    return res


# ------------------------------------------------------------------------------------------
# c. batched kernel
# ------------------------------------------------------------------------------------------
def bench_batch(reps, quick):
    sizes = (64,) if quick else (64, 256)
    period, t_sim = 0.005, 1.5
    nper = int(round(t_sim / period))
    res = {"control_period_s": period, "simulated_s": t_sim, "control_periods": nper, "sizes": {}}
    nthreads_avail = numba.config.NUMBA_NUM_THREADS
    threads = [t for t in (1, 2) if t <= nthreads_avail]
    # single plant, same control loop, for comparison
    pl = Plant(thesis_rig(2.5))

    def single():
        for _ in range(nper):
            pl.advance(period, 1)

    t_single = timeit(single, pl.reset, reps)
    res["single_plant_control_loop"] = {**stats(t_single),
                                        "plant_s_per_wall_s": t_sim / float(np.median(t_single)),
                                        "plant_steps_per_s": nper / float(np.median(t_single)),
                                        "us_per_advance_5ms_call": float(np.median(t_single)) / nper * 1e6}
    y_single = pl.y.copy()
    for B in sizes:
        batch = PlantBatch([thesis_rig(2.5)] * B)
        cmds = np.ones(B)

        def run_batch():
            for _ in range(nper):
                batch.advance(cmds, period)

        entry = {}
        times = {nt: [] for nt in threads}
        for nt in threads:  # warm-up (compiles / starts the thread pool)
            numba.set_num_threads(nt)
            batch.reset()
            run_batch()
        for _ in range(max(3, reps // 2)):  # interleaved, so that load from others hits both alike
            for nt in threads:
                numba.set_num_threads(nt)
                batch.reset()
                t0 = time.perf_counter()
                run_batch()
                times[nt].append(time.perf_counter() - t0)
        for nt in threads:
            t = times[nt]
            entry[f"{nt}_threads"] = {**stats(t), "plant_s_per_wall_s": B * t_sim / float(np.median(t)),
                                      "plant_steps_per_s": B * nper / float(np.median(t)),
                                      "plant_steps_per_s_min_time": B * nper / float(np.min(t))}
        numba.set_num_threads(nthreads_avail)
        if len(threads) == 2:
            entry["speedup_2_over_1"] = (entry["1_threads"]["median_s"] / entry["2_threads"]["median_s"])
            # from the fastest repeats: what 2 threads give when no other process takes a core
            entry["speedup_2_over_1_min_times"] = (entry["1_threads"]["min_s"] / entry["2_threads"]["min_s"])
        entry["max_abs_diff_vs_single_plant"] = float(np.max(np.abs(batch.Y - y_single[None, :])))
        entry["batch_over_single_throughput_1_thread"] = (
            entry["1_threads"]["plant_s_per_wall_s"] / res["single_plant_control_loop"]["plant_s_per_wall_s"])
        res["sizes"][str(B)] = entry
    try:
        res["threading_layer"] = numba.threading_layer()
    except ValueError:
        res["threading_layer"] = None
    return res


# ------------------------------------------------------------------------------------------
# d. against scipy.integrate.solve_ivp on the same jitted RHS
# ------------------------------------------------------------------------------------------
T_WINDOW_START = 0.35
T_WINDOW_LEN = 0.3


def _plant_solve(y0, d0, P, dt, t1):
    Pp = P.copy()
    Pp[L.P_DT] = dt
    y, d = y0.copy(), d0.copy()
    st, _ = K.advance(y, Pp, d, t1, NOREC, 0.0, False)
    if st != L.STATUS_OK:
        raise RuntimeError(f"plant status {st}")
    return y, d


def bench_scipy(reps, quick):
    from scipy.integrate import solve_ivp

    rig = thesis_rig(2.5, line={"model": "lumped"})
    pl = Plant(rig)
    n = pl.n_cells
    b = 2 * n - 1
    stroke = rig.cylinder.stroke_m
    tried = []
    # the window: just after breakaway with the valve fully open, ending before arrival; the
    # preferred start is T_WINDOW_START, later/earlier ones are tried if the rig has changed
    for t_start, t_len in [(T_WINDOW_START, T_WINDOW_LEN), (0.45, 0.3), (0.3, 0.3), (0.5, 0.2),
                           (0.35, 0.15), (0.6, 0.2)]:
        pl.reset()
        pl.advance(t_start, 1)
        s, se = pl.valve_opening
        checks = {"mode_moving": pl.mode == L.MODE_MOVING, "velocity_positive": pl.velocity_m_s > 0,
                  "valve_open": s == 1.0 and se == 1.0, "no_pending_commands": int(pl.d[L.D_NQ]) == 0,
                  "not_arrived": pl.arrival_time_s is None}
        y0, d0 = pl.snapshot()
        t0 = pl.time_s
        t1 = t0 + t_len
        P = pl.P.copy()
        y_pl, d_pl = _plant_solve(y0, d0, P, pl.dt_s, t1)
        win_checks = {"still_moving": int(d_pl[L.D_MODE]) == L.MODE_MOVING,
                      "not_arrived": d_pl[L.D_T_ARRIVE] < 0,
                      "no_stick_events": d_pl[L.D_STICKS] == d0[L.D_STICKS],
                      "x_end_below_stroke": y_pl[b + L.Y_X] < stroke}
        tried.append({"window_s": [t0, t1], **checks, **win_checks})
        if all(checks.values()) and all(win_checks.values()):
            break
    else:
        raise RuntimeError(f"no smooth window found: {tried}")

    def observe(y):
        pd, pe, _, _ = K.chamber_pressures(y, P, b)
        return {"x": float(y[b + L.Y_X]), "v": float(y[b + L.Y_V]), "pd": float(pd), "pe": float(pe)}

    def plant_solve(dt):  # the plant's own stepper from the window start
        return _plant_solve(y0, d0, P, dt, t1)

    # scipy: fixed discrete state (mode 0, valve fully open and no pending command)
    d_ivp = d0.copy()
    dy = np.empty_like(y0)
    pbuf = np.empty(n)
    rhs = K.rhs

    def fun(t, y):
        rhs(t, y, P, d_ivp, 0, dy, pbuf)
        return dy.copy()

    # absolute tolerance per component: rtol x the component's size over the window
    scale = np.maximum(np.abs(y0), np.abs(y_pl))
    scale[scale == 0.0] = 1e-20

    def ivp(method, rtol):
        return solve_ivp(fun, (t0, t1), y0.copy(), method=method, rtol=rtol, atol=rtol * scale)

    ref_sol = ivp("DOP853", 1e-12)
    if not ref_sol.success:
        raise RuntimeError(f"reference solve_ivp failed: {ref_sol.message}")
    y_ref = ref_sol.y[:, -1]
    o_ref = observe(y_ref)
    o_0 = observe(y0)

    def errors(y):
        o = observe(y)
        e = {"x": abs(o["x"] - o_ref["x"]) / abs(o_ref["x"] - o_0["x"]),
             "v": abs(o["v"] - o_ref["v"]) / abs(o_ref["v"]),
             "pd": abs(o["pd"] - o_ref["pd"]) / o_ref["pd"],
             "pe": abs(o["pe"] - o_ref["pe"]) / o_ref["pe"]}
        e["combined"] = max(e["x"], e["pd"], e["pe"])
        return e

    res = {"rig": "thesis_rig(2.5, line={'model': 'lumped'})", "n_cells": n,
           "window_s": [t0, t1], "window_checks": {**checks, **win_checks}, "windows_tried": tried,
           "state_start": o_0, "state_end_reference": o_ref,
           "error_definition": ("combined = max(|dx| / (x_ref(t1) - x(t0)), |dp_drive| / p_drive_ref, "
                                "|dp_exhaust| / p_exhaust_ref) at t1"),
           "reference": {"method": "DOP853", "rtol": 1e-12, "atol": "1e-12 x component scale",
                         "nfev": int(ref_sol.nfev)}}

    # cross-check of the reference: the plant with tiny substeps must agree (same equations)
    y_fine, _ = plant_solve(pl.dt_s / 64)
    res["reference_crosscheck_plant_dt_over_64"] = errors(y_fine)

    # plant at its default substep and finer ones (the default may be unstable, see stability)
    plant_rows = []
    for k in (1, 2, 4, 8):
        dtk = pl.dt_s / k
        t_k = timeit(lambda: plant_solve(dtk), None, reps)
        plant_rows.append({"dt_divisor": k, "dt_s": dtk,
                           "substeps": math.ceil((t1 - t0) / dtk - 1e-9), **stats(t_k),
                           "errors": errors(plant_solve(dtk)[0])})
    res["plant"] = {"dt_limited_by": pl.dt_limited_by, **plant_rows[0]}
    res["plant_dt_study"] = plant_rows
    res["stability_scan_lumped_default"] = stability_scan(rig)

    methods = ("RK45",) if quick else ("RK45", "LSODA", "Radau")
    rtols = ([1e-2, 1e-4, 1e-6, 1e-8] if quick
             else [10.0 ** (-k / 2) for k in range(4, 21)])  # 1e-2 .. 1e-10
    sweeps = {}
    for method in methods:
        rows = []
        for rtol in rtols:
            try:
                sol = ivp(method, rtol)  # warm-up (also compiles new rhs signatures)
            except Exception as exc:  # noqa: BLE001
                rows.append({"rtol": rtol, "error": repr(exc)})
                continue
            if not sol.success:
                rows.append({"rtol": rtol, "error": sol.message})
                continue
            t_once = time.perf_counter()
            ivp(method, rtol)
            t_once = time.perf_counter() - t_once
            r = reps if t_once < 0.2 else (3 if t_once < 2.0 else 1)
            t = timeit(lambda: ivp(method, rtol), None, r, warmup=0)
            rows.append({"rtol": rtol, **stats(t), "nfev": int(sol.nfev),
                         "njev": int(getattr(sol, "njev", 0) or 0),
                         "steps": int(sol.t.size - 1), "errors": errors(sol.y[:, -1])})
            if float(np.median(t)) > (5.0 if quick else 20.0):
                break
        sweeps[method] = {"rows": rows,
                          "equal_accuracy": [_equal_accuracy(rows, pr["errors"]["combined"], pr["median_s"])
                                             for pr in plant_rows]}
    res["solve_ivp"] = sweeps
    # per-call cost of the Python-wrapped RHS that solve_ivp sees
    yy = y0.copy()
    nc = 2000 if quick else 20000
    t_call = timeit(lambda: [fun(t0, yy) for _ in range(nc)], None, max(3, reps // 2))
    res["python_wrapped_rhs_us_per_call"] = float(np.median(t_call)) / nc * 1e6
    return res


def _equal_accuracy(rows, err_target, t_plant):
    """Wall time of a solve_ivp method at the plant's error: log-log interpolation between the
    two tolerances that bracket it; else the loosest tolerance that is at least as accurate."""
    ok = [r for r in rows if "errors" in r]
    if not ok:
        return None
    ok.sort(key=lambda r: -r["rtol"])  # loosest first
    out = {"target_error": err_target}
    better = [r for r in ok if r["errors"]["combined"] <= err_target]
    if better:
        lo = better[0]
        out["loosest_rtol_at_least_as_accurate"] = lo["rtol"]
        out["time_at_loosest_s"] = lo["median_s"]
        out["ratio_at_loosest"] = lo["median_s"] / t_plant
    interp = None
    for a, c in zip(ok, ok[1:]):
        ea, ec = a["errors"]["combined"], c["errors"]["combined"]
        if ea > err_target >= ec and ea > 0 and ec > 0:
            w = (math.log(err_target) - math.log(ea)) / (math.log(ec) - math.log(ea))
            interp = math.exp(math.log(a["median_s"]) + w * (math.log(c["median_s"]) - math.log(a["median_s"])))
            out["interpolated_rtol"] = math.exp(math.log(a["rtol"]) + w * (math.log(c["rtol"]) - math.log(a["rtol"])))
            break
    if interp is not None:
        out["time_at_equal_accuracy_s"] = interp
        out["ratio"] = interp / t_plant
        out["how"] = "log-log interpolation between bracketing rtols"
    elif better:
        out["time_at_equal_accuracy_s"] = out["time_at_loosest_s"]
        out["ratio"] = out["ratio_at_loosest"]
        out["how"] = ("every tested rtol is at least as accurate as the plant (solve_ivp is "
                      "stability-limited here): time at the loosest rtol")
    else:
        out["how"] = "no tested rtol reaches the plant's accuracy"
    return out


# ------------------------------------------------------------------------------------------
# d'. full strokes: the plant against an event-driven solve_ivp driver on the same kernels
# ------------------------------------------------------------------------------------------
#: cut-off command times: at 2.5 bar the lumped rig's piston then decelerates and creeps towards
#: the end (still moving at 3 s), at 1.5 bar it sticks mid-stroke (a stick event)
FS_CUT = {2.5: 0.6, 1.5: 0.5}


def _fs_cases(bar):
    """name -> (valve commands (time [s], value), t_end [s])"""
    tc = FS_CUT.get(bar, 0.6)
    return {"conventional": (((0.0, 1),), 2.0), f"cut@{tc}s": (((0.0, 1), (tc, 0)), 3.0)}
FS_EVENTS = ("breakaway", "stick", "v=0", "arrival", "x=0")


def _fs_plant(P, y0, d0, schedule, t_end, dt):
    """The plant's own stepper from reset with the commands (as ``Plant.run`` gives them:
    advance to the command time, command, go on), substep ``dt``."""
    Pp = P.copy()
    Pp[L.P_DT] = dt
    y, d = y0.copy(), d0.copy()
    for k, (tc, v) in enumerate(schedule):
        if tc > d[L.D_T]:
            st, _ = K.advance(y, Pp, d, tc, NOREC, 0.0, False)
            if st != L.STATUS_OK:
                raise RuntimeError(f"plant status {st}")
        K.command(d, Pp, float(v))
    st, _ = K.advance(y, Pp, d, t_end, NOREC, 0.0, False)
    if st != L.STATUS_OK:
        raise RuntimeError(f"plant status {st}")
    return y, d


def _fs_hybrid(P, y0, d0, schedule, t_end, method, rtol, atol):
    """Event-driven (hybrid) solution with ``solve_ivp``; physics only from the plant's kernels.

    Continuous part: ``K.rhs(t, y, P, d, mode, ...)`` with the discrete state ``d`` and the
    piston ``mode`` frozen over a segment. Segments end at the valve's breakpoints (a command
    given, a queued command coming due = ``d[D_Q0]``, the end of the spool ramp in force, the end
    of the exhaust-path ramp), where ``K.command`` / ``K._pop_due_commands`` update ``d`` exactly
    as the plant does (``valve_opening`` inside ``rhs`` then gives the opening of the ramp in
    force), and at the first terminal event of the piston's mode, located by solve_ivp:

    - START (x = 0): breakaway when ``f - Fs`` crosses 0 upwards (``_piston_events``:
      ``if f > fs: MODE_MOVING, D_MOVED = 1``);
    - STUCK: ``|f| - Fs`` crosses 0 upwards (``if abs(f) > fs: MODE_MOVING``);
    - END (x = stroke): ``-f - Fs`` crosses 0 upwards (``if f < -fs: MODE_MOVING``);
    - MOVING: arrival, ``x - stroke`` upwards (``if x >= stroke``: x = stroke, v = 0, MODE_END,
      D_T_ARRIVE the first time; the kernel interpolates it within its substep, here it is the
      located root); retracted stop, ``x`` downwards (``elif x <= 0.0``: x = v = 0, MODE_START);
      stick, ``max(|v| - V_STICK, |f| - Fs)`` downwards: the kernel's Karnopp check
      (``v_old * v <= 0 or abs(v) < V_STICK``, then ``if abs(f) <= fs``: v = 0, MODE_STUCK,
      D_STICKS += 1; a reversal passes through |v| < V_STICK first, so the band covers it);
      velocity reversal with |f| > Fs, ``sigma v`` downwards (``elif v_old * v <= 0.0: v = 0``,
      still moving; sigma = the direction of motion of the segment, from v or, at v = 0, from
      the acceleration, so a restart at v = 0 cannot re-fire it): the friction's sign flips
      there, so the segment ends to keep the RHS smooth.

    Differences from the kernel: events are located (the plant checks them at substep ends, so a
    breakaway or stick can come up to one substep late, which is part of its error);
    ``D_T_CLOSED`` and the sensor lag are not tracked (no metric uses them). Returns
    ``(y, d, info)``.
    """
    from scipy.integrate import solve_ivp

    n = int(P[L.P_NCELLS])
    b = 2 * n - 1
    ix, iv = b + L.Y_X, b + L.Y_V
    stroke, fs, A, ramp = P[L.P_STROKE], P[L.P_FS], P[L.P_AP], P[L.P_RAMP]
    y, d = y0.copy(), d0.copy()
    dy = np.empty_like(y)
    pbuf = np.empty(n)
    rhs, cp = K.rhs, K.chamber_pressures
    sched = sorted((float(tc), float(v)) for tc, v in schedule)
    t = float(d[L.D_T])
    info = {"segments": 0, "nfev": 0, "steps": 0, "events": {e: 0 for e in FS_EVENTS},
            "event_times": []}
    state = {"mode": int(d[L.D_MODE]), "sigma": 1.0}

    def fun(tau, yy):
        rhs(tau, yy, P, d, state["mode"], dy, pbuf)
        return dy.copy()

    def force(yy):
        pd, pe, _, _ = cp(yy, P, b)
        return (pd - pe) * A

    def ev(fn, direction):
        fn.terminal = True
        fn.direction = direction
        return fn

    ev_start = ev(lambda tau, yy: force(yy) - fs, 1.0)
    ev_stuck = ev(lambda tau, yy: abs(force(yy)) - fs, 1.0)
    ev_end = ev(lambda tau, yy: -force(yy) - fs, 1.0)
    ev_arrive = ev(lambda tau, yy: yy[ix] - stroke, 1.0)
    ev_x0 = ev(lambda tau, yy: yy[ix], -1.0)
    ev_stick = ev(lambda tau, yy: max(abs(yy[iv]) - K.V_STICK, abs(force(yy)) - fs), -1.0)
    ev_rev = ev(lambda tau, yy: state["sigma"] * yy[iv], -1.0)
    events_by_mode = {L.MODE_START: [(ev_start, "breakaway")], L.MODE_STUCK: [(ev_stuck, "breakaway")],
                      L.MODE_END: [(ev_end, "breakaway")],
                      L.MODE_MOVING: [(ev_arrive, "arrival"), (ev_x0, "x=0"), (ev_stick, "stick"),
                                      (ev_rev, "v=0")]}
    eps = 1e-12
    while t < t_end - eps:
        # valve: commands given now, queued commands due now (the kernels' own updates)
        d[L.D_T] = t
        for tc, v in sched:
            if abs(tc - t) <= eps:
                K.command(d, P, v)
        K._pop_due_commands(d, P, t + eps)
        bps = [t_end] + [tc for tc, _ in sched if tc > t + eps]
        if d[L.D_NQ] > 0:
            bps.append(d[L.D_Q0])
        t_ramp = d[L.D_T_S] + abs(d[L.D_TARGET] - d[L.D_S]) * ramp
        t_exh = d[L.D_T_EXH] + ramp
        bps += [tb for tb in (t_ramp, t_exh) if tb > t + eps]
        t_next = min(bps)
        mode = int(d[L.D_MODE])
        state["mode"] = mode
        if mode == L.MODE_MOVING:
            v = y[iv]
            if v == 0.0:
                rhs(t, y, P, d, mode, dy, pbuf)
                v = dy[iv]
            state["sigma"] = 1.0 if v >= 0.0 else -1.0
        evs = events_by_mode[mode]
        sol = solve_ivp(fun, (t, t_next), y, method=method, rtol=rtol, atol=atol,
                        events=[e for e, _ in evs])
        info["segments"] += 1
        info["nfev"] += int(sol.nfev)
        info["steps"] += int(sol.t.size - 1)
        if sol.status < 0:
            raise RuntimeError(f"solve_ivp {method} rtol={rtol} failed at t={t}: {sol.message}")
        if sol.status == 0:
            y = sol.y[:, -1].copy()
            t = t_next
            continue
        # the earliest terminal event
        k = min((i for i in range(len(evs)) if sol.t_events[i].size),
                key=lambda i: sol.t_events[i][0])
        t = float(sol.t_events[k][0])
        y = sol.y_events[k][0].copy()
        name = evs[k][1]
        info["events"][name] += 1
        info["event_times"].append((name, t))
        d[L.D_T] = t
        if mode != L.MODE_MOVING:  # _piston_events: a held piston keeps its exact position
            y[iv] = 0.0
            d[L.D_MODE] = L.MODE_MOVING
            if mode == L.MODE_START:
                d[L.D_MOVED] = 1.0
        elif name == "arrival":
            if d[L.D_T_ARRIVE] < 0.0:
                d[L.D_T_ARRIVE] = t
            y[ix], y[iv] = stroke, 0.0
            d[L.D_MODE] = L.MODE_END
        elif name == "x=0":
            y[ix], y[iv] = 0.0, 0.0
            d[L.D_MODE] = L.MODE_START
        elif name == "stick":
            y[iv] = 0.0
            d[L.D_MODE] = L.MODE_STUCK
            d[L.D_STICKS] += 1.0
        else:  # velocity reversal with |f| > Fs
            y[iv] = 0.0
    d[L.D_T] = t
    K._pop_due_commands(d, P, t)
    return y, d, info


def _fs_metrics(y, d, P):
    b = 2 * int(P[L.P_NCELLS]) - 1
    ta = float(d[L.D_T_ARRIVE])
    return {"arrival_time_s": ta if ta >= 0 else None, "energy_wasted_j": float(K.energy_wasted(y, P, d)),
            "position_m": float(y[b + L.Y_X]), "velocity_m_s": float(y[b + L.Y_V]), "mode": int(d[L.D_MODE]),
            "sticks": int(d[L.D_STICKS]), "air_mass_in_kg": float(y[b + L.Y_MIN]),
            "valve_closed": bool(K.valve_closed(d, P))}


def _fs_errors(m, ref):
    """Relative errors of stroke time, wasted energy, final position; combined = their max
    (air mass drawn reported, not combined)."""
    e = {}
    if ref["arrival_time_s"] is not None or m["arrival_time_s"] is not None:
        if ref["arrival_time_s"] is None or m["arrival_time_s"] is None:
            e["arrival_time"] = math.inf
        else:
            e["arrival_time"] = abs(m["arrival_time_s"] - ref["arrival_time_s"]) / ref["arrival_time_s"]
    e["energy_wasted"] = abs(m["energy_wasted_j"] - ref["energy_wasted_j"]) / abs(ref["energy_wasted_j"])
    e["position"] = abs(m["position_m"] - ref["position_m"]) / abs(ref["position_m"])
    e["combined"] = max(e.values())
    e["air_mass_in"] = abs(m["air_mass_in_kg"] - ref["air_mass_in_kg"]) / ref["air_mass_in_kg"]
    return e


def bench_fullstroke(reps, quick):
    """Whole strokes (events included): the plant's stepper against solve_ivp driven from event
    to event on the same jitted kernels, wall time at equal accuracy."""
    res = {"rig": "thesis_rig(p, line={'model': 'lumped'})", "cases": {},
           "error_definition": ("combined = max of the relative errors of the arrival time, the wasted energy "
                                "(K.energy_wasted at t_end) and the final position, against DOP853 rtol 1e-10 "
                                "through the same event-driven driver"),
           "driver": _fs_hybrid.__doc__}
    pressures = (2.5,) if quick else (2.5, 1.5)
    methods = ("RK45",) if quick else ("RK45", "LSODA", "Radau")
    rtols = [1e-3, 1e-5, 1e-7] if quick else [10.0 ** -k for k in range(2, 11)]
    for bar in pressures:
        rig = thesis_rig(bar, line={"model": "lumped"})
        pl = Plant(rig)
        P = pl.P.copy()
        y0, d0 = pl.initial_state()
        for cname, (schedule, t_end) in _fs_cases(bar).items():
            key = f"{bar}bar {cname}"
            print(f"   [fullstroke] {key}", file=sys.stderr, flush=True)
            # reference and its cross-check
            y_pl, d_pl = _fs_plant(P, y0, d0, schedule, t_end, pl.dt_s)
            scale = np.maximum(np.abs(y0), np.abs(y_pl))
            scale[scale == 0.0] = 1e-20
            t_r = time.perf_counter()
            y_r, d_r, info_r = _fs_hybrid(P, y0, d0, schedule, t_end, "DOP853", 1e-10, 1e-10 * scale)
            t_r = time.perf_counter() - t_r
            m_ref = _fs_metrics(y_r, d_r, P)
            cross = {}
            for k in (64, 256):
                yk, dk = _fs_plant(P, y0, d0, schedule, t_end, pl.dt_s / k)
                mk = _fs_metrics(yk, dk, P)
                cross[f"dt/{k}"] = {"metrics": mk, "errors": _fs_errors(mk, m_ref)}
            # plant at dt, dt/2, dt/4, timed round-robin (before and after the sweep)
            divs = (1, 2, 4)
            cases = [(k, (lambda k=k: _fs_plant(P, y0, d0, schedule, t_end, pl.dt_s / k)), lambda: None)
                     for k in divs]
            t_pl = interleaved(cases, reps)
            plant_rows = []
            for k in divs:
                yk, dk = _fs_plant(P, y0, d0, schedule, t_end, pl.dt_s / k)
                mk = _fs_metrics(yk, dk, P)
                plant_rows.append({"dt_divisor": k, "dt_s": pl.dt_s / k, "metrics": mk,
                                   "errors": _fs_errors(mk, m_ref)})
            sweeps = {}
            for method in methods:
                rows = []
                for rtol in rtols:
                    atol = rtol * scale
                    try:
                        t_once = time.perf_counter()
                        ys, ds, info = _fs_hybrid(P, y0, d0, schedule, t_end, method, rtol, atol)
                        t_once = time.perf_counter() - t_once
                    except Exception as exc:  # noqa: BLE001
                        rows.append({"rtol": rtol, "error": repr(exc)})
                        continue
                    r = 1 if t_once > 1.0 else (3 if t_once > 0.1 else max(3, reps // 2))
                    t = timeit(lambda: _fs_hybrid(P, y0, d0, schedule, t_end, method, rtol, atol), None,
                               r, warmup=0)
                    mm = _fs_metrics(ys, ds, P)
                    rows.append({"rtol": rtol, **stats(t), "nfev": info["nfev"], "steps": info["steps"],
                                 "segments": info["segments"], "events": info["events"],
                                 "metrics": mm, "errors": _fs_errors(mm, m_ref)})
                    if float(np.median(t)) > (5.0 if quick else 15.0):
                        break
                sweeps[method] = {"rows": rows}
            t_pl2 = interleaved(cases, reps)
            for pr in plant_rows:
                pr.update(stats(t_pl[pr["dt_divisor"]] + t_pl2[pr["dt_divisor"]]))
                pr["substeps_approx"] = math.ceil(t_end / pr["dt_s"])
            for method, s in sweeps.items():
                s["equal_accuracy"] = [_equal_accuracy(s["rows"], pr["errors"]["combined"], pr["median_s"])
                                       for pr in plant_rows]
            res["cases"][key] = {
                "supply_bar_gauge": bar, "schedule": [list(c) for c in schedule], "t_end_s": t_end,
                "plant_dt_s": pl.dt_s, "dt_limited_by": pl.dt_limited_by, "n_cells": pl.n_cells,
                "reference": {"method": "DOP853", "rtol": 1e-10, "atol": "1e-10 x component scale",
                              "wall_s": t_r, "metrics": m_ref, "nfev": info_r["nfev"],
                              "steps": info_r["steps"], "segments": info_r["segments"],
                              "events": info_r["events"], "event_times": info_r["event_times"]},
                "reference_crosscheck_plant": cross,
                "plant_events": {"sticks": int(d_pl[L.D_STICKS]), "moved": bool(d_pl[L.D_MOVED])},
                "plant": plant_rows, "solve_ivp": sweeps}
    return res


# ------------------------------------------------------------------------------------------
# e. profile
# ------------------------------------------------------------------------------------------
@njit(cache=False)
def _loop_rhs(y, P, d, mode, dy, p, n_calls):
    acc = 0.0
    t = d[L.D_T]
    for i in range(n_calls):
        y[0] += 1e-30 * acc  # data dependence so that nothing is hoisted
        acc += K.rhs(t, y, P, d, mode, dy, p)
    return acc


@njit(cache=False)
def _loop_substep(y, P, d, h, n_calls):
    ny = y.shape[0]
    n = int(P[L.P_NCELLS])
    k = np.empty(ny)
    y1 = np.empty(ny)
    y2 = np.empty(ny)
    p = np.empty(n)
    for i in range(n_calls):
        K.substep(y, P, d, h, k, y1, y2, p)
    return y[0]


@njit(cache=False)
def _loop_mass_flow(pa, pb, cda, sT, oc, n_calls):
    acc = 0.0
    for i in range(n_calls):
        acc += mass_flow(pa + 1e-9 * i, pb, cda, sT, sT, oc)
    return acc




def bench_profile(reps, quick):
    res = {}
    nc = 200_000 if quick else 2_000_000
    for label, rig in (("fd_default", thesis_rig(2.5)),
                       ("lumped", thesis_rig(2.5, line={"model": "lumped"}))):
        pl = Plant(rig)
        pl.reset()
        pl.advance(0.6, 1)  # moving, valve open, mid-stroke
        y, d = pl.snapshot()
        dy = np.empty_like(y)
        p = np.empty(pl.n_cells)
        yy = y.copy()
        _loop_rhs(yy, pl.P, d, 0, dy, p, 10)
        t_rhs = timeit(lambda: _loop_rhs(yy, pl.P, d, 0, dy, p, nc), None, max(3, reps // 2))
        ns_rhs = float(np.median(t_rhs)) / nc * 1e9
        nsub = nc // 10
        h = pl.dt_s

        def setup_sub():
            ys[:], ds[:] = y, d

        ys, ds = y.copy(), d.copy()
        _loop_substep(ys, pl.P, ds, h, 10)
        t_sub = timeit(lambda: _loop_substep(ys, pl.P, ds, h, nsub), setup_sub, max(3, reps // 2))
        ns_sub = float(np.median(t_sub)) / nsub * 1e9
        res[label] = {"n_cells": pl.n_cells, "dt_s": pl.dt_s, "dt_limited_by": pl.dt_limited_by,
                      "ns_per_rhs_call": ns_rhs, "ns_per_substep": ns_sub,
                      "substep_over_3_rhs": ns_sub / (3 * ns_rhs),
                      "substeps_per_simulated_s": 1.0 / pl.dt_s,
                      "rtf_bound_from_substep_cost": 1.0 / (ns_sub * 1e-9 / pl.dt_s),
                      "stability_limits_s": dict(sorted(stability_limits(rig).items(),
                                                        key=lambda kv: kv[1]))}
    P = Plant(thesis_rig(2.5)).P
    oc = P[L.P_OC:L.P_OC + NOC].copy()
    _loop_mass_flow(3.0e5, 2.5e5, 1e-5, 17.0, oc, 10)
    t_mf = timeit(lambda: _loop_mass_flow(3.0e5, 2.5e5, 1e-5, 17.0, oc, nc), None, max(3, reps // 2))
    res["ns_per_mass_flow_subsonic"] = float(np.median(t_mf)) / nc * 1e9
    _loop_mass_flow(3.0e5, 1.0e5, 1e-5, 17.0, oc, 10)
    t_mf = timeit(lambda: _loop_mass_flow(3.0e5, 1.0e5, 1e-5, 17.0, oc, nc), None, max(3, reps // 2))
    res["ns_per_mass_flow_choked"] = float(np.median(t_mf)) / nc * 1e9
    return res


# ------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------
def _ratio_cell(ea):
    """A table cell for an :func:`_equal_accuracy` result: the ratio, ``(<=)`` when it is taken at
    the loosest rtol (every tested one more accurate), ``n/a`` when none is as accurate."""
    ratio = (ea or {}).get("ratio")
    if ratio is None:
        return "n/a"
    return g(ratio, 4) + ("" if ea.get("how", "").startswith("log-log") else " (<=)")


def report(R):
    out = []
    if "rtf" in R:
        a = R["rtf"]
        rows = []
        for k, e in a.items():
            rows.append([k, g(e["dt_s"] * 1e6, 4), e["dt_limited_by"], e["substeps_advance"],
                         g(e["advance"]["median_s"] * 1e3, 4), g(e["rtf_advance"], 4),
                         g(e["rtf_run_record_1ms"], 4), g(e["rtf_control_loop_5ms"], 4),
                         g(e["ns_per_substep_advance"], 4), g(e["us_per_advance_5ms_call"], 3),
                         g(e["cpu_time"]["rtf_advance"], 4), g(e["cpu_time"]["us_per_advance_5ms_call"], 3),
                         g(e["arrival_time_s"], 6)])
        out.append(fmt_table(["supply", "dt[us]", "dt limited by", "substeps", "advance 2s [ms]",
                              "RTF advance", "RTF run(rec 1ms)", "RTF 5ms-loop", "ns/substep",
                              "us / advance(5ms)", "RTF advance (CPU)", "us / advance(5ms) (CPU)",
                              "arrival [s]"], rows,
                             f"a. Real-time factor, one plant, default configuration "
                             f"(goal RTF >= {GOAL_RTF:.0f}); medians of {a['2.5bar']['advance']['n']} repeats; (CPU): "
                             "this thread's CPU time, which does not count waiting for a core on a busy machine"))
        inproc = {k: e["first_call_in_process_s"] for k, e in a.items()}
        out.append("   first call in this process (cache load): "
                   + ", ".join(f"{k}: {v:.3f} s" for k, v in inproc.items()))

    fc = R.get("first_call", {})
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

    if "accuracy" in R:
        acc = R["accuracy"]
        rows = []
        for k, e in acc["by_pressure"].items():
            for label, m, er in (
                    ("default vs ref(4x)", e["default"], e["errors_default_vs_reference"]),
                    ("ref(4x) vs ref(8x)", e["reference"], e["errors_reference_vs_reference8"]),
                    ("default vs extrapolated", e["default"], e["errors_default_vs_extrapolated"]),
                    ("ref(4x) vs extrapolated", e["reference"], e["errors_reference_vs_extrapolated"])):
                rows.append([k, label, g(m["arrival_time_s"], 6), pct(er["stroke_time_pct"]),
                             pct(er["energy_conventional_pct"]), pct(er["energy_endcut_pct"]),
                             pct(er["energy_midcut_pct"]), pct(er["energy_latecut_pct"]),
                             pct(er["latecut_arrival_pct"]), g(er["max_abs_pct"], 3)])
        out.append(fmt_table(["supply", "comparison", "stroke [s]", "stroke err", "E conv err", "E end-cut err",
                              f"E cut@{T_CUT_MID}s err", "E late-cut err", "late-cut arrival err", "max|err|%"],
                             rows, f"b. Accuracy against the converged reference (goal |err| <= {GOAL_ERR_PCT} %)"))
        lines = [f"   E conv = closed form (driving side filled to supply at full stroke), identical for every "
                 f"grid; E end-cut: run({T_END_ACC}, cut_on_arrival=True); E cut@{T_CUT_MID}s: cut commanded at "
                 f"{T_CUT_MID} s (piston stops mid-stroke); E late-cut: cut commanded at "
                 + ", ".join(f"{v} s ({k} bar)" for k, v in T_CUT_LATE.items())
                 + f" (piston still arrives); energies read at t = {T_END_ACC} s with the valve closed.",
                 "   extrapolated = Richardson extrapolation n_cells -> inf from the 4x and 8x levels with the "
                 "order observed from the 1x/4x/8x levels (h ~ 1/n_cells, dt ~ h)"]
        for k, e in acc["by_pressure"].items():
            ri, r8 = e["reference_grid"], e["reference8_grid"]
            lines.append(f"   {k}: ref(4x) n_cells={ri['n_cells']} dt={ri['dt_s']:.4g}s ({ri['note']}; "
                         f"stability limit {ri['stability_limit_s']:.4g}s); ref(8x) n_cells={r8['n_cells']} "
                         f"dt={r8['dt_s']:.4g}s ({r8['note']}); observed orders: " + ", ".join(
                             f"{q} {g(p, 3)}" for q, p in e["observed_order_in_1_over_n_cells"].items()
                             if q in GOAL_QUANTITIES))
            for lab, m in (("default", e["default"]), ("ref(4x)", e["reference"])):
                ec, mc, lc = m["endcut"], m["midcut"], m["latecut"]
                lines.append(f"     {lab}: E conv={m['energy_conventional_j']:.2f}J  end-cut E={ec['energy_wasted_j']:.2f}J "
                             f"(closed {ec['valve_closed']}, stopped {ec['piston_stopped']})  cut@{T_CUT_MID}s "
                             f"E={mc['energy_wasted_j']:.3f}J (closed {mc['valve_closed']}, v={mc['velocity_m_s']:.2g} m/s, "
                             f"x={mc['position_m']:.4f} m)  late-cut E={lc['energy_wasted_j']:.2f}J (closed "
                             f"{lc['valve_closed']}, stopped {lc['piston_stopped']}, arrival {g(lc['arrival_time_s'], 5)} s)")
            s = e["stability_scan_default"]
            lines.append(f"     IMEX stability scan of the default (states every 10 ms, conventional): max rho(R(dt J)) "
                         f"= {s['max_amp']:.4g} ({'stable' if s['stable'] else 'UNSTABLE'}); largest stable dt "
                         f"{s['dt_max_stable_s'] * 1e6:.4g} us = {1 / s['dt_over_dt_max_stable']:.3g} x dt")
        out.append("\n".join(lines))

        rows = []
        for r in acc["tradeoff"]:
            s = r["stability_scan_2.5bar"]
            for bar in ("2.5bar", "1.5bar"):
                er = r[bar]["errors"]
                ex = r[bar]["errors_vs_extrapolated"]
                ok = r["rtf_2.5bar"] >= GOAL_RTF and er["max_abs_pct"] is not None and er["max_abs_pct"] <= GOAL_ERR_PCT
                first = bar == "2.5bar"
                rows.append([r["n_cells"], g(r["linear_ratio"]), g(r["dt_s"] * 1e6, 4) if first else "",
                             r["dt_limited_by"].replace("orifice port: line cell -> driving chamber", "port orifice")
                             if first else "",
                             g(r["rtf_2.5bar"], 4) if first else "",
                             (f"{s['max_amp']:.3g}" + ("" if s["stable"] else " !")) if first else "", bar,
                             pct(er["stroke_time_pct"], 2), pct(er["energy_endcut_pct"], 2),
                             pct(er["energy_midcut_pct"], 2), pct(er["energy_latecut_pct"], 2),
                             g(er["max_abs_pct"], 3), g(ex["max_abs_pct"], 3), "yes" if ok else "no"])
        out.append(fmt_table(["n_cells", "lin_ratio", "dt[us]", "dt limited by", "RTF", "max|R|", "supply",
                              "stroke err", "E end-cut", "E cut@0.45", "E late-cut", "max|err| ref4x",
                              "max|err| extrap", "goals met"], rows,
                             f"b'. RTF / accuracy trade-off (errors vs the default-model ref(4x) above, linear_ratio "
                             f"{acc['default_linear_ratio']}; RTF = "
                             "advance(2 s) at 2.5 bar, same process; max|R| = IMEX amplification scan, ! = unstable)"))
        lm = acc["linear_ratio_model_change"]
        out.append(f"   model change alone, other linear_ratio vs the default {acc['default_linear_ratio']}, both at "
                   "ref(4x) resolution: " + "; ".join(
                       f"lin {v['linear_ratio']} {k.split('@')[1]}: "
                       f"stroke {pct(v['errors_vs_default_reference']['stroke_time_pct'], 2)}, "
                       f"E end-cut {pct(v['errors_vs_default_reference']['energy_endcut_pct'], 2)}, "
                       f"E cut@0.45 {pct(v['errors_vs_default_reference']['energy_midcut_pct'], 2)}, "
                       f"E late-cut {pct(v['errors_vs_default_reference']['energy_latecut_pct'], 2)}"
                       for k, v in lm.items()))

    if "batch" in R:
        bt = R["batch"]
        sp = bt["single_plant_control_loop"]
        rows = [["single Plant, 5 ms loop", "1", "-", g(sp["median_s"] * 1e3, 4), g(sp["plant_s_per_wall_s"], 4),
                 g(sp["plant_steps_per_s"] / 1e3, 4), g(sp["us_per_advance_5ms_call"], 3), "-", "-", "-"]]
        for B, e in bt["sizes"].items():
            for key in ("1_threads", "2_threads"):
                if key not in e:
                    continue
                rows.append([f"PlantBatch B={B}", B, key.split("_")[0], g(e[key]["median_s"] * 1e3, 4),
                             g(e[key]["plant_s_per_wall_s"], 4), g(e[key]["plant_steps_per_s"] / 1e3, 4),
                             g(1e6 / e[key]["plant_steps_per_s"], 3),
                             g(e.get("speedup_2_over_1"), 3) if key == "2_threads" else "",
                             g(e.get("speedup_2_over_1_min_times"), 3) if key == "2_threads" else "",
                             g(e["max_abs_diff_vs_single_plant"], 3) if key == "1_threads" else ""])
        out.append(fmt_table(["case", "B", "threads", "wall [ms]", "plant-s / wall-s", "plant-steps/s [k]",
                              "us / plant-step", "speed-up 2/1",
                              "speed-up 2/1 (min times)", "max|Y-Y_single|"], rows,
                             f"c. Batched kernel: 1.5 s simulated in 5 ms control periods "
                             f"(threading layer {bt.get('threading_layer')}); a plant-step = one 5 ms "
                             f"period of one plant (Plant.advance(0.005, 1) / PlantBatch.advance(cmds, 0.005))"))

    if "scipy" in R:
        sc = R["scipy"]
        pe = sc["plant"]
        ss = sc["stability_scan_lumped_default"]
        lines = [f"d. solve_ivp vs the plant's stepper on the same jitted rhs ({sc['rig']}); window "
                 f"t = {sc['window_s'][0]:.3f} .. {sc['window_s'][1]:.3f} s (checks: all ok)",
                 f"   error: {sc['error_definition']}; reference DOP853 rtol=1e-12 "
                 f"(cross-check: plant with dt/64 differs by {sc['reference_crosscheck_plant_dt_over_64']['combined']:.2e})",
                 f"   plant default dt = {pe['dt_s'] * 1e6:.4g} us ({pe['dt_limited_by']}); IMEX stability scan of this "
                 f"configuration: max |R(dt*lambda)| = {ss['max_amp']:.4g} ({'stable' if ss['stable'] else 'UNSTABLE'}), "
                 f"largest stable dt {ss['dt_max_stable_s'] * 1e6:.4g} us = {1 / ss['dt_over_dt_max_stable']:.3g} x dt",
                 f"   Python-wrapped rhs as solve_ivp calls it: {sc['python_wrapped_rhs_us_per_call']:.3g} us/call"]
        out.append("\n".join(lines))
        rows = []
        for m, s in sc["solve_ivp"].items():
            for r in s["rows"]:
                if "errors" not in r:
                    rows.append([m, g(r["rtol"], 3), "failed", "", "", "", ""])
                    continue
                rows.append([m, g(r["rtol"], 3), g(r["median_s"] * 1e3, 4), r["steps"], r["nfev"],
                             g(r["errors"]["combined"], 3), g(r["median_s"] / pe["median_s"], 4)])
        out.append(fmt_table(["method", "rtol", "wall [ms]", "steps", "nfev", "error", "wall / plant(dt)"], rows,
                             "   solve_ivp sweep"))
        rows = []
        for i, prow in enumerate(sc["plant_dt_study"]):
            row = [f"dt/{prow['dt_divisor']}", g(prow["dt_s"] * 1e6, 4), prow["substeps"],
                   g(prow["median_s"] * 1e3, 4), g(prow["errors"]["combined"], 3)]
            row += [_ratio_cell(s["equal_accuracy"][i]) for s in sc["solve_ivp"].values()]
            rows.append(row)
        out.append(fmt_table(["plant", "dt[us]", "substeps", "wall [ms]", "error"]
                             + [f"{m} time ratio @ equal err" for m in sc["solve_ivp"]], rows,
                             f"   wall time of solve_ivp at the plant's error / plant's wall time (goal >= "
                             f"{GOAL_SCIPY_RATIO:.0f}); (<=): every tested rtol is more accurate, ratio at the loosest; "
                             f"n/a: no tested rtol is as accurate"))

    if "fullstroke" in R:
        fs = R["fullstroke"]
        out.append("d'. Full strokes: the plant's stepper against solve_ivp driven from event to event on the same "
                   f"kernels ({fs['rig']})\n   error: {fs['error_definition']}")
        for key, c in fs["cases"].items():
            ref = c["reference"]
            mr = ref["metrics"]
            cr = c["reference_crosscheck_plant"]
            lines = [f"   {key}: commands {c['schedule']}, t_end {c['t_end_s']} s; reference: arrival "
                     f"{g(mr['arrival_time_s'], 7)} s, E wasted {mr['energy_wasted_j']:.5g} J, x_end "
                     f"{mr['position_m']:.6g} m, mode {mr['mode']}, sticks {mr['sticks']}; {ref['segments']} segments, "
                     f"events {ref['events']}, {ref['nfev']} rhs calls, {ref['wall_s']:.3g} s",
                     "     event times (reference): " + ", ".join(f"{n} {t:.6g}" for n, t in ref["event_times"]),
                     "     cross-check, plant vs reference: " + ", ".join(
                         f"{k} combined {v['errors']['combined']:.2e} (arrival {g(v['errors'].get('arrival_time'), 3)}, "
                         f"E {v['errors']['energy_wasted']:.2e}, x {v['errors']['position']:.2e})" for k, v in cr.items())]
            out.append("\n".join(lines))
            rows = []
            for m, s in c["solve_ivp"].items():
                for r in s["rows"]:
                    if "errors" not in r:
                        rows.append([m, g(r["rtol"], 3), "failed", "", "", "", "", "", ""])
                        continue
                    ev = ", ".join(f"{k}:{v}" for k, v in r["events"].items() if v)
                    rows.append([m, g(r["rtol"], 3), g(r["median_s"] * 1e3, 4), r["steps"], r["nfev"],
                                 r["segments"], ev, g(r["errors"]["combined"], 3),
                                 g(r["median_s"] / c["plant"][0]["median_s"], 4)])
            out.append(fmt_table(["method", "rtol", "wall [ms]", "steps", "nfev", "segments", "events",
                                  "error", "wall / plant(dt)"], rows, f"   {key}: solve_ivp sweep"))
            rows = []
            for i, prow in enumerate(c["plant"]):
                e = prow["errors"]
                row = [f"dt/{prow['dt_divisor']}", g(prow["dt_s"] * 1e6, 4), prow["substeps_approx"],
                       g(prow["median_s"] * 1e3, 4), g(e.get("arrival_time"), 3), g(e["energy_wasted"], 3),
                       g(e["position"], 3), g(e["combined"], 3)]
                row += [_ratio_cell(s["equal_accuracy"][i]) for s in c["solve_ivp"].values()]
                rows.append(row)
            out.append(fmt_table(["plant", "dt[us]", "substeps", "wall [ms]", "err arrival", "err E", "err x",
                                  "error"] + [f"{m} ratio @ equal err" for m in c["solve_ivp"]], rows,
                                 f"   {key}: solve_ivp wall time at the plant's error / plant's wall time "
                                 "((<=): every tested rtol is more accurate, ratio at the loosest; n/a: none as accurate)"))

    if "profile" in R:
        pr = R["profile"]
        rows = []
        for k in ("fd_default", "lumped"):
            e = pr[k]
            rows.append([k, e["n_cells"], g(e["dt_s"] * 1e6, 4), e["dt_limited_by"], g(e["ns_per_rhs_call"], 4),
                         g(e["ns_per_substep"], 4), g(e["substep_over_3_rhs"], 3),
                         g(e["substeps_per_simulated_s"], 5), g(e["rtf_bound_from_substep_cost"], 4)])
        out.append(fmt_table(["config", "n_cells", "dt[us]", "dt limited by", "ns/rhs", "ns/substep",
                              "substep/(3 rhs)", "substeps per sim-s", "RTF bound"], rows,
                             f"e. Profile (jitted loops): mass_flow {pr['ns_per_mass_flow_subsonic']:.3g} ns "
                             f"subsonic, {pr['ns_per_mass_flow_choked']:.3g} ns choked"))
        lim = pr["fd_default"]["stability_limits_s"]
        out.append("   stability limits, default (before safety 0.9): " + ", ".join(
            f"{k} {v * 1e6:.4g} us" for k, v in lim.items()))

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
             ("accuracy", lambda: bench_accuracy(reps, args.quick)),
             ("batch", lambda: bench_batch(reps, args.quick)),
             ("scipy", lambda: bench_scipy(reps, args.quick)),
             ("fullstroke", lambda: bench_fullstroke(reps, args.quick)),
             ("profile", lambda: bench_profile(reps, args.quick))]
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
        json.dump(R, fh, indent=1, default=_json_default)
    print(f"wrote {out / 'plant.json'}")


def _json_default(o):
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


if __name__ == "__main__":
    main()
