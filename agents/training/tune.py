"""Hyperparameter search with Ray Tune and Optuna (:func:`tune_hyperparameters`,
``pneugym train --algo ppo --tune SPACE.yaml --trials 20``), as RL Baselines3 Zoo does with
Optuna: each trial is one training run (``--set`` overrides drawn from the space) scored on the
validation conditions; the held-out figures come later from ``pneugym evaluate``.

The search space is a YAML (or JSON) mapping from configuration keys to one distribution each::

    algo.learning_rate: {loguniform: [1.0e-5, 1.0e-3]}
    algo.gamma: {uniform: [0.9, 0.999]}
    env.history: {choice: [4, 8, 12]}
    algo.n_epochs: {randint: [3, 11]}      # upper bound excluded

Optuna's TPE sampler is seeded with ``--seed``; with one trial at a time the search is
reproducible, with several at once the order trials finish in steers the next suggestions.
Needs ``pip install "pneugym[ray]"``.
"""
from __future__ import annotations

import json

import math
import time
from pathlib import Path
from typing import Any, Mapping

from .rundir import atomic_write_json
from .sweep import portable, recorded_options

TUNE_FILE = "tune.json"
METRIC = "validation_return"
_DISTS = {"uniform": 2, "loguniform": 2, "randint": 2, "choice": None}


def _number(path, key: str, kind: str, v: Any, integer: bool = False) -> float | int:
    """A bound of ``kind`` as a number (YAML reads ``1e-5`` as a string)."""
    try:
        x = float(v) if not isinstance(v, bool) else float("nan")
    except (TypeError, ValueError):
        x = float("nan")
    if not math.isfinite(x) or (integer and x != int(x)):
        raise ValueError(f"--tune {path}: {key}: {kind} takes {'integers' if integer else 'numbers'}"
                         f", got {v!r}")
    return int(x) if integer else x


def load_space(path: str | Path) -> dict[str, dict[str, Any]]:
    """The search space of ``path`` (see the module docstring), checked: bounds are numbers
    (``randint``: integers, ``loguniform``: above 0) with low < high."""
    import yaml

    try:
        with open(path) as f:
            space = yaml.safe_load(f)
    except OSError as exc:
        raise ValueError(f"--tune {path}: cannot read it ({exc.strerror})") from None
    if not isinstance(space, Mapping) or not space:
        raise ValueError(f"--tune {path}: expected a mapping of config keys to distributions")
    out = {}
    for key, dist in space.items():
        if not (isinstance(dist, Mapping) and len(dist) == 1 and next(iter(dist)) in _DISTS):
            raise ValueError(f"--tune {path}: {key}: expected one of {sorted(_DISTS)} with its "
                             f"arguments, e.g. {{loguniform: [1.0e-5, 1.0e-3]}}; got {dist!r}")
        (kind, args), = dist.items()
        n = _DISTS[kind]
        if not isinstance(args, list) or (n is not None and len(args) != n) or not args:
            raise ValueError(f"--tune {path}: {key}: {kind} takes a list of "
                             f"{n or 'one or more'} values, got {args!r}")
        if n is not None:
            args = [_number(path, key, kind, v, kind == "randint") for v in args]
            if not args[0] < args[1] or (kind == "loguniform" and args[0] <= 0):
                raise ValueError(f"--tune {path}: {key}: {kind} needs "
                                 f"{'0 < ' if kind == 'loguniform' else ''}low < high, got {args!r}")
        out[str(key)] = {kind: args}
    return out


