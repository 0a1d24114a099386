"""A neural policy's network, exported to run without PyTorch: ONNX (onnxruntime) or a numpy-only
runtime, behind the same decision code (ESAC's rule, the SB3 decision rules).

- :func:`export` writes a directory: ``model.onnx`` (the network, its input normalisation
  inside), ``weights.npz`` (the same network's Linear weights and biases, activations and
  normalisation, for :class:`NumpyNetwork`) and ``controller.json`` (what rebuilds the policy:
  its kind, observation layouts, decision rule, checksums of both files).
- :func:`with_backend` runs a loaded policy's network on ``torch``, ``onnx`` or ``numpy``.
- :func:`load_exported` rebuilds the policy from an exported directory without importing torch
  or stable-baselines3.

Which network: ESAC's predictor (inputs: the model's observation, plus the delay [s] for a model
with ``delay_input``; outputs: 2 class logits and 5 standardised regression values, which
:meth:`~agents.esac.ESACPredictor.raw` de-standardises); for PPO and A2C the actor up to its
action probabilities (keep, cut), the softmax of its logits; for DQN the Q-network's Q-values.
An asymmetric actor-critic's network takes only the actor's ``actor_inputs`` first columns.

Tolerance: the three backends compute in float32 and differ only by rounding (summation order,
the exponential). On observations of the environment every output ``a`` of onnx or numpy
satisfies ``|a - b| <= ATOL + RTOL * |b|`` against torch's ``b``, :data:`ATOL` = :data:`RTOL` =
1e-5 (tests/test_export.py; measured on the trained 3 x 128 ESAC networks over nominal
episodes: max ``|a - b|`` 7.6e-5 on outputs up to 145, 0.25 of the tolerance; on PPO's
probabilities 1.2e-7, benchmarks/bench_deploy.py). Decisions are thresholds on these
outputs: an episode's decisions agree unless an output comes within that distance of a
threshold. :func:`export` compares the backends on random probe inputs and
refuses beyond :data:`EXPORT_GATE` times the tolerance (off the data, rounding grows; a larger
gap means that a runtime computes another network).
"""
from __future__ import annotations

import copy
import hashlib
import io
import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

if TYPE_CHECKING:
    from agents.base import Policy

#: absolute and relative tolerance between torch's outputs and onnxruntime's or numpy's
ATOL = 1e-5
RTOL = 1e-5
#: :func:`export` refuses a network whose runtimes differ by more than this many tolerances
EXPORT_GATE = 10.0
#: the backends a network runs on
BACKENDS = ("torch", "onnx", "numpy")
FORMAT = "pneugym-controller/1"
ONNX_FILE, WEIGHTS_FILE, CONTROLLER_FILE = "model.onnx", "weights.npz", "controller.json"
#: the ONNX operator set written (onnxruntime >= 1.19, the extra's lowest, runs it)
OPSET = 17
#: the activations the numpy runtime implements (torch module name -> runtime name)
ACTIVATIONS = {"Tanh": "tanh", "ReLU": "relu", "SiLU": "silu", "Sigmoid": "sigmoid"}
#: bounds of an exported directory's files, far above any real controller's
MAX_JSON_BYTES = 4 << 20
MAX_WEIGHT_BYTES = 1 << 30
_BASELINES = "conventional, endstroke, gaslaw, gaslaw-rig, mpc, oracle"


# ------------------------------------------------------------------------------------------
# runtimes
# ------------------------------------------------------------------------------------------
def _tanh(h: np.ndarray) -> np.ndarray:
    return np.tanh(h)


def _relu(h: np.ndarray) -> np.ndarray:
    return np.maximum(h, np.float32(0.0))


def _silu(h: np.ndarray) -> np.ndarray:
    # exp(-h) is clipped where silu(h) is 0 in float32 anyway (no overflow warning)
    return h / (np.float32(1.0) + np.exp(np.minimum(-h, np.float32(80.0))))


def _sigmoid(h: np.ndarray) -> np.ndarray:
    return np.float32(1.0) / (np.float32(1.0) + np.exp(np.minimum(-h, np.float32(80.0))))


def _identity(h: np.ndarray) -> np.ndarray:
    return h


_NUMPY_ACT: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "tanh": _tanh, "relu": _relu, "silu": _silu, "sigmoid": _sigmoid, "identity": _identity}


