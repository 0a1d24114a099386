"""ESAC's training data: rollouts of the batched environment cut off at random times
(:func:`generate_rollouts`), cached on disk (:func:`rollouts`), and the network's samples and
targets drawn from them (:func:`samples`, :func:`targets`).

Each episode is cut at a random time; its final figures label the observation at the cut
(``Δ = 0``) and the observations :data:`LAGS` control periods before it (the same outcome seen
``Δ`` earlier: before the cut an episode is the uncut one).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..base import run_first_episodes
from ..oracle import TimedCutPolicy

GENERATOR_VERSION = 3  # bump when generate_rollouts changes what it records
#: control periods before the cut at which an observation is also recorded (Δ = lag x period):
#: dense near the cut, up to 1.28 s, so that the lookahead sees the whole rest of a slow stroke
LAGS = (0, 2, 4, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)


@functools.lru_cache(maxsize=1)
def source_hash() -> str:
    """SHA-256 (first 16 hex digits) of the ``pneugym`` package's Python sources: a changed plant
    makes cached rollouts stale. Computed once per process (train.py calls it at the start, so
    that sources edited while it runs do not key results of the code it has loaded)."""
    import pneugym

    root = Path(pneugym.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def generate_rollouts(n: int, seed: int, history: int = 8, preset: Any = "randomized",
                      env_config: Mapping[str, Any] | None = None, batch: int = 512,
                      focus: tuple[float, float] = (0.3, 1.0), focus_share: float = 0.8,
                      lags: Sequence[int] = LAGS, progress: bool = True) -> dict[str, np.ndarray]:
    """``n`` episodes with a random cut-off time each, in batches of the vector environment
    (``autoreset=False``). The cut time is uniform in ``[0, T + window]`` (``T`` the conventional
    stroke time of the episode's conditions), or, for a share ``focus_share`` of the episodes, in
    ``focus`` times that (where the outcome changes from stall to slow to on time). Episode ``j``
    draws its conditions from ``preset`` with seed ``seed + j`` and its cut time from
    ``default_rng([seed, j])``.

    Returns arrays with one row per episode that was cut before it ended: ``obs`` (the
    observation at the cut), ``obs_lag`` (B, len(lags), size: the observations ``lags`` control
    periods before the cut, NaN before the episode began), ``lag_s`` (the lags [s]), ``t_cut``
    [s], and the final figures ``completed``, ``stalled``,
    ``final_position_m``, ``stroke_time_s`` (NaN if incomplete), ``conventional_time_s``,
    ``energy_wasted_j``, ``energy_conventional_j``, ``saving_ratio``, ``stick_slip_events``,
    ``objective``, plus the conditions' fields."""
    from tqdm import tqdm

    from pneugym.envs import conventional_figures
    from pneugym.envs.cutoff import CutOffVectorEnv

    cfg = dict(env_config or {})
    cfg["history"] = history
    lags = tuple(int(k) for k in lags)
    if not lags or lags[0] != 0 or any(b <= a for a, b in zip(lags, lags[1:])):
        raise ValueError(f"lags = {lags!r}: increasing control periods starting at 0")
    cols: dict[str, list] = {}
    period = None
    bar = tqdm(total=n, desc="ESAC rollouts", unit="ep", disable=not progress)
    for start in range(0, n, batch):
        b = min(batch, n - start)
        env = CutOffVectorEnv(num_envs=b, autoreset=False, preset=preset, **cfg)
        env.reset(seed=seed + start)  # draws the conditions from the preset
        conds = list(env.conditions)
        window = env.decision_window_s
        t_conv = np.array([conventional_figures(c.rig(env.rig), c.dip)[0] for c in conds])
        u = np.array([np.random.default_rng([seed, start + i]).random(2) for i in range(b)])
        # a fifth of the cut times anywhere, the rest where the outcome turns (stall, slow,
        # on time): from 30 % of the conventional stroke time on
        lo = np.where(u[:, 0] < focus_share, focus[0], 0.0)
        hi = np.where(u[:, 0] < focus_share, focus[1], 1.0)
        t_cut = (lo + (hi - lo) * u[:, 1]) * (t_conv + window)
        pol = _RecordingCut(env.observation_layout(), t_cut, lags)
        period = env.observation_layout()["control_period_s"]
        final = run_first_episodes(env, pol, conds, seed + start)
        x_lag, t_rec = pol.obs, pol.t_rec
        keep = ~np.isnan(t_rec)
        rows = {
            "obs": x_lag[:, 0], "obs_lag": x_lag, "t_cut": t_rec,
            "completed": np.array(final["completed"], dtype=bool),
            "stalled": np.array(final["stalled"], dtype=bool),
            "final_position_m": np.array(final["position_m"], dtype=float),
            "stroke_time_s": np.array([np.nan if v is None else v
                                       for v in final["stroke_time_s"]], dtype=float),
            "conventional_time_s": np.array(final["conventional_stroke_time_s"], dtype=float),
            "energy_wasted_j": np.array(final["energy_wasted_j"], dtype=float),
            "energy_conventional_j": np.array(final["energy_conventional_j"], dtype=float),
            "saving_ratio": np.array(final["saving_ratio"], dtype=float),
            "stick_slip_events": np.array(final["stick_slip_events"], dtype=np.int64),
            "objective": np.array(final["objective"], dtype=float),
        }
        for key in conds[0].__dataclass_fields__:
            if key != "rig_changes":  # the rig itself is not a number (family presets)
                rows[key] = np.array([getattr(c, key) for c in conds], dtype=float)
        for key, val in rows.items():
            cols.setdefault(key, []).append(val[keep])
        bar.update(b)
    bar.close()
    out = {k: np.concatenate(v) for k, v in cols.items()}
    out["lag_s"] = np.asarray(lags, dtype=float) * float(period)
    return out


class _RecordingCut(TimedCutPolicy):
    """Cuts at ``t_cut_s`` and records each row's observations at its cut and ``lags`` control
    periods before it (a ring buffer of the recent observations)."""

    def __init__(self, layout: Mapping[str, Any], t_cut_s: np.ndarray, lags: Sequence[int]):
        super().__init__(layout, t_cut_s)
        self.lags = np.asarray(lags, dtype=np.int64)
        self._k = 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        a = super().act(obs)
        depth = int(self.lags[-1]) + 1
        if self._k == 0:
            self._ring = np.full((depth,) + obs.shape, np.nan, dtype=np.float32)
            self.obs = np.full((obs.shape[0], self.lags.size, obs.shape[1]), np.nan,
                               dtype=np.float32)
            self.t_rec = np.full(obs.shape[0], np.nan)
        self._ring[self._k % depth] = obs
        new = np.flatnonzero((a == 1) & np.isnan(self.t_rec))
        for j, lag in enumerate(self.lags):
            if self._k - lag >= 0:
                self.obs[new, j] = self._ring[(self._k - lag) % depth, new]
        self.t_rec[new] = self.read(obs, "time")[new]
        self._k += 1
        return a


def rollouts(cache_dir: str | Path | None, n: int, seed: int, history: int = 8,
             preset: str = "randomized", env_config: Mapping[str, Any] | None = None,
             lags: Sequence[int] = LAGS, progress: bool = True) -> dict[str, np.ndarray]:
    """:func:`generate_rollouts`, cached in ``cache_dir`` as ``.npz`` (written atomically) under
    a key of the arguments, the generator version and :func:`source_hash`."""
    spec = {"n": n, "seed": seed, "history": history, "preset": preset,
            "env_config": {k: repr(v) for k, v in sorted(dict(env_config or {}).items())},
            "lags": [int(k) for k in lags],
            "generator": GENERATOR_VERSION, "pneugym_sources": source_hash()}
    key = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    path = Path(cache_dir) / f"esac-rollouts-{key}.npz" if cache_dir else None
    if path is not None and path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files if k != "spec"}
    data = generate_rollouts(n, seed, history, preset, env_config, lags=lags, progress=progress)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, spec=np.array(json.dumps(spec)), **data)
        os.replace(tmp, path)
    return data


