"""Operating scenarios: one rig run for thousands of consecutive strokes while its hidden truth
drifts (seal wear, a shift's temperature, the compressor's pressure, the product's load, a leak).

A :class:`Scenario` gives each quantity as knots ``((stroke, value), ...)``, linear between knots
and held beyond them; a step is two knots one stroke apart. The truth changes every
``resolution`` strokes (a drift step: slow drift is piecewise constant, which lets the
drift-aware oracle plan once per step), with a seeded random jitter of the friction per step.
:meth:`Scenario.conditions` turns stroke ``k`` into the :class:`~pneugym.envs.Conditions` the plant
runs under. The controller never sees them: it sees its sensors, the supply set-point (the supply
pressure measured at the regulator, so a sagging compressor is seen), the payload (an operator
knows the product's mass) and the measured outcome of each stroke. Every quantity is in SI units (supply in Pa gauge, leak area in m^2, Cd included).
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..envs.conditions import Conditions
from ..params import did_you_mean

#: The drifting quantities and their plausible ranges (a value outside is refused).
QUANTITIES: dict[str, tuple[float, float, str]] = {
    "supply_pressure_gauge_pa": (0.5e5, 10e5, "supply pressure at the regulator [Pa gauge]"),
    "load_mass_kg": (0.0, 200.0, "payload [kg]"),
    "friction_scale": (0.2, 5.0, "factor on the rig's static, Coulomb and viscous friction"),
    "valve_delay_scale": (0.2, 5.0, "factor on the valve's switching delay"),
    "leak_drive_area_m2": (0.0, 1e-5, "leak from the driving chamber to atmosphere [m^2]"),
}
NOMINAL = {"supply_pressure_gauge_pa": 250_000.0, "load_mass_kg": 10.0, "friction_scale": 1.0,
           "valve_delay_scale": 1.0, "leak_drive_area_m2": 0.0}
#: Sensor noise of every stroke (standard deviations): as the robustness suite's worst case.
POSITION_NOISE_M = 3e-5
PRESSURE_NOISE_PA = 400.0

Knots = tuple[tuple[int, float], ...]
#: a rig's name in a scenario's (``wear@my_rig``)
RIG_LABEL = re.compile(r"[A-Za-z0-9_.-]{1,64}")
#: a scenario's name (``NAME`` or ``NAME@RIG``): it goes into run ids and report file names
SCENARIO_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}(@[A-Za-z0-9_.-]{1,64})?")


def _knots(name: str, value: Any) -> Knots:
    """``value`` as knots: a number (constant) or ``[(stroke, value), ...]`` with strictly
    increasing strokes >= 0, each value inside the quantity's range."""
    lo, hi, what = QUANTITIES[name]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        pts = ((0, float(value)),)
    else:
        try:
            pts = tuple((int(k), float(v)) for k, v in value)
        except (TypeError, ValueError):
            raise ValueError(f"Scenario {name} = {value!r}: give a number or a list of "
                             f"(stroke, value) knots") from None
    if not pts or any(b[0] <= a[0] for a, b in zip(pts, pts[1:])) or pts[0][0] < 0:
        raise ValueError(f"Scenario {name}: knots {pts!r} need strokes >= 0, strictly increasing")
    for k, v in pts:
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"Scenario {name} = {v!r} at stroke {k}: outside [{lo:g}, {hi:g}] "
                             f"({what})")
    return pts