class NumpyNetwork:
    """An MLP in numpy (float32): ``(x - in_mean) / in_std``, then Linear layers each followed by
    its activation, then the output (``softmax`` or none). Built from :func:`network_arrays`'
    arrays (``weights.npz``); ESAC's also carry ``out_mean`` and ``out_std`` (the regression
    heads' standardisation, applied by the predictor). An ESAC ensemble's (``members`` K)
    hold each member's layers as ``m{j}_weight_{k}``, ``m{j}_bias_{k}`` and ``combine``, how
    each output combines the members' (``min``, ``max`` or ``mean``)."""

    def __init__(self, arrays: Mapping[str, np.ndarray], where: str = "the weights"):
        def get(name: str) -> np.ndarray:
            if name not in arrays:
                raise ValueError(f"{where} has no {name!r}: not a network pneugym exported")
            return np.asarray(arrays[name])

        acts = [str(a) for a in get("activations").reshape(-1)]
        output = str(get("output").reshape(()))
        bad = [a for a in acts if a not in _NUMPY_ACT]
        if bad or output not in ("none", "softmax") or not acts:
            raise ValueError(f"{where}: activations {acts}, output {output!r}; the numpy runtime "
                             f"has {sorted(_NUMPY_ACT)} and outputs 'none' or 'softmax'")
        self.in_mean = _float32(get("in_mean"), f"{where}: in_mean", ndim=1)
        self.in_std = _float32(get("in_std"), f"{where}: in_std", ndim=1)
        if self.in_std.shape != self.in_mean.shape or not np.all(self.in_std > 0):
            raise ValueError(f"{where}: in_std must match in_mean's shape and be > 0")
        self.n_in = int(self.in_mean.shape[0])
        # (x - 0) / 1 is x: skipped (SB3 networks have no input normalisation)
        self._normalise = bool(np.any(self.in_mean != 0) or np.any(self.in_std != 1))
        n_members = int(get("members").reshape(())) if "members" in arrays else 1
        if not 1 <= n_members <= 32:  # (agents.esac.model.MAX_MEMBERS: no torch needed here)
            raise ValueError(f"{where}: members = {n_members}; an ensemble has 1 to 32")
        prefixes = [""] if "members" not in arrays else [f"m{j}_" for j in range(n_members)]
        self.members = [self._stack(get, pre, acts, where) for pre in prefixes]
        self.layers = self.members[0]
        self.n_out = self.layers[-1][0].shape[1]
        self.combine: list[str] | None = None
        if "members" in arrays:
            self.combine = [str(c) for c in get("combine").reshape(-1)]
            if len(self.combine) != self.n_out or set(self.combine) - {"min", "max", "mean"}:
                raise ValueError(f"{where}: combine {self.combine}: one of 'min', 'max', "
                                 f"'mean' per output ({self.n_out})")
            if any(m[-1][0].shape[1] != self.n_out for m in self.members):
                raise ValueError(f"{where}: the members' outputs differ in number")
        self.activations = acts
        self.output = output
        self.out_mean = self.out_std = None
        if "out_mean" in arrays:
            self.out_mean = _float32(get("out_mean"), f"{where}: out_mean", ndim=1)
            self.out_std = _float32(get("out_std"), f"{where}: out_std", ndim=1)

    def _stack(self, get: Callable[[str], np.ndarray], pre: str, acts: list[str], where: str
               ) -> list[tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]]:
        """The Linear layers ``{pre}weight_k``, ``{pre}bias_k`` with their activations."""
        layers = []
        width = self.n_in
        for k, act in enumerate(acts):
            w = _float32(get(f"{pre}weight_{k}"), f"{where}: {pre}weight_{k}", ndim=2)
            b = _float32(get(f"{pre}bias_{k}"), f"{where}: {pre}bias_{k}", ndim=1)
            if w.shape[1] != width or b.shape != (w.shape[0],):
                raise ValueError(f"{where}: layer {pre}{k} has weight {w.shape} and bias "
                                 f"{b.shape}; expected ({b.shape[0]}, {width}) and "
                                 f"({w.shape[0]},)")
            layers.append((np.ascontiguousarray(w.T), b, _NUMPY_ACT[act]))
            width = w.shape[0]
        return layers

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The outputs (B, n_out) [float32] for inputs ``x`` (B, n_in)."""
        z = np.asarray(x, dtype=np.float32)
        if self._normalise:
            z = (z - self.in_mean) / self.in_std
        outs = []
        for layers in self.members:
            h = z
            for w_t, b, act in layers:
                h = act(h @ w_t + b)
            outs.append(h)
        h = outs[0]
        if self.combine is not None:
            o = np.stack(outs)
            h = np.where(np.array([c == "min" for c in self.combine]), o.min(axis=0),
                         np.where(np.array([c == "max" for c in self.combine]), o.max(axis=0),
                                  o.mean(axis=0))).astype(np.float32)
        if self.output == "softmax":
            e = np.exp(h - h.max(axis=1, keepdims=True))
            h = e / e.sum(axis=1, keepdims=True)
        return h

    def __repr__(self) -> str:
        widths = [self.n_in] + [w.shape[1] for w, _, _ in self.layers]
        k = f", members={len(self.members)}" if self.combine is not None else ""
        return f"NumpyNetwork({widths}, {self.activations}, output={self.output!r}{k})"


def _float32(a: np.ndarray, where: str, ndim: int) -> np.ndarray:
    if a.dtype != np.float32 or a.ndim != ndim or not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: expected a finite float32 array of {ndim} dimension(s), got "
                         f"{a.dtype} {a.shape}")
    return a


class OnnxNetwork:
    """An ONNX network on onnxruntime's CPU provider, one thread (intra- and inter-op):
    float32 (B, n_in) -> float32 (B, n_out)."""

    def __init__(self, model: bytes, threads: int = 1):
        try:
            import onnxruntime as ort
        except ImportError:
            raise ImportError("the onnx backend needs onnxruntime: pip install "
                              "'pneugym[deploy]'") from None
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = int(threads)
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self.session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        self._input = self.session.get_inputs()[0].name

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The outputs (B, n_out) [float32] for inputs ``x`` (B, n_in)."""
        return self.session.run(None, {self._input: np.ascontiguousarray(x, dtype=np.float32)})[0]


