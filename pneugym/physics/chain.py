"""The implicit stage equation of the lumped line's orifice chain (thesis Appendix 2 line):
supply -> valve -> line cell 0 -> joint -> ... -> line cell n-1 -> port -> driving chamber.

With the lumped line every exchange of its cells is an orifice flow (thesis eqs. 4.1-4.3), and
the small cells make all of them stiff, so each IMEX stage (:mod:`pneugym.physics.stepping`)
solves the whole chain at once: Newton's method on its ``n + 1`` flows [kg/s] with a
tridiagonal Jacobian (Thomas algorithm). Every flow moves mass between two volumes, so mass is
conserved to round-off. Pressures absolute [Pa], masses [kg].
"""
from numba import njit

from .layout import (
    NP, P_AV, P_CDA_LINE, P_DX, P_LINE_A, P_LINE_D, P_MU, P_OC, P_R, P_SQRT_T, P_T, Y_MD,
)
from .line import cell_momentum_terms, wall_friction
from .orifice import flow_deriv_fwd

#: Newton iterations at most in :func:`implicit_chain`
CHAIN_MAX_IT = 30
#: :func:`implicit_chain` stops when its last Newton correction is at most this fraction of the
#: largest flow of the chain: the convergence is quadratic, so the flows are then exact to
#: round-off (the chain is cheap: a few cells)
CHAIN_TOL = 1e-9
#: Newton iterations at most in :func:`implicit_fd_line`
FD_MAX_IT = 30
#: :func:`implicit_fd_line` stops when its last correction is at most this fraction of the
#: largest flow plus :data:`FD_ATOL`
FD_TOL = 1e-6
#: ... the absolute part [kg/s] (flows near zero: a line at rest)
FD_ATOL = 1e-10


@njit(cache=True, error_model="numpy", inline="always")
def signed_flow_deriv(pa, pb, cda, sTa, sTb, c, o):
    """Signed orifice flow a -> b [kg/s] and its partial derivatives ``(q, dq/dpa, dq/dpb)``
    [kg/(s Pa)], in either direction: :func:`pneugym.physics.orifice.flow_deriv_fwd` (thesis
    eqs. 4.1-4.3) from the higher to the lower pressure."""
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
        f, fa, fb = signed_flow_deriv(ps, p_dn, cda_v, sT, sT, P, P_OC)
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
            f, fa, fb = signed_flow_deriv(p_up, p_dn, cda_l, sT, sT, P, P_OC)
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
        f, fa, fb = signed_flow_deriv(p_up, p_d, cda_p, sT, sTd, P, P_OC)
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


