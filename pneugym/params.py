"""Rig parameters: typed, validated dataclasses with the thesis rig as default.

All values are SI, pressures absolute unless the name says ``gauge``. The groups mirror the
``rig`` section of the measured-run format (``MEASUREMENT_FORMAT.md``) so that a measured run's
JSON builds a plant directly (:meth:`RigParams.from_measurement`).

Defaults marked *calibrated* are not given by the thesis; they were fitted once by
``python -m pneugym.calibrate`` to the thesis's published figures (see README).
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import numbers
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

#: Thesis Fig. 3.6: main-valve switching delay [s] against supply gauge pressure [Pa].
THESIS_VALVE_DELAY = ((150_000.0, 0.215), (250_000.0, 0.185))


#: Cylinder designs (:attr:`CylinderParams.design`) and stroke directions
#: (:attr:`RigParams.stroke_direction`).
CYLINDER_DESIGNS = ("double-rod", "single-rod")
STROKE_DIRECTIONS = ("extend", "retract")
STANDARD_GRAVITY = 9.80665  # [m/s²]

_GROUP_NAMES = ("gas", "cylinder", "line", "valve", "friction", "effects", "solver")
try:  # numpy's bool is not a Python bool but is no number either
    from numpy import bool_ as np_bool
except ImportError:  # pragma: no cover
    np_bool = bool


def did_you_mean(name: Any, known: Any) -> str:
    """`` (did you mean 'x'?)`` for the known name nearest to ``name``, or ``""``."""
    m = difflib.get_close_matches(str(name), [str(k) for k in known], n=1, cutoff=0.6)
    return f" (did you mean {m[0]!r}?)" if m else ""


def _check(obj: Any, name: str, ok: bool, what: str) -> None:
    if not ok:
        raise ValueError(
            f"{type(obj).__name__}.{name} = {getattr(obj, name)!r} is invalid: must be {what}"
        )


def _finite(obj: Any) -> None:
    """Every number field must be a finite real number (no NaN, inf, ``None`` unless the field
    allows it, strings, lists); float fields are stored as Python floats (numpy scalars,
    fractions and ints included), so that equal rigs compare and hash equal."""
    for name, skip, is_str, is_float, none_ok, want in _field_kinds(type(obj)):
        v = getattr(obj, name)
        if type(v) is float and not (skip or is_str) and math.isfinite(v):
            continue  # the common case: a finite Python float, nothing to convert
        if v is None:
            if none_ok:
                continue
            raise ValueError(f"{type(obj).__name__}.{name} = None is invalid: must be {want}")
        if skip:
            continue  # groups and tee volumes check themselves
        if is_str:
            if not isinstance(v, str):
                raise ValueError(f"{type(obj).__name__}.{name} = {v!r} is invalid: must be a "
                                 f"string")
            continue
        if isinstance(v, (bool, np_bool)) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
            raise ValueError(f"{type(obj).__name__}.{name} = {v!r} is invalid: must be a finite number")
        if is_float:
            object.__setattr__(obj, name, float(v))


@functools.cache
def _field_kinds(cls: type) -> tuple[tuple[str, bool, bool, bool, bool, str], ...]:
    """What :func:`_finite` checks of each field of dataclass ``cls`` (read from its annotation
    once per class): ``(name, skipped, a string, a float, None allowed, what a None needs)``."""
    out = []
    for f in fields(cls):
        kind = str(f.type)
        skip = f.name in _GROUP_NAMES or "tuple" in kind
        want = "a string" if "str" in kind else "a finite number"
        out.append((f.name, skip, "str" in kind, "float" in kind, "None" in kind, want))
    return tuple(out)


def _plausible(obj: Any, name: str, hi: float, hint: str) -> None:
    """Refuse a value above ``hi``, which no real rig has: ``hint`` names the likely unit slip."""
    v = getattr(obj, name)
    if v > hi:
        raise ValueError(f"{type(obj).__name__}.{name} = {v!r} is not plausible (at most {hi:g}): "
                         f"{hint}")


def _positive(obj: Any, *names: str) -> None:
    for n in names:
        _check(obj, n, getattr(obj, n) > 0, "> 0")


def _nonneg(obj: Any, *names: str) -> None:
    for n in names:
        _check(obj, n, getattr(obj, n) >= 0, ">= 0")


@dataclass(frozen=True)
class GasParams:
    """Air and ambient (thesis: isothermal at 293 K, γ = 1.4, R = 287)."""

    gas_constant_j_per_kg_k: float = 287.0
    gamma: float = 1.4
    ambient_temperature_k: float = 293.15
    ambient_pressure_pa: float = 101_325.0
    viscosity_pa_s: float = 1.81e-5  # kinematic 1.51e-5 m²/s at 1.2 kg/m³ (thesis)

    def __post_init__(self) -> None:
        _finite(self)
        _positive(self, "gas_constant_j_per_kg_k", "ambient_temperature_k", "ambient_pressure_pa",
                  "viscosity_pa_s")
        _check(self, "gamma", 1.0 < self.gamma < 2.0, "in (1, 2)")
        _check(self, "ambient_pressure_pa", 1e4 <= self.ambient_pressure_pa <= 2e5,
               "in [1e4, 2e5] Pa absolute (bar given as Pa? 1 bar = 1e5 Pa)")
        _check(self, "ambient_temperature_k", 150.0 <= self.ambient_temperature_k <= 600.0,
               "in [150, 600] K (°C given as K? 20 °C = 293.15 K)")
        _check(self, "gas_constant_j_per_kg_k", 50.0 <= self.gas_constant_j_per_kg_k <= 5000.0,
               "in [50, 5000] J/(kg K) (air: 287; kJ given as J?)")
        _check(self, "viscosity_pa_s", self.viscosity_pa_s <= 1e-3,
               "<= 1e-3 Pa s (air: 1.81e-5; µPa s given as Pa s?)")

    @property
    def sound_speed_isothermal_m_s(self) -> float:
        return math.sqrt(self.gas_constant_j_per_kg_k * self.ambient_temperature_k)


@dataclass(frozen=True)
class CylinderParams:
    """Double-acting cylinder; the default is the thesis's double-rod SMC C92SB-125-180W with end
    cushions (thesis 3.1, 3.4).

    ``design``: ``"double-rod"`` (both piston faces are annuli) or ``"single-rod"`` (ISO 15552 /
    ISO 6432: the cap side has the full bore area, the rod side the annulus).
    ``dead_volume_m3``: the cap side's dead volume (each side's on a double-rod cylinder),
    ``dead_volume_rod_m3`` the rod side's (None: the same). ``mounting_angle_deg``: 0
    horizontal, +90 rod pointing up (extending lifts the load), -90 rod pointing down."""

    bore_m: float = 0.125
    rod_m: float = 0.032
    stroke_m: float = 0.18
    dead_volume_m3: float = 2.44e-4  # calibrated: each chamber at its end of stroke, port included
    port_area_m2: float = 3.89e-5  # calibrated: driving port, line -> chamber
    cushion_length_m: float = 0.0136  # calibrated
    cushion_factor_drive: float = 0.420  # calibrated: drive port area factor in the first zone
    cushion_factor_exhaust: float = 0.0101  # calibrated: exhaust area factor in the last zone
    cushion_ramp_m: float = 0.002  # smooth transition of the cushion factor (numerics)
    moving_mass_extra_kg: float = 1.0  # "other masses" Mo (thesis 6.1)
    design: str = "double-rod"
    dead_volume_rod_m3: float | None = None
    mounting_angle_deg: float = 0.0

    def __post_init__(self) -> None:
        _finite(self)
        _positive(self, "bore_m", "stroke_m", "dead_volume_m3", "port_area_m2",
                  "cushion_factor_drive", "cushion_factor_exhaust", "cushion_ramp_m")
        _check(self, "design", self.design in CYLINDER_DESIGNS,
               f"one of {list(CYLINDER_DESIGNS)}{did_you_mean(self.design, CYLINDER_DESIGNS)}")
        if self.dead_volume_rod_m3 is not None:
            _positive(self, "dead_volume_rod_m3")
            _plausible(self, "dead_volume_rod_m3", 0.1, "litres or cm³ given as m³? (1 L = 1e-3 m³)")
        _check(self, "mounting_angle_deg", -90.0 <= self.mounting_angle_deg <= 90.0,
               "in [-90, 90] degrees (0 horizontal, +90 rod pointing up, -90 rod pointing "
               "down)")
        if self.design == "single-rod":
            _check(self, "rod_m", self.rod_m > 0.0, "> 0 for a single-rod cylinder")
        _nonneg(self, "rod_m", "cushion_length_m", "moving_mass_extra_kg")
        _check(self, "rod_m", self.rod_m < self.bore_m, f"< bore_m ({self.bore_m})")
        _check(self, "cushion_length_m", self.cushion_length_m < 0.5 * self.stroke_m,
               f"< half the stroke ({0.5 * self.stroke_m})")
        _check(self, "cushion_factor_drive", self.cushion_factor_drive <= 1.0, "in (0, 1]")
        _check(self, "cushion_factor_exhaust", self.cushion_factor_exhaust <= 1.0, "in (0, 1]")
        _plausible(self, "bore_m", 1.0, f"mm given as m? (a {self.bore_m:g} mm bore is "
                                        f"{self.bore_m / 1000:g} m)")
        _plausible(self, "stroke_m", 10.0, f"mm given as m? (a {self.stroke_m:g} mm stroke is "
                                           f"{self.stroke_m / 1000:g} m)")
        _plausible(self, "dead_volume_m3", 0.1, "litres or cm³ given as m³? (1 L = 1e-3 m³)")
        _plausible(self, "port_area_m2", 0.01, "mm² given as m²? (1 mm² = 1e-6 m²)")
        _plausible(self, "moving_mass_extra_kg", 1e4, "grams given as kg?")

    @property
    def piston_area_m2(self) -> float:
        """Annulus area [m²]: the rod side's, and both sides' of a double-rod cylinder."""
        return math.pi / 4.0 * (self.bore_m**2 - self.rod_m**2)

    @property
    def cap_area_m2(self) -> float:
        """Area [m²] of the cap side's piston face: the full bore of a single-rod cylinder, the
        annulus of a double-rod one."""
        if self.design == "double-rod":
            return self.piston_area_m2
        return math.pi / 4.0 * self.bore_m**2

    @property
    def rod_dead_volume_m3(self) -> float:
        """Dead volume [m³] of the rod side's chamber at its end of stroke."""
        return self.dead_volume_m3 if self.dead_volume_rod_m3 is None else self.dead_volume_rod_m3