class FirstColumns:
    """``net`` on the first ``n`` columns of its input: an asymmetric actor-critic's actor,
    whose input the policy pads with the privileged columns the actor never reads."""

    def __init__(self, net: Callable[[np.ndarray], np.ndarray], n: int):
        self.net, self.n = net, int(n)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.net(x[:, :self.n] if x.shape[1] != self.n else x)

    def __repr__(self) -> str:
        return f"FirstColumns({self.net!r}, {self.n})"


# ------------------------------------------------------------------------------------------
# the policies' networks
# ------------------------------------------------------------------------------------------
def _kind(policy: Any) -> str:
    """``"esac"`` or ``"sb3"``; a policy without a network is refused."""
    from agents.esac.policy import ESACPolicy
    from agents.learned import SB3Policy

    if isinstance(policy, ESACPolicy):
        return "esac"
    if isinstance(policy, SB3Policy):
        return "sb3"
    name = getattr(policy, "name", type(policy).__name__)
    raise ValueError(f"{name!r} ({type(policy).__name__}) has no neural network: it needs no "
                     f"export. The baselines ({_BASELINES}) are a few lines of numpy already and "
                     f"run as they are; export takes ESAC and stable-baselines3 (PPO, A2C, DQN) "
                     f"policies")


def _exported_dir(policy: Any) -> Path | None:
    return getattr(policy, "exported_from", None)


def _torch_module(policy: Any, kind: str):
    """The torch module computing the exported network, and its input width."""
    import torch

    n_in = _net_inputs(policy, kind)
    if kind == "esac":
        return policy.predictor.net.eval(), n_in
    model = policy.model
    if policy.outputs == "q_values":
        return model.q_net.eval(), n_in
    sb3 = model.policy

    class ActorProbs(torch.nn.Module):
        """The actor up to its action probabilities (SB3: the categorical's probs)."""

        def __init__(self):
            super().__init__()
            self.features, self.mlp, self.action = (sb3.pi_features_extractor,
                                                    sb3.mlp_extractor, sb3.action_net)

        def forward(self, x):
            logits = self.action(self.mlp.forward_actor(self.features(x)))
            return torch.softmax(logits, dim=-1)

    return ActorProbs().eval(), n_in


