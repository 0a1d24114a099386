"""Piston and sensor events, applied at the end of every substep (thesis 3.4, 5.6, 6.1-6.2).

Between substeps the piston's friction/end-stop ``mode`` (``d[D_MODE]``: moving, stuck, held at
the extended end, held at the retracted end) changes by the Karnopp rules, with the net air
force ``F = (p_d - p_e) A_p`` [N] and the breakaway friction ``Fs`` [N]:

- moving: reaching ``x >= stroke`` -> held at the end (arrival time interpolated within the
  substep), ``x <= 0`` -> held at the start; a velocity reversal or ``|v| < V_STICK`` with
  ``|F| <= Fs`` -> stuck (a stick event); a reversal with ``|F| > Fs`` -> ``v = 0``, still moving;
- stuck: ``|F| > Fs`` -> moving; at the end: ``F < -Fs`` -> moving; at the start: ``F > Fs`` ->
  moving (the breakaway).

A held piston keeps its exact position (no chattering). The sensors then follow their
first-order lag, integrated exactly over the substep.
"""
import math

from numba import njit

from .cylinder import chamber_pressures, piston_force
from .layout import (
    D_MODE, D_MOVED, D_STICKS, D_T_ARRIVE, MODE_END, MODE_MOVING, MODE_START, MODE_STUCK, P_FS,
    P_LAG, P_STROKE, Y_SD, Y_SE, Y_V, Y_X,
)

#: Karnopp velocity dead band [m/s]: a decelerating piston slower than this sticks if |F| <= Fs.
V_STICK = 1e-5


@njit(cache=True, error_model="numpy", inline="always")
def piston_events(y, P, d, h, t, b, mode, x_old, v_old):
    """Stick/slip and end stops (Karnopp, module docstring) at the end of a substep of ``h`` [s]
    that started at ``t`` [s] in ``mode`` from position ``x_old`` [m] and velocity ``v_old``
    [m/s]; updates ``y`` and ``d`` in place. Then the sensor pressures [Pa], a first-order lag
    with time constant ``P[P_LAG]`` [s] for a pressure held over the substep::

        p_s += (1 - exp(-h / lag)) (p - p_s)       (p_s = p when lag = 0)
    """
    # a held piston keeps its exact position: RK3 rounding must not move it
    if mode != MODE_MOVING:
        y[b + Y_X] = x_old
        y[b + Y_V] = 0.0
    stroke = P[P_STROKE]
    fs = P[P_FS]
    pd, pe, vd, ve = chamber_pressures(y, P, b)
    f = piston_force(pd, pe, P)
    x, v = y[b + Y_X], y[b + Y_V]
    if mode == MODE_MOVING:
        if x >= stroke:
            if d[D_T_ARRIVE] < 0.0:
                frac = (stroke - x_old) / (x - x_old) if x > x_old else 1.0
                d[D_T_ARRIVE] = t + frac * h
            y[b + Y_X] = stroke
            y[b + Y_V] = 0.0
            d[D_MODE] = MODE_END
        elif x <= 0.0:
            y[b + Y_X] = 0.0
            y[b + Y_V] = 0.0
            d[D_MODE] = MODE_START
        elif v_old != 0.0 and (v_old * v <= 0.0 or abs(v) < V_STICK):
            # velocity reversal, or coming to rest within the dead band: Karnopp stick check
            if abs(f) <= fs:
                y[b + Y_V] = 0.0
                d[D_MODE] = MODE_STUCK
                d[D_STICKS] += 1.0
            elif v_old * v <= 0.0:
                y[b + Y_V] = 0.0
    elif mode == MODE_STUCK:
        if abs(f) > fs:
            d[D_MODE] = MODE_MOVING
    elif mode == MODE_END:
        if f < -fs:
            d[D_MODE] = MODE_MOVING
    else:  # MODE_START
        if f > fs:
            d[D_MODE] = MODE_MOVING
            d[D_MOVED] = 1.0

    # sensors: first-order lag, integrated exactly for a pressure held over the substep
    lag = P[P_LAG]
    if lag > 0.0:
        a = 1.0 - math.exp(-h / lag)
        y[b + Y_SD] += a * (pd - y[b + Y_SD])
        y[b + Y_SE] += a * (pe - y[b + Y_SE])
    else:
        y[b + Y_SD] = pd
        y[b + Y_SE] = pe
