"""Long runs in bounded time and memory: each run is cut to the window that carries information
and, if that is still long, block-averaged to a bounded number of samples.

- **Window** (runs lasting more than :data:`MAX_WINDOW_S` after the extend command; shorter
  runs, such as the thesis protocol's 2-3 s, are used whole): from :data:`PRE_TRIGGER_S` before
  the extend command (``t = 0``) to :data:`SETTLE_MARGIN_S` after the last event: the end of the
  motion, the last valve command change reaching the valve (valve delay + ramp), and every
  compared channel settling (staying within :data:`SETTLE_TOLERANCE` or 5 noise sigmas of its
  final level). The window ends at most :data:`MAX_WINDOW_S` after the extend command (a leak
  keeps the pressure falling for minutes).
- **Decimation**: if a window holds more than :data:`MAX_SAMPLES` samples, blocks of ``k``
  consecutive samples are averaged (``k`` common to all runs of a fit, so that the noise
  estimated from the averaged data holds for every run: averaging ``k`` samples of white noise
  divides its sigma by ``sqrt(k)``, and the noise is estimated after averaging). The valve
  commands keep their exact times (:attr:`MeasuredRun.commands`) and the replay averages the
  simulation over the same blocks (:func:`pneugym.discrepancy.residuals.replay`), so nothing is
  lost but the high-frequency noise.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..data import MeasuredRun
from ..params import RigParams
from .residuals import channels_of

#: samples kept before the extend command [s]
PRE_TRIGGER_S = 1.0
#: time kept after the last event (motion, valve, settling) [s]
SETTLE_MARGIN_S = 1.0
#: longest window after the extend command [s]; runs up to this long are not windowed
MAX_WINDOW_S = 20.0
#: most samples of a run after windowing; more are block-averaged
MAX_SAMPLES = 10_000
#: a channel has settled once it stays this close to its final level (or 5 noise sigmas)
SETTLE_TOLERANCE = {"x": 1e-4, "p_drive": 1e3, "p_exhaust": 1e3, "mdot_supply": 1e-5, "T_drive": 0.5}
#: the final level is the median of the run's last this-many seconds
FINAL_S = 0.5


@dataclass(frozen=True)
class Preparation:
    """What was done to one run before the fit (times in s since the extend command)."""

    run: str
    samples_measured: int
    t_measured_s: tuple[float, float]
    t_used_s: tuple[float, float]  # first and last sample time used (block centres if averaged)
    windowed: bool
    t_events_end_s: float | None  # when motion, valve and every channel had settled (None: never)
    capped: bool  # the window was cut at MAX_WINDOW_S although the run had not settled
    block: int  # samples averaged per row (1 = none)
    samples_used: int

    def sentence(self) -> str:
        a, b = self.t_measured_s
        u0, u1 = self.t_used_s
        parts = []
        if self.windowed:
            why = (f"still changing at the {MAX_WINDOW_S:g} s cap" if self.capped else
                   f"motion, valve and signals settled by {self.t_events_end_s:.3g} s, "
                   f"+ {SETTLE_MARGIN_S:g} s margin")
            parts.append(f"window {u0:.3g} to {u1:.4g} s of {a:.3g} to {b:.4g} s ({why})")
        if self.block > 1:
            parts.append(f"block-averaged by {self.block} (noise sigma / {math.sqrt(self.block):.2g})")
        if not parts:
            return f"{self.run}: used whole ({self.samples_measured} samples)"
        return (f"{self.run}: " + "; ".join(parts)
                + f": {self.samples_used} of {self.samples_measured} samples used")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["sentence"] = self.sentence()
        return d


def settle_time(run: MeasuredRun, rig: RigParams) -> float | None:
    """When the run's information ends [s]: the last valve change has reached the valve and
    every compared channel stays near its final level. ``None`` if a channel never settles."""
    t = run.t
    sched = run.schedule()
    t_valve = sched[-1][0] + rig.valve_delay_s + rig.valve.ramp_s if len(sched) > 1 else 0.0
    final = t >= t[-1] - FINAL_S
    if final.sum() < 5:
        return None
    latest = t_valve
    for c in channels_of(run):
        y = getattr(run, c)
        yf = y[final]
        noise = float(np.std(np.diff(yf))) / math.sqrt(2.0)
        tol = max(SETTLE_TOLERANCE[c], 5.0 * noise)
        away = np.flatnonzero(np.abs(y - np.median(yf)) > tol)
        if away.size:
            if t[away[-1]] >= t[-1] - FINAL_S:
                return None  # still moving at the end of the run
            latest = max(latest, float(t[away[-1] + 1]))
    return latest


def window(run: MeasuredRun, rig: RigParams) -> tuple[MeasuredRun, float | None, bool]:
    """``run`` cut to its informative window; returns ``(run, settle time, capped)``. A run no
    longer than :data:`MAX_WINDOW_S`, or whose window is all of it, is returned as it is."""
    if run.t[-1] <= MAX_WINDOW_S:
        return run, None, False
    t_set = settle_time(run, rig)
    end = MAX_WINDOW_S if t_set is None else min(t_set + SETTLE_MARGIN_S, MAX_WINDOW_S)
    capped = t_set is None or t_set + SETTLE_MARGIN_S > MAX_WINDOW_S
    keep = (run.t >= -PRE_TRIGGER_S) & (run.t <= end)
    if keep.all() or keep.sum() < 2:
        return run, t_set, False
    i0, i1 = int(np.argmax(keep)), int(keep.size - np.argmax(keep[::-1]))
    return _slice(run, i0, i1), t_set, capped


def _slice(run: MeasuredRun, i0: int, i1: int) -> MeasuredRun:
    cols = {c: a[i0:i1].copy() for c, a in run.columns.items() if c in _NUMERIC and a is not None}
    t_end = float(run.t[i1 - 1])
    commands = tuple((t, v) for t, v in run.schedule() if t <= t_end)
    return MeasuredRun(name=run.name, meta=run.meta, source=run.source, block=run.block,
                       commands=commands if run.commands is not None else None, **cols)


def block_average(run: MeasuredRun, k: int) -> MeasuredRun:
    """Means of ``k`` consecutive samples (a last partial block is dropped); the valve column
    becomes the fraction of each block commanded open, the commands keep their exact times."""
    n = len(run) // k
    if k <= 1 or n < 2:
        return run
    cols = {c: a[: n * k].reshape(n, k).mean(axis=1)
            for c, a in run.columns.items() if c in _NUMERIC and a is not None}
    t_last = float(run.t[n * k - 1])
    commands = tuple((t, v) for t, v in run.schedule() if t <= t_last)
    return MeasuredRun(name=run.name, meta=run.meta, source=run.source, block=run.block * k,
                       commands=commands, **cols)


_NUMERIC = ("t", "valve", "x", "p_drive", "p_exhaust", "p_supply", "mdot_supply", "T_drive")


def prepare(runs: Sequence[MeasuredRun], rigs: Sequence[RigParams],
            max_samples: int = MAX_SAMPLES) -> tuple[list[MeasuredRun], list[Preparation]]:
    """Window every run, then block-average all of them by a common factor if a window holds
    more than ``max_samples`` samples. Short runs come back unchanged (the same objects)."""
    cut = [window(r, g) for r, g in zip(runs, rigs)]
    steps = [r.sample_dt_s * math.ceil(len(r) / max_samples) for r, _, _ in cut]
    target = max(steps)
    out, info = [], []
    for orig, (r, t_set, capped) in zip(runs, cut):
        k = max(1, round(target / r.sample_dt_s)) if any(len(c[0]) > max_samples for c in cut) else 1
        p = block_average(r, k)
        info.append(Preparation(
            run=orig.name, samples_measured=len(orig),
            t_measured_s=(float(orig.t[0]), float(orig.t[-1])),
            t_used_s=(float(p.t[0]), float(p.t[-1])), windowed=r is not orig,
            t_events_end_s=t_set, capped=capped and r is not orig, block=p.block // orig.block,
            samples_used=len(p)))
        out.append(p)
    return out, info
