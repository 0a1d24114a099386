"""Embarrassingly parallel work (training seeds, sweep trials, benchmark cases) on one machine or
on a Ray cluster, with one function: :func:`run_tasks`.

- ``workers=1`` and no address: in this process, one task after the other.
- ``workers=N``: ``N`` local processes (``concurrent.futures``, started by ``spawn`` so that no
  worker inherits numba's or torch's threads half-way).
- ``ray_address``: Ray tasks (``pip install "pneugym[ray]"``): ``"local"`` starts a Ray runtime in
  this process with ``workers`` CPUs, ``"auto"`` or ``"HOST:PORT"`` joins a running cluster
  (``ray start --head`` on one machine, ``ray start --address HOST:PORT`` on the others; every
  node needs pneugym installed).

A task is a picklable, module-level function and its keyword arguments; it must set its own seeds
and threads, so the same task gives the same numbers wherever it runs. Results come back in the
order of the tasks.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

from tqdm.auto import tqdm


def add_arguments(ap: argparse.ArgumentParser | argparse._ArgumentGroup, tasks: str) -> None:
    """``--workers`` and ``--ray-address`` of a command line whose ``tasks`` run in parallel."""
    ap.add_argument("--workers", type=int, default=1,
                    help=f"local processes for {tasks} (default 1: one after the other; the "
                         "numbers are the same)")
    ap.add_argument("--ray-address", default=None, metavar="ADDR",
                    help=f"run {tasks} as Ray tasks: local (a Ray runtime here with --workers "
                         "CPUs), auto or HOST:PORT (a running cluster; files must be readable "
                         "on every node); needs pneugym[ray]")


def backend_name(workers: int = 1, ray_address: str | None = None) -> str:
    """``"serial"``, ``"processes"`` or ``"ray"``: where :func:`run_tasks` runs with these."""
    check_workers(workers)
    if ray_address is not None:
        return "ray"
    return "processes" if workers > 1 else "serial"


def check_workers(workers: int) -> int:
    """``workers`` as a positive int, else a ValueError that names it."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    return workers


def run_tasks(fn: Callable[..., Any], tasks: Sequence[Mapping[str, Any]], workers: int = 1,
              ray_address: str | None = None, progress: bool = True, desc: str = "tasks",
              num_cpus: float = 1.0, pythonpath: Sequence[str] = ()) -> list[Any]:
    """``[fn(**t) for t in tasks]``, run as the module docstring says; results in task order.

    ``num_cpus``: CPUs Ray reserves per task (one by default: tasks pin their own threads);
    ``pythonpath``: folders Ray workers import from besides the installed packages (e.g. the
    folder of a script whose functions are the tasks; on a cluster it must exist on every node).
    The first failing task's exception is raised once it is seen: queued tasks are cancelled
    (Ray cancels the running ones too; a local process finishes the task it is running)."""
    backend = backend_name(workers, ray_address)
    tasks = [dict(t) for t in tasks]
    bar = tqdm(total=len(tasks), desc=desc, disable=not progress)
    try:
        if backend == "serial":
            out = []
            for t in tasks:
                out.append(fn(**t))
                bar.update()
            return out
        if backend == "processes":
            return _processes(fn, tasks, workers, bar)
        return _ray(fn, tasks, workers, ray_address, bar, num_cpus, pythonpath)
    finally:
        bar.close()


def _call(fn: Callable[..., Any], kwargs: Mapping[str, Any]) -> Any:
    return fn(**kwargs)


def _processes(fn, tasks, workers, bar) -> list[Any]:
    out: list[Any] = [None] * len(tasks)
    ctx = multiprocessing.get_context("spawn")
    ex = ProcessPoolExecutor(min(workers, max(1, len(tasks))), mp_context=ctx)
    try:
        futures = {ex.submit(_call, fn, t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futures):
            out[futures[fut]] = fut.result()
            bar.update()
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
    return out


def ray_problem(ray_address: str | None) -> str | None:
    """Why ``--ray-address`` cannot be used here (Ray not installed), for the command lines to
    refuse before any work; None if it can (or is not given)."""
    import importlib.util

    if ray_address is not None and importlib.util.find_spec("ray") is None:
        return '--ray-address needs Ray: pip install -e ".[ray]"'
    return None


def ray_init(ray_address: str, workers: int = 1, pythonpath: Sequence[str] = ()) -> None:
    """Connect to Ray (``"local"``: start one here with ``workers`` CPUs), once per process;
    ``pythonpath`` as in :func:`run_tasks`."""
    try:
        import ray
    except ImportError:
        raise ValueError('--ray-address needs Ray: pip install "pneugym[ray]"') from None
    if ray.is_initialized():
        return
    kw: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False,
                              configure_logging=False)
    if pythonpath:
        path = [*pythonpath, *filter(None, [os.environ.get("PYTHONPATH")])]
        kw["runtime_env"] = {"env_vars": {"PYTHONPATH": os.pathsep.join(path)}}
    if ray_address == "local":  # a new runtime, even where `ray start` left one running
        ray.init(address="local", num_cpus=workers, **kw)
    else:
        ray.init(address=ray_address, **kw)


def _ray(fn, tasks, workers, ray_address, bar, num_cpus, pythonpath) -> list[Any]:
    ray_init(ray_address, workers, pythonpath)  # (refuses a missing Ray with a ValueError)
    import ray

    remote = ray.remote(num_cpus=num_cpus, max_retries=0)(_call)
    refs = [remote.remote(fn, t) for t in tasks]
    index = {ref: i for i, ref in enumerate(refs)}
    out: list[Any] = [None] * len(tasks)
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                out[index[ref]] = ray.get(ref)
                bar.update()
    finally:
        for ref in pending:  # after a failure (or Ctrl-C): nothing keeps running on the cluster
            ray.cancel(ref, force=True)
    return out
