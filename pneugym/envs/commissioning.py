"""What one recorded stroke tells a policy about its rig (``observe_commissioning=True``).

A rig file states the datasheet; the valve's flow, the friction while moving, the cushions and
the leaks it cannot state show in a stroke the rig has made. The *commissioning stroke* is the
thesis's end-stroke cut-off, held: extend at the operating point (supply, load), cut off the
moment the piston arrives, keep recording :data:`HOLD_END_S` after the arrival. Up to the arrival
it is the conventional stroke; after it the trapped air shows leaks and heat exchange.
:data:`COMMISSIONING_OBSERVATION` are its features; :func:`trace_features` computes them from the
samples (one function for a simulated and a measured stroke), :func:`run_features` from a
measured run (``pneugym-measurement/1``), :func:`simulated_features` from the plant (what the
environment observes: the rig at the operating point, nominal friction and valve delay, no
noise). Units SI, pressures gauge in the features.
"""
from __future__ import annotations

import functools
import os
from typing import Any

import numpy as np

from ..params import RigParams
from .cutoff import BREAKAWAY_M, COMMISSIONING_OBSERVATION

ARRIVAL_TOLERANCE_M = 5e-4  # the piston counts as arrived this close to the end of stroke
HOLD_START_S, HOLD_END_S = 0.5, 1.5  # the hold window [s after the arrival]
WINDOW_S = 0.01  # pressures are averaged over this much [s] (the noise of a single sample)


def arrival_index(x: np.ndarray, stroke_m: float) -> int | None:
    """The first sample of ``x`` [m] within :data:`ARRIVAL_TOLERANCE_M` of the stroke's end
    (``stroke_m``), or None if the piston never gets there."""
    arrived = np.flatnonzero(np.asarray(x) >= stroke_m - ARRIVAL_TOLERANCE_M)
    return int(arrived[0]) if arrived.size else None


def trace_features(t: np.ndarray, x: np.ndarray, p_drive: np.ndarray, p_exhaust: np.ndarray,
                   stroke_m: float, what: str = "the commissioning stroke") -> np.ndarray:
    """The unscaled :data:`COMMISSIONING_OBSERVATION` of a stroke cut off on arrival and held:
    samples ``t`` [s] from the extend command, position ``x`` [m], port pressures gauge [Pa].
    Raises ``ValueError`` when the piston never arrives or the record ends before the hold."""
    t, x, pd, pe = (np.asarray(a, dtype=float) for a in (t, x, p_drive, p_exhaust))
    ia = arrival_index(x, stroke_m)
    if ia is None:
        raise ValueError(f"{what}: the piston never reaches the end of stroke ({stroke_m:g} m; "
                         f"at most {np.max(x):.4g} m): record a stroke that completes")
    ta = float(t[ia])
    if t[-1] < ta + HOLD_END_S:
        raise ValueError(f"{what} ends {t[-1] - ta:.3g} s after the arrival; record at least "
                         f"{HOLD_END_S:g} s of hold after it")
    tb = float(t[int(np.flatnonzero(x > BREAKAWAY_M)[0])])

    def mean(p: np.ndarray, t0: float, t1: float) -> float:
        sel = (t >= t0) & (t <= t1)
        return float(np.mean(p[sel])) if sel.any() else float(p[np.searchsorted(t, t0)])

    mid = (t >= tb + 0.25 * (ta - tb)) & (t <= tb + 0.75 * (ta - tb))
    dp = float(np.median(pd[mid] - pe[mid])) if mid.any() else float(pd[ia] - pe[ia])
    p0 = mean(pd, ta + HOLD_START_S - WINDOW_S, ta + HOLD_START_S)
    p1 = mean(pd, ta + HOLD_END_S - WINDOW_S, ta + HOLD_END_S)
    return np.array([ta, ta - tb, mean(pd, ta - WINDOW_S, ta), mean(pe, ta - WINDOW_S, ta), dp,
                     (p0 - p1) / max(p0, 1e3)])


