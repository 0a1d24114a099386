"""Running an evaluation: every policy on the same episodes of each suite, all episodes of a
policy stepped as one batch (:func:`run_policy`), and the metrics per suite and per condition
(:func:`summarize`); :func:`evaluate` returns the ``results.json`` structure.
``oracle_fraction = (return - conventional return) / (oracle return - conventional return)`` on
the suite's (or condition's) mean returns."""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from tqdm import tqdm

import pneugym  # noqa: F401  (registers the environment)
from agents import BASELINES
from agents.base import Policy, run_first_episodes
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv
from pneugym.parallel import backend_name, run_tasks
from pneugym.provenance import provenance

from .outputs import outside_reasons
from .specs import check_policy_specs, evaluation_env_config, make_named_policy, parse_spec
from .suites import NOISE, suite_episodes


def run_policy(policy: Policy, conds: Sequence[Conditions], env_config: dict, seed: int
               ) -> dict[str, np.ndarray]:
    """Final figures of one episode per condition, all stepped as one batch."""
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **env_config)
    return run_first_episodes(env, policy, list(conds), seed)


def _mean(v: Sequence[Any]) -> float | None:
    vals = [float(x) for x in v if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(vals)) if vals else None


def oracle_fraction(ret: float, conv: float, oracle: float) -> float | None:
    """``(ret - conv) / (oracle - conv)`` of mean returns (None when the oracle gains nothing)."""
    gap = oracle - conv
    return (ret - conv) / gap if abs(gap) > 1e-12 else None


def summarize(rec: list[dict[str, Any]], conv: float, oracle: float) -> dict[str, Any]:
    """Suite (or condition) metrics of one policy's episode records."""
    ret = _mean([r["objective"] for r in rec])
    return {
        "episodes": len(rec),
        "saving_mean": _mean([r["saving_ratio"] for r in rec]),
        "time_increase_mean": _mean([r["time_increase"] for r in rec]),
        "stall_rate": _mean([r["stalled"] for r in rec]),
        "stick_slip_rate": _mean([r["stick_slip_events"] > 0 for r in rec]),
        "completion_rate": _mean([r["completed"] for r in rec]),
        "return_mean": ret,
        "oracle_fraction": oracle_fraction(ret, conv, oracle),
        "outside_training_rate": _mean([bool(r["outside_training"]) for r in rec
                                        if r.get("outside_training") is not None]),
    }


def outside_training(policy: Policy, c: Conditions) -> str | None:
    """What of episode conditions ``c``'s operating point lies outside the conditions
    ``policy`` was trained on (``""``: nothing; None: the policy records none, a baseline)."""
    space = getattr(policy, "training_space", None)
    if space is None:
        return None
    return "; ".join(space.outside(c.supply_pressure_gauge_pa, c.load_mass_kg))


def _warn_outside(name: str, rec: Sequence[Mapping[str, Any]]) -> None:
    """A :class:`~agents.training.TrainingRangeWarning`: operating points of the points suite
    lie outside what policy ``name`` was trained on."""
    import warnings

    from agents.training.validation import RETRAIN_OVER_RANGE, TrainingRangeWarning

    n = sum(bool(r.get("outside_training")) for r in rec)
    warnings.warn(f"{name}: {n} of the points suite's {len(rec)} episodes lie outside the "
                  f"conditions it was trained on ({'; '.join(outside_reasons(rec))}); there "
                  f"its decisions extrapolate (retrain it over them: pneugym train ... "
                  f"{RETRAIN_OVER_RANGE})", TrainingRangeWarning, stacklevel=3)


def _absolute(spec: str) -> str:
    """``spec`` with its model path made absolute (a worker may run in another folder)."""
    name, path, _ = parse_spec(spec)
    if path is None:
        return spec
    return f"{name}={Path(path).resolve()}{spec[len(name) + 1 + len(path):]}"


