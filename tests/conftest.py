"""Shared fixtures for the pneugym test-suite.

The numba kernels are compiled once per machine (``cache=True``); a cold run of the whole suite
first compiles them (about a minute for the plant and its batch; each ``pytest -n`` worker
compiles what it needs before the cache has it). The plant runs below are cheap (a few ms each
once compiled), so the session fixtures only exist to avoid repeating the same runs in many tests.

Nothing here hard-codes calibrated defaults (areas, lengths, dead volumes): tests compare relations
and physics, so they keep holding after a re-calibration of the default rig.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import settings

from pneugym import Plant, RigParams, Trajectory

# Property tests draw the same examples on every run ("ci", the default), so that CI is never
# red by the luck of a draw; HYPOTHESIS_PROFILE=explore draws new ones each run (with, e.g.,
# PNEUGYM_PROPERTY_EXAMPLES=1000 for the plant's random-rig test) to search for new failures.
settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

#: Simulated time [s] for runs that should reach the end of stroke. The thesis's conventional
#: stroke takes ~1.2-1.3 s and a predicted cut-off ~1.4-1.7 s; 5 s leaves ample margin for any
#: calibration while staying cheap (~20k substeps).
T_MAX = 5.0


@dataclass
class Run:
    """A finished plant run: the plant (read its state, do not advance it) and its trajectory."""

    plant: Plant
    traj: Trajectory

    @property
    def params(self) -> RigParams:
        return self.plant.params


DOCS = "tests/test_docs.py"

#: Under ``pytest -n N`` (N > 1) the workers already keep the cores busy: each worker, and every
#: command a docs test starts (:data:`ONE_THREAD`), runs numba and torch on one thread, as
#: anything beside other work should (docs/scale.md: a descheduled thread stalls its team at
#: every step, and a spinning one takes the other worker's core). The tests of the threaded path
#: set their threads themselves. Results do not depend on the thread count (tested).
SHARED_CORES = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1
ONE_THREAD = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "OPENBLAS_NUM_THREADS": "1"} if SHARED_CORES else {}


def pytest_configure(config: pytest.Config) -> None:
    """One numba and one torch thread per worker when several workers share the cores."""
    if SHARED_CORES:
        import numba
        import torch

        numba.set_num_threads(1)
        torch.set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The docs pages (``test_docs.py``, the longest single tests) first, so that under
    ``pytest -n N`` no worker is left with a long page at the end."""
    items.sort(key=lambda item: not item.nodeid.startswith(DOCS))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``pytest -n N`` (pytest-xdist): every test module goes to one worker, so its module
    fixtures are built once, while each docs page may go to any; in collection order."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    config.option.loadscopereorder = False  # keep the docs pages first

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return nodeid if nodeid.startswith(DOCS) else nodeid.split("::", 1)[0]

    return ModuleScheduling(config, log)


def simulate(params: RigParams | None = None, schedule=((0.0, 1),), t_end: float = T_MAX,
             cut_on_arrival: bool = False, record_dt: float = 1e-3) -> Run:
    """Run a fresh plant from the thesis's initial state of an extension."""
    plant = Plant(params or RigParams())
    traj = plant.run(t_end, schedule=schedule, record_dt=record_dt, cut_on_arrival=cut_on_arrival)
    return Run(plant, traj)


def net_force(run: Run) -> np.ndarray:
    """Net pneumatic force on the piston [N] at the recorded samples."""
    return (run.traj["p_drive"] - run.traj["p_exhaust"]) * run.params.cylinder.piston_area_m2


@pytest.fixture(scope="session")
def conventional() -> Run:
    """Default rig, conventional extension: supply connected at t = 0 and never cut."""
    run = simulate()
    assert run.plant.arrival_time_s is not None, "the default rig must complete a conventional stroke"
    return run


@pytest.fixture(scope="session")
def end_stroke_cut() -> Run:
    """Default rig, the thesis's end-stroke cut-off (cut the supply on arrival)."""
    return simulate(cut_on_arrival=True)


@pytest.fixture(scope="session")
def load_bench():
    """``load_bench("bench_x")``: the script ``benchmarks/bench_x.py`` as a module (the
    benchmarks are scripts, not a package)."""
    import importlib.util
    from pathlib import Path

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
