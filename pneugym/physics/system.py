"""The whole plant as one set of jitted kernels: right-hand side, SSP-RK3 substep with the
stick-slip / end-stop / valve events, control-level advance and a batched ``prange`` advance.

Array layouts: :mod:`pneugym.physics.layout`. Everything is SI with absolute pressures.
"""
import math

import numpy as np
from numba import njit, prange

from .cylinder import chamber_dT, cushion_factor, enthalpy_flow, friction_force
from .energy import potential_energy
from .layout import (
    D_CMD, D_MODE, D_MOVED, D_NQ, D_Q0, D_S, D_STATUS, D_STICKS, D_T, D_T_ARRIVE, D_T_CLOSED,
    D_T_EXH, D_T_S, D_TARGET, MODE_END, MODE_MOVING, MODE_START, MODE_STUCK, NEVER, NP, NR, NY,
    P_AP, P_CDA_EXH, P_CDA_LEAK_D, P_CDA_LEAK_P, P_CDA_LINE, P_CDA_PORT, P_CDA_VALVE,
    P_AV, P_CUSH_FD, P_DIP_DEPTH, P_DIP_DUR, P_DIP_T0, P_CUSH_FE, P_CUSH_LEN, P_CUSH_RAMP, P_DELAY, P_DT, P_DX, P_FC,
    P_FS, P_GAMMA, P_OC, P_SQRT_T, P_KV, P_LAG, P_LINE_A, P_LINE_D, P_LINE_MODEL, P_MASS,
    P_MU, P_NCELLS, P_PA, P_PS, P_R, P_RAMP, P_STRIB_F, P_STRIB_V, P_STROKE, P_T, P_TAU_TH,
    P_V0D, P_V0E, QCAP, R_CMD, R_MDOT, R_MIN, R_PD, R_PE, R_PPORT, R_PVALVE, R_S, R_SD, R_SE,
    R_SE_P, R_T, R_TD, R_TE, R_V, R_X, STATUS_NONFINITE, STATUS_NONPOSITIVE, STATUS_OK, Y_MD,
    Y_ME, Y_MIN, Y_MOUT, Y_SD, Y_SE, Y_TD, Y_TE, Y_V, Y_X,
)
from .line import fd_continuity, fd_momentum, lumped_rhs
from .orifice import flow_at, flow_deriv_fwd, implicit_flow


#: Implicit tableau of the IMEX substep (the explicit one is SSP-RK3: c = 0, 1, 1/2; weights
#: 1/6, 1/6, 2/3 for both). The same abscissae as the explicit part: a flow that passes through
#: the last line cell (explicit in, implicit out) leaves its mass unchanged at every stage
#: (with IMEX-SSP3(3,3,2), whose implicit abscissae differ, the errors were several times
#: larger). First stage explicit; order 2; A-stable and L-stable (R(-inf) = 0): the member
#: a33 = 1/4 of the one-parameter family of such tableaus with these c and b. See ``stage_rhs``.
IMEX_A21, IMEX_A22 = 2.0 / 3.0, 1.0 / 3.0
IMEX_A31, IMEX_A32, IMEX_A33 = 7.0 / 48.0, 5.0 / 48.0, 0.25

#: Karnopp velocity dead band [m/s]: a decelerating piston slower than this sticks if |F| <= Fs.
V_STICK = 1e-5


# --------------------------------------------------------------------------------------------
# valve
# --------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy", inline="always")
def _ramp(s0, t0, target, tau, ramp):
    """Spool opening at ``tau`` moving from ``s0`` at ``t0`` towards ``target`` at 1/ramp per s."""
    ds = (tau - t0) / ramp
    if target > s0:
        return min(target, s0 + ds)
    if target < s0:
        return max(target, s0 - ds)
    return s0