def targets(data: Mapping[str, np.ndarray], stroke_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Training targets ``(B, 2 + 5)``: completed, stick-slip (labels), final position / stroke,
    ``log(stroke time / conventional stroke time)``, conventional stroke time [s], wasted energy /
    conventional, conventional wasted energy [J]; and their mask (the time ratio only where the
    stroke completed)."""
    y = np.stack([
        data["completed"].astype(float), (data["stick_slip_events"] > 0).astype(float),
        data["final_position_m"] / stroke_m,
        np.log(np.nan_to_num(data["stroke_time_s"] / data["conventional_time_s"], nan=1.0)),
        data["conventional_time_s"],
        data["energy_wasted_j"] / data["energy_conventional_j"],
        data["energy_conventional_j"],
    ], axis=1)
    mask = np.ones_like(y)
    mask[:, 3] = data["completed"]
    return y.astype(np.float32), mask.astype(np.float32)


def samples(data: Mapping[str, np.ndarray], stroke_m: float, delay_input: bool = True
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Network inputs, targets, mask (:func:`targets`) and each sample's episode index. With
    ``delay_input`` every recorded lag of every episode is one sample, its input the observation
    ``Δ`` before the cut followed by ``Δ`` [s]; without, the observations at the cut only."""
    y, mask = targets(data, stroke_m)
    if not delay_input:
        return data["obs"].astype(np.float32), y, mask, np.arange(y.shape[0])
    xl = data["obs_lag"]
    b, nl, n = xl.shape
    ok = ~np.isnan(xl[:, :, 0])
    delay = np.broadcast_to(np.asarray(data["lag_s"], np.float32), (b, nl))
    x = np.concatenate([xl, delay[:, :, None]], axis=2)[ok]
    rows = np.broadcast_to(np.arange(b)[:, None], (b, nl))[ok]
    return x.astype(np.float32), y[rows], mask[rows], rows

