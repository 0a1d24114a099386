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
def mass_flow(p_a, p_b, cda, sqrt_Ta, sqrt_Tb, oc):
    """Signed mass flow a -> b [kg/s] through effective area ``cda`` = Cd·A [m²].

    ``sqrt_Ta``, ``sqrt_Tb``: square roots of the temperatures [K] on each side."""
    return flow_at(p_a, p_b, cda, sqrt_Ta, sqrt_Tb, oc, 0)


@njit(cache=True, error_model="numpy")
def linear_conductance(p_up, cda, T, oc):
    """Largest |d mdot / d p_dn| [kg/(s Pa)] of the orifice at upstream pressure ``p_up``."""
    return cda / math.sqrt(T) * oc[OC_CM_LIN] / oc[OC_LIN]
