"""Section d (``scipy``) of ``bench_plant.py``: the plant's own stepper against
``scipy.integrate.solve_ivp`` on the same jitted right-hand side (lumped line, a smooth window
between breakaway and arrival), wall time at equal accuracy. Also the helpers that section d'
(``bench_fullstroke.py``) shares: the equal-accuracy interpolation and its table cell. See
``benchmarks/README.md``.

    python benchmarks/bench_solve_ivp.py [--quick] [--out DIR]   # = bench_plant.py --only scipy
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from common import GOAL_SCIPY_RATIO, fmt_table, g, stats, timeit
from imex_stability import stability_scan
from pneugym import Plant, thesis_rig
from pneugym.physics import layout as L
from pneugym.physics import system as K

NOREC = np.zeros((0, L.NR))
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
                          "equal_accuracy": [equal_accuracy(rows, pr["errors"]["combined"], pr["median_s"])
                                             for pr in plant_rows]}
    res["solve_ivp"] = sweeps
    # per-call cost of the Python-wrapped RHS that solve_ivp sees
    yy = y0.copy()
    nc = 2000 if quick else 20000
    t_call = timeit(lambda: [fun(t0, yy) for _ in range(nc)], None, max(3, reps // 2))
    res["python_wrapped_rhs_us_per_call"] = float(np.median(t_call)) / nc * 1e6
    return res


def equal_accuracy(rows, err_target, t_plant):
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


def ratio_cell(ea):
    """A table cell for an :func:`equal_accuracy` result: the ratio, ``(<=)`` when it is taken at
    the loosest rtol (every tested one more accurate), ``n/a`` when none is as accurate."""
    ratio = (ea or {}).get("ratio")
    if ratio is None:
        return "n/a"
    return g(ratio, 4) + ("" if ea.get("how", "").startswith("log-log") else " (<=)")


def report_scipy(sc):
    """Text blocks of section d (scipy) for the report."""
    out = []
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
        row += [ratio_cell(s["equal_accuracy"][i]) for s in sc["solve_ivp"].values()]
        rows.append(row)
    out.append(fmt_table(["plant", "dt[us]", "substeps", "wall [ms]", "error"]
                         + [f"{m} time ratio @ equal err" for m in sc["solve_ivp"]], rows,
                         f"   wall time of solve_ivp at the plant's error / plant's wall time (goal >= "
                         f"{GOAL_SCIPY_RATIO:.0f}); (<=): every tested rtol is more accurate, ratio at the loosest; "
                         f"n/a: no tested rtol is as accurate"))
    return out


if __name__ == "__main__":
    import bench_plant

    bench_plant.main(["--only", "scipy", *sys.argv[1:]])
