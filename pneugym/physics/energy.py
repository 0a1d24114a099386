"""Air energy accounting (thesis 5.5-5.7)."""
import math

from numba import njit


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
