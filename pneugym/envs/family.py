"""A family of rigs: each episode draws its own rig, so that a policy learns how to cut off air
rather than one rig's timing.

:class:`RigFamily` holds realistic ranges for what differs from one installation to the next
(dead volume, supply line, valve, port and exhaust areas, cushions, friction, valve delay) and the
model form (finite-difference or lumped line, thesis or ISO 6358 orifices, the cushion transition,
small leaks, heat transfer), so that a policy cannot lean on one simulator's quirks.
:meth:`RigFamily.sample` draws the changes to a base rig as ``((dotted field, value), ...)``,
which :class:`~pneugym.envs.conditions.Conditions` carries as ``rig_changes``: the rig is then
part of an episode's conditions (its oracle, its conventional figures, every cache key).
Bore, rod and stroke stay the base rig's (the observation scales the position by the stroke);
the cylinder's design (single-rod) and mounting angle are drawn when the family asks for them.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from ..params import RigParams, did_you_mean

Range = tuple[float, float]
Change = tuple[str, Any]

#: the rig fields a family (and ``Conditions.rig_changes``) may set, dotted
CHANGEABLE = (
    "cylinder.dead_volume_m3", "cylinder.port_area_m2", "cylinder.cushion_length_m",
    "cylinder.cushion_factor_drive", "cylinder.cushion_factor_exhaust", "cylinder.cushion_ramp_m",
    "line.length_m", "line.diameter_m", "line.model", "valve.area_m2", "valve.exhaust_area_m2",
    "valve.delay_s", "valve.flow_model", "friction.static_n", "friction.coulomb_n",
    "friction.viscous_n_s_per_m", "effects.leak_drive_area_m2", "effects.leak_piston_area_m2",
    "effects.heat_transfer_time_constant_s", "effects.stribeck_force_n",
    "effects.stribeck_velocity_m_s", "effects.sensor_lag_s",
    "solver.dt_s", "cylinder.design", "cylinder.mounting_angle_deg", "cylinder.dead_volume_rod_m3",
)


#: the rig fields a :class:`RigFamily` draws (the others stay the base rig's)
FAMILY_FIELDS = (
    "cylinder.dead_volume_m3", "cylinder.port_area_m2", "cylinder.cushion_length_m",
    "cylinder.cushion_factor_drive", "cylinder.cushion_factor_exhaust", "cylinder.cushion_ramp_m",
    "line.length_m", "line.diameter_m", "line.model", "valve.area_m2", "valve.exhaust_area_m2",
    "valve.delay_s", "valve.flow_model", "friction.static_n", "friction.coulomb_n",
    "friction.viscous_n_s_per_m", "effects.leak_drive_area_m2",
    "effects.heat_transfer_time_constant_s",
)


def apply_changes(base: RigParams, changes: tuple[Change, ...]) -> RigParams:
    """``base`` with ``changes`` (``(dotted field, value)`` pairs) applied."""
    if not changes:
        return base
    groups: dict[str, dict[str, Any]] = {}
    for path, value in changes:
        g, name = path.split(".", 1)
        groups.setdefault(g, {})[name] = value
    if "delay_s" in groups.get("valve", {}):
        groups["valve"]["delay_scale"] = 1.0  # a delay set here is the delay, not scaled again
    return base.with_(**groups)


class StrokeRefused(ValueError):
    """A drawn rig whose conventional stroke does not complete in time, or chatters into the
    end (:func:`checked_substep`): the draw is redrawn; any other ``ValueError`` is a real one."""


def checked_substep(rig: RigParams, dip: tuple[float, float, float], t_max_s: float,
                    max_sticks: int | None = None) -> float | None:
    """Simulate ``rig``'s conventional stroke (with the supply ``dip``): ``None`` if it ran at the
    automatic substep, else the smaller substep [s] the plant fell back to (a rig where the
    automatic bound is too loose for the valve opening onto the empty line: some long, thin FD
    lines fed by a valve wider than the tube). Raises :class:`StrokeRefused` if the piston does not
    arrive within ``t_max_s``, or if its conventional stroke sticks and slips more than
    ``max_sticks`` times (a cushion set so that the piston chatters into the end)."""
    import warnings

    from ..plant import Plant, RigWarning

    plant = Plant(rig)
    plant.set_supply_dip(*dip)
    dt0 = plant.dt_s
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RigWarning)
        plant.advance(t_max_s, command=1, stop_on_arrival=True)
    if plant.arrival_time_s is None:
        raise StrokeRefused(f"the conventional stroke does not complete within {t_max_s} s")
    if max_sticks is not None:
        from .episode import stick_slips

        n = int(stick_slips(plant.d))
        if n > max_sticks:
            raise StrokeRefused(f"the conventional stroke sticks and slips {n} times")
    return None if plant.dt_s == dt0 else float(plant.dt_s)


def draw_substep(cond: Any, base: RigParams, family: "RigFamily") -> float | None:
    """:func:`checked_substep` of a family draw's conditions ``cond`` on ``base``: raises
    :class:`StrokeRefused` for a draw to redraw, a ``ValueError`` saying so for a rig the plant
    refuses (the base or the ranges are wrong, not the draw)."""
    try:
        rig = cond.rig(base)
    except ValueError as exc:
        raise ValueError(f"the rig family draws a rig the plant refuses on this base: {exc}"
                         ) from exc
    return checked_substep(rig, cond.dip, family.max_conventional_time_s,
                           family.max_conventional_sticks)


def check_changes(changes: Any, what: str = "rig_changes") -> tuple[Change, ...]:
    """``changes`` as a sorted tuple of ``(dotted field, value)`` pairs of :data:`CHANGEABLE`
    fields (a mapping or pairs, e.g. from JSON, are accepted); anything else is refused."""
    if isinstance(changes, Mapping):
        changes = list(changes.items())
    try:
        pairs = [(p, v) for p, v in changes]
    except (TypeError, ValueError):
        raise ValueError(f"{what} = {changes!r:.120} is invalid: must be (field, value) pairs, "
                         f"e.g. (('line.length_m', 2.0),)") from None
    out = {}
    for p, v in pairs:
        if p not in CHANGEABLE:
            raise ValueError(f"{what}: {p!r} is not a rig field a family sets"
                             f"{did_you_mean(p, CHANGEABLE)}; known: {list(CHANGEABLE)}")
        if p in out:
            raise ValueError(f"{what}: {p!r} is given twice")
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (str, int, float, np.number)):
            raise ValueError(f"{what}: {p} = {v!r} must be a number or, for a model form, a name")
        out[p] = v if isinstance(v, str) else float(v)
    return tuple(sorted(out.items()))


def _real(v: Any) -> bool:
    """A real number, not a bool (nor a string that float() would read)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _range(name: str, v: Any, lo_ok: float = 0.0) -> Range:
    if not (isinstance(v, (tuple, list)) and len(v) == 2 and all(map(_real, v))):
        raise ValueError(f"RigFamily.{name} = {v!r} must be a (low, high) pair of numbers")
    lo, hi = (float(x) for x in v)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo_ok <= lo <= hi):
        raise ValueError(f"RigFamily.{name} = {v!r}: need finite {lo_ok:g} <= low <= high")
    return lo, hi


