"""Advancing one plant in time: the substep loop (with or without recording), the control-level
command + advance in one call, and the recorded channels.

``advance`` / ``advance_ws`` take substeps of at most ``P[P_DT]`` [s] up to a given time and
record rows of the channels ``R_*`` (:mod:`pneugym.physics.layout`) on a uniform grid;
``command_advance`` is what one control period of :class:`pneugym.plant.Plant` and of the
environments calls. No equation of the model is written here: the physics is
:func:`pneugym.physics.stepping.substep` and the kernels it calls.
"""
import math

import numpy as np
from numba import njit

from .cylinder import chamber_pressures, cushion_factor
from .layout import (
    D_CMD, D_MODE, D_T, D_T_ARRIVE, MODE_MOVING, ND, NP, NR, NY, P_CUSH_FD, P_CUSH_FE, P_CUSH_LEN,
    P_CUSH_RAMP, P_DT, P_LINE_MODEL, P_NCELLS, P_R, P_STROKE, P_T, R_CMD, R_MDOT, R_MIN, R_PD,
    R_PE, R_PPORT, R_PVALVE, R_S, R_SD, R_SE, R_SE_P, R_T, R_TD, R_TE, R_V, R_X, STATUS_OK, Y_MIN,
    Y_SD, Y_SE, Y_TD, Y_TE, Y_V, Y_X,
)
from .stepping import substep
from .valve import command, supply_flow, valve_opening