def _linear_stack(modules, where: str) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Weights, biases and activations of a sequence of Linear layers and activations."""
    ws: list[np.ndarray] = []
    bs: list[np.ndarray] = []
    acts: list[str] = []
    for m in modules:
        name = type(m).__name__
        if name == "Linear":
            if ws and len(acts) < len(ws):
                acts.append("identity")
            ws.append(m.weight.detach().cpu().numpy().astype(np.float32))
            bs.append(m.bias.detach().cpu().numpy().astype(np.float32) if m.bias is not None
                      else np.zeros(m.out_features, np.float32))
        elif name in ACTIVATIONS and len(acts) < len(ws):
            acts.append(ACTIVATIONS[name])
        elif name not in ("Flatten", "Identity", "FlattenExtractor"):
            raise ValueError(f"{where}: layer {name} is not a Linear layer or one of the "
                             f"activations {sorted(ACTIVATIONS)}: the numpy runtime cannot run it")
    acts += ["identity"] * (len(ws) - len(acts))
    return ws, bs, acts


def network_arrays(policy: Any) -> dict[str, np.ndarray]:
    """The arrays of ``policy``'s network for :class:`NumpyNetwork` (``weights.npz``):
    ``in_mean``, ``in_std``, ``weight_k`` (out, in) and ``bias_k`` per Linear layer,
    ``activations`` (after each layer), ``output`` and, for ESAC, ``out_mean``, ``out_std``."""
    kind = _kind(policy)
    src = getattr(policy, "source", "the policy")
    members: list[tuple[list[np.ndarray], list[np.ndarray]]] = []
    if kind == "esac":
        from agents.esac import ENSEMBLE_COMBINE, is_ensemble

        net = policy.predictor.net
        bodies = list(net.members) if is_ensemble(net) else [net.body]
        for body in bodies:
            ws, bs, acts = _linear_stack(body, f"{src}: the ESAC network")
            members.append((ws, bs))
        out: dict[str, np.ndarray] = {
            "in_mean": net.in_mean.detach().numpy().astype(np.float32),
            "in_std": net.in_std.detach().numpy().astype(np.float32),
            "out_mean": net.out_mean.detach().numpy().astype(np.float32),
            "out_std": net.out_std.detach().numpy().astype(np.float32),
            "output": np.array("none")}
    else:
        model = policy.model
        n_in = _net_inputs(policy, kind)
        if policy.outputs == "q_values":
            qn = model.q_net
            mods = [qn.features_extractor, *qn.q_net]
            output = "none"
        else:
            sb3 = model.policy
            mods = [sb3.pi_features_extractor, *sb3.mlp_extractor.policy_net, sb3.action_net]
            output = "softmax"
        ws, bs, acts = _linear_stack(mods, f"{src}: the network")
        if not ws or ws[0].shape[1] != n_in:
            raise ValueError(f"{src}: the network's first layer takes "
                             f"{ws[0].shape[1] if ws else 0} inputs, expected {n_in}")
        out = {"in_mean": np.zeros(n_in, np.float32), "in_std": np.ones(n_in, np.float32),
               "output": np.array(output)}
    out["activations"] = np.array(acts)
    if len(members) > 1:  # an ESAC ensemble
        from agents.esac import CLASS_HEADS, REG_HEADS

        out["members"] = np.array(len(members))
        out["combine"] = np.array([ENSEMBLE_COMBINE[h] for h in (*CLASS_HEADS, *REG_HEADS)])
        for j, (ws, bs) in enumerate(members):
            for k, (w, b) in enumerate(zip(ws, bs)):
                out[f"m{j}_weight_{k}"], out[f"m{j}_bias_{k}"] = w, b
        return out
    for k, (w, b) in enumerate(zip(ws, bs)):
        out[f"weight_{k}"], out[f"bias_{k}"] = w, b
    return out


def onnx_model(policy: Any) -> bytes:
    """``policy``'s network as an ONNX model (opset :data:`OPSET`, input ``obs`` (batch, n_in),
    output ``out`` (batch, n_out), float32)."""
    import warnings

    import torch

    module, n_in = _torch_module(policy, _kind(policy))
    buf = io.BytesIO()
    # The TorchScript-based exporter (dynamo=False): it ships with the pinned torch and runs
    # offline, where the default torch.export-based one needs the onnxscript package; these
    # plain MLPs (Linear, activations, softmax) are exactly what it handles. It warns that it
    # is deprecated: the checks against torch (export, tests) would catch any change.
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        torch.onnx.export(module, (torch.zeros(1, n_in),), buf, dynamo=False,
                          input_names=["obs"], output_names=["out"], opset_version=OPSET,
                          dynamic_axes={"obs": {0: "batch"}, "out": {0: "batch"}})
    return buf.getvalue()


def _backend_fn(kind: str, net: Callable[[np.ndarray], np.ndarray], n_in: int, size: int
                ) -> Callable[[np.ndarray], np.ndarray]:
    return FirstColumns(net, n_in) if kind == "sb3" and n_in != size else net


def _set_backend(policy: Any, kind: str, fn: Callable[[np.ndarray], np.ndarray] | None) -> None:
    if kind == "esac":
        policy.predictor.backend = fn
    else:
        policy.backend = fn


def _copy(policy: Any, kind: str) -> Any:
    """A copy of ``policy`` (its own episode state) sharing the network and its runtime."""
    held = (policy.predictor.net, policy.predictor._backend) if kind == "esac" \
        else (policy.model, policy._backend)
    memo = {id(o): o for o in held if o is not None}
    return copy.deepcopy(policy, memo)


def with_backend(policy: Policy, backend: str) -> Policy:
    """A copy of ``policy`` (an ESAC or SB3 policy) whose network runs on ``backend``:
    ``"torch"`` (the model as loaded), ``"onnx"`` (onnxruntime, CPU, one thread) or
    ``"numpy"`` (:class:`NumpyNetwork`). The decision code is the policy's own; outputs agree
    with torch's within ``ATOL + RTOL * |out|`` (module docstring). A policy from
    :func:`load_exported` switches between ``onnx`` and ``numpy`` only."""
    if backend not in BACKENDS:
        raise ValueError(f"backend = {backend!r}: choose one of {list(BACKENDS)}")
    kind = _kind(policy)
    src = _exported_dir(policy)
    new = _copy(policy, kind)
    if src is not None:
        if backend == "torch":
            raise ValueError(f"{policy.source} runs without torch (exported); choose 'onnx' or "
                             f"'numpy', or load the trained model for 'torch'")
        fresh = load_exported(src, policy.read.layout, backend=backend)
        net = fresh.predictor._backend if kind == "esac" else fresh._backend
        _set_backend(new, kind, net)
        new.backend_name = backend
        return new
    fn: Callable[[np.ndarray], np.ndarray] | None = None
    if backend != "torch":
        n_in = _net_inputs(policy, kind)
        net = (NumpyNetwork(network_arrays(policy), policy.source) if backend == "numpy"
               else OnnxNetwork(onnx_model(policy)))
        fn = _backend_fn(kind, net, n_in, _net_size(policy, kind))
    _set_backend(new, kind, fn)
    new.backend_name = backend
    return new


def _net_inputs(policy: Any, kind: str) -> int:
    """Columns the exported network reads (an asymmetric actor: its ``actor_inputs``)."""
    if kind == "esac":
        return int(policy.predictor.n_in)
    return int(policy.actor_inputs or policy.full_layout["size"])


def _net_size(policy: Any, kind: str) -> int:
    """Columns of the observations the policy hands its network."""
    if kind == "esac":
        return int(policy.predictor.n_in)
    return int(policy.full_layout["size"])


def max_difference(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """``max |a - b|`` and the largest ``|a - b| / (ATOL + RTOL |b|)`` (<= 1: within
    tolerance) of outputs ``a`` against reference outputs ``b``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = np.abs(a - b)
    return {"max_abs": float(d.max(initial=0.0)),
            "max_ratio": float((d / (ATOL + RTOL * np.abs(b))).max(initial=0.0))}


