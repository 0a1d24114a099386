"""One substep of the plant: a 3-stage IMEX Runge-Kutta step, then the valve and piston events.

Explicit part: SSP-RK3 (``c = 0, 1, 1/2``; weights ``1/6, 1/6, 2/3``) on everything but the
stiff orifice flows. Implicit part: the valve and port flows (with the lumped line, its whole
orifice chain; with ``SolverParams(line_scheme="implicit")``, the whole FD line), with the
diagonally implicit tableau ``IMEX_A*`` below on the same abscissae and weights; each stage's equation is solved exactly (:func:`pneugym.physics.rhs.stage_rhs`).
Order 2 (3 for the explicit part alone), A- and L-stable implicit part; mass moves by the same
flows on both sides, so it is conserved to round-off. The substep ``h`` [s] is at most
``P[P_DT]``, chosen by :func:`pneugym.plant.choose_dt` from the explicit part's stability limits.
"""
import math

from numba import njit

from .events import piston_events
from .layout import (
    D_MODE, D_S, D_STATUS, D_T, D_T_CLOSED, D_T_S, D_TARGET, MODE_MOVING, P_LINE_MODEL, P_NCELLS,
    P_RAMP, STATUS_NONFINITE, STATUS_NONPOSITIVE, STATUS_OK, Y_MD, Y_ME, Y_MIN, Y_TD, Y_TE, Y_V, Y_X,
)
from .rhs import stage_rhs
from .valve import pop_due_commands, spool_position, valve_opening

#: Implicit tableau of the IMEX substep (the explicit one is SSP-RK3: c = 0, 1, 1/2; weights
#: 1/6, 1/6, 2/3 for both). The same abscissae as the explicit part: a flow that passes through
#: the last line cell (explicit in, implicit out) leaves its mass unchanged at every stage
#: (with IMEX-SSP3(3,3,2), whose implicit abscissae differ, the errors were several times
#: larger). First stage explicit; order 2; A-stable and L-stable (R(-inf) = 0): the member
#: a33 = 1/4 of the one-parameter family of such tableaus with these c and b. See ``stage_rhs``.
IMEX_A21, IMEX_A22 = 2.0 / 3.0, 1.0 / 3.0
IMEX_A31, IMEX_A32, IMEX_A33 = 7.0 / 48.0, 5.0 / 48.0, 0.25


