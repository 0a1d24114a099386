"""Model-predictive cut-off: estimate the rig online from the stroke so far, run the plant ahead,
cut when cutting now is best.

A deployable, non-privileged policy for rigs no policy was trained on. It knows what a user
writes in a rig file (the environment's rig: bore, rod, stroke, cushions; and, from the
observation's rig features, line length and diameter, dead volume and payload) and the sensors.
What it cannot be told it estimates from the stroke's own samples: soon after the piston has
broken away, and again every ``replan_periods`` control periods until it cuts,

1. **fit** (:func:`scipy.optimize.least_squares`) the valve delay, the static, Coulomb and
   viscous friction and the valve, port and exhaust areas (scales on the rig's) so that the
   plant's noise-free sensor trace with the supply kept (:func:`pneugym.envs.rollout.keep_traces`)
   matches the measured one, position and both port pressures;
2. **plan**: run the plant ahead (the oracle's search, :func:`agents.oracle.search_cuts`) on the
   fitted rig for every cut-off time from now on and never. What the stroke does not show before
   the cut (cushion settings, leaks, heat transfer) the plan cannot fit: it averages the return
   over ``prior_members`` draws of them from the rig family (:data:`HIDDEN`), so that a cut that
   would stall on a plausible rig is paid for. It schedules the cut whose *worst* return within
   ``margin_periods`` control periods either side is best: a cut on the edge of a stick-slip or
   a stall, which the fitted rig may misplace by a few ms, is given up for a little air
   (issue 12, part 5).

The line and orifice model forms stay the rig file's. Cost: about 1.5 s of computation per
episode with ``prior_members=0`` (the rig file's cushions, no leak), about 8 s with the default
six draws (2 cores); far from a 5 ms control period in Python, and the subject of the deployable
controller (docs/policies.md).
"""
from __future__ import annotations

import math
import warnings
from typing import Any, Callable, Collection, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares

from pneugym.envs import Conditions, conventional_figures
from pneugym.envs.family import RigFamily
from pneugym.envs.rollout import keep_traces
from pneugym.params import RigParams
from pneugym.plant import RigWarning, SimulationError

from .oracle import OraclePolicy, TimedCutPolicy, search_cuts, settle_windows

#: The fitted quantities: (name, low, high, log-scaled). Areas are scales on the rig file's.
FITTED = (("valve delay [s]", 0.01, 0.45, False), ("static friction [N]", 100.0, 800.0, False),
          ("Coulomb friction [N]", 40.0, 350.0, False),
          ("viscous friction [N s/m]", 300.0, 5000.0, True), ("valve area scale", 0.2, 4.0, True),
          ("port area scale", 0.2, 4.0, True), ("exhaust area scale", 0.2, 4.0, True))
_LO = np.array([f[1] for f in FITTED])
_HI = np.array([f[2] for f in FITTED])
_LOG = np.array([f[3] for f in FITTED])
#: trace residual scales: position [m], port pressures [Pa]
TRACE_SCALES = np.array([3e-3, 2e4, 2e4])
DATASHEET = ("line_length", "line_diameter", "dead_volume", "payload")
#: the rig-file values of a cylinder the observation does not hold (from ``rig_changes``)
CYLINDER_FIELDS = ("cylinder.design", "cylinder.mounting_angle_deg")


def to_unit(theta: np.ndarray) -> np.ndarray:
    """Fitted quantities -> the unit cube the fit works in (log scale where marked)."""
    lin = (theta - _LO) / (_HI - _LO)
    log = (np.log(theta) - np.log(_LO)) / (np.log(_HI) - np.log(_LO))
    return np.clip(np.where(_LOG, log, lin), 0.0, 1.0)


def from_unit(u: np.ndarray) -> np.ndarray:
    """The unit cube -> fitted quantities (``u`` (..., 7))."""
    lin = _LO + (_HI - _LO) * u
    log = np.exp(np.log(_LO) + (np.log(_HI) - np.log(_LO)) * u)
    return np.where(_LOG, log, lin)


def rig_changes(theta: np.ndarray, base: RigParams) -> dict[str, float]:
    """The ``rig_changes`` of fitted quantities ``theta`` on ``base``."""
    fs = float(theta[1])
    return {"valve.delay_s": float(theta[0]), "friction.static_n": fs,
            "friction.coulomb_n": min(float(theta[2]), 0.9 * fs),  # below breakaway, as sealed
            "friction.viscous_n_s_per_m": float(theta[3]),
            "valve.area_m2": base.valve.area_m2 * float(theta[4]),
            "cylinder.port_area_m2": base.cylinder.port_area_m2 * float(theta[5]),
            "valve.exhaust_area_m2": base.valve.exhaust_area_m2 * float(theta[6])}


