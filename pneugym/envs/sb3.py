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

from .cutoff import CutOffVectorEnv


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
    def reset(self) -> np.ndarray:
        seed = self._seeds[0]
        seeds = None if seed is None else [s if s is not None else 0 for s in self._seeds]
        opts = self._options[0] or None
        obs, _ = self.venv.reset(seed=seeds, options=opts)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, rew, term, trunc, info = self.venv.step(self._actions)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        done = term | trunc
        if done.any():
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

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        fn = getattr(self.venv, method_name)
        return [fn(*method_args, **method_kwargs) for _ in self._idx(indices)]

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
