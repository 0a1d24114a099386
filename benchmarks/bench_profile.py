"""Section e (``profile``) of ``bench_plant.py``: jitted loops time one ``rhs`` call, one IMEX
``substep`` and one orifice ``mass_flow`` call; the RTF bound ``dt / (time per substep)`` and the
stability limits of the default configuration. See ``benchmarks/README.md``.

    python benchmarks/bench_profile.py [--quick] [--out DIR]   # = bench_plant.py --only profile
"""
from __future__ import annotations

import sys

import numpy as np
from numba import njit

from common import fmt_table, g, timeit
from pneugym import Plant, thesis_rig
from pneugym.physics import layout as L
from pneugym.physics import system as K
from pneugym.physics.orifice import NOC, mass_flow
from pneugym.plant import stability_limits


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


def report_profile(pr):
    """Text block of section e (profile) for the report."""
    out = []
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
    return out


if __name__ == "__main__":
    import bench_plant

    bench_plant.main(["--only", "profile", *sys.argv[1:]])
