"""Controllers for a rig's operating life (:mod:`pneugym.operation`): a frozen policy, and two that
adapt from the strokes they have made (thesis 6.8, ch. 7).

Every controller here sees only what a real one sees: its sensors during a stroke, the supply
set-point and the payload, and each finished stroke's measured outcome (completed, stalled, the
stick-slip events the position trace shows, the stroke time an end switch gives, the wasted
energy from the driving chamber's final pressure; :data:`MEASURED`).
The conventional stroke time and energy that the objective is counted against are measured on
*reference strokes*, cut off on arrival (the end-stroke rule: the conventional stroke time, and
the air the valve's delay lets in, spent and counted) or, with ``reference_cut="never"``, run
uncut (all their air spent): every 100th stroke, or, for adaptive ESAC with
``reference_on_change``, at each change of the told operating point and ``reference_every``
strokes after the last one (:class:`ReferenceSchedule`).

- :class:`Frozen`: any policy (a baseline's name or ``NAME=PATH`` of a trained one), unchanged.
- :class:`AdaptiveGasLaw`: the Gas-Law rule with its K table scaled by a factor adjusted after
  every block of strokes by perturb-and-observe: alternate strokes run K slightly higher and
  lower, and the factor moves toward the side whose measured objective (stick-slip included)
  was better; a stroke short of its end moves it up (a later cut) at once.
- :class:`AdaptiveESAC`: ESAC fine-tuned from its own recorded strokes (each stroke labels the
  observations at its cut and before it with its measured outcome, as rollouts do), a share of
  strokes exploring another time demand; a candidate is deployed only if it predicts the most
  recent strokes, which it was not trained on, better than the running model. Its time demand
  follows the measured outcome (:class:`DemandTuner`): it moves to an explored demand only when
  the recent strokes there scored clearly better (stick-slip included).

The operating loop calls :meth:`Frozen.plan` before each block, :meth:`Frozen.update` with the
block's measured outcome, :meth:`Frozen.adapt` at the start of each block (with the record) and
:meth:`Frozen.state` / :meth:`Frozen.restore` to checkpoint.
"""
from __future__ import annotations

import copy
import json
import math
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .base import Policy

#: the outcome columns a controller may read (measured); ``objective`` and ``saving_ratio`` are
#: the simulator's and stay with the report
MEASURED = ("stroke", "reference", "explore", "supply_setpoint_pa", "cutoff_time_s", "completed",
            "stalled", "stick_slip_events", "stroke_time_s", "final_position_m",
            "energy_wasted_j", "energy_conventional_j", "free_air_nl")


def measured_objective(rec: Mapping[str, np.ndarray], conv_time_s: np.ndarray,
                       conv_energy_j: np.ndarray, w_time: float = 0.3, w_stick: float = 0.5,
                       w_stall: float = 2.0) -> np.ndarray:
    """The environment's objective as a controller can measure it: wasted energy over the
    reference stroke's, minus the weighted time increase over the reference stroke's, stick-slip
    (once per stroke with any, where the environment counts each event) and stall (an incomplete
    stroke scores as a stall)."""
    t = np.asarray(rec["stroke_time_s"], dtype=float)
    done = np.asarray(rec["completed"], dtype=bool)
    inc = np.where(done, np.maximum(np.nan_to_num(t / conv_time_s - 1.0), 0.0), 0.0)
    return (-np.asarray(rec["energy_wasted_j"], float) / conv_energy_j - w_time * inc
            - w_stick * (np.asarray(rec["stick_slip_events"]) > 0)
            - w_stall * (~done))


def reference_energy(rec: Mapping[str, np.ndarray]) -> np.ndarray:
    """Each stroke's conventional energy [J] as a reference stroke measures it: the wasted
    energy of an uncut stroke (the driving side filled to supply), else the recorded
    ``energy_conventional_j`` (the same closed form, for a reference cut off on arrival)."""
    wasted = np.asarray(rec["energy_wasted_j"], dtype=float)
    conv, cut_s = rec.get("energy_conventional_j"), rec.get("cutoff_time_s")
    if conv is None or cut_s is None:
        return wasted
    cut = np.array([v is not None and np.isfinite(float(v)) for v in cut_s])
    conv = np.array([np.nan if v is None else float(v) for v in conv])
    return np.where(cut & np.isfinite(conv), conv, wasted)


def latest_reference(rec: Mapping[str, np.ndarray], conv: tuple[float, float]
                     ) -> tuple[float, float]:
    """The stroke time [s] and conventional energy [J] of the block's last reference stroke
    (:func:`reference_energy`), else ``conv``: what an adapting controller's measured objective
    is counted against."""
    ref = np.flatnonzero(np.asarray(rec["reference"], dtype=bool))
    if not ref.size:
        return conv
    return float(rec["stroke_time_s"][ref[-1]]), float(reference_energy(rec)[ref[-1]])


