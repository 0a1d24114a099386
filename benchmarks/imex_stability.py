"""IMEX stability scan of the linearised plant (used by the accuracy and solve_ivp sections).

At states sampled along an extension the jitted ``rhs`` is linearised by finite differences
(``J``), the part the substep treats implicitly is split off (``J_I``: the port flow, the valve
flow with more than one line cell, the lumped line's joints) and the substep's amplification
matrix for ``y' = (J - J_I) y + J_I y`` is built from the explicit SSP-RK3 tableau and the
implicit tableau ``IMEX_A*`` of :mod:`pneugym.physics.stepping`. A state is unstable when the
spectral radius exceeds the physical growth ``exp(dt max Re λ)``.
"""
from __future__ import annotations

import math

import numpy as np

import common  # noqa: F401  (puts the repository root on sys.path)
from pneugym import Plant
from pneugym.physics import layout as L
from pneugym.physics import system as K
from pneugym.physics.cylinder import cushion_factor
from pneugym.physics.orifice import flow_at

T_END_SCAN = 3.0  # [s] length of the extension sampled (as long as the accuracy section's runs)


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
    if P[L.P_LINE_MODEL] == 1.0 and n > 1:
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


def stability_scan(rig, t_end=T_END_SCAN, every=0.01, cut_at=None):
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