#: the supply-line models (:attr:`LineParams.model`)
LINE_MODELS = ("fd", "lumped")
#: how the substep treats the FD line: explicit (the default) or solved implicitly whole
LINE_SCHEMES = ("explicit", "implicit")
#: the orifice laws (:attr:`ValveParams.flow_model`)
ORIFICE_MODELS = ("thesis", "iso6358")


def forms_tried(stated: str, tried: Sequence[str] | None, known: Sequence[str], what: str) -> list[str]:
    """The stated model form first, then the other names of ``tried`` (a line model or an
    orifice law, ``what``); ``ValueError`` naming one not in ``known``."""
    out = list(dict.fromkeys([stated, *(tried or ())]))
    for m in out:
        if m not in known:
            raise ValueError(f"{what} {m!r}: choose from {tuple(known)}")
    return out


@dataclass(frozen=True)
class LineParams:
    """Supply line between the main valve and the driving port (PU tube, ID 5 mm; thesis 4.7).

    ``model``: ``"fd"`` (1-D compressible finite differences, default) or ``"lumped"`` (the
    thesis's lumped-volume line, volumes joined by orifices). ``tee_volumes`` are lumped volumes
    ``(position_m, volume_m3)`` along the line (transducer tees), added to the cell at that place.
    """

    length_m: float = 0.725  # calibrated once, then held (not stated in the thesis; see pneugym.calibrate)
    diameter_m: float = 0.005
    n_cells: int = 3
    model: str = "fd"
    tee_volumes: tuple[tuple[float, float], ...] = ()
    artificial_viscosity: float = 1.0  # quadratic (von Neumann-Richtmyer) coefficient, FD only

    def __post_init__(self) -> None:
        _finite(self)
        _positive(self, "length_m", "diameter_m")
        _check(self, "n_cells", isinstance(self.n_cells, numbers.Integral) and 1 <= self.n_cells <= 4096,
               "an int in [1, 4096]")
        object.__setattr__(self, "n_cells", int(self.n_cells))
        _check(self, "model", self.model in LINE_MODELS, "'fd' or 'lumped'")
        _check(self, "artificial_viscosity", 0.0 <= self.artificial_viscosity <= 10.0, "in [0, 10]")
        _plausible(self, "length_m", 100.0, "mm given as m?")
        _plausible(self, "diameter_m", 0.1, "mm given as m? (a 5 mm tube is 0.005 m)")
        try:
            tees = tuple((float(p), float(v)) for p, v in self.tee_volumes)
        except (TypeError, ValueError):
            raise ValueError(f"LineParams.tee_volumes = {self.tee_volumes!r} is invalid: must be "
                             f"pairs (position_m, volume_m3)") from None
        object.__setattr__(self, "tee_volumes", tees)
        for i, (pos, vol) in enumerate(self.tee_volumes):
            if not (math.isfinite(pos) and 0.0 <= pos <= self.length_m):
                raise ValueError(f"LineParams.tee_volumes[{i}] position {pos!r} must be in [0, length_m]")
            if not (math.isfinite(vol) and 0.0 <= vol <= 0.01):
                raise ValueError(f"LineParams.tee_volumes[{i}] volume {vol!r} must be in [0, 0.01] "
                                 f"m³ (cm³ given as m³? 1 cm³ = 1e-6 m³)")

    @property
    def area_m2(self) -> float:
        return math.pi / 4.0 * self.diameter_m**2