#: with ``reference_on_change``, a reference stroke is due at a told supply set-point this far
#: [Pa] from the last reference stroke's, or a payload this far (relative) from its payload
REFERENCE_SUPPLY_TOL_PA = 1e4
REFERENCE_LOAD_TOL = 0.05
#: how a reference stroke runs: never cut (the conventional stroke), or cut off on arrival (the
#: end-stroke rule, thesis 5.7: the same stroke time, and the air the valve's delay lets in)
REFERENCE_CUTS = ("never", "arrival")


class ReferenceSchedule:
    """Which strokes run as *reference strokes* (the conventional figures the measured
    objective is counted against), and how: every ``every``-th stroke (0: none), run uncut
    (``cut="never"``) or cut off on arrival (``cut="arrival"``: the stroke time is the
    conventional one, and the conventional energy the closed form the record keeps beside the
    wasted energy, ``energy_conventional_j``). With ``on_change``,
    also the first stroke told an operating point away from the last reference stroke's
    (supply set-point by more than :data:`REFERENCE_SUPPLY_TOL_PA`, payload by more than
    :data:`REFERENCE_LOAD_TOL`), and ``every`` then counts from the last reference stroke: the
    conventional figures change with the operating point, and while it holds they drift only
    slowly (wear, leaks), so the references can be sparse."""

    def __init__(self, every: int, on_change: bool = False, cut: str = "never"):
        if not (isinstance(every, int) and every >= 0) or (on_change and every < 1):
            raise ValueError(f"reference_every = {every!r} must be an integer >= 0 (strokes "
                             f"between reference strokes; 0: none), >= 1 with reference_on_change")
        if cut not in REFERENCE_CUTS:
            raise ValueError(f"reference_cut = {cut!r}: choose from {REFERENCE_CUTS}")
        self.every, self.on_change, self.cut = every, bool(on_change), cut
        self.last: int | None = None  # the last reference stroke (with on_change)
        self.point: tuple[float, float] | None = None  # its told (supply [Pa g], load [kg])

    def flags(self, strokes: np.ndarray, told: Any = None) -> np.ndarray:
        """The reference flag of each of ``strokes`` (in order); ``told``: each stroke's told
        conditions (needed with ``on_change``)."""
        strokes = np.asarray(strokes)
        if not self.every:
            return np.zeros(strokes.size, dtype=bool)
        if not self.on_change:
            return strokes % self.every == 0
        if told is None or len(told) != strokes.size:
            raise ValueError("reference strokes on a change of the operating point need each "
                             "stroke's told conditions (plan(strokes, told))")
        out = np.zeros(strokes.size, dtype=bool)
        for i, (k, c) in enumerate(zip(strokes, told)):
            pt = (float(c.supply_pressure_gauge_pa), float(c.load_mass_kg))
            if (self.last is None or k - self.last >= self.every or self._moved(pt)):
                out[i], self.last, self.point = True, int(k), pt
        return out

    def _moved(self, pt: tuple[float, float]) -> bool:
        s0, m0 = self.point
        return (abs(pt[0] - s0) > REFERENCE_SUPPLY_TOL_PA
                or abs(pt[1] - m0) > REFERENCE_LOAD_TOL * max(abs(m0), 1e-9))

    def config(self) -> dict[str, Any]:
        """``reference_cut`` unless ``"never"`` (so that a run recorded before the option
        resumes)."""
        return {} if self.cut == "never" else {"reference_cut": self.cut}

    def state(self) -> dict[str, Any]:
        return {"last": self.last, "point": None if self.point is None else list(self.point)}

    def restore(self, s: Mapping[str, Any]) -> None:
        self.last = None if s.get("last") is None else int(s["last"])
        self.point = None if s.get("point") is None else tuple(float(v) for v in s["point"])