@dataclass(frozen=True)
class RigFamily:
    """Ranges a rig is drawn from (SI units). ``*_scale`` ranges multiply the base rig's value;
    ``log`` ranges are drawn log-uniformly (areas, volumes, lengths, factors), the others
    uniformly. ``p_*`` are the probabilities of each model form or effect. A draw whose
    conventional stroke takes longer than ``max_conventional_time_s`` (valve delay included) at
    the episode's supply and load is redrawn (:meth:`~pneugym.envs.conditions.ConditionSpace.
    sample`), so every episode can complete within the time limit; so is one whose conventional
    stroke sticks and slips more than ``max_conventional_sticks`` times (its cushion makes the
    piston chatter into the end: no one runs a rig so adjusted, and the objective, which counts
    every event, would then prefer not moving at all).

    Cylinders: with probability ``p_single_rod`` a draw makes the base cylinder single-rod (the
    cap side drives the extension, the rod side keeps the drawn dead volume), with probability
    ``p_inclined`` it mounts it at an angle drawn uniformly from ``mounting_angle_deg`` (+90:
    rod up, the extension lifts the load). Both are 0 by default: the default family draws
    exactly the rigs it always drew (the transfer suite's held-out rigs among them); the
    ``"family-cylinders"`` preset of :mod:`pneugym.envs.conditions` turns them on."""

    dead_volume_m3: Range = (2e-5, 5e-4)
    line_length_m: Range = (0.3, 5.0)
    line_diameter_m: Range = (0.004, 0.008)
    valve_area_scale: Range = (0.3, 3.0)
    port_area_scale: Range = (0.3, 3.0)
    exhaust_area_scale: Range = (0.3, 3.0)
    cushion_length_m: Range = (0.005, 0.025)
    cushion_factor_drive: Range = (0.05, 1.0)
    cushion_factor_exhaust: Range = (0.005, 0.3)
    cushion_ramp_m: Range = (0.001, 0.004)
    static_friction_n: Range = (150.0, 600.0)
    coulomb_friction_n: Range = (60.0, 250.0)
    viscous_friction_n_s_per_m: Range = (500.0, 3000.0)
    valve_delay_s: Range = (0.02, 0.3)
    p_lumped_line: float = 0.3
    p_iso6358: float = 0.5
    p_leak: float = 0.25
    leak_area_m2: Range = (1e-8, 2e-7)
    p_heat_transfer: float = 0.25
    heat_transfer_time_constant_s: Range = (0.3, 3.0)
    max_conventional_time_s: float = 2.5
    max_conventional_sticks: int = 1
    p_single_rod: float = 0.0
    p_inclined: float = 0.0
    mounting_angle_deg: Range = (-90.0, 90.0)

    _LOG = ("dead_volume_m3", "line_length_m", "valve_area_scale", "port_area_scale",
            "exhaust_area_scale", "cushion_factor_drive", "cushion_factor_exhaust",
            "viscous_friction_n_s_per_m", "leak_area_m2", "heat_transfer_time_constant_s")

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("p_"):
                if not (_real(v) and 0.0 <= v <= 1.0):
                    raise ValueError(f"RigFamily.{f.name} = {v!r} must be a probability in [0, 1]")
            elif f.name == "max_conventional_sticks":
                if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                    raise ValueError(f"RigFamily.{f.name} = {v!r} must be an integer >= 0")
            elif f.name == "mounting_angle_deg":
                lo, hi = _range(f.name, (v[0] + 90.0, v[1] + 90.0) if isinstance(
                    v, (tuple, list)) and len(v) == 2 else v)
                if hi > 180.0:
                    raise ValueError(f"RigFamily.{f.name} = {v!r} must lie in [-90, 90] degrees")
                object.__setattr__(self, f.name, (lo - 90.0, hi - 90.0))
            elif f.name == "max_conventional_time_s":
                if not (_real(v) and 0.0 < v <= 3600.0):
                    raise ValueError(f"RigFamily.{f.name} = {v!r} must be in (0, 3600] s")
            else:
                object.__setattr__(self, f.name, _range(f.name, v, 1e-12 if f.name in self._LOG
                                                        else 0.0))
        # the extremes must make valid rigs, with each drawn form and effect on and off (a
        # probability's uniform at 0 turns it on where it can be on)
        chance = [i for i, k in enumerate((_DRAWS + _CYLINDER_DRAWS)[:self._n_draws])
                  if k.startswith("p_")]
        for pick in (0.0, 1.0):
            for on in (False, True):
                u = np.full(self._n_draws, pick)
                u[chance] = 0.0 if on else 1.0
                apply_changes(RigParams(), self._changes(u, RigParams()))

    @property
    def fields(self) -> tuple[str, ...]:
        """The rig fields this family's draws set (dotted): :data:`FAMILY_FIELDS`, and the
        cylinder's design and mounting angle when it draws them."""
        extra = ("cylinder.design", "cylinder.mounting_angle_deg") if self.draws_cylinders else ()
        return FAMILY_FIELDS + extra

    @property
    def draws_cylinders(self) -> bool:
        """Whether draws change the cylinder's design or mounting angle."""
        return self.p_single_rod > 0.0 or self.p_inclined > 0.0

    @property
    def _n_draws(self) -> int:
        """Uniforms per rig: the cylinder's only when drawn, so that the default family's
        streams are those it always had."""
        return len(_DRAWS) + (len(_CYLINDER_DRAWS) if self.draws_cylinders else 0)

    def _draw(self, name: str, u: float) -> float:
        lo, hi = getattr(self, name)
        if name in self._LOG:
            return float(math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u))
        return lo + (hi - lo) * u

    def _changes(self, u: np.ndarray, base: RigParams) -> tuple[Change, ...]:
        d = dict(zip(_DRAWS + _CYLINDER_DRAWS, u))
        c, v = base.cylinder, base.valve
        fs = self._draw("static_friction_n", d["fs"])
        leak = d["p_leak"] < self.p_leak
        heat = d["p_heat"] < self.p_heat_transfer
        changes = {
            "cylinder.dead_volume_m3": self._draw("dead_volume_m3", d["v0"]),
            "cylinder.port_area_m2": c.port_area_m2 * self._draw("port_area_scale", d["port"]),
            "cylinder.cushion_length_m": self._draw("cushion_length_m", d["cl"]),
            "cylinder.cushion_factor_drive": self._draw("cushion_factor_drive", d["cfd"]),
            "cylinder.cushion_factor_exhaust": self._draw("cushion_factor_exhaust", d["cfe"]),
            "cylinder.cushion_ramp_m": self._draw("cushion_ramp_m", d["ramp"]),
            "line.length_m": self._draw("line_length_m", d["len"]),
            "line.diameter_m": self._draw("line_diameter_m", d["dia"]),
            "line.model": "lumped" if d["p_lumped"] < self.p_lumped_line else "fd",
            "valve.area_m2": v.area_m2 * self._draw("valve_area_scale", d["valve"]),
            "valve.exhaust_area_m2": v.exhaust_area_m2 * self._draw("exhaust_area_scale", d["exh"]),
            "valve.delay_s": self._draw("valve_delay_s", d["delay"]),
            "valve.flow_model": "iso6358" if d["p_iso"] < self.p_iso6358 else "thesis",
            "friction.static_n": fs,
            # Coulomb friction below the breakaway force, as on every real seal
            "friction.coulomb_n": min(self._draw("coulomb_friction_n", d["fc"]), 0.9 * fs),
            "friction.viscous_n_s_per_m": self._draw("viscous_friction_n_s_per_m", d["kv"]),
            "effects.leak_drive_area_m2": self._draw("leak_area_m2", d["leak"]) if leak else 0.0,
            "effects.heat_transfer_time_constant_s": (
                self._draw("heat_transfer_time_constant_s", d["tau"]) if heat else 0.0),
        }
        if self.draws_cylinders:
            single = d["p_single"] < self.p_single_rod
            changes["cylinder.design"] = "single-rod" if single else c.design
            changes["cylinder.mounting_angle_deg"] = (
                self._draw("mounting_angle_deg", d["angle"]) if d["p_incl"] < self.p_inclined
                else c.mounting_angle_deg)
        return tuple(sorted(changes.items()))

    def outside(self, rig: RigParams, base: RigParams | None = None) -> list[str]:
        """The drawn quantities of ``rig`` outside this family's ranges (scales against
        ``base``, default the thesis rig), e.g. ``["line.length_m 6.5 not in [0.3, 5]"]``."""
        base = base or RigParams()
        c, v, f = rig.cylinder, rig.valve, rig.friction
        checks = (
            ("cylinder.dead_volume_m3", c.dead_volume_m3, self.dead_volume_m3),
            ("cylinder.port_area_m2", c.port_area_m2, tuple(
                s * base.cylinder.port_area_m2 for s in self.port_area_scale)),
            ("cylinder.cushion_length_m", c.cushion_length_m, self.cushion_length_m),
            ("cylinder.cushion_factor_drive", c.cushion_factor_drive, self.cushion_factor_drive),
            ("cylinder.cushion_factor_exhaust", c.cushion_factor_exhaust,
             self.cushion_factor_exhaust),
            ("line.length_m", rig.line.length_m, self.line_length_m),
            ("line.diameter_m", rig.line.diameter_m, self.line_diameter_m),
            ("valve.area_m2", v.area_m2, tuple(s * base.valve.area_m2
                                               for s in self.valve_area_scale)),
            ("valve.exhaust_area_m2", v.exhaust_area_m2, tuple(
                s * base.valve.exhaust_area_m2 for s in self.exhaust_area_scale)),
            ("valve delay [s]", rig.valve_delay_s, self.valve_delay_s),
            ("friction.static_n", f.static_n, self.static_friction_n),
            ("friction.coulomb_n", f.coulomb_n, (0.0, self.coulomb_friction_n[1])),
            ("friction.viscous_n_s_per_m", f.viscous_n_s_per_m, self.viscous_friction_n_s_per_m),
            ("effects.leak_drive_area_m2", rig.effects.leak_drive_area_m2,
             (0.0, self.leak_area_m2[1])),
        )
        if self.p_inclined > 0.0:
            (lo, hi), a0 = self.mounting_angle_deg, base.cylinder.mounting_angle_deg
            checks += (("cylinder.mounting_angle_deg", c.mounting_angle_deg,
                        (min(lo, a0), max(hi, a0))),)
        elif c.mounting_angle_deg != base.cylinder.mounting_angle_deg:
            checks += (("cylinder.mounting_angle_deg", c.mounting_angle_deg,
                        (base.cylinder.mounting_angle_deg,) * 2),)
        tol = 1e-9
        out = [f"{name} {val:.4g} not in [{lo:.4g}, {hi:.4g}]" for name, val, (lo, hi) in checks
               if not lo - tol * abs(lo) <= val <= hi + tol * abs(hi)]
        if c.design != base.cylinder.design and self.p_single_rod == 0.0:
            out.append(f"cylinder.design {c.design} not drawn (the family draws "
                       f"{base.cylinder.design} only)")
        return out

    def sample(self, rng: np.random.Generator, base: RigParams | None = None
               ) -> tuple[Change, ...]:
        """One rig's changes to ``base`` (default the thesis rig), from a fixed number of draws."""
        return self._changes(rng.random(self._n_draws), base or RigParams())

    def with_(self, **changes: Any) -> "RigFamily":
        names = [f.name for f in fields(self)]
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise ValueError(f"RigFamily has no field(s) {unknown}"
                             f"{did_you_mean(unknown[0], names)}; known: {names}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: the uniforms one rig draws, in order (adding one at the end keeps earlier streams)
_DRAWS = ("v0", "port", "cl", "cfd", "cfe", "ramp", "len", "dia", "p_lumped", "valve", "exh",
          "delay", "p_iso", "fs", "fc", "kv", "p_leak", "leak", "p_heat", "tau")
#: the uniforms of the cylinder's design and mounting, drawn after those (only when on)
_CYLINDER_DRAWS = ("p_single", "angle", "p_incl")

__all__ = ["RigFamily", "StrokeRefused", "draw_substep", "CHANGEABLE", "FAMILY_FIELDS", "apply_changes", "check_changes", "checked_substep"]
