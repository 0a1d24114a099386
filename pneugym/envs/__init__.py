"""Gymnasium environments on the pneugym plant: ``pneugym/CutOff-v0`` (registered on
``import pneugym``), its batched vector version and an SB3 ``VecEnv`` adapter."""
from .conditions import PRESETS, Conditions, ConditionSpace
from .cutoff import (
    OBSERVATION, PARAM_OBSERVATION, REGISTERED_MAX_STEPS, CutOffEnv, CutOffVectorEnv,
    conventional_figures,
)

ENV_ID = "pneugym/CutOff-v0"
MAX_EPISODE_STEPS = REGISTERED_MAX_STEPS  # 4 s at the default 5 ms control period


def register() -> None:
    """Register ``pneugym/CutOff-v0`` (idempotent)."""
    import gymnasium as gym

    if ENV_ID in gym.registry:
        return
    gym.register(id=ENV_ID, entry_point="pneugym.envs.cutoff:CutOffEnv",
                 vector_entry_point="pneugym.envs.cutoff:make_vec",
                 max_episode_steps=MAX_EPISODE_STEPS)


__all__ = ["Conditions", "ConditionSpace", "PRESETS", "CutOffEnv", "CutOffVectorEnv",
           "OBSERVATION", "PARAM_OBSERVATION", "conventional_figures", "ENV_ID", "MAX_EPISODE_STEPS", "register"]
