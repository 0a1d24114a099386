"""Air energy and mass accounting (thesis 5.5-5.10): the potential energy of compressed air
(eq. 5.9), flow exergy, the saving ratio (eq. 5.10), and, on the packed plant state, the energy
a stroke wastes, the driving side's remaining force and the air mass in the plant.

Energies in J, pressures absolute in Pa, volumes in m³, masses in kg.
"""
import math

from numba import njit

from .cylinder import chamber_pressures
from .layout import D_CMD, D_T_ARRIVE, NP, P_AP, P_FLOAD, P_NCELLS, P_PA, P_PS, P_R, P_STROKE, P_T, P_V0D, Y_MD, Y_ME, Y_X
from .valve import valve_closed


@njit(cache=True, error_model="numpy")
def potential_energy(p, V, pa):
    """Air potential energy [J] of volume ``V`` [m³] at ``p`` [Pa] (thesis eq. 5.9):
    the work of an isothermal expansion to ``pa``, ``p V (ln(p/pa) + pa/p - 1)``."""
    if p <= 0.0:
        return 0.0
    return p * V * (math.log(p / pa) + pa / p - 1.0)


@njit(cache=True, error_model="numpy")
def flow_exergy(mass, p, pa, R, T):
    """Isothermal flow exergy [J] of ``mass`` [kg] of air delivered at ``p`` [Pa]: ``m R T ln(p/pa)``."""
    return mass * R * T * math.log(p / pa)


def saving_ratio(e_conventional: float, e_cutoff: float) -> float:
    """Energy saving ratio of thesis eq. 5.10 (a fraction, not %)."""
    return (e_conventional - e_cutoff) / e_conventional


@njit(cache=True, error_model="numpy")
def driving_side_energy(y, P):
    """Air potential energy [J] of the line cells and the driving chamber (thesis eq. 5.9):
    ``E = sum_i e(p_i, V_i) + e(p_d, V_d)`` with ``e`` = :func:`potential_energy`."""
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
def filled_energy(P, x):
    """Potential energy [J] of the driving side filled to the supply set-point with the piston
    at ``x`` [m] (the closed form of a conventional stroke):
    ``e(p_s, sum_i V_i + V0_d + A_p x)`` with ``e`` = :func:`potential_energy`."""
    n = int(P[P_NCELLS])
    vol = P[P_V0D] + P[P_AP] * x
    for i in range(n):
        vol += P[NP + i]
    return potential_energy(P[P_PS], vol, P[P_PA])


@njit(cache=True, error_model="numpy")
def energy_wasted(y, P, d):
    """Energy [J] wasted if the return stroke began now (thesis 5.5-5.7): the driving side filled
    to supply pressure while the supply is (or will be) connected, else the trapped air. Filled
    at the piston's position, or at the full stroke once it has arrived: the supply pushes a
    piston that rebounds from a stiff cushion back to the end."""
    b = 2 * int(P[P_NCELLS]) - 1
    if d[D_CMD] > 0.5 or not valve_closed(d, P):
        return filled_energy(P, P[P_STROKE] if d[D_T_ARRIVE] >= 0.0 else y[b + Y_X])
    return driving_side_energy(y, P)


@njit(cache=True, error_model="numpy")
def max_drive_force(y, P):
    """Largest net force [N] the driving-side air can still push with if no more air comes in:
    line and driving chamber equalised, exhaust vented to ambient, the constant loads along the
    motion (gravity, external force) included. A stuck piston whose ``max_drive_force`` is at
    most the breakaway friction can never move again::

        F = ((m_d + sum_i m_i) R T / (V0_d + A_d x + sum_i V_i) - p_a) A_d + F_load
    """
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    m = y[b + Y_MD]
    vol = P[P_V0D] + P[P_AP] * min(max(y[b + Y_X], 0.0), P[P_STROKE])
    for i in range(n):
        m += y[i]
        vol += P[NP + i]
    return (m * P[P_R] * P[P_T] / vol - P[P_PA]) * P[P_AP] + P[P_FLOAD]


@njit(cache=True, error_model="numpy")
def total_air_mass(y, P):
    """Air mass [kg] in the line and both chambers: ``sum_i m_i + m_d + m_e``."""
    n = int(P[P_NCELLS])
    b = 2 * n - 1
    m = 0.0
    for i in range(n):
        m += y[i]
    return m + y[b + Y_MD] + y[b + Y_ME]
