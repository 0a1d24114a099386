"""ESAC's predictor: the network (:func:`make_net`), its training (:func:`fit`) and
:class:`ESACPredictor`, which maps observations to the predicted outcome of a cut now, or ``Δ``
later, in SI units.
"""
from __future__ import annotations

import functools
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


#: How an ensemble combines its members' outputs, head by head (:class:`ESACEnsemble`): the
#: worst member for every head the rule's safety and objective read, the mean for the two the
#: rule only divides by (the conventional stroke's time and energy).
ENSEMBLE_COMBINE = {"complete": "min", "stick": "max", "final_position": "min",
                    "log_time_ratio": "max", "conventional_time_s": "mean",
                    "wasted_fraction": "max", "energy_conventional_j": "mean"}
#: the most members a model may have
MAX_MEMBERS = 32


def _body(n_in: int, hidden: Sequence[int]):
    """The MLP from the normalised observation to the ``2 + 5`` raw outputs."""
    nn = _torch().nn
    layers: list[Any] = []
    last = n_in
    for h in hidden:
        layers += [nn.Linear(last, h), nn.SiLU()]
        last = h
    layers.append(nn.Linear(last, len(CLASS_HEADS) + len(REG_HEADS)))
    return nn.Sequential(*layers)


def _norm_buffers(module, n_in: int) -> None:
    """The input and output normalisation, as buffers (saved with the weights)."""
    torch = _torch()
    module.register_buffer("in_mean", torch.zeros(n_in))
    module.register_buffer("in_std", torch.ones(n_in))
    module.register_buffer("out_mean", torch.zeros(len(REG_HEADS)))
    module.register_buffer("out_std", torch.ones(len(REG_HEADS)))


def _copy_norm(dst, src) -> None:
    """``src``'s input and output normalisation into ``dst``'s buffers."""
    with _torch().no_grad():
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            getattr(dst, name).copy_(getattr(src, name))


def _check_members(members: Any) -> int:
    if not (isinstance(members, int) and 1 <= members <= MAX_MEMBERS):
        raise ValueError(f"members = {members!r}: an ESAC ensemble has 1 to {MAX_MEMBERS} "
                         f"networks")
    return members


def make_net(n_in: int, hidden: Sequence[int] = (128, 128, 128), members: int = 1):
    """An MLP from the observation to ``2 + 5`` outputs (logits, standardised values), with the
    input and output normalisation as buffers (saved with the weights); with ``members > 1``
    an :class:`ESACEnsemble` of that many MLPs sharing the normalisation."""
    nn = _torch().nn
    _check_members(members)

    class ESACNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.body = _body(n_in, hidden)
            _norm_buffers(self, n_in)

        def forward(self, x):
            """Raw outputs: class logits, then standardised regression values."""
            return self.body((x - self.in_mean) / self.in_std)

    if members == 1:
        return ESACNet()
    return _ensemble_class()([_body(n_in, hidden) for _ in range(members)])


@functools.cache
def _ensemble_class():
    nn = _torch().nn
    torch = _torch()
    heads = (*CLASS_HEADS, *REG_HEADS)

    class ESACEnsemble(nn.Module):
        """``members`` MLPs (:func:`make_net`'s bodies) on one input and output normalisation;
        :meth:`forward` gives each head as :data:`ENSEMBLE_COMBINE` combines the members'
        (standardised outputs share their scale, so the worst member in them is the worst in
        units). Where the members agree this is their common prediction; where they disagree
        (inputs unlike their training data) the most cautious one."""

        def __init__(self, bodies):
            super().__init__()
            self.members = nn.ModuleList(bodies)
            _norm_buffers(self, int(bodies[0][0].in_features))
            for how in ("min", "max"):
                self.register_buffer(f"_{how}", torch.tensor(
                    [ENSEMBLE_COMBINE[h] == how for h in heads]), persistent=False)

        def member(self, k: int):
            """Member ``k`` as a single network (:func:`make_net`), sharing nothing."""
            import copy

            body = self.members[k]
            widths = [m.out_features for m in body if isinstance(m, nn.Linear)][:-1]
            net = make_net(int(self.in_mean.shape[0]), widths)
            net.body = copy.deepcopy(body)
            _copy_norm(net, self)
            return net

        def all_outputs(self, x):
            """Every member's raw outputs (K, B, 7)."""
            z = (x - self.in_mean) / self.in_std
            return torch.stack([m(z) for m in self.members])

        def forward(self, x):
            o = self.all_outputs(x)
            return torch.where(self._min, o.min(dim=0).values,
                               torch.where(self._max, o.max(dim=0).values, o.mean(dim=0)))

    return ESACEnsemble


def is_ensemble(net: Any) -> bool:
    """True if ``net`` is an :class:`ESACEnsemble` (several members)."""
    return hasattr(net, "members")