def policy_records(spec: str, suite: str, episodes: int, seed: int, env_config: dict,
                   policy: Policy | None = None, probe: CutOffVectorEnv | None = None,
                   eps: list[tuple[str, Conditions]] | None = None,
                   commission: Mapping[str, Any] | None = None,
                   rigs: Sequence[str] | None = None, points: Any = None
                   ) -> tuple[str, list[dict[str, Any]], float]:
    """``(name, per-episode records, wall time [s])`` of one policy on one suite (a task of
    :func:`pneugym.parallel.run_tasks` when evaluation runs in parallel). ``policy``: already
    loaded, else built or loaded from ``spec``; ``probe`` (an environment of ``env_config``)
    and ``eps`` (the suite's episodes): made here unless given; ``commission``: options of the
    commissioning fit of a policy that plans on a model of each rig (``mpc-rig``); ``rigs``:
    for such a policy, only the episodes of these rigs (a task per rig; the records are those
    of a run of the whole suite); ``points``: the ``points`` suite's operating points."""
    probe = probe or CutOffVectorEnv(num_envs=1, **env_config)
    if eps is None:
        eps = suite_episodes(suite, episodes, seed, probe.config.get("rig"),
                             points if suite == "points" else None)
    name = parse_spec(spec)[0]
    if policy is None:
        name, policy = make_named_policy(spec, probe)
    t0 = time.perf_counter()
    sel = list(range(len(eps)))
    if getattr(policy, "commissioned_per_rig", False) and policy.model is None:
        from .commissioning import rig_groups, run_commissioned  # a model of each rig

        policy.commission_options.update(commission or {})
        out = run_commissioned(policy, eps, env_config, seed, probe.rig, run_policy, only=rigs)
        if rigs is not None:
            sel = sorted(i for r in rigs for i in rig_groups(eps)[r])
    elif rigs is not None:
        raise ValueError(f"policy {name!r} is not commissioned per rig: it runs a suite whole")
    else:
        out = run_policy(policy, [c for _, c in eps], env_config, seed)
    wall = time.perf_counter() - t0
    return name, [{"suite": suite, "policy": name, "condition": eps[i][0], "episode": i,
                   **{k: _py(v[k_]) for k, v in out.items()}, **_conditions(*eps[i]),
                   "outside_training": outside_training(policy, eps[i][1])}
                  for k_, i in enumerate(sel)], wall


def gather(keys: Sequence[tuple[str, str, Any]],
           outs: Sequence[tuple[str, list[dict[str, Any]], float]]
           ) -> dict[tuple[str, str], tuple[str, list[dict[str, Any]], float]]:
    """The tasks' results ``outs`` (of :func:`policy_records`, one per ``(suite, spec, rigs)``
    of ``keys``) per ``(suite, spec)``: the records in episode order, the wall time the sum of
    its tasks' (the policy's computing time, not the elapsed time)."""
    done: dict[tuple[str, str], tuple[str, list[dict[str, Any]], float]] = {}
    for (suite, spec, _), (name, rec, w) in zip(keys, outs, strict=True):
        prev = done.get((suite, spec), (name, [], 0.0))
        done[(suite, spec)] = (name, prev[1] + rec, prev[2] + w)
    return {k: (name, sorted(rec, key=lambda r: r["episode"]), w)
            for k, (name, rec, w) in done.items()}


def _per_rig_tasks(spec: str, eps: list[tuple[str, Conditions]]) -> list[list[str] | None]:
    """How a (suite, policy) pair is split into tasks: one per rig for a baseline commissioned
    per rig (``mpc-rig``: each rig's strokes, fit and episodes are independent) on a suite of
    several rigs, else one task (``[None]``: the whole suite in one batch, as the numbers of a
    batch depend on its episodes' shared sensor noise)."""
    from .commissioning import rig_groups

    name, path, _ = parse_spec(spec)
    groups = rig_groups(eps)
    if path is None and getattr(BASELINES.get(name), "commissioned_per_rig", False) \
            and len(groups) > 1:
        return [[r] for r in groups]
    return [None]


