"""Replaying a measured run in the plant, phases of a run, noise levels, NRMSE and gap reduction,
localisation.

Channels compared (measured CSV column -> plant channel): ``x`` -> ``x``, ``p_drive`` ->
``p_drive_sensor``, ``p_exhaust`` -> ``p_exhaust_sensor`` (the transducers at the cylinder
ports, lagged if ``sensor_lag_s`` > 0), and, when a run has them, ``mdot_supply`` and
``T_drive``.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..data import MeasuredRun
from ..params import RigParams
from ..plant import Plant, SimulationError

#: measured column -> recorded plant channel
CHANNELS = {"x": "x", "p_drive": "p_drive_sensor", "p_exhaust": "p_exhaust_sensor",
            "mdot_supply": "mdot_supply", "T_drive": "T_drive"}
CORE_CHANNELS = ("x", "p_drive", "p_exhaust")
UNITS = {"x": "m", "p_drive": "Pa", "p_exhaust": "Pa", "mdot_supply": "kg/s", "T_drive": "K"}
#: smallest noise level [channel unit] a channel is given (noise-free simulated data)
NOISE_FLOOR = {"x": 1e-7, "p_drive": 1.0, "p_exhaust": 1.0, "mdot_supply": 1e-8, "T_drive": 1e-3}

PHASES = ("before_motion", "stroke", "trapped", "end_supply")
PHASE_TEXT = {"before_motion": "before motion", "stroke": "stroke with supply",
              "trapped": "trapped air after cut-off", "end_supply": "end of stroke with supply"}
def phase_shares(by_phase: Mapping[str, float]) -> str:
    """``"trapped air after cut-off +80%, stroke with supply +5%"``: a candidate's share of the
    misfit removed per phase (shares under 1 % left out)."""
    return ", ".join(f"{PHASE_TEXT[p]} {v:+.0%}" for p, v in by_phase.items() if abs(v) >= 0.01)


#: the piston counts as moving once it is this far [m] from its first position ...
MOTION_THRESHOLD_M = 5e-4
#: ... and as arrived this close [m] to the end of stroke
ARRIVAL_THRESHOLD_M = 1e-3


def channels_of(run: MeasuredRun) -> tuple[str, ...]:
    """The channels of ``run`` that are compared with the plant."""
    return CORE_CHANNELS + tuple(c for c in ("mdot_supply", "T_drive") if getattr(run, c) is not None)


def replay(run: MeasuredRun, params: RigParams) -> dict[str, np.ndarray]:
    """Simulate ``run``'s valve commands on rig ``params``; channels at the run's sample times.

    The plant starts at ``t = 0`` (the extend command) from rest; samples before ``t = 0`` get
    the initial state. A block-averaged run (``run.block = k > 1``) gets the simulation at the
    original sampling averaged over the same blocks of ``k`` samples. Raises
    :class:`pneugym.plant.SimulationError` if the plant fails, ``ValueError`` if it refuses the
    rig or the commands; either names the run."""
    k = int(run.block)
    dt = run.sample_dt_s / k
    t_end = max(float(run.t[-1]) + 0.5 * (k - 1) * dt, dt)
    try:
        traj = Plant(params).run(t_end, run.schedule(), record_dt=dt)
    except SimulationError as exc:
        raise SimulationError(f"{run_label(run)}: {exc}") from exc
    except ValueError as exc:
        raise ValueError(f"{run_label(run)}: {exc}") from exc
    ts = traj["t"]
    if k == 1:
        return {c: np.interp(run.t, ts, traj[CHANNELS[c]]) for c in channels_of(run)}
    fine = (run.t[:, None] + (np.arange(k) - 0.5 * (k - 1)) * dt).ravel()
    return {c: np.interp(fine, ts, traj[CHANNELS[c]]).reshape(-1, k).mean(axis=1)
            for c in channels_of(run)}


def run_label(run: MeasuredRun) -> str:
    """``run 'NAME' (path.csv)``: how errors name a run."""
    src = f" ({run.source.with_name(run.source.name + '.csv')})" if run.source is not None else ""
    return f"run {run.name!r}{src}"


def noise_at_floor(sigma: Mapping[str, float]) -> list[str]:
    """Channels whose estimated noise is at :data:`NOISE_FLOOR` (noise-free data)."""
    return [c for c, v in sigma.items() if v <= NOISE_FLOOR[c]]


@dataclass(frozen=True)
class RunPhases:
    """Phase of every sample of a run, from the measured position and valve command."""

    labels: np.ndarray  # index into PHASES per sample
    t_motion_s: float | None  # first sample with the piston moving
    t_arrival_s: float | None  # first sample at the end of stroke
    t_cut_effective_s: float | None  # first cut-off command + valve delay

    def mask(self, phase: str) -> np.ndarray:
        return self.labels == PHASES.index(phase)

    def spans(self, t: np.ndarray) -> list[tuple[str, float, float]]:
        """``(phase, t_start, t_end)`` of each contiguous stretch."""
        out = []
        edges = np.flatnonzero(np.diff(self.labels)) + 1
        starts = np.concatenate([[0], edges])
        ends = np.concatenate([edges, [self.labels.size]])
        for a, b in zip(starts, ends):
            out.append((PHASES[int(self.labels[a])], float(t[a]), float(t[b - 1])))
        return out


def run_phases(run: MeasuredRun, rig: RigParams) -> RunPhases:
    """Label samples ``before_motion``, ``stroke`` (moving, supply connected), ``trapped``
    (after a cut-off has reached the valve: valve delay + ramp after the command) and
    ``end_supply`` (at the end of stroke, supply connected)."""
    t, x = run.t, run.x
    x0 = float(np.median(x[: min(20, x.size)]))
    moving = np.flatnonzero(np.abs(x - x0) > MOTION_THRESHOLD_M)
    t_move = float(t[moving[0]]) if moving.size else None
    arrived = np.flatnonzero(x >= rig.cylinder.stroke_m - ARRIVAL_THRESHOLD_M)
    t_arr = float(t[arrived[0]]) if arrived.size else None
    # supply state at the valve: the command, delayed by the valve delay and ramp
    lag = rig.valve_delay_s + rig.valve.ramp_s
    cmd_at_valve = np.interp(t - lag, t, run.valve, left=0.0)
    opened = np.maximum.accumulate(cmd_at_valve > 0.5)
    cut = opened & (cmd_at_valve < 0.5)
    t_cut = None
    if cut.any():
        t_cut = float(t[np.flatnonzero(cut)[0]])
    lab = np.full(t.size, PHASES.index("stroke"))
    if t_arr is not None:
        lab[t >= t_arr] = PHASES.index("end_supply")
    lab[t < (t_move if t_move is not None else np.inf)] = PHASES.index("before_motion")
    lab[cut] = PHASES.index("trapped")
    return RunPhases(lab, t_move, t_arr, t_cut)


def estimate_noise(runs: Sequence[MeasuredRun], window: int = 25) -> dict[str, float]:
    """Noise standard deviation of every channel, from quiet segments.

    Quiet segments are windows of ``window`` samples with the piston at rest (measured position
    within 0.2 mm); each window is detrended by a quadratic, and the channel's noise is the
    median of the windows' residual standard deviations (pooled over the runs). A channel
    quieter than :data:`NOISE_FLOOR` (noise-free, e.g. simulated, data) gets the floor, so the
    residuals in noise units never divide by zero; :func:`noise_at_floor` lists those channels."""
    chans = sorted({c for r in runs for c in channels_of(r)}, key=list(CHANNELS).index)
    k = np.arange(window) - (window - 1) / 2.0
    B = np.stack([np.ones(window), k, k * k], axis=1)
    proj = np.eye(window) - B @ np.linalg.pinv(B)
    stds: dict[str, list[np.ndarray]] = {c: [] for c in chans}
    for r in runs:
        n = len(r) // window
        if n == 0:
            continue
        xw = r.x[: n * window].reshape(n, window)
        rest = (xw.max(axis=1) - xw.min(axis=1)) < 2e-4
        if not rest.any():
            rest[:] = True
        for c in channels_of(r):
            w = getattr(r, c)[: n * window].reshape(n, window)[rest]
            res = w @ proj.T
            stds[c].append(np.sqrt((res * res).sum(axis=1) / (window - 3)))
    out = {}
    for c in chans:
        s = float(np.median(np.concatenate(stds[c]))) if stds[c] else 0.0
        out[c] = max(s, NOISE_FLOOR[c])
    return out


def nrmse(runs: Sequence[MeasuredRun], sims: Sequence[Mapping[str, np.ndarray]]) -> dict[str, float]:
    """NRMSE of each channel over a set of runs, and ``overall``, their mean.

    ``NRMSE_c = sqrt(mean over all samples of (measured - simulated)^2) / (max - min of the
    measured channel over the set)``. Channels present in only some runs use those runs."""
    out: dict[str, float] = {}
    chans = [c for c in CHANNELS if any(c in s for s in sims)]
    for c in chans:
        res = [getattr(r, c) - s[c] for r, s in zip(runs, sims) if c in s]
        meas = np.concatenate([getattr(r, c) for r, s in zip(runs, sims) if c in s])
        rng = float(meas.max() - meas.min()) or 1.0
        e = np.concatenate(res)
        out[c] = float(np.sqrt(np.mean(e * e)) / rng)
    out["overall"] = float(np.mean([out[c] for c in chans]))
    return out


#: an overall NRMSE at or below this is no gap: the model reproduces the runs to round-off
#: (noise-free data simulated with the rig the JSON states); no gap reduction is computed
NO_GAP = 1e-9


def reduction(before: float, after: float) -> float | None:
    """``1 - after / before``, or ``None`` when ``before`` is no gap (<= :data:`NO_GAP`)."""
    return None if not before > NO_GAP else 1.0 - after / before


@dataclass(frozen=True)
class Finding:
    """Residual statistics of one channel in one phase of one run (``z`` = residual / noise)."""

    run: str
    phase: str
    channel: str
    n: int
    t_start_s: float
    t_end_s: float
    rms_z: float
    mean_z: float
    max_abs_z: float
    t_max_s: float

    def sentence(self) -> str:
        side = "below" if self.mean_z > 0 else "above"
        return (f"{self.channel} during {PHASE_TEXT[self.phase]} of run {self.run} "
                f"(t = {self.t_start_s:.2f}-{self.t_end_s:.2f} s): residual RMS {self.rms_z:.1f} sigma, "
                f"mean {self.mean_z:+.1f} sigma (model {side} the measurement), worst "
                f"{self.max_abs_z:.1f} sigma at t = {self.t_max_s:.3f} s")


def localise(runs: Sequence[MeasuredRun], sims: Sequence[Mapping[str, np.ndarray]],
             phases: Sequence[RunPhases], sigma: Mapping[str, float]) -> list[Finding]:
    """Residual statistics per run, phase and channel, worst (largest RMS in sigma) first."""
    out = []
    for r, s, ph in zip(runs, sims, phases):
        for c in (c for c in s if c in CHANNELS):  # not "t" of Discrepancy.predict
            z = (getattr(r, c) - s[c]) / sigma[c]
            for p in PHASES:
                m = ph.mask(p)
                if m.sum() < 2:
                    continue
                zm, tm = z[m], r.t[m]
                i = int(np.argmax(np.abs(zm)))
                out.append(Finding(r.name, p, c, int(m.sum()), float(tm[0]), float(tm[-1]),
                                   float(np.sqrt(np.mean(zm * zm))), float(zm.mean()),
                                   float(abs(zm[i])), float(tm[i])))
    return sorted(out, key=lambda f: -f.rms_z)
