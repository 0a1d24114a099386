"""The runs that follow a short answer: the workflow's suggested experiment as run plans.

When the workflow answers ``none`` with the evidence short for a candidate, or ``ambiguous``, it
suggests an experiment (:data:`~.candidates.EXPOSING_EXPERIMENTS`). :func:`suggested_runs` turns
the suggestion into extension strokes that the measurement format holds (a supply pressure, a
valve schedule and a length), planned on the rig the runs state, where the effect acts longest
or fastest:

- a **hold** (leakage, heat exchange): cut off on arrival and recorded for 6 s, at the runs'
  highest supply; the trapped air, where neither line nor orifices act, shows a leak's fall
  and the air's settling;
- a **slow stroke** (Stribeck friction): never cut, at the lowest supply (on a 0.1 bar grid from
  0.4 bar) at which the stated rig completes the stroke within 4 s: creep and stick-slip;
- a **fast stroke** (a transducer lag): never cut, at 6 bar: the fastest pressure rise;
- an **early cut-off** (a dead volume): cut when the stated rig's piston is at 30 % of the
  stroke, at the runs' highest supply; the trapped air expands over most of the stroke and its
  pressure follows the whole volume, dead volume included.

:func:`simulate_plans` makes them on a simulated rig (the benchmark follows the suggestion:
``benchmarks/bench_discrepancy.py --follow-up``); on a real rig, run them as planned, record them
in the measurement format and give them to the workflow with the first runs.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..data import MeasuredRun, simulate_run
from ..params import RigParams
from ..plant import Plant

HOLD_S = 6.0  #: length of a hold run [s]
SLOW_LIMIT_S = 4.0  #: a slow stroke must complete within this on the stated rig [s]
FAST_SUPPLY_PA = 6e5  #: supply of the fast stroke [Pa gauge]
EARLY_FRACTION = 0.3  #: the early cut-off's piston position, share of the stroke
#: the effects a stroke is planned for (others, e.g. a valve delay, keep the suggestion's text)
PLANNED = ("leakage", "heat_transfer", "stribeck_friction", "sensor_lag", "dead_volume")


@dataclass(frozen=True)
class RunPlan:
    """One extension stroke to measure: ``cut`` is ``"never"``, ``"arrival"`` or ``"at"`` (the
    command at ``cut_s`` [s] after the extend command); pressures in Pa gauge, times in s."""

    name: str
    supply_pressure_gauge_pa: float
    load_mass_kg: float
    cut: str
    cut_s: float | None
    t_end_s: float
    why: str

    def to_dict(self) -> dict:
        return asdict(self)

    def sentence(self) -> str:
        """The plan in one line, for the report and the summary."""
        cut = (f"cut off at {self.cut_s:g} s" if self.cut == "at" else
               {"never": "never cut", "arrival": "cut off on arrival"}[self.cut])
        return (f"`{self.name}`: {self.supply_pressure_gauge_pa / 1e5:.3g} bar gauge, "
                f"{self.load_mass_kg:g} kg, "
                f"{cut}, recorded for {self.t_end_s:g} s: {self.why}")

    def schedule(self) -> list[tuple[float, int]]:
        """Valve commands for :meth:`pneugym.plant.Plant.run` / :func:`~pneugym.data.simulate_run`."""
        return [(0.0, 1)] if self.cut != "at" else [(0.0, 1), (float(self.cut_s), 0)]


def _at(rig: RigParams, supply_pa: float) -> RigParams:
    return rig.with_(supply_pressure_gauge_pa=float(supply_pa))


def _hold(rig: RigParams, supply_pa: float) -> RunPlan:
    return RunPlan("hold", supply_pa, rig.load_mass_kg, "arrival", None, HOLD_S,
                   "a hold after a cut-off on arrival: the trapped air shows a leak's fall and the "
                   "air's settling to wall temperature")


def _slow(rig: RigParams) -> RunPlan | None:
    for bar in np.arange(0.4, 6.05, 0.1):
        pa = round(float(bar), 1) * 1e5
        try:
            traj = Plant(_at(rig, pa)).run(SLOW_LIMIT_S, [(0.0, 1)], record_dt=1e-2)
        except ValueError:  # below what moves the piston at all
            continue
        if traj["x"][-1] >= 0.995 * rig.cylinder.stroke_m:
            return RunPlan("slow_stroke", pa, rig.load_mass_kg, "never", None, SLOW_LIMIT_S + 1.0,
                           f"a slow stroke at {pa / 1e5:.1f} bar, the lowest that completes within "
                           f"{SLOW_LIMIT_S:g} s on the stated rig: creep and stick-slip show the "
                           f"friction at low speed")
    return None


def _fast(rig: RigParams) -> RunPlan:
    return RunPlan("fast_stroke", FAST_SUPPLY_PA, rig.load_mass_kg, "never", None, 2.0,
                   f"a stroke at {FAST_SUPPLY_PA / 1e5:g} bar: the fastest pressure rise shows a "
                   f"transducer's lag")


def _early(rig: RigParams, supply_pa: float) -> RunPlan | None:
    at = _at(rig, supply_pa)
    traj = Plant(at).run(3.0, [(0.0, 1)], record_dt=1e-3)
    reached = np.flatnonzero(traj["x"] >= EARLY_FRACTION * rig.cylinder.stroke_m)
    if reached.size == 0:
        return None
    cut = max(float(traj["t"][reached[0]]) - at.valve_delay_s - rig.valve.ramp_s, 0.0)
    return RunPlan("early_cutoff_30", supply_pa, rig.load_mass_kg, "at", round(cut, 3), 4.0,
                   f"a cut-off at {EARLY_FRACTION:.0%} of the stroke: the trapped air expands over "
                   f"most of the stroke, its pressure following the whole volume, dead volume "
                   f"included")


def suggested_runs(effects: list[str], rigs: list[RigParams]) -> list[RunPlan]:
    """The runs that expose ``effects`` (one, or the two an ambiguous answer names), planned on
    ``rigs``, the rigs the runs state (``MeasuredRun.rig``): on the first one's load; one plan
    per kind, in the order asked."""
    if not rigs:
        raise ValueError("suggested_runs needs the rigs the runs state")
    rig = rigs[0]
    high = max(g.supply_pressure_gauge_pa for g in rigs)
    makers = dict(zip(PLANNED, (lambda: _hold(rig, high), lambda: _hold(rig, high),
                                lambda: _slow(rig), lambda: _fast(rig), lambda: _early(rig, high))))
    plans: list[RunPlan] = []
    for name in effects:
        if name not in makers:
            raise ValueError(f"no run plan exposes {name!r}; plans exist for {sorted(makers)}")
        plan = makers[name]()
        if plan is not None and plan.name not in {p.name for p in plans}:
            plans.append(plan)
    return plans


def simulate_plans(plans: list[RunPlan], truth: RigParams, known: RigParams, *, seed: int,
                   prefix: str = "followup_") -> list[MeasuredRun]:
    """The planned runs made on a simulated rig ``truth`` (1 kHz, the default noise), their JSON
    stating ``known`` at the plan's operating point; a noise stream of its own per run."""
    out = []
    for k, p in enumerate(plans):
        op = {"supply_pressure_gauge_pa": p.supply_pressure_gauge_pa, "load_mass_kg": p.load_mass_kg}
        out.append(simulate_run(truth.with_(**op), p.schedule(), t_end=p.t_end_s,
                                cut_on_arrival=p.cut == "arrival", noise="default",
                                known=known.with_(**op), seed=seed + k, name=f"{prefix}{p.name}",
                                description=p.why))
    return out
