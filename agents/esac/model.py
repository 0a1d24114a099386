"""ESAC's predictor: the network (:func:`make_net`), its training (:func:`fit`) and
:class:`ESACPredictor`, which maps observations to the predicted outcome of a cut now, or ``Δ``
later, in SI units.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np

#: Classification heads (logits) and regression heads (standardised), in output order.
CLASS_HEADS = ("complete", "stick")
REG_HEADS = ("final_position", "log_time_ratio", "conventional_time_s", "wasted_fraction",
             "energy_conventional_j")


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
        groups: np.ndarray | None = None, progress: bool = True, init: Any = None
        ) -> tuple[Any, dict[str, Any]]:
    """Train the predictor on ``x`` (B, n_in), targets ``y`` and ``mask`` of
    :func:`~agents.esac.data.targets`: binary cross-entropy on the class heads, mean squared
    error on the standardised regression heads (masked), AdamW with a one-cycle learning rate;
    keeps the weights of the best validation loss. The validation rows are a random
    ``val_fraction`` of the ``groups`` (episode of each row; default: each row its own), so that
    no episode is on both sides. ``time_loss="l1"`` fits the time ratio's conditional median
    instead of its mean: sharper at the knee where a later cut stops lengthening the stroke (the
    mean smooths it into a bias). ``init``: a trained network to fine-tune (a copy is trained; its
    input and output normalisation are kept, so that its units stay those it was trained in).
    Returns the network and the loss history."""
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
    xt = torch.as_tensor(x, dtype=torch.float32)
    yt = torch.as_tensor(y, dtype=torch.float32)
    mt = torch.as_tensor(mask, dtype=torch.float32)
    if init is not None:
        import copy

        net = copy.deepcopy(init)
        if int(net.in_mean.shape[0]) != x.shape[1]:
            raise ValueError(f"init takes {int(net.in_mean.shape[0])} inputs, the samples have "
                             f"{x.shape[1]}")
    else:
        net = make_net(x.shape[1], hidden)
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
        return _loss(net, xt[rows], yt[rows], mt[rows], time_loss)

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


def _loss(net, x, y, m, time_loss: str = "mse"):
    """The training loss (a torch scalar) of ``net`` on inputs ``x``, targets ``y``, mask ``m``:
    binary cross-entropy of the class heads plus the masked mean squared error of the
    standardised regression heads (absolute error on the time ratio with ``time_loss="l1"``)."""
    torch = _torch()
    nc = len(CLASS_HEADS)
    out = net(x)
    bce = torch.nn.functional.binary_cross_entropy_with_logits(out[:, :nc], y[:, :nc])
    z = (y[:, nc:] - net.out_mean) / net.out_std
    mr = m[:, nc:]
    err = (out[:, nc:] - z) ** 2
    if time_loss == "l1":
        k = REG_HEADS.index("log_time_ratio")
        err = torch.cat([err[:, :k], (out[:, nc + k:nc + k + 1] - z[:, k:k + 1]).abs(),
                         err[:, k + 1:]], dim=1)
    return bce + (err * mr).sum() / mr.sum().clamp_min(1.0)


def loss(net, x: np.ndarray, y: np.ndarray, mask: np.ndarray, time_loss: str = "mse") -> float:
    """:func:`fit`'s loss of ``net`` on samples ``x``, ``y``, ``mask`` (e.g. of a held-out
    record), without training."""
    torch = _torch()
    with torch.no_grad():
        return float(_loss(net, torch.as_tensor(x, dtype=torch.float32),
                           torch.as_tensor(y, dtype=torch.float32),
                           torch.as_tensor(mask, dtype=torch.float32), time_loss))


class ESACPredictor:
    """The trained network with its units: :meth:`__call__` maps observations (in the model's
    layout) to the predicted outcome of cutting now, or ``delay_s`` later, in SI units.
    ``lookahead_s``: the delays the model was trained on (empty without ``delay_input``).

    ``backend`` evaluates the network: a callable from float32 inputs (B, n_in) to its float32
    raw outputs (B, 7: class logits, standardised regression values), the input normalisation
    included; default (None) the torch ``net`` (:meth:`torch_forward`). It is the only place
    the network runs (:mod:`pneugym.deploy.export` swaps it for onnxruntime or numpy). ``net``
    then needs only its normalisation buffers ``in_mean`` (n_in,), ``out_mean`` and
    ``out_std`` (5,): the regression heads are de-standardised in :meth:`raw`."""

    def __init__(self, net, layout: Mapping[str, Any], delay_input: bool = False,
                 lookahead_s: Sequence[float] = (),
                 backend: Callable[[np.ndarray], np.ndarray] | None = None):
        self.net = net
        self.layout = dict(layout)
        self.delay_input = bool(delay_input)
        self.lookahead_s = np.asarray([d for d in lookahead_s if d > 0], dtype=float)
        self.n_in = int(net.in_mean.shape[0])
        if self.delay_input != (self.n_in == int(layout["size"]) + 1):
            raise ValueError(f"the network takes {self.n_in} inputs: not the "
                             f"observation size {layout['size']}"
                             f"{' + 1 (delay)' if self.delay_input else ''}")
        feats = {f["name"]: f for f in layout["features"]}
        self.stroke_m = float(feats["position"]["scale"])
        self._backend = backend

    @property
    def backend(self) -> Callable[[np.ndarray], np.ndarray]:
        """The network evaluation: float32 (B, n_in) -> float32 raw outputs (B, 7)."""
        return self._backend if self._backend is not None else self.torch_forward

    @backend.setter
    def backend(self, fn: Callable[[np.ndarray], np.ndarray] | None) -> None:
        self._backend = fn

    def torch_forward(self, x: np.ndarray) -> np.ndarray:
        """The torch network's raw outputs (B, 7) [float32] for float32 inputs ``x`` (B, n_in)."""
        torch = _torch()
        with torch.no_grad():
            return self.net(torch.as_tensor(x)).numpy()

    def raw(self, x: np.ndarray) -> np.ndarray:
        """The network's outputs (class logits, regression values in units) for inputs ``x``."""
        out = np.array(self.backend(np.ascontiguousarray(x, dtype=np.float32)), dtype=np.float32)
        nc = len(CLASS_HEADS)
        # float32, as the network's buffers: the same numbers whichever backend ran it
        out[:, nc:] = (out[:, nc:] * np.asarray(self.net.out_std, dtype=np.float32)
                       + np.asarray(self.net.out_mean, dtype=np.float32))
        return out.astype(np.float64)

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

