"""Operating conditions of one episode and the distributions they are drawn from.

A :class:`Conditions` is everything that makes one stroke differ from another on the same rig:
supply set-point, load, friction and valve-delay scales, a supply-pressure dip and the sensor
noise. A :class:`ConditionSpace` says how to draw them (each field a fixed value or a uniform
``(low, high)`` range); :data:`PRESETS` names the standard ones. All draws go through the
``numpy.random.Generator`` handed in (the environment's ``np_random``), so a seed reproduces them.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from ..params import RigParams, _check, _finite, _nonneg, _positive, did_you_mean
from .family import RigFamily, StrokeRefused, apply_changes, check_changes, draw_substep


@dataclass(frozen=True)
class Conditions:
    """The conditions of one episode (SI units, gauge supply pressure).

    ``friction_scale`` multiplies the static, Coulomb and viscous friction; ``valve_delay_scale``
    the rig's switching delay at this supply pressure. The dip lowers the supply by ``dip_depth``
    times its gauge pressure along a raised cosine (``dip_duration_s = 0``: no dip). Sensor noise
    is white and Gaussian, with these standard deviations, on the sampled sensors only.
    ``rig_changes`` (``(dotted field, value)`` pairs, :mod:`pneugym.envs.family`) change the rig
    itself for this episode, before the other fields apply.
    """

    supply_pressure_gauge_pa: float = 250_000.0
    load_mass_kg: float = 10.0
    friction_scale: float = 1.0
    valve_delay_scale: float = 1.0
    dip_start_s: float = 0.0
    dip_duration_s: float = 0.0
    dip_depth: float = 0.0
    position_noise_m: float = 0.0
    pressure_noise_pa: float = 0.0
    rig_changes: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        _finite(self)
        object.__setattr__(self, "rig_changes", check_changes(self.rig_changes,
                                                              "Conditions.rig_changes"))
        _positive(self, "supply_pressure_gauge_pa", "valve_delay_scale")
        _nonneg(self, "load_mass_kg", "friction_scale", "dip_start_s", "dip_duration_s",
                "position_noise_m", "pressure_noise_pa")
        _check(self, "dip_depth", 0 <= self.dip_depth < 1, "in [0, 1)")

    @property
    def supply_bar_gauge(self) -> float:
        return self.supply_pressure_gauge_pa / 1e5

    @property
    def dip(self) -> tuple[float, float, float]:
        """``(start_s, duration_s, depth)`` for :meth:`pneugym.plant.Plant.set_supply_dip`."""
        return self.dip_start_s, self.dip_duration_s, self.dip_depth

    def rig(self, base: RigParams | None = None) -> RigParams:
        """``base`` (default: the thesis rig) under these conditions."""
        base = apply_changes(base or RigParams(), self.rig_changes)
        rig = base.with_(supply_pressure_gauge_pa=float(self.supply_pressure_gauge_pa),
                         load_mass_kg=float(self.load_mass_kg))
        f = rig.friction
        s = self.friction_scale
        return rig.with_(
            friction={"static_n": f.static_n * s, "coulomb_n": f.coulomb_n * s,
                      "viscous_n_s_per_m": f.viscous_n_s_per_m * s},
            # the delay as the plant uses it (the rig's own scale included), scaled once
            valve={"delay_s": rig.valve_delay_s * self.valve_delay_scale, "delay_scale": 1.0})

    def physics_key(self) -> tuple[float, ...]:
        """The fields that change the plant's motion (not the sensor noise)."""
        return (self.supply_pressure_gauge_pa, self.load_mass_kg, self.friction_scale,
                self.valve_delay_scale, self.dip_start_s, self.dip_duration_s, self.dip_depth,
                self.rig_changes)

    def noise_free(self) -> Conditions:
        """The same conditions without sensor noise (the same :meth:`physics_key`)."""
        return dataclasses.replace(self, position_noise_m=0.0, pressure_noise_pa=0.0)

    def to_dict(self) -> dict[str, Any]:
        """The fields; ``rig_changes`` as a dict (JSON-ready; :func:`as_conditions` takes it
        back)."""
        d = dataclasses.asdict(self)
        d["rig_changes"] = dict(d["rig_changes"])
        return d


Range = tuple[float, float]


def _number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _as_range(name: str, value: Any) -> Range:
    """A number (fixed) or a ``(low, high)`` pair of numbers; strings are refused, never read
    character by character."""
    if _number(value):
        lo = hi = float(value)
    elif isinstance(value, (tuple, list, np.ndarray)) and len(value) == 2 \
            and all(_number(v) for v in value):
        lo, hi = (float(v) for v in value)
    else:
        raise ValueError(f"ConditionSpace.{name} must be a number or a (low, high) pair of "
                         f"numbers; got {value!r}")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"ConditionSpace.{name} = {value!r}: need finite low <= high")
    return lo, hi