def scaled(values: np.ndarray) -> np.ndarray:
    """:func:`trace_features` as the observation holds them (``value / scale``)."""
    return np.asarray(values, dtype=float) / np.array([f.scale for f in COMMISSIONING_OBSERVATION])


def as_features(value: Any, stroke_m: float, what: str = "the commissioning stroke"
                ) -> np.ndarray:
    """The scaled features of a commissioning stroke given as a measured run (a
    :class:`~pneugym.data.MeasuredRun` or the path of its JSON, :func:`run_features`) or as
    the features themselves. Raises ``ValueError`` naming ``what`` for anything else."""
    from ..data import MeasuredRun

    if isinstance(value, (MeasuredRun, str, os.PathLike)):
        return run_features(value, stroke_m)
    try:
        f = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        f = np.zeros(0)
    n = len(COMMISSIONING_OBSERVATION)
    if f.size != n or not np.isfinite(f).all():
        raise ValueError(f"{what} needs {n} finite numbers (the scaled features "
                         f"{[x.name for x in COMMISSIONING_OBSERVATION]}), a MeasuredRun or the "
                         f"path of one; got {value!r:.200}")
    return f


def run_features(run: Any, stroke_m: float) -> np.ndarray:
    """The scaled features of a measured commissioning stroke (a
    :class:`~pneugym.data.MeasuredRun`, or the path of its JSON): extend, cut off on arrival,
    held at least :data:`HOLD_END_S` after it."""
    from ..data import MeasuredRun, read_run

    if not isinstance(run, MeasuredRun):
        run = read_run(run)
    pa = float(run.meta.get("ambient_pressure_pa", 101_325.0))
    return scaled(trace_features(run.t, run.x, run.p_drive - pa, run.p_exhaust - pa, stroke_m,
                                 what=f"commissioning run {run.name!r}"))


@functools.lru_cache(maxsize=8192)
def simulated_features(rig: RigParams, record_dt_s: float = 1e-3) -> np.ndarray:
    """The scaled features of ``rig``'s commissioning stroke, simulated without noise (cached,
    read-only). ``rig`` at the operating point: its supply and load, nominal friction
    and valve delay. Raises ``ValueError`` if the stroke never completes within 20 s."""
    from ..plant import Plant

    from .cutoff import conventional_figures

    t_conv, _ = conventional_figures(rig)
    # (a margin: a plant that had to retry with a shorter substep arrives a little later; one
    # that arrives later still, e.g. creeping the last fraction of a millimetre after a
    # stick-slip, is run again to its own arrival plus the hold)
    t_end = t_conv + HOLD_END_S + 0.25
    for _ in range(2):
        tr = Plant(rig).run(t_end, cut_on_arrival=True, record_dt=record_dt_s)
        ia = arrival_index(tr["x"], rig.cylinder.stroke_m)
        if ia is None or tr["t"][-1] >= tr["t"][ia] + HOLD_END_S:
            break
        t_end = float(tr["t"][ia]) + HOLD_END_S + 0.25
    pa = rig.gas.ambient_pressure_pa
    out = scaled(trace_features(tr["t"], tr["x"], tr["p_drive_sensor"] - pa,
                                tr["p_exhaust_sensor"] - pa, rig.cylinder.stroke_m))
    out.setflags(write=False)
    return out


def condition_features(cond: Any, base: RigParams) -> np.ndarray:
    """:func:`simulated_features` of the rig an episode under ``cond`` (a
    :class:`~pneugym.envs.conditions.Conditions`) runs on (``base`` with its ``rig_changes``),
    commissioned at its supply and load: nominal friction and valve delay, no supply dip."""
    from .conditions import Conditions

    nominal = Conditions(supply_pressure_gauge_pa=cond.supply_pressure_gauge_pa,
                         load_mass_kg=cond.load_mass_kg, rig_changes=cond.rig_changes)
    return simulated_features(nominal.rig(base))