def ensemble_of(nets: Sequence[Any]):
    """The :class:`ESACEnsemble` of single networks ``nets`` that share their normalisation
    (:func:`fit` with ``members``); its buffers are the first's."""
    import copy

    torch = _torch()
    first = nets[0]
    for k, n in enumerate(nets[1:], 1):
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            if not torch.equal(getattr(n, name), getattr(first, name)):
                raise ValueError(f"member {k} of the ensemble has its own {name}: members must "
                                 f"share the normalisation")
    ens = _ensemble_class()([copy.deepcopy(n.body) for n in nets])
    _copy_norm(ens, first)
    return ens.eval()


def fit(x: np.ndarray, y: np.ndarray, mask: np.ndarray, hidden: Sequence[int] = (128, 128, 128),
        epochs: int = 60, batch_size: int = 256, lr: float = 2e-3, weight_decay: float = 1e-5,
        val_fraction: float = 0.1, seed: int = 0, patience: int = 15, time_loss: str = "mse",
        groups: np.ndarray | None = None, progress: bool = True, init: Any = None,
        members: int = 1) -> tuple[Any, dict[str, Any]]:
    """Train the predictor on ``x`` (B, n_in), targets ``y`` and ``mask`` of
    :func:`~agents.esac.data.targets`: binary cross-entropy on the class heads, mean squared
    error on the standardised regression heads (masked), AdamW with a one-cycle learning rate;
    keeps the weights of the best validation loss. The validation rows are a random
    ``val_fraction`` of the ``groups`` (episode of each row; default: each row its own), so that
    no episode is on both sides. ``time_loss="l1"`` fits the time ratio's conditional median
    instead of its mean: sharper at the knee where a later cut stops lengthening the stroke (the
    mean smooths it into a bias). ``init``: a trained network to fine-tune (a copy is trained; its
    input and output normalisation are kept, so that its units stay those it was trained in).
    ``members > 1`` fits an :class:`ESACEnsemble`: member ``k`` from its own initialisation
    with seed ``seed + MEMBER_SEED_STEP * k`` (its own validation split and minibatch order) on
    the first member's normalisation; an ensemble ``init`` is fine-tuned member by member.
    Returns the network and the loss history (an ensemble's: the first member's curves, the
    mean best validation loss and each member's figures under ``members``)."""
    if time_loss not in ("mse", "l1"):
        raise ValueError(f"time_loss = {time_loss!r}: choose 'mse' or 'l1'")
    kw = dict(hidden=hidden, epochs=epochs, batch_size=batch_size, lr=lr,
              weight_decay=weight_decay, val_fraction=val_fraction, patience=patience,
              time_loss=time_loss, groups=groups, progress=progress)
    if init is not None and is_ensemble(init):
        return _fit_members(x, y, mask, seed, [init.member(k) for k in range(len(init.members))],
                            kw)
    if _check_members(members) > 1:
        if init is not None:
            raise ValueError("fit: members > 1 starts an ensemble afresh; to fine-tune one, "
                             "pass it as init")
        first, hist = fit(x, y, mask, seed=seed, **kw)
        inits = [first]
        for k in range(1, members):
            _torch().manual_seed(seed + MEMBER_SEED_STEP * k)
            inits.append(make_net(x.shape[1], hidden))
            _copy_norm(inits[-1], first)
        return _fit_members(x, y, mask, seed, inits, kw, done=(first, hist))
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


#: member ``k`` of an ensemble fits with seed ``seed + MEMBER_SEED_STEP * k``
MEMBER_SEED_STEP = 1000


def _fit_members(x, y, mask, seed: int, inits: Sequence[Any], kw: Mapping[str, Any],
                 done: tuple[Any, dict[str, Any]] | None = None) -> tuple[Any, dict[str, Any]]:
    """:func:`fit` of each network of ``inits`` (fine-tuned from it; member ``k`` with seed
    ``seed + MEMBER_SEED_STEP * k``; ``done``: member 0 already fitted), as one ensemble."""
    nets, hists = [], []
    for k, net in enumerate(inits):
        if k == 0 and done is not None:
            net, h = done
        else:
            net, h = fit(x, y, mask, seed=seed + MEMBER_SEED_STEP * k, init=net, **kw)
        nets.append(net)
        hists.append(h)
    hist = {"train": hists[0]["train"], "val": hists[0]["val"],
            "best_val": float(np.mean([h["best_val"] for h in hists])),
            "epochs_run": int(sum(h["epochs_run"] for h in hists)),
            "fit_wall_s": float(sum(h["fit_wall_s"] for h in hists)),
            "members": [{"best_val": float(h["best_val"]), "epochs_run": int(h["epochs_run"])}
                        for h in hists]}
    return ensemble_of(nets), hist


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