@njit(cache=True, error_model="numpy")
def record_row(y, P, d, out, q_in):
    """Write the recorded channels (layout ``R_*``: time [s], position [m], velocity [m/s],
    pressures [Pa], openings, masses [kg], temperatures [K], command) of the current state into
    ``out``; ``q_in`` [kg/s] is the supply flow to record (:func:`pneugym.physics.valve.supply_flow`)."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    RT = P[P_R] * P[P_T]
    pd, pe, vd, ve = chamber_pressures(y, P, b)
    s, se = valve_opening(d, P, d[D_T])
    out[R_T] = d[D_T]
    out[R_X] = y[b + Y_X]
    out[R_V] = y[b + Y_V]
    out[R_PD] = pd
    out[R_PE] = pe
    out[R_PPORT] = y[n - 1] * RT / P[NP + n - 1]
    out[R_PVALVE] = y[0] * RT / P[NP]
    out[R_S] = s
    out[R_SE] = se
    out[R_MIN] = y[b + Y_MIN]
    out[R_TD] = y[b + Y_TD]
    out[R_TE] = y[b + Y_TE]
    out[R_SD] = y[b + Y_SD]
    out[R_SE_P] = y[b + Y_SE]
    out[R_CMD] = d[D_CMD]
    out[R_MDOT] = q_in


def work_size(P):
    """Length of the work array that :func:`advance_ws` needs for parameters ``P``: three state
    vectors (the substep's stages), a backup of the state (:func:`split_substep`), the ``n``
    line pressures and the implicit FD line's scratch. Plain Python (called once per plant)."""
    n = int(P[P_NCELLS])
    return 4 * (2 * n - 1 + NY) + ND + n + 5 * (n + 1) + 2 * (n - 1)


#: with the implicit FD line, a substep that ends non-physical is taken again from its start in
#: 2, 4, ... up to this many parts (the implicit tableau is not stiffly accurate: at substeps of
#: several ms, the final combination of the stages can overshoot through a sudden closure)
MAX_SPLIT = 16

#: with the implicit FD line, a substep in which the piston's mode changes (it sticks, breaks
#: away, arrives, leaves an end), its velocity changes by as much as it was (it starts, stops
#: or reverses) or it passes through a cushion's transition is taken again from its start in
#: this many parts: the events are applied between substeps, so at the implicit line's
#: substeps of up to 5 ms they would otherwise be placed only to within 5 ms, a velocity that
#: crosses zero within a substep would take the sliding friction's kick of the wrong sign and
#: miss the stick check, and a port or exhaust area that changes several-fold within a substep
#: (a 2 mm transition crossed at 0.25 m/s in 8 ms) would be followed too coarsely
EVENT_SPLIT = 8


@njit(cache=True, error_model="numpy", inline="always")
def piston_event(y, P, d, yb, db):
    """True if, between the backups ``yb``, ``db`` and the state ``y``, ``d``, the piston's mode
    changed or, moving, its velocity changed by at least its magnitude at the start or a
    cushion's area factor (:func:`pneugym.physics.cylinder.cushion_factor`) changed."""
    if d[D_MODE] != db[D_MODE]:
        return True
    if db[D_MODE] != MODE_MOVING:
        return False
    b = 2 * int(P[P_NCELLS]) - 1
    v0, v = yb[b + Y_V], y[b + Y_V]
    if (v0 != 0.0 or v != 0.0) and abs(v - v0) >= abs(v0):
        return True
    x0, x = yb[b + Y_X], y[b + Y_X]
    length, ramp, stroke = P[P_CUSH_LEN], P[P_CUSH_RAMP], P[P_STROKE]
    fd = P[P_CUSH_FD]
    if cushion_factor(x0, length, fd, ramp) != cushion_factor(x, length, fd, ramp):
        return True
    fe = P[P_CUSH_FE]
    return cushion_factor(stroke - x0, length, fe, ramp) != cushion_factor(stroke - x, length, fe, ramp)


@njit(cache=True, error_model="numpy", _nrt=False)
def split_substep(y, P, d, h, k, y1, y2, p, yb, db):
    """:func:`pneugym.physics.stepping.substep`; with the implicit FD line (``P_LINE_MODEL``
    2), a substep that ends non-physical is restored (``yb``, ``db``: backups of ``y``, ``d``)
    and taken again as 2, 4, ... :data:`MAX_SPLIT` equal ones, and a substep with a piston
    event (:func:`piston_event`) as :data:`EVENT_SPLIT` equal ones, up to and including the
    first in which the mode changes (the caller goes on from the event). Returns the status."""
    if P[P_LINE_MODEL] != 2.0:  # the explicit and lumped lines: the substep as it is
        return substep(y, P, d, h, k, y1, y2, p)
    for i in range(y.shape[0]):
        yb[i] = y[i]
    for i in range(d.shape[0]):
        db[i] = d[i]
    m = 1
    ev = False  # taking a substep with a piston event in parts
    st = STATUS_OK
    while True:
        for _ in range(m):
            mode = d[D_MODE]
            st = substep(y, P, d, h / m, k, y1, y2, p)
            if st != STATUS_OK or (ev and d[D_MODE] != mode):
                break  # (after the part with the mode change: the caller goes on from there)
        if m >= MAX_SPLIT:
            break
        if st == STATUS_OK:
            if m > 1 or not piston_event(y, P, d, yb, db):
                break
            m = EVENT_SPLIT
            ev = True
        else:
            m *= 2
        for i in range(y.shape[0]):
            y[i] = yb[i]
        for i in range(d.shape[0]):
            d[i] = db[i]
    return st


@njit(cache=True, error_model="numpy")
def advance(y, P, d, t_end, rec, rec_dt, stop_on_arrival):
    """Advance to time ``t_end`` [s] in substeps of at most ``P[P_DT]``.

    If ``rec_dt > 0``, rows of ``rec`` (shape (m, NR)) are filled at times that are multiples of
    ``rec_dt`` (substeps are shortened to land on them); recording stops when ``rec`` is full.
    If ``stop_on_arrival``, returns as soon as the piston first reaches the extended end.
    Returns ``(status, rows_written)``.
    """
    n = int(P[P_NCELLS])
    w = np.empty(4 * y.shape[0] + ND + n + 5 * (n + 1) + 2 * (n - 1))
    return advance_ws(y, P, d, t_end, rec, rec_dt, stop_on_arrival, w)


@njit(cache=True, error_model="numpy", _nrt=False)
def advance_ws(y, P, d, t_end, rec, rec_dt, stop_on_arrival, w):
    """:func:`advance` with a caller-owned work array ``w`` (length :func:`work_size`), so that a
    control loop allocates nothing."""
    ny = y.shape[0]
    k = w[0:ny]
    y1 = w[ny:2 * ny]
    y2 = w[2 * ny:3 * ny]
    yb = w[3 * ny:4 * ny]
    db = w[4 * ny:4 * ny + ND]
    p = w[4 * ny + ND:]  # the line pressures, then the implicit FD line's scratch
    dt = P[P_DT]
    nrec = 0
    mrec = rec.shape[0]
    t_next = 0.0
    if rec_dt > 0.0:
        t_next = math.ceil(d[D_T] / rec_dt - 1e-9) * rec_dt
    eps = 1e-12
    st = STATUS_OK
    while d[D_T] < t_end - eps:
        t = d[D_T]
        if rec_dt > 0.0 and nrec < mrec and t >= t_next - eps:
            record_row(y, P, d, rec[nrec], supply_flow(y, P, d))
            nrec += 1
            t_next = (math.floor(t / rec_dt + 1e-9) + 1.0) * rec_dt
        h = min(dt, t_end - t)
        if rec_dt > 0.0 and nrec < mrec:
            h = min(h, t_next - t)
        st = split_substep(y, P, d, h, k, y1, y2, p, yb, db)
        if st != STATUS_OK or (stop_on_arrival and d[D_T_ARRIVE] >= 0.0):
            break
    if st == STATUS_OK and rec_dt > 0.0 and nrec < mrec and d[D_T] >= t_next - eps:
        record_row(y, P, d, rec[nrec], supply_flow(y, P, d))
        nrec += 1
    return st, nrec


@njit(cache=True, error_model="numpy", _nrt=False)
def command_advance(y, P, d, w, value, duration, stop_on_arrival):
    """Give the valve command ``value`` (none if negative) and advance by ``duration`` [s]: the
    control-level step in one call. ``w``: work array (:func:`work_size`). Returns the status."""
    if value >= 0.0:
        command(d, P, value)
    norec = w[:0].reshape((0, NR))  # no recording (a view: nothing is allocated)
    st, _ = advance_ws(y, P, d, d[D_T] + duration, norec, 0.0, stop_on_arrival, w)
    return st