def _probe_inputs(policy: Any, kind: str, n: int = 256, seed: int = 0) -> np.ndarray:
    """Inputs to compare the backends on at export: the ESAC network's input distribution
    (mean +- 2 std), or observations' range [-1, 1] for SB3 networks."""
    rng = np.random.default_rng(seed)
    if kind == "esac":
        net = policy.predictor.net
        mean, std = (np.asarray(t.detach().numpy(), np.float32) for t in (net.in_mean, net.in_std))
        return (mean + 2 * std * rng.uniform(-1, 1, (n, mean.size))).astype(np.float32)
    return rng.uniform(-1, 1, (n, _net_size(policy, kind))).astype(np.float32)


# ------------------------------------------------------------------------------------------
# the exported directory
# ------------------------------------------------------------------------------------------
def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _plain(o: Any) -> Any:
    """JSON-able: numpy scalars and arrays as numbers and lists, tuples as lists."""
    if isinstance(o, Mapping):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return o


def _trained_rig(policy: Any) -> dict[str, Any] | None:
    rig = getattr(policy, "trained_rig", None)
    if rig is None:
        return None
    from pneugym.rigfile import as_rig

    return _plain(as_rig(rig, "the policy's trained rig").to_dict())


def export(policy: Policy, out_dir: str | os.PathLike) -> dict[str, Path]:
    """Export ``policy``'s network (an ESAC or SB3 policy, as :func:`agents.registry.load_policy`
    builds it) to ``out_dir``: ``model.onnx``, ``weights.npz`` and ``controller.json``.
    Before writing, onnxruntime's and numpy's outputs are compared with torch's on 256 random
    probe inputs (ValueError beyond :data:`EXPORT_GATE` tolerances; the figures go to
    controller.json's ``check``).
    Returns the paths by key ``onnx``, ``weights``, ``controller``. A policy without a network
    (a baseline) is refused with a ValueError."""
    import pneugym
    from pneugym.provenance import provenance

    kind = _kind(policy)
    src = getattr(policy, "source", "the policy")
    if _exported_dir(policy) is not None:
        raise ValueError(f"{src} is already exported at {_exported_dir(policy)}: copy that "
                         f"directory")
    arrays = network_arrays(policy)
    model = onnx_model(policy)
    numpy_net = NumpyNetwork(arrays, src)
    module, n_in = _torch_module(policy, kind)
    x = _probe_inputs(policy, kind)[:, :n_in]
    import torch

    with torch.no_grad():
        ref = module(torch.as_tensor(x)).numpy()
    check = {"inputs": f"{x.shape[0]} random probe inputs",
             "onnx": max_difference(OnnxNetwork(model)(x), ref),
             "numpy": max_difference(numpy_net(x), ref)}
    for name, d in check.items():
        if isinstance(d, dict) and d["max_ratio"] > EXPORT_GATE:
            raise ValueError(f"{src}: the {name} network's outputs differ from torch's by up to "
                             f"{d['max_abs']:.3g}, {d['max_ratio']:.0f} times the tolerance "
                             f"{ATOL:g} + {RTOL:g} |out|: not the same network")
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    weights = buf.getvalue()
    meta: dict[str, Any] = {
        "format": FORMAT, "kind": kind, "source": src,
        "pneugym_version": pneugym.__version__,
        "model_layout": policy.model_layout, "env_layout": policy.read.layout,
        "network": {"inputs": n_in, "outputs": numpy_net.n_out,
                    "gives": "raw" if kind == "esac" else policy.outputs,
                    "widths": [numpy_net.n_in] + [w.shape[1] for w, _, _ in numpy_net.layers],
                    "activations": numpy_net.activations, "output": numpy_net.output,
                    "onnx_opset": OPSET},
        "tolerance": {"atol": ATOL, "rtol": RTOL}, "check": check,
        "trained_rig": _trained_rig(policy),
        "trained_preset": getattr(policy, "trained_preset", None),
        "trained_conditions": getattr(policy, "trained_conditions", None),
    }
    if kind == "esac":
        pred = policy.predictor
        meta["esac"] = {"delay_input": pred.delay_input,
                        "lookahead_s": pred.lookahead_s.tolist(), "stroke_m": pred.stroke_m,
                        "out_mean": arrays["out_mean"].tolist(),
                        "out_std": arrays["out_std"].tolist(), "rule": policy.rule()}
    else:
        meta["sb3"] = {"algo": str(getattr(policy.model, "algo", type(policy.model).__name__)
                                   ).lower(),
                       "outputs": policy.outputs, "decision": policy.decision,
                       "actor_inputs": policy.actor_inputs, "pad": policy._pad,
                       "full_layout": policy.full_layout}
    meta["sha256"] = {ONNX_FILE: _sha256(model), WEIGHTS_FILE: _sha256(weights)}
    meta["provenance"] = provenance()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"onnx": out / ONNX_FILE, "weights": out / WEIGHTS_FILE,
             "controller": out / CONTROLLER_FILE}
    _write(paths["onnx"], model)
    _write(paths["weights"], weights)
    _write(paths["controller"],
           (json.dumps(_plain(meta), indent=1, allow_nan=False) + "\n").encode())
    return paths


