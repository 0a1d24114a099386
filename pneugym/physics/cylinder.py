"""Double-acting cylinder: chamber volumes and pressures, end cushions, friction, chamber energy
equation.

Thesis 3.4, 5.6, 6.1-6.2: ``(M + Mo) dv/dt = F - F_f`` with the drive force :func:`piston_force`
(``(p_drive - p_exhaust) A_p`` for the thesis's double-rod, horizontal cylinder); the piston stays
stuck while ``|F| <= Fs`` (Karnopp), then ``F_f = sign(v) (C + Kv |v|)`` plus the optional
Stribeck term. The stick/slip and end-stop logic is in :mod:`pneugym.physics.events`.
"""
import math

from numba import njit

from .layout import (
    P_AE, P_AP, P_FLOAD, P_PA, P_R, P_STROKE, P_V0D, P_V0E, Y_MD, Y_ME, Y_TD, Y_TE, Y_X,
)


@njit(cache=True, error_model="numpy", inline="always")
def chamber_pressures(y, P, b):
    """Driving and exhaust chamber pressures [Pa] and volumes [m³] for state ``y`` (``b = 2n - 1``
    the offset of the chamber states): the ideal gas law ``p = m R T / V`` with

        V_d = V0_d + A_d x,    V_e = V0_e + A_e (stroke - x),    x clipped to [0, stroke]

    (``A_d``, ``A_e``: the driving and exhaust piston faces). Returns ``(p_d, p_e, V_d, V_e)``."""
    x = min(max(y[b + Y_X], 0.0), P[P_STROKE])
    vd = P[P_V0D] + P[P_AP] * x
    ve = P[P_V0E] + P[P_AE] * (P[P_STROKE] - x)
    R = P[P_R]
    return y[b + Y_MD] * R * y[b + Y_TD] / vd, y[b + Y_ME] * R * y[b + Y_TE] / ve, vd, ve


@njit(cache=True, error_model="numpy", inline="always")
def piston_force(pd, pe, P):
    """Net force [N] on the piston along the stroke's motion, friction aside::

        F = p_d A_d - p_e A_e + p_a (A_e - A_d) + F_load
          = (p_d - p_e) A_d + (p_a - p_e) (A_e - A_d) + F_load

    ambient pressure ``p_a`` on the rod's end face (``A_e - A_d``: the rod's area, signed), and
    ``F_load`` the constant gravity and external force along the motion. For a double-rod,
    horizontal cylinder it is ``(p_d - p_e) A_p`` exactly (the other terms are zeros)."""
    return (pd - pe) * P[P_AP] + (P[P_PA] - pe) * (P[P_AE] - P[P_AP]) + P[P_FLOAD]


@njit(cache=True, error_model="numpy", inline="always")
def cushion_factor(dist, length, factor, ramp):
    """Orifice-area factor at ``dist`` [m] from the cushioned end: ``factor`` inside the zone,
    1 outside, joined by a smoothstep of width ``ramp`` [m] centred on the zone's edge."""
    if length <= 0.0 or factor >= 1.0:
        return 1.0
    s = (dist - (length - 0.5 * ramp)) / ramp
    if s <= 0.0:
        return factor
    if s >= 1.0:
        return 1.0
    s = s * s * (3.0 - 2.0 * s)
    return factor + (1.0 - factor) * s


@njit(cache=True, error_model="numpy", inline="always")
def friction_force(v, f_drive, fc, kv, fstr, vstr):
    """Sliding friction [N] opposing ``v`` [m/s]; at ``v == 0`` it opposes the drive ``f_drive``."""
    sgn = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else (1.0 if f_drive >= 0.0 else -1.0))
    av = abs(v)
    f = fc + kv * av
    if fstr > 0.0:
        z = av / vstr
        f += fstr * math.exp(-z * z)
    return sgn * f


@njit(cache=True, error_model="numpy", inline="always")
def enthalpy_flow(mdot_in, T_src, T, cp, cv, R):
    """Energy-equation term ``m c_v dT/dt`` [W] of a signed inflow ``mdot_in`` [kg/s]."""
    if mdot_in >= 0.0:
        return mdot_in * (cp * T_src - cv * T)
    return mdot_in * R * T


@njit(cache=True, error_model="numpy", inline="always")
def chamber_dT(m, T, p, dVdt, heat_in, cv, T_wall, tau):
    """dT/dt [K/s] of a chamber: flows (``heat_in`` from :func:`enthalpy_flow`), work, wall heat
    transfer with time constant ``tau`` [s] (``hA = m c_v / tau``)."""
    return (heat_in - p * dVdt) / (m * cv) + (T_wall - T) / tau