def _ray_space(space: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    from ray import tune

    make = {"uniform": tune.uniform, "loguniform": tune.loguniform, "randint": tune.randint}
    out = {}
    for key, dist in space.items():
        (kind, args), = dist.items()
        out[key] = tune.choice(list(args)) if kind == "choice" else make[kind](*args)
    return out


def _overrides(values: Mapping[str, Any]) -> list[str]:
    """A trial's values as ``--set`` items, each value as JSON (a YAML ``--set`` reads it back
    as it was: ``null`` for None, a quoted text for a string)."""
    return [f"{k}={json.dumps(v)}" for k, v in values.items()]


def _trial(config: dict[str, Any], algo: str, root: str, seed: int,
           train_kw: dict[str, Any]) -> None:
    """One trial: a training run in ``<root>/trials/<trial id>``, its validation figures
    reported to Tune."""
    from ray import tune

    from .trainer import command_line, train

    trial = tune.get_context().get_trial_id()
    kw = dict(train_kw, overrides=[*train_kw.get("overrides", ()), *_overrides(config)],
              progress=False)
    out = Path(root) / "trials" / trial
    run = train(algo, out, seed=seed, command=command_line(algo, out, seed, kw), **kw)
    best = run.get("best", {})
    ret = best.get("return")
    tune.report({METRIC: float(ret) if ret is not None else None,
                 "oracle_fraction": best.get("oracle_fraction"),
                 "stall_rate": best.get("stall_rate"), "wall_s": run.get("total_wall_s")})


def tune_hyperparameters(algo: str, out: str | Path, space_file: str | Path, trials: int,
                         seed: int = 0, workers: int = 1, ray_address: str | None = None,
                         **train_kw: Any) -> dict[str, Any]:
    """Search ``space_file`` with ``trials`` training runs of ``algo`` (``workers`` at a time),
    maximising the validation return; writes ``<out>/tune.json`` (every trial, the best
    overrides, configuration and versions) and returns it."""
    from pneugym.outputs import check_output_dir
    from pneugym.parallel import check_workers, ray_init
    from pneugym.provenance import provenance

    from .config import load_config

    space = load_space(space_file)
    check_workers(workers)
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"--trials must be a positive integer, got {trials!r}")
    for key, dist in space.items():  # every key with every choice and bound, before Ray starts
        (_, args), = dist.items()
        for v in args:
            load_config(algo, train_kw.get("budget", "default"), train_kw.get("config"),
                        [*train_kw.get("overrides", ()), *_overrides({key: v})],
                        preset=train_kw.get("preset"), timesteps=train_kw.get("timesteps"),
                        seed=seed, rig=train_kw.get("rig"))
    train_kw = portable(algo, train_kw, [seed])  # Tune runs each trial in a folder of its own
    try:
        from ray import tune
        from ray.tune.search.optuna import OptunaSearch
    except ImportError:
        raise ValueError('--tune needs Ray Tune and Optuna: pip install "pneugym[ray]"') from None
    out = check_output_dir(str(out), "tuning folder (--out)").resolve()
    ray_init(ray_address or "local", workers)
    t0 = time.perf_counter()
    trainable = tune.with_parameters(_trial, algo=algo, root=str(out), seed=seed,
                                     train_kw=dict(train_kw))
    tuner = tune.Tuner(
        tune.with_resources(trainable, {"cpu": 1}), param_space=_ray_space(space),
        tune_config=tune.TuneConfig(
            search_alg=OptunaSearch(metric=METRIC, mode="max", seed=seed),
            num_samples=trials, max_concurrent_trials=workers),
        run_config=tune.RunConfig(storage_path=str(out / "ray_results"), name="tune",
                                  verbose=0))
    grid = tuner.fit()
    rows, failed = [], []
    for res in grid:
        if res.error is not None:
            failed.append({"overrides": _overrides(res.config), "error": str(res.error)})
            continue
        m = res.metrics
        rows.append({"trial": m["trial_id"], "overrides": _overrides(res.config),
                     **{k: m.get(k) for k in (METRIC, "oracle_fraction", "stall_rate",
                                              "wall_s")}})
    rows.sort(key=lambda r: -math.inf if r[METRIC] is None else r[METRIC], reverse=True)
    result = {"algo": algo, "space": space, "trials": trials, "seed": seed, "workers": workers,
              "ray_address": ray_address, "metric": METRIC, "wall_s": time.perf_counter() - t0,
              "best": rows[0] if rows else None, "results": rows, "failed": failed,
              "train_options": recorded_options(train_kw),
              "provenance": provenance()}
    atomic_write_json(out / TUNE_FILE, result)
    if failed:
        raise RuntimeError(f"{len(failed)} of {trials} tuning trials failed (recorded in "
                           f"{out / TUNE_FILE}); the first: {failed[0]['error']}")
    return result
