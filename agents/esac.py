"""ESAC, the Energy Saving Actuation Control the thesis proposes in 6.8 but never builds: a neural
network that, from the current sensor history, predicts what would happen if the supply were cut
**now** (or after a short delay), and a controller that cuts at the first instant the prediction
says the stroke completes with a safety margin and within the time demand, and that waiting
longer no longer pays.

**Predictor** (:class:`ESACNet`, :class:`ESACPredictor`). Input: the observation of
``pneugym/CutOff-v0`` with ``history=k`` (the last ``k`` samples of position, velocity, both port
pressures, supply set-point, time, cut flag) and, for a model with ``delay_input``, the delay
``Δ`` [s] before the cut. Outputs, for a cut at ``now + Δ``:

- ``p_complete``: probability that the piston still reaches the end of stroke;
- ``final_position_m``: where it ends (the stroke length if it completes);
- ``stroke_time_s``: when it arrives (from the extend command), if it completes;
- ``conventional_time_s``: when it would arrive without a cut (so ``time_increase`` =
  ``stroke_time_s / conventional_time_s - 1`` needs nothing the controller cannot see);
- ``wasted_fraction`` and ``wasted_energy_j``: the air energy left in the driving side (eq. 5.9),
  as a fraction of a conventional stroke's and in joules;
- ``p_stick``: probability of a stick-slip event on the way.

**Training data** (:func:`generate_rollouts`): episodes of the batched environment over the
``randomized`` conditions, each cut off at a random time; the episode's final figures label the
observation at the cut (``Δ = 0``) and the observations ``LAGS`` control periods before it (the
same outcome seen ``Δ`` earlier: before the cut an episode is the uncut one). Cached on disk
(:func:`rollouts`), keyed by the generator's settings and a hash of the plant's sources.

**Controller** (:class:`ESACPolicy`): cut when ``p_complete >= 1 - margin``, the predicted final
position is within ``tolerance_m`` of the stroke end, the predicted time increase is at most
``max_time_increase`` (the time demand), ``p_stick <= max_stick`` and, with ``lookahead``, no
predicted later cut (``Δ`` in the training lags) scores a better objective. ``margin`` is the
safety margin: the accepted predicted risk of an incomplete stroke. train.py tunes the rule on
validation conditions (training seeds), ``train.choose_decision``.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from .base import run_first_episodes
from .learned import LearnedPolicy
from .oracle import TimedCutPolicy

FORMAT = "pneugym-esac-1"
#: Classification heads (logits) and regression heads (standardised), in output order.
CLASS_HEADS = ("complete", "stick")
REG_HEADS = ("final_position", "log_time_ratio", "conventional_time_s", "wasted_fraction",
             "energy_conventional_j")
GENERATOR_VERSION = 3  # bump when generate_rollouts changes what it records
#: control periods before the cut at which an observation is also recorded (Δ = lag x period):
#: dense near the cut, up to 1.28 s, so that the lookahead sees the whole rest of a slow stroke
LAGS = (0, 2, 4, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)


# ------------------------------------------------------------------------------------------------
# data
# ------------------------------------------------------------------------------------------------
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
        for key in conds[0].to_dict():
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


# ------------------------------------------------------------------------------------------------
# network
# ------------------------------------------------------------------------------------------------
def _torch():
    import torch

    return torch


def make_net(n_in: int, hidden: Sequence[int] = (128, 128, 128)):
    """An MLP from the observation to ``2 + 5`` outputs (logits, standardised values), with the
    input and output normalisation as buffers (saved with the weights)."""
    torch = _torch()
    nn = torch.nn

    class ESACNet(nn.Module):
        def __init__(self):
            super().__init__()
            layers: list[nn.Module] = []
            last = n_in
            for h in hidden:
                layers += [nn.Linear(last, h), nn.SiLU()]
                last = h
            layers.append(nn.Linear(last, len(CLASS_HEADS) + len(REG_HEADS)))
            self.body = nn.Sequential(*layers)
            self.register_buffer("in_mean", torch.zeros(n_in))
            self.register_buffer("in_std", torch.ones(n_in))
            self.register_buffer("out_mean", torch.zeros(len(REG_HEADS)))
            self.register_buffer("out_std", torch.ones(len(REG_HEADS)))

        def forward(self, x):
            """Raw outputs: class logits, then standardised regression values."""
            return self.body((x - self.in_mean) / self.in_std)

    return ESACNet()


def fit(x: np.ndarray, y: np.ndarray, mask: np.ndarray, hidden: Sequence[int] = (128, 128, 128),
        epochs: int = 60, batch_size: int = 256, lr: float = 2e-3, weight_decay: float = 1e-5,
        val_fraction: float = 0.1, seed: int = 0, patience: int = 15, time_loss: str = "mse",
        groups: np.ndarray | None = None, progress: bool = True) -> tuple[Any, dict[str, Any]]:
    """Train the predictor on ``x`` (B, n_in), targets ``y`` and ``mask`` of :func:`targets`:
    binary cross-entropy on the class heads, mean squared error on the standardised regression
    heads (masked), AdamW with a one-cycle learning rate; keeps the weights of the best
    validation loss. The validation rows are a random ``val_fraction`` of the ``groups`` (episode
    of each row; default: each row its own), so that no episode is on both sides. ``time_loss="l1"``
    fits the time ratio's conditional median instead of its mean: sharper at the knee where a
    later cut stops lengthening the stroke (the mean smooths it into a bias). Returns the network
    and the loss history."""
    if time_loss not in ("mse", "l1"):
        raise ValueError(f"time_loss = {time_loss!r}: choose 'mse' or 'l1'")
    from tqdm import tqdm

    torch = _torch()
    nc = len(CLASS_HEADS)
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    g = np.arange(x.shape[0]) if groups is None else np.asarray(groups)
    uniq = rng.permutation(np.unique(g))
    nv = max(1, int(round(val_fraction * uniq.size)))
    is_val = np.isin(g, uniq[:nv])
    vi, ti = np.flatnonzero(is_val), rng.permutation(np.flatnonzero(~is_val))
    net = make_net(x.shape[1], hidden)
    xt = torch.as_tensor(x, dtype=torch.float32)
    yt = torch.as_tensor(y, dtype=torch.float32)
    mt = torch.as_tensor(mask, dtype=torch.float32)
    with torch.no_grad():
        net.in_mean[:] = xt[ti].mean(0)
        net.in_std[:] = xt[ti].std(0).clamp_min(1e-6)
        yr, mr = yt[ti, nc:], mt[ti, nc:]
        mean = (yr * mr).sum(0) / mr.sum(0).clamp_min(1.0)
        var = (((yr - mean) * mr) ** 2).sum(0) / mr.sum(0).clamp_min(1.0)
        net.out_mean[:] = mean
        net.out_std[:] = var.sqrt().clamp_min(1e-6)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    steps = epochs * max(1, math.ceil(ti.size / batch_size))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps,
                                                pct_start=0.1)

    def loss_of(rows):
        out = net(xt[rows])
        bce = torch.nn.functional.binary_cross_entropy_with_logits(out[:, :nc], yt[rows, :nc])
        z = (yt[rows, nc:] - net.out_mean) / net.out_std
        m = mt[rows, nc:]
        err = (out[:, nc:] - z) ** 2
        if time_loss == "l1":
            k = REG_HEADS.index("log_time_ratio")
            err = torch.cat([err[:, :k], (out[:, nc + k:nc + k + 1] - z[:, k:k + 1]).abs(),
                             err[:, k + 1:]], dim=1)
        return bce + (err * m).sum() / m.sum().clamp_min(1.0)

    hist: dict[str, Any] = {"train": [], "val": []}
    best, best_state, stale = math.inf, None, 0
    t0 = time.perf_counter()
    bar = tqdm(range(epochs), desc="ESAC fit", unit="epoch", disable=not progress)
    for _ in bar:
        net.train()
        perm = torch.as_tensor(ti)[torch.randperm(ti.size, generator=gen)]
        total = 0.0
        for k in range(0, ti.size, batch_size):
            rows = perm[k:k + batch_size]
            loss = loss_of(rows)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * rows.numel()
        net.eval()
        with torch.no_grad():
            val = loss_of(torch.as_tensor(vi)).item()
        hist["train"].append(total / ti.size)
        hist["val"].append(val)
        bar.set_postfix(train=f"{hist['train'][-1]:.4f}", val=f"{val:.4f}")
        if val < best - 1e-5:
            best, stale = val, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            stale += 1
            if stale >= patience:
                break
    if best_state is not None:
        net.load_state_dict(best_state)
    net.eval()
    hist.update(best_val=best, epochs_run=len(hist["val"]), fit_wall_s=time.perf_counter() - t0)
    return net, hist


class ESACPredictor:
    """The trained network with its units: :meth:`__call__` maps observations (in the model's
    layout) to the predicted outcome of cutting now, or ``delay_s`` later, in SI units.
    ``lookahead_s``: the delays the model was trained on (empty without ``delay_input``)."""

    def __init__(self, net, layout: Mapping[str, Any], delay_input: bool = False,
                 lookahead_s: Sequence[float] = ()):
        self.net = net
        self.layout = dict(layout)
        self.delay_input = bool(delay_input)
        self.lookahead_s = np.asarray([d for d in lookahead_s if d > 0], dtype=float)
        if self.delay_input != (net.in_mean.shape[0] == int(layout["size"]) + 1):
            raise ValueError(f"the network takes {net.in_mean.shape[0]} inputs: not the "
                             f"observation size {layout['size']}"
                             f"{' + 1 (delay)' if self.delay_input else ''}")
        feats = {f["name"]: f for f in layout["features"]}
        self.stroke_m = float(feats["position"]["scale"])

    def raw(self, x: np.ndarray) -> np.ndarray:
        """The network's outputs (class logits, regression values in units) for inputs ``x``."""
        torch = _torch()
        with torch.no_grad():
            out = self.net(torch.as_tensor(np.asarray(x, dtype=np.float32)))
            nc = len(CLASS_HEADS)
            out[:, nc:] = out[:, nc:] * self.net.out_std + self.net.out_mean
        return out.numpy().astype(np.float64)

    def __call__(self, obs: np.ndarray, delay_s: float | Sequence[float] | None = None
                 ) -> dict[str, np.ndarray]:
        """Predictions for observations ``obs`` (B, size): arrays of shape (B,), or (B, D) for a
        sequence of ``D`` delays [s] (models with ``delay_input`` only)."""
        obs = np.atleast_2d(np.asarray(obs, dtype=np.float32))
        b = obs.shape[0]
        shape: tuple[int, ...] = (b,)
        if self.delay_input:
            d = np.atleast_1d(np.asarray(0.0 if delay_s is None else delay_s, np.float32))
            if np.ndim(delay_s) == 1:
                shape = (b, d.size)
            x = np.concatenate([np.repeat(obs, d.size, axis=0),
                                np.tile(d, b)[:, None]], axis=1)
        elif delay_s is not None and np.any(np.asarray(delay_s) != 0):
            raise ValueError("this ESAC model predicts a cut now only (no delay input)")
        else:
            x = obs
        o = self.raw(x)
        p_c = 0.5 * (1.0 + np.tanh(0.5 * o[:, 0]))  # logistic, without overflow
        p_s = 0.5 * (1.0 + np.tanh(0.5 * o[:, 1]))
        xf, lr, tc, wf, ec = (o[:, 2 + k] for k in range(5))
        ratio = np.exp(np.minimum(lr, 5.0))
        out = {"p_complete": p_c, "p_stick": p_s,
               "final_position_m": np.minimum(xf, 1.0) * self.stroke_m,
               "stroke_time_s": ratio * tc, "conventional_time_s": tc,
               "time_increase": ratio - 1.0,
               "wasted_fraction": wf, "wasted_energy_j": wf * ec,
               "energy_conventional_j": ec}
        return {k: v.reshape(shape) for k, v in out.items()}


