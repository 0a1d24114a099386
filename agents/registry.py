"""Build a policy by name for an environment."""
from __future__ import annotations

from typing import Any

from .base import Policy
from .baselines import ConventionalPolicy, EndStrokePolicy
from .gaslaw import GasLawPolicy
from .oracle import OraclePolicy

BASELINES: dict[str, type[Policy]] = {
    "conventional": ConventionalPolicy, "endstroke": EndStrokePolicy, "gaslaw": GasLawPolicy,
    "oracle": OraclePolicy,
}


def make_policy(name: str, env, **kwargs: Any) -> Policy:
    """The baseline ``name`` for ``env`` (a ``pneugym/CutOff-v0`` env, single or vector)."""
    if name not in BASELINES:
        raise ValueError(f"unknown policy {name!r}; baselines are {sorted(BASELINES)} "
                         f"(saved models are given as NAME=PATH)")
    return BASELINES[name].for_env(env, **kwargs)


class SB3Policy(Policy):
    """A saved stable-baselines3 model (PPO, DQN, A2C) behind the common interface."""

    name = "sb3"

    def __init__(self, layout, model):
        super().__init__(layout)
        shape = tuple(model.observation_space.shape)
        if shape != (self.read.size,):
            raise ValueError(f"the model expects observations of shape {shape}, the environment "
                             f"gives ({self.read.size},): its observation layout differs")
        self.model = model

    def act(self, obs):
        a, _ = self.model.predict(obs, deterministic=True)
        return a


def load_policy(path: str, env) -> Policy:
    """A saved model for ``env``: a stable-baselines3 ``.zip`` (PPO, DQN or A2C)."""
    import zipfile
    from pathlib import Path

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no saved model at {path}")
    if not zipfile.is_zipfile(p):
        raise ValueError(f"{path} is not a stable-baselines3 model (.zip)")
    from stable_baselines3 import A2C, DQN, PPO

    errors = []
    for algo in (PPO, DQN, A2C):
        try:
            model = algo.load(p, device="cpu")
        except Exception as exc:  # noqa: BLE001 - try the next algorithm, report all
            errors.append(f"{algo.__name__}: {exc}")
            continue
        return SB3Policy(env.unwrapped.observation_layout(), model)
    raise ValueError(f"could not load {path} as PPO, DQN or A2C: " + "; ".join(errors))