class Frozen:
    """A policy that never changes: ``spec`` a baseline's name (``gaslaw``, ``endstroke``, ...)
    or ``NAME=PATH`` of a trained model, built for ``env`` (the operating vector environment)."""

    needs_inputs = False  #: whether the loop records the observations at each cut
    reference_every = 0  #: 0: no reference strokes
    privileged = False  #: told the true conditions (the oracle: a check, not a controller)

    def __init__(self, spec: str, env: Any, seed: int = 0,
                 references: ReferenceSchedule | None = None):
        from .evaluation.specs import make_named_policy

        self.spec = spec
        self.name, self.policy = make_named_policy(spec, env)
        self.privileged = bool(getattr(self.policy, "privileged", False))
        self.seed = int(seed)
        self.version = f"{self.name}"
        self.references = references or ReferenceSchedule(self.reference_every)

    def config(self) -> dict[str, Any]:
        """What identifies the controller (recorded with the run)."""
        return {"kind": type(self).__name__, "spec": self.spec}

    def plan(self, strokes: np.ndarray, told: Any = None
             ) -> tuple[Policy, dict[str, np.ndarray]]:
        """The policy for a block of strokes and each stroke's flags: ``reference`` (run as
        :attr:`references` says) and ``explore``; ``told``: each stroke's told conditions
        (supply set-point, payload)."""
        n = strokes.size
        return self.policy, {"reference": self.references.flags(strokes, told),
                             "explore": np.zeros(n, dtype=bool)}

    def update(self, rec: Mapping[str, np.ndarray]) -> None:
        """Learn from a block's measured outcome (:data:`MEASURED`)."""

    def adapt(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        """Before stroke ``stroke``: build and perhaps deploy a new model from the record.
        Returns the models built (rows of the record's ``models`` table)."""
        return []

    def state(self) -> bytes:
        """The controller's state, for the checkpoint."""
        return json.dumps({"version": self.version}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        """Back to a checkpointed state."""


#: the adaptive Gas-Law factor stays within exp(+-LOG_G_MAX) of the calibrated K (0.25-4x)
LOG_G_MAX = math.log(4.0)


class AdaptiveGasLaw(Frozen):
    """The Gas-Law rule (as shipped, K per supply pressure) with its K scaled by a factor ``g``
    learned in operation: within a block, even strokes run ``g * exp(+delta)``, odd ones
    ``g * exp(-delta)``; after it, ``log g`` moves by ``step`` toward the better side (mean
    measured objective, stick-slip included), and by ``backoff`` up after any stroke that did
    not reach its end; ``g`` stays within 0.25-4."""

    reference_every = 100

    def __init__(self, env: Any, seed: int = 0, delta: float = 0.08, step: float = 0.04,
                 backoff: float = 0.15, spec: str = "gaslaw", reference_cut: str = "arrival"):
        super().__init__(spec, env, seed,
                         ReferenceSchedule(self.reference_every, cut=reference_cut))
        self.delta, self.step, self.backoff = float(delta), float(step), float(backoff)
        self.log_g = 0.0
        self.conv = (math.nan, math.nan)  # the latest reference stroke's time [s], energy [J]
        self.version = self._version()

    def _version(self) -> str:
        return f"gaslaw-adaptive g={math.exp(self.log_g):.4f}"

    def config(self) -> dict[str, Any]:
        return {**super().config(), "delta": self.delta, "step": self.step,
                "backoff": self.backoff, "reference_every": self.references.every,
                **self.references.config()}

    def plan(self, strokes: np.ndarray, told: Any = None
             ) -> tuple[Any, dict[str, np.ndarray]]:
        ref = self.references.flags(strokes, told)
        sign = np.where(strokes % 2 == 0, 1.0, -1.0)
        factor = np.exp(self.log_g + self.delta * sign)
        self.policy.k_scale = factor
        return self.policy, {"reference": ref, "explore": np.zeros(strokes.size, bool)}

    def update(self, rec: Mapping[str, np.ndarray]) -> None:
        ref = np.asarray(rec["reference"], dtype=bool)
        self.conv = latest_reference(rec, self.conv)
        cut = ~ref
        if not cut.any() or not math.isfinite(self.conv[0]):
            return
        if (~np.asarray(rec["completed"], bool) & cut).any():
            self.log_g += self.backoff  # a stroke short of its end: cut later at once
        else:  # stick-slip is in the measured objective: the side that sticks less wins
            j = measured_objective(rec, self.conv[0], self.conv[1])
            up = cut & (np.asarray(rec["stroke"]) % 2 == 0)
            down = cut & ~up
            if up.any() and down.any():
                self.log_g += self.step * np.sign(j[up].mean() - j[down].mean())
        self.log_g = float(np.clip(self.log_g, -LOG_G_MAX, LOG_G_MAX))
        self.version = self._version()

    def state(self) -> bytes:
        return json.dumps({"log_g": self.log_g, "conv": list(self.conv)}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        s = json.loads(state)
        self.log_g, self.conv = float(s["log_g"]), tuple(float(v) for v in s["conv"])
        self.version = self._version()


class DemandTuner:
    """The time demand that recent strokes scored best with, measured: each cut stroke adds its
    demand and its :func:`measured_objective`; :meth:`choose` estimates the mean objective at
    each demand of ``grid`` from the last ``window`` strokes (triangular kernel of half-width
    ``bandwidth`` on the demand) and moves from the current demand to the best only if the
    difference exceeds ``z`` standard errors, with at least ``min_n`` effective strokes on each
    side. The exploring strokes supply the other demands; a drift that makes another demand
    better (a load at which the tuned cut meets stick-slip) shows there first."""

    def __init__(self, grid: np.ndarray, window: int = 250, bandwidth: float = 0.05,
                 z: float = 2.0, min_n: float = 8.0):
        grid = np.asarray(grid, dtype=float)
        if grid.ndim != 1 or grid.size < 2 or not np.all(np.isfinite(grid)):
            raise ValueError(f"grid = {grid!r}: give two or more finite demands")
        if not (window >= 10 and bandwidth > 0 and z >= 0 and min_n >= 2):
            raise ValueError("window >= 10, bandwidth > 0, z >= 0 and min_n >= 2")
        self.grid, self.window, self.bandwidth = grid, int(window), float(bandwidth)
        self.z, self.min_n = float(z), float(min_n)
        self.stroke = np.zeros(0, dtype=np.int64)
        self.demand = np.zeros(0)
        self.value = np.zeros(0)

    def add(self, strokes: np.ndarray, demands: np.ndarray, values: np.ndarray) -> None:
        """Record strokes' demands and measured objectives (non-finite ones are skipped)."""
        ok = np.isfinite(values) & np.isfinite(demands)
        self.stroke = np.concatenate([self.stroke, np.asarray(strokes, np.int64)[ok]])
        self.demand = np.concatenate([self.demand, np.asarray(demands, float)[ok]])
        self.value = np.concatenate([self.value, np.asarray(values, float)[ok]])
        if self.stroke.size:
            keep = self.stroke > self.stroke.max() - self.window
            self.stroke, self.demand = self.stroke[keep], self.demand[keep]
            self.value = self.value[keep]

    def estimate(self, d: float) -> tuple[float, float, float]:
        """Mean measured objective near demand ``d``, its standard error and the effective
        number of strokes behind it."""
        w = np.maximum(0.0, 1.0 - np.abs(self.demand - d) / self.bandwidth)
        sw = w.sum()
        if sw <= 0.0:
            return math.nan, math.inf, 0.0
        n = sw * sw / float((w * w).sum())
        m = float((w * self.value).sum() / sw)
        var = float((w * (self.value - m) ** 2).sum() / sw) * n / max(n - 1.0, 1.0)
        return m, math.sqrt(var / n), n

    def choose(self, current: float) -> float:
        """The demand for the next strokes: ``current`` unless a demand of the grid scored
        better by more than ``z`` standard errors of the difference."""
        m0, s0, n0 = self.estimate(current)
        if n0 < self.min_n:
            return current
        best, gain = current, 0.0
        for d in self.grid:
            m, s, n = self.estimate(float(d))
            if n < self.min_n or abs(d - current) < 1e-9:
                continue
            g = m - m0 - self.z * math.hypot(s, s0)
            if g > gain + 1e-12:
                best, gain = float(d), g
        return best

    def state(self) -> dict[str, list]:
        return {"stroke": self.stroke.tolist(), "demand": self.demand.tolist(),
                "value": self.value.tolist()}

    def restore(self, s: Mapping[str, list]) -> None:
        self.stroke = np.asarray(s["stroke"], dtype=np.int64)
        self.demand = np.asarray(s["demand"], dtype=float)
        self.value = np.asarray(s["value"], dtype=float)


class AdaptiveESAC(Frozen):
    """ESAC fine-tuned in operation from its recorded strokes.

    Every ``adapt_every`` strokes it takes the last ``window`` recorded cut strokes, labels each
    one's observations at the cut (and before it, for a model with delay input) with its
    measured outcome and the latest reference stroke's conventional figures, fine-tunes the
    running network on the older ones (``epochs`` at learning rate ``lr``) and scores both on
    the newest ``holdout`` share: the candidate is deployed only if its loss there is lower by
    ``min_gain`` (relative). A share ``explore`` of the strokes runs with a time demand drawn
    from ``explore_range`` instead of the tuned one, so that the record shows the outcome of
    other cut times too. With ``tune_demand`` the regular strokes' time demand follows the
    measured outcome of the last ``tune_window`` strokes (:class:`DemandTuner` on the explored
    range, in steps of a sixth of it; ``tune_z`` standard errors to move). A model that stops
    cutting records nothing to learn from, so when the running model is not the shipped one and
    none of its last ``rollback_after`` strokes (reference strokes aside) cut, the shipped model
    runs again (a *rollback*, recorded as a model of kind ``rollback``; 0: never). The deployment
    test scores predictions of the cuts the record holds, so it cannot see a model that cuts
    where none was recorded and stalls there: a freshly deployed model is on *probation* for its
    first ``probation`` regular strokes (reference and exploring strokes aside), and if
    ``probation_stalls`` of them stall, the model it replaced runs again (recorded as kind
    ``withdrawn``; ``probation=0``: never). With ``explore_max`` above the range's top, the
    range grows by its first width whenever the tuned demand reaches its top step, up to
    ``explore_max`` (for a rig whose best cut makes the stroke far longer than the conventional
    one; default ``None``: the range never grows). Every ``reference_every``-th stroke is a
    reference stroke; with ``reference_on_change`` one runs at the first stroke, at the first
    stroke told another operating point and ``reference_every`` strokes after the last one
    (:class:`ReferenceSchedule`; e.g. ``reference_every=500``: fewer uncut strokes, which paid
    on the thesis-rig ESAC and cost the family ESAC, docs/operation.md); ``reference_cut``:
    ``"arrival"`` (cut off on arrival, the default) or ``"never"`` (uncut)."""

    needs_inputs = True
    reference_every = 100

    def __init__(self, spec: str, env: Any, seed: int = 0, adapt_every: int = 250,
                 window: int = 1000, holdout: float = 0.25, epochs: int = 30, lr: float = 5e-4,
                 min_gain: float = 0.02, explore: float = 0.1,
                 explore_range: tuple[float, float] = (0.0, 0.3), tune_demand: bool = True,
                 tune_window: int = 250, tune_z: float = 2.0, rollback_after: int = 50,
                 probation: int = 50, probation_stalls: int = 3,
                 explore_max: float | None = None, reference_every: int = 100,
                 reference_on_change: bool = False, reference_cut: str = "arrival"):
        super().__init__(spec, env, seed,
                         ReferenceSchedule(reference_every, reference_on_change, reference_cut))
        from .esac.policy import ESACPolicy

        if not isinstance(self.policy, ESACPolicy):
            raise ValueError(f"{spec!r} is not an ESAC model: adaptive ESAC fine-tunes ESAC "
                             f"models (give esac=runs/esac)")
        if not (1 <= adapt_every and 0.0 < holdout < 1.0 and 0.0 <= explore < 1.0):
            raise ValueError("adapt_every >= 1, holdout in (0, 1), explore in [0, 1)")
        if not (isinstance(rollback_after, int) and rollback_after >= 0):
            raise ValueError(f"rollback_after = {rollback_after!r} must be an integer >= 0 "
                             f"(strokes; 0: never roll back)")
        if not (isinstance(probation, int) and probation >= 0 and isinstance(probation_stalls, int)
                and 1 <= probation_stalls and (probation == 0 or probation_stalls <= probation)):
            raise ValueError(f"probation = {probation!r} (regular strokes, 0: none) and "
                             f"probation_stalls = {probation_stalls!r} (stalls that withdraw a "
                             f"model, 1 to probation) must be integers")
        self.rollback_after = rollback_after
        self.probation, self.probation_stalls = probation, probation_stalls
        # the model a fresh one replaced, while the fresh one is on probation: its version, its
        # network and whether it is the shipped one (None: no model on probation)
        self.previous: tuple[str, Any, bool] | None = None
        self.shipped = copy.deepcopy(self.policy.predictor.net)  # what a rollback runs again
        self.deployed_at = 0  # the stroke the running model took over at
        self.shipped_runs = True  # the running model is the shipped one (none fine-tuned)
        self.adapt_every, self.window, self.holdout = int(adapt_every), int(window), holdout
        self.epochs, self.lr, self.min_gain = int(epochs), float(lr), float(min_gain)
        self.explore, self.explore_range = float(explore), tuple(explore_range)
        self.layout = env.unwrapped.observation_layout()
        from .esac.data import LAGS

        # the recorded lags' delays [s] (the loop records the observations LAGS periods back)
        self.lag_s = np.asarray(LAGS, dtype=float) * float(self.layout["control_period_s"])
        self.rule = self.policy.rule()
        self.generation = 0
        self.last_adapt = 0
        self.model_version = f"{self.name}-v0"
        lo, hi = self.explore_range
        explore_max = hi if explore_max is None else explore_max
        if not (0.0 <= lo < hi <= explore_max <= 5.0):
            raise ValueError(f"explore_range = {explore_range!r} and explore_max = "
                             f"{explore_max!r}: need 0 <= low < high <= explore_max <= 5")
        self.explore_width, self.explore_max = hi - lo, float(explore_max)
        self.tune_demand = bool(tune_demand)
        self.tuner = DemandTuner(np.linspace(lo, hi, 7), window=tune_window,
                                 bandwidth=(hi - lo) / 6.0, z=tune_z)
        self.demand = float(self.rule["max_time_increase"])
        self.conv = (math.nan, math.nan)  # the latest reference stroke's time [s], energy [J]
        self._planned = np.zeros(0)
        self.version = self._version()

    def _version(self) -> str:
        return (f"{self.model_version} demand={self.demand:.3f}" if self.tune_demand
                else self.model_version)

    def config(self) -> dict[str, Any]:
        return {**super().config(), "adapt_every": self.adapt_every, "window": self.window,
                "holdout": self.holdout, "epochs": self.epochs, "lr": self.lr,
                "min_gain": self.min_gain, "explore": self.explore,
                "explore_range": list(self.explore_range),
                "reference_every": self.references.every,
                "tune_demand": self.tune_demand, "tune_window": self.tuner.window,
                "tune_z": self.tuner.z, "rollback_after": self.rollback_after,
                "probation": self.probation, "probation_stalls": self.probation_stalls,
                "explore_max": self.explore_max,
                "reference_on_change": self.references.on_change, **self.references.config()}

    def plan(self, strokes: np.ndarray, told: Any = None
             ) -> tuple[Any, dict[str, np.ndarray]]:
        from .esac.policy import ESACPolicy

        ref = self.references.flags(strokes, told)
        u = np.array([np.random.default_rng([self.seed, int(k), 7]).random(2) for k in strokes])
        explore = (u[:, 0] < self.explore) & ~ref
        lo, hi = self.explore_range
        demand = np.where(explore, lo + (hi - lo) * u[:, 1], self.demand)
        self._planned = demand
        rule = {k: v for k, v in self.rule.items() if k != "max_time_increase"}
        pol = ESACPolicy(self.layout, self.policy.predictor, max_time_increase=demand,
                         source=self.policy.source, **rule)
        return pol, {"reference": ref, "explore": explore}

    def update(self, rec: Mapping[str, np.ndarray]) -> None:
        """The time demand from the block's measured outcome (with ``tune_demand``)."""
        ref = np.asarray(rec["reference"], dtype=bool)
        self.conv = latest_reference(rec, self.conv)
        if not self.tune_demand or not math.isfinite(self.conv[0]) or ref.all():
            return
        j = measured_objective(rec, self.conv[0], self.conv[1], float(self.rule["w_time"]),
                               float(self.rule["w_stick"]), float(self.rule["w_stall"]))
        cut = ~ref
        self.tuner.add(np.asarray(rec["stroke"])[cut], self._planned[cut], j[cut])
        self.demand = self.tuner.choose(self.demand)
        self._grow()
        self.version = self._version()

    def _grow(self) -> None:
        """Widen the explored demands when the tuned one reached the range's top step: the top
        grows by the first range's width (up to :attr:`explore_max`), the tuner's grid keeping
        its step."""
        lo, hi = self.explore_range
        step = self.explore_width / 6.0
        if self.demand < hi - step - 1e-9 or hi >= self.explore_max - 1e-9:
            return
        self._set_top(min(self.explore_max, hi + self.explore_width))

    def _set_top(self, hi: float) -> None:
        lo = self.explore_range[0]
        self.explore_range = (lo, hi)
        self.tuner.grid = np.linspace(lo, hi, int(round((hi - lo) * 6.0 / self.explore_width)) + 1)

    # -- learning from the record --------------------------------------------------------------
    def _samples(self, rec: Mapping[str, np.ndarray], first: int = 0
                 ) -> tuple[np.ndarray, ...] | None:
        """Inputs, targets, mask and stroke index of the record's cut strokes from ``first`` on,
        labelled with the latest earlier reference stroke's conventional time and energy."""
        from .esac.data import samples

        ref = rec["reference"].astype(bool)
        idx = np.arange(ref.size)
        last_ref = np.maximum.accumulate(np.where(ref, idx, -1))
        use = ~ref & (last_ref >= 0) & np.array([b is not None for b in rec["decision_inputs"]])
        use &= rec["stroke"] >= first
        use &= ~np.isnan(rec["cutoff_time_s"])
        if use.sum() < 20:
            return None
        j = last_ref[use]
        pred = self.policy.predictor
        size = int(pred.layout["size"])
        obs_lag = np.stack([np.frombuffer(b, dtype=np.float32).reshape(-1, size)
                            for b in rec["decision_inputs"][use]])
        data = {
            "obs": obs_lag[:, 0], "obs_lag": obs_lag, "lag_s": self.lag_s,
            "completed": rec["completed"][use].astype(bool),
            "stick_slip_events": rec["stick_slip_events"][use].astype(np.int64),
            "final_position_m": rec["final_position_m"][use].astype(float),
            "stroke_time_s": np.array([np.nan if v is None else v
                                       for v in rec["stroke_time_s"][use]], dtype=float),
            "conventional_time_s": rec["stroke_time_s"][j].astype(float),
            "energy_wasted_j": rec["energy_wasted_j"][use].astype(float),
            "energy_conventional_j": reference_energy(rec)[j],
        }
        x, y, mask, rows = samples(data, pred.stroke_m, pred.delay_input)
        return x, y, mask, rec["stroke"][use][rows]

    def _rollback(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        """The shipped model again if the running one, a fine-tuned one, has not cut on any of
        its last :attr:`rollback_after` strokes (reference strokes aside)."""
        n = self.rollback_after
        if not n or self.shipped_runs or stroke - self.deployed_at < n:
            return []
        rec = record.strokes(run_id, self.deployed_at, stroke - 1,
                             columns=("stroke", "reference", "cutoff_time_s"))
        cut = np.array([v is not None and not math.isnan(v) for v in rec["cutoff_time_s"]])
        own = ~rec["reference"].astype(bool)
        if own.sum() < n or cut[own][-n:].any():
            return []
        return self._take_back(self.shipped, True, stroke, "rollback",
                               {"to": f"{self.name}-v0",
                                "reason": f"no cut in the last {n} strokes"})

    def _take_back(self, net: Any, shipped: bool, stroke: int, kind: str,
                   detail: dict[str, Any]) -> list[dict[str, Any]]:
        """Run ``net`` again (the shipped model if ``shipped``) from ``stroke`` as a new
        version, with no model on probation; returns its row of the record's ``models``."""
        self.generation += 1
        self.previous = None
        version = f"{self.name}-v{self.generation}"
        self.policy.predictor.net = net
        if shipped:
            self.shipped = copy.deepcopy(net)  # (kept apart from the running net)
        self.model_version, self.deployed_at, self.shipped_runs = version, stroke, shipped
        self.version = self._version()
        return [{"version": version, "stroke": stroke, "kind": kind, "deployed": True,
                 "score_new": None, "score_running": None, "detail": detail,
                 "blob": _net_bytes(net, self.policy)}]

    def _probation(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        """The model replaced by the running one again if :attr:`probation_stalls` of the running
        one's first :attr:`probation` regular strokes stalled; the probation ends when they ran
        with fewer stalls."""
        if self.previous is None:
            return []
        rec = record.strokes(run_id, self.deployed_at, stroke - 1,
                             columns=("stroke", "reference", "explore", "stalled"))
        regular = ~(rec["reference"].astype(bool) | rec["explore"].astype(bool))
        stalls = int(rec["stalled"].astype(bool)[regular][:self.probation].sum())
        if stalls < self.probation_stalls:
            if regular.sum() >= self.probation:
                self.previous = None  # passed
            return []
        version, net, shipped = self.previous
        return self._take_back(net, shipped, stroke, "withdrawn",
                               {"to": version, "withdrawn": self.model_version, "reason":
                                f"{stalls} of its first {self.probation} regular strokes "
                                f"stalled"})

    def adapt(self, record: Any, run_id: str, stroke: int) -> list[dict[str, Any]]:
        back = self._probation(record, run_id, stroke) or self._rollback(record, run_id, stroke)
        if back:
            return back
        if stroke - self.last_adapt < self.adapt_every:
            return []
        from .esac.model import fit, loss

        self.last_adapt = stroke
        # a further reference_every strokes back: the reference stroke that labels the first ones
        rec = record.strokes(run_id, max(0, stroke - self.window - self.references.every),
                             stroke - 1, columns=MEASURED + ("decision_inputs",))
        got = self._samples(rec, first=stroke - self.window) if rec["stroke"].size else None
        if got is None:
            return []
        x, y, mask, st = got
        cut = np.quantile(np.unique(st), 1.0 - self.holdout)
        tr, te = st < cut, st >= cut
        if tr.sum() < 20 or te.sum() < 5:
            return []
        running = self.policy.predictor.net
        cand, hist = fit(x[tr], y[tr], mask[tr], epochs=self.epochs, lr=self.lr,
                         batch_size=128, seed=self.seed + stroke, patience=self.epochs,
                         groups=st[tr], progress=False, init=running)
        s_new, s_old = loss(cand, x[te], y[te], mask[te]), loss(running, x[te], y[te], mask[te])
        deploy = s_new < (1.0 - self.min_gain) * s_old
        self.generation += 1
        version = f"{self.name}-v{self.generation}"
        if deploy:
            if self.probation:
                self.previous = (self.model_version, running, self.shipped_runs)
            self.policy.predictor.net = cand
            self.model_version, self.deployed_at, self.shipped_runs = version, stroke, False
            self.version = self._version()
        return [{"version": version, "stroke": stroke, "kind": "esac", "deployed": bool(deploy),
                 "score_new": s_new, "score_running": s_old,
                 "detail": {"train_samples": int(tr.sum()), "holdout_samples": int(te.sum()),
                            "epochs_run": hist["epochs_run"]},
                 "blob": _net_bytes(cand, self.policy)}]

    def state(self) -> bytes:
        return json.dumps({"version": self.version, "model_version": self.model_version,
                           "generation": self.generation, "last_adapt": self.last_adapt,
                           "demand": self.demand, "conv": list(self.conv),
                           "tuner": self.tuner.state(), "deployed_at": self.deployed_at,
                           "shipped_runs": self.shipped_runs,
                           "explore_top": self.explore_range[1],
                           "references": self.references.state(),
                           "previous": None if self.previous is None else
                           [self.previous[0], self.previous[2]]}).encode()

    def restore(self, state: bytes, record: Any, run_id: str) -> None:
        s = json.loads(state)
        self.generation, self.last_adapt = int(s["generation"]), int(s["last_adapt"])
        self.model_version, self.demand = s["model_version"], float(s["demand"])
        self.deployed_at = int(s.get("deployed_at", 0))
        self.shipped_runs = bool(s.get("shipped_runs", self.model_version == f"{self.name}-v0"))
        self.conv = tuple(float(v) for v in s["conv"])
        self.tuner.restore(s["tuner"])
        if "explore_top" in s:
            self._set_top(float(s["explore_top"]))
        if "references" in s:
            self.references.restore(s["references"])
        self.version = self._version()
        if not self.shipped_runs:  # (a rollback runs the shipped model, loaded already)
            self.policy.predictor.net = self._recorded(record, run_id, self.model_version)
        prev = s.get("previous")
        self.previous = None
        if prev is not None:
            version, shipped = prev[0], bool(prev[1])
            net = (copy.deepcopy(self.shipped) if shipped
                   else self._recorded(record, run_id, version))
            self.previous = (version, net, shipped)

    @staticmethod
    def _recorded(record: Any, run_id: str, version: str) -> Any:
        """The network of model ``version`` in the record's ``models`` table."""
        row = record.con.execute("SELECT blob FROM models WHERE run_id = ? AND version = ?",
                                 [run_id, version]).fetchone()
        if row is None:
            raise ValueError(f"run {run_id!r}: its checkpoint names model {version}, which the "
                             f"record does not hold")
        return _net_from_bytes(row[0])


def _net_bytes(net: Any, policy: Any) -> bytes:
    """A network as the bytes of an ESAC model file (:mod:`agents.esac.modelfile`)."""
    from .esac.modelfile import save

    pred = policy.predictor
    meta = {"layout": pred.layout, "n_in": pred.n_in, "hidden": _hidden(net),
            "delay_input": pred.delay_input, "lookahead_s": pred.lookahead_s.tolist(),
            "rule": policy.rule()}
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "model.pt"
        save(f, net, meta)
        return f.read_bytes()


def _net_from_bytes(blob: bytes) -> Any:
    from .esac.modelfile import load

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "model.pt"
        f.write_bytes(blob)
        return load(f)[0].net


def _hidden(net: Any) -> list[int]:
    import torch

    from .esac import is_ensemble

    body = net.members[0] if is_ensemble(net) else net.body  # an ensemble's: its first
    return [m.out_features for m in body if isinstance(m, torch.nn.Linear)][:-1]


def make_controller(spec: str, env: Any, seed: int = 0, **options: Any) -> Frozen:
    """An operating controller from its spec: ``NAME`` or ``NAME=PATH`` (frozen),
    ``gaslaw-adaptive``, or ``esac-adaptive=PATH`` (an ESAC run or model); ``options``: keyword
    arguments of the adaptive controller (e.g. ``rollback_after=0``)."""
    if not is_adaptive(spec):
        if options:
            raise ValueError(f"controller options {sorted(options)} are for esac-adaptive=PATH "
                             f"or gaslaw-adaptive, not {spec!r}")
        return Frozen(spec, env, seed)
    if spec.startswith("esac-adaptive="):
        return AdaptiveESAC(spec, env, seed, **options)
    if spec == "gaslaw-adaptive":
        bad = sorted(set(options) - set(GASLAW_OPTIONS))
        if bad:
            raise ValueError(f"controller options {bad} are not gaslaw-adaptive's: it takes "
                             f"{GASLAW_OPTIONS}")
        return AdaptiveGasLaw(env, seed, **options)


#: the options :func:`make_controller` passes to :class:`AdaptiveGasLaw`
GASLAW_OPTIONS = ("delta", "step", "backoff", "reference_cut")


def is_adaptive(spec: str) -> bool:
    """Whether controller ``spec`` (of :func:`make_controller`) adapts, i.e. takes options."""
    return spec == "gaslaw-adaptive" or spec.startswith("esac-adaptive=")
