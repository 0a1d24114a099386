"""Section b (``accuracy``) of ``bench_plant.py``: the default discretisation against a converged
reference (4x line cells, dt/4), a Richardson-extrapolated limit from the 1x/4x/8x levels, the
IMEX stability scan, and the RTF / accuracy trade-off of other line grids and orifice linear
zones (b'). See ``benchmarks/README.md``.

    python benchmarks/bench_accuracy.py [--quick] [--out DIR]   # = bench_plant.py --only accuracy
"""
from __future__ import annotations

import sys

from common import GOAL_ERR_PCT, GOAL_RTF, fmt_table, g, interleaved, pct, rel_pct, stats
from imex_stability import stability_scan
from pneugym import Plant, thesis_rig
from pneugym.physics import layout as L
from pneugym.plant import choose_dt, stability_limits

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


def stroke_metrics(rig, record_dt=1e-3):
    """Stroke time and wasted energies of one configuration: conventional (closed form),
    end-stroke cut-off, early mid-stroke cut-off (``T_CUT_MID``, piston stops mid-stroke) and a
    later cut-off (``T_CUT_LATE``, valve closed mid-stroke, the piston still arrives). The cut
    runs record every ``record_dt`` [s], which shortens substeps longer than it."""
    bar = round(rig.supply_pressure_gauge_pa / 1e5, 3)
    pl = Plant(rig)
    out = {"dt_s": pl.dt_s, "dt_limited_by": pl.dt_limited_by, "n_cells": pl.n_cells}
    pl.reset()
    pl.advance(T_END_ACC, 1)
    out["arrival_time_s"] = pl.arrival_time_s
    out["energy_conventional_j"] = pl.energy_wasted_j  # closed form (filled to supply, x = stroke)

    pl.reset()
    pl.run(T_END_ACC, cut_on_arrival=True, record_dt=record_dt)
    out["endcut"] = _after_cut(pl)

    pl.reset()
    pl.run(T_END_ACC, schedule=[(0.0, 1), (T_CUT_MID, 0)], record_dt=record_dt)
    out["midcut"] = _after_cut(pl)

    t_late = T_CUT_LATE.get(bar, 1.2)
    pl.reset()
    pl.run(T_END_ACC, schedule=[(0.0, 1), (t_late, 0)], record_dt=record_dt)
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
        # the FD line solved implicitly, at its own substep (recorded every 50 ms: a 1 ms grid
        # would shorten its 5 ms substeps)
        m_imp = stroke_metrics(rig.with_(solver={"line_scheme": "implicit"}), record_dt=0.05)
        entry["implicit_line"] = m_imp
        entry["errors_implicit_line_vs_reference"] = compare(m_imp, m_ref)
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
# report
# ------------------------------------------------------------------------------------------
def report_accuracy(acc):
    """Text blocks of section b (accuracy) and b' (trade-off) for the report."""
    out = []
    rows = []
    for k, e in acc["by_pressure"].items():
        for label, m, er in (
                ("default vs ref(4x)", e["default"], e["errors_default_vs_reference"]),
                ("ref(4x) vs ref(8x)", e["reference"], e["errors_reference_vs_reference8"]),
                ("default vs extrapolated", e["default"], e["errors_default_vs_extrapolated"]),
                ("ref(4x) vs extrapolated", e["reference"], e["errors_reference_vs_extrapolated"]),
                ("implicit line vs ref(4x)", e["implicit_line"],
                 e["errors_implicit_line_vs_reference"])):
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
    return out


if __name__ == "__main__":
    import bench_plant

    bench_plant.main(["--only", "accuracy", *sys.argv[1:]])
