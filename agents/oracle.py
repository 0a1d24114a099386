"""The oracle: the best single cut-off time for an episode, found with **privileged** access to
the episode's conditions (load, supply, friction, valve delay, dip), by searching on copies of the
plant. No deployable controller knows these; the oracle is the upper bound for any latched
policy at the control period's resolution, and the reference of ``oracle_fraction``.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from .base import Policy, run_first_episodes


class TimedCutPolicy(Policy):
    """Cuts the supply from time ``t_cut_s`` on (one value, or one per observation row;
    ``inf`` = never)."""

    name = "timed"

    def __init__(self, layout: Mapping[str, Any], t_cut_s: float | np.ndarray = math.inf):
        super().__init__(layout)
        self.t_cut_s = np.asarray(t_cut_s, dtype=float)
        self._half = 0.5 * float(layout["control_period_s"])

    def act(self, obs: np.ndarray) -> np.ndarray:
        return (self.read(obs, "time") >= self.t_cut_s - self._half).astype(np.int64)


class OraclePolicy(TimedCutPolicy):
    """Cuts at the control step that maximises the episode's return under its true conditions.

    Call :meth:`begin_episodes` with the conditions of the episodes about to start (evaluate.py
    does, from the reset ``info``). The search evaluates a cut at every ``coarse``-th control step
    (and never cutting) in one batched run, then every step around the three best; ``plan`` results
    are cached per condition. ``env_config`` must be the evaluated environment's configuration.
    """

    name = "oracle"
    privileged = True

    def __init__(self, layout: Mapping[str, Any], env_config: Mapping[str, Any] | None = None,
                 coarse: int = 4, seed: int = 0):
        super().__init__(layout)
        if not (isinstance(coarse, int) and coarse >= 1):
            raise ValueError(f"coarse = {coarse!r} must be an integer >= 1")
        self.env_config = {k: v for k, v in dict(env_config or {}).items()
                           if k not in ("preset", "conditions", "render_mode")}
        self.coarse, self.seed = coarse, seed
        self.period = float(layout["control_period_s"])
        self._cache: dict[tuple, tuple[float, float]] = {}

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "OraclePolicy":
        u = env.unwrapped
        return cls(u.observation_layout(), env_config=u.config, **kwargs)

    def _rig(self):
        from pneugym.envs.cutoff import CutOffVectorEnv

        if not hasattr(self, "_base_rig"):
            self._base_rig = CutOffVectorEnv(num_envs=1, **self.env_config).rig
        return self._base_rig

    def _returns(self, cond, t_cuts: np.ndarray) -> np.ndarray:
        from pneugym.envs.cutoff import CutOffVectorEnv

        env = CutOffVectorEnv(num_envs=t_cuts.size, **self.env_config)
        pol = TimedCutPolicy(env.observation_layout(), t_cuts)
        return run_first_episodes(env, pol, [cond] * t_cuts.size, self.seed)["objective"]

    def plan(self, cond) -> tuple[float, float]:
        """``(t_cut_s, return)`` of the best cut-off for conditions ``cond`` (``inf`` = never)."""
        from pneugym.envs import conventional_figures

        key = cond.physics_key()
        if key in self._cache:
            return self._cache[key]
        quiet = type(cond)(**{**cond.to_dict(), "position_noise_m": 0.0, "pressure_noise_pa": 0.0})
        t_conv, _ = conventional_figures(quiet.rig(self._rig()), quiet.dip)
        window = float(self.env_config.get("decision_window_s", 0.02))
        last = int(math.ceil((t_conv + window) / self.period)) + 1
        steps = np.arange(0, last + 1, self.coarse)
        t = np.append(steps * self.period, math.inf)
        j = self._returns(quiet, t)
        best = np.argsort(-j)[:3]
        fine = set()
        for i in best:
            if math.isfinite(t[i]):
                k = int(round(t[i] / self.period))
                fine.update(range(max(0, k - self.coarse + 1), k + self.coarse))
        fine -= set(int(s) for s in steps)
        if fine:
            tf = np.array(sorted(fine), dtype=float) * self.period
            t = np.concatenate([t, tf])
            j = np.concatenate([j, self._returns(quiet, tf)])
        i = int(np.argmax(j))
        self._cache[key] = (float(t[i]), float(j[i]))
        return self._cache[key]

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        self.t_cut_s = np.array([self.plan(c)[0] for c in conditions])
