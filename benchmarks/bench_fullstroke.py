"""Section d' (``fullstroke``) of ``bench_plant.py``: whole strokes (valve commands, breakaway,
stick-slip, end stop) of the plant's stepper against ``solve_ivp`` driven from event to event by
a hybrid driver that uses only the plant's kernels (``_fs_hybrid``), wall time at equal
accuracy. See ``benchmarks/README.md``.

    python benchmarks/bench_fullstroke.py [--quick] [--out DIR]   # = bench_plant.py --only fullstroke
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from bench_solve_ivp import NOREC, equal_accuracy, ratio_cell
from common import fmt_table, g, interleaved, stats, timeit
from pneugym import Plant, thesis_rig
from pneugym.physics import layout as L
from pneugym.physics import system as K

#: cut-off command times: at 2.5 bar the lumped rig's piston then decelerates and creeps towards
#: the end (still moving at 3 s), at 1.5 bar it sticks mid-stroke (a stick event)
FS_CUT = {2.5: 0.6, 1.5: 0.5}
FS_EVENTS = ("breakaway", "stick", "v=0", "arrival", "x=0")


def _fs_cases(bar):
    """name -> (valve commands (time [s], value), t_end [s])"""
    tc = FS_CUT.get(bar, 0.6)
    return {"conventional": (((0.0, 1),), 2.0), f"cut@{tc}s": (((0.0, 1), (tc, 0)), 3.0)}


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
    of the exhaust-path ramp), where ``K.command`` / ``K.pop_due_commands`` update ``d`` exactly
    as the plant does (``valve_opening`` inside ``rhs`` then gives the opening of the ramp in
    force), and at the first terminal event of the piston's mode, located by solve_ivp:

    - START (x = 0): breakaway when ``f - Fs`` crosses 0 upwards (``K.piston_events``:
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
        K.pop_due_commands(d, P, t + eps)
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
        if mode != L.MODE_MOVING:  # K.piston_events: a held piston keeps its exact position
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
    K.pop_due_commands(d, P, t)
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
                s["equal_accuracy"] = [equal_accuracy(s["rows"], pr["errors"]["combined"], pr["median_s"])
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


def report_fullstroke(fs):
    """Text blocks of section d' (fullstroke) for the report."""
    out = []
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
            row += [ratio_cell(s["equal_accuracy"][i]) for s in c["solve_ivp"].values()]
            rows.append(row)
        out.append(fmt_table(["plant", "dt[us]", "substeps", "wall [ms]", "err arrival", "err E", "err x",
                              "error"] + [f"{m} ratio @ equal err" for m in c["solve_ivp"]], rows,
                             f"   {key}: solve_ivp wall time at the plant's error / plant's wall time "
                             "((<=): every tested rtol is more accurate, ratio at the loosest; n/a: none as accurate)"))
    return out


if __name__ == "__main__":
    import bench_plant

    bench_plant.main(["--only", "fullstroke", *sys.argv[1:]])