@njit(cache=True, error_model="numpy", inline="always")
def valve_opening(d, P, tau):
    """Main-valve opening [0, 1] and exhaust-path opening at time ``tau`` (>= d[D_T]).

    Exact for the ramp in force and the next queued command (at most one per substep)."""
    ramp = P[P_RAMP]
    s0, t0, tg = d[D_S], d[D_T_S], d[D_TARGET]
    t_exh = d[D_T_EXH]
    if d[D_NQ] > 0 and tau > d[D_Q0]:
        te = d[D_Q0]
        s0 = _ramp(s0, t0, tg, te, ramp)
        t0, tg = te, d[D_Q0 + 1]
        if tg > 0.5 and t_exh >= NEVER:
            t_exh = te
    s = _ramp(s0, t0, tg, tau, ramp)
    se = 0.0
    if tau > t_exh:
        se = min(1.0, (tau - t_exh) / ramp)
    return s, se


@njit(cache=True, error_model="numpy")
def command(d, P, value):
    """Give the valve command ``value`` (1 = supply connected, 0 = cut off) at the current time.
    It takes effect after the valve delay ``P[P_DELAY]``."""
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
def _pop_due_commands(d, P, t):
    """Make queued commands whose effective time is <= t the ramp in force."""
    while d[D_NQ] > 0 and d[D_Q0] <= t:
        te, tg = d[D_Q0], d[D_Q0 + 1]
        d[D_S] = _ramp(d[D_S], d[D_T_S], d[D_TARGET], te, P[P_RAMP])
        d[D_T_S] = te
        d[D_TARGET] = tg
        if tg > 0.5 and d[D_T_EXH] >= NEVER:
            d[D_T_EXH] = te
        nq = int(d[D_NQ])
        for k in range(nq - 1):
            d[D_Q0 + 2 * k] = d[D_Q0 + 2 * k + 2]
            d[D_Q0 + 2 * k + 1] = d[D_Q0 + 2 * k + 3]
        d[D_NQ] = nq - 1


# --------------------------------------------------------------------------------------------
# pressures and right-hand side
# --------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy", inline="always")
def supply_pressure(P, tau):
    """Supply pressure [Pa] at time ``tau``: the set-point, minus an optional raised-cosine dip
    of ``P[P_DIP_DEPTH]`` times the gauge pressure, lasting ``P[P_DIP_DUR]`` from ``P[P_DIP_T0]``."""
    ps = P[P_PS]
    dur = P[P_DIP_DUR]
    if dur > 0.0:
        u = (tau - P[P_DIP_T0]) / dur
        if 0.0 < u < 1.0:
            ps -= P[P_DIP_DEPTH] * (ps - P[P_PA]) * 0.5 * (1.0 - math.cos(2.0 * math.pi * u))
    return ps


@njit(cache=True, error_model="numpy", inline="always")
def chamber_pressures(y, P, b):
    """Driving and exhaust chamber pressures [Pa] and volumes [m³] for state ``y``."""
    x = min(max(y[b + Y_X], 0.0), P[P_STROKE])
    vd = P[P_V0D] + P[P_AP] * x
    ve = P[P_V0E] + P[P_AP] * (P[P_STROKE] - x)
    R = P[P_R]
    return y[b + Y_MD] * R * y[b + Y_TD] / vd, y[b + Y_ME] * R * y[b + Y_TE] / ve, vd, ve


@njit(cache=True, error_model="numpy")
def rhs(tau, y, P, d, mode, dy, p):
    """dy/dt at time ``tau``; ``p`` (n) receives the line-cell pressures. Returns the supply flow."""
    s, se = valve_opening(d, P, tau)
    return rhs_valve(tau, s, se, y, P, mode, dy, p)


