"""ESAC's controller (thesis 6.8): :class:`ESACPolicy` cuts off the supply at the first
instant the predictor says the stroke completes with the margin, within the time demand, and
that waiting longer no longer pays; :func:`load_policy` builds it from a model file and
:func:`sweep_rule` scores rules on conditions (train.py tunes the rule with it).
"""
from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ..base import run_first_episodes
from ..learned import LearnedPolicy
from .model import ESACPredictor
from .modelfile import load
from .rule import RULE_DEFAULTS, RULE_PARAMETERS, check_rule


class ESACPolicy(LearnedPolicy):
    """The ESAC controller (thesis 6.8): cut off at the first instant the predictor says

    1. the stroke completes with the safety ``margin``: predicted risk of an incomplete stroke at
       most ``margin``, predicted final position within ``tolerance_m`` of the stroke end;
    2. within the time demand: predicted stroke time at most ``1 + max_time_increase`` times the
       predicted conventional one (or at most ``time_demand_s`` seconds if given);
    3. with a predicted stick-slip risk of at most ``max_stick``;
    4. and, with ``lookahead`` (a model with ``delay_input``), that waiting no longer pays: no cut
       ``Δ`` later (``Δ`` in the predictor's ``lookahead_s``) has a predicted objective
       (:meth:`objective`) more than ``hysteresis`` above that of cutting now. The time demand
       is then a bound, and the trade-off inside it is the objective's (``w_time``,
       ``w_stick``, ``w_stall``).

    Without ``lookahead`` (the thesis's rule) it cuts as soon as 1-3 hold, i.e. as late as the
    time demand allows. Every parameter may be an array with one value per observation row
    (sweeps). ``last_prediction`` holds the predictions (cut now) of the last call.
    """

    name = "esac"

    def __init__(self, env_layout: Mapping[str, Any], predictor: ESACPredictor,
                 margin: float | np.ndarray = RULE_DEFAULTS["margin"],
                 max_time_increase: float | np.ndarray = RULE_DEFAULTS["max_time_increase"],
                 max_stick: float | np.ndarray = RULE_DEFAULTS["max_stick"],
                 tolerance_m: float | np.ndarray = RULE_DEFAULTS["tolerance_m"],
                 lookahead: int | np.ndarray = RULE_DEFAULTS["lookahead"],
                 w_time: float | np.ndarray = RULE_DEFAULTS["w_time"],
                 w_stick: float | np.ndarray = RULE_DEFAULTS["w_stick"],
                 w_stall: float | np.ndarray = RULE_DEFAULTS["w_stall"],
                 hysteresis: float | np.ndarray = RULE_DEFAULTS["hysteresis"],
                 time_demand_s: float | np.ndarray | None = None, source: str = "the ESAC model"):
        super().__init__(env_layout, predictor.layout, source)
        self.predictor = predictor
        rule = check_rule({"margin": margin, "max_time_increase": max_time_increase,
                           "max_stick": max_stick, "tolerance_m": tolerance_m,
                           "lookahead": lookahead, "w_time": w_time, "w_stick": w_stick,
                           "w_stall": w_stall, "hysteresis": hysteresis,
                           "time_demand_s": time_demand_s}, f"{source}: rule", per_row=True)
        margin, lookahead = rule["margin"], rule["lookahead"]
        self.margin = np.asarray(margin, dtype=float)
        self.max_time_increase = np.asarray(max_time_increase, dtype=float)
        self.max_stick = np.asarray(max_stick, dtype=float)
        self.tolerance_m = np.asarray(tolerance_m, dtype=float)
        self.lookahead = np.asarray(lookahead).astype(np.int64)
        self.w_time = np.asarray(w_time, dtype=float)
        self.w_stick = np.asarray(w_stick, dtype=float)
        self.w_stall = np.asarray(w_stall, dtype=float)
        self.hysteresis = np.asarray(hysteresis, dtype=float)
        self.time_demand_s = None if time_demand_s is None else np.asarray(time_demand_s, float)
        if np.any(self.lookahead != 0) and predictor.lookahead_s.size == 0:
            raise ValueError(f"{source} predicts a cut now only: lookahead needs a model "
                             f"trained with delay_input (train.py, esac fit.delay_input)")
        names = [f["name"] for f in predictor.layout["features"]]
        h = int(predictor.layout["history"])
        self._cut_index = (h - 1) * len(names) + names.index("supply_cut")
        self.last_prediction: dict[str, np.ndarray] | None = None

    def rule(self) -> dict[str, Any]:
        """The controller's parameters (the safety ``margin`` among them)."""
        out = {k: getattr(self, k).tolist() for k in RULE_DEFAULTS}
        if self.time_demand_s is not None:
            out["time_demand_s"] = self.time_demand_s.tolist()
        return out

    def _col(self, v: np.ndarray, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """A per-row parameter shaped to broadcast against predictions ``p`` (B,) or (B, D)."""
        ref = p["p_complete"]
        return v.reshape(v.shape + (1,) * (ref.ndim - v.ndim)) if v.ndim == 1 else v

    def objective(self, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """The predicted objective of the cut ``p`` describes: the env's ``-wasted_fraction -
        w_time * time_increase - w_stick * stick-slip``, with the stall risk at ``w_stall``."""
        c = functools.partial(self._col, p=p)
        return (-p["wasted_fraction"] - c(self.w_time) * np.maximum(p["time_increase"], 0.0)
                - c(self.w_stick) * p["p_stick"] - c(self.w_stall) * (1.0 - p["p_complete"]))

    def safe(self, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """Rule 1: the stroke completes with the margin."""
        c = functools.partial(self._col, p=p)
        return ((p["p_complete"] >= 1.0 - c(self.margin))
                & (p["final_position_m"] >= self.predictor.stroke_m - c(self.tolerance_m)))

    def decide(self, p: Mapping[str, np.ndarray], later: Mapping[str, np.ndarray] | None = None
               ) -> np.ndarray:
        """The cut decision for predictions ``p`` of a cut now and, for rule 4, ``later`` ones
        (B, D) of cuts after the lookahead delays."""
        ok = self.safe(p)
        if self.time_demand_s is not None:
            ok &= p["stroke_time_s"] <= self.time_demand_s
        else:
            ok &= p["time_increase"] <= self.max_time_increase
        ok &= p["p_stick"] <= self.max_stick
        if later is not None:
            j_later = np.where(self.safe(later), self.objective(later), -np.inf).max(axis=1)
            waiting_pays = j_later > self.objective(p) + self.hysteresis
            ok &= ~((np.broadcast_to(self.lookahead, ok.shape) != 0) & waiting_pays)
        return ok

    def act_model(self, obs: np.ndarray) -> np.ndarray:
        p = self.predictor(obs)
        self.last_prediction = p
        later = None
        if np.any(self.lookahead != 0):
            later = self.predictor(obs, self.predictor.lookahead_s)
        already = obs[:, self._cut_index] > 0.5
        return (self.decide(p, later) | already).astype(np.int64)



def load_policy(path: str | Path, env_layout: Mapping[str, Any], **rule: Any) -> ESACPolicy:
    """The ESAC controller saved at ``path`` for an environment of ``env_layout``, with the saved
    (tuned) rule unless overridden by ``rule``."""
    from pneugym.params import did_you_mean

    unknown = sorted(set(rule) - set(RULE_PARAMETERS))
    if unknown:
        raise ValueError(f"unknown ESAC rule parameter(s) {unknown}"
                         f"{did_you_mean(unknown[0], RULE_PARAMETERS)}; choose from "
                         f"{list(RULE_PARAMETERS)}")
    rule = check_rule(rule, f"ESAC model {path}: the rule override")
    pred, meta = load(path)
    params = {**RULE_DEFAULTS, **meta.get("rule", {}), **rule}
    pol = ESACPolicy(env_layout, pred, source=f"ESAC model {path}", **params)
    pol.trained_rig = meta.get("rig")  # a RigParams dict; None: the thesis rig
    pol.trained_preset = (meta.get("data") or {}).get("preset")
    pol.trained_conditions = (meta.get("data") or {}).get("conditions")  # env.conditions
    return pol



def sweep_rule(predictor: ESACPredictor, conditions: Sequence[Any], grid: Iterable[Mapping],
               env_config: Mapping[str, Any] | None = None, seed: int = 0
               ) -> list[dict[str, Any]]:
    """Mean return of the controller for each rule in ``grid`` on ``conditions`` (one batched
    run of ``len(grid) * len(conditions)`` episodes)."""
    from pneugym.envs.cutoff import CutOffVectorEnv

    grid = list(grid)
    nc = len(conditions)
    cfg = {**dict(env_config or {}), "history": int(predictor.layout["history"])}
    env = CutOffVectorEnv(num_envs=nc * len(grid), autoreset=False, **cfg)
    arrays = {k: np.repeat([g.get(k, RULE_DEFAULTS[k]) for g in grid], nc)
              for k in RULE_DEFAULTS}
    pol = ESACPolicy(env.observation_layout(), predictor, **arrays)
    out = run_first_episodes(env, pol, list(conditions) * len(grid), seed)
    res = []
    for k, g in enumerate(grid):
        s = slice(k * nc, (k + 1) * nc)
        res.append({**{kk: float(v) for kk, v in g.items()},
                    "return": float(np.mean(out["objective"][s])),
                    "stall_rate": float(np.mean(out["stalled"][s])),
                    "saving": float(np.mean(out["saving_ratio"][s]))})
    return res