@dataclass(frozen=True)
class ValveParams:
    """Closed-centre 5/3 main valve and the exhaust path (thesis 3.3, 5.3).

    ``delay_s=None`` interpolates the thesis's pressure-dependent delay (0.215 s at 1.5 bar,
    0.185 s at 2.5 bar gauge, linear, clipped to [0.05, 0.4] s). ``delay_scale`` multiplies
    the delay (stated or interpolated): a slower or faster valve of the same kind, as a
    calibration finds it. The spool then opens or closes
    linearly over ``ramp_s``. The exhaust path opens with the first opening and stays open.
    ``flow_model``: ``"thesis"`` (eqs. 4.1-4.3) or ``"iso6358"`` (sonic conductance from the
    same area, critical ratio ``iso_b``). Below a pressure drop of ``linear_ratio`` (relative) the
    orifice flow is linear in Δp, so that the flow is smooth through Δp = 0.
    """

    area_m2: float = 1.56e-5  # calibrated: supply path through the main valve
    exhaust_area_m2: float = 3.25e-5  # calibrated: exhaust chamber -> atmosphere, whole path
    discharge_coefficient: float = 0.72
    delay_s: float | None = None
    delay_scale: float = 1.0
    ramp_s: float = 0.01
    flow_model: str = "thesis"
    iso_b: float = 0.528
    linear_ratio: float = 0.05

    def __post_init__(self) -> None:
        _finite(self)
        _positive(self, "area_m2", "exhaust_area_m2", "ramp_s")
        _check(self, "discharge_coefficient", 0.0 < self.discharge_coefficient <= 1.0, "in (0, 1]")
        if self.delay_s is not None:
            _check(self, "delay_s", 0.0 <= self.delay_s <= 5.0, "None or in [0, 5] s (ms given as s?)")
        _check(self, "delay_scale", 0.0 < self.delay_scale <= 10.0, "in (0, 10]")
        _plausible(self, "area_m2", 0.01, "mm² given as m²? (1 mm² = 1e-6 m²)")
        _plausible(self, "exhaust_area_m2", 0.01, "mm² given as m²? (1 mm² = 1e-6 m²)")
        _plausible(self, "ramp_s", 1.0, "ms given as s? (10 ms = 0.01 s)")
        _check(self, "flow_model", self.flow_model in ORIFICE_MODELS, "'thesis' or 'iso6358'")
        _check(self, "iso_b", 0.0 <= self.iso_b < 1.0, "in [0, 1)")
        _check(self, "linear_ratio", 1e-4 <= self.linear_ratio <= 0.2, "in [1e-4, 0.2]")

    def delay_for(self, supply_gauge_pa: float) -> float:
        """Switching delay [s] at a supply gauge pressure [Pa]."""
        if self.delay_s is not None:
            return float(self.delay_s) * self.delay_scale
        (p1, d1), (p2, d2) = THESIS_VALVE_DELAY
        d = d1 + (d2 - d1) * (supply_gauge_pa - p1) / (p2 - p1)
        return float(min(max(d, 0.05), 0.4)) * self.delay_scale


