"""Orifice mass flow (thesis eqs. 4.1-4.3, or ISO 6358), bidirectional and smooth through Δp = 0.

Thesis form: ``mdot = Cd A Cm p_up / sqrt(T_up)`` with ``Cm = 0.0404`` when choked
(``p_dn / p_up <= 0.528``) and ``Cm = sqrt(2γ/(R(γ-1)) (r^(2/γ) - r^((γ+1)/γ)))`` otherwise.
The choked constant is the subsonic formula at the critical ratio (0.04042; the thesis rounds to
0.0405), so the flow is continuous. ISO 6358: ``mdot = C ρ0 p_up sqrt(T0/T_up) sqrt(1 - ((r-b)/(1-b))²)``
with the sonic conductance ``C`` taken equal in the choked region (same ``Cd A``).
For ``r > 1 - lin`` the flow is the straight line from ``mdot(1 - lin)`` to 0 (laminar-like), which
keeps the explicit stepping stable near equal pressures.

The kernels take the constants as an array ``oc`` (see :func:`orifice_constants`) so that nothing
transcendental is recomputed in the hot loop.
"""
import math

import numpy as np
from numba import njit

R_CRIT = 0.528
# layout of the orifice-constant block
OC_GAMMA_INV = 0  # 1/γ
OC_KSUB = 1       # 2γ/(R(γ-1))
OC_MODEL = 2      # 0 thesis, 1 ISO 6358
OC_B = 3          # ISO critical ratio
OC_LIN = 4        # linear zone width (relative pressure drop)
OC_CM_STAR = 5    # choked flow parameter
OC_CM_LIN = 6     # flow parameter at r = 1 - lin
NOC = 7


@njit(cache=True, error_model="numpy", inline="always")
def _cm_thesis(r, g_inv, ksub):
    a = math.exp(math.log(r) * g_inv)  # r^(1/γ)
    ct = ksub * (a * a - r * a)
    return math.sqrt(ct) if ct > 0.0 else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def flow_parameter_at(r, c, o):
    """:func:`flow_parameter` with the constant block at ``c[o:o + NOC]``."""
    # one exit only: numba cannot prune the reference counting of ``c`` past early returns
    cm = c[o + OC_CM_STAR]
    if c[o + OC_MODEL] == 0.0:
        if r > R_CRIT:
            cm = _cm_thesis(r, c[o + OC_GAMMA_INV], c[o + OC_KSUB])
    else:
        b = c[o + OC_B]
        if r > b:
            z = (r - b) / (1.0 - b)
            cm = cm * math.sqrt(1.0 - z * z) if z < 1.0 else 0.0
    return cm


@njit(cache=True, error_model="numpy", inline="always")
def flow_parameter(r, oc):
    """Flow parameter ``Cm(r)`` for ``r = p_dn/p_up`` in (0, 1]: ``mdot = CdA p_up Cm / sqrt(T_up)``."""
    return flow_parameter_at(r, oc, 0)


@njit(cache=True, error_model="numpy")
def orifice_constants(gamma, R, model, b, lin):
    """The constant block ``oc`` used by :func:`mass_flow`."""
    oc = np.zeros(NOC)
    oc[OC_GAMMA_INV] = 1.0 / gamma
    oc[OC_KSUB] = 2.0 * gamma / (R * (gamma - 1.0))
    oc[OC_MODEL] = model
    oc[OC_B] = b
    oc[OC_LIN] = lin
    oc[OC_CM_STAR] = _cm_thesis(R_CRIT, oc[OC_GAMMA_INV], oc[OC_KSUB])
    oc[OC_CM_LIN] = 0.0
    oc[OC_CM_LIN] = flow_parameter(1.0 - lin, oc)
    return oc


@njit(cache=True, error_model="numpy", inline="always")
def flow_at(p_a, p_b, cda, sqrt_Ta, sqrt_Tb, c, o):
    """:func:`mass_flow` with the constant block at ``c[o:o + NOC]``: the plant's hot loop reads
    it from the parameter array ``P`` directly instead of making a view of it."""
    q = 0.0
    if cda > 0.0:
        if p_a >= p_b:
            pu, pd, sT, sgn = p_a, p_b, sqrt_Ta, 1.0
        else:
            pu, pd, sT, sgn = p_b, p_a, sqrt_Tb, -1.0
        r = pd / pu
        k = cda * pu / sT
        lin = c[o + OC_LIN]
        if r > 1.0 - lin:
            q = sgn * k * c[o + OC_CM_LIN] * (1.0 - r) / lin
        else:
            q = sgn * k * flow_parameter_at(r, c, o)
    return q


@njit(cache=True, error_model="numpy", inline="always")
def laminar_flow(p_a, p_b, k, mu, RT):
    """Signed isothermal laminar (Hagen-Poiseuille) mass flow a -> b [kg/s] through capillaries
    of conductance ``k`` (``pi d^4 / (128 l)`` summed over the pores) [m³]:
    ``k (p_a² - p_b²) / (2 mu R T)``; the gas takes the wall's temperature (``R T`` [J/kg] at
    ambient, ``mu`` [Pa s] the viscosity there). Valid while each pore's flow stays laminar."""
    return k * (p_a * p_a - p_b * p_b) / (2.0 * mu * RT)