# The hot loop. ``_nrt=False``: the substep allocates nothing, and without numba's runtime the
# array arguments of the inlined kernels are not reference-counted (atomic increments and
# decrements around every branch cost about a third of a substep). ``error_model="numpy"``
# everywhere: a division by zero gives inf/NaN, which the state check below reports, instead
# of a Python exception path in every division. ``fastmath={"contract"}`` only (fused
# multiply-adds, ~5 % faster): no "nnan"/"ninf" (the state check needs isfinite) and no "arcp"
# (x / 3 as x * 0.333... rounds the stage update unevenly and the mass balance drifts from
# 1e-15 to 1e-12 relative).
@njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def substep(y, P, d, h, k, y1, y2, p):
    """Advance ``y`` and ``d`` in place by ``h`` [s] with a 3-stage IMEX Runge-Kutta step, then
    apply the events: valve commands coming due, stick/slip and end stops (Karnopp), sensor lag.
    Returns a status code (``STATUS_OK``, ``STATUS_NONFINITE``, ``STATUS_NONPOSITIVE``).

    Explicit part: SSP-RK3 (Butcher form): everything but the valve and port flows.
    Implicit part (:func:`pneugym.physics.rhs.stage_rhs`): those two flows, with the diagonally
    implicit tableau ``IMEX_A*`` (first stage explicit) on the same abscissae 0, 1, 1/2 and the
    same weights, so that for the rates ``f_i`` (explicit) and ``q_i`` (implicit) of the stages::

        y(t + h) = y(t) + h (f_1 + f_2 + 4 f_3) / 6 + h (q_1 + q_2 + 4 q_3) / 6

    Order 2 (3 for the explicit part alone); mass moves between cells by the same flows on both
    sides, so it is conserved to round-off. ``k``, ``y1``, ``y2``: work arrays of the state's
    length (``y1`` receives the first two stages' explicit rates summed, ``k`` the second's and
    then the third's, ``y2`` the stage state); ``p``: scratch, the line pressures first (n), then
    (implicit FD line) its solver's and the faces' flows
    (:func:`pneugym.physics.advance.work_size`)."""
    t = d[D_T]
    ny = y.shape[0]
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    mode = int(d[D_MODE])
    v_old = y[b + Y_V]
    x_old = y[b + Y_X]
    z = y2
    fdi = P[P_LINE_MODEL] == 2.0
    # with the implicit FD line (substeps up to 5 ms), the sliding friction keeps the substep's
    # direction: a velocity that crosses zero within it would otherwise take a kick of the wrong
    # sign, end the substep moving on and miss the stick check (a piston creeping on for
    # seconds where it sticks with short substeps)
    vdir = 0.0
    if fdi and mode == MODE_MOVING and v_old != 0.0:
        vdir = 1.0 if v_old > 0.0 else -1.0

    # stage 1 (c = 0): the state itself
    s, se = valve_opening(d, P, t)
    qv1, qp1, _ = stage_rhs(t, s, se, y, P, mode, y1, p, 0.0, 0.0, 0.0, vdir)
    # stage 2 (c = 1): y + h k1 + h (a21 q1 + a22 q2)
    for i in range(ny):
        z[i] = y[i] + h * y1[i]
    c = h * IMEX_A21
    z[0] += c * qv1
    z[n - 1] -= c * qp1
    z[b + Y_MD] += c * qp1
    chain = P[P_LINE_MODEL] == 1.0 and n > 1
    # the implicit FD line's scratch beyond the pressures and its solver's (``work_size``):
    # the faces' stage-1 + stage-2 flows, then their stage-3 starting values
    acc = n + 5 * (n + 1)
    if fdi:  # faces: implicit momentum; cells: the stage-1 face flows, implicit too
        for j in range(n - 1):
            z[n + j] = y[n + j] + c * y1[n + j]
            q = c * y[n + j]
            z[j] -= q
            z[j + 1] += q
    if chain:  # the lumped line's joints: implicit, their flows in the face slots of the rates
        for j in range(n - 1):
            q = c * y1[n + j]
            z[j] -= q
            z[j + 1] += q
            k[n + j] = y1[n + j]  # the guess of stage 2
    s, se = valve_opening(d, P, t + h)
    qv2, qp2, _ = stage_rhs(t + h, s, se, z, P, mode, k, p, h * IMEX_A22, qv1, qp1, vdir)
    # stage 3 (c = 1/2): y + h/4 (k1 + k2) + h (a31 q1 + a32 q2 + a33 q3)
    c = h * IMEX_A31
    c2 = h * IMEX_A32
    if chain:  # the joints' implicit masses of stage 3 (p: scratch until stage_rhs)
        for j in range(n - 1):
            p[j] = c * y1[n + j] + c2 * k[n + j]
    if fdi:  # stage 1's face flows are y's, stage 2's z's; rates M1 in y1, M2 in k
        for j in range(n - 1):
            p[j] = c * y[n + j] + c2 * z[n + j]
            p[acc + j] = y[n + j] + z[n + j]
            p[acc + n - 1 + j] = y[n + j] + c * y1[n + j] + c2 * k[n + j]
    for i in range(ny):
        y1[i] += k[i]
        z[i] = y[i] + 0.25 * h * y1[i]
    z[0] += c * qv1 + c2 * qv2
    if chain or fdi:  # (the chain's guess of stage 3 is stage 2's flows, already in k)
        for j in range(n - 1):
            z[j] -= p[j]
            z[j + 1] += p[j]
    if fdi:
        for j in range(n - 1):
            z[n + j] = p[acc + n - 1 + j]
    z[n - 1] -= c * qp1 + c2 * qp2
    z[b + Y_MD] += c * qp1 + c2 * qp2
    s, se = valve_opening(d, P, t + 0.5 * h)
    qv3, qp3, _ = stage_rhs(t + 0.5 * h, s, se, z, P, mode, k, p, h * IMEX_A33, qv2, qp2, vdir)
    # weights 1/6, 1/6, 2/3 for both parts
    h6 = h / 6.0
    for i in range(ny):
        y[i] += h6 * (y1[i] + 4.0 * k[i])
    qv = h6 * (qv1 + qv2 + 4.0 * qv3)
    qp = h6 * (qp1 + qp2 + 4.0 * qp3)
    y[0] += qv
    y[b + Y_MIN] += qv
    y[n - 1] -= qp
    y[b + Y_MD] += qp
    if chain:  # the face slots took h (q1 + q2 + 4 q3) / 6 of each joint: move it, reset them
        for j in range(n - 1):
            q = y[n + j]
            y[j] -= q
            y[j + 1] += q
            y[n + j] = 0.0
    if fdi:  # the faces' flows of the three stages (stage 3's in z) move the cells' mass
        for j in range(n - 1):
            q = h6 * (p[acc + j] + 4.0 * z[n + j])
            y[j] -= q
            y[j + 1] += q

    # valve: advance the ramp, record a completed closing, pop due commands
    t_new = t + h
    s_before = spool_position(d[D_S], d[D_T_S], d[D_TARGET], t, P[P_RAMP])
    pop_due_commands(d, P, t_new)
    s_now = spool_position(d[D_S], d[D_T_S], d[D_TARGET], t_new, P[P_RAMP])
    if s_now <= 0.0 and (s_before > 0.0 or d[D_S] > 0.0) and d[D_TARGET] == 0.0 \
            and d[D_T_CLOSED] < d[D_T_S]:
        d[D_T_CLOSED] = d[D_T_S] + d[D_S] * P[P_RAMP]
    d[D_T] = t_new

    # state check (one exit only: numba keeps reference counting around early returns)
    status = STATUS_OK
    for i in range(ny):
        if not math.isfinite(y[i]):
            status = STATUS_NONFINITE
    if status == STATUS_OK:
        for i in range(n):
            if y[i] <= 0.0:
                status = STATUS_NONPOSITIVE
        if y[b + Y_MD] <= 0.0 or y[b + Y_ME] <= 0.0 or y[b + Y_TD] <= 0.0 or y[b + Y_TE] <= 0.0:
            status = STATUS_NONPOSITIVE
    if status != STATUS_OK:
        d[D_STATUS] = status
    else:
        piston_events(y, P, d, h, t, b, mode, x_old, v_old)
    return status