@njit(cache=True, error_model="numpy", inline="always")
def rhs_valve(tau, s, se, y, P, mode, dy, p):
    """:func:`rhs` with the main-valve and exhaust-path openings ``s``, ``se`` given."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    q_imp, q_port, q_in = stage_rhs(tau, s, se, y, P, mode, dy, p, 0.0, 0.0, 0.0)
    dy[0] += q_imp
    dy[n - 1] -= q_port
    dy[b + Y_MD] += q_port
    dy[b + Y_MIN] += q_imp
    if P[P_LINE_MODEL] != 0.0 and n > 1:  # the lumped line's joint flows
        for j in range(n - 1):
            q = dy[n + j]
            dy[j] -= q
            dy[j + 1] += q
            dy[n + j] = 0.0
    return q_in


#: Newton iterations at most in :func:`implicit_chain`
CHAIN_MAX_IT = 30
#: :func:`implicit_chain` stops when its last Newton correction is at most this fraction of the
#: largest flow of the chain: the convergence is quadratic, so the flows are then exact to
#: round-off (the chain is cheap: a few cells)
CHAIN_TOL = 1e-9


@njit(cache=True, error_model="numpy", inline="always")
def _flow_deriv(pa, pb, cda, sTa, sTb, c, o):
    """Signed flow a -> b and its partial derivatives ``(q, dq/dpa, dq/dpb)`` (either direction)."""
    if pa >= pb:
        q, da, db = flow_deriv_fwd(pa, pb, cda, sTa, c, o)
        return q, da, db
    q, db, da = flow_deriv_fwd(pb, pa, cda, sTb, c, o)
    return -q, -da, -db


@njit(cache=True, error_model="numpy", inline="always")
def implicit_chain(z, P, n, b, hg, ps, cda_v, cda_p, kd, sTd, qv, qp, qj, cp, dp):
    """The implicit stage equation of the lumped line's whole orifice chain: supply -> valve ->
    line cell 0 -> joint -> ... -> line cell n-1 -> port -> driving chamber.

    The ``n + 1`` flows (row 0 the valve, rows 1..n-1 the joints ``qj[r - 1]`` between cells
    r-1 and r, row n the port) solve ``q_r = flow_r(state + hg q)``: each at the pressures left
    after every flow of the chain has moved ``hg q`` of mass out of its upstream and into its
    downstream volume (the supply is a reservoir). Row r depends on the flows r-1, r, r+1 only:
    Newton's method with the tridiagonal Jacobian solved by the Thomas algorithm. The Jacobian
    ``1 + hg (f_a k_a - f_b k_b)`` on the diagonal, ``-hg f_a k_a`` and ``hg f_b k_b`` beside it
    (``f_a >= 0 >= f_b`` the orifice law's pressure derivatives, ``k = dp/dm``) is strictly
    row-diagonally dominant, so the elimination needs no pivoting. A step that would leave a
    non-positive mass is halved. Converged when the correction is below ``CHAIN_TOL`` of the
    largest flow.

    ``z``: the stage state (cells ``z[0..n-1]``, driving-chamber mass ``z[b + Y_MD]``), not
    modified; ``qv``, ``qp``, ``qj`` (length n-1, in place): the guesses, on return the flows;
    ``cp`` (n), ``dp`` (n-1): scratch. Returns ``(qv, qp)``.
    """
    RT = P[P_R] * P[P_T]
    sT = P[P_SQRT_T]
    cda_l = P[P_CDA_LINE]
    md0 = z[b + Y_MD]
    for _ in range(CHAIN_MAX_IT):
        # residuals, Jacobian rows and the Thomas forward sweep in one pass
        # row 0: supply (reservoir) -> cell 0
        q_next = qj[0] if n > 1 else qp
        k_dn = RT / P[NP]
        p_dn = k_dn * (z[0] + hg * (qv - q_next))
        f, fa, fb = _flow_deriv(ps, p_dn, cda_v, sT, sT, P, P_OC)
        diag = 1.0 - hg * fb * k_dn
        c_r = hg * fb * k_dn
        cp[0] = c_r / diag
        d0 = (qv - f) / diag
        d_prev = d0
        scale = abs(qv)
        for r in range(1, n):
            q_r = qj[r - 1]
            q_next = qj[r] if r < n - 1 else qp
            k_up = k_dn
            p_up = p_dn
            k_dn = RT / P[NP + r]
            p_dn = k_dn * (z[r] + hg * (q_r - q_next))
            f, fa, fb = _flow_deriv(p_up, p_dn, cda_l, sT, sT, P, P_OC)
            a_r = -hg * fa * k_up
            diag = 1.0 + hg * (fa * k_up - fb * k_dn) - a_r * cp[r - 1]
            cp[r] = hg * fb * k_dn / diag
            d_prev = (q_r - f - a_r * d_prev) / diag
            dp[r - 1] = d_prev
            scale = max(scale, abs(q_r))
        # row n: cell n-1 -> driving chamber
        k_up = k_dn
        p_up = p_dn
        p_d = kd * (md0 + hg * qp)
        f, fa, fb = _flow_deriv(p_up, p_d, cda_p, sT, sTd, P, P_OC)
        a_r = -hg * fa * k_up
        diag = 1.0 + hg * (fa * k_up - fb * kd) - a_r * cp[n - 1]
        dq_n = (qp - f - a_r * d_prev) / diag
        scale = max(scale, abs(qp))
        # back substitution: the corrections, joints into dp
        dmax = abs(dq_n)
        dq_next = dq_n
        for r in range(n - 1, 0, -1):
            dq_next = dp[r - 1] - cp[r] * dq_next
            dp[r - 1] = dq_next
            dmax = max(dmax, abs(dq_next))
        dq_0 = d0 - cp[0] * dq_next
        dmax = max(dmax, abs(dq_0))
        # damping: a volume with a positive mass keeps one
        lam = 1.0
        for _h in range(60):
            ok = md0 + hg * (qp - lam * dq_n) > 0.0 or md0 + hg * qp <= 0.0
            q_in = qv - lam * dq_0
            q_in0 = qv
            for r in range(n):
                if r < n - 1:
                    q_out = qj[r] - lam * dp[r]
                    q_out0 = qj[r]
                else:
                    q_out = qp - lam * dq_n
                    q_out0 = qp
                if z[r] + hg * (q_in - q_out) <= 0.0 < z[r] + hg * (q_in0 - q_out0):
                    ok = False
                q_in = q_out
                q_in0 = q_out0
            if ok:
                break
            lam *= 0.5
        qv -= lam * dq_0
        qp -= lam * dq_n
        for r in range(n - 1):
            qj[r] -= lam * dp[r]
        if dmax <= CHAIN_TOL * scale:
            break
    return qv, qp


@njit(cache=True, error_model="numpy", inline="always")
def stage_rhs(tau, s, se, y, P, mode, dy, p, hg, qv0, qp0):
    """One stage of the IMEX substep: the implicit part, then the explicit right-hand side.

    The implicit part is the port flow from the last line cell into the driving chamber and the
    supply flow through the main valve into line cell 0: the stiffest exchanges (small line cells
    behind orifices; the port's limited the explicit substep to 274 µs, the valve's to 606 µs).
    With ``hg = h a_ii > 0`` each solves its stage equation ``q = flow(state + hg q)`` with
    :func:`pneugym.physics.orifice.implicit_flow` (exact in the orifices' linear zone, Newton
    from the guesses ``qv0``, ``qp0`` outside it), port first, and ``y`` is updated in place to
    the stage state (cell 0, cell n-1 and the driving-chamber mass). With one line cell the
    valve flow stays explicit (it is then evaluated at the stage state). ``hg = 0``: no implicit
    step, the flows at ``y``.

    Then ``dy`` receives every other term at the stage state: the line without the implicit flows
    in the continuity of its end cells, the chambers without the port flow in the driving-chamber
    mass, the piston; the implicit flows enter the line momentum (end-cell fluxes) and the
    chamber energy equation. ``dy[b + Y_MIN]`` holds only an explicit valve flow.
    Returns ``(q_valve_implicit, q_port, q_supply)`` [kg/s]: the implicit valve flow (0 when it is
    explicit), the port flow, the supply flow.
    """
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    R, gam, T, pa = P[P_R], P[P_GAMMA], P[P_T], P[P_PA]
    sT = P[P_SQRT_T]
    RT = R * T
    for i in range(n):
        p[i] = y[i] * RT / P[NP + i]
    pd, pe, vd, ve = chamber_pressures(y, P, b)
    x, v = y[b + Y_X], y[b + Y_V]
    Td, Te = y[b + Y_TD], y[b + Y_TE]
    sTd = sT if Td == T else math.sqrt(Td)
    sTe = sT if Te == T else math.sqrt(Te)
    stroke = P[P_STROKE]

    fd = cushion_factor(x, P[P_CUSH_LEN], P[P_CUSH_FD], P[P_CUSH_RAMP])
    fe = cushion_factor(stroke - x, P[P_CUSH_LEN], P[P_CUSH_FE], P[P_CUSH_RAMP])
    cda_v = s * P[P_CDA_VALVE]
    cda_p = fd * P[P_CDA_PORT]
    q_imp = 0.0  # the implicit valve flow (0 when the valve flow is explicit)
    chain = P[P_LINE_MODEL] != 0.0 and n > 1  # lumped line: the whole orifice chain is implicit
    if hg > 0.0 and chain:
        # valve, joints (guesses and result in dy[n..b-1]) and port together; p and the unused
        # face slots y[n..b-1] are the solver's scratch
        kd = R * Td / vd
        ps = supply_pressure(P, tau) if s > 0.0 else P[P_PA]
        q_in, q_port = implicit_chain(y, P, n, b, hg, ps, cda_v, cda_p, kd, sTd, qv0, qp0,
                                      dy[n:b], p, y[n:b])
        y[0] += hg * q_in
        for j in range(n - 1):
            y[j] -= hg * dy[n + j]
            y[j + 1] += hg * dy[n + j]
        y[n - 1] -= hg * q_port
        y[b + Y_MD] += hg * q_port
        for i in range(n):
            p[i] = y[i] * RT / P[NP + i]
        pd = y[b + Y_MD] * R * Td / vd
        q_imp = q_in
    elif hg > 0.0:
        # port: implicit (line cell n-1 <-> driving chamber)
        kc = RT / P[NP + n - 1]
        kd = R * Td / vd
        q_port = implicit_flow(p[n - 1], pd, kc, kd, hg, cda_p, sT, sTd, P, P_OC, qp0)
        y[n - 1] -= hg * q_port
        y[b + Y_MD] += hg * q_port
        p[n - 1] = y[n - 1] * RT / P[NP + n - 1]
        pd = y[b + Y_MD] * R * Td / vd
        # valve: implicit unless the one cell also takes the port flow (n = 1)
        q_in = 0.0
        if s > 0.0:
            if n > 1:
                q_in = implicit_flow(supply_pressure(P, tau), p[0], 0.0, RT / P[NP], hg, cda_v,
                                     sT, sT, P, P_OC, qv0)
                y[0] += hg * q_in
                p[0] = y[0] * RT / P[NP]
                q_imp = q_in
            else:
                q_in = flow_at(supply_pressure(P, tau), p[0], cda_v, sT, sT, P, P_OC)
    else:
        q_port = flow_at(p[n - 1], pd, cda_p, sT, sTd, P, P_OC)
        q_in = 0.0
        if s > 0.0:
            q_in = flow_at(supply_pressure(P, tau), p[0], cda_v, sT, sT, P, P_OC)
            if n > 1:
                q_imp = q_in
        if chain:  # the joints' flows, as the implicit part's rates
            for j in range(n - 1):
                dy[n + j] = flow_at(p[j], p[j + 1], P[P_CDA_LINE], sT, sT, P, P_OC)

    # explicit part
    q_ex = 0.0
    if se > 0.0:
        q_ex = flow_at(pe, pa, se * fe * P[P_CDA_EXH], sTe, sT, P, P_OC)
    q_ld = flow_at(pd, pa, P[P_CDA_LEAK_D], sTd, sT, P, P_OC)
    q_lp = flow_at(pd, pe, P[P_CDA_LEAK_P], sTd, sTe, P, P_OC)

    # line (the valve and port flows are left out of the end cells' continuity)
    if P[P_LINE_MODEL] == 0.0:
        fd_continuity(y, 0.0, 0.0, dy, n)
        fd_momentum(y, q_in, q_port, p, RT, P[P_LINE_A], P[P_DX], P[P_LINE_D], P[P_MU], P[P_AV],
                    dy, n)
    elif chain:  # every exchange of the cells is implicit; dy[n..b-1] holds the joints' flows
        for i in range(n):
            dy[i] = 0.0
    else:  # one lumped cell
        lumped_rhs(p, 0.0, 0.0, P[P_CDA_LINE], sT, P, P_OC, dy, n)
        for j in range(n, b):
            dy[j] = 0.0

    # chambers
    dy[b + Y_MD] = -q_ld - q_lp
    dy[b + Y_ME] = q_lp - q_ex
    tau_th = P[P_TAU_TH]
    if tau_th > 0.0:
        cv = R / (gam - 1.0)
        cp = cv + R
        vmove = v if mode == MODE_MOVING else 0.0
        hd = (enthalpy_flow(q_port, T, Td, cp, cv, R) + enthalpy_flow(-q_ld, T, Td, cp, cv, R)
              + enthalpy_flow(-q_lp, Te, Td, cp, cv, R))
        he = enthalpy_flow(q_lp, Td, Te, cp, cv, R) + enthalpy_flow(-q_ex, T, Te, cp, cv, R)
        dy[b + Y_TD] = chamber_dT(y[b + Y_MD], Td, pd, P[P_AP] * vmove, hd, cv, T, tau_th)
        dy[b + Y_TE] = chamber_dT(y[b + Y_ME], Te, pe, -P[P_AP] * vmove, he, cv, T, tau_th)
    else:
        dy[b + Y_TD] = 0.0
        dy[b + Y_TE] = 0.0

    # piston
    if mode == MODE_MOVING:
        f = (pd - pe) * P[P_AP]
        ff = friction_force(v, f, P[P_FC], P[P_KV], P[P_STRIB_F], P[P_STRIB_V])
        dy[b + Y_X] = v
        dy[b + Y_V] = (f - ff) / P[P_MASS]
    else:
        dy[b + Y_X] = 0.0
        dy[b + Y_V] = 0.0
    dy[b + Y_SD] = 0.0  # sensors are filtered exactly at the end of each substep
    dy[b + Y_SE] = 0.0
    dy[b + Y_MIN] = 0.0
    dy[b + Y_MOUT] = q_ex + q_ld
    if n == 1:  # explicit valve flow
        dy[0] += q_in
        dy[b + Y_MIN] = q_in
    return q_imp, q_port, q_in


# --------------------------------------------------------------------------------------------
# one substep
# --------------------------------------------------------------------------------------------
# The hot loop: one IMEX step (see ``substep``). ``_nrt=False``: the substep allocates
# nothing, and without numba's runtime the array arguments of the inlined kernels are not reference-counted (atomic increments and
# decrements around every branch cost about a third of a substep). ``error_model="numpy"``
# everywhere: a division by zero gives inf/NaN, which the state check below reports, instead
# of a Python exception path in every division. ``fastmath={"contract"}`` only (fused
# multiply-adds, ~5 % faster): no "nnan"/"ninf" (the state check needs isfinite) and no "arcp"
# (x / 3 as x * 0.333... rounds the stage update unevenly and the mass balance drifts from
# 1e-15 to 1e-12 relative).
@njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def substep(y, P, d, h, k, y1, y2, p):
    """Advance by ``h`` [s] with a 3-stage IMEX Runge-Kutta step, then apply the events: valve
    commands coming due, stick/slip and end stops (Karnopp), sensor lag. Returns a status code.

    Explicit part: SSP-RK3 (Butcher form): everything but the valve and port flows.
    Implicit part (:func:`stage_rhs`): those two flows, with the diagonally implicit tableau
    ``IMEX_A*`` (first stage explicit) on the same abscissae 0, 1, 1/2 and the same weights
    1/6, 1/6, 2/3. Order 2 (3 for the explicit part alone); mass moves between cells by the same
    flows on both sides, so it is conserved to round-off. ``k``, ``y1``, ``y2``: work arrays of the
    state's length (``y1`` receives the first two stages' explicit rates summed, ``k`` the
    second's and then the third's, ``y2`` the stage state)."""
    t = d[D_T]
    ny = y.shape[0]
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    mode = int(d[D_MODE])
    v_old = y[b + Y_V]
    x_old = y[b + Y_X]
    z = y2

    # stage 1 (c = 0): the state itself
    s, se = valve_opening(d, P, t)
    qv1, qp1, _ = stage_rhs(t, s, se, y, P, mode, y1, p, 0.0, 0.0, 0.0)
    # stage 2 (c = 1): y + h k1 + h (a21 q1 + a22 q2)
    for i in range(ny):
        z[i] = y[i] + h * y1[i]
    c = h * IMEX_A21
    z[0] += c * qv1
    z[n - 1] -= c * qp1
    z[b + Y_MD] += c * qp1
    chain = P[P_LINE_MODEL] != 0.0 and n > 1
    if chain:  # the lumped line's joints: implicit, their flows in the face slots of the rates
        for j in range(n - 1):
            q = c * y1[n + j]
            z[j] -= q
            z[j + 1] += q
            k[n + j] = y1[n + j]  # the guess of stage 2
    s, se = valve_opening(d, P, t + h)
    qv2, qp2, _ = stage_rhs(t + h, s, se, z, P, mode, k, p, h * IMEX_A22, qv1, qp1)
    # stage 3 (c = 1/2): y + h/4 (k1 + k2) + h (a31 q1 + a32 q2 + a33 q3)
    c = h * IMEX_A31
    c2 = h * IMEX_A32
    if chain:  # the joints' implicit masses of stage 3 (p: scratch until stage_rhs)
        for j in range(n - 1):
            p[j] = c * y1[n + j] + c2 * k[n + j]
    for i in range(ny):
        y1[i] += k[i]
        z[i] = y[i] + 0.25 * h * y1[i]
    z[0] += c * qv1 + c2 * qv2
    if chain:  # (the guess of stage 3 is stage 2's flows, already in k)
        for j in range(n - 1):
            z[j] -= p[j]
            z[j + 1] += p[j]
    z[n - 1] -= c * qp1 + c2 * qp2
    z[b + Y_MD] += c * qp1 + c2 * qp2
    s, se = valve_opening(d, P, t + 0.5 * h)
    qv3, qp3, _ = stage_rhs(t + 0.5 * h, s, se, z, P, mode, k, p, h * IMEX_A33, qv2, qp2)
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

    # valve: advance the ramp, record a completed closing, pop due commands
    t_new = t + h
    s_before = _ramp(d[D_S], d[D_T_S], d[D_TARGET], t, P[P_RAMP])
    _pop_due_commands(d, P, t_new)
    s_now = _ramp(d[D_S], d[D_T_S], d[D_TARGET], t_new, P[P_RAMP])
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
        _piston_events(y, P, d, h, t, b, mode, x_old, v_old)
    return status


@njit(cache=True, error_model="numpy", inline="always")
def _piston_events(y, P, d, h, t, b, mode, x_old, v_old):
    """Stick/slip and end stops (Karnopp) at the end of a substep, then the sensor lag."""
    # a held piston keeps its exact position: RK3 rounding must not move it
    if mode != MODE_MOVING:
        y[b + Y_X] = x_old
        y[b + Y_V] = 0.0
    stroke = P[P_STROKE]
    fs = P[P_FS]
    pd, pe, vd, ve = chamber_pressures(y, P, b)
    f = (pd - pe) * P[P_AP]
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


# --------------------------------------------------------------------------------------------
# drivers
# --------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def record_row(y, P, d, out, q_in):
    """Write the recorded channels (layout ``R_*``) of the current state into ``out``."""
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


@njit(cache=True, error_model="numpy")
def supply_flow(y, P, d):
    """Mass flow from the supply into the line [kg/s] at the current state."""
    s, se = valve_opening(d, P, d[D_T])
    if s <= 0.0:
        return 0.0
    p0 = y[0] * P[P_R] * P[P_T] / P[NP]
    return flow_at(supply_pressure(P, d[D_T]), p0, s * P[P_CDA_VALVE], P[P_SQRT_T], P[P_SQRT_T],
                   P, P_OC)


def work_size(P):
    """Length of the work array that :func:`advance_ws` needs for parameters ``P``."""
    n = int(P[P_NCELLS])
    return 3 * (2 * n - 1 + NY) + n


@njit(cache=True, error_model="numpy")
def advance(y, P, d, t_end, rec, rec_dt, stop_on_arrival):
    """Advance to time ``t_end`` [s] in substeps of at most ``P[P_DT]``.

    If ``rec_dt > 0``, rows of ``rec`` (shape (m, NR)) are filled at times that are multiples of
    ``rec_dt`` (substeps are shortened to land on them); recording stops when ``rec`` is full.
    If ``stop_on_arrival``, returns as soon as the piston first reaches the extended end.
    Returns ``(status, rows_written)``.
    """
    w = np.empty(3 * y.shape[0] + int(P[P_NCELLS]))
    return advance_ws(y, P, d, t_end, rec, rec_dt, stop_on_arrival, w)


@njit(cache=True, error_model="numpy", _nrt=False)
def advance_ws(y, P, d, t_end, rec, rec_dt, stop_on_arrival, w):
    """:func:`advance` with a caller-owned work array ``w`` (length :func:`work_size`), so that a
    control loop allocates nothing."""
    ny = y.shape[0]
    n = int(P[P_NCELLS])
    k = w[0:ny]
    y1 = w[ny:2 * ny]
    y2 = w[2 * ny:3 * ny]
    p = w[3 * ny:3 * ny + n]
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
        st = substep(y, P, d, h, k, y1, y2, p)
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


@njit(cache=True, error_model="numpy", parallel=True)
def advance_batch(Y, Ps, Ds, commands, duration, status, W):
    """Give each plant ``i`` the command ``commands[i]`` and advance it by ``duration`` [s].

    ``Y`` (B, ny), ``Ps`` (B, np), ``Ds`` (B, nd) as in :mod:`layout`, ``W`` (B, work_size) work
    arrays; plants with a non-zero ``status[i]`` are skipped. Plants run in parallel (numba
    ``prange``)."""
    nb = Y.shape[0]
    for i in prange(nb):
        if status[i] == 0:
            status[i] = command_advance(Y[i], Ps[i], Ds[i], W[i], commands[i], duration, False)


@njit(cache=True, error_model="numpy")
def driving_side_energy(y, P):
    """Air potential energy [J] of the line cells and the driving chamber (thesis eq. 5.9)."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    RT = P[P_R] * P[P_T]
    pa = P[P_PA]
    e = 0.0
    for i in range(n):
        vol = P[NP + i]
        e += potential_energy(y[i] * RT / vol, vol, pa)
    pd, pe, vd, ve = chamber_pressures(y, P, b)
    e += potential_energy(pd, vd, pa)
    return e


