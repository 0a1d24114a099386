"""The common policy interface and a reader that turns observations back into physical units."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np


class ObservationReader:
    """Reads the newest sample's features of a ``pneugym/CutOff-v0`` observation in SI units
    (pressures gauge [Pa]), and the rig features (``observe_rig``), from the environment's
    ``observation_layout()``."""

    def __init__(self, layout: Mapping[str, Any]):
        self.layout = dict(layout)
        feats = layout["features"]
        self.size = int(layout["size"])
        base = (int(layout["history"]) - 1) * len(feats)
        self._index = {f["name"]: (base + k, float(f["scale"])) for k, f in enumerate(feats)}
        start = int(layout["history"]) * len(feats)
        self._index.update({f["name"]: (start + k, float(f["scale"]))
                            for k, f in enumerate(layout.get("rig_features") or [])})

    def __call__(self, obs: np.ndarray, name: str) -> np.ndarray:
        """Feature ``name`` of the newest sample of each row of ``obs`` (B, size)."""
        if name not in self._index:
            raise KeyError(f"observation has no feature {name!r}; have {sorted(self._index)}")
        k, scale = self._index[name]
        return obs[:, k].astype(np.float64) * scale


class Policy:
    """Base class: subclasses implement :meth:`act` on a batch of observations (B, size)."""

    name = "policy"
    #: the conditions a trained policy was trained on (a ``ConditionSpace``, set when it is
    #: loaded, :func:`agents.registry.load_policy`); None: untrained, or not recorded
    training_space: Any = None
    #: whether :meth:`act` needs :meth:`begin_episodes` first (it plans or calibrates on each
    #: episode's conditions: the oracle, the per-rig Gas-Law rule)
    needs_conditions = False
    _told_rows: int | None = None  # how many episodes' conditions it was last told

    def __init__(self, layout: Mapping[str, Any]):
        self.read = ObservationReader(layout)

    @classmethod
    def for_env(cls, env, **kwargs: Any) -> "Policy":
        """The policy for an environment (single or vector) of ``pneugym/CutOff-v0``."""
        u = env.unwrapped
        return cls(u.observation_layout(), **kwargs)

    def act(self, obs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def begin_episodes(self, conditions: Sequence[Any]) -> None:
        """Told the conditions of the episodes about to start (one per observation row). The
        oracle and the per-rig Gas-Law rule need them (:attr:`needs_conditions`: they refuse to
        act before); rules that read a rig's datasheet values take them from each condition's
        ``rig_changes``; the others ignore them."""

    def predict(self, obs: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        """Actions (0 keep the supply, 1 cut off) for one observation or a batch, as in SB3."""
        o = np.asarray(obs)
        if o.ndim not in (1, 2) or o.shape[-1] != self.read.size:
            raise ValueError(f"{self.name}: an observation of shape {o.shape}; this policy reads "
                             f"{self.read.size} values each (one observation, or a batch of "
                             f"them): was it built for another environment's layout?")
        if not np.isfinite(o).all():
            raise ValueError(f"{self.name}: the observation holds NaN or infinity "
                             f"(a sensor or the environment failed)")
        single = o.ndim == 1
        if self.needs_conditions:
            rows = 1 if single else o.shape[0]
            if self._told_rows is None:
                raise RuntimeError(f"{self.name} plans on each episode's conditions: call "
                                   f"begin_episodes(conditions) after each reset (evaluate.py "
                                   f"and run_first_episodes do)")
            if rows != self._told_rows:
                raise ValueError(f"{self.name} was told {self._told_rows} episodes' conditions "
                                 f"(begin_episodes), given {rows} observations: one condition "
                                 f"per observation row")
        o = o.reshape(-1, self.read.size)
        a = np.asarray(self.act(o), dtype=np.int64).reshape(o.shape[0])
        return (a[0] if single else a), state


def run_first_episodes(env, policy: Policy, conditions: Sequence[Any], seed: int
                       ) -> dict[str, np.ndarray]:
    """Run the first episode of every sub-environment of a vector env under ``conditions`` and
    return the final-info arrays (one entry per sub-environment). Build the env with
    ``autoreset=False`` so that finished sub-environments idle instead of starting new episodes."""
    n = env.num_envs
    obs, _ = env.reset(seed=seed, options={"conditions": list(conditions)})
    policy.begin_episodes(list(conditions))
    out: dict[str, list] = {}
    done = np.zeros(n, dtype=bool)
    state = None
    while not done.all():
        act, state = policy.predict(obs, state)
        obs, _, term, trunc, info = env.step(act)
        collect_finals(info, done, out)
    return {k: np.array(v) for k, v in out.items()}


def collect_finals(info: dict[str, Any], done: np.ndarray, out: dict[str, list]) -> np.ndarray:
    """Copy the final figures of the sub-environments that just finished (a vector env step's
    ``info``) into ``out`` (one list per key, one entry per sub-environment) and mark them
    ``done``; returns their indices."""
    if "final_info" not in info:
        return np.zeros(0, dtype=np.int64)
    fi = info["final_info"]
    new = np.flatnonzero(info["_final_info"] & ~done)
    for i in new:
        for key, val in fi.items():
            if not key.startswith("_"):
                out.setdefault(key, [None] * done.size)[i] = val[i]
        done[i] = True
    return new