def nominal(base: RigParams) -> np.ndarray:
    """The fitted quantities of the rig file itself (where the fit starts)."""
    f = base.friction
    return np.array([base.valve_delay_s, f.static_n, f.coulomb_n, f.viscous_n_s_per_m,
                     1.0, 1.0, 1.0])


class ModelPredictivePolicy(TimedCutPolicy):
    """Fits the rig to the stroke so far and cuts at the robustly best time the plant predicts
    (module docstring). ``env_config``: the evaluated environment's configuration (its rig is
    the rig file; the observation must hold the rig features, ``observe_rig=True``).

    ``prior_members``: draws of the :data:`HIDDEN` quantities from ``prior`` (default the
    :class:`~pneugym.envs.family.RigFamily` ranges) the plan averages over; 0: plan on the rig
    file's values alone. ``after_breakaway_periods``: control periods after breakaway (the
    observation's ``t_breakaway``) before the first fit; ``replan_periods``: control periods between re-fits (and re-plans) until the cut;
    ``margin_periods``: half-width of the robust choice; ``fit_evals`` / ``refit_evals``: batched
    trace evaluations of the first and of each later fit; ``coarse``: the plan's coarse grid
    in control periods."""

    name = "mpc"

    def __init__(self, layout: Mapping[str, Any], env_config: Mapping[str, Any] | None = None,
                 replan_periods: int = 20, margin_periods: int = 3, fit_evals: int = 12,
                 refit_evals: int = 4, coarse: int = 4, after_breakaway_periods: int = 4,
                 prior_members: int = 6, prior: RigFamily | None = None, seed: int = 0):
        super().__init__(layout, math.inf)
        for name, v, lo in (("replan_periods", replan_periods, 1), ("margin_periods",
                            margin_periods, 0), ("fit_evals", fit_evals, 1),
                            ("refit_evals", refit_evals, 1), ("coarse", coarse, 1),
                            ("after_breakaway_periods", after_breakaway_periods, 0),
                            ("prior_members", prior_members, 0)):
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
                raise ValueError(f"{name} = {v!r} must be an integer >= {lo}")
        names = {f["name"] for f in layout.get("rig_features") or []}
        if not {*DATASHEET, "t_breakaway"} <= names:
            raise ValueError("the model-predictive policy reads the rig's datasheet values from "
                             "the observation: make the environment with observe_rig=True (as "
                             "evaluate.py does)")
        self.env_config = {k: v for k, v in dict(env_config or {}).items()
                           if k not in ("preset", "conditions", "render_mode")}
        self.planner = OraclePolicy(layout, self.env_config, coarse=coarse, seed=seed)
        self.base: RigParams = self.planner.base_rig
        self.period = float(layout["control_period_s"])
        self.window = float(self.env_config.get("decision_window_s", 0.02))
        self.replan, self.margin = replan_periods, margin_periods
        self.after = after_breakaway_periods
        self.members = hidden_members(prior or RigFamily(), prior_members, self.base, seed)
        self.fit_evals, self.refit_evals = fit_evals, refit_evals
        self._rows = 0
        self._cylinder: list[dict[str, Any]] = []  # each row's cylinder, as its rig file states

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        """Episodes on cylinders of their own (``rig_changes``, e.g. the cylinders suite): the
        plan takes each one's design and mounting angle, as its rig file states them (the
        other datasheet values it reads from the observation)."""
        self._cylinder = [{k: v for k, v in getattr(c, "rig_changes", ()) if k in CYLINDER_FIELDS}
                          for c in conditions]

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "ModelPredictivePolicy":
        u = env.unwrapped
        return cls(u.observation_layout(), env_config=u.config, **kwargs)

    # -- the control loop --------------------------------------------------------------------
    def _reset_rows(self, rows: np.ndarray) -> None:
        for i in rows:
            self._trace[i] = []
            self._u[i] = None
        self.t_cut_s[rows] = math.inf
        self._last[rows] = -math.inf

    def act(self, obs: np.ndarray) -> np.ndarray:
        n = obs.shape[0]
        t = self.read(obs, "time")
        if self._rows != n:
            self._rows = n
            self._trace: list[list[tuple[float, ...]]] = [[] for _ in range(n)]
            self._u: list[np.ndarray | None] = [None] * n
            self.t_cut_s = np.full(n, math.inf)
            self._last = np.full(n, -math.inf)
        started = np.array([bool(tr) and t[i] < tr[-1][0] for i, tr in enumerate(self._trace)])
        self._reset_rows(np.flatnonzero(started))
        x, pd, pe = (self.read(obs, k) for k in ("position", "p_drive", "p_exhaust"))
        for i in range(n):
            self._trace[i].append((t[i], x[i], pd[i], pe[i]))
        tb = self.read(obs, "t_breakaway")  # the time now until the piston has broken away
        moved = tb < t - self._half
        cut = self.read(obs, "supply_cut") > 0.5
        eps = 1e-9
        due = np.flatnonzero(moved & ~cut & (t >= tb + self.after * self.period - eps)
                             & (t >= self._last + self.replan * self.period - eps)
                             & (t < self.t_cut_s - self._half))
        if due.size:
            self._plan(obs, due, t)
        return (t >= self.t_cut_s - self._half).astype(np.int64)

    def _conditions(self, obs: np.ndarray, i: int, theta: np.ndarray) -> Conditions:
        """Noise-free conditions of row ``i`` under fitted quantities ``theta``."""
        row = obs[i:i + 1]
        length, dia, vol, load = (float(self.read(row, k)[0]) for k in DATASHEET)
        # the observed dead volume is the driving side's in all (the chamber's and an extra
        # volume at the port the rig file states, which the base rig adds again); the rod
        # side's own field only where the rig file gives the rod side one (else both sides
        # share dead_volume_m3, as the rig family draws it)
        own_rod = self.base.cylinder.dead_volume_rod_m3 is not None
        chamber = "cylinder.dead_volume_rod_m3" if (
            self.base.stroke_direction == "retract" and own_rod) else "cylinder.dead_volume_m3"
        extra = self.base.effects.dead_volume_m3
        changes = {"line.length_m": round(length, 6), "line.diameter_m": round(dia, 7),
                   chamber: float(f"{max(vol - extra, 1e-9):.5g}"),
                   **(self._cylinder[i] if i < len(self._cylinder) else {}),
                   **rig_changes(theta, self.base)}
        return Conditions(supply_pressure_gauge_pa=round(float(self.read(row,
                          "supply_setpoint")[0]), 0), load_mass_kg=round(load, 4),
                          rig_changes=tuple(sorted(changes.items())))

    def fit(self, obs: np.ndarray, i: int) -> np.ndarray:
        """Fit row ``i``'s rig to its samples so far (warm-started from its last fit); returns
        the fitted quantities."""
        first = self._u[i] is None
        theta, self._u[i] = fit_trace(
            np.asarray(self._trace[i])[:, 1:],
            lambda th: self._conditions(obs, i, th).rig(self.base), self.period,
            to_unit(nominal(self.base)) if first else self._u[i],
            self.fit_evals if first else self.refit_evals)
        return theta

    def _plan(self, obs: np.ndarray, rows: np.ndarray, t: np.ndarray) -> None:
        # candidate rigs that need a smaller substep are the plan's business, not the user's
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RigWarning)
            self._plan_rows(obs, rows, t)

    def _plan_rows(self, obs: np.ndarray, rows: np.ndarray, t: np.ndarray) -> None:
        conds, ranges = {}, {}
        for i in rows:
            self._last[i] = t[i]
            fitted = self._conditions(obs, i, self.fit(obs, i))
            t_end = []
            for m, hidden in enumerate(self.members):
                c = with_changes(fitted, hidden)
                try:  # (the call the planner's environment makes: cached, and refused here if
                    # this rig cannot be stepped or never arrives)
                    t_end.append(conventional_figures(c.rig(self.base), c.dip,
                                                      period_s=self.period)[0])
                except (ValueError, SimulationError):
                    continue
                conds[i, m] = c
            if t_end:
                ranges[i] = (int(math.ceil(t[i] / self.period - 1e-9)),
                             int(math.ceil((max(t_end) + self.window) / self.period)) + 1)
        if not ranges:
            return  # no rig to plan on: keep the last plan

        def score(cands: dict) -> dict:
            per = self.planner.score_cuts(
                conds, {(i, m): cands[i] for i, m in conds if i in cands})
            return {i: {tc: float(np.mean([per[i, m][tc] for (j, m) in per if j == i]))
                        for tc in cands[i]} for i in cands}

        scores = search_cuts(score, ranges, self.period, self.planner.coarse)
        for i, t in settle_windows(score, scores,
                                   lambda i: robust_best(scores[i], self.margin * self.period),
                                   ranges, self.period, self.margin).items():
            self.t_cut_s[i] = t


