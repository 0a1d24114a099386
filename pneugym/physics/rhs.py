"""The plant's right-hand side: every equation of the model assembled on the packed state
(layouts in :mod:`pneugym.physics.layout`), and the implicit part of each IMEX stage.

For line cells ``i``, faces ``j`` and the chambers (``q_v`` valve, ``q_p`` driving port, ``q_ex``
exhaust path, ``q_ld``/``q_lp`` leaks: orifice flows [kg/s], thesis eqs. 4.1-4.3; ``q_ld`` adds a
laminar leak's, :func:`pneugym.physics.orifice.laminar_flow`)::

    dm_i/dt  = q_i - q_(i+1)                      line continuity (q_0 = q_v, q_n = q_p)
    dq_j/dt  = momentum of the FD line             :mod:`pneugym.physics.line` (eqs. 2.86-2.89)
    dm_d/dt  = q_p - q_ld - q_lp                  driving chamber
    dm_e/dt  = q_lp - q_ex                        exhaust chamber
    dT/dt    = chamber energy equation            only with heat transfer (P_TAU_TH > 0)
    dx/dt    = v,   (M + Mo) dv/dt = (p_d - p_e) A_p - F_f     while the piston moves
    dm_in/dt = q_v,   dm_out/dt = q_ex + q_ld     cumulative supply and vented mass

with ``p = m R T / V`` everywhere (:func:`pneugym.physics.cylinder.chamber_pressures` for the
chambers). SI units, absolute pressures. Stick/slip and end stops are events between substeps
(:mod:`pneugym.physics.events`), not part of the right-hand side.
"""
import math

from numba import njit

from .chain import implicit_chain, implicit_fd_line
from .cylinder import (
    chamber_dT, chamber_pressures, cushion_factor, enthalpy_flow, friction_force, piston_force,
)
from .layout import (
    MODE_MOVING, NP, P_AE, P_AP, P_AV, P_CDA_EXH, P_CDA_LEAK_D, P_CDA_LEAK_P, P_CDA_LINE, P_CDA_PORT,
    P_CDA_VALVE, P_CUSH_FD, P_CUSH_FE, P_CUSH_LEN, P_CUSH_RAMP, P_DX, P_FC, P_GAMMA, P_KV,
    P_LINE_A, P_LINE_D, P_LINE_MODEL, P_MASS, P_MU, P_NCELLS, P_OC, P_PA, P_R, P_SQRT_T,
    P_KLAM_LEAK_D, P_STRIB_F, P_STRIB_V, P_STROKE, P_T, P_TAU_TH, Y_MD, Y_ME, Y_MIN, Y_MOUT, Y_SD, Y_SE, Y_TD,
    Y_TE, Y_V, Y_X,
)
from .line import fd_continuity, fd_momentum, lumped_rhs
from .orifice import flow_at, implicit_flow, laminar_flow
from .valve import supply_pressure, valve_opening


