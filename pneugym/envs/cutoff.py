"""The cut-off environment: decide, every control period, whether to cut off the air supply of a
pneumatic cylinder during its extension stroke.

**Episode.** One extension stroke of the thesis rig, from the extend command (``t = 0``; the
valve opens only after its switching delay) to the end of the stroke. It *terminates* when the
piston has reached the end of stroke and either the supply has actually closed (valve delay and
ramp elapsed) after a cut-off, or ``decision_window_s`` has passed since the arrival without a
cut-off (the supply then stays connected and the driving side counts as filled to supply
pressure); or as a **stall**, when the piston is stuck short of the stroke with the supply cut and
closed, and the trapped air can no longer push it past the breakaway friction. It is *truncated*
at ``time_limit_s``.

**Action** ``Discrete(2)``: 0 = keep the supply connected, 1 = cut it off. The cut-off is latched
(as in the thesis) unless ``reversible=True``, where each action sets the valve command.

**Observation** ``Box(float32)``: ``history`` samples (oldest first) of the seven sensor features
of :data:`OBSERVATION`, each ``(value - offset) / scale``, then, with ``observe_rig=True``, the
rig's datasheet values of :data:`RIG_OBSERVATION` (what a user writes in a rig file), then, with
``observe_commissioning=True`` as well, what one recorded stroke of the rig at the operating
point shows (:data:`COMMISSIONING_OBSERVATION`, :mod:`pneugym.envs.commissioning`), then, with
``observe_params=True``, the privileged features of :data:`PARAM_OBSERVATION`.

**Reward.** The return of an episode equals its objective

    J = - E_wasted / E_conv - w_time * max(0, T / T_conv - 1) - w_stick * n_stick
        - w_stall * (stroke not completed)

with ``E_wasted`` the air potential energy left in the driving side when the return stroke
would begin (thesis eq. 5.9), ``E_conv`` that of a conventional stroke at the same conditions
(closed form), ``T`` the stroke time (the time limit if it never completed), ``T_conv`` the
conventional stroke time at the same conditions (simulated once per condition and cached) and
``n_stick`` the stick-slip events. ``reward_mode="dense"`` (default) pays the change of ``J``
evaluated on the current state every step (it telescopes to ``J`` exactly); ``"sparse"`` pays
``J`` at the last step.

**Conditions** (load, supply, friction and valve-delay scales, a supply-pressure dip, sensor
noise) are drawn at every reset from a :class:`~pneugym.envs.conditions.ConditionSpace` with
``self.np_random``; ``reset(options={"conditions": Conditions(...)})`` forces them, and
``reset(options={"commissioning": ...})`` (``observe_commissioning``) tells an episode a
commissioning stroke (:func:`check_commissioning`) instead of the simulated one.
"""
from __future__ import annotations

import functools
import math
import numbers
import operator
from dataclasses import dataclass
from typing import Any, Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..params import RigParams, did_you_mean
from ..physics import layout as L
from ..physics import system as K
from ..physics.energy import saving_ratio
from ..plant import Plant, SimulationError, set_supply_dip
from ..units import free_air_nl
from . import episode as EP
from .conditions import Conditions, ConditionSpace, as_conditions, resolve


@dataclass(frozen=True)
class Feature:
    """One observation element: ``(value - offset) / scale``."""

    name: str
    unit: str
    scale: float
    offset: str = "0"
    description: str = ""


PRESSURE_SCALE_PA = 6e5
VELOCITY_SCALE_M_S = 0.5

#: The sensor features of one sample (computed by :func:`pneugym.envs.episode.sense`).
OBSERVATION: tuple[Feature, ...] = (
    Feature("position", "m", math.nan, "0", "piston position from the retracted end / stroke"),
    Feature("velocity", "m/s", VELOCITY_SCALE_M_S, "0",
            "velocity estimate: difference of the last two measured positions / period"),
    Feature("p_drive", "Pa", PRESSURE_SCALE_PA, "ambient", "driving-port transducer, gauge"),
    Feature("p_exhaust", "Pa", PRESSURE_SCALE_PA, "ambient", "exhaust-port transducer, gauge"),
    Feature("supply_setpoint", "Pa", PRESSURE_SCALE_PA, "ambient", "supply set-point, gauge"),
    Feature("time", "s", math.nan, "0", "time since the extend command / time_limit_s"),
    Feature("supply_cut", "-", 1.0, "0", "1 while the supply is cut"),
)
#: What a policy may know of the rig (``observe_rig=True``): the datasheet values its rig file
#: states (fixed for an episode), then what the stroke so far tells of the rest (from the noisy
#: sensors: when the driving pressure rose, i.e. the valve delay; when the piston broke away, and
#: the pressure difference that moved it, i.e. friction and load). Before an event the feature
#: holds the time (or pressure difference) now. A policy trained on a family of rigs learns from
#: them which rig it is on.
RIG_OBSERVATION: tuple[Feature, ...] = (
    Feature("line_length", "m", 5.0, "0", "supply line length"),
    Feature("line_diameter", "m", 0.008, "0", "supply line inner diameter"),
    Feature("dead_volume", "m3", 5e-4, "0", "stated dead volume of the driving chamber"),
    Feature("payload", "kg", 40.0, "0", "the load the cylinder moves"),
    Feature("t_pressure_rise", "s", 1.0, "0",
            "time the driving-port pressure first exceeded 0.1 bar gauge"),
    Feature("t_breakaway", "s", 1.0, "0", "time the piston first passed 2 mm"),
    Feature("dp_breakaway", "Pa", PRESSURE_SCALE_PA, "0",
            "driving minus exhaust port pressure when the piston first passed 2 mm"),
)
#: The features of the commissioning stroke, in observation order (``value / scale``).
COMMISSIONING_OBSERVATION: tuple[Feature, ...] = (
    Feature("comm_stroke_time", "s", 1.0, "0",
            "commissioning stroke: time from the extend command to the arrival (the "
            "conventional stroke time at this operating point)"),
    Feature("comm_motion_time", "s", 1.0, "0",
            "commissioning stroke: from the breakaway (piston past 2 mm) to the arrival"),
    Feature("comm_p_drive_arrival", "Pa", PRESSURE_SCALE_PA, "ambient",
            "commissioning stroke: driving-port pressure over the 10 ms before the arrival"),
    Feature("comm_p_exhaust_arrival", "Pa", PRESSURE_SCALE_PA, "ambient",
            "commissioning stroke: exhaust-port pressure over the 10 ms before the arrival "
            "(the exhaust cushion)"),
    Feature("comm_dp_motion", "Pa", PRESSURE_SCALE_PA, "0",
            "commissioning stroke: median driving minus exhaust pressure over the middle half "
            "of the motion (what it takes to keep moving)"),
    Feature("comm_hold_decay", "-", 1.0, "0",
            "commissioning stroke: relative drop of the driving pressure (gauge) over the hold, "
            "from 0.5 s to 1.5 s after the arrival (leaks, heat exchange)"),
)
N_DATASHEET = 4  # the first RIG_OBSERVATION features: the rig file's values
RISE_PA = 1e4  # gauge pressure [Pa] that marks the valve's opening in the driving port
BREAKAWAY_M = 2e-3  # position [m] that marks the piston's breakaway
#: Privileged features (``observe_params=True``): the true conditions of the episode.
PARAM_OBSERVATION: tuple[Feature, ...] = (
    Feature("load_mass", "kg", 30.0, "0", "payload"),
    Feature("friction_scale", "-", 1.0, "0", "factor on the nominal friction"),
    Feature("valve_delay", "s", 0.4, "0", "valve switching delay"),
)
REGISTERED_MAX_STEPS = 800  # max_episode_steps of pneugym/CutOff-v0 (4 s at 5 ms)
_MAYBE_NONE = ("stroke_time_s", "time_increase", "cutoff_time_s")
#: the step info's keys, in the order of the rows of :func:`pneugym.envs.episode.info_row`
_STEP_INFO = ("time_s", "position_m", "p_drive_pa", "p_exhaust_pa", "measured_x_m",
              "measured_p_drive_pa", "measured_p_exhaust_pa", "supply_cut")
