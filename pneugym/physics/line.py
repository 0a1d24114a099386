"""Supply line: 1-D isothermal compressible flow on a staggered grid (thesis eqs. 2.86-2.89, 4.28-4.31).

Cells hold air mass ``m_i`` (pressure ``p_i = m_i R T / V_i``); faces hold mass flow ``q_j``
[kg/s]. Continuity ``dm_i/dt = q_i - q_{i+1}``; momentum at an interior face (flux form)::

    dq/dt = A (p_L - p_R)/dx - (F_R - F_L)/dx + A (τ_R - τ_L)/dx - f q|q| / (2 d ρ A)

with ``F = q_c² / (ρ A)`` the momentum flux at cell centres (``q_c`` = mean of the cell's faces),
``τ = (4/3) μ du/dx`` the normal viscous stress of the thesis, and the wall friction factor ``f``
laminar (64/Re) below Re 2300, Blasius (0.3164 Re^-0.25) above 4000, linear in between,
scaled by ``n/(n-1)`` so that the interior faces carry the friction of the whole tube.
Central differences throughout: 2nd order in space; the time integrator (SSP-RK3) is 3rd order.
The boundary faces (valve, port) carry orifice flows that the caller computes.

The lumped option (thesis Appendix 2) joins the same cells by orifices of the tube's area.
"""
import math

from numba import njit

from .orifice import flow_at


@njit(cache=True, error_model="numpy", inline="always")
def friction_factor(re):
    """Darcy friction factor of a smooth tube at Reynolds number ``re`` (>= 0)."""
    if re < 1e-12:
        return 0.0
    if re <= 2300.0:
        return 64.0 / re
    fb = 0.3164 / math.sqrt(math.sqrt(re))
    if re >= 4000.0:
        return fb
    w = (re - 2300.0) / 1700.0
    f4000 = 0.3164 / math.sqrt(math.sqrt(4000.0))
    return (1.0 - w) * (64.0 / 2300.0) + w * f4000


@njit(cache=True, error_model="numpy", inline="always")
def wall_friction(q, inv_rho, A, d, mu):
    """Wall-friction term of the face momentum equation [kg/s²] (sign opposes ``q``);
    ``inv_rho`` is the specific volume [m³/kg] at the face."""
    aq = abs(q)
    re = aq * d / (A * mu)
    if re <= 2300.0:  # laminar in closed form: 32 μ q / (ρ d²)
        return 32.0 * mu * q * inv_rho / (d * d)
    return friction_factor(re) * q * aq * inv_rho / (2.0 * d * A)


@njit(cache=True, error_model="numpy", inline="always")
def _art_visc(dq_cell, inv_rho, inv_a, cq):
    """Artificial-viscosity pressure [Pa] of a cell whose face flows differ by ``dq_cell``."""
    if cq <= 0.0 or dq_cell >= 0.0:
        return 0.0
    du = dq_cell * inv_rho * inv_a
    return cq * du * du / inv_rho


@njit(cache=True, error_model="numpy", inline="always")
def fd_rhs(y, q_in, q_out, p, RT, A, dx, d, mu, cq, dy, n):
    """Right-hand side of the FD line.

    ``y``: the state, laid out as in the plant: cell masses ``y[0..n-1]``, then the interior face
    flows ``y[n + j]``, j = 0..n-2 (face between cell j and j+1); ``p``: cell pressures [Pa];
    ``RT`` [J/kg] (isothermal line, 1/ρ = RT/p); ``q_in``/``q_out``: boundary flows into cell 0
    and out of cell n-1 [kg/s]. Writes ``dy[0..n-1]`` (continuity) and ``dy[n..2n-2]`` (momentum).
    ``cq``: von Neumann-Richtmyer quadratic artificial viscosity, a pressure ``cq ρ Δu²`` added in
    compressing cells (``Δu < 0`` across the cell); O(dx²) where the flow is smooth, it keeps
    the scheme stable through the shocks of a sudden closure.
    """
    fd_continuity(y, q_in, q_out, dy, n)
    fd_momentum(y, q_in, q_out, p, RT, A, dx, d, mu, cq, dy, n)


@njit(cache=True, error_model="numpy", inline="always")
def fd_continuity(y, q_in, q_out, dy, n):
    """Continuity part of :func:`fd_rhs`: writes ``dy[0..n-1]``."""
    for i in range(n):
        qa = q_in if i == 0 else y[n + i - 1]
        qb = q_out if i == n - 1 else y[n + i]
        dy[i] = qa - qb