def _read(path: Path, limit: int) -> bytes:
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: an exported controller has {ONNX_FILE}, "
                                f"{WEIGHTS_FILE} and {CONTROLLER_FILE} (pneugym.deploy.export)")
    if path.stat().st_size > limit:
        raise ValueError(f"{path} is {path.stat().st_size:,} bytes, more than the {limit:,} an "
                         f"exported controller's file may have")
    return path.read_bytes()


def _read_meta(d: Path) -> dict[str, Any]:
    f = d / CONTROLLER_FILE
    try:
        meta = json.loads(_read(f, MAX_JSON_BYTES))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"{f} is not a controller description export() wrote: {exc}") from None
    fmt = meta.get("format") if isinstance(meta, dict) else None
    if fmt != FORMAT:
        raise ValueError(f"{f}: format {fmt!r:.60}; expected {FORMAT!r} (written by "
                         f"pneugym.deploy.export.export)")
    if meta.get("kind") not in ("esac", "sb3") or not isinstance(meta.get(meta["kind"]), dict):
        raise ValueError(f"{f}: kind {meta.get('kind')!r}; expected 'esac' or 'sb3' with its "
                         f"section")
    sums = meta.get("sha256")
    if not isinstance(sums, dict) or not all(isinstance(sums.get(k), str)
                                             for k in (ONNX_FILE, WEIGHTS_FILE)):
        raise ValueError(f"{f} has no sha256 of {ONNX_FILE} and {WEIGHTS_FILE}")
    return meta