@dataclass(frozen=True)
class FrictionParams:
    """Piston friction (thesis 5.6): static breakaway, then ``coulomb + viscous * v``.

    Defaults: Fs = 359 N and the linear fit of Table 5.1, C = 126 N, Kv = 1557 N s/m.
    """

    static_n: float = 359.0
    coulomb_n: float = 126.0
    viscous_n_s_per_m: float = 1557.0

    def __post_init__(self) -> None:
        _finite(self)
        _nonneg(self, "static_n", "coulomb_n", "viscous_n_s_per_m")


@dataclass(frozen=True)
class EffectParams:
    """Optional effects; every default is the null value that reproduces the nominal model exactly.

    - ``leak_drive_area_m2``: effective leak area (Cd included) driving chamber -> atmosphere.
    - ``leak_piston_area_m2``: effective leak area across the piston seal (drive <-> exhaust).
    - ``leak_drive_laminar_m3``: a laminar (capillary, porous) leak driving chamber ->
      atmosphere, ``K = pi d^4 / (128 l)`` summed over its pores (diameter ``d``, length ``l``)
      [m³]: isothermal Hagen-Poiseuille flow ``q = K (p_d² - p_a²) / (2 mu R T)`` at the wall's
      (ambient) temperature, valid while each pore's flow stays laminar; it keeps a long tail
      near ambient where an orifice empties the chamber in a finite time.
    - ``heat_transfer_time_constant_s``: 0 = isothermal chambers (thesis); > 0 solves the energy
      equation of each chamber with wall heat transfer ``hA = m c_v / tau`` to the wall at ambient.
    - ``stribeck_force_n``, ``stribeck_velocity_m_s``: extra friction at low speed,
      ``F_s * exp(-(v / v_s)^2)`` (velocity weakening); 0 N = off.
    - ``sensor_lag_s``: first-order time constant of the pressure transducers (0 = ideal).
    - ``dead_volume_m3``: extra volume at the driving port (adds to the chamber's dead volume).
    """

    leak_drive_area_m2: float = 0.0
    leak_piston_area_m2: float = 0.0
    leak_drive_laminar_m3: float = 0.0
    heat_transfer_time_constant_s: float = 0.0
    stribeck_force_n: float = 0.0
    stribeck_velocity_m_s: float = 0.01
    sensor_lag_s: float = 0.0
    dead_volume_m3: float = 0.0

    def __post_init__(self) -> None:
        _finite(self)
        _nonneg(self, "leak_drive_area_m2", "leak_piston_area_m2", "leak_drive_laminar_m3",
                "heat_transfer_time_constant_s", "stribeck_force_n", "sensor_lag_s",
                "dead_volume_m3")
        _positive(self, "stribeck_velocity_m_s")
        for name in ("leak_drive_area_m2", "leak_piston_area_m2"):
            _plausible(self, name, 1e-4, "mm² given as m²? (1 mm² = 1e-6 m²)")
        _plausible(self, "leak_drive_laminar_m3", 1e-9, "pi d^4 / (128 l) in m³: a pore of "
                   "0.1 mm over 1 mm is 2.5e-15 m³")
        _plausible(self, "sensor_lag_s", 1.0, "ms given as s? (15 ms = 0.015 s)")
        _plausible(self, "heat_transfer_time_constant_s", 1e4, "a time constant in s")
        _plausible(self, "dead_volume_m3", 0.1, "litres or cm³ given as m³? (1 L = 1e-3 m³)")
        _plausible(self, "stribeck_velocity_m_s", 10.0, "mm/s given as m/s?")

    @property
    def active(self) -> tuple[str, ...]:
        """Names of the effects switched on."""
        on = []
        if self.leak_drive_area_m2 > 0 or self.leak_piston_area_m2 > 0 or self.leak_drive_laminar_m3 > 0:
            on.append("leakage")
        if self.heat_transfer_time_constant_s > 0:
            on.append("heat_transfer")
        if self.stribeck_force_n > 0:
            on.append("stribeck_friction")
        if self.sensor_lag_s > 0:
            on.append("sensor_lag")
        if self.dead_volume_m3 > 0:
            on.append("dead_volume")
        return tuple(on)