# Compiled once, not inlined into the substep: numba inlines ``inline="always"`` at its own IR
# level, typing each inlined body again at every call site, and the substep's three stages made
# a cold compile take over 12 minutes (about 50 s this way). Without the runtime (``_nrt=False``)
# its array arguments are not reference-counted, and with the substep's ``fastmath`` flags LLVM
# gives the substep the same results to the last bit.
@njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def stage_rhs(tau, s, se, y, P, mode, dy, p, hg, qv0, qp0, vdir):
    """One stage of the IMEX substep: the implicit part, then the explicit right-hand side.

    The implicit part is the port flow from the last line cell into the driving chamber and the
    supply flow through the main valve into line cell 0: the stiffest exchanges (small line cells
    behind orifices; the port's limited the explicit substep to 274 µs, the valve's to 606 µs).
    With ``hg = h a_ii > 0`` [s] each solves its stage equation ``q = flow(state + hg q)`` with
    :func:`pneugym.physics.orifice.implicit_flow` (exact in the orifices' linear zone, Newton
    from the guesses ``qv0``, ``qp0`` [kg/s] outside it), port first, and ``y`` is updated in
    place to the stage state (cell 0, cell n-1 and the driving-chamber mass). With one line cell
    the valve flow stays explicit (it is then evaluated at the stage state). With the lumped line
    of more than one cell, valve, joints and port are solved together
    (:func:`pneugym.physics.chain.implicit_chain`; the joints' guesses and flows in
    ``dy[n..b-1]``). With the implicit FD line (``P_LINE_MODEL`` 2) the whole line is solved
    with them (:func:`pneugym.physics.chain.implicit_fd_line`; the faces' momentum in
    ``dy[n..b-1]``, ``p[n:]`` its scratch). ``hg = 0``: no implicit step, the flows at ``y``.

    Then ``dy`` receives every other term at the stage state: the line without the implicit flows
    in the continuity of its end cells, the chambers without the port flow in the driving-chamber
    mass, the piston; the implicit flows enter the line momentum (end-cell fluxes) and the
    chamber energy equation. ``dy[b + Y_MIN]`` holds only an explicit valve flow.
    ``vdir`` (+1, -1; 0: none): the substep's direction of motion, which the sliding friction
    keeps opposing in a stage whose velocity has crossed zero (the implicit FD line's long
    substeps; the reversal is then the stick event at the substep's end).
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
    chain = P[P_LINE_MODEL] == 1.0 and n > 1  # lumped line: the whole orifice chain is implicit
    fdi = P[P_LINE_MODEL] == 2.0  # FD line solved implicitly whole (set only with n > 1)
    if hg > 0.0 and fdi:
        # valve, cells, faces and port together; the faces' implicit rates into dy[n..b-1]
        kd = R * Td / vd
        ps = supply_pressure(P, tau) if s > 0.0 else P[P_PA]
        q_in, q_port = implicit_fd_line(y, P, n, b, hg, ps, cda_v, cda_p, kd, sTd, qv0, qp0,
                                        p[n:], dy)
        for i in range(n):
            p[i] = y[i] * RT / P[NP + i]
        pd = y[b + Y_MD] * R * Td / vd
        q_imp = q_in
    elif hg > 0.0 and chain:
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
    if P[P_KLAM_LEAK_D] > 0.0:
        q_ld += laminar_flow(pd, pa, P[P_KLAM_LEAK_D], P[P_MU], RT)
    q_lp = flow_at(pd, pe, P[P_CDA_LEAK_P], sTd, sTe, P, P_OC)

    # line (the valve and port flows are left out of the end cells' continuity)
    if P[P_LINE_MODEL] == 0.0:
        fd_continuity(y, 0.0, 0.0, dy, n)
        fd_momentum(y, q_in, q_port, p, RT, P[P_LINE_A], P[P_DX], P[P_LINE_D], P[P_MU], P[P_AV],
                    dy, n)
    elif fdi:  # every term of the line is implicit; dy[n..b-1] holds the faces' momentum
        if hg == 0.0:
            fd_momentum(y, q_in, q_port, p, RT, P[P_LINE_A], P[P_DX], P[P_LINE_D], P[P_MU],
                        P[P_AV], dy, n)
        for i in range(n):
            dy[i] = 0.0
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
        dy[b + Y_TE] = chamber_dT(y[b + Y_ME], Te, pe, -P[P_AE] * vmove, he, cv, T, tau_th)
    else:
        dy[b + Y_TD] = 0.0
        dy[b + Y_TE] = 0.0

    # piston
    if mode == MODE_MOVING:
        f = piston_force(pd, pe, P)
        vf = v
        if vdir != 0.0 and v * vdir <= 0.0:  # crossed zero within the substep: keep its direction
            vf = vdir * max(abs(v), 1e-300)
        ff = friction_force(vf, f, P[P_FC], P[P_KV], P[P_STRIB_F], P[P_STRIB_V])
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


@njit(cache=True, error_model="numpy", inline="always")
def rhs_valve(tau, s, se, y, P, mode, dy, p):
    """:func:`rhs` with the main-valve and exhaust-path openings ``s``, ``se`` [0, 1] given:
    :func:`stage_rhs` without an implicit step (``hg = 0``), its valve, port and lumped-joint
    flows added back into ``dy``, so that ``dy`` is the whole right-hand side."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    q_imp, q_port, q_in = stage_rhs(tau, s, se, y, P, mode, dy, p, 0.0, 0.0, 0.0, 0.0)
    dy[0] += q_imp
    dy[n - 1] -= q_port
    dy[b + Y_MD] += q_port
    dy[b + Y_MIN] += q_imp
    if P[P_LINE_MODEL] == 1.0 and n > 1:  # the lumped line's joint flows
        for j in range(n - 1):
            q = dy[n + j]
            dy[j] -= q
            dy[j + 1] += q
            dy[n + j] = 0.0
    elif P[P_LINE_MODEL] == 2.0:  # the implicit FD line's continuity
        for j in range(n - 1):
            q = y[n + j]
            dy[j] -= q
            dy[j + 1] += q
    return q_in


@njit(cache=True, error_model="numpy")
def rhs(tau, y, P, d, mode, dy, p):
    """The whole right-hand side ``dy = dy/dt`` (SI units per s, layout ``y``) at time ``tau`` [s]
    for piston ``mode`` held fixed; ``p`` (n) receives the line-cell pressures [Pa]. Returns the
    supply flow [kg/s]. Used for analysis (Jacobians, ``solve_ivp``); the substep calls
    :func:`stage_rhs`."""
    s, se = valve_opening(d, P, tau)
    return rhs_valve(tau, s, se, y, P, mode, dy, p)