_STEP_INFO_MASKS = tuple("_" + k for k in _STEP_INFO)
#: The number fields of :class:`Conditions` (``infos["conditions"]`` of the vector env).
_COND_FIELDS = tuple(k for k in Conditions.__dataclass_fields__ if k != "rig_changes")
_cond_values = operator.attrgetter(*_COND_FIELDS)
OBS_BOUND = 10.0  # the Box is [-10, 10]; observations are clipped to it


def datasheet_features(rig: RigParams) -> tuple[float, float, float, float]:
    """The first :data:`N_DATASHEET` features of :data:`RIG_OBSERVATION` for ``rig``, scaled:
    line length and diameter, stated dead volume, payload (what its rig file says)."""
    return (rig.line.length_m / 5.0, rig.line.diameter_m / 0.008,
            (rig.drive_dead_volume_m3 + rig.effects.dead_volume_m3) / 5e-4,
            rig.load_mass_kg / 40.0)


def stroke_events(events: np.ndarray, newest: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The stroke-so-far features of :data:`RIG_OBSERVATION` (B, 3), scaled and clipped, from
    the newest sample's features ``newest`` (B, NF) of :func:`pneugym.envs.episode.sense`.
    ``events`` (B, 3): time of the pressure rise [s], time of the breakaway [s] and the pressure
    difference then [Pa], NaN until they happen; updated in place."""
    x, t = newest[:, 0] * scales[0], newest[:, 5] * scales[3]
    pd = newest[:, 2] * PRESSURE_SCALE_PA
    dp = (newest[:, 2] - newest[:, 3]) * PRESSURE_SCALE_PA
    rise = np.isnan(events[:, 0]) & (pd > RISE_PA)
    events[rise, 0] = t[rise]
    moved = np.isnan(events[:, 1]) & (x > BREAKAWAY_M)
    events[moved, 1], events[moved, 2] = t[moved], dp[moved]
    now = np.stack([t, t, dp], axis=1)
    vals = np.where(np.isnan(events), now, events) / np.array([1.0, 1.0, PRESSURE_SCALE_PA])
    return np.clip(vals, -OBS_BOUND, OBS_BOUND)


RESET_OPTIONS = ("conditions", "commissioning")
MAX_HISTORY = 1000  # samples per observation (5 s at 5 ms)
_MAX_OPTION_HINT = {"control_period_s": (1.0, "ms given as s? (5 ms = 0.005 s)"),
                    "decision_window_s": (10.0, "ms given as s? (20 ms = 0.02 s)"),
                    "time_limit_s": (3600.0, "a stroke takes seconds"),
                    "sensor_lag_s": (1.0, "ms given as s? (15 ms = 0.015 s)")}
_MAX_OPTION = {k: v[0] for k, v in _MAX_OPTION_HINT.items()}


def check_flag(name: str, value: Any) -> bool:
    """A yes/no option: a bool (numpy's too), never a string or a number read as truthy."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} = {value!r} is invalid: must be True or False")
    return bool(value)


def check_action(action: Any) -> int:
    """One action as :class:`gymnasium.spaces.Discrete` (2) takes it: an integer 0 or 1 (Python,
    numpy, or a 0-d integer array); anything else is refused, never rounded or reshaped."""
    if isinstance(action, (bool, np.bool_)):
        return int(action)
    if isinstance(action, np.ndarray) and action.shape != ():
        raise ValueError(f"action {action!r} has shape {action.shape}: one environment takes one "
                         f"action, 0 (keep) or 1 (cut off); pass action.item()")
    if not (isinstance(action, (int, np.integer)) or (
            isinstance(action, np.ndarray) and action.dtype.kind in "biu")) or int(action) not in (0, 1):
        raise ValueError(f"action {action!r} is invalid: the action space is Discrete(2), 0 "
                         f"(keep the supply) or 1 (cut it off), as an integer")
    return int(action)


def check_actions(actions: Any, n: int) -> np.ndarray:
    """A batch of ``n`` actions, each 0 or 1 (integers), shape exactly ``(n,)``."""
    if type(actions) is np.ndarray and actions.dtype == np.int64 and actions.shape == (n,) \
            and EP.binary(actions):  # the common case: 0/1 as int64, checked in one call
        return actions.copy()
    a = np.asarray(actions)
    if a.shape != (n,):
        raise ValueError(f"actions must have shape ({n},), one per sub-environment; got shape "
                         f"{a.shape}")
    if a.dtype.kind not in "biu" or not ((a == 0) | (a == 1)).all():
        bad = a if a.dtype.kind not in "biu" else a[(a != 0) & (a != 1)]
        raise ValueError(f"actions must be integers 0 (keep) or 1 (cut off); got "
                         f"{bad.ravel()[:5]!r} (dtype {a.dtype})")
    return a.astype(np.int64)


def check_options(options: Any) -> Mapping[str, Any]:
    """``reset`` options: a mapping whose keys are in :data:`RESET_OPTIONS`."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ValueError(f"reset options must be a dict, got {options!r}")
    for k in options:
        if k not in RESET_OPTIONS:
            raise ValueError(f"unknown reset option {k!r}{did_you_mean(k, RESET_OPTIONS)}; "
                             f"known: {list(RESET_OPTIONS)}")
    return options


def check_commissioning(value: Any, observed: bool, stroke_m: float,
                        what: str = "options['commissioning']") -> np.ndarray:
    """A ``commissioning`` reset option as the scaled :data:`COMMISSIONING_OBSERVATION`
    (:func:`pneugym.envs.commissioning.as_features`: the features themselves, a measured
    commissioning stroke or the path of its JSON), refused where none is ``observed``."""
    if not observed:
        raise ValueError(f"{what}: this environment does not observe a commissioning stroke "
                         f"(build it with observe_rig=True, observe_commissioning=True)")
    from .commissioning import as_features

    return as_features(value, stroke_m, what)


@functools.lru_cache(maxsize=4096)
def _template(params: RigParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Packed parameters and the initial state ``(P, y0, d0)`` of a rig (cached)."""
    plant = Plant(params)
    return plant.P.copy(), plant.y.copy(), plant.d.copy()


@functools.lru_cache(maxsize=4096)
def conventional_figures(params: RigParams, dip: tuple[float, float, float] = (0.0, 0.0, 0.0),
                         t_max_s: float = 20.0, period_s: float = 0.0) -> tuple[float, float]:
    """Conventional stroke time [s] (valve delay included) and wasted energy [J] of ``params``
    with a supply dip, simulated once and cached. Raises ``ValueError`` if it never arrives.

    ``period_s > 0`` advances in control periods of that length, as an episode does (the last
    substep of every period is shortened to land on it), so that a conventional episode's
    stroke time equals this one to the last bit; ``0``: one call."""
    plant = Plant(params)
    plant.set_supply_dip(*dip)
    if period_s > 0.0:
        plant.command(1)
        n = int(math.ceil(t_max_s / period_s))
        for _ in range(n):
            plant.advance(period_s, stop_on_arrival=True)
            if plant.arrival_time_s is not None:
                break
    else:
        plant.advance(t_max_s, command=1, stop_on_arrival=True)
    if plant.arrival_time_s is None:
        raise ValueError(f"the conventional stroke does not complete within {t_max_s} s for "
                         f"{params.supply_pressure_gauge_pa / 1e5:.3g} bar gauge, "
                         f"{params.load_mass_kg} kg: the conditions are beyond the rig")
    return plant.arrival_time_s, plant.conventional_energy_j


def _check_settings(values: Mapping[str, Any], reward_mode: Any) -> None:
    """The environment's numeric settings (periods and limits [s], reward weights) and its
    reward mode, each refused by name when invalid."""
    for name, val in values.items():
        if name not in ("control_period_s", "time_limit_s", "decision_window_s", "w_time",
                        "w_stall", "w_stick", "sensor_lag_s"):
            raise ValueError(f"unknown setting {name!r} (weights: w_time, w_stall, w_stick)")
        ok = isinstance(val, numbers.Real) and not isinstance(val, (bool, np.bool_)) \
            and math.isfinite(val)
        if not ok or val < 0 or (val == 0 and name in ("control_period_s", "time_limit_s")):
            raise ValueError(f"{name} = {val!r} is invalid (a finite number >= 0; > 0 for "
                             f"control_period_s and time_limit_s)")
        if val > _MAX_OPTION.get(name, math.inf):
            hi, hint = _MAX_OPTION_HINT[name]
            raise ValueError(f"{name} = {val!r} is not plausible (at most {hi:g} s): {hint}")
    if reward_mode not in ("dense", "sparse"):
        raise ValueError(f"reward_mode = {reward_mode!r}: choose 'dense' or 'sparse'")


def _max_valve_delay_s(space: ConditionSpace, rig: RigParams) -> float:
    """The longest valve delay [s] an episode of ``space`` on ``rig`` can have (the thesis
    valve's delay is linear in the supply pressure, clipped: longest at an end of the range)."""
    from .family import apply_changes

    r = apply_changes(rig, space.rig_changes) if space.rig_changes else rig
    d = max(r.valve.delay_for(p) for p in space.supply_pressure_gauge_pa)
    if space.family is not None:
        d = max(d, space.family.valve_delay_s[1] * r.valve.delay_scale)
    return d * space.valve_delay_scale[1]


def _check_queue(delay_s: float, period_s: float) -> None:
    """A reversible cut-off may change the command every control period: all the changes in
    flight during one valve delay must fit the valve's queue (``QCAP``)."""
    if delay_s / period_s + 2 > L.QCAP:
        raise ValueError(
            f"reversible=True with a valve delay of up to {delay_s * 1e3:.0f} ms and a "
            f"{period_s * 1e3:g} ms control period: more valve commands in flight than the "
            f"valve queues ({L.QCAP}); choose a longer control_period_s or a latched cut-off "
            f"(reversible=False)")


class _CutOffCore:
    """The state and logic shared by :class:`CutOffEnv` (one episode) and
    :class:`CutOffVectorEnv` (a batch): packed plants ``Y, P, D``, episode arrays ``E``."""

    def _configure(self, n: int, preset, conditions, rig, control_period_s, time_limit_s,
                   decision_window_s, reversible, history, observe_params, observe_rig,
                   observe_commissioning,
                   sensor_lag_s,
                   w_time, w_stall, w_stick, reward_mode) -> None:
        _check_settings({"control_period_s": control_period_s, "time_limit_s": time_limit_s,
                         "decision_window_s": decision_window_s, "w_time": w_time,
                         "w_stall": w_stall, "w_stick": w_stick, "sensor_lag_s": sensor_lag_s},
                        reward_mode)
        if not (isinstance(history, (int, np.integer)) and not isinstance(history, bool)
                and 1 <= history <= MAX_HISTORY):
            raise ValueError(f"history = {history!r} must be an integer in [1, {MAX_HISTORY}]")
        for name, val in (("reversible", reversible), ("observe_params", observe_params),
                          ("observe_rig", observe_rig),
                          ("observe_commissioning", observe_commissioning)):
            check_flag(name, val)
        from ..rigfile import as_rig

        base = as_rig(rig, "rig")
        self.config["rig"] = None if rig is None else base  # a file is read once
        self.space: ConditionSpace = resolve(preset, conditions, base)
        if reversible:  # every episode the space can draw must fit the valve's queue
            _check_queue(_max_valve_delay_s(self.space, base), float(control_period_s))
        if sensor_lag_s:
            base = base.with_(effects={"sensor_lag_s": float(sensor_lag_s)})
        self.rig = base
        self.control_period_s = float(control_period_s)
        self.time_limit_s = float(time_limit_s)
        self.decision_window_s = float(decision_window_s)
        self.reversible = bool(reversible)
        self.history = int(history)
        self.observe_params = bool(observe_params)
        self.observe_rig = bool(observe_rig)
        self.observe_commissioning = bool(observe_commissioning)
        if self.observe_commissioning and not self.observe_rig:
            raise ValueError("observe_commissioning=True needs observe_rig=True: the "
                             "commissioning stroke's features follow the rig's datasheet values")
        #: the rig features observed: datasheet and stroke events, then the commissioning stroke's
        self._rig_features: tuple[Feature, ...] = (
            (RIG_OBSERVATION if self.observe_rig else ())
            + (COMMISSIONING_OBSERVATION if self.observe_commissioning else ()))
        self.weights = {"w_time": float(w_time), "w_stall": float(w_stall),
                        "w_stick": float(w_stick)}
        self.reward_mode = reward_mode
        self.conditions: list[Conditions | None] = [None] * n
        self._cond_values = np.zeros((n, len(_COND_FIELDS)))  # each episode's, in that order
        self._rig_changes = np.empty(n, dtype=object)  # each episode's, as a dict (the info's)
        for i in range(n):
            self._rig_changes[i] = {}

        P, y0, d0 = _template(self.rig)
        self.Y = np.zeros((n, y0.size))
        self.P = np.zeros((n, P.size))
        self.D = np.zeros((n, d0.size))
        self.E = np.zeros((n, EP.NE))
        self._W = np.empty((n, K.work_size(P)))  # the plants' work arrays
        self._starts: dict[tuple, tuple] = {}  # physics key -> rows of P, Y, D, E; datasheet
        self._b = 2 * self.rig.line.n_cells - 1
        self._noise = np.zeros((n, 3))
        self._noise_zero = True  # no noise left in self._noise (so it need not be zeroed)
        self._noise_std = np.zeros((n, 3))
        self._x_prev = np.zeros(n)
        self._events = np.full((n, 3), np.nan)  # t rise, t breakaway, dp breakaway (observe_rig)
        self._scales = np.array([self.rig.cylinder.stroke_m, VELOCITY_SCALE_M_S,
                                 PRESSURE_SCALE_PA, self.time_limit_s])
        n_extra = len(self._rig_features) + (
            len(PARAM_OBSERVATION) if observe_params else 0)
        self._extra = np.zeros((n, n_extra))
        nobs = self.history * EP.NF + n_extra
        self._obs = np.zeros((n, nobs), dtype=np.float32)
        self._hist = np.zeros((n, self.history, EP.NF))
        self._single_obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(nobs,),
                                            dtype=np.float32)
        self._rewards = np.zeros(n)
        self._status = np.zeros(n, dtype=np.int64)

    # -- describing ------------------------------------------------------------------------
    @property
    def observation_names(self) -> list[str]:
        """Name of every observation element (``name[-k]`` = k samples ago)."""
        names = [f"{f.name}[{k - self.history + 1}]" if self.history > 1 else f.name
                 for k in range(self.history) for f in OBSERVATION]
        names += [f.name for f in self._rig_features]
        if self.observe_params:
            names += [f.name for f in PARAM_OBSERVATION]
        return names

    def observation_layout(self) -> dict[str, Any]:
        """Everything a saved model needs to check that it sees the same observation."""
        feats = [{"name": f.name, "unit": f.unit,
                  "scale": (self.rig.cylinder.stroke_m if f.name == "position" else
                            self.time_limit_s if f.name == "time" else f.scale),
                  "offset": f.offset, "description": f.description} for f in OBSERVATION]
        params = [{"name": f.name, "unit": f.unit, "scale": f.scale, "description": f.description}
                  for f in PARAM_OBSERVATION] if self.observe_params else []
        rig = [{"name": f.name, "unit": f.unit, "scale": f.scale, "description": f.description}
               for f in self._rig_features]
        return {"history": self.history, "features": feats, "rig_features": rig,
                "param_features": params,
                "size": int(self._obs.shape[1]), "control_period_s": self.control_period_s}

    # -- episodes --------------------------------------------------------------------------
    def _start(self, i: int, cond: Conditions) -> None:
        """Start episode ``i`` under ``cond``: plant at the extend command, bookkeeping zeroed."""
        key = (cond.physics_key(), self.control_period_s)  # (the conventional stroke's period)
        start = self._starts.get(key)
        if start is None:  # (building the rig and hashing it costs ~0.2 ms: once per conditions)
            start = self._first_start(cond)
            if len(self._starts) >= 4096:
                self._starts.clear()
            self._starts[key] = start
        P, y0, d0, e0, datasheet = start
        if self.reversible:  # (conditions given at reset, or settings changed since)
            _check_queue(float(P[L.P_DELAY]), self.control_period_s)
        self.P[i], self.Y[i], self.D[i], self.E[i] = P, y0, d0, e0
        self._settings(self.E[i])  # public attributes a user (or SB3's set_attr) may change
        self.conditions[i] = cond
        self._rig_changes[i] = dict(cond.rig_changes)
        self._cond_values[i] = _cond_values(cond)
        self._noise_std[i] = (cond.position_noise_m, cond.pressure_noise_pa,
                              cond.pressure_noise_pa)
        k = len(self._rig_features)
        if k:
            self._extra[i, :N_DATASHEET] = datasheet[:N_DATASHEET]
            self._extra[i, len(RIG_OBSERVATION):k] = datasheet[N_DATASHEET:]
            self._events[i] = np.nan
        if self.observe_params:
            self._extra[i, k:] = (cond.load_mass_kg / 30.0, cond.friction_scale,
                              float(self.P[i, L.P_DELAY]) / 0.4)
        self._status[i] = 0

    def _tell_commissioning(self, i: int, features: Any) -> None:
        """Episode ``i`` observes ``features`` (:func:`check_commissioning`) as its
        commissioning stroke instead of the one simulated from its conditions."""
        k = len(self._rig_features)
        self._extra[i, k - len(COMMISSIONING_OBSERVATION):k] = features

    def _first_start(self, cond: Conditions) -> tuple:
        """The rows of ``P, Y, D, E`` that start an episode under ``cond`` (supply dip set, extend
        commanded, bookkeeping zeroed) and its :func:`datasheet_features` (``observe_rig``):
        they depend on :meth:`Conditions.physics_key` only, so :meth:`_start` keeps them."""
        params = cond.rig(self.rig)
        P, y0, d0 = (a.copy() for a in _template(params))
        t_conv, e_conv = conventional_figures(params, cond.dip, period_s=self.control_period_s)
        set_supply_dip(P, *cond.dip)
        K.command(d0, P, 1.0)
        e = np.zeros(EP.NE)
        e[EP.E_T_CONV], e[EP.E_E_CONV] = t_conv, e_conv
        e[EP.E_T_CUT] = -1.0
        datasheet = datasheet_features(params) if self.observe_rig else None
        if self.observe_commissioning:  # the rig at this operating point, as commissioned
            from .commissioning import condition_features

            datasheet = (*datasheet, *condition_features(cond, self.rig))
        return P, y0, d0, e, datasheet

    def _settings(self, e: np.ndarray) -> None:
        """The environment's settings into an episode's bookkeeping row ``e``, checked again:
        they are public attributes a user (or SB3's ``set_attr``) may change between episodes."""
        _check_settings({"control_period_s": self.control_period_s,
                         "time_limit_s": self.time_limit_s,
                         "decision_window_s": self.decision_window_s, **self.weights},
                        self.reward_mode)
        check_flag("reversible", self.reversible)
        self._scales[3] = self.time_limit_s  # the time feature's scale follows the limit
        e[EP.E_REV] = float(self.reversible)
        e[EP.E_T_LIMIT] = self.time_limit_s
        e[EP.E_WINDOW] = self.decision_window_s
        e[EP.E_W_TIME] = self.weights["w_time"]
        e[EP.E_W_STALL] = self.weights["w_stall"]
        e[EP.E_W_STICK] = self.weights["w_stick"]
        e[EP.E_DENSE] = 1.0 if self.reward_mode == "dense" else 0.0
        e[EP.E_PERIOD] = self.control_period_s

    def _draw_noise(self, rows: np.ndarray, rng: np.random.Generator) -> None:
        """The sensor noise of episodes ``rows``' next observation."""
        sel = slice(None) if rows is self._all else rows  # all of them: views, not copies
        std = self._noise_std[sel]
        if np.count_nonzero(std):
            self._noise[sel] = rng.standard_normal((rows.size, 3)) * std
            self._noise_zero = False
        elif not self._noise_zero:  # (never a noisy episode's last draw left on a noise-free one)
            self._noise[sel] = 0.0
            self._noise_zero = rows is self._all

    def _observe(self, rows: np.ndarray, rng: np.random.Generator, fresh: bool) -> None:
        """Sense episodes ``rows`` (with noise) and write their observations."""
        self._draw_noise(rows, rng)
        EP.observe(self.Y, self.P, self.D, self.E, rows, self._noise, self._x_prev, self._scales,
                   fresh, self._hist, self._extra, OBS_BOUND, self._obs)
        if self.observe_rig:
            self._observe_events(rows)

    def _observe_events(self, rows: np.ndarray) -> None:
        """The stroke-so-far features of :data:`RIG_OBSERVATION` from the latest (noisy) sample
        of episodes ``rows``, written into their observations."""
        ev = self._events[rows]
        vals = stroke_events(ev, self._hist[rows, -1], self._scales)
        self._events[rows] = ev
        col = self.history * EP.NF + N_DATASHEET
        self._obs[rows, col:col + 3] = vals

    def _retry(self, i: int, action: int, y0: np.ndarray, d0: np.ndarray, e0: np.ndarray
               ) -> float:
        """Episode ``i``'s step went non-physical: step it again from its state before the step
        with half the substep (kept for the rest of the episode), at most ``MAX_STEP_RETRIES``
        times, as :class:`~pneugym.plant.Plant` does; returns the step's reward. Still failing,
        ``self._status[i]`` stays set (:meth:`_check_status` raises)."""
        import warnings

        from ..plant import MAX_STEP_RETRIES, RigWarning

        r = 0.0
        for _ in range(MAX_STEP_RETRIES):
            self.Y[i], self.D[i], self.E[i] = y0, d0, e0
            self.P[i, L.P_DT] *= 0.5
            r, st = EP.step_one(self.Y[i], self.P[i], self.D[i], self.E[i], action, self._W[i])
            self._status[i] = st
            if not st:
                warnings.warn(f"episode {i} under {self.conditions[i]}: a step went "
                              f"non-physical; retried with half the substep, "
                              f"{self.P[i, L.P_DT]:.3g} s, for the rest of the episode",
                              RigWarning, stacklevel=3)
                break
        return float(r)

    def _check_status(self) -> None:
        bad = np.flatnonzero(self._status)
        if bad.size:
            i = int(bad[0])
            plant = Plant(self.conditions[i].rig(self.rig))
            plant.P[:], plant.y[:], plant.d[:] = self.P[i], self.Y[i], self.D[i]
            try:
                plant._check(int(self._status[i]))
            except SimulationError as exc:
                raise SimulationError(f"episode {i} under {self.conditions[i]}: {exc}") from None

    def _step_info(self, i: int) -> dict[str, Any]:
        y, d = self.Y[i], self.D[i]
        pd, pe, _, _ = K.chamber_pressures(y, self.P[i], self._b)
        mx, mpd, mpe = self._measured(i)
        return {"time_s": float(d[L.D_T]), "position_m": float(y[self._b + L.Y_X]),
                "p_drive_pa": float(pd), "p_exhaust_pa": float(pe),
                "supply_cut": bool(self.E[i, EP.E_CUT] > 0.0),
                "measured_x_m": float(mx), "measured_p_drive_pa": float(mpd),
                "measured_p_exhaust_pa": float(mpe)}

    def _measured(self, rows: int | slice) -> tuple[Any, Any, Any]:
        """What the sensors of episode(s) ``rows`` (an index or a slice) read at the last
        observation: position [m], driving and exhaust port pressures [Pa absolute], noise
        included (what a :class:`pneugym.deploy.Controller` on the rig would be fed)."""
        b, Y, noise = self._b, self.Y, self._noise
        return (Y[rows, b + L.Y_X] + noise[rows, 0], Y[rows, b + L.Y_SD] + noise[rows, 1],
                Y[rows, b + L.Y_SE] + noise[rows, 2])

    def _final_info(self, i: int) -> dict[str, Any]:
        """The episode's figures (``info`` of its last step)."""
        e, d = self.E[i], self.D[i]
        completed = bool(e[EP.E_COMPLETED] > 0.0)
        t_conv = float(e[EP.E_T_CONV])
        stroke = float(d[L.D_T_ARRIVE]) if completed else None
        ew, ec = float(e[EP.E_E_WASTED]), float(e[EP.E_E_CONV])
        return {
            "saving_ratio": float(saving_ratio(ec, ew)),
            "energy_wasted_j": ew,
            "energy_conventional_j": ec,
            "air_mass_kg": float(self.Y[i, self._b + L.Y_MIN]),
            "free_air_nl": free_air_nl(float(self.Y[i, self._b + L.Y_MIN])),
            "stroke_time_s": stroke,
            "conventional_stroke_time_s": t_conv,
            "time_increase": (stroke / t_conv - 1.0) if completed else None,
            "cutoff_time_s": float(e[EP.E_T_CUT]) if e[EP.E_T_CUT] >= 0.0 else None,
            "stalled": bool(e[EP.E_STALLED] > 0.0),
            "stick_slip_events": int(EP.stick_slips(d)),
            "completed": completed,
            "objective": float(e[EP.E_OBJ]),
        }


_DEFAULTS = dict(preset=None, conditions=None, rig=None, control_period_s=0.005,
                 time_limit_s=4.0, decision_window_s=0.02, reversible=False, history=1,
                 observe_params=False, observe_rig=False, observe_commissioning=False, sensor_lag_s=0.0, w_time=0.3, w_stall=2.0, w_stick=0.5,
                 reward_mode="dense")


class CutOffEnv(_CutOffCore, gym.Env):
    """One cut-off episode per reset (see the module docstring for the task).

    Parameters (all keyword): ``preset`` (``"thesis-1.5bar"``, ``"thesis-2.5bar"``,
    ``"randomized"``, ``"rig"``, a :class:`ConditionSpace` or fixed :class:`Conditions`; default
    ``"rig"``: the rig's own supply and load, for the thesis rig 2.5 bar and 10 kg);
    ``conditions`` (overrides of the space's fields, numbers or ``(low, high)``); ``rig`` (the
    rig: a :class:`RigParams`, a dict of its fields or of a measured run's ``rig`` section, or the
    path of a rig file, :meth:`RigParams.load`; default the thesis rig); ``control_period_s`` (5 ms); ``time_limit_s``
    (4 s); ``decision_window_s`` after arrival (20 ms); ``reversible``; ``history`` (samples per
    observation); ``observe_params``; ``observe_rig`` (the rig file's datasheet values,
    :data:`RIG_OBSERVATION`); ``observe_commissioning`` (with ``observe_rig``: the features of
    one recorded stroke of the rig at the operating point, cut off on arrival and held,
    :data:`COMMISSIONING_OBSERVATION`); ``sensor_lag_s`` (transducer lag); the objective weights
    ``w_time`` (0.3), ``w_stall`` (2), ``w_stick`` (0.5); ``reward_mode`` (``"dense"``/``"sparse"``);
    ``render_mode`` (``"rgb_array"``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **config: Any):
        unknown = set(config) - set(_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown CutOffEnv option(s) {sorted(unknown)}"
                             f"{did_you_mean(sorted(unknown)[0], _DEFAULTS)}; "
                             f"known: {sorted(_DEFAULTS)}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}: only 'rgb_array' is supported")
        self.config = {**_DEFAULTS, **config}
        self._configure(1, **self.config)
        steps = math.ceil(self.time_limit_s / self.control_period_s - 1e-9)
        if steps > REGISTERED_MAX_STEPS:
            gym.logger.warn(
                f"time_limit_s / control_period_s = {steps} steps, more than the "
                f"{REGISTERED_MAX_STEPS} of the registered TimeLimit: with gymnasium.make, pass "
                f"max_episode_steps={steps} too, or episodes end early without their final info")
        self.render_mode = render_mode
        self.action_space = spaces.Discrete(2)
        self.observation_space = self._single_obs_space
        self._y, self._p, self._d, self._e = self.Y[0], self.P[0], self.D[0], self.E[0]
        self._all = np.zeros(1, dtype=np.int64)
        self._trace: list[np.ndarray] = []

    def reset(self, *, seed: int | None = None, options: Mapping[str, Any] | None = None):
        super().reset(seed=seed)
        cond = check_options(options).get("conditions")
        if cond is None:
            cond = self.space.sample(self.np_random, self.rig)
        else:
            cond = as_conditions(cond, "options['conditions']")
        self._start(0, cond)
        told = check_options(options).get("commissioning")
        if told is not None:
            self._tell_commissioning(0, check_commissioning(
                told, self.observe_commissioning, float(self.P[0, L.P_STROKE])))
        self._observe(self._all, self.np_random, fresh=True)
        self._trace = []
        self._record()
        info = self._step_info(0)
        info["conditions"] = cond.to_dict()
        return self._obs[0].copy(), info

    def step(self, action):
        if self._e[EP.E_T_LIMIT] == 0.0:
            raise RuntimeError("call reset() before step()")
        if self._e[EP.E_DONE] != 0.0:
            raise RuntimeError("the episode has ended: call reset()")
        act = check_action(action)
        before = (self._y.copy(), self._d.copy(), self._e.copy())
        r, st = EP.step_one(self._y, self._p, self._d, self._e, act, self._W[0])
        if st:
            self._status[0] = st
            r = self._retry(0, act, *before)
            self._check_status()
        self._observe(self._all, self.np_random, fresh=False)
        self._record()
        done = self._e[EP.E_DONE]
        info = self._step_info(0)
        if done:
            info.update(self._final_info(0))
        return self._obs[0].copy(), float(r), bool(done == 1.0), bool(done == 2.0), info

    # -- rendering ---------------------------------------------------------------------------
    def _record(self) -> None:
        if self.render_mode == "rgb_array":
            row = np.zeros(L.NR)
            K.record_row(self._y, self._p, self._d, row, 0.0)
            self._trace.append(row)

    def render(self):
        if self.render_mode != "rgb_array":
            gym.logger.warn("render() needs render_mode='rgb_array'")
            return None
        from .render import episode_figure_rgb
        return episode_figure_rgb(np.array(self._trace), self.conditions[0],
                                  self.rig.cylinder.stroke_m, self.P[0, L.P_PA])


class CutOffVectorEnv(_CutOffCore, VectorEnv):
    """``num_envs`` cut-off episodes stepped together in one parallel jitted call
    (:func:`pneugym.envs.episode.step_observe`). Same options as :class:`CutOffEnv`, plus
    ``max_episode_steps``. Sub-environment ``i`` draws its conditions from its own generator
    (seeded ``seed + i``, as :class:`gymnasium.vector.SyncVectorEnv` does), so it reproduces the
    episodes of a ``CutOffEnv`` reset with ``seed + i``; sensor noise comes from one shared
    generator. Autoreset is *same-step*: a finished sub-environment is reset at once, its last
    observation and info are in ``infos["final_obs"]`` and ``infos["final_info"]``. With
    ``autoreset=False`` a finished sub-environment idles instead (not stepped, reward 0, its flags
    stay set) until the next ``reset``: for evaluating a fixed set of episodes.
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 1, max_episode_steps: int | None = None,
                 autoreset: bool = True, **config: Any):
        unknown = set(config) - set(_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown CutOffVectorEnv option(s) {sorted(unknown)}"
                             f"{did_you_mean(sorted(unknown)[0], _DEFAULTS)}; known: "
                             f"{sorted(_DEFAULTS)}")
        if not (isinstance(num_envs, (int, np.integer)) and not isinstance(num_envs, bool)
                and num_envs >= 1):
            raise ValueError(f"num_envs = {num_envs!r} must be an integer >= 1")
        self.config = {**_DEFAULTS, **config}
        if max_episode_steps is not None and not (
                isinstance(max_episode_steps, (int, np.integer)) and not isinstance(
                    max_episode_steps, bool) and max_episode_steps >= 1):
            raise ValueError(f"max_episode_steps = {max_episode_steps!r} must be None or an "
                             f"integer >= 1")
        self.num_envs = int(num_envs)
        self._configure(self.num_envs, **self.config)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.autoreset = check_flag("autoreset", autoreset)
        if not self.autoreset:
            self.metadata = {**self.metadata, "autoreset_mode": AutoresetMode.DISABLED}
        self.render_mode = None
        self.single_action_space = spaces.Discrete(2)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.single_observation_space = self._single_obs_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._rngs: list[np.random.Generator] = []
        self._steps = np.zeros(self.num_envs, dtype=np.int64)
        self._info = np.zeros((self.num_envs, 8))  # the step info (EP.info_row)
        self._ones = np.ones(self.num_envs, dtype=bool)
        self._before = (np.empty_like(self.Y), np.empty_like(self.D), np.empty_like(self.E))
        self._all = np.arange(self.num_envs)

    def reset(self, *, seed: int | list[int] | None = None,
              options: Mapping[str, Any] | None = None):
        n = self.num_envs
        seeds = _seeds(seed, n)
        super().reset(seed=seeds[0])
        conds = check_options(options).get("conditions")
        if conds is not None:
            if isinstance(conds, (Conditions, Mapping, str)) or not hasattr(conds, "__len__") \
                    or len(conds) != n:
                raise ValueError(f"options['conditions'] needs a list of one Conditions (or "
                                 f"None) per environment ({n}); got {conds!r:.200}")
            conds = [None if c is None else as_conditions(c, f"options['conditions'][{i}]")
                     for i, c in enumerate(conds)]
        told = check_options(options).get("commissioning")
        if told is not None:
            if isinstance(told, (str, Mapping)) or not hasattr(told, "__len__") \
                    or len(told) != n:
                raise ValueError(f"options['commissioning'] needs a list of one commissioning "
                                 f"stroke (or None) per environment ({n}); got {told!r:.200}")
            if not self.observe_commissioning:
                check_commissioning(None, False, 0.0)
        # a sub-environment reset without a seed goes on with its stream (as a gymnasium env
        # does); a fresh stream from the OS only before its first seed
        self._rngs = [seeding.np_random(s)[0] if s is not None or not self._rngs else self._rngs[i]
                      for i, s in enumerate(seeds)]
        for i in range(n):
            c = conds[i] if conds is not None else None
            self._start(i, c if c is not None else self.space.sample(self._rngs[i], self.rig))
            if told is not None and told[i] is not None:
                self._tell_commissioning(i, check_commissioning(
                    told[i], True, float(self.P[i, L.P_STROKE]),
                    f"options['commissioning'][{i}]"))
        self._steps[:] = 0
        self._idle = np.zeros(n, dtype=bool)
        self._observe(self._all, self.np_random, fresh=True)
        infos = self._batch_info()
        infos["conditions"] = self._conditions_info()
        infos["_conditions"] = np.ones(n, dtype=bool)
        return self._obs.copy(), infos

    def step(self, actions):
        return self._step(actions, full_info=True)

    def _step(self, actions, full_info: bool):
        """:meth:`step`; with ``full_info=False`` (the SB3 adapter, which keeps only the finished
        episodes' figures) the infos hold only ``final_obs`` and ``final_info``."""
        if not self._rngs:
            raise RuntimeError("call reset() before step()")
        acts = check_actions(actions, self.num_envs)
        n = self.num_envs
        Yb, Db, Eb = self._before  # the state before the step, for a retry
        terminated, truncated = np.empty(n, dtype=bool), np.empty(n, dtype=bool)
        # one compiled call steps, senses, limits and reads out every episode (noise drawn first)
        self._draw_noise(self._all, self.np_random)
        n_ended = EP.step_observe(
            self.Y, self.P, self.D, self.E, acts, self._rewards, self._status, self._W,
            self._noise, self._x_prev, self._scales, self._hist, self._extra, OBS_BOUND,
            self._obs, self._b, self._info, Yb, Db, Eb, self._steps,
            self.max_episode_steps or 0, self._idle, terminated, truncated)
        state_known = True  # self._info holds every episode's step info
        if np.count_nonzero(self._status):  # a step that went non-physical: retried, sensed
            state_known = False
            bad = np.flatnonzero(self._status)
            for i in bad:
                self._rewards[i] = self._retry(i, int(acts[i]), Yb[i], Db[i], Eb[i])
            self._check_status()
            EP.observe(self.Y, self.P, self.D, self.E, bad, self._noise, self._x_prev,
                       self._scales, False, self._hist, self._extra, OBS_BOUND, self._obs)
            for i in bad:
                if self.max_episode_steps is not None and \
                        self._steps[i] >= self.max_episode_steps and self.E[i, EP.E_DONE] == 0.0:
                    self._rewards[i] += EP.truncate(self.Y[i], self.P[i], self.D[i], self.E[i])
            done = self.E[:, EP.E_DONE]
            terminated, truncated = done == 1.0, done == 2.0
            n_ended = 1  # (counted again below)
        if self.observe_rig:
            self._observe_events(self._all)
        rewards = self._rewards.copy()
        ended = ((terminated | truncated) & ~self._idle).nonzero()[0] if n_ended else ()
        extra: dict[str, Any] = {}
        if len(ended):
            state_known = False
            final_obs = np.empty(self.num_envs, dtype=object)  # all None
            finals = {}
            for i in ended:
                final_obs[i] = self._obs[i].copy()
                finals[int(i)] = {**self._step_info(i), **self._final_info(i)}
                if self.autoreset:
                    self._start(int(i), self.space.sample(self._rngs[i], self.rig))
                    self._steps[i] = 0
                else:
                    self._idle[i] = True
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[ended] = True
            if self.autoreset:  # the step's info describes the new episodes, as in SyncVectorEnv
                self._observe(ended, self.np_random, fresh=True)
                if full_info:
                    extra["conditions"] = self._conditions_info()
                    extra["_conditions"] = mask
            extra["final_obs"] = final_obs
            extra["_final_obs"] = mask
            extra["final_info"] = self._stack_final(finals, mask)
            extra["_final_info"] = mask
        infos = {**self._batch_info(state_known), **extra} if full_info else extra
        return self._obs.copy(), rewards, terminated, truncated, infos

    def _stack_final(self, finals: dict[int, dict[str, Any]], mask: np.ndarray
                     ) -> dict[str, Any]:
        """Final infos as arrays; keys whose value may be None (never cut, not completed) are
        object arrays in every step, so None never turns into NaN."""
        first = next(iter(finals.values()))
        out: dict[str, Any] = {}
        for key in first:
            if key in _MAYBE_NONE:
                arr = np.empty(self.num_envs, dtype=object)  # all None
            elif isinstance(first[key], bool):
                arr = np.zeros(self.num_envs, dtype=bool)
            elif isinstance(first[key], int):
                arr = np.zeros(self.num_envs, dtype=np.int64)
            else:
                arr = np.zeros(self.num_envs)
            for i, f in finals.items():
                arr[i] = f[key]
            out[key] = arr
            out["_" + key] = mask
        return out

    def _conditions_info(self) -> dict[str, np.ndarray]:
        out = dict(zip(_COND_FIELDS, self._cond_values.T.copy()))
        out["rig_changes"] = self._rig_changes.copy()  # (one dict per episode, made at its start)
        return out

    def _batch_info(self, state_known: bool = False) -> dict[str, Any]:
        """The step's info: every plant's state and what its sensors read (read out again unless
        ``state_known``: the step's compiled call left it in ``self._info``)."""
        if not state_known:
            EP.info_rows(self.Y, self.P, self.D, self.E, self._noise, self._b, self._info)
        cols = self._info.T.copy()
        info = dict(zip(_STEP_INFO, cols))
        info["supply_cut"] = info["supply_cut"].astype(bool)  # (E_CUT is 0 or 1)
        info.update(dict.fromkeys(_STEP_INFO_MASKS, self._ones.copy()))
        return info


def _seed_ok(s: Any) -> bool:
    return s is None or (isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 0)


def _seeds(seed: Any, n: int) -> list[int | None]:
    """One seed per sub-environment: ``seed + i`` from one integer, or a list of ``n`` (each an
    integer >= 0 or None)."""
    if _seed_ok(seed):
        return [None] * n if seed is None else [int(seed) + i for i in range(n)]
    if isinstance(seed, (list, tuple, np.ndarray)) and len(seed) == n and all(map(_seed_ok, seed)):
        return [None if s is None else int(s) for s in seed]
    raise ValueError(f"seed = {seed!r:.100} is invalid: must be None, an integer >= 0, or a list "
                     f"of {n} such seeds (one per sub-environment)")


def make_vec(num_envs: int = 1, max_episode_steps: int | None = None, **config: Any
             ) -> CutOffVectorEnv:
    """The ``vector_entry_point`` of ``pneugym/CutOff-v0``."""
    return CutOffVectorEnv(num_envs=num_envs, max_episode_steps=max_episode_steps, **config)
