"""Checking that a :class:`~pneugym.deploy.Controller` decides as its policy does inside the
environment: the episodes are run in the environment, and a controller is fed what the
environment's sensors read there (noise included, ``info["measured_*"]``), sample by sample.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .controller import Controller


def environment_trace(policy: Any, conditions: Sequence[Any], seed: int,
                      env_config: Mapping[str, Any]) -> list[dict[str, np.ndarray]]:
    """Run one episode per condition (one batch) with ``policy``; per episode, what its sensors
    read at every decision (``t``, ``x``, ``p_drive``, ``p_exhaust``: s, m, Pa absolute), the
    observation and the valve command in force after the decision (latched)."""
    from ..envs.cutoff import CutOffVectorEnv

    env = CutOffVectorEnv(num_envs=len(conditions), autoreset=False, **env_config)
    obs, info = env.reset(seed=seed, options={"conditions": list(conditions)})
    policy.begin_episodes(list(conditions))
    keys = ("time_s", "measured_x_m", "measured_p_drive_pa", "measured_p_exhaust_pa")
    rec: list[dict[str, list]] = [{k: [] for k in (*keys, "obs", "command")} for _ in conditions]
    done = np.zeros(len(conditions), dtype=bool)
    while not done.all():
        act, _ = policy.predict(obs)
        for i in np.flatnonzero(~done):
            r = rec[i]
            for k in keys:
                r[k].append(float(info[k][i]))
            r["obs"].append(obs[i].copy())
            r["command"].append(int(bool(info["supply_cut"][i]) or int(act[i]) == 1))
        obs, _, term, trunc, info = env.step(act)
        done |= term | trunc
    names = dict(zip(keys, ("t", "x", "p_drive", "p_exhaust")))
    return [{names.get(k, k): np.asarray(v) for k, v in r.items()} for r in rec]


def check_equivalence(make_policy: Callable[[Any], Any], conditions: Sequence[Any], seed: int = 0,
                      env_config: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Run ``conditions`` in the environment with ``make_policy(env)`` and replay every episode's
    sensor readings through a :class:`Controller` around a second ``make_policy`` built for a
    one-episode environment on that episode's rig (its ``rig_changes``) and feed it what the
    sensors read. Returns the episodes and decisions compared, and how many differ: observation
    elements (bit for bit) and valve commands, with the first difference found."""
    from ..envs.cutoff import CutOffVectorEnv
    from ..envs.family import apply_changes

    from ..envs.commissioning import condition_features

    cfg = {"observe_rig": True, "observe_commissioning": True, **dict(env_config or {})}
    probe = CutOffVectorEnv(num_envs=len(conditions), autoreset=False, **cfg)
    traces = environment_trace(make_policy(probe), conditions, seed, cfg)
    base = probe.rig
    out: dict[str, Any] = {"episodes": len(conditions), "decisions": 0,
                           "observations_differing": 0, "commands_differing": 0, "first": None}
    for k, (cond, tr) in enumerate(zip(conditions, traces)):
        env = CutOffVectorEnv(num_envs=1, **{**cfg, "rig": apply_changes(base, cond.rig_changes)})
        ctl = Controller(make_policy(env), env)
        ctl.set_commissioning(condition_features(cond, base))  # as the environment was told
        ctl.reset(cond.supply_pressure_gauge_pa + base.gas.ambient_pressure_pa,
                  cond.load_mass_kg)
        for j in range(tr["t"].size):
            cmd = ctl.step(tr["t"][j], tr["x"][j], tr["p_drive"][j], tr["p_exhaust"][j])
            same_obs = np.array_equal(ctl.observation.view(np.uint32), tr["obs"][j].view(np.uint32))
            out["decisions"] += 1
            out["observations_differing"] += int(not same_obs)
            out["commands_differing"] += int(cmd != tr["command"][j])
            if (not same_obs or cmd != tr["command"][j]) and out["first"] is None:
                diff = np.flatnonzero(ctl.observation != tr["obs"][j])
                out["first"] = {"episode": k, "step": j, "t_s": float(tr["t"][j]),
                                "command": cmd, "environment": int(tr["command"][j]),
                                "elements": [probe.observation_names[d] for d in diff[:5]]}
    return out
