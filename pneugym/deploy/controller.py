"""A cut-off policy as a controller for a real rig: raw sensor samples in, the valve command out.

:class:`Controller` builds the observation a policy was trained on from raw SI samples (position,
absolute port pressures, time since the extend command), exactly as the environment does (it
senses through the same jitted :func:`pneugym.envs.episode.sense` and the same rig features), asks
the policy, and latches the cut. Fed the environment's own sensor values, it makes the decisions
the policy makes inside the environment, bit for bit.
"""
from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..envs import episode as EP
from ..envs.conditions import Conditions
from ..envs.cutoff import (COMMISSIONING_OBSERVATION, OBS_BOUND, RIG_OBSERVATION,
                           datasheet_features, stroke_events)
from ..params import RigParams

#: Policies that cannot run on a real rig, and why.
NOT_DEPLOYABLE = {
    "oracle": "it reads each episode's hidden conditions (true friction, valve delay, cushions) "
              "and plans with them: an upper bound for benchmarks, not a controller",
}
PERIOD_TOLERANCE = 0.05  # a sample may come this fraction of the control period early or late
MAX_PRESSURE_PA = 5e6  # 50 bar absolute: above, a sample is taken for a unit error


class SampleError(ValueError):
    """A sample the controller refuses: wrong period, out of order, not finite, or in the wrong
    unit."""


def _number(name: str, value: Any) -> float:
    ok = isinstance(value, (numbers.Real, np.floating, np.integer)) and not isinstance(
        value, (bool, np.bool_))
    if not ok or not math.isfinite(float(value)):
        raise SampleError(f"{name} = {value!r} is not a finite number (SI units: s, m, Pa)")
    return float(value)