# ------------------------------------------------------------------------------------------------
# accuracy
# ------------------------------------------------------------------------------------------------
def accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Prediction errors on a rollout set (held-out conditions): completion accuracy, final
    position, stroke time, time increase and wasted energy."""
    p = pred(data["obs"])
    comp = data["completed"].astype(bool)
    c_hat = p["p_complete"] >= 0.5
    stall = ~comp
    out: dict[str, Any] = {
        "samples": int(comp.size), "completed_share": float(comp.mean()),
        "completion_accuracy": float((c_hat == comp).mean()),
        "false_complete_rate": float((c_hat & stall).sum() / max(1, stall.sum())),
        "final_position_mae_mm": float(np.mean(np.abs(p["final_position_m"]
                                                      - data["final_position_m"])) * 1e3),
        "final_position_mae_mm_incomplete": float(np.mean(np.abs(
            p["final_position_m"][stall] - data["final_position_m"][stall])) * 1e3)
        if stall.any() else None,
        "wasted_fraction_mae": float(np.mean(np.abs(
            p["wasted_fraction"] - data["energy_wasted_j"] / data["energy_conventional_j"]))),
        "wasted_energy_mae_j": float(np.mean(np.abs(p["wasted_energy_j"]
                                                    - data["energy_wasted_j"]))),
        "conventional_time_mae_ms": float(np.mean(np.abs(p["conventional_time_s"]
                                                         - data["conventional_time_s"])) * 1e3),
        "stick_accuracy": float(((p["p_stick"] >= 0.5) == (data["stick_slip_events"] > 0))
                                .mean()),
    }
    if comp.any():
        t_true = data["stroke_time_s"][comp]
        ti_true = t_true / data["conventional_time_s"][comp] - 1.0
        err = p["stroke_time_s"][comp] - t_true
        out.update(
            stroke_time_mae_ms=float(np.mean(np.abs(err)) * 1e3),
            stroke_time_median_ae_ms=float(np.median(np.abs(err)) * 1e3),
            stroke_time_mape=float(np.mean(np.abs(err) / t_true)),
            time_increase_mae=float(np.mean(np.abs(p["time_increase"][comp] - ti_true))))
        # the region the controller decides in: completing cuts with at most +50 % time
        near = ti_true <= 0.5
        if near.any():
            out["stroke_time_mae_ms_within_50pct"] = float(np.mean(np.abs(err[near])) * 1e3)
            out["time_increase_mae_within_50pct"] = float(np.mean(np.abs(
                p["time_increase"][comp][near] - ti_true[near])))
    if pred.delay_input and "obs_lag" in data:
        out["by_delay"] = [_delay_accuracy(pred, data, j) for j in range(len(data["lag_s"]))]
    return out


def _delay_accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray], j: int
                    ) -> dict[str, Any]:
    """Errors of the predictions made ``lag_s[j]`` before the cut (lookahead rule's inputs)."""
    ok = ~np.isnan(data["obs_lag"][:, j, 0])
    delay = float(data["lag_s"][j])
    if not ok.any():  # no cut came this long after the episode began
        return {"delay_s": delay, "samples": 0}
    p = pred(data["obs_lag"][ok, j], delay)
    comp = data["completed"][ok].astype(bool)
    wf = data["energy_wasted_j"][ok] / data["energy_conventional_j"][ok]
    row = {"delay_s": delay, "samples": int(ok.sum()),
           "completion_accuracy": float(((p["p_complete"] >= 0.5) == comp).mean()),
           "wasted_fraction_mae": float(np.mean(np.abs(p["wasted_fraction"] - wf)))}
    ti = data["stroke_time_s"][ok][comp] / data["conventional_time_s"][ok][comp] - 1.0
    near = ti <= 0.5
    if near.any():
        row["time_increase_mae_within_50pct"] = float(np.mean(np.abs(
            p["time_increase"][comp][near] - ti[near])))
    return row


def plot_accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray], path: str | Path,
                  title: str = "ESAC on held-out conditions") -> None:
    """Predicted vs simulated: completion probability vs cut time, final position, stroke time
    and wasted energy (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = pred(data["obs"])
    comp = data["completed"].astype(bool)
    fig, ax = plt.subplots(2, 2, figsize=(9, 7.5))
    rel_t = data["t_cut"] / data["conventional_time_s"]
    ax[0, 0].scatter(rel_t[comp], p["p_complete"][comp], s=3, alpha=0.3, label="completed")
    ax[0, 0].scatter(rel_t[~comp], p["p_complete"][~comp], s=3, alpha=0.3, label="incomplete")
    ax[0, 0].set_xlabel("cut time / conventional stroke time")
    ax[0, 0].set_ylabel("predicted P(complete)")
    ax[0, 0].legend(fontsize=8, markerscale=3)
    s = pred.stroke_m * 1e3
    ax[0, 1].scatter(data["final_position_m"] * 1e3, p["final_position_m"] * 1e3, s=3, alpha=0.3)
    ax[0, 1].plot([0, s], [0, s], "k--", lw=0.8)
    ax[0, 1].set_xlabel("final position, simulated [mm]")
    ax[0, 1].set_ylabel("predicted [mm]")
    t = data["stroke_time_s"][comp]
    ax[1, 0].scatter(t, p["stroke_time_s"][comp], s=3, alpha=0.3)
    lim = [float(np.nanmin(t)), float(min(np.nanmax(t), 4.0))] if comp.any() else [0, 4]
    ax[1, 0].plot(lim, lim, "k--", lw=0.8)
    ax[1, 0].set_xlabel("stroke time, simulated [s] (completed strokes)")
    ax[1, 0].set_ylabel("predicted [s]")
    wf = data["energy_wasted_j"] / data["energy_conventional_j"]
    ax[1, 1].scatter(wf, p["wasted_fraction"], s=3, alpha=0.3)
    ax[1, 1].plot([0, 1.05], [0, 1.05], "k--", lw=0.8)
    ax[1, 1].set_xlabel("wasted energy / conventional, simulated")
    ax[1, 1].set_ylabel("predicted")
    for a in ax.flat:
        a.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------
# controller
# ------------------------------------------------------------------------------------------------
RULE_DEFAULTS = {"margin": 0.05, "max_time_increase": 0.2, "max_stick": 0.5,
                 "tolerance_m": 0.002, "lookahead": 0, "w_time": 0.3, "w_stick": 0.5,
                 "w_stall": 2.0, "hysteresis": 0.0}
#: every rule parameter: (lowest, highest, what it is); ``lookahead`` is a flag (0 or 1),
#: ``time_demand_s`` (optional, None: use ``max_time_increase``) must be > 0
RULE_PARAMETERS = {
    "margin": (0.0, 1.0, "the accepted predicted risk of an incomplete stroke, a probability "
                         "in [0, 1]"),
    "max_time_increase": (0.0, math.inf, "the time demand, a predicted stroke-time increase "
                                         ">= 0 (0.1: +10 %)"),
    "max_stick": (0.0, 1.0, "the accepted stick-slip risk, a probability in [0, 1]"),
    "tolerance_m": (0.0, math.inf, "how close to the stroke end the predicted final position "
                                   "must be, metres >= 0"),
    "lookahead": (0, 1, "0 (cut as soon as rules 1-3 hold) or 1 (and only once waiting no "
                        "longer pays)"),
    "w_time": (0.0, math.inf, "the objective's weight of the time increase, >= 0"),
    "w_stick": (0.0, math.inf, "the objective's weight of a stick-slip event, >= 0"),
    "w_stall": (0.0, math.inf, "the objective's weight of a stall, >= 0"),
    "hysteresis": (0.0, math.inf, "how much better a later cut must predict, >= 0"),
    "time_demand_s": (0.0, math.inf, "an absolute time demand, seconds > 0 (or none)"),
}


def _rule_number(name: str, v: Any) -> Any:
    """``v`` for rule parameter ``name`` if valid (``lookahead`` as an int), else raises
    ValueError without a location (see :func:`check_rule`)."""
    lo, hi, what = RULE_PARAMETERS[name]
    try:
        ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
            and math.isfinite(float(v)) and lo <= float(v) <= hi
    except OverflowError:  # an integer beyond any float
        ok = False
    if name == "lookahead":
        ok = (isinstance(v, (bool, np.bool_)) or ok) and float(v) in (0.0, 1.0)
        if ok:
            return int(v)
    elif name == "time_demand_s":
        ok = ok and float(v) > 0
    if not ok:
        raise ValueError(f"{v!r}: expected {what}")
    return v


def check_rule(params: Mapping[str, Any], where: str, per_row: bool = False) -> dict[str, Any]:
    """ESAC rule parameters (a model's saved rule, an override, a config's grid), checked: known
    names (:data:`RULE_PARAMETERS`, with the nearest for a typo), each a finite number in its
    range (``lookahead`` 0 or 1, ``time_demand_s`` > 0 or None). With ``per_row`` a parameter
    may be an array with one value per observation row. Returns them (``lookahead`` as ints);
    raises ValueError naming ``where`` and the parameter."""
    from pneugym.params import did_you_mean

    if not isinstance(params, Mapping):
        raise ValueError(f"{where} is {params!r}; expected an object of rule parameters "
                         f"({', '.join(RULE_PARAMETERS)})")
    out: dict[str, Any] = {}
    for name, v in params.items():
        if name not in RULE_PARAMETERS:
            raise ValueError(f"{where}: {name!r} is not an ESAC rule parameter"
                             f"{did_you_mean(name, RULE_PARAMETERS)}; they are "
                             f"{', '.join(RULE_PARAMETERS)}")
        if name == "time_demand_s" and v is None:
            out[name] = None
            continue
        try:
            if per_row and isinstance(v, (list, tuple, np.ndarray)) and np.ndim(v) == 1:
                vals = [_rule_number(name, x) for x in np.asarray(v).tolist()]
                out[name] = np.asarray(vals, dtype=np.int64 if name == "lookahead" else float)
            else:
                out[name] = _rule_number(name, v.item() if isinstance(v, np.ndarray)
                                         and v.ndim == 0 else v)
        except ValueError as exc:
            raise ValueError(f"{where}: {name} = {exc}") from None
    return out


class ESACPolicy(LearnedPolicy):
    """The ESAC controller (thesis 6.8): cut off at the first instant the predictor says

    1. the stroke completes with the safety ``margin``: predicted risk of an incomplete stroke at
       most ``margin``, predicted final position within ``tolerance_m`` of the stroke end;
    2. within the time demand: predicted stroke time at most ``1 + max_time_increase`` times the
       predicted conventional one (or at most ``time_demand_s`` seconds if given);
    3. with a predicted stick-slip risk of at most ``max_stick``;
    4. and, with ``lookahead`` (a model with ``delay_input``), that waiting no longer pays: no cut
       ``Δ`` later (``Δ`` in the predictor's ``lookahead_s``) has a predicted objective
       (:meth:`objective`) more than ``hysteresis`` above that of cutting now. The time demand
       is then a bound, and the trade-off inside it is the objective's (``w_time``,
       ``w_stick``, ``w_stall``).

    Without ``lookahead`` (the thesis's rule) it cuts as soon as 1-3 hold, i.e. as late as the
    time demand allows. Every parameter may be an array with one value per observation row
    (sweeps). ``last_prediction`` holds the predictions (cut now) of the last call.
    """

    name = "esac"

    def __init__(self, env_layout: Mapping[str, Any], predictor: ESACPredictor,
                 margin: float | np.ndarray = RULE_DEFAULTS["margin"],
                 max_time_increase: float | np.ndarray = RULE_DEFAULTS["max_time_increase"],
                 max_stick: float | np.ndarray = RULE_DEFAULTS["max_stick"],
                 tolerance_m: float | np.ndarray = RULE_DEFAULTS["tolerance_m"],
                 lookahead: int | np.ndarray = RULE_DEFAULTS["lookahead"],
                 w_time: float | np.ndarray = RULE_DEFAULTS["w_time"],
                 w_stick: float | np.ndarray = RULE_DEFAULTS["w_stick"],
                 w_stall: float | np.ndarray = RULE_DEFAULTS["w_stall"],
                 hysteresis: float | np.ndarray = RULE_DEFAULTS["hysteresis"],
                 time_demand_s: float | np.ndarray | None = None, source: str = "the ESAC model"):
        super().__init__(env_layout, predictor.layout, source)
        self.predictor = predictor
        rule = check_rule({"margin": margin, "max_time_increase": max_time_increase,
                           "max_stick": max_stick, "tolerance_m": tolerance_m,
                           "lookahead": lookahead, "w_time": w_time, "w_stick": w_stick,
                           "w_stall": w_stall, "hysteresis": hysteresis,
                           "time_demand_s": time_demand_s}, f"{source}: rule", per_row=True)
        margin, lookahead = rule["margin"], rule["lookahead"]
        self.margin = np.asarray(margin, dtype=float)
        self.max_time_increase = np.asarray(max_time_increase, dtype=float)
        self.max_stick = np.asarray(max_stick, dtype=float)
        self.tolerance_m = np.asarray(tolerance_m, dtype=float)
        self.lookahead = np.asarray(lookahead).astype(np.int64)
        self.w_time = np.asarray(w_time, dtype=float)
        self.w_stick = np.asarray(w_stick, dtype=float)
        self.w_stall = np.asarray(w_stall, dtype=float)
        self.hysteresis = np.asarray(hysteresis, dtype=float)
        self.time_demand_s = None if time_demand_s is None else np.asarray(time_demand_s, float)
        if np.any(self.lookahead != 0) and predictor.lookahead_s.size == 0:
            raise ValueError(f"{source} predicts a cut now only: lookahead needs a model "
                             f"trained with delay_input (train.py, esac fit.delay_input)")
        names = [f["name"] for f in predictor.layout["features"]]
        h = int(predictor.layout["history"])
        self._cut_index = (h - 1) * len(names) + names.index("supply_cut")
        self.last_prediction: dict[str, np.ndarray] | None = None

    def rule(self) -> dict[str, Any]:
        """The controller's parameters (the safety ``margin`` among them)."""
        out = {k: getattr(self, k).tolist() for k in RULE_DEFAULTS}
        if self.time_demand_s is not None:
            out["time_demand_s"] = self.time_demand_s.tolist()
        return out

    def _col(self, v: np.ndarray, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """A per-row parameter shaped to broadcast against predictions ``p`` (B,) or (B, D)."""
        ref = p["p_complete"]
        return v.reshape(v.shape + (1,) * (ref.ndim - v.ndim)) if v.ndim == 1 else v

    def objective(self, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """The predicted objective of the cut ``p`` describes: the env's ``-wasted_fraction -
        w_time * time_increase - w_stick * stick-slip``, with the stall risk at ``w_stall``."""
        c = functools.partial(self._col, p=p)
        return (-p["wasted_fraction"] - c(self.w_time) * np.maximum(p["time_increase"], 0.0)
                - c(self.w_stick) * p["p_stick"] - c(self.w_stall) * (1.0 - p["p_complete"]))

    def safe(self, p: Mapping[str, np.ndarray]) -> np.ndarray:
        """Rule 1: the stroke completes with the margin."""
        c = functools.partial(self._col, p=p)
        return ((p["p_complete"] >= 1.0 - c(self.margin))
                & (p["final_position_m"] >= self.predictor.stroke_m - c(self.tolerance_m)))

    def decide(self, p: Mapping[str, np.ndarray], later: Mapping[str, np.ndarray] | None = None
               ) -> np.ndarray:
        """The cut decision for predictions ``p`` of a cut now and, for rule 4, ``later`` ones
        (B, D) of cuts after the lookahead delays."""
        ok = self.safe(p)
        if self.time_demand_s is not None:
            ok &= p["stroke_time_s"] <= self.time_demand_s
        else:
            ok &= p["time_increase"] <= self.max_time_increase
        ok &= p["p_stick"] <= self.max_stick
        if later is not None:
            j_later = np.where(self.safe(later), self.objective(later), -np.inf).max(axis=1)
            waiting_pays = j_later > self.objective(p) + self.hysteresis
            ok &= ~((np.broadcast_to(self.lookahead, ok.shape) != 0) & waiting_pays)
        return ok

    def act_model(self, obs: np.ndarray) -> np.ndarray:
        p = self.predictor(obs)
        self.last_prediction = p
        later = None
        if np.any(self.lookahead != 0):
            later = self.predictor(obs, self.predictor.lookahead_s)
        already = obs[:, self._cut_index] > 0.5
        return (self.decide(p, later) | already).astype(np.int64)


# ------------------------------------------------------------------------------------------------
# saving and loading
# ------------------------------------------------------------------------------------------------
def save(path: str | Path, net, meta: Mapping[str, Any]) -> None:
    """Write the weights and ``meta`` (JSON-able: layout, architecture, rule, provenance) in one
    file, atomically."""
    torch = _torch()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    torch.save({"format": FORMAT, "state_dict": net.state_dict(),
                "meta": json.dumps(dict(meta), allow_nan=False)}, tmp)
    os.replace(tmp, path)


def is_esac_file(path: str | Path) -> bool:
    """True if ``path`` looks like a saved ESAC model (a torch file, not an SB3 zip)."""
    import zipfile

    p = Path(path)
    if not p.is_file():
        return False
    if p.suffix == ".pt":
        return True
    if not zipfile.is_zipfile(p):
        return False
    with zipfile.ZipFile(p) as z:
        return "data" not in z.namelist()


#: bounds of an ESAC network a model file may describe (the default is 3 x 128)
MAX_HIDDEN_WIDTH = 4096
MAX_HIDDEN_LAYERS = 16
#: the metadata (``data.pkl`` in the torch file) and the whole file, inflated
MAX_META_BYTES = 16 << 20
MAX_FILE_BYTES = 1 << 30


def _read_blob(path: Path) -> tuple[dict[str, Any], int]:
    """The saved dictionary of an ESAC model (tensors and strings only: ``weights_only``), and
    the bytes its entries hold once inflated (sizes checked before anything is read)."""
    import zipfile

    from .safe_load import check_zip_sizes

    torch = _torch()
    if not path.is_file():
        raise FileNotFoundError(f"no ESAC model at {path}")
    stored = path.stat().st_size
    if stored > MAX_FILE_BYTES:
        raise ValueError(f"{path} is {stored:,} bytes; pneugym reads ESAC models of up to "
                         f"{MAX_FILE_BYTES:,} bytes")
    if zipfile.is_zipfile(path):
        try:
            with zipfile.ZipFile(path) as z:
                stored = sum(check_zip_sizes(path, z, "ESAC model",
                                             limits={"data.pkl": MAX_META_BYTES},
                                             total=MAX_FILE_BYTES).values())
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise ValueError(f"{path} is not a readable ESAC model: {exc}") from None
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for a damaged file
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        raise ValueError(f"{path} is not a readable ESAC model (a torch file written by "
                         f"train.py --algo esac): {type(exc).__name__}: {first}. Is it "
                         f"truncated, or another kind of file?") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ValueError(f"{path} is not an ESAC model ({FORMAT})")
    return blob, stored


def torch_isfinite_all(t) -> bool:
    """True if every entry of tensor ``t`` is finite."""
    return bool(_torch().isfinite(t).all())


def _meta_error(path: Path, key: str, value: Any, expected: str) -> ValueError:
    r = repr(value)
    return ValueError(f"{path}: its metadata's {key} is {r if len(r) <= 80 else r[:80] + '...'};"
                      f" expected {expected} (not an ESAC model train.py wrote, or altered)")


def _read_meta(path: Path, blob: Mapping[str, Any]) -> dict[str, Any]:
    """The metadata of an ESAC model, checked before anything is built from it: ``n_in`` and
    ``hidden`` (bounded: :data:`MAX_HIDDEN_WIDTH`, :data:`MAX_HIDDEN_LAYERS`), the observation
    ``layout`` (:func:`agents.learned.check_layout_record`) and ``n_in`` consistent with it,
    ``delay_input``, ``lookahead_s`` and the tuned ``rule`` (:func:`check_rule`). ValueError
    (:class:`~agents.learned.LayoutMismatchError` for the layout) names the file and key."""
    from .learned import check_layout_record, is_finite_number

    try:
        meta = json.loads(blob["meta"])
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: its metadata is missing or not JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: its metadata is JSON nested too deeply (not an ESAC model "
                         f"train.py wrote)") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit
        raise ValueError(f"{path}: its metadata is not the JSON train.py writes: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: its metadata is a JSON {type(meta).__name__}; expected an "
                         f"object (n_in, hidden, layout, rule, ...)")

    def count(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    n_in = meta.get("n_in")
    if not count(n_in) or n_in <= 0:
        raise _meta_error(path, "n_in", n_in, "the network's input size, an integer > 0")
    hidden = meta.get("hidden")
    if not (isinstance(hidden, list) and len(hidden) <= MAX_HIDDEN_LAYERS and all(
            count(h) and 1 <= h <= MAX_HIDDEN_WIDTH for h in hidden)):
        raise _meta_error(path, "hidden", hidden, f"a list of at most {MAX_HIDDEN_LAYERS} layer "
                          f"widths from 1 to {MAX_HIDDEN_WIDTH}")
    if "layout" not in meta:
        raise _meta_error(path, "layout", None, "the observation layout it was trained on")
    layout = check_layout_record(meta["layout"], f"{path}: its metadata's layout")
    delay_input = meta.get("delay_input", False)
    if not isinstance(delay_input, bool):
        raise _meta_error(path, "delay_input", delay_input, "true or false")
    if n_in != int(layout["size"]) + int(delay_input):
        raise _meta_error(path, "n_in", n_in, f"{int(layout['size']) + int(delay_input)}: the "
                          f"layout's size {layout['size']}"
                          f"{' + 1 (the delay input)' if delay_input else ''}")
    look = meta.get("lookahead_s", [])
    if not (isinstance(look, list) and len(look) <= 1000 and all(
            is_finite_number(d) and 0 <= d <= 3600 for d in look)):
        raise _meta_error(path, "lookahead_s", look, "a list of delays in seconds (finite, 0 to "
                          "3600)")
    if "rule" in meta:
        meta["rule"] = check_rule(meta["rule"], f"{path}: its metadata's rule")
    return meta


def load(path: str | Path) -> tuple[ESACPredictor, dict[str, Any]]:
    """The predictor and the metadata of a saved ESAC model. Only tensors and strings are read
    (``torch.load(weights_only=True)``); a damaged file, another kind of file or metadata out of
    bounds (:func:`_read_meta`) is a ValueError naming it, raised before the network is built.
    """
    path = Path(path)
    blob, stored = _read_blob(path)
    meta = _read_meta(path, blob)
    widths = [int(meta["n_in"]), *meta["hidden"], len(CLASS_HEADS) + len(REG_HEADS)]
    need = 4 * sum(a * b + b for a, b in zip(widths, widths[1:]))
    if need > stored:
        raise ValueError(f"{path}: its metadata describes a network (n_in {meta['n_in']}, hidden "
                         f"{meta['hidden']}) of {need:,} bytes of weights, but the file holds "
                         f"{stored:,}: altered or damaged; pneugym does not build it")
    net = make_net(int(meta["n_in"]), meta["hidden"])
    try:
        net.load_state_dict(blob.get("state_dict"))
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        raise ValueError(f"{path}: its weights do not fit the network its metadata describes "
                         f"(n_in {meta['n_in']}, hidden {meta['hidden']}): {first}") from None
    state = net.state_dict()
    bad = [k for k, t in state.items() if not torch_isfinite_all(t)]
    bad += [k for k in ("in_std", "out_std") if k not in bad and not bool((state[k] > 0).all())]
    if bad:
        raise ValueError(f"{path}: its weights {bad} hold NaN, infinite or (for a scale) "
                         f"non-positive values: a damaged file; retrain it")
    net.eval()
    return ESACPredictor(net, meta["layout"], meta.get("delay_input", False),
                         meta.get("lookahead_s", ())), meta


def load_policy(path: str | Path, env_layout: Mapping[str, Any], **rule: Any) -> ESACPolicy:
    """The ESAC controller saved at ``path`` for an environment of ``env_layout``, with the saved
    (tuned) rule unless overridden by ``rule``."""
    from pneugym.params import did_you_mean

    unknown = sorted(set(rule) - set(RULE_PARAMETERS))
    if unknown:
        raise ValueError(f"unknown ESAC rule parameter(s) {unknown}"
                         f"{did_you_mean(unknown[0], RULE_PARAMETERS)}; choose from "
                         f"{list(RULE_PARAMETERS)}")
    rule = check_rule(rule, f"ESAC model {path}: the rule override")
    pred, meta = load(path)
    params = {**RULE_DEFAULTS, **meta.get("rule", {}), **rule}
    return ESACPolicy(env_layout, pred, source=f"ESAC model {path}", **params)


# ------------------------------------------------------------------------------------------------
# tuning the rule
# ------------------------------------------------------------------------------------------------
def sweep_rule(predictor: ESACPredictor, conditions: Sequence[Any], grid: Iterable[Mapping],
               env_config: Mapping[str, Any] | None = None, seed: int = 0
               ) -> list[dict[str, Any]]:
    """Mean return of the controller for each rule in ``grid`` on ``conditions`` (one batched
    run of ``len(grid) * len(conditions)`` episodes)."""
    from pneugym.envs.cutoff import CutOffVectorEnv

    grid = list(grid)
    nc = len(conditions)
    cfg = {**dict(env_config or {}), "history": int(predictor.layout["history"])}
    env = CutOffVectorEnv(num_envs=nc * len(grid), autoreset=False, **cfg)
    arrays = {k: np.repeat([g.get(k, RULE_DEFAULTS[k]) for g in grid], nc)
              for k in RULE_DEFAULTS}
    pol = ESACPolicy(env.observation_layout(), predictor, **arrays)
    out = run_first_episodes(env, pol, list(conditions) * len(grid), seed)
    res = []
    for k, g in enumerate(grid):
        s = slice(k * nc, (k + 1) * nc)
        res.append({**{kk: float(v) for kk, v in g.items()},
                    "return": float(np.mean(out["objective"][s])),
                    "stall_rate": float(np.mean(out["stalled"][s])),
                    "saving": float(np.mean(out["saving_ratio"][s]))})
    return res

