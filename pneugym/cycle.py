"""A working cycle of a double-acting cylinder: extend, dwell, retract, dwell.

The plant simulates one stroke with one driving side; a cycle is two strokes of it. The extension
runs on the rig with ``stroke_direction="extend"`` (the cap side drives), the retraction on the
same rig with ``"retract"`` (the rod side drives). At the reversal the chambers keep their air
and its temperature: the cap side becomes the retraction's exhaust chamber, the rod side its
driving chamber; the retraction's supply line starts at ambient (it vented during the extension), and the
extension's line vents (its air is wasted, as eq. 5.9 counts it). Each stroke may be cut off;
each is accounted as the environment accounts an extension (thesis eq. 5.9 on whichever side
drives), and the cycle's air in normal litres and compressor energy (:mod:`pneugym.units`).

    from pneugym.cycle import run_cycle
    c = run_cycle(rig, cut_extend_s=0.95, dwell_s=0.3)
    c.free_air_nl, c.extend.saving_ratio, c.retract.arrival_time_s
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from .params import RigParams
from .physics import layout as L
from .plant import Plant, check_duration
from .units import compressor_energy_kwh, free_air_nl

CHUNK_S = 0.005  # the stroke is advanced in steps of this length until it arrives [s]
#: The chamber state each side keeps across the reversal: (extension's index, retraction's).
CARRIED = ((L.Y_MD, L.Y_ME), (L.Y_ME, L.Y_MD), (L.Y_TD, L.Y_TE), (L.Y_TE, L.Y_TD),
           (L.Y_SD, L.Y_SE), (L.Y_SE, L.Y_SD))


def check_cycle_rig(rig: RigParams) -> None:
    """Refuse effects bound to the driving side of one stroke: a cycle swaps the sides."""
    e = rig.effects
    if e.dead_volume_m3 or e.leak_drive_area_m2 or e.leak_drive_laminar_m3:
        raise ValueError("effects.dead_volume_m3, effects.leak_drive_area_m2 and "
                         "effects.leak_drive_laminar_m3 belong to the "
                         "driving side of one stroke: a cycle would move them to the other "
                         "chamber at the reversal; give the dead volumes per side in "
                         "CylinderParams (dead_volume_m3, dead_volume_rod_m3) instead")


@dataclass(frozen=True)
class StrokeResult:
    """One stroke of a cycle: times [s] from its own command, air drawn [kg] and [NL], the
    energy wasted when the next stroke begins [J] (eq. 5.9) against a conventional stroke's."""

    direction: str
    cutoff_s: float | None
    arrival_time_s: float | None
    air_mass_kg: float
    free_air_nl: float
    energy_wasted_j: float
    energy_conventional_j: float
    saving_ratio: float
    stick_slip_events: int


@dataclass(frozen=True)
class CycleResult:
    """A cycle: both strokes, its duration [s] (strokes and dwells), air [kg], [NL], compressor
    energy [kWh], the chamber pressures [Pa] it ends with (cap side, rod side; the start of the
    next cycle), and its mass balance: the largest relative error of either stroke's balance
    and of the chambers' pressures carried across the reversal (round-off)."""

    extend: StrokeResult
    retract: StrokeResult
    cycle_time_s: float | None
    air_mass_kg: float
    free_air_nl: float
    compressor_kwh: float
    end_pressures_pa: tuple[float, float]
    mass_balance_error: float

    @property
    def completed(self) -> bool:
        return self.extend.arrival_time_s is not None and self.retract.arrival_time_s is not None

    def to_dict(self) -> dict:
        return asdict(self)


def _stroke(plant: Plant, cut_s: float | None, dwell_s: float, t_max_s: float) -> StrokeResult:
    """Command the supply, cut off at ``cut_s`` (None: never), run to the arrival (or
    ``t_max_s``), then the dwell; the plant stays at the end of the dwell."""
    plant.command(1)
    if cut_s is not None:
        if cut_s > 0.0:  # (a cut at 0 s: the open command taken back at once)
            plant.advance(cut_s, stop_on_arrival=False)
        plant.command(0)
    while plant.arrival_time_s is None and plant.time_s < t_max_s:
        plant.advance(CHUNK_S, stop_on_arrival=True)
    if dwell_s > 0.0:
        plant.advance(dwell_s)
    return StrokeResult(plant.params.stroke_direction, cut_s, plant.arrival_time_s,
                        plant.air_mass_in_kg, free_air_nl(plant.air_mass_in_kg),
                        plant.energy_wasted_j, plant.conventional_energy_j, plant.saving_ratio,
                        plant.stick_events)