#: the rig quantities a stroke does not show before the cut: the plan averages over draws of them
HIDDEN = ("cylinder.cushion_length_m", "cylinder.cushion_factor_drive",
          "cylinder.cushion_factor_exhaust", "cylinder.cushion_ramp_m",
          "effects.leak_drive_area_m2", "effects.heat_transfer_time_constant_s")


def hidden_members(prior: RigFamily, n: int, base: RigParams, seed: int
                   ) -> list[tuple[tuple[str, Any], ...]]:
    """``n`` draws of the :data:`HIDDEN` quantities from ``prior`` (seeded); none: the rig
    file's own values (one member, no change)."""
    if n == 0:
        return [()]
    rng = np.random.default_rng([seed, 17])
    draws = [dict(prior.sample(rng, base)) for _ in range(n)]
    return [tuple((k, d[k]) for k in HIDDEN) for d in draws]


def with_changes(cond: Conditions, changes: tuple[tuple[str, Any], ...]) -> Conditions:
    """``cond`` with more ``rig_changes`` (they replace the same fields)."""
    if not changes:
        return cond
    merged = {**dict(cond.rig_changes), **dict(changes)}
    return Conditions(**{**cond.to_dict(), "rig_changes": tuple(sorted(merged.items()))})


def fit_trace(measured: np.ndarray, make_rig: Callable[[np.ndarray], RigParams],
              period_s: float, u0: np.ndarray, max_evals: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit of the :data:`FITTED` quantities to a measured stroke with the supply
    kept: ``measured`` (n, 3) position [m] and port gauge pressures [Pa] sampled every
    ``period_s`` from the extend command; ``make_rig(theta)`` the rig of fitted quantities
    ``theta``. Starts at ``u0`` (unit cube, :func:`to_unit`); at most ``max_evals`` batched
    evaluations of the residuals and their forward-difference Jacobian (one
    :func:`~pneugym.envs.rollout.keep_traces` call each). Returns ``(theta, u)``."""
    n_steps = measured.shape[0] - 1
    norm = math.sqrt(measured.size)
    jac_of: dict[bytes, np.ndarray] = {}

    def residuals(us: np.ndarray) -> np.ndarray:
        rigs = []
        for u in us:
            try:
                rigs.append(make_rig(from_unit(u)))
            except ValueError:
                rigs.append(None)
        sim = keep_traces(rigs, period_s, n_steps)
        r = ((sim - measured) / TRACE_SCALES).reshape(len(us), -1) / norm
        return np.where(np.isfinite(r), r, 10.0)  # a rig that cannot be stepped fits badly

    def fun(u: np.ndarray) -> np.ndarray:
        h = np.where(u + 0.01 <= 1.0, 0.01, -0.01)
        r = residuals(np.vstack([u, u + np.diag(h)]))  # value and Jacobian in one batch
        jac_of[u.tobytes()] = ((r[1:] - r[0]) / h[:, None]).T
        return r[0]

    sol = least_squares(fun, np.asarray(u0, dtype=float), jac=lambda u: jac_of[u.tobytes()],
                        bounds=(0.0, 1.0), method="trf", x_scale=0.1, max_nfev=max_evals)
    return from_unit(sol.x), sol.x


def expected_best(returns: Mapping[float, float], margin_s: float,
                  allowed: Collection[float] | None = None) -> float:
    """The cut-off time whose mean return among the tried times within ``margin_s`` either side
    is best: the expected return when the model misplaces the cut's effects by up to
    ``margin_s`` (``inf``, never cutting, stands for itself). ``allowed``: the times it may
    choose from (default all; the windows still read every tried time)."""
    finite = sorted(t for t in returns if math.isfinite(t))
    mean = {t: float(np.mean([returns[s] for s in finite if abs(s - t) <= margin_s + 1e-9]))
            for t in finite}
    if math.inf in returns:
        mean[math.inf] = returns[math.inf]
    return _best(mean, allowed)


def robust_best(returns: Mapping[float, float], margin_s: float,
                allowed: Collection[float] | None = None) -> float:
    """The cut-off time whose worst return among the tried times within ``margin_s`` either side
    is best (``inf``, never cutting, stands for itself); ``allowed`` as :func:`expected_best`."""
    finite = sorted(t for t in returns if math.isfinite(t))
    worst = {t: min(returns[s] for s in finite if abs(s - t) <= margin_s + 1e-9) for t in finite}
    if math.inf in returns:
        worst[math.inf] = returns[math.inf]
    return _best(worst, allowed)


def _best(value: Mapping[float, float], allowed: Collection[float] | None) -> float:
    """The key of ``value`` with the highest value among ``allowed`` (all when ``None``)."""
    keys = [t for t in value if allowed is None or t in allowed]
    if not keys:
        raise ValueError("no allowed cut-off time among the tried ones")
    return max(keys, key=value.get)
