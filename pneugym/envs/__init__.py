"""Gymnasium environments on the pneugym plant: ``pneugym/CutOff-v0`` (one stroke) and
``pneugym/CutOffCycle-v0`` (a working cycle, extend and retract; registered on
``import pneugym``), the stroke's batched vector version and an SB3 ``VecEnv`` adapter."""
from .conditions import PRESETS, Conditions, ConditionSpace
from .cutoff import (
    OBSERVATION, PARAM_OBSERVATION, REGISTERED_MAX_STEPS, CutOffEnv, CutOffVectorEnv,
    conventional_figures,
)
from .cycle import CYCLE_MAX_STEPS, CutOffCycleEnv

ENV_ID = "pneugym/CutOff-v0"
CYCLE_ENV_ID = "pneugym/CutOffCycle-v0"
MAX_EPISODE_STEPS = REGISTERED_MAX_STEPS  # 4 s at the default 5 ms control period


def register() -> None:
    """Register ``pneugym/CutOff-v0`` and ``pneugym/CutOffCycle-v0`` (idempotent)."""
    import gymnasium as gym

    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="pneugym.envs.cutoff:CutOffEnv",
                     vector_entry_point="pneugym.envs.cutoff:make_vec",
                     max_episode_steps=MAX_EPISODE_STEPS)
    if CYCLE_ENV_ID not in gym.registry:
        gym.register(id=CYCLE_ENV_ID, entry_point="pneugym.envs.cycle:CutOffCycleEnv",
                     max_episode_steps=CYCLE_MAX_STEPS)


__all__ = ["Conditions", "ConditionSpace", "PRESETS", "CutOffEnv", "CutOffVectorEnv",
           "CutOffCycleEnv", "OBSERVATION", "PARAM_OBSERVATION", "conventional_figures", "ENV_ID",
           "CYCLE_ENV_ID", "MAX_EPISODE_STEPS", "register"]