@dataclass(frozen=True)
class Scenario:
    """A rig's operating life: each drifting quantity (:data:`QUANTITIES`) as knots, the strokes
    per hour (for per-hour and per-shift figures), the drift step ``resolution`` [strokes] and
    the standard deviation of the friction's random jitter per drift step."""

    name: str
    description: str = ""
    drift: Mapping[str, Any] = field(default_factory=dict)
    strokes_per_hour: float = 600.0
    shift_hours: float = 8.0
    resolution: int = 10
    friction_jitter: float = 0.02

    def __post_init__(self) -> None:
        if not (isinstance(self.name, str) and SCENARIO_NAME.fullmatch(self.name)):
            raise ValueError(f"Scenario name {self.name!r}: letters, digits, '_', '-' and '.' "
                             f"only, not starting with '.' (it goes into run ids and report "
                             f"file names)")
        unknown = [k for k in self.drift if k not in QUANTITIES]
        if unknown:
            raise ValueError(f"Scenario {self.name!r}: {unknown[0]!r} is not a drifting quantity"
                             f"{did_you_mean(unknown[0], QUANTITIES)}; they are "
                             f"{', '.join(QUANTITIES)}")
        knots = {k: _knots(k, self.drift.get(k, NOMINAL[k])) for k in QUANTITIES}
        object.__setattr__(self, "drift", knots)
        for name in ("strokes_per_hour", "shift_hours"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Scenario.{name} = {v!r} must be > 0")
        if not (isinstance(self.resolution, int) and self.resolution >= 1):
            raise ValueError(f"Scenario.resolution = {self.resolution!r}: an integer >= 1 "
                             f"(strokes per drift step)")
        if not 0.0 <= self.friction_jitter < 0.2:
            raise ValueError(f"Scenario.friction_jitter = {self.friction_jitter!r}: in [0, 0.2)")

    def value(self, name: str, stroke: int) -> float:
        """Quantity ``name`` at ``stroke`` (its drift step's start), without jitter."""
        pts = self.drift[name]
        k0 = stroke - stroke % self.resolution
        return float(np.interp(k0, [k for k, _ in pts], [v for _, v in pts]))

    def truth(self, stroke: int, seed: int) -> dict[str, float]:
        """The hidden truth at ``stroke``: every quantity, the friction with this drift step's
        jitter (drawn from ``default_rng([seed, step])``)."""
        if stroke < 0:
            raise ValueError(f"stroke = {stroke} must be >= 0")
        out = {k: self.value(k, stroke) for k in QUANTITIES}
        step = stroke // self.resolution
        if self.friction_jitter > 0:
            z = float(np.random.default_rng([seed, step]).normal())
            out["friction_scale"] *= math.exp(self.friction_jitter * max(-3.0, min(3.0, z)))
        return out

    def conditions(self, stroke: int, seed: int) -> Conditions:
        """The plant's :class:`~pneugym.envs.Conditions` at ``stroke`` (sensor noise included)."""
        t = self.truth(stroke, seed)
        changes = ((("effects.leak_drive_area_m2", t["leak_drive_area_m2"]),)
                   if t["leak_drive_area_m2"] > 0 else ())
        return Conditions(supply_pressure_gauge_pa=t["supply_pressure_gauge_pa"],
                          load_mass_kg=t["load_mass_kg"], friction_scale=t["friction_scale"],
                          valve_delay_scale=t["valve_delay_scale"],
                          position_noise_m=POSITION_NOISE_M, pressure_noise_pa=PRESSURE_NOISE_PA,
                          rig_changes=changes)

    def on_rig(self, rig: Any, label: str) -> "Scenario":
        """This life on another rig (a :class:`~pneugym.params.RigParams`), named
        ``NAME@label``: the scenarios are written for the thesis rig's operating point (2.5 bar
        gauge, 10 kg), so the supply and payload knots move by the factors of the rig's stated
        supply and payload to those; friction and valve delay are factors already, and a leak
        is the area it is (a fitting leaks alike on any cylinder)."""
        if not (isinstance(label, str) and RIG_LABEL.fullmatch(label)):
            raise ValueError(f"rig name {label!r}: letters, digits, '_', '-' and '.' only (it "
                             f"goes into the run's id, SCENARIO@RIG/seedN/CONTROLLER)")
        scale = {"supply_pressure_gauge_pa": rig.supply_pressure_gauge_pa
                 / NOMINAL["supply_pressure_gauge_pa"],
                 "load_mass_kg": rig.load_mass_kg / NOMINAL["load_mass_kg"]}
        drift = {k: tuple((s, v * scale.get(k, 1.0)) for s, v in pts)
                 for k, pts in self.drift.items()}
        try:
            return dataclasses.replace(self, name=f"{self.name}@{label}", drift=drift,
                                       description=f"{self.description} (on {label}: supply "
                                       f"x{scale['supply_pressure_gauge_pa']:.3g}, payload "
                                       f"x{scale['load_mass_kg']:.3g})")
        except ValueError as exc:
            raise ValueError(f"scenario {self.name!r} on rig {label!r} (supply "
                             f"{rig.supply_pressure_gauge_pa / 1e5:g} bar gauge, payload "
                             f"{rig.load_mass_kg:g} kg): {exc}") from None

    def hour(self, stroke: int) -> float:
        """Operating hours at the start of ``stroke``."""
        return stroke / self.strokes_per_hour

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (recorded with every run)."""
        d = dataclasses.asdict(self)
        d["drift"] = {k: [list(p) for p in v] for k, v in self.drift.items()}
        return d


def _s(name: str, description: str, **drift: Any) -> Scenario:
    return Scenario(name=name, description=description, drift=drift)


#: The named scenarios. Their lives are compressed: 5000 strokes hold what a cylinder sees in
#: a long time (wear), a shift (shift) or a production week (load-change).
SCENARIOS: dict[str, Scenario] = {s.name: s for s in (
    _s("healthy", "the thesis rig at 2.5 bar and 10 kg, nothing drifts (friction jitters 2 % per "
                  "drift step): the control for false alarms"),
    _s("wear", "seals wear: friction grows 60 %, the valve's delay 30 %, a leak grows to "
               "1.5e-7 m^2 in the second half",
       friction_scale=[(0, 1.0), (5000, 1.6)], valve_delay_scale=[(0, 1.0), (5000, 1.3)],
       leak_drive_area_m2=[(0, 0.0), (2500, 0.0), (5000, 1.5e-7)]),
    _s("shift", "an 8-hour shift: a cold start (friction +30 %) warming up, the compressor "
                "sagging from 3 to 2 bar at peak demand and recovering",
       friction_scale=[(0, 1.3), (1500, 1.0), (2500, 0.85), (5000, 1.0)],
       supply_pressure_gauge_pa=[(0, 3e5), (1000, 3e5), (2000, 2e5), (3000, 2e5),
                                 (4000, 3e5)]),
    _s("leak-onset", "healthy until stroke 2000, then a fitting starts leaking: 4e-7 m^2 by "
                     "stroke 2500, held",
       leak_drive_area_m2=[(0, 0.0), (2000, 0.0), (2500, 4e-7)]),
    _s("aging", "an old cylinder, beyond what the policies were trained on (friction +-30 %, "
                "valve delay +-20 %): friction doubles, the valve's delay grows 60 %, a leak grows "
                "to 2e-7 m^2",
       friction_scale=[(0, 1.0), (5000, 2.0)], valve_delay_scale=[(0, 1.0), (5000, 1.6)],
       leak_drive_area_m2=[(0, 0.0), (5000, 2e-7)]),
    _s("load-change", "the product changes: the load steps from 10 to 25 kg at stroke 1500 and "
                      "to 5 kg at stroke 3500",
       load_mass_kg=[(0, 10.0), (1499, 10.0), (1500, 25.0), (3499, 25.0), (3500, 5.0)]),
)}


def scenario(name: str | Scenario) -> Scenario:
    """A named scenario (:data:`SCENARIOS`) or the one given."""
    if isinstance(name, Scenario):
        return name
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}{did_you_mean(name, SCENARIOS)}; choose from "
                         f"{', '.join(SCENARIOS)}")
    return SCENARIOS[name]