def evaluate(policies: Sequence[str], suites: Sequence[str], episodes: int, seed: int,
             env_config: dict | None = None,
             preloaded: Mapping[str, Policy] | None = None, progress: bool = True,
             workers: int = 1, ray_address: str | None = None,
             commission: Mapping[str, Any] | None = None,
             points: Any = None) -> dict[str, Any]:
    """Run every policy on every suite; returns the results.json structure. ``preloaded``:
    policies already loaded (:func:`~agents.evaluation.specs.load_models`), by name;
    ``progress``: a progress bar over the policies of each suite. ``workers`` /
    ``ray_address``: every (suite, policy) pair as a task of :func:`pneugym.parallel.run_tasks`
    (each worker loads its model from the spec's path; the numbers are the same), and every rig
    of a suite a task of its own for a policy commissioned per rig (``mpc-rig``; its wall time
    is then its tasks' sum);
    ``commission``: options of ``mpc-rig``'s commissioning fits (``starts``, ``max_nfev``);
    ``points``: the ``points`` suite's operating points, ``(supply bar g, load kg)`` pairs
    (default the transfer suite's)."""
    from .suites import check_points

    env_config = evaluation_env_config(env_config)
    if points is not None:
        points = check_points(points)
        if "points" not in suites:
            raise ValueError(f"operating points are given, but the suites are {list(suites)}: "
                             f"they are the points suite's")
    check_policy_specs(policies)
    names = list(dict.fromkeys(["conventional", *policies, "oracle"]))  # references always run
    probe = CutOffVectorEnv(num_envs=1, **env_config)
    preloaded = dict(preloaded or {})
    results: dict[str, Any] = {"suites": {}}
    parallel = backend_name(workers, ray_address) != "serial"
    done: dict[tuple[str, str], tuple[str, list[dict[str, Any]], float]] = {}
    suite_eps = {suite: suite_episodes(suite, episodes, seed, probe.config.get("rig"),
                                       points if suite == "points" else None)
                 for suite in suites}
    if parallel:  # a task per (suite, policy) pair, or per rig of a policy commissioned per rig
        keys = [(suite, spec, rigs) for suite in suites for spec in names
                for rigs in _per_rig_tasks(spec, suite_eps[suite])]
        outs = run_tasks(policy_records, [
            {"spec": _absolute(spec), "suite": suite, "episodes": episodes, "seed": seed,
             "env_config": env_config, "commission": dict(commission or {}), "rigs": rigs,
             "points": points}
            for suite, spec, rigs in keys], workers, ray_address,
            progress, desc="evaluation")
        done = gather(keys, outs)
    for suite in suites:
        eps = suite_eps[suite]
        records: dict[str, list[dict[str, Any]]] = {}
        wall: dict[str, float] = {}
        for spec in tqdm(names, desc=f"{suite} suite", unit="policy",
                         disable=not progress or parallel):
            name = parse_spec(spec)[0]
            name, records[name], wall[name] = done.get((suite, spec)) or policy_records(
                spec, suite, episodes, seed, env_config, preloaded.get(name), probe, eps,
                commission)
        conv_ret = _mean([r["objective"] for r in records["conventional"]])
        orc_ret = _mean([r["objective"] for r in records["oracle"]])
        labels = list(dict.fromkeys(label for label, _ in eps))
        pols = {}
        for name, rec in records.items():
            s = summarize(rec, conv_ret, orc_ret)
            s["wall_time_s"] = wall[name]
            s["per_condition"] = {}
            for lab in labels:
                sub = [r for r in rec if r["condition"] == lab]
                cr = _mean([r["objective"] for r in records["conventional"] if r["condition"] == lab])
                orr = _mean([r["objective"] for r in records["oracle"] if r["condition"] == lab])
                s["per_condition"][lab] = summarize(sub, cr, orr)
            if any("/" in lab for lab in labels):  # conditions of several rigs: per rig too
                s["per_rig"] = {}
                for rig in dict.fromkeys(lab.split("/")[0] for lab in labels):
                    def of(recs):
                        return [r for r in recs if r["condition"].split("/")[0] == rig]
                    s["per_rig"][rig] = summarize(
                        of(rec), _mean([r["objective"] for r in of(records["conventional"])]),
                        _mean([r["objective"] for r in of(records["oracle"])]))
            pols[name] = s
            if suite == "points" and s["outside_training_rate"]:
                _warn_outside(name, rec)
        results["suites"][suite] = {"policies": pols, "conditions": labels,
                                    "episodes": [r for rec in records.values() for r in rec]}
        rigs = {lab.split("/")[0]: dict(c.rig_changes) for lab, c in eps if "/" in lab}
        if rigs:
            results["suites"][suite]["rigs"] = rigs
    results["config"] = {"policies": names, "suites": list(suites), "episodes": episodes,
                         "commission": dict(commission or {}),
                         "points": [list(p) for p in points] if points is not None else None,
                         "seed": seed, "env_config": {k: repr(v) if not isinstance(
                             v, (int, float, str, bool, type(None))) else v
                             for k, v in env_config.items() if k != "rig"},
                         "rig": probe.rig.to_dict(),
                         "sensor_noise": NOISE}
    results["seed"] = seed
    prov = provenance()
    results["versions"] = prov.pop("versions")
    results["provenance"] = prov
    return results


def _conditions(label: str, c: Conditions) -> dict[str, Any]:
    """An episode record's conditions: their fields, the rig by name (the suite's ``rigs`` say
    what it changes) instead of the changes themselves."""
    d = c.to_dict()
    if d.pop("rig_changes") or "/" in label:
        d["rig"] = label.split("/")[0]
    return d


def _py(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return v