class Controller:
    """One cylinder's cut-off controller around a policy built for ``env`` (a
    ``pneugym/CutOff-v0`` environment, single or vector, whose rig, control period, time limit
    and observation layout the controller takes; build it with ``observe_rig=True`` for the
    policies that read the rig's datasheet values, and ``observe_commissioning=True`` as well
    for those that read a commissioning stroke, :mod:`pneugym.envs.commissioning`).

    A policy that reads a commissioning stroke needs one recorded at the operating point it runs
    at (extend, cut off on arrival, held 1.5 s after it): give it with
    :meth:`set_commissioning` or to :meth:`reset`. Call :meth:`reset` at every extend command,
    then :meth:`step` once per control period with the newest samples; it returns the valve
    command (0 keep the supply, 1 cut it off), latched once cut. Use :meth:`load` to build one
    from a policy's name or a trained model.
    """

    def __init__(self, policy: Any, env: Any, source: str = "the policy",
                 period_tolerance: float = PERIOD_TOLERANCE):
        u = env.unwrapped
        if u.observe_params:
            raise ValueError(f"{source}: the environment observes privileged parameters "
                             f"(observe_params=True), which no rig's sensors give")
        if u.reversible:
            raise ValueError(f"{source}: a controller latches the cut; build the environment "
                             f"with reversible=False")
        if u.rig.stroke_direction != "extend":
            raise ValueError(f"{source}: the rig's stroke_direction is "
                             f"{u.rig.stroke_direction!r}; the controller runs extension strokes "
                             f"(position from the retracted end), the strokes its policies were "
                             f"trained on")
        if not 0.0 < period_tolerance < 0.5:
            raise ValueError(f"period_tolerance = {period_tolerance!r} must lie in (0, 0.5) (a "
                             f"fraction of the control period)")
        self.policy = policy
        self.source = source
        self.rig: RigParams = u.rig
        self.period_s = float(u.control_period_s)
        #: the episode's time limit [s] the policy was built for (its time feature's scale)
        self.time_limit_s = float(u.time_limit_s)
        self.period_tolerance = float(period_tolerance)
        self.layout = u.observation_layout()
        self._scales = u._scales.copy()
        self._n_hist = int(u.history)
        self._n_rig = len(RIG_OBSERVATION) if u.observe_rig else 0
        self._n_comm = len(COMMISSIONING_OBSERVATION) if u.observe_commissioning else 0
        model = getattr(policy, "model_layout", None) or {}
        names = {f.name for f in COMMISSIONING_OBSERVATION}
        #: whether the policy reads a commissioning stroke's features
        self.reads_commissioning = any(f.get("name") in names
                                       for f in model.get("rig_features") or [])
        if self.reads_commissioning and not self._n_comm:
            raise ValueError(f"{source} reads a commissioning stroke's features; build the "
                             f"environment with observe_commissioning=True")
        self.commissioning: np.ndarray | None = None
        self._sense = EP.sense
        self._hist = np.zeros((self._n_hist, EP.NF))
        self._obs = np.zeros((1, int(self.layout["size"])), dtype=np.float32)
        self._pa = float(self.rig.gas.ambient_pressure_pa)
        self._t: float | None = None
        self._ready = False

    # -- building ------------------------------------------------------------------------------
    @classmethod
    def load(cls, source: str | os.PathLike, rig: Any = None, *, runs: str | os.PathLike = "runs",
             control_period_s: float | None = None, time_limit_s: float | None = None,
             backend: str = "torch", **policy_kwargs: Any) -> "Controller":
        """The controller of ``source``: a baseline's name (``conventional``, ``endstroke``,
        ``gaslaw``, ``gaslaw-rig``, ``mpc``), a learned policy's name (its run under ``runs``,
        e.g. ``esac``, ``ppo``, ``esac-family``), a run directory of ``pneugym train``, a model
        file (ESAC ``.pt``, SB3 ``.zip``, Gas-Law calibration ``.json``) or a directory written
        by :func:`pneugym.deploy.export.export`. ``rig``: the rig it controls (a rig file, a
        dict, a :class:`RigParams`; default the thesis rig), from which the policies take the
        datasheet values they need. The control period and time scale default to what the run
        was trained with; ``backend`` (``torch``, ``onnx``, ``numpy``) runs a neural policy's
        network; ``policy_kwargs`` override a model's decision rule, as in
        :func:`agents.registry.load_policy`."""
        from agents.evaluation.specs import LEARNED

        from ..envs.cutoff import CutOffVectorEnv
        from ..rigfile import as_rig

        rig = as_rig(rig, "rig")
        name = os.fspath(source)
        if name in NOT_DEPLOYABLE:
            raise ValueError(f"{name!r} cannot be deployed: {NOT_DEPLOYABLE[name]}")
        path = Path(name)
        if name in LEARNED and not path.exists():
            path = Path(runs) / name
            if not path.exists():
                raise FileNotFoundError(f"{name!r}: no trained run at {path} (train it: pneugym "
                                        f"train --algo ... --out {path}, or give --runs)")
        env_cfg = _trained_env(path) if path.exists() else {}
        cfg = {"control_period_s": control_period_s if control_period_s is not None
               else env_cfg.get("control_period_s", 0.005),
               "time_limit_s": time_limit_s if time_limit_s is not None
               else env_cfg.get("time_limit_s", 4.0)}
        env = CutOffVectorEnv(num_envs=1, rig=rig, observe_rig=True, observe_commissioning=True,
                              **cfg)
        policy = _policy(name, path, env, backend, policy_kwargs)
        return cls(policy, env, source=getattr(policy, "source", name))

    def set_commissioning(self, stroke: Any) -> None:
        """The commissioning stroke the next strokes run with: a measured run (a
        :class:`~pneugym.data.MeasuredRun` or the path of its JSON) of the rig at the operating
        point, extended, cut off on arrival and held at least 1.5 s after it, or its features
        (:func:`pneugym.envs.commissioning.run_features`). Raises ``ValueError`` for a run that
        never arrives or ends too soon."""
        from ..envs.commissioning import as_features

        feats = as_features(stroke, self.rig.cylinder.stroke_m)
        self.commissioning = feats

    # -- running -------------------------------------------------------------------------------
    def reset(self, supply_setpoint_pa: float, load_mass_kg: float | None = None,
              commissioning: Any = None) -> None:
        """Start a stroke at the extend command: the supply set-point [Pa absolute] and the
        payload [kg] (default the rig's) of this stroke; ``commissioning``: a commissioning
        stroke at this operating point (:meth:`set_commissioning`; default the last one
        given), which the policies that read one need."""
        if commissioning is not None:
            self.set_commissioning(commissioning)
        if self.reads_commissioning and self.commissioning is None:
            raise ValueError(f"{self.source} reads a commissioning stroke of the rig at its "
                             f"operating point (extend, cut off on arrival, held 1.5 s): record "
                             f"one and give it, reset(..., commissioning=RUN) or "
                             f"set_commissioning(RUN)")
        ps = _number("supply_setpoint_pa", supply_setpoint_pa)
        if not self._pa + 1e4 <= ps <= self._pa + 2e6:
            hint = (" (bar given as Pa?)" if ps < 100 else
                    " (a gauge pressure? give it absolute: gauge + ambient)" if ps < self._pa
                    else "")
            raise SampleError(f"supply_setpoint_pa = {ps!r} is not a plausible absolute supply "
                              f"pressure ({self._pa + 1e4:g} to {self._pa + 2e6:g} Pa){hint}")
        load = self.rig.load_mass_kg if load_mass_kg is None else _number("load_mass_kg",
                                                                         load_mass_kg)
        rig = self.rig.with_(load_mass_kg=load, supply_pressure_gauge_pa=ps - self._pa)
        self._ps = ps
        self._extra = np.array(datasheet_features(rig)) if self._n_rig else np.zeros(0)
        self._events = np.full((1, 3), np.nan)
        self._t = None
        self._x_prev = 0.0
        self._cut = 0.0
        self.cut_time_s: float | None = None
        self._ready = True
        self.policy.begin_episodes([Conditions(supply_pressure_gauge_pa=ps - self._pa,
                                               load_mass_kg=load)])

    def step(self, t_s: float, x_m: float, p_drive_pa: float, p_exhaust_pa: float) -> int:
        """The valve command (0 keep the supply, 1 cut it off) after the samples at ``t_s`` [s]
        since the extend command: piston position ``x_m`` [m] from the retracted end, driving
        and exhaust port pressures [Pa absolute]. The first sample comes within one control
        period of the extend command, the next ones one period apart; a sample out of order,
        at another period, not finite or in another unit raises :class:`SampleError`."""
        if not self._ready:
            raise RuntimeError("call reset() at the extend command before step()")
        t, x = self._check_time(t_s), self._check_position(x_m)
        pd = self._check_pressure("p_drive_pa", p_drive_pa)
        pe = self._check_pressure("p_exhaust_pa", p_exhaust_pa)
        fresh = self._t is None
        if not fresh:
            self._hist[:-1] = self._hist[1:]
        self._sense(self._hist[-1], x, x if fresh else self._x_prev, pd, pe, self._ps, self._pa,
                    t, self._cut, self.period_s, self._scales)
        if fresh:
            self._hist[:-1] = self._hist[-1]
        self._x_prev, self._t = x, t
        obs = self._observation()
        act, _ = self.policy.predict(obs)
        if int(np.asarray(act).reshape(-1)[0]) == 1 and self._cut == 0.0:
            self._cut, self.cut_time_s = 1.0, t
        return int(self._cut)

    @property
    def cut(self) -> bool:
        """Whether the supply is cut (latched until the next :meth:`reset`)."""
        return self._ready and self._cut > 0.0

    @property
    def observation(self) -> np.ndarray:
        """The policy's last observation (float32), as the environment would have built it."""
        return self._obs[0].copy()

    def _observation(self) -> np.ndarray:
        n = self._hist.size
        self._obs[0, :n] = np.clip(self._hist.reshape(-1), -OBS_BOUND, OBS_BOUND)
        if self._n_rig:
            k = self._extra.size
            self._obs[0, n:n + k] = np.clip(self._extra, -OBS_BOUND, OBS_BOUND)
            self._obs[0, n + k:n + self._n_rig] = stroke_events(self._events, self._hist[-1:],
                                                                self._scales)[0]
        if self._n_comm:  # zeros for the policies that do not read them (their columns dropped)
            m = n + self._n_rig
            self._obs[0, m:m + self._n_comm] = (0.0 if self.commissioning is None else np.clip(
                self.commissioning, -OBS_BOUND, OBS_BOUND))
        return self._obs

    # -- checking samples ----------------------------------------------------------------------
    def _check_time(self, t_s: Any) -> float:
        t = _number("t_s", t_s)
        p, tol = self.period_s, self.period_tolerance * self.period_s
        if self._t is None:
            if not -tol <= t < p + tol:
                raise SampleError(f"the first sample after reset() is at t_s = {t!r} s; it must "
                                  f"come within one control period ({p:g} s) of the extend "
                                  f"command (t_s is the time since it, in seconds)")
            return t
        dt = t - self._t
        if dt <= 0.0:
            raise SampleError(f"sample at t_s = {t!r} s is out of order: the last one was at "
                              f"{self._t!r} s")
        if abs(dt - p) > tol:
            raise SampleError(f"sample at t_s = {t!r} s comes {dt * 1e3:.4g} ms after the last; "
                              f"the controller runs at the control period it was trained for, "
                              f"{p * 1e3:g} ms (+-{tol * 1e3:.2g} ms): resample, or give the "
                              f"samples in seconds")
        return t

    def _check_position(self, x_m: Any) -> float:
        x = _number("x_m", x_m)
        s = self.rig.cylinder.stroke_m
        lo, hi = -0.05 * s - 2e-3, 1.05 * s + 2e-3
        if not lo <= x <= hi:
            hint = " (mm given as m?)" if lo <= x / 1e3 <= hi else ""
            raise SampleError(f"x_m = {x!r} is outside the stroke ({s:g} m, from the retracted "
                              f"end){hint}")
        return x

    def _check_pressure(self, name: str, value: Any) -> float:
        p = _number(name, value)
        lo = 0.3 * self._pa
        if not lo <= p <= MAX_PRESSURE_PA:
            if 0 < p * 1e5 <= MAX_PRESSURE_PA and p * 1e5 >= lo:
                hint = " (bar given as Pa?)"
            elif lo <= p * 1e3 <= MAX_PRESSURE_PA:
                hint = " (kPa given as Pa?)"
            elif lo <= p + self._pa <= MAX_PRESSURE_PA:
                hint = " (a gauge pressure? give it absolute: gauge + ambient)"
            else:
                hint = ""
            raise SampleError(f"{name} = {p!r} is not a plausible absolute pressure ({lo:g} to "
                              f"{MAX_PRESSURE_PA:g} Pa){hint}")
        return p


