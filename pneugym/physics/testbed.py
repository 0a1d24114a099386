"""The supply line alone, between simple boundaries: the rig for the analytic checks
(choked charging, isothermal discharge, acoustic modes, laminar pressure drop, convergence order)
and for the thesis's line experiment (4.10). It steps the same kernels as the plant
(:func:`line.fd_rhs`, :func:`line.lumped_rhs`, :func:`orifice.mass_flow`) with SSP-RK3.

Boundary array ``bc`` (length 6): ``[kind_l, value_l, cda_l, kind_r, value_r, cda_r]`` with kind
0 = closed, 1 = prescribed mass flow ``value`` [kg/s] (into the line on the left, out on the
right), 2 = orifice of effective area ``cda`` [m²] to a reservoir at pressure ``value`` [Pa].
State ``y``: ``n`` cell masses then ``n - 1`` interior face flows (as in the plant).
"""
import numpy as np
from numba import njit

from .layout import NP, P_AV, P_DX, P_CDA_LINE, P_LINE_A, P_LINE_D, P_LINE_MODEL, P_MU, P_NCELLS, P_OC, P_R, P_SQRT_T, P_T
from .line import fd_rhs, lumped_rhs
from .orifice import NOC, mass_flow


@njit(cache=True, error_model="numpy")
def _boundary(kind, value, cda, p_cell, left, sT, oc):
    if kind == 1:
        return value
    if kind == 2:
        if left:
            return mass_flow(value, p_cell, cda, sT, sT, oc)
        return mass_flow(p_cell, value, cda, sT, sT, oc)
    return 0.0


@njit(cache=True, error_model="numpy")
def line_rhs(y, P, bc, dy, p):
    n = int(P[P_NCELLS])
    RT = P[P_R] * P[P_T]
    oc = P[P_OC:P_OC + NOC]
    sT = P[P_SQRT_T]
    for i in range(n):
        p[i] = y[i] * RT / P[NP + i]
    q_in = _boundary(bc[0], bc[1], bc[2], p[0], True, sT, oc)
    q_out = _boundary(bc[3], bc[4], bc[5], p[n - 1], False, sT, oc)
    if P[P_LINE_MODEL] != 1.0:  # FD (explicit or implicit: the same right-hand side)
        fd_rhs(y, q_in, q_out, p, RT, P[P_LINE_A], P[P_DX], P[P_LINE_D], P[P_MU], P[P_AV], dy, n)
    else:
        lumped_rhs(p, q_in, q_out, P[P_CDA_LINE], sT, P, P_OC, dy, n)
        for j in range(n, 2 * n - 1):
            dy[j] = 0.0


@njit(cache=True, error_model="numpy")
def line_run(y, P, bc, dt, t_end, rec_every):
    """Step the line to ``t_end`` [s] with substep ``dt``; every ``rec_every`` substeps record
    the cell pressures. Returns ``(times, pressures (m, n))``; ``y`` is updated in place."""
    n = int(P[P_NCELLS])
    ny = y.shape[0]
    k = np.empty(ny)
    y1 = np.empty(ny)
    y2 = np.empty(ny)
    p = np.empty(n)
    nsteps = int(np.round(t_end / dt))
    m = nsteps // rec_every + 1
    times = np.empty(m)
    out = np.empty((m, n))
    RT = P[P_R] * P[P_T]
    r = 0
    for s in range(nsteps + 1):
        if s % rec_every == 0 and r < m:
            times[r] = s * dt
            for i in range(n):
                out[r, i] = y[i] * RT / P[NP + i]
            r += 1
        if s == nsteps:
            break
        line_rhs(y, P, bc, k, p)
        for i in range(ny):
            y1[i] = y[i] + dt * k[i]
        line_rhs(y1, P, bc, k, p)
        for i in range(ny):
            y2[i] = 0.75 * y[i] + 0.25 * (y1[i] + dt * k[i])
        line_rhs(y2, P, bc, k, p)
        for i in range(ny):
            y[i] = (y[i] + 2.0 * (y2[i] + dt * k[i])) / 3.0
    return times[:r], out[:r]
