"""Sensor traces of many rigs with the supply kept, sampled as an episode samples them: what a
model-predictive controller compares with the stroke it has measured so far
(:class:`agents.mpc.ModelPredictivePolicy`). The plants are the environment's (same packed
parameters, same kernels, same sensors), advanced together one control period at a time.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..params import RigParams
from ..physics import system as K
from ..physics.batch import advance_batch
from . import episode as EP
from .cutoff import PRESSURE_SCALE_PA, VELOCITY_SCALE_M_S, _template


def keep_traces(rigs: Sequence[RigParams | None], period_s: float, n_steps: int
                ) -> np.ndarray:
    """Noise-free sensor samples of each rig's stroke with the supply kept: an array
    (B, n_steps + 1, 3) of position [m], driving- and exhaust-port gauge pressure [Pa] at
    ``0, period_s, ..., n_steps * period_s`` after the extend command (an episode's observation
    times). A rig that is ``None``, cannot be stepped (ValueError) or goes non-physical gives a
    NaN trace. The rigs must share the line grid (the environment's requirement too)."""
    if not (isinstance(n_steps, (int, np.integer)) and n_steps >= 0):
        raise ValueError(f"n_steps = {n_steps!r} must be an integer >= 0")
    if not period_s > 0:
        raise ValueError(f"period_s = {period_s!r} must be > 0")
    b = len(rigs)
    temps = []
    for r in rigs:
        try:
            temps.append(None if r is None else _template(r))
        except ValueError:
            temps.append(None)
    ok = next((t for t in temps if t is not None), None)
    out = np.full((b, n_steps + 1, 3), np.nan)
    if ok is None:
        return out
    P, Y, D = (np.zeros((b, a.size)) for a in ok)
    status = np.zeros(b, dtype=np.int64)
    for i, t in enumerate(temps):
        P[i], Y[i], D[i] = t if t is not None else ok
        status[i] = 0 if t is not None else -1
        K.command(D[i], P[i], 1.0)
    E = np.zeros((b, EP.NE))
    E[:, EP.E_PERIOD] = period_s
    W = np.empty((b, K.work_size(P[0])))
    scales = np.array([1.0, VELOCITY_SCALE_M_S, PRESSURE_SCALE_PA, 1.0])  # position in m
    hist = np.zeros((b, 1, EP.NF))
    x_prev, noise = np.zeros(b), np.zeros((b, 3))
    extra, obs = np.zeros((b, 0)), np.zeros((b, EP.NF), dtype=np.float32)
    rows = np.arange(b)
    commands = np.ones(b)
    for k in range(n_steps + 1):
        EP.observe(Y, P, D, E, rows, noise, x_prev, scales, k == 0, hist, extra, np.inf, obs)
        out[:, k, 0] = hist[:, 0, 0]
        out[:, k, 1:] = hist[:, 0, 2:4] * PRESSURE_SCALE_PA
        if k < n_steps:
            advance_batch(Y, P, D, commands, period_s, status, W)
    out[status != 0] = np.nan
    return out