@dataclass(frozen=True)
class ConditionSpace:
    """Uniform ranges ``(low, high)`` to draw :class:`Conditions` from (a number = fixed).

    A dip happens with probability ``dip_probability``; its depth, duration and start are then
    drawn from their ranges (the start counted from the extend command). With a ``family``
    (:class:`~pneugym.envs.family.RigFamily`) each draw also draws a rig (``rig_changes``), and a
    draw whose conventional stroke is too slow is redrawn; else ``rig_changes`` are fixed.
    """

    supply_pressure_gauge_pa: Range = (250_000.0, 250_000.0)
    load_mass_kg: Range = (10.0, 10.0)
    friction_scale: Range = (1.0, 1.0)
    valve_delay_scale: Range = (1.0, 1.0)
    dip_probability: float = 0.0
    dip_depth: Range = (0.0, 0.0)
    dip_duration_s: Range = (0.0, 0.0)
    dip_start_s: Range = (0.0, 0.0)
    position_noise_m: Range = (0.0, 0.0)
    pressure_noise_pa: Range = (0.0, 0.0)
    family: RigFamily | None = None
    rig_changes: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if self.family is not None and not isinstance(self.family, RigFamily):
            raise ValueError(f"ConditionSpace.family = {self.family!r:.80} must be a RigFamily "
                             f"or None")
        object.__setattr__(self, "rig_changes", check_changes(self.rig_changes,
                                                              "ConditionSpace.rig_changes"))
        for f in fields(self):
            if f.name in ("family", "rig_changes"):
                continue
            if f.name == "dip_probability":
                if not (_number(self.dip_probability) and 0.0 <= self.dip_probability <= 1.0):
                    raise ValueError(f"ConditionSpace.dip_probability = {self.dip_probability!r} "
                                     f"must be in [0, 1]")
                continue
            object.__setattr__(self, f.name, _as_range(f.name, getattr(self, f.name)))
        # the extremes must make valid conditions
        for pick in (0, 1):
            Conditions(**{f.name: getattr(self, f.name)[pick] for f in fields(Conditions)
                          if f.name != "rig_changes"})

    def with_(self, **changes: Any) -> "ConditionSpace":
        names = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise ValueError(f"ConditionSpace has no field(s) {unknown}"
                             f"{did_you_mean(unknown[0], names)}; known: {sorted(names)}")
        return dataclasses.replace(self, **changes)

    def sample(self, rng: np.random.Generator, base: RigParams | None = None) -> Conditions:
        """Draw one :class:`Conditions` (a fixed number of draws, so streams stay aligned); with a
        ``family``, a rig too, on ``base`` (default the thesis rig), redrawn until the
        conventional stroke completes within the family's ``max_conventional_time_s``."""
        if self.family is None:
            return self._sample(rng, self.rig_changes)
        base = base or RigParams()
        for _ in range(100):
            cond = self._sample(rng, ())
            changes = self.family.sample(rng, base)
            cond = dataclasses.replace(cond, rig_changes=changes)
            try:
                dt = draw_substep(cond, base, self.family)
            except StrokeRefused:
                continue
            if dt is not None:  # the plant needed a smaller substep: every episode takes it
                cond = dataclasses.replace(cond, rig_changes=changes + (("solver.dt_s", dt),))
            return cond
        raise ValueError(f"{self.family} draws no rig whose conventional stroke completes within "
                         f"{self.family.max_conventional_time_s} s in 100 tries: widen "
                         f"max_conventional_time_s or narrow the ranges")

    def _sample(self, rng: np.random.Generator, changes: tuple) -> Conditions:
        u = rng.random(10)

        def pick(name: str, k: int) -> float:
            lo, hi = getattr(self, name)
            return lo + (hi - lo) * float(u[k])

        dip = float(u[4]) < self.dip_probability
        return Conditions(
            supply_pressure_gauge_pa=pick("supply_pressure_gauge_pa", 0),
            load_mass_kg=pick("load_mass_kg", 1),
            friction_scale=pick("friction_scale", 2),
            valve_delay_scale=pick("valve_delay_scale", 3),
            dip_depth=pick("dip_depth", 5) if dip else 0.0,
            dip_duration_s=pick("dip_duration_s", 6) if dip else 0.0,
            dip_start_s=pick("dip_start_s", 7) if dip else 0.0,
            position_noise_m=pick("position_noise_m", 8),
            pressure_noise_pa=pick("pressure_noise_pa", 9),
            rig_changes=changes,
        )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def outside(self, supply_pressure_gauge_pa: float, load_mass_kg: float) -> list[str]:
        """What of an operating point (supply set-point [Pa gauge], load [kg]) lies outside the
        ranges this space draws, e.g. ``["supply 6 bar g outside 1.5-5"]`` (empty if nothing
        does). The operating point is what a rig file states and a user sets; the other fields
        scale what a rig file states (a family varies the rig itself)."""
        out = []
        for name, field, value, unit, scale in (
                ("supply", "supply_pressure_gauge_pa", supply_pressure_gauge_pa, "bar g", 1e-5),
                ("load", "load_mass_kg", load_mass_kg, "kg", 1.0)):
            lo, hi = getattr(self, field)
            if not lo - 1e-9 * abs(lo) <= value <= hi + 1e-9 * abs(hi):
                out.append(f"{name} {value * scale:g} {unit} outside {lo * scale:g}-{hi * scale:g}")
        return out


