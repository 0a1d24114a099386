"""Validation during training: fixed conditions drawn from the training preset
(:func:`validation_conditions`), the conventional and oracle returns on them
(:func:`validation_references`, cached) and the :func:`oracle_fraction`; whether a rig's own
operating point lies inside the training conditions (:func:`operating_point_outside`); a
model's decision rule swept over its grid in one batched run (:func:`sweep_decisions`) and the
row to act by (:func:`choose_decision`)."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .rundir import atomic_write_json


def validation_conditions(preset: str, n: int, seed: int, rig: Any = None,
                          conditions: Mapping[str, Any] | None = None) -> list:
    """``n`` fixed conditions drawn from ``preset`` (each from ``default_rng([seed, i])``) with
    the training's ``conditions`` overrides (``env.conditions``, the ranges trained on); ``rig``
    (a rig file, mapping or RigParams) gives the operating point of the ``"rig"`` preset."""
    from pneugym.envs.conditions import resolve
    from pneugym.rigfile import as_rig

    rig = as_rig(rig)
    space = resolve(preset, conditions, rig=rig)
    return [space.sample(np.random.default_rng([seed, i]), rig) for i in range(n)]


class TrainingRangeWarning(UserWarning):
    """The rig's own operating point (its supply and load) lies outside the conditions a run
    trains on."""


#: what a :class:`TrainingRangeWarning` tells to do: train over the range the rig runs at
RETRAIN_OVER_RANGE = ("--set 'env.conditions.supply_pressure_gauge_pa=[LOW, HIGH]' --set "
                      "'env.conditions.load_mass_kg=[LOW, HIGH]' (SI units)")


def operating_point_outside(preset: str, rig: Any = None,
                            conditions: Mapping[str, Any] | None = None) -> str | None:
    """What of ``rig``'s own operating point (supply set-point, load) lies outside the ranges
    ``preset`` with the ``conditions`` overrides draws (``None`` if nothing does), e.g.
    ``"supply 6 bar g outside 1.5-5"``."""
    from pneugym.envs.conditions import resolve
    from pneugym.rigfile import as_rig

    rig = as_rig(rig)
    space = resolve(preset, conditions, rig=rig)
    out = space.outside(rig.supply_pressure_gauge_pa, rig.load_mass_kg)
    return "; ".join(out) or None


def validation_references(conds: Sequence[Any], env_config: Mapping[str, Any], seed: int,
                          cache_dir: Path | None) -> dict[str, float]:
    """Mean returns of the conventional scheme and the (privileged) oracle on the validation
    conditions, for the oracle fraction in the logs; cached on disk."""
    from agents import esac

    options = sorted((k, repr(v)) for k, v in env_config.items() if k != "history")
    key = hashlib.sha256(json.dumps([[c.to_dict() for c in conds], options, seed,
                                     esac.source_hash()], sort_keys=True).encode()).hexdigest()[:16]
    path = cache_dir / f"validation-references-{key}.json" if cache_dir else None
    if path is not None and path.is_file():
        return json.loads(path.read_text())
    from agents import ConventionalPolicy, OraclePolicy
    from agents.base import run_first_episodes
    from pneugym.envs.cutoff import CutOffVectorEnv

    cfg = {k: v for k, v in env_config.items() if k not in ("preset", "conditions")}
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **cfg)
    refs = {}
    for name, pol in (("conventional", ConventionalPolicy.for_env(env)),
                      ("oracle", OraclePolicy.for_env(env))):
        refs[name] = float(np.mean(run_first_episodes(env, pol, conds, seed)["objective"]))
    if path is not None:
        atomic_write_json(path, refs)
    return refs


def oracle_fraction(ret: float, refs: Mapping[str, float]) -> float | None:
    """``(ret - conventional) / (oracle - conventional)`` on the references ``refs``
    (:func:`validation_references`); None when the two references coincide."""
    gap = refs["oracle"] - refs["conventional"]
    return (ret - refs["conventional"]) / gap if abs(gap) > 1e-12 else None


def sweep_decisions(model, layout: Mapping[str, Any], conds: Sequence[Any],
                    env_cfg: Mapping[str, Any], seed: int, rule: str, grid: Sequence[float]
                    ) -> list[dict[str, Any]]:
    """Mean return and stall rate of ``model`` on ``conds`` under each value of its decision
    ``rule`` (:class:`agents.learned.SB3Policy`), all in one batched run."""
    from agents.base import run_first_episodes
    from agents.learned import SB3Policy
    from pneugym.envs.cutoff import CutOffVectorEnv

    n = len(conds)
    env = CutOffVectorEnv(num_envs=n * len(grid), autoreset=False, **env_cfg)
    pol = SB3Policy(env.observation_layout(), model, layout,
                    decision={"rule": rule, "value": np.repeat(np.asarray(grid, float), n)})
    out = run_first_episodes(env, pol, list(conds) * len(grid), seed)
    return [{"rule": rule, "value": float(v),
             "return": float(np.mean(out["objective"][k * n:(k + 1) * n])),
             "stall_rate": float(np.mean(out["stalled"][k * n:(k + 1) * n])),
             "saving": float(np.mean(out["saving_ratio"][k * n:(k + 1) * n]))}
            for k, v in enumerate(grid)]


def decision_grids(decision: Mapping[str, Any]) -> dict[str, list[float]]:
    """The decision rules to tune and their grids: ``decision["rules"]`` (``{rule: grid}``), or
    the single ``decision["rule"]`` over ``decision["grid"]``."""
    if decision.get("rules"):
        return {str(k): [float(x) for x in v] for k, v in decision["rules"].items()}
    return {str(decision["rule"]): [float(x) for x in decision.get("grid", [0.5])]}


def choose_decision(rows: Sequence[Mapping[str, Any]], prefer_saving_within: float = 0.0,
                    max_stall_rate: float = math.inf) -> dict[str, Any]:
    """The validation row (``return``, ``saving``, ``stall_rate``) to act by: among the rows that
    stall at most ``max_stall_rate`` (all, if none does), the best mean return; or, with
    ``prefer_saving_within > 0``, the row that saves most among those within that much of the
    best return and stalling no more often. The objective is flat near its optimum and its
    near-ties are noise; the saving is the thesis's aim."""
    if not rows:
        raise ValueError("no validation rows to choose from")
    if prefer_saving_within < 0:
        raise ValueError(f"prefer_saving_within = {prefer_saving_within} must be >= 0")
    ok = [r for r in rows if r["stall_rate"] <= max_stall_rate] or list(rows)
    top = max(ok, key=lambda r: r["return"])
    if prefer_saving_within <= 0:
        return dict(top)
    near = [r for r in ok if r["return"] >= top["return"] - prefer_saving_within
            and r["stall_rate"] <= top["stall_rate"]]
    return dict(max(near, key=lambda r: (r.get("saving", 0.0), r["return"])))