@njit(cache=True, error_model="numpy", inline="always")
def fd_momentum(y, q_in, q_out, p, RT, A, dx, d, mu, cq, dy, n):
    """Momentum part of :func:`fd_rhs`: writes ``dy[n..2n-2]``; the boundary flows ``q_in``,
    ``q_out`` enter the cell-centre fluxes and stresses of the end cells."""
    if n > 1:  # (no early return: it would keep numba's reference counting in the hot loop)
        inv_a = 1.0 / A
        inv_dx = 1.0 / dx
        # the n - 1 interior faces carry the wall friction of the whole length n dx (the end
        # half-cells lie between a face and an orifice, where no momentum equation is solved)
        fscale = n / (n - 1.0)
        c43 = (4.0 / 3.0) * mu * inv_a * inv_dx
        # specific volume from the pressure (isothermal: 1/ρ = RT/p), cell-centre flux and stress
        inv_rho_l = RT / p[0]
        qa = q_in
        qb = y[n]
        qc = 0.5 * (qa + qb)
        flux_l = qc * qc * inv_rho_l * inv_a
        tau_l = c43 * (qb - qa) * inv_rho_l
        pq_l = p[0] + _art_visc(qb - qa, inv_rho_l, inv_a, cq)
        for j in range(n - 1):
            i = j + 1
            qa = y[n + j]
            qb = q_out if i == n - 1 else y[n + i]
            inv_rho_r = RT / p[i]
            qc = 0.5 * (qa + qb)
            flux_r = qc * qc * inv_rho_r * inv_a
            tau_r = c43 * (qb - qa) * inv_rho_r
            pq_r = p[i] + _art_visc(qb - qa, inv_rho_r, inv_a, cq)
            dy[n + j] = (A * (pq_l - pq_r) - (flux_r - flux_l) + A * (tau_r - tau_l)) * inv_dx \
                - fscale * wall_friction(qa, 0.5 * (inv_rho_l + inv_rho_r), A, d, mu)
            flux_l = flux_r
            tau_l = tau_r
            pq_l = pq_r
            inv_rho_l = inv_rho_r


@njit(cache=True, error_model="numpy", inline="always")
def lumped_rhs(p, q_in, q_out, cda, sqrt_T, c, o, dy, n):
    """Right-hand side of the lumped line: cells joined by orifices of effective area ``cda``
    (orifice constants at ``c[o:o + NOC]``). Writes ``dy[0..n-1]``."""
    qa = q_in
    for i in range(n):
        if i == n - 1:
            qb = q_out
        else:
            qb = flow_at(p[i], p[i + 1], cda, sqrt_T, sqrt_T, c, o)
        dy[i] = qa - qb
        qa = qb


@njit(cache=True, error_model="numpy", inline="always")
def cell_momentum_terms(qa, qb, p, dpdq, inv_a, c43, cq, RT):
    """A line cell's part of the face momentum, ``G = A (p + p_av - τ) + F`` [N] (pressure
    with artificial viscosity, convective flux ``F = q_c² / (ρ A)``, normal viscous stress
    ``τ``), and its derivatives with respect to the cell's inflow ``qa`` and outflow ``qb``
    [kg/s] through the cell's mass in an implicit stage (``dpdq`` = hg dp/dm [Pa s/kg]).
    Returns ``(G, dG/dqa, dG/dqb, 1/ρ)``. The same terms as :func:`fd_momentum`, whose face
    rate is ``(G_left - G_right) / dx`` less the wall friction (there summed in another order,
    which the explicit line's results keep; their equality to round-off is a test)."""
    ir = RT / p
    qc = 0.5 * (qa + qb)
    dq = qb - qa
    flux = qc * qc * ir * inv_a
    tau = c43 * dq * ir
    av = _art_visc(dq, ir, inv_a, cq)
    g = (p + av - tau) / inv_a + flux
    # d/dp of each term (1/ρ = RT/p), times dp/dqa = dpdq (dp/dqb = -dpdq)
    dgp = 1.0 / inv_a - (flux + (av - tau) / inv_a) / p
    dflux = qc * ir * inv_a
    dtau = c43 * ir / inv_a
    dav = 0.0
    if av != 0.0:
        dav = 2.0 * av / dq / inv_a
    return g, dgp * dpdq + dflux + dtau - dav, -dgp * dpdq + dflux - dtau + dav, ir