def _verified(d: Path, name: str, meta: Mapping[str, Any]) -> bytes:
    data = _read(d / name, MAX_WEIGHT_BYTES)
    if _sha256(data) != meta["sha256"][name]:
        raise ValueError(f"{d / name} does not match the checksum controller.json records "
                         f"(sha256 {_sha256(data)[:16]}..., recorded "
                         f"{meta['sha256'][name][:16]}...): altered or damaged since export; "
                         f"export it again")
    return data


def _finite_list(v: Any, where: str, n: int | None = None) -> list[float]:
    from agents.learned import is_finite_number

    if not isinstance(v, list) or not all(is_finite_number(x) for x in v) or (
            n is not None and len(v) != n):
        raise ValueError(f"{where} is {v!r:.80}; expected a list of {n or ''} finite numbers")
    return [float(x) for x in v]


def load_exported(out_dir: str | os.PathLike, env_layout: Mapping[str, Any],
                  backend: str = "numpy") -> Policy:
    """The policy exported to ``out_dir`` (:func:`export`), for an environment of observation
    layout ``env_layout``, its network on ``backend`` (``"numpy"`` or ``"onnx"``); torch and
    stable-baselines3 are not imported. Both network files are checked against the checksums
    in ``controller.json`` (a ValueError refuses a changed file), the layouts against each other
    as for a trained model (:class:`~agents.learned.LayoutMismatchError`)."""
    from agents.esac.model import ESACPredictor
    from agents.esac.policy import ESACPolicy
    from agents.esac.rule import check_rule
    from agents.learned import SB3Policy, check_decision, check_layout_record

    if backend not in ("onnx", "numpy"):
        raise ValueError(f"backend = {backend!r}: an exported controller runs on 'onnx' or "
                         f"'numpy' (torch: load the trained model)")
    d = Path(out_dir)
    f = d / CONTROLLER_FILE
    meta = _read_meta(d)
    weights = _verified(d, WEIGHTS_FILE, meta)
    model = _verified(d, ONNX_FILE, meta)
    try:
        with np.load(io.BytesIO(weights), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError) as exc:
        raise ValueError(f"{d / WEIGHTS_FILE} is not readable: {exc}") from None
    numpy_net = NumpyNetwork(arrays, str(d / WEIGHTS_FILE))
    net = numpy_net if backend == "numpy" else OnnxNetwork(model)
    kind = meta["kind"]
    sec = meta[kind]
    source = f"exported controller {d} ({meta.get('source', 'a trained model')})"
    if kind == "esac":
        layout = check_layout_record(meta.get("model_layout"), f"{f}: model_layout")
        if not isinstance(sec.get("delay_input"), bool):
            raise ValueError(f"{f}: esac.delay_input is {sec.get('delay_input')!r}; expected "
                             f"true or false")
        look = _finite_list(sec.get("lookahead_s"), f"{f}: esac.lookahead_s")
        for key in ("out_mean", "out_std"):
            rec = np.asarray(_finite_list(sec.get(key), f"{f}: esac.{key}", 5), np.float32)
            if getattr(numpy_net, key) is None or not np.array_equal(rec, getattr(numpy_net, key)):
                raise ValueError(f"{f}: esac.{key} differs from {WEIGHTS_FILE}'s")
        rule = check_rule(sec.get("rule"), f"{f}: esac.rule")
        pred = ESACPredictor(numpy_net, layout, sec["delay_input"], look, backend=net)
        pol = ESACPolicy(env_layout, pred, source=source, **rule)
    else:
        full = check_layout_record(sec.get("full_layout"), f"{f}: sb3.full_layout")
        outputs = sec.get("outputs")
        actor_inputs = sec.get("actor_inputs")
        if outputs not in ("probs", "q_values") or not (
                actor_inputs is None or (isinstance(actor_inputs, int)
                                         and 0 < actor_inputs <= int(full["size"]))):
            raise ValueError(f"{f}: sb3.outputs {outputs!r}, actor_inputs {actor_inputs!r}; "
                             f"expected 'probs' or 'q_values', and none or a column count")
        n_in = int(actor_inputs or full["size"])
        if numpy_net.n_in != n_in or numpy_net.n_out != 2:
            raise ValueError(f"{f}: the network takes {numpy_net.n_in} inputs and gives "
                             f"{numpy_net.n_out} outputs; expected {n_in} and 2")
        stand_in = ExportedSB3Model(str(sec.get("algo")), int(full["size"]), actor_inputs,
                                    outputs)
        decision = check_decision(sec.get("decision"), f"{f}: sb3.decision", per_row=True)
        pol = SB3Policy(env_layout, stand_in, full, source=source, decision=decision)
        pol.backend = _backend_fn(kind, net, n_in, int(full["size"]))
    if meta.get("trained_rig") is not None:
        from pneugym.rigfile import as_rig

        pol.trained_rig = as_rig(meta["trained_rig"], f"{f}: trained_rig")
    pol.trained_preset = meta.get("trained_preset")
    pol.trained_conditions = meta.get("trained_conditions")
    if pol.trained_conditions is not None and not isinstance(pol.trained_conditions, dict):
        raise ValueError(f"{f}: trained_conditions is {pol.trained_conditions!r:.80}; expected "
                         f"the training's condition overrides (a mapping) or null")
    from agents.registry import training_space

    pol.training_space = training_space(pol, None)
    pol.exported_from = d
    pol.backend_name = backend
    pol.export_meta = meta
    return pol