@dataclass(frozen=True)
class SolverParams:
    """Time stepping: IMEX Runge-Kutta, SSP-RK3 for everything but the valve and port flows,
    which are implicit. ``dt_s=None`` picks the substep automatically from the explicit part's
    stability limits (the line's acoustic CFL limit, the explicit orifices), times ``safety``."""

    dt_s: float | None = None
    safety: float = 0.9
    min_dt_s: float = 1e-7
    line_scheme: str = "explicit"

    def __post_init__(self) -> None:
        _finite(self)
        _check(self, "min_dt_s", self.min_dt_s >= 1e-9,
               ">= 1e-9 s (a smaller substep takes hours per simulated second)")
        if self.dt_s is not None:
            _check(self, "dt_s", self.dt_s >= self.min_dt_s,
                   f"None or >= min_dt_s = {self.min_dt_s:g} s (a smaller substep takes hours per "
                   f"simulated second; µs given as s?)")
        _check(self, "safety", 0.0 < self.safety <= 1.0, "in (0, 1]")
        _check(self, "line_scheme", self.line_scheme in LINE_SCHEMES,
               " or ".join(repr(x) for x in LINE_SCHEMES))


#: Lowest plausible supply [Pa gauge] (0.1 bar): below it the value is almost surely bar given as Pa.
MIN_SUPPLY_GAUGE_PA = 1e4
_GROUPS = {"gas": GasParams, "cylinder": CylinderParams, "line": LineParams, "valve": ValveParams,
           "friction": FrictionParams, "effects": EffectParams, "solver": SolverParams}


