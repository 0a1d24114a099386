"""Supply and main valve: the closed-centre 5/3 valve's spool, its command queue and the exhaust
path (thesis 3.3, 5.3), the supply pressure, and the supply flow through the valve.

A command takes effect after the switching delay ``P[P_DELAY]`` [s] (thesis Fig. 3.6); the spool
then moves linearly at ``1 / P[P_RAMP]`` per second towards its target::

    s(τ) = clamp(s0 ± (τ - t0) / ramp, towards target)        s in [0, 1]

The exhaust path (valve V3) starts opening with the first opening command and stays open,
``se(τ) = min(1, (τ - t_exh) / ramp)``. The valve's state is the discrete state ``d`` (``D_S``,
``D_T_S``, ``D_TARGET``, ``D_T_EXH``, ``D_CMD``, the queue ``D_NQ``/``D_Q0``; see
:mod:`pneugym.physics.layout`). Times in s, pressures absolute in Pa, flows in kg/s.
"""
import math

from numba import njit

from .layout import (
    D_CMD, D_NQ, D_Q0, D_S, D_T, D_T_EXH, D_T_S, D_TARGET, NEVER, NP, P_CDA_VALVE, P_DELAY,
    P_DIP_DEPTH, P_DIP_DUR, P_DIP_T0, P_OC, P_PA, P_PS, P_R, P_RAMP, P_SQRT_T, P_T, QCAP,
)
from .orifice import flow_at


@njit(cache=True, error_model="numpy", inline="always")
def spool_position(s0, t0, target, tau, ramp):
    """Spool opening [0, 1] at time ``tau`` [s] of a ramp that left ``s0`` at ``t0`` [s] towards
    ``target`` at ``1 / ramp`` per s (``ramp`` [s]: the full opening time)::

        s(tau) = min(target, s0 + (tau - t0) / ramp)    opening
        s(tau) = max(target, s0 - (tau - t0) / ramp)    closing
    """
    ds = (tau - t0) / ramp
    if target > s0:
        return min(target, s0 + ds)
    if target < s0:
        return max(target, s0 - ds)
    return s0


@njit(cache=True, error_model="numpy", inline="always")
def valve_opening(d, P, tau):
    """Main-valve opening ``s`` [0, 1] and exhaust-path opening ``se`` [0, 1] at time ``tau`` [s]
    (>= d[D_T]): ``s`` from :func:`spool_position`, ``se = min(1, (tau - t_exh) / ramp)``.

    Exact for the ramp in force and the next queued command (at most one per substep)."""
    ramp = P[P_RAMP]
    s0, t0, tg = d[D_S], d[D_T_S], d[D_TARGET]
    t_exh = d[D_T_EXH]
    if d[D_NQ] > 0 and tau > d[D_Q0]:
        te = d[D_Q0]
        s0 = spool_position(s0, t0, tg, te, ramp)
        t0, tg = te, d[D_Q0 + 1]
        if tg > 0.5 and t_exh >= NEVER:
            t_exh = te
    s = spool_position(s0, t0, tg, tau, ramp)
    se = 0.0
    if tau > t_exh:
        se = min(1.0, (tau - t_exh) / ramp)
    return s, se


@njit(cache=True, error_model="numpy")
def command(d, P, value):
    """Give the valve command ``value`` (1 = supply connected, 0 = cut off) at the current time
    ``d[D_T]``: it is queued and takes effect at ``d[D_T] + P[P_DELAY]`` [s]. A repeated command
    is ignored; a full queue (``QCAP``) drops its oldest entry."""
    v = 1.0 if value > 0.5 else 0.0
    if v == d[D_CMD]:
        return
    d[D_CMD] = v
    nq = int(d[D_NQ])
    if nq >= QCAP:  # drop the oldest pending change: keep the newest intent
        for k in range(nq - 1):
            d[D_Q0 + 2 * k] = d[D_Q0 + 2 * k + 2]
            d[D_Q0 + 2 * k + 1] = d[D_Q0 + 2 * k + 3]
        nq -= 1
    d[D_Q0 + 2 * nq] = d[D_T] + P[P_DELAY]
    d[D_Q0 + 2 * nq + 1] = v
    d[D_NQ] = nq + 1


@njit(cache=True, error_model="numpy", inline="always")
def pop_due_commands(d, P, t):
    """Make every queued command whose effective time is <= ``t`` [s] the ramp in force: the
    spool's position at that time (:func:`spool_position`) starts the new ramp; the first
    opening also starts the exhaust path's ramp."""
    while d[D_NQ] > 0 and d[D_Q0] <= t:
        te, tg = d[D_Q0], d[D_Q0 + 1]
        d[D_S] = spool_position(d[D_S], d[D_T_S], d[D_TARGET], te, P[P_RAMP])
        d[D_T_S] = te
        d[D_TARGET] = tg
        if tg > 0.5 and d[D_T_EXH] >= NEVER:
            d[D_T_EXH] = te
        nq = int(d[D_NQ])
        for k in range(nq - 1):
            d[D_Q0 + 2 * k] = d[D_Q0 + 2 * k + 2]
            d[D_Q0 + 2 * k + 1] = d[D_Q0 + 2 * k + 3]
        d[D_NQ] = nq - 1


@njit(cache=True, error_model="numpy")
def valve_closed(d, P):
    """True when the main valve is fully closed (``s = 0`` now) and no opening is pending."""
    s, se = valve_opening(d, P, d[D_T])
    if s > 0.0:
        return False
    for k in range(int(d[D_NQ])):
        if d[D_Q0 + 2 * k + 1] > 0.5:
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def supply_pressure(P, tau):
    """Supply pressure [Pa, absolute] at time ``tau`` [s]: the set-point ``ps``, minus an
    optional raised-cosine dip of depth ``P[P_DIP_DEPTH]`` (a fraction of the gauge pressure)
    lasting ``P[P_DIP_DUR]`` [s] from ``P[P_DIP_T0]`` [s]::

        p(tau) = ps - depth (ps - pa) (1 - cos(2 pi u)) / 2,   u = (tau - t0) / dur in (0, 1)
    """
    ps = P[P_PS]
    dur = P[P_DIP_DUR]
    if dur > 0.0:
        u = (tau - P[P_DIP_T0]) / dur
        if 0.0 < u < 1.0:
            ps -= P[P_DIP_DEPTH] * (ps - P[P_PA]) * 0.5 * (1.0 - math.cos(2.0 * math.pi * u))
    return ps


@njit(cache=True, error_model="numpy")
def supply_flow(y, P, d):
    """Mass flow [kg/s] from the supply through the main valve into line cell 0 at the current
    state: the orifice law (thesis eqs. 4.1-4.3, :func:`pneugym.physics.orifice.flow_at`) with
    ``Cd A = s P[P_CDA_VALVE]`` from :func:`supply_pressure` to the cell pressure
    ``p0 = m0 R T / V0``; 0 while the valve is closed."""
    s, se = valve_opening(d, P, d[D_T])
    if s <= 0.0:
        return 0.0
    p0 = y[0] * P[P_R] * P[P_T] / P[NP]
    return flow_at(supply_pressure(P, d[D_T]), p0, s * P[P_CDA_VALVE], P[P_SQRT_T], P[P_SQRT_T],
                   P, P_OC)
