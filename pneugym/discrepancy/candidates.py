"""What the workflow fits: the nominal parameters (always) and the candidate effects.

Every fitted quantity is a :class:`FitParam`: a field of :class:`~pneugym.params.RigParams`
(``"group.field"``), its physical bounds, its null value (the value meaning *no effect*) and the
range the multi-start draws starting values from. The optimiser works on a transformed variable
``u`` of order one: ``u = ln(θ / ref) / step`` for log parameters, ``u = θ / ref`` otherwise.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..params import RigParams
from .residuals import PHASES


@dataclass(frozen=True)
class FitParam:
    """One fitted rig parameter (SI units, those of the field it names)."""

    path: str  # "group.field" of RigParams, e.g. "effects.sensor_lag_s"
    lo: float
    hi: float
    ref: float  # reference scale: u = θ/ref (linear) or ln(θ/ref)/log_step (log)
    log: bool = False
    log_step: float = 1.0
    null: float | None = None  # value meaning "no effect" (None: a shape parameter)
    start: tuple[float, float] | None = None  # plausible range for random starts (natural units)
    unit: str = ""
    diff_step: float | None = None  # finite-difference step in u (None: the fit's default)
    relative: bool = False  # the value is a factor on each run's stated value (unit "x stated")

    def __post_init__(self) -> None:
        if not (self.lo < self.hi) or (self.log and self.lo <= 0):
            raise ValueError(f"FitParam {self.path}: bounds must satisfy 0 < lo < hi (log) or lo < hi")
        if self.ref <= 0:
            raise ValueError(f"FitParam {self.path}: ref must be > 0")

    @property
    def name(self) -> str:
        return self.path.split(".", 1)[1]

    def stated(self, rig: RigParams) -> float:
        """The value that leaves ``rig`` as it is stated (1 for a relative parameter)."""
        return 1.0 if self.relative else read(rig, self.path)

    def to_u(self, value: float) -> float:
        v = min(max(float(value), self.lo), self.hi)
        return math.log(v / self.ref) / self.log_step if self.log else v / self.ref

    def from_u(self, u: float) -> float:
        return self.ref * math.exp(u * self.log_step) if self.log else u * self.ref

    def dvalue_du(self, u: float) -> float:
        return self.from_u(u) * self.log_step if self.log else self.ref

    @property
    def u_bounds(self) -> tuple[float, float]:
        return self.to_u(self.lo), self.to_u(self.hi)

    def draw(self, rng: np.random.Generator) -> float:
        """A random start (log-uniform over ``start`` for positive ranges, else uniform)."""
        a, b = self.start or (self.lo, self.hi)
        if a > 0:
            return float(math.exp(rng.uniform(math.log(a), math.log(b))))
        return float(rng.uniform(a, b))


@dataclass(frozen=True)
class Candidate:
    """A named model extension: the effect parameters it adds, and what it explains."""

    name: str
    params: tuple[FitParam, ...]
    explains: str = ""
    typical: Mapping[str, float] = field(default_factory=dict)  # first start (natural units)
    #: the phase of a run (one of ``residuals.PHASES``) where the effect shows most distinctly
    #: and the model's form matters least: the candidate must improve the fit there
    #: (``own_phase`` check) if a run has that phase. None: no such check.
    phase: str | None = None

    def __post_init__(self) -> None:
        if self.phase is not None and self.phase not in PHASES:
            raise ValueError(f"Candidate {self.name}: phase {self.phase!r} must be one of {PHASES}")

    @property
    def magnitude(self) -> tuple[FitParam, ...]:
        """The parameters with a null value: the effect is present if one is clearly away from it."""
        return tuple(p for p in self.params if p.null is not None)


def apply(base: RigParams, params: Sequence[FitParam], values: Sequence[float]) -> RigParams:
    """``base`` with the fitted values written into their fields."""
    groups: dict[str, dict[str, float]] = {}
    for p, v in zip(params, values):
        g, name = p.path.split(".", 1)
        groups.setdefault(g, {})[name] = float(v) * (read(base, p.path) if p.relative else 1.0)
    return base.with_(**groups)


def read(rig: RigParams, path: str) -> float:
    """The value of field ``"group.field"`` of ``rig``."""
    g, name = path.split(".", 1)
    return float(getattr(getattr(rig, g), name))


#: relative bounds of the nominal parameters freed beyond Cd and friction (``extended``)
EXTENDED = (
    # path, lo, hi, unit: factors on the value each run's JSON states
    ("valve.delay_scale", 0.8, 1.25, "x stated"),       # spool delay: when anything starts
    ("valve.exhaust_area_m2", 0.6, 1.6, "x stated"),    # exhaust path against the supply path
    ("cylinder.port_area_m2", 0.6, 1.6, "x stated"),    # line -> chamber restriction
    ("cylinder.cushion_length_m", 0.7, 1.4, "x stated"),  # where the end cushion begins
)


def nominal_params(rig: RigParams, extended: bool = True, relative_friction: bool = False,
                   relative_cd: float | None = None) -> tuple[FitParam, ...]:
    """The nominal parameters calibrated before any effect (issue step 2), around the values
    ``rig`` states: orifice discharge coefficient of all orifices (0.5x to 1.3x the stated
    value, at most 1), static (breakaway), Coulomb and viscous friction; log-scaled (one
    unit = 10 %), within physical bounds. With ``extended`` also the valve delay, the exhaust
    and port areas and the cushion length, as factors on each run's stated value
    (:data:`EXTENDED`): a real rig differs from its model in form as well as in numbers, and
    these parameters absorb much of that before any effect is tried. The dead volume is not
    freed: it is a candidate effect. With ``relative_friction`` the friction is fitted as
    factors on each run's stated friction (the same bounds and transformed variable), for runs
    that state friction of their own (each stroke's, :func:`pneugym.operation.monitor.monitor`).
    With ``relative_cd`` (the largest of the runs' stated coefficients, when they differ) the
    discharge coefficient is fitted as one factor on each run's stated value (the same bounds,
    each run's at most 1)."""
    cd = rig.valve.discharge_coefficient
    fr = rig.friction
    if relative_cd is not None:
        out = [FitParam("valve.discharge_coefficient", 0.5, min(1.0 / relative_cd, 1.3), 1.0,
                        log=True, log_step=0.1, unit="x stated", relative=True)]
    else:
        out = [FitParam("valve.discharge_coefficient", 0.5 * cd, min(1.0, 1.3 * cd), cd,
                        log=True, log_step=0.1, unit="-")]
    for name, val, default, lo_f, hi_f in (("static_n", fr.static_n, 359.0, 1 / 3, 3.0),
                                           ("coulomb_n", fr.coulomb_n, 126.0, 0.05, 4.0),
                                           ("viscous_n_s_per_m", fr.viscous_n_s_per_m, 1557.0, 0.02, 5.0)):
        ref = val if val > 0 else default
        unit = "N s/m" if name.startswith("viscous") else "N"
        rel = relative_friction and val > 0
        if rel:  # u = ln(factor) / 0.1 on the stated value: the same u as the absolute fit's
            ref, unit = 1.0, "x stated"
        # the breakaway moment is resolved to a substep: the SSR is a staircase in static_n,
        # so its finite difference spans several stairs (3 %)
        out.append(FitParam(f"friction.{name}", lo_f * ref, hi_f * ref, ref, log=True, log_step=0.1,
                            unit=unit, diff_step=0.3 if name == "static_n" else None,
                            relative=rel))
    if extended:
        for path, lo, hi, unit in EXTENDED:
            if path == "cylinder.cushion_length_m":  # a cushion stays shorter than half the stroke
                hi = min(hi, 0.499 * rig.cylinder.stroke_m / rig.cylinder.cushion_length_m)
            out.append(FitParam(path, lo, hi, 1.0, log=True, log_step=0.1, unit=unit, relative=True))
    return tuple(out)


#: The candidate effects (names as in ``EffectParams.active``).
CANDIDATES: dict[str, Candidate] = {c.name: c for c in (
    Candidate(
        "leakage",
        (FitParam("effects.leak_drive_area_m2", 0.0, 5e-6, 1e-7, null=0.0, start=(3e-8, 1e-6), unit="m²"),
         FitParam("effects.leak_piston_area_m2", 0.0, 5e-6, 1e-7, null=0.0, start=(3e-8, 1e-6), unit="m²")),
        "trapped pressure sagging after cut-off, exhaust pressure creeping up (seal leak)",
        {"leak_drive_area_m2": 1e-7, "leak_piston_area_m2": 1e-7}, phase="trapped"),
    Candidate(
        "heat_transfer",
        (FitParam("effects.heat_transfer_time_constant_s", 1e-3, 20.0, 1.0, log=True, null=0.0,
                  start=(0.05, 3.0), unit="s"),),
        "pressure overshoot on fast filling/expansion that relaxes as the air reaches wall temperature",
        {"heat_transfer_time_constant_s": 0.5}),
    Candidate(
        "stribeck_friction",
        (FitParam("effects.stribeck_force_n", 0.0, 1000.0, 100.0, null=0.0, start=(30.0, 300.0), unit="N"),
         FitParam("effects.stribeck_velocity_m_s", 1e-3, 0.3, 0.01, log=True, start=(0.005, 0.08),
                  unit="m/s")),
        "extra friction at low speed: slow breakaway, creeping end of stroke (velocity weakening)",
        {"stribeck_force_n": 100.0, "stribeck_velocity_m_s": 0.02}, phase="trapped"),
    Candidate(
        "sensor_lag",
        (FitParam("effects.sensor_lag_s", 0.0, 0.2, 0.01, null=0.0, start=(0.002, 0.04), unit="s"),),
        "measured pressures late on every fast change while the position fits",
        {"sensor_lag_s": 0.01}),
    Candidate(
        "dead_volume",
        (FitParam("effects.dead_volume_m3", 0.0, 2e-3, 1e-4, null=0.0, start=(1e-5, 4e-4), unit="m³"),),
        "slower pressure rise before motion, lower pressure after expansion (extra volume at the port)",
        {"dead_volume_m3": 5e-5}),
)}

#: A change an ageing rig makes beyond the five effects: its valve switches later than
#: commissioned (spool and seal wear, a slower pilot). The condition monitor tests it beside
#: the five effects (its basic calibration keeps the stated delay; a slower valve otherwise reads
#: as an extra dead volume). The workflow's extended calibration frees the delay itself, so there
#: it cannot be a candidate.
VALVE_DELAY = Candidate(
    "valve_delay",
    (FitParam("valve.delay_scale", 0.5, 3.0, 1.0, log=True, log_step=0.1, null=1.0,
              start=(0.8, 1.8), unit="x stated", relative=True),),
    "every pressure change and the motion start later than commissioned, their course as before "
    "(a slower valve: spool wear, a slow pilot)",
    {"delay_scale": 1.2})

#: Candidates beyond :data:`CANDIDATES`, by name (not tested unless asked for).
MORE_CANDIDATES: dict[str, Candidate] = {VALVE_DELAY.name: VALVE_DELAY}

#: Experiments that separate two candidates (keys: sorted name pairs).
SEPARATING_EXPERIMENTS: dict[tuple[str, str], str] = {
    ("heat_transfer", "leakage"):
        "a longer hold after cut-off (at least 5 s, piston at the end of stroke): a leak keeps the "
        "trapped pressure falling towards ambient, heat transfer settles within a few time constants",
    ("dead_volume", "sensor_lag"):
        "a slow supply ramp with the piston blocked: a lag only shifts the measured pressure in time, "
        "an extra volume changes how fast it rises for the same flow (record mdot_supply)",
    ("heat_transfer", "sensor_lag"):
        "hold the pressure after a fast fill: a sensor lag settles within tens of ms, heat transfer "
        "drifts over its time constant; or add a fast reference transducer",
    ("dead_volume", "heat_transfer"):
        "a slow fill (throttled supply, nearly isothermal) at the retracted end: an extra volume still "
        "slows the rise, heat transfer then has no effect",
    ("stribeck_friction", "sensor_lag"):
        "compare position and pressure timing: Stribeck friction delays the motion, a sensor lag only "
        "the measured pressures",
    ("leakage", "stribeck_friction"):
        "a hold with the piston blocked mid-stroke after cut-off: only a leak changes the pressure",
    ("dead_volume", "leakage"):
        "a hold after cut-off at the end of stroke: a leak lowers the pressure, a dead volume does not",
    ("leakage", "sensor_lag"):
        "a longer hold after cut-off: a lag settles in tens of ms, a leak keeps the pressure falling",
    ("dead_volume", "stribeck_friction"):
        "a fill with the piston blocked: a dead volume slows the pressure rise, friction does not act",
    ("heat_transfer", "stribeck_friction"):
        "a fill and hold with the piston blocked: heat transfer shows as a pressure drift, friction not",
    ("dead_volume", "valve_delay"):
        "a fill with the piston blocked and the valve's command recorded: a slower valve shifts the "
        "whole pressure rise later, an extra volume makes it slower",
    ("sensor_lag", "valve_delay"):
        "a fast reference transducer at the port: a sensor lag delays only the measured pressures, a "
        "slower valve the pressure and the motion alike",
    ("leakage", "valve_delay"):
        "a hold after cut-off at the end of stroke: a leak lowers the trapped pressure, the valve's "
        "timing does not",
}


#: Experiments that expose one candidate when its evidence is short (material, but not
#: significant on these runs): where the effect acts longest and the model's form matters least.
EXPOSING_EXPERIMENTS: dict[str, str] = {
    "leakage": "a hold of at least 5 s after a cut-off at the end of stroke, and a hold with the "
               "piston blocked: a leak keeps the trapped pressure falling towards ambient",
    "heat_transfer": "a fast fill followed by a hold of several seconds with the piston at the end of "
                     "stroke: the pressure settles as the air reaches wall temperature",
    "stribeck_friction": "slow strokes (throttled supply, or a low supply pressure near breakaway): "
                         "creep and stick-slip show the friction at low speed",
    "sensor_lag": "a step of pressure measured by a fast reference transducer beside the slow one",
    "dead_volume": "a fill with the piston blocked at the start of stroke, with mdot_supply recorded: "
                   "an extra volume slows the pressure rise for the same flow",
    "valve_delay": "the valve's command and the first pressure rise at the port recorded at 1 kHz or "
                   "faster: the delay between them",
}


def exposing_experiment(name: str) -> str:
    """The suggested experiment when the evidence for ``name`` is short."""
    return EXPOSING_EXPERIMENTS.get(
        name, f"a longer run in the phase where {name} acts, at another supply pressure and load")


def separating_experiment(a: str, b: str) -> str:
    """The suggested experiment that would tell effect ``a`` from ``b``."""
    key = tuple(sorted((a, b)))
    return SEPARATING_EXPERIMENTS.get(
        key, f"an experiment where {a} and {b} predict different responses: vary the hold after "
             f"cut-off, the supply pressure and the load, and compare again")