#: ``rig`` keys of the measured-run format -> (group, field) of :class:`RigParams`.
MEASUREMENT_RIG_KEYS: dict[str, tuple[str, str]] = {
    "bore_m": ("cylinder", "bore_m"), "rod_m": ("cylinder", "rod_m"),
    "stroke_m": ("cylinder", "stroke_m"), "dead_volume_m3": ("cylinder", "dead_volume_m3"),
    "port_area_m2": ("cylinder", "port_area_m2"),
    "cushion_length_m": ("cylinder", "cushion_length_m"),
    "cushion_factor_drive": ("cylinder", "cushion_factor_drive"),
    "cushion_factor_exhaust": ("cylinder", "cushion_factor_exhaust"),
    "moving_mass_extra_kg": ("cylinder", "moving_mass_extra_kg"),
    "line_length_m": ("line", "length_m"), "line_diameter_m": ("line", "diameter_m"),
    "valve_area_m2": ("valve", "area_m2"), "exhaust_area_m2": ("valve", "exhaust_area_m2"),
    "discharge_coefficient": ("valve", "discharge_coefficient"),
    "valve_delay_s": ("valve", "delay_s"),
    "cylinder_design": ("cylinder", "design"),
    "dead_volume_rod_m3": ("cylinder", "dead_volume_rod_m3"),
    "mounting_angle_deg": ("cylinder", "mounting_angle_deg"),
}
#: Top-level keys of a measured run's JSON that are :class:`RigParams` fields (the stroke
#: measured and what loads it); the last two are optional (extension, no external force).
MEASUREMENT_TOP_FIELDS = ("supply_pressure_gauge_pa", "load_mass_kg", "stroke_direction",
                          "external_force_n")
MEASUREMENT_FRICTION_KEYS: dict[str, tuple[str, str]] = {
    k: ("friction", k) for k in ("static_n", "coulomb_n", "viscous_n_s_per_m")}


def _groups(rig: Any) -> None:
    """Each group of a :class:`RigParams` must be its dataclass (not a number, dict or None)."""
    for name, cls in _GROUPS.items():
        v = getattr(rig, name)
        if not isinstance(v, cls):
            raise ValueError(f"RigParams.{name} = {v!r} is invalid: must be a {cls.__name__} "
                             f"(or, in with_/from_dict, a dict of its fields)")