def _trained_env(path: Path) -> dict[str, Any]:
    """The control period and time limit a run (or a model in a run directory, or an export:
    its ``controller.json``'s ``model_layout``) trained with."""
    from agents.learned import read_run

    from .export import CONTROLLER_FILE

    if path.is_dir() and (path / CONTROLLER_FILE).is_file():
        try:
            layout = json.loads((path / CONTROLLER_FILE).read_text())["model_layout"]
            time = [f for f in layout["features"] if f["name"] == "time"]
            return {"control_period_s": float(layout["control_period_s"]),
                    **({"time_limit_s": float(time[0]["scale"])} if time else {})}
        except (ValueError, KeyError, TypeError, IndexError):
            return {}  # (load_exported refuses a broken file with its own message)
    run = read_run(path) if (path.is_dir() or path.is_file()) else None
    env = dict((run or {}).get("env_config") or {})
    return {k: env[k] for k in ("control_period_s", "time_limit_s") if k in env}


def _policy(name: str, path: Path, env: Any, backend: str, kwargs: dict[str, Any]) -> Any:
    """The policy ``name`` (a baseline) or at ``path`` for ``env``, its network on ``backend``."""
    from agents import BASELINES, make_policy
    from agents.registry import load_policy

    if backend not in ("torch", "onnx", "numpy"):
        raise ValueError(f"backend = {backend!r}: choose 'torch', 'onnx' or 'numpy'")
    if name in BASELINES and not path.exists():
        if backend != "torch":
            raise ValueError(f"{name!r} has no network: it runs as it is (backend='torch')")
        return make_policy(name, env, **kwargs)
    if path.is_dir() and (path / "controller.json").is_file():
        from .export import load_exported

        if kwargs:
            raise ValueError(f"{path} is an exported controller: its decision rule is fixed at "
                             f"export; got overrides {sorted(kwargs)}")
        from agents.registry import check_operating_point, check_rig

        policy = load_exported(path, env.unwrapped.observation_layout(),
                               backend="numpy" if backend == "torch" else backend)
        check_rig(policy, None, env)
        check_operating_point(policy, env)
        return policy
    if not path.exists():
        from agents.evaluation.specs import LEARNED

        raise FileNotFoundError(f"{name!r} is neither a baseline ({sorted(BASELINES)}), a "
                                f"learned policy's name ({list(LEARNED)}) nor an existing path")
    policy = load_policy(path, env, **kwargs)
    if backend != "torch":
        from .export import with_backend

        policy = with_backend(policy, backend)
    return policy