class ExportedSB3Model:
    """What :class:`~agents.learned.SB3Policy` reads of a stable-baselines3 model, for an
    exported network (no torch): ``observation_space.shape``, ``policy.actor_inputs`` and what
    the network gives (``pneugym_outputs``: ``probs`` or ``q_values``)."""

    def __init__(self, algo: str, obs_size: int, actor_inputs: int | None, outputs: str):
        self.algo = algo
        self.observation_space = SimpleNamespace(shape=(int(obs_size),))
        self.policy = SimpleNamespace(actor_inputs=actor_inputs)
        self.pneugym_outputs = outputs

    def __repr__(self) -> str:
        return f"ExportedSB3Model({self.algo!r}, outputs={self.pneugym_outputs!r})"


def parser():
    """The options of ``pneugym export``."""
    import argparse

    p = argparse.ArgumentParser(
        prog="pneugym export", description="Export a trained neural policy (ESAC, PPO, DQN) to "
        "ONNX and a numpy-only runtime: model.onnx, weights.npz, controller.json.",
        epilog="examples:\n"
               "  pneugym export runs/esac --out export/esac\n"
               "  pneugym export esac-family --runs runs --rig my_rig.yaml --out export/family\n"
               "then: Controller.load('export/esac', backend='onnx') (pneugym.deploy)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="a run directory, a model file (.pt, .zip) or a learned "
                                  "policy's name under --runs")
    p.add_argument("--out", required=True, help="folder to write the export into")
    p.add_argument("--rig", default=None, help="rig file of the rig it will control (checked "
                                               "against the rig the model was trained on)")
    p.add_argument("--runs", default="runs", help="where learned policies' runs are")
    return p


def main(argv: Any = None) -> dict[str, Path] | int:
    """``pneugym export``: load the model as a controller would, export it, print the check."""
    from .controller import Controller

    args = parser().parse_args(argv)
    try:
        policy = Controller.load(args.source, rig=args.rig, runs=args.runs).policy
        paths = export(policy, args.out)
    except (ValueError, OSError) as exc:  # a refused model or rig: named, exit status 2
        print(f"error: {exc}", file=sys.stderr)
        return 2
    check = json.loads(paths["controller"].read_text())["check"]
    for name in ("onnx", "numpy"):
        print(f"{name:5s}: max |difference| from torch {check[name]['max_abs']:.2g} "
              f"({check[name]['max_ratio']:.2g} of the tolerance {ATOL:g} + {RTOL:g} |out|)")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return paths


__all__ = ["ATOL", "RTOL", "EXPORT_GATE", "BACKENDS", "FORMAT", "NumpyNetwork", "OnnxNetwork", "FirstColumns",
           "ExportedSB3Model", "export", "with_backend", "load_exported", "network_arrays",
           "onnx_model", "max_difference", "main"]
