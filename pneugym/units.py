"""Engineer's units beside the energy ratio: free air in normal litres, the compressor's
electrical energy, and its cost.

- **Normal litres** (NL): volume of the air at normal conditions, 0 °C and 1.01325 bar (DIN 1343,
  ISO 2533's reference): dry air then weighs :data:`NORMAL_DENSITY_KG_M3` = 1.2922 kg/m³, so
  1 g of air is 0.774 NL.
- **Compressor energy**: the electrical energy an industrial compressor plant spends per normal
  m³ delivered. :data:`SPECIFIC_ENERGY_KWH_PER_NM3` = 0.1 kWh/Nm³ is typical at 6-7 bar for
  a screw compressor with its dryer and losses (published plant figures run from about 0.09 to
  0.13 kWh/Nm³; a leaky or oversized plant reaches 0.15+). Give your own figure: it scales
  every energy and cost linearly.

Everything takes the mass of air drawn from the supply [kg] (``Plant.air_mass_in_kg``, the
environment's ``info["air_mass_kg"]``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

NORMAL_DENSITY_KG_M3 = 1.2922  # dry air at 0 °C and 101 325 Pa (DIN 1343)
SPECIFIC_ENERGY_KWH_PER_NM3 = 0.1  # electrical energy per normal m³ at 6-7 bar (see above)


def _check(name: str, value: float, allow_zero: bool = True) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} = {value!r} must be a finite number "
                         f"{'>= 0' if allow_zero else '> 0'}")
    return float(value)


def free_air_nl(mass_kg: float) -> float:
    """Free air [NL] of ``mass_kg`` [kg] of air at normal conditions (0 °C, 1.01325 bar)."""
    return _check("mass_kg", mass_kg) / NORMAL_DENSITY_KG_M3 * 1e3


def compressor_energy_kwh(mass_kg: float,
                          specific_kwh_per_nm3: float = SPECIFIC_ENERGY_KWH_PER_NM3) -> float:
    """Electrical energy [kWh] the compressor plant spends to deliver ``mass_kg`` [kg] of air."""
    return free_air_nl(mass_kg) * 1e-3 * _check("specific_kwh_per_nm3", specific_kwh_per_nm3,
                                                 allow_zero=False)


@dataclass(frozen=True)
class AirCost:
    """The air of one cycle, and what it costs over a year of cycles."""

    free_air_nl_per_cycle: float
    energy_kwh_per_cycle: float
    cycles_per_year: float
    energy_kwh_per_year: float
    cost_per_year: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def air_cost(mass_kg_per_cycle: float, cycles_per_minute: float, hours_per_year: float = 4000.0,
             price_per_kwh: float = 0.2,
             specific_kwh_per_nm3: float = SPECIFIC_ENERGY_KWH_PER_NM3) -> AirCost:
    """Free air and compressor energy per cycle, and energy [kWh] and cost (in the currency of
    ``price_per_kwh``) per year at ``cycles_per_minute`` for ``hours_per_year`` (default 4000 h:
    two shifts)."""
    per = compressor_energy_kwh(mass_kg_per_cycle, specific_kwh_per_nm3)
    n = (_check("cycles_per_minute", cycles_per_minute) * 60.0
         * _check("hours_per_year", hours_per_year))
    year = per * n
    return AirCost(free_air_nl(mass_kg_per_cycle), per, n, year,
                   year * _check("price_per_kwh", price_per_kwh))