@njit(cache=True, error_model="numpy")
def valve_closed(d, P):
    """True when the main valve is fully closed and no opening is pending."""
    s, se = valve_opening(d, P, d[D_T])
    if s > 0.0:
        return False
    for k in range(int(d[D_NQ])):
        if d[D_Q0 + 2 * k + 1] > 0.5:
            return False
    return True


@njit(cache=True, error_model="numpy")
def filled_energy(P, x):
    """Potential energy [J] of the driving side filled to the supply set-point with the piston
    at ``x`` [m] (the closed form of a conventional stroke)."""
    n = int(P[P_NCELLS])
    vol = P[P_V0D] + P[P_AP] * x
    for i in range(n):
        vol += P[NP + i]
    return potential_energy(P[P_PS], vol, P[P_PA])


@njit(cache=True, error_model="numpy")
def energy_wasted(y, P, d):
    """Energy [J] wasted if the return stroke began now (thesis 5.5-5.7): the driving side filled
    to supply pressure while the supply is (or will be) connected, else the trapped air."""
    b = 2 * int(P[P_NCELLS]) - 1
    if d[D_CMD] > 0.5 or not valve_closed(d, P):
        return filled_energy(P, y[b + Y_X])
    return driving_side_energy(y, P)


@njit(cache=True, error_model="numpy")
def max_drive_force(y, P):
    """Largest net force [N] the driving-side air can still push with if no more air comes in:
    line and driving chamber equalised, exhaust vented to ambient. A stuck piston whose
    ``max_drive_force`` is at most the breakaway friction can never move again."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    m = y[b + Y_MD]
    vol = P[P_V0D] + P[P_AP] * min(max(y[b + Y_X], 0.0), P[P_STROKE])
    for i in range(n):
        m += y[i]
        vol += P[NP + i]
    return (m * P[P_R] * P[P_T] / vol - P[P_PA]) * P[P_AP]


@njit(cache=True, error_model="numpy")
def total_air_mass(y, P):
    """Air mass in the line and both chambers [kg]."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    m = 0.0
    for i in range(n):
        m += y[i]
    return m + y[b + Y_MD] + y[b + Y_ME]
