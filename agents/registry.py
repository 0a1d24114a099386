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
