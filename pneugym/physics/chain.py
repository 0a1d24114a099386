"""The implicit stage equation of the lumped line's orifice chain (thesis Appendix 2 line):
supply -> valve -> line cell 0 -> joint -> ... -> line cell n-1 -> port -> driving chamber.

With the lumped line every exchange of its cells is an orifice flow (thesis eqs. 4.1-4.3), and
the small cells make all of them stiff, so each IMEX stage (:mod:`pneugym.physics.stepping`)
solves the whole chain at once: Newton's method on its ``n + 1`` flows [kg/s] with a
tridiagonal Jacobian (Thomas algorithm). Every flow moves mass between two volumes, so mass is
conserved to round-off. Pressures absolute [Pa], masses [kg].
"""
from numba import njit

from .layout import NP, P_CDA_LINE, P_OC, P_R, P_SQRT_T, P_T, Y_MD
from .orifice import flow_deriv_fwd

#: Newton iterations at most in :func:`implicit_chain`
CHAIN_MAX_IT = 30
#: :func:`implicit_chain` stops when its last Newton correction is at most this fraction of the
#: largest flow of the chain: the convergence is quadratic, so the flows are then exact to
#: round-off (the chain is cheap: a few cells)
CHAIN_TOL = 1e-9


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