@dataclass(frozen=True)
class RigParams:
    """The whole rig and operating point; the default is the thesis rig at 2.5 bar, 10 kg."""

    supply_pressure_gauge_pa: float = 250_000.0
    load_mass_kg: float = 10.0
    stroke_direction: str = "extend"
    external_force_n: float = 0.0
    gas: GasParams = field(default_factory=GasParams)
    cylinder: CylinderParams = field(default_factory=CylinderParams)
    line: LineParams = field(default_factory=LineParams)
    valve: ValveParams = field(default_factory=ValveParams)
    friction: FrictionParams = field(default_factory=FrictionParams)
    effects: EffectParams = field(default_factory=EffectParams)
    solver: SolverParams = field(default_factory=SolverParams)

    def __post_init__(self) -> None:
        _groups(self)
        _finite(self)
        _check(self, "supply_pressure_gauge_pa", 0.0 < self.supply_pressure_gauge_pa <= 1.9e6,
               "in (0, 1.9e6] Pa gauge (the supply must be above ambient)")
        _check(self, "supply_pressure_gauge_pa", self.supply_pressure_gauge_pa >= MIN_SUPPLY_GAUGE_PA,
               f">= {MIN_SUPPLY_GAUGE_PA:g} Pa gauge (bar given as Pa? "
               f"{self.supply_pressure_gauge_pa:g} bar = {self.supply_pressure_gauge_pa * 1e5:g} Pa)")
        _nonneg(self, "load_mass_kg")
        _plausible(self, "load_mass_kg", 1e4, "grams given as kg?")
        _check(self, "stroke_direction", self.stroke_direction in STROKE_DIRECTIONS,
               f"one of {list(STROKE_DIRECTIONS)}"
               f"{did_you_mean(self.stroke_direction, STROKE_DIRECTIONS)}")
        _check(self, "external_force_n", abs(self.external_force_n) <= 1e6,
               "at most 1e6 N in size (a constant process force opposing the stroke, in N)")
        if self.moving_mass_kg <= 0.0:
            raise ValueError(f"RigParams: the moving mass load_mass_kg + "
                             f"CylinderParams.moving_mass_extra_kg = {self.moving_mass_kg:g} kg "
                             f"must be > 0 (the piston and rods weigh something)")

    # -- derived ---------------------------------------------------------------------------
    @property
    def supply_pressure_pa(self) -> float:
        """Absolute supply pressure [Pa]."""
        return self.supply_pressure_gauge_pa + self.gas.ambient_pressure_pa

    @property
    def moving_mass_kg(self) -> float:
        return self.load_mass_kg + self.cylinder.moving_mass_extra_kg

    # -- the stroke: which chamber drives, the loads along the motion -----------------------
    @property
    def drive_piston_area_m2(self) -> float:
        """Piston face area [m²] of the driving chamber: the cap side's when extending, the rod
        side's (annulus) when retracting."""
        c = self.cylinder
        return c.cap_area_m2 if self.stroke_direction == "extend" else c.piston_area_m2

    @property
    def exhaust_piston_area_m2(self) -> float:
        """Piston face area [m²] of the exhausting chamber."""
        c = self.cylinder
        return c.piston_area_m2 if self.stroke_direction == "extend" else c.cap_area_m2

    @property
    def drive_dead_volume_m3(self) -> float:
        """Dead volume [m³] of the driving chamber (the cylinder's; without the effects')."""
        c = self.cylinder
        return c.dead_volume_m3 if self.stroke_direction == "extend" else c.rod_dead_volume_m3

    @property
    def exhaust_dead_volume_m3(self) -> float:
        """Dead volume [m³] of the exhausting chamber."""
        c = self.cylinder
        return c.rod_dead_volume_m3 if self.stroke_direction == "extend" else c.dead_volume_m3

    @property
    def load_force_n(self) -> float:
        """Constant force [N] on the piston along the stroke's motion (negative: opposing):
        gravity on the moving mass at the mounting angle, and the external force, which opposes
        the stroke. Extending a cylinder with its rod up lifts the load."""
        sign = 1.0 if self.stroke_direction == "extend" else -1.0
        lift = self.moving_mass_kg * STANDARD_GRAVITY * math.sin(
            math.radians(self.cylinder.mounting_angle_deg))
        return -sign * lift - self.external_force_n

    def cannot_move(self) -> str | None:
        """Why the supply can never move the piston (its force at full supply, with the loads
        along the motion, does not beat the static friction), or None."""
        force = self.supply_pressure_gauge_pa * self.drive_piston_area_m2 + self.load_force_n
        if force > self.friction.static_n:
            return None
        load = (f" (with {self.load_force_n:+.4g} N of gravity and external force along the "
                f"motion)" if self.load_force_n else "")
        return (f"the supply ({self.supply_pressure_gauge_pa:g} Pa gauge) pushes the piston with "
                f"at most {force:.4g} N{load}, not more than the static friction "
                f"FrictionParams.static_n = {self.friction.static_n:g} N: the piston can never "
                f"move (supply in bar given as Pa, a bore in mm given as m, or friction too high?)")

    @property
    def valve_delay_s(self) -> float:
        return self.valve.delay_for(self.supply_pressure_gauge_pa)

    # -- construction helpers --------------------------------------------------------------
    def with_(self, **changes: Any) -> "RigParams":
        """Copy with changes; nested groups take dicts, e.g. ``with_(friction={"static_n": 300})``.
        Unknown names are refused with the nearest known one."""
        kw: dict[str, Any] = {}
        names = [f.name for f in fields(self)]
        for k, v in changes.items():
            if k not in names:
                raise ValueError(f"RigParams has no field {k!r}{did_you_mean(k, names)}; "
                                 f"fields: {names}")
            if k in _GROUPS:
                kw[k] = _group_value(getattr(self, k), k, v)
            elif dataclasses.is_dataclass(v) or isinstance(v, Mapping):
                raise ValueError(f"RigParams.{k} = {v!r} is invalid: must be a finite number")
            else:
                kw[k] = v
        return replace(self, **kw)

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain data: the top-level numbers and one dict per group (the
        parameter form of a rig file, :mod:`pneugym.rigfile`); :meth:`from_dict` inverts it."""
        return dataclasses.asdict(self)

    @classmethod
    def load(cls, path: str | os.PathLike[str], base: "RigParams | None" = None) -> "RigParams":
        """The rig in a rig file (``.json``, ``.yaml``, ``.yml``; :func:`pneugym.rigfile.load`):
        the parameter form, the measurement form or a measured run's JSON; what the file does
        not give keeps ``base`` (default: the thesis rig). Refusals name the file and the key."""
        from .rigfile import load

        return load(path, base)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write this rig to a ``.json``, ``.yaml`` or ``.yml`` file, atomically; returns its
        ``Path``. :meth:`load` gives back an equal rig (:func:`pneugym.rigfile.save`)."""
        from .rigfile import save

        return save(self, path)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "RigParams":
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming the nearest."""
        if not isinstance(d, Mapping) or not all(isinstance(k, str) for k in d):
            raise ValueError(f"RigParams.from_dict needs a mapping of field names, got {d!r}")
        base = cls()
        return base.with_(**{k: (dict(v) if isinstance(v, Mapping) else v) for k, v in d.items()})

    @classmethod
    def from_measurement(cls, meta: Mapping[str, Any], base: "RigParams | None" = None) -> "RigParams":
        """Rig from a measured run's JSON (``pneugym-measurement/1``); missing keys keep ``base``.
        Unknown keys of the ``rig`` section are refused with the nearest known one; values are
        taken as given (a string or ``None`` is refused by the field it maps to)."""
        if not isinstance(meta, Mapping):
            raise ValueError(f"a measured run's JSON must be an object, got {meta!r:.80}")
        base = base or cls()
        rig = meta.get("rig") or {}
        if not isinstance(rig, Mapping):
            raise ValueError(f"key 'rig' must be an object, got {rig!r:.80}")
        fr = rig.get("friction") or {}
        if not isinstance(fr, Mapping):
            raise ValueError(f"key 'rig.friction' must be an object, got {fr!r:.80}")
        groups: dict[str, dict[str, Any]] = {}
        for section, keys, items in (("rig", MEASUREMENT_RIG_KEYS, rig.items()),
                                     ("rig.friction", MEASUREMENT_FRICTION_KEYS, fr.items())):
            for key, value in items:
                if section == "rig" and key == "friction":
                    continue
                if key not in keys:
                    raise ValueError(f"key {section}.{key!s} is unknown{did_you_mean(key, keys)}; "
                                     f"known: {sorted(keys)}")
                g, name = keys[key]
                groups.setdefault(g, {})[name] = value
        if "delay_s" in groups.get("valve", {}):
            groups["valve"]["delay_scale"] = 1.0  # the format states the delay itself, scale included
        top = {k: meta[k] for k in MEASUREMENT_TOP_FIELDS if k in meta}
        gas = {k: meta[k] for k in ("ambient_pressure_pa", "ambient_temperature_k") if k in meta}
        if gas:
            groups["gas"] = gas
        return base.with_(**top, **groups)

    def to_measurement_rig(self) -> dict[str, Any]:
        """The ``rig`` section of the measured-run format for these parameters."""
        c, ln, v, f = self.cylinder, self.line, self.valve, self.friction
        return {
            "bore_m": c.bore_m, "rod_m": c.rod_m, "stroke_m": c.stroke_m,
            "dead_volume_m3": c.dead_volume_m3, "line_length_m": ln.length_m,
            "line_diameter_m": ln.diameter_m, "valve_area_m2": v.area_m2,
            "port_area_m2": c.port_area_m2, "exhaust_area_m2": v.exhaust_area_m2,
            "cushion_length_m": c.cushion_length_m, "cushion_factor_drive": c.cushion_factor_drive,
            "cushion_factor_exhaust": c.cushion_factor_exhaust,
            "discharge_coefficient": v.discharge_coefficient, "valve_delay_s": self.valve_delay_s,
            "moving_mass_extra_kg": c.moving_mass_extra_kg,
            "friction": {"static_n": f.static_n, "coulomb_n": f.coulomb_n,
                         "viscous_n_s_per_m": f.viscous_n_s_per_m},
            **{key: getattr(c, name) for key, (_, name) in MEASUREMENT_RIG_KEYS.items()
               if name in _CYLINDER_FORM and getattr(c, name) != _CYLINDER_FORM[name]},
        }


#: cylinder fields a measured run's rig section states only when they differ from these (files
#: of double-rod horizontal cylinders keep the keys they always had)
_CYLINDER_FORM = {"design": "double-rod", "dead_volume_rod_m3": None, "mounting_angle_deg": 0.0}


def _group_value(cur: Any, name: str, v: Any) -> Any:
    """The new value of group ``name``: a dict of changes to ``cur``, or an instance."""
    cls = _GROUPS[name]
    if isinstance(v, cls):
        return v
    if not isinstance(v, Mapping):
        raise ValueError(f"RigParams.{name} = {v!r} is invalid: must be a dict of "
                         f"{cls.__name__} fields or a {cls.__name__}")
    known = [f.name for f in fields(cls)]
    unknown = [k for k in v if k not in known]
    if unknown:
        hints = "".join(did_you_mean(k, known) for k in unknown[:1])
        raise ValueError(f"{cls.__name__} has no field(s) {sorted(map(str, unknown))}{hints}; "
                         f"fields: {known}")
    return replace(cur, **dict(v))


def thesis_rig(supply_bar_gauge: float = 2.5, **changes: Any) -> RigParams:
    """The thesis rig at 1.5 or 2.5 bar (gauge) supply with 10 kg payload."""
    return RigParams(supply_pressure_gauge_pa=supply_bar_gauge * 1e5).with_(**changes)