@njit(cache=True, error_model="numpy", inline="always")
def mass_flow(p_a, p_b, cda, sqrt_Ta, sqrt_Tb, oc):
    """Signed mass flow a -> b [kg/s] through effective area ``cda`` = Cd·A [m²].

    ``sqrt_Ta``, ``sqrt_Tb``: square roots of the temperatures [K] on each side."""
    return flow_at(p_a, p_b, cda, sqrt_Ta, sqrt_Tb, oc, 0)


@njit(cache=True, error_model="numpy")
def linear_conductance(p_up, cda, T, oc):
    """Largest |d mdot / d p_dn| [kg/(s Pa)] of the orifice at upstream pressure ``p_up``."""
    return cda / math.sqrt(T) * oc[OC_CM_LIN] / oc[OC_LIN]


@njit(cache=True, error_model="numpy", inline="always")
def flow_deriv_fwd(pu, pd, cda, sqrt_Tu, c, o):
    """Forward flow ``pu -> pd`` (``pu >= pd``) [kg/s] as :func:`flow_at` computes it, and its
    partial derivatives ``(q, dq/dpu, dq/dpd)`` [kg/s, kg/(s Pa)], the temperature held fixed.
    :func:`implicit_flow` iterates with them."""
    q = 0.0
    d_up = 0.0
    d_dn = 0.0
    if cda > 0.0:
        r = pd / pu
        kc = cda / sqrt_Tu
        lin = c[o + OC_LIN]
        cm = c[o + OC_CM_STAR]
        dcm = 0.0  # dCm/dr
        if r > 1.0 - lin:
            g = c[o + OC_CM_LIN] / lin
            cm = g * (1.0 - r)
            dcm = -g
        elif c[o + OC_MODEL] == 0.0:
            if r > R_CRIT:
                g_inv = c[o + OC_GAMMA_INV]
                ksub = c[o + OC_KSUB]
                a = math.exp(math.log(r) * g_inv)  # r^(1/γ)
                ct = ksub * (a * a - r * a)
                if ct > 0.0:
                    cm = math.sqrt(ct)
                    # d(a² - r a)/dr = 2 a²/(γ r) - a (1 + 1/γ)
                    dcm = ksub * (2.0 * g_inv * a * a / r - a * (1.0 + g_inv)) / (2.0 * cm)
                else:
                    cm = 0.0
        else:
            b = c[o + OC_B]
            if r > b:
                z = (r - b) / (1.0 - b)
                if z < 1.0:
                    w = math.sqrt(1.0 - z * z)
                    dcm = -cm * z / (w * (1.0 - b))
                    cm = cm * w
                else:
                    cm = 0.0
        # q = kc pu Cm(pd/pu): d/dpu = kc (Cm - r Cm'), d/dpd = kc Cm'
        q = kc * pu * cm
        d_up = kc * (cm - r * dcm)
        d_dn = kc * dcm
    return q, d_up, d_dn


#: Newton iterations at most in :func:`implicit_flow` (from a guess one stage old, 1-2 do)
IMPLICIT_MAX_IT = 16
#: relative size of the last Newton correction at which :func:`implicit_flow` stops. The
#: convergence is quadratic: the residual left is of the order of its square (measured: at most
#: 1e-7 of the flow along extensions with cut-offs at 1.5 and 2.5 bar; 1e-7 instead changes the
#: stroke times and energies by < 1e-5 relative and costs ~1.3x the substep)
IMPLICIT_TOL = 1e-3


@njit(cache=True, error_model="numpy", inline="always")
def implicit_flow(pa, pb, ka, kb, hg, cda, sqrt_Ta, sqrt_Tb, c, o, q0):
    """The flow ``q`` a -> b [kg/s] that solves the implicit stage equation
    ``q = flow(pa - hg ka q, pb + hg kb q)``: the flow at the pressures that it leaves behind
    after moving ``hg q`` of mass between two volumes (``ka``, ``kb`` = dp/dm of each side
    [Pa/kg], 0 for a reservoir; ``hg`` = step x implicit coefficient [s]); ``q0``: a guess.

    The root lies between 0 and ``qh``, the solution of the same equation with the linear-zone
    law extended to any pressure drop (the flow law lies below that line), and the pressures
    keep their order for every ``hg`` (no overshoot). ``qh`` is the root when its pressures lie
    in the linear zone. Otherwise Newton's method from the guess, kept inside ``[0, qh]``: along
    the path the flow is concave in ``q`` (a perspective of the concave ``Cm(r)``, linear zone
    included), so the residual is convex and the iterates converge monotonically after the first."""
    q = 0.0
    if cda > 0.0:
        sgn = 1.0
        if pa < pb:  # solve b -> a
            pa, pb, ka, kb, sqrt_Ta, sqrt_Tb, q0, sgn = pb, pa, kb, ka, sqrt_Tb, sqrt_Ta, -q0, -1.0
        lin = c[o + OC_LIN]
        g = cda * c[o + OC_CM_LIN] / (lin * sqrt_Ta)
        qh = g * (pa - pb) / (1.0 + hg * g * (ka + kb))
        q = qh
        a = pa - hg * ka * qh
        if a - (pb + hg * kb * qh) > lin * a:  # outside the linear zone
            q = min(max(q0, 0.0), qh)
            for _ in range(IMPLICIT_MAX_IT):
                a = pa - hg * ka * q
                f, fa, fb = flow_deriv_fwd(a, pb + hg * kb * q, cda, sqrt_Ta, c, o)
                dq = (q - f) / (1.0 + hg * (fa * ka - fb * kb))
                q = min(max(q - dq, 0.0), qh)
                if abs(dq) <= IMPLICIT_TOL * q:
                    break
        q *= sgn
    return q
