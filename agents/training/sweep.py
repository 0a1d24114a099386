"""Many training runs at once: one algorithm over several seeds (:func:`train_seeds`,
``pneugym train --seeds 0-4``), on local processes or a Ray cluster (:mod:`pneugym.parallel`).

Each seed trains into ``<out>/seed_<s>`` exactly as ``pneugym train --seed s`` would (the
trainer pins numba and torch to their configured threads, so a seed gives the same numbers
wherever it runs); ``<out>/sweep.json`` gathers every run's validation figures with their mean
and spread, the configuration and the versions.
"""
from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .rundir import atomic_write_json
from .seeds import check_seed

SWEEP_FILE = "sweep.json"


def parse_seeds(text: str) -> list[int]:
    """``"0-4"`` -> [0, 1, 2, 3, 4]; ``"0,3,7"`` and ``"0-2,10"`` too. Each a training seed."""
    seeds: list[int] = []
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m or (m.group(2) is not None and int(m.group(2)) < int(m.group(1))):
            raise ValueError(f"--seeds {text!r}: expected seeds like 0-4 or 0,3,7")
        lo = int(m.group(1))
        seeds.extend(range(lo, int(m.group(2) or lo) + 1))
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds {text!r}: a seed is given twice")
    for s in seeds:
        check_seed("training", s)
    return seeds


def portable(algo: str, train_kw: dict[str, Any], seeds: Sequence[int]) -> dict[str, Any]:
    """``train_kw`` checked for every seed (the whole configuration, as ``train`` checks it),
    with every path made absolute (``config``, a rig file, the cache folder): a Ray worker runs
    in another folder than this process."""
    from .config import DEFAULT_CACHE_DIR, load_config

    kw = dict(train_kw)
    cfg: dict[str, Any] = {}
    for s in seeds:
        cfg = load_config(algo, kw.get("budget", "default"), kw.get("config"),
                          kw.get("overrides", ()), preset=kw.get("preset"),
                          timesteps=kw.get("timesteps"), seed=s, rig=kw.get("rig"))
    if kw.get("config") is not None:
        kw["config"] = str(Path(kw["config"]).resolve())
    if isinstance(kw.get("rig"), (str, Path)):
        kw["rig"] = str(Path(kw["rig"]).resolve())
    cache = Path(cfg.get("cache_dir", DEFAULT_CACHE_DIR)).resolve()
    kw["overrides"] = [*kw.get("overrides", ()), f"cache_dir={cache}"]
    return kw


def recorded_options(train_kw: dict[str, Any]) -> dict[str, Any]:
    """``train_kw`` as a results file records it (paths as text; the rig is in the config)."""
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in train_kw.items() if k != "rig"}


def _one_seed(algo: str, out: str, seed: int, train_kw: dict[str, Any]) -> dict[str, Any]:
    """Train one seed (a task of :func:`pneugym.parallel.run_tasks`); its ``run.json`` content."""
    from .trainer import command_line, train

    return train(algo, out, seed=seed, command=command_line(algo, out, seed, train_kw), **train_kw)


def _figures(run: dict[str, Any]) -> dict[str, Any]:
    best = run.get("best", {})
    return {"seed": run["seed"], "status": run.get("status"),
            "validation_return": best.get("return"),
            "oracle_fraction": best.get("oracle_fraction"),
            "stall_rate": best.get("stall_rate"), "wall_s": run.get("total_wall_s")}


def _spread(values: Sequence[float | None]) -> dict[str, float] | None:
    v = np.array([x for x in values if x is not None], dtype=float)
    if not v.size:
        return None
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max())}


def train_seeds(algo: str, out: str | Path, seeds: Sequence[int], workers: int = 1,
                ray_address: str | None = None, progress: bool = True,
                **train_kw: Any) -> dict[str, Any]:
    """Train ``algo`` once per seed into ``<out>/seed_<s>``; returns (and writes to
    ``<out>/sweep.json``) the per-seed validation figures and their spread.

    ``train_kw`` as :func:`~agents.training.trainer.train` takes them (budget, overrides, rig,
    ...); ``workers`` / ``ray_address`` as :func:`pneugym.parallel.run_tasks`. Per-run progress
    bars are off when runs go in parallel (one bar counts finished runs)."""
    from pneugym.outputs import check_output_dir
    from pneugym.parallel import backend_name, run_tasks
    from pneugym.provenance import provenance

    backend = backend_name(workers, ray_address)
    if not seeds:
        raise ValueError("--seeds: no seed given")
    kw = portable(algo, train_kw, seeds)  # checked before any run starts
    kw["progress"] = progress and backend == "serial"
    check_output_dir(str(out), "sweep folder (--out)")
    out = Path(out)
    for s in seeds:
        d = out / f"seed_{s}"
        if d.exists() and (not d.is_dir() or any(d.iterdir())):
            raise ValueError(f"{d} is not empty: give a new --out (a sweep starts new runs)")
    tasks = [{"algo": algo, "out": str((out / f"seed_{s}").resolve()), "seed": int(s),
              "train_kw": kw} for s in seeds]
    t0 = time.perf_counter()
    runs = run_tasks(_one_seed, tasks, workers, ray_address, progress=progress,
                     desc=f"{algo} seeds")
    rows = [_figures(r) for r in runs]
    sweep = {"algo": algo, "seeds": [int(s) for s in seeds], "backend": backend,
             "workers": workers, "ray_address": ray_address, "wall_s": time.perf_counter() - t0,
             "runs": {f"seed_{r['seed']}": row for r, row in zip(runs, rows)},
             "summary": {k: _spread([row[k] for row in rows])
                         for k in ("validation_return", "oracle_fraction", "wall_s")},
             "config": runs[0]["config"] | {"seed": None},
             "train_options": recorded_options(train_kw),
             "provenance": provenance()}
    atomic_write_json(out / SWEEP_FILE, sweep)
    return sweep
