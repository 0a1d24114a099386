"""Least-squares fitting of rig parameters to measured runs through the plant.

The residual vector is ``(measured - simulated) / sigma`` for every compared channel of every
run (``sigma`` the channel's noise level), so a model that is right up to the noise has a
sum of squares near the number of samples. Fits are multi-start
``scipy.optimize.least_squares`` (trust-region reflective, bounds) on the transformed variables
of :class:`~pneugym.discrepancy.candidates.FitParam`; every start is an independent job, so
starts can run in parallel processes.
"""
from __future__ import annotations

import copy
import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_all_start_methods, get_context

import numpy as np
from scipy.optimize import least_squares

from ..data import MeasuredRun
from ..params import RigParams
from ..plant import SimulationError, choose_dt
from .candidates import FitParam, apply, nominal_params, read
from .residuals import channels_of, estimate_noise, replay

#: residual (in sigma) given to every sample when the plant fails for a trial parameter set
FAILED_RESIDUAL = 1e4
#: default finite-difference step of the Jacobian, in transformed units (see FitParam):
#: 0.05 = 0.5 % of a log parameter (log_step 0.1), 5 % of a linear one's reference. The plant
#: resolves stick/slip events to a substep, so the SSR has fine stairs; a step spanning
#: several of them gives a useful gradient.
DIFF_STEP = 0.05
#: least-squares restarts from the last solution while they improve the SSR by > 1 %: the
#: trust region of a rough objective collapses early (``xtol``), a restart re-opens it
RESTARTS = 3


#: fitted fields that speed up the plant's fastest process (orifice flows into small volumes)
FLOW_PATHS = ("valve.discharge_coefficient", "valve.area_m2", "valve.exhaust_area_m2",
              "cylinder.port_area_m2")


def fixed_step(rig: RigParams, params: Sequence[FitParam]) -> RigParams:
    """``rig`` with the substep fixed at the stable one for the largest flows the fit may try
    (every fitted discharge coefficient and area at its upper bound), so that every trial runs
    on the same time grid (an automatic substep would change with them and jitter the
    residuals)."""
    fast = [p for p in params if p.path in FLOW_PATHS]
    dt, _ = choose_dt(apply(rig, fast, [p.hi for p in fast]))
    return rig.with_(solver={"dt_s": dt})


class Problem:
    """Weighted residuals of ``runs`` for the fitted ``params`` (each run on its own base rig)."""

    def __init__(self, runs: Sequence[MeasuredRun], bases: Sequence[RigParams],
                 sigma: Mapping[str, float], params: Sequence[FitParam]):
        self.runs = list(runs)
        self.bases = list(bases)
        self.sigma = dict(sigma)
        self.params = tuple(params)
        self.n = sum(len(r) * len(channels_of(r)) for r in self.runs)

    def values(self, u: np.ndarray) -> np.ndarray:
        return np.array([p.from_u(x) for p, x in zip(self.params, u)])

    def rigs(self, values: Sequence[float]) -> list[RigParams]:
        return [apply(b, self.params, values) for b in self.bases]

    def simulate(self, values: Sequence[float]) -> list[dict[str, np.ndarray]]:
        """Simulated channels of every run (raises SimulationError / ValueError)."""
        return [replay(r, rig) for r, rig in zip(self.runs, self.rigs(values))]

    def segments(self, values: Sequence[float]) -> list[tuple[str, str, np.ndarray]]:
        """``(run, channel, weighted residual)`` for every run and channel."""
        out = []
        for r, sim in zip(self.runs, self.simulate(values)):
            for c in channels_of(r):
                out.append((r.name, c, (getattr(r, c) - sim[c]) / self.sigma[c]))
        return out

    def residuals(self, u: np.ndarray) -> np.ndarray:
        try:
            return np.concatenate([s for _, _, s in self.segments(self.values(u))])
        except (SimulationError, ValueError):
            return np.full(self.n, FAILED_RESIDUAL)


@dataclass
class FitResult:
    """Best of a multi-start fit."""

    params: tuple[FitParam, ...]
    values: np.ndarray  # natural units
    u: np.ndarray
    ssr: float
    jac: np.ndarray  # Jacobian of the weighted residuals w.r.t. u at the optimum
    nfev: int  # function evaluations over all starts (Jacobian evaluations excluded)
    start_ssr: list[float]  # final SSR of every start

    def as_dict(self) -> dict[str, float]:
        return {p.path: float(v) for p, v in zip(self.params, self.values)}