# Compiled once, not inlined into the stage (as ``stage_rhs`` is not into the substep): the
# kernels' cold compile took 65 s with it inlined, 54-56 s so, 36 s before it (2-core machine).
@njit(cache=True, error_model="numpy", _nrt=False, fastmath={"contract"})
def implicit_fd_line(z, P, n, b, hg, ps, cda_v, cda_p, kd, sTd, qv, qp, s, dy):
    """The implicit stage equation of the FD line solved whole (``SolverParams(line_scheme=
    "implicit")``): valve, continuity and momentum of every cell and face, port.

    Unknowns: the ``n + 1`` flows ``F`` [kg/s] (row 0 the valve flow, rows 1..n-1 the face flows
    at the stage, row n the port flow). The cells hold ``z_i + hg (F_i - F_(i+1))``, the driving
    chamber ``z_md + hg F_n``; the valve and port rows are the orifice laws at those pressures,
    each face row ``F_r = z_q + hg mom_r`` with the whole momentum equation of
    :func:`pneugym.physics.line.fd_momentum` (pressure, convective flux, viscous stress,
    artificial viscosity, wall friction). Newton's method on a tridiagonal Jacobian (Thomas
    algorithm), exact but for the wall friction's
    (:func:`pneugym.physics.line.cell_momentum_terms`). Converged when the correction is below
    ``FD_TOL`` of the largest flow plus ``FD_ATOL``; a step that would leave a non-positive mass
    is halved.

    ``z``: the stage's starting state; on return its line cells, faces and driving-chamber mass
    hold the stage state. ``dy[n..b-1]`` receives the faces' implicit rates ``mom_r``. ``s``:
    scratch of length >= 5 (n + 1). Returns ``(qv, qp)``.
    """
    RT = P[P_R] * P[P_T]
    sT = P[P_SQRT_T]
    A = P[P_LINE_A]
    inv_a = 1.0 / A
    inv_dx = 1.0 / P[P_DX]
    d_t = P[P_LINE_D]
    mu = P[P_MU]
    cq = P[P_AV]
    c43 = (4.0 / 3.0) * mu * inv_a * inv_dx
    fscale = n / (n - 1.0)
    m1 = n + 1
    F = s[0:m1]
    cp = s[m1:2 * m1]
    dp = s[2 * m1:3 * m1]
    mass = s[3 * m1:4 * m1]
    kk = s[4 * m1:5 * m1]
    md0 = z[b + Y_MD]
    F[0] = qv
    for j in range(n - 1):
        F[j + 1] = z[n + j]
    F[n] = qp
    for i in range(n):
        kk[i] = RT / P[NP + i]
    for _ in range(FD_MAX_IT):
        for i in range(n):
            mass[i] = z[i] + hg * (F[i] - F[i + 1])
        # row 0: supply (reservoir) -> cell 0
        p_l = kk[0] * mass[0]
        f, fa, fb = signed_flow_deriv(ps, p_l, cda_v, sT, sT, P, P_OC)
        diag = 1.0 - hg * fb * kk[0]
        cp[0] = hg * fb * kk[0] / diag
        dp[0] = (F[0] - f) / diag
        scale = abs(F[0])
        # cell 0's terms for the first face row
        g_l, ga_l, gb_l, ir_l = cell_momentum_terms(F[0], F[1], p_l, kk[0] * hg, inv_a, c43, cq, RT)
        for r in range(1, n):
            p_r = kk[r] * mass[r]
            g_r, ga_r, gb_r, ir_r = cell_momentum_terms(F[r], F[r + 1], p_r, kk[r] * hg, inv_a,
                                                        c43, cq, RT)
            fr = fscale * wall_friction(F[r], 0.5 * (ir_l + ir_r), A, d_t, mu)
            mom = (g_l - g_r) * inv_dx - fr
            # friction's derivative: laminar exact, turbulent its secant doubled
            dfr = 0.0
            if F[r] != 0.0:
                dfr = fr / F[r]
                if abs(F[r]) * d_t * inv_a / mu > 2300.0:
                    dfr *= 2.0
            a_r = -hg * ga_l * inv_dx
            diag = 1.0 - hg * ((gb_l - ga_r) * inv_dx - dfr) - a_r * cp[r - 1]
            cp[r] = hg * gb_r * inv_dx / diag
            dp[r] = (F[r] - z[n + r - 1] - hg * mom - a_r * dp[r - 1]) / diag
            scale = max(scale, abs(F[r]))
            p_l = p_r
            g_l, gb_l, ga_l, ir_l = g_r, gb_r, ga_r, ir_r
        # row n: cell n-1 -> driving chamber
        f, fa, fb = signed_flow_deriv(p_l, kd * (md0 + hg * F[n]), cda_p, sT, sTd, P, P_OC)
        a_r = -hg * fa * kk[n - 1]
        diag = 1.0 + hg * (fa * kk[n - 1] - fb * kd) - a_r * cp[n - 1]
        dp[n] = (F[n] - f - a_r * dp[n - 1]) / diag
        scale = max(scale, abs(F[n]))
        # back substitution: the corrections into dp
        dmax = abs(dp[n])
        for r in range(n - 1, -1, -1):
            dp[r] -= cp[r] * dp[r + 1]
            dmax = max(dmax, abs(dp[r]))
        # damping: a volume with a positive mass keeps one
        lam = 1.0
        for _h in range(60):
            ok = md0 + hg * (F[n] - lam * dp[n]) > 0.0 or md0 + hg * F[n] <= 0.0
            for i in range(n):
                m_new = z[i] + hg * ((F[i] - lam * dp[i]) - (F[i + 1] - lam * dp[i + 1]))
                if m_new <= 0.0 < mass[i]:
                    ok = False
            if ok:
                break
            lam *= 0.5
        for r in range(m1):
            F[r] -= lam * dp[r]
        if dmax <= FD_TOL * scale + FD_ATOL:
            break
    for i in range(n):
        z[i] += hg * (F[i] - F[i + 1])
    for j in range(n - 1):
        dy[n + j] = (F[j + 1] - z[n + j]) / hg
        z[n + j] = F[j + 1]
    z[b + Y_MD] = md0 + hg * F[n]
    return F[0], F[n]
