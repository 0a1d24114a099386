"""The thesis's expansion-index puzzle (thesis 5.4, eq. 5.2).

After a cut-off the trapped air expands as the piston moves on. The thesis fitted
``p V^n = const`` to the driving chamber and found ``n = 2.7``, "far from" 1.0 (isothermal) to
1.4 (adiabatic), and suspected leakage. A leak removes air during the expansion, so the
pressure falls faster than the volume grows and the apparent index is too high. With the
leak in the model, the air mass ``m(t)`` left in the chamber is known, and the index of the
air that stays, ``p (V/m)^n = const``, is physical again.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data import MeasuredRun
from ..params import RigParams
from ..plant import Plant
from .residuals import RunPhases, run_phases

#: the window ends when the piston has covered this fraction of its travel after the cut-off
TRAVEL_FRACTION = 0.95


@dataclass(frozen=True)
class ExpansionIndex:
    """Polytropic index fitted over the expansion window ``[t_start_s, t_end_s]``."""

    n: float  # least-squares slope of -d ln p / d ln(V/m)
    n_endpoints: float  # thesis eq. 5.2 from the window's first and last samples
    t_start_s: float
    t_end_s: float
    volume_ratio: float  # V_end / V_start
    samples: int


def expansion_window(run: MeasuredRun, rig: RigParams, phases: RunPhases | None = None) -> np.ndarray:
    """Samples of the trapped-air expansion: after the cut-off has reached the valve, until
    the piston has covered :data:`TRAVEL_FRACTION` of the travel it makes after the cut-off.
    Empty if the run is not cut off or the piston does not move afterwards."""
    ph = phases or run_phases(run, rig)
    m = np.zeros(len(run), bool)
    if ph.t_cut_effective_s is None:
        return m
    after = run.t >= ph.t_cut_effective_s
    x0, x1 = float(run.x[after][0]), float(np.max(run.x[after]))
    if x1 - x0 < 1e-3:
        return m
    reached = np.flatnonzero(after & (run.x >= x0 + TRAVEL_FRACTION * (x1 - x0)))
    m[after & (run.t <= run.t[reached[0]])] = True
    return m


def fit_index(p: np.ndarray, volume: np.ndarray, mass: np.ndarray | None = None) -> tuple[float, float]:
    """Index ``n`` of ``p (V/m)^n = const`` by least squares on logs, and eq. 5.2 from the
    end points; ``mass=None`` is the thesis's fixed mass."""
    spec = volume if mass is None else volume / mass
    lx, ly = np.log(spec), np.log(p)
    n_ls = -float(np.polyfit(lx, ly, 1)[0])
    n_ep = float((ly[0] - ly[-1]) / (lx[-1] - lx[0]))
    return n_ls, n_ep


def _chamber_volume(rig: RigParams, x: np.ndarray) -> np.ndarray:
    return rig.drive_dead_volume_m3 + rig.effects.dead_volume_m3 + rig.drive_piston_area_m2 * x


def expansion_index(run: MeasuredRun, rig: RigParams, model: RigParams | None = None) -> ExpansionIndex:
    """The expansion index of a measured run's trapped air.

    ``model=None``: the thesis's identification, fixed mass, from the measured driving
    pressure and the volume from the measured position (``rig``'s dead volume). With a
    ``model`` (e.g. the workflow's updated rig), the air mass left in the driving chamber is
    taken from that model's replay of the run, so leaked air no longer counts as expansion."""
    win = expansion_window(run, rig)
    if win.sum() < 5:
        raise ValueError(f"run {run.name!r} has no trapped-air expansion (no cut-off with motion after it)")
    vol = _chamber_volume(model or rig, run.x[win])
    mass = None
    if model is not None:
        traj = Plant(model).run(float(run.t[-1]), run.schedule(), record_dt=run.sample_dt_s)
        t = traj["t"]
        R = model.gas.gas_constant_j_per_kg_k
        m_sim = traj["p_drive"] * _chamber_volume(model, traj["x"]) / (R * traj["T_drive"])
        mass = np.interp(run.t[win], t, m_sim)
    n, n_ep = fit_index(run.p_drive[win], vol, mass)
    tw = run.t[win]
    return ExpansionIndex(n, n_ep, float(tw[0]), float(tw[-1]), float(vol[-1] / vol[0]), int(win.sum()))