@dataclass
class Job:
    """One start of one fit (picklable, for a process pool)."""

    runs: list
    bases: list
    sigma: dict
    params: tuple
    start: np.ndarray  # natural units
    max_nfev: int  # per least-squares run (restarts included separately)


def solve(job: Job) -> tuple[np.ndarray, float, np.ndarray, int]:
    """Run one ``least_squares`` start; returns ``(u, ssr, jac, nfev)``."""
    prob = Problem(job.runs, job.bases, job.sigma, job.params)
    lo = np.array([p.u_bounds[0] for p in prob.params])
    hi = np.array([p.u_bounds[1] for p in prob.params])
    u0 = np.array([p.to_u(v) for p, v in zip(prob.params, job.start)])
    u0 = np.clip(u0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    step = np.array([p.diff_step or DIFF_STEP for p in prob.params])
    nfev, prev = 0, np.inf
    for _ in range(1 + RESTARTS):
        sol = least_squares(prob.residuals, u0, bounds=(lo, hi), method="trf", x_scale=1.0,
                            diff_step=step, max_nfev=job.max_nfev, ftol=1e-6, xtol=1e-6,
                            gtol=1e-8)
        nfev += int(sol.nfev)
        if 2.0 * sol.cost > 0.99 * prev:
            break
        prev, u0 = 2.0 * sol.cost, np.clip(sol.x, lo, hi)
    return sol.x, float(2.0 * sol.cost), sol.jac, nfev


class Executor:
    """Runs jobs serially (``n_jobs = 1``) or in a pool of ``n_jobs`` worker processes."""

    def __init__(self, n_jobs: int = 1):
        if n_jobs is None or n_jobs < 1:
            n_jobs = max(1, os.cpu_count() or 1)
        self.n_jobs = int(n_jobs)
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable, jobs: Sequence, on_done: Callable[[], None] | None = None) -> list:
        if self.n_jobs == 1 or len(jobs) <= 1:
            out = []
            for j in jobs:
                out.append(fn(j))
                if on_done:
                    on_done()
            return out
        if self._pool is None:
            # fork (Linux) hands the workers the compiled kernels and needs no main guard;
            # elsewhere spawn (scripts then need ``if __name__ == "__main__":``)
            method = "fork" if "fork" in get_all_start_methods() else "spawn"
            self._pool = ProcessPoolExecutor(self.n_jobs, mp_context=get_context(method))
        futures = [self._pool.submit(fn, j) for j in jobs]
        out = []
        for f in futures:
            out.append(f.result())
            if on_done:
                on_done()
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def best_of(prob: Problem, results: Sequence[tuple[np.ndarray, float, np.ndarray, int]]) -> FitResult:
    """The start with the smallest SSR."""
    i = int(np.argmin([r[1] for r in results]))
    u, ssr, jac, _ = results[i]
    return FitResult(prob.params, prob.values(u), u, ssr, jac, sum(r[3] for r in results),
                     [r[1] for r in results])


def own_friction(runs: Sequence[MeasuredRun], max_nfev: int = 20,
                 base: RigParams | None = None) -> list[MeasuredRun]:
    """``runs`` with each one's friction (static, Coulomb, viscous [N, N, N s/m]) fitted to that
    run alone through the plant (one least-squares start from the stated values, ``max_nfev``
    iterations; the run's rig read over ``base``) and stated in its JSON. Friction varies from
    stroke to stroke; left to one friction for all, that variation's misfit in the motion can
    hide a small effect elsewhere (a leak in the trapped air). The workflow then fits one
    factor on each run's friction (:func:`~pneugym.discrepancy.candidates.nominal_params`,
    ``relative_friction``)."""
    sigma = estimate_noise(runs)
    out = []
    for r in runs:
        rig = r.rig(base)
        params = tuple(p for p in nominal_params(rig, extended=False)
                       if p.path.startswith("friction."))
        start = np.array([read(rig, p.path) for p in params])
        u, _, _, _ = solve(Job([r], [fixed_step(rig, params)], sigma, params, start, max_nfev))
        meta = copy.deepcopy(r.meta)
        fr = meta.setdefault("rig", {}).setdefault("friction", {})
        for p, x in zip(params, u):
            fr[p.name] = p.from_u(float(x))
        out.append(dataclasses.replace(r, meta=meta))
    return out