def as_conditions(c: Any, what: str = "conditions") -> Conditions:
    """``c`` as :class:`Conditions`: an instance, or a mapping of its fields (unknown names are
    refused with the nearest known one)."""
    if isinstance(c, Conditions):
        return c
    if not isinstance(c, Mapping):
        raise ValueError(f"{what} = {c!r} is invalid: must be Conditions or a dict of its fields")
    known = [f.name for f in fields(Conditions)]
    unknown = [k for k in c if k not in known]
    if unknown:
        raise ValueError(f"{what}: Conditions has no field {unknown[0]!r}"
                         f"{did_you_mean(unknown[0], known)}; fields: {known}")
    return Conditions(**c)


def fixed(c: Conditions) -> ConditionSpace:
    """The space that always draws ``c``."""
    d = c.to_dict()
    d.pop("rig_changes", None)
    return ConditionSpace(dip_probability=1.0 if c.dip_duration_s > 0 else 0.0,
                          rig_changes=c.rig_changes, **{k: (v, v) for k, v in d.items()})


PRESETS: dict[str, ConditionSpace] = {
    # the thesis's two operating points: nominal rig, 10 kg, no disturbance
    "thesis-1.5bar": ConditionSpace(supply_pressure_gauge_pa=150_000.0),
    "thesis-2.5bar": ConditionSpace(supply_pressure_gauge_pa=250_000.0),
    # domain randomisation for learning robust policies
    "randomized": ConditionSpace(
        supply_pressure_gauge_pa=(150_000.0, 500_000.0), load_mass_kg=(5.0, 30.0),
        friction_scale=(0.7, 1.3), valve_delay_scale=(0.8, 1.2),
        dip_probability=0.5, dip_depth=(0.0, 0.3), dip_duration_s=(0.05, 0.3),
        dip_start_s=(0.0, 1.0), position_noise_m=(0.0, 3e-5), pressure_noise_pa=(0.0, 400.0)),
    # a family of rigs (pneugym.envs.family): each episode its own rig, load and supply, as well
    # as the disturbances of "randomized"
    "family": ConditionSpace(
        supply_pressure_gauge_pa=(150_000.0, 600_000.0), load_mass_kg=(2.0, 40.0),
        dip_probability=0.5, dip_depth=(0.0, 0.3), dip_duration_s=(0.05, 0.3),
        dip_start_s=(0.0, 1.0), position_noise_m=(0.0, 3e-5), pressure_noise_pa=(0.0, 400.0),
        family=RigFamily()),
    # the family with the cylinders users have: half of the draws single-rod, half inclined
    # (-90 to +90 degrees: lifting or lowering the load as they extend)
}
PRESETS["family-cylinders"] = PRESETS["family"].with_(
    family=RigFamily(p_single_rod=0.5, p_inclined=0.5))


#: The preset of a rig's own operating point (its supply and load), no disturbance.
RIG_PRESET = "rig"


def operating_point(rig: RigParams | None = None) -> ConditionSpace:
    """The space that always draws ``rig``'s own supply and load (default: the thesis rig at
    2.5 bar and 10 kg, the same conditions as ``"thesis-2.5bar"``)."""
    rig = rig or RigParams()
    return ConditionSpace(supply_pressure_gauge_pa=rig.supply_pressure_gauge_pa,
                          load_mass_kg=rig.load_mass_kg)


#: Every preset name :func:`resolve` takes.
PRESET_NAMES = sorted([*PRESETS, RIG_PRESET])


def resolve(preset: str | ConditionSpace | Conditions | None,
            overrides: Mapping[str, Any] | None = None,
            rig: RigParams | None = None) -> ConditionSpace:
    """A :class:`ConditionSpace` from a preset name, a space or fixed conditions, with field
    overrides (numbers or ranges). ``None`` or ``"rig"``: the operating point of ``rig``
    (:func:`operating_point`; for the thesis rig the same as ``"thesis-2.5bar"``)."""
    if preset is None or preset == RIG_PRESET:
        space = operating_point(rig)
    elif isinstance(preset, ConditionSpace):
        space = preset
    elif isinstance(preset, Conditions):
        space = fixed(preset)
    elif isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}{did_you_mean(preset, PRESET_NAMES)}; "
                             f"choose one of {PRESET_NAMES}")
        space = PRESETS[preset]
    else:
        raise ValueError(f"preset must be a name, a ConditionSpace or Conditions; got {preset!r}")
    if overrides is not None and not isinstance(overrides, Mapping):
        raise ValueError(f"conditions = {overrides!r:.80} must be a dict of ConditionSpace fields "
                         f"(e.g. {{'load_mass_kg': (5, 30)}}); a named set of conditions is a "
                         f"preset (preset={overrides!r:.40})")
    return space.with_(**dict(overrides)) if overrides else space


__all__ = ["Conditions", "ConditionSpace", "PRESETS", "PRESET_NAMES", "RIG_PRESET", "resolve",
           "operating_point", "fixed", "as_conditions"]