def _check(name: str, value: float | None, allow_none: bool = True) -> None:
    if value is None and allow_none:
        return
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0:
        raise ValueError(f"{name} = {value!r} must be a finite number >= 0 [s]"
                         + (" or None" if allow_none else ""))


def run_cycle(rig: RigParams, cut_extend_s: float | None = None,
              cut_retract_s: float | None = None, dwell_s: float = 0.2,
              start_pressures_pa: tuple[float, float] | None = None,
              t_max_s: float = 10.0) -> CycleResult:
    """One cycle of ``rig``'s cylinder: extend (cut off ``cut_extend_s`` [s] after its command,
    None: never), dwell ``dwell_s`` [s], retract (``cut_retract_s``), dwell. It starts retracted
    with the cap and rod sides at ``start_pressures_pa`` [Pa absolute] (default: the cap side at
    ambient, the rod side at supply, as after a conventional retraction); a stroke that does not
    arrive within ``t_max_s`` [s] ends the cycle there (``cycle_time_s`` None)."""
    for name, v in (("cut_extend_s", cut_extend_s), ("cut_retract_s", cut_retract_s)):
        _check(name, v)
    check_cycle_rig(rig)
    _check("dwell_s", dwell_s, allow_none=False)
    t_max_s = check_duration(t_max_s, "t_max_s")
    pa = rig.gas.ambient_pressure_pa
    ext = Plant(rig.with_(stroke_direction="extend"))
    if start_pressures_pa is not None:
        ext.reset(p_drive_pa=start_pressures_pa[0], p_exhaust_pa=start_pressures_pa[1])
    out = _stroke(ext, cut_extend_s, dwell_s, t_max_s)
    cap_p, rod_p = ext.p_drive_pa, ext.p_exhaust_pa
    ret = Plant(rig.with_(stroke_direction="retract"))
    if out.arrival_time_s is None:  # stalled: the retraction starts from where it stopped
        travel = rig.cylinder.stroke_m - ext.position_m
    else:
        travel = 0.0
    ret.reset(p_line_pa=pa, p_drive_pa=rod_p, p_exhaust_pa=cap_p, position_m=travel)
    b_e, b_r = ext._b, ret._b
    for a, b in CARRIED:  # each chamber keeps its air and heat
        ret.y[b_r + b] = ext.y[b_e + a]
    ret._m0 = ret.total_air_mass_kg
    pd_r, pe_r = ret.p_drive_pa, ret.p_exhaust_pa
    err = max(abs(pd_r / rod_p - 1.0), abs(pe_r / cap_p - 1.0),
              abs(ext.mass_balance_error_kg) / ext.total_air_mass_kg)
    back = _stroke(ret, cut_retract_s, dwell_s, t_max_s)
    err = max(err, abs(ret.mass_balance_error_kg) / ret.total_air_mass_kg)
    mass = out.air_mass_kg + back.air_mass_kg
    done = out.arrival_time_s is not None and back.arrival_time_s is not None
    return CycleResult(out, back, (out.arrival_time_s + back.arrival_time_s + 2 * dwell_s)
                       if done else None, mass, free_air_nl(mass), compressor_energy_kwh(mass),
                       (ret.p_exhaust_pa, ret.p_drive_pa), float(err))


def steady_cycle(rig: RigParams, cycles: int = 3, **kwargs) -> CycleResult:
    """The last of ``cycles`` cycles, each starting with the chamber pressures the previous one
    ended with (the first as :func:`run_cycle`): the cycle a machine repeats."""
    if not isinstance(cycles, int) or isinstance(cycles, bool) or cycles < 1:
        raise ValueError(f"cycles = {cycles!r} must be an integer >= 1")
    start = kwargs.pop("start_pressures_pa", None)
    for _ in range(cycles):
        c = run_cycle(rig, start_pressures_pa=start, **kwargs)
        start = c.end_pressures_pa
    return c
