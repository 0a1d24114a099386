"""The batched environment behind stable-baselines3's ``VecEnv`` interface, for training.

>>> from pneugym.envs.sb3 import CutOffVecEnv
>>> venv = CutOffVecEnv(num_envs=8, preset="randomized")        # doctest: +SKIP
>>> model = stable_baselines3.PPO("MlpPolicy", venv)             # doctest: +SKIP

Finished sub-environments are reset in the same step (SB3's convention): ``infos[i]`` then holds
``terminal_observation``, ``TimeLimit.truncated`` and the episode's final figures.
"""
from __future__ import annotations

from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

from .cutoff import RESET_OPTIONS, CutOffVectorEnv, _seed_ok, check_options


class CutOffVecEnv(VecEnv):
    """SB3 ``VecEnv`` over :class:`~pneugym.envs.cutoff.CutOffVectorEnv` (one jitted call steps
    all ``num_envs``). Keywords are the environment's options."""

    def __init__(self, num_envs: int = 8, max_episode_steps: int | None = None, **config: Any):
        self.venv = CutOffVectorEnv(num_envs=num_envs, max_episode_steps=max_episode_steps,
                                    **config)
        self.render_mode = None
        super().__init__(num_envs, self.venv.single_observation_space,
                         self.venv.single_action_space)
        self._actions: np.ndarray | None = None

    # -- VecEnv ------------------------------------------------------------------------------
    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        """SB3's ``seed``: sub-environment ``i`` gets ``seed + i`` at the next reset."""
        if not _seed_ok(seed):
            raise ValueError(f"seed = {seed!r} is invalid: must be None or an integer >= 0")
        return super().seed(None if seed is None else int(seed))

    def reset(self) -> np.ndarray:
        seed = self._seeds[0]
        seeds = None if seed is None else [s if s is not None else 0 for s in self._seeds]
        obs, _ = self.venv.reset(seed=seeds, options=self._batched_options())
        self._reset_seeds()
        self._reset_options()
        return obs

    def _batched_options(self) -> dict[str, Any] | None:
        """SB3's per-environment options as the batched env's: each reset option (both are per
        environment: ``conditions``, ``commissioning``) gathered into one list, ``None`` for an
        environment not given it (the same option for all, as ``set_options(dict)`` gives it,
        becomes that value for each)."""
        opts = [o or {} for o in self._options]
        keys = [k for k in RESET_OPTIONS if any(k in o for o in opts)]
        check_options({k: None for o in opts for k in o})  # an unknown key named
        return {k: [o.get(k) for o in opts] for k in keys} or None

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, rew, term, trunc, info = self.venv._step(self._actions, full_info=False)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        done = term | trunc
        if np.count_nonzero(done):
            fi = info["final_info"]
            for i in np.flatnonzero(done):
                d = {k: v[i] for k, v in fi.items() if not k.startswith("_")}
                d["terminal_observation"] = info["final_obs"][i]
                d["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
                d["episode_return"] = d["objective"]
                infos[i] = d
        return obs, rew.astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    # -- attribute access (one shared object: every index sees the same value) ---------------
    def _idx(self, indices: VecEnvIndices) -> list[int]:
        return list(self._get_indices(indices))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        if attr_name == "render_mode":
            return [None for _ in self._idx(indices)]
        return [getattr(self.venv, attr_name) for _ in self._idx(indices)]

    def _all(self, indices: VecEnvIndices, what: str) -> list[int]:
        """The sub-environments share one batched env: a change or a call reaches all of them,
        so it may only be asked of all of them."""
        idx = self._idx(indices)
        if sorted(idx) != list(range(self.num_envs)):
            raise ValueError(f"{what} with indices={indices!r}: the {self.num_envs} "
                             f"sub-environments are one batched env; call it for all of them "
                             f"(indices=None)")
        return idx

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._all(indices, f"set_attr({attr_name!r})")
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        """Call ``method_name`` of the batched env once; its result is repeated per index."""
        idx = self._all(indices, f"env_method({method_name!r})")
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in idx]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper],
                       indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._idx(indices)]

    def observation_layout(self) -> dict[str, Any]:
        return self.venv.observation_layout()

    @property
    def unwrapped(self) -> CutOffVectorEnv:
        return self.venv

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]
