"""Loading stable-baselines3 models and replay buffers without running code from the file.

An SB3 ``.zip`` holds the weights (``*.pth``, which SB3 reads with ``torch.load(weights_only=True)``:
tensors only) and a JSON ``data`` entry whose non-JSON values (the policy class, the spaces,
schedules, buffers...) are cloudpickled: unpickling them runs whatever code the file names. So
:func:`load_sb3` reads ``data`` with :mod:`json` alone and hands SB3 a plain replacement for
*every* pickled entry (``custom_objects``), built from the JSON and an allowlist; an entry it cannot
replace is refused (:class:`UnsafeModelError`). SB3 then never reaches ``cloudpickle.loads``.
Before anything is read or built, sizes are checked, so that a small file cannot make pneugym
allocate gigabytes: the zip's entries from its directory (:func:`check_zip_sizes`), the recorded
observation size against the recorded layout (or the environment), and the network
``policy_kwargs`` describe against the weights the file holds. The recorded layout
(``pneugym_layout``) and decision rule (``pneugym_decision``) are checked for structure, types
and ranges; a problem is a ValueError naming the file and the key.

Replay buffers are written as plain numpy arrays (:func:`save_replay_buffer`, ``.npz``) and read
back with ``allow_pickle=False`` after checking every shape and dtype (:func:`load_replay_buffer`).

>>> model = load_sb3("runs/ppo/best_model.zip", "ppo")          # doctest: +SKIP
"""
from __future__ import annotations

import inspect
import io
import json
import os
import pickle  # for its error class only: nothing here unpickles
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .learned import LayoutMismatchError

SERIALIZED = ":serialized:"
#: the algorithms pneugym loads, and the SB3 classes behind them
ALGOS = ("ppo", "dqn", "a2c")
#: entries SB3 rebuilds from plain values in ``_setup_model`` / ``_setup_learn`` when None
REBUILT = ("lr_schedule", "exploration_schedule", "rollout_buffer_class", "replay_buffer_class",
           "_last_obs", "_last_original_obs", "_last_episode_starts", "ep_info_buffer",
           "ep_success_buffer")
#: hyperparameters that may be callables: a resumed run takes them from its config, inference
#: from the algorithm's defaults (they do not act at inference)
SCHEDULES = ("learning_rate", "clip_range", "clip_range_vf", "train_freq")
#: what SB3 never writes into ``data`` (``_excluded_save_params``): a file holding one was altered
NEVER_SAVED = ("policy", "device", "env", "replay_buffer", "rollout_buffer", "_vec_normalize_env",
               "_logger", "_custom_logger", "q_net", "q_net_target")
#: the arrays (and counters) of an SB3 ``ReplayBuffer`` that :func:`save_replay_buffer` keeps
REPLAY_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


#: limits checked before anything is read or built (a small file must not make pneugym allocate
#: gigabytes): the zip on disk, its entries once inflated, the JSON ``data`` entry, each weights
#: file, the number of entries, and how much an entry may inflate (a zip bomb)
MAX_MODEL_BYTES = 2 << 30
MAX_DATA_BYTES = 16 << 20
MAX_WEIGHTS_BYTES = 1 << 30
MAX_ENTRIES = 64
MAX_INFLATION = 1000
#: the largest observation a model may take (a recorded layout's size is bounded far below it)
MAX_OBSERVATION_SIZE = 65536


class UnsafeModelError(ValueError):
    """A model file holds something pneugym will not load (a pickled object it cannot replace)."""


def check_zip_sizes(path: Path, z: zipfile.ZipFile, what: str = "stable-baselines3 model",
                    limits: Mapping[str, int] | None = None,
                    total: int = MAX_MODEL_BYTES) -> dict[str, int]:
    """The inflated size of every entry of the zip ``z`` (``path``), from its directory, checked
    before any is read: at most :data:`MAX_ENTRIES` entries, each within ``limits`` (by name
    suffix; default :data:`MAX_DATA_BYTES` for ``data``, :data:`MAX_WEIGHTS_BYTES` for the
    rest), ``total`` in all, and none inflating more than :data:`MAX_INFLATION` times
    (beyond 16 MB). Raises ValueError naming the file and the entry."""
    infos = z.infolist()
    if len(infos) > MAX_ENTRIES:
        raise ValueError(f"{path} holds {len(infos)} entries; a {what} has a handful (at most "
                         f"{MAX_ENTRIES} are read): not a {what}, or altered")
    sizes: dict[str, int] = {}
    for info in infos:
        limit = MAX_WEIGHTS_BYTES
        for suffix, lim in (limits or {"data": MAX_DATA_BYTES}).items():
            if info.filename == suffix or info.filename.endswith("/" + suffix):
                limit = lim
        if info.file_size > limit:
            raise ValueError(f"{path}: its entry {info.filename!r} inflates to "
                             f"{info.file_size:,} bytes, more than the {limit:,} a {what} "
                             f"needs; pneugym does not read it (a damaged or crafted file)")
        if info.file_size > 16 << 20 and info.file_size > MAX_INFLATION * max(
                info.compress_size, 1):
            raise ValueError(f"{path}: its entry {info.filename!r} inflates {info.compress_size:,}"
                             f" bytes to {info.file_size:,} (a zip bomb); pneugym does not read "
                             f"it")
        sizes[info.filename] = sizes.get(info.filename, 0) + info.file_size
    if sum(sizes.values()) > total:
        raise ValueError(f"{path}: its entries inflate to {sum(sizes.values()):,} bytes in all, "
                         f"more than the {total:,} pneugym reads from a {what}")
    return sizes


def _refuse_pickle(path: Path, key: str, hint: str = "") -> UnsafeModelError:
    return UnsafeModelError(
        f"{path} holds a pickled object under {key!r}; pneugym never unpickles model files"
        + (f": {hint}" if hint else " (train.py's models have none there: was this file made "
           "elsewhere or altered?)"))


def is_serialized(value: Any) -> bool:
    """True for an SB3 ``data`` entry stored as a cloudpickle."""
    return isinstance(value, dict) and SERIALIZED in value


def _nested_pickle(value: Any) -> bool:
    if is_serialized(value):
        return True
    if isinstance(value, dict):
        return any(_nested_pickle(v) for v in value.values())
    if isinstance(value, list):
        return any(_nested_pickle(v) for v in value)
    return False


def read_model_data(path: str | Path) -> tuple[bytes, dict[str, Any]]:
    """The bytes of the SB3 zip at ``path`` and its ``data`` entry, parsed as JSON only; the
    file's and its entries' sizes are checked first (:func:`check_zip_sizes`)."""
    p = Path(path)
    try:
        if p.stat().st_size > MAX_MODEL_BYTES:
            raise ValueError(f"{p} is {p.stat().st_size:,} bytes; pneugym reads models of up to "
                             f"{MAX_MODEL_BYTES:,} bytes")
        raw = p.read_bytes()
    except OSError as exc:
        raise ValueError(f"{p} cannot be read: {exc.strerror or exc}") from None
    try:
        with zipfile.ZipFile(io.BytesIO(raw)) as z:
            if "data" not in z.namelist():
                raise ValueError(f"{p} is a zip without the 'data' entry of a stable-baselines3 "
                                 f"model")
            check_zip_sizes(p, z)
            with z.open("data") as fh:
                text = fh.read(MAX_DATA_BYTES + 1).decode("utf-8")
    except (zipfile.BadZipFile, UnicodeDecodeError, EOFError, OSError) as exc:
        raise ValueError(f"{p} is not a readable stable-baselines3 model (.zip): {exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: its 'data' entry is not JSON ({exc.msg} at line {exc.lineno})"
                         ) from None
    except RecursionError:
        raise ValueError(f"{p}: its 'data' entry is JSON nested too deeply for a "
                         f"stable-baselines3 model (altered or damaged)") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit
        raise ValueError(f"{p}: its 'data' entry is not the JSON of a stable-baselines3 model: "
                         f"{exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{p}: its 'data' entry is a JSON {type(data).__name__}, expected an "
                         f"object")
    return raw, data


def guess_algo(data: Mapping[str, Any]) -> str | None:
    """``"ppo"``, ``"dqn"`` or ``"a2c"`` from the hyperparameters a model's ``data`` holds."""
    if "exploration_initial_eps" in data or "target_update_interval" in data:
        return "dqn"
    if "clip_range" in data and "n_epochs" in data:
        return "ppo"
    if "gae_lambda" in data and "n_steps" in data:
        return "a2c"
    return None


def algo_class(algo: str):
    """The SB3 class of ``algo`` (``ppo``, ``dqn``, ``a2c``)."""
    from stable_baselines3 import A2C, DQN, PPO

    return {"ppo": PPO, "dqn": DQN, "a2c": A2C}[algo]


def _int_list(v: Any) -> list[int] | None:
    if isinstance(v, list) and v and all(isinstance(x, int) and not isinstance(x, bool)
                                          and x > 0 for x in v):
        return v
    return None


def recorded_layout(path: Path, data: Mapping[str, Any],
                    fallback: Mapping[str, Any] | None = None) -> dict[str, Any] | None:
    """The observation layout a model records (``pneugym_layout``), else ``fallback`` (its
    run.json's), checked (:func:`agents.learned.check_layout_record`); None if neither."""
    from .learned import check_layout_record

    if data.get("pneugym_layout") is not None:
        return check_layout_record(data["pneugym_layout"], f"{path}: pneugym_layout")
    if fallback is not None:
        return check_layout_record(fallback, f"{path}: the observation_layout of its run.json")
    return None


def _obs_size(path: Path, data: Mapping[str, Any], layout: Mapping[str, Any] | None,
              default: int | None) -> tuple[int, str]:
    """The observation size a model takes, and where it was read from: the recorded
    ``observation_space._shape``, which must equal the recorded layout's size (else
    ``default``, the environment's), checked before any space or network is built."""
    space = data.get("observation_space")
    shape = _int_list(space.get("_shape")) if isinstance(space, dict) else None
    want, where = (int(layout["size"]), "its recorded observation layout") if layout \
        else (default, "the environment's observation") if default is not None else (None, "")
    if shape is not None:
        if len(shape) != 1:
            raise LayoutMismatchError(f"{path}: the model takes observations of shape "
                                      f"{tuple(shape)}; the cut-off environment's are flat")
        if want is not None and shape[0] != want:
            raise LayoutMismatchError(f"{path}: observation_space._shape is {tuple(shape)}, but "
                                      f"{where} has size {want}: the model was trained on "
                                      f"another observation layout, or the file was altered")
        if shape[0] > MAX_OBSERVATION_SIZE:
            raise ValueError(f"{path}: observation_space._shape is {tuple(shape)}; the cut-off "
                             f"environment's observations have at most {MAX_OBSERVATION_SIZE} "
                             f"entries (a damaged or crafted file)")
        return shape[0], "observation_space._shape"
    if want is None:
        raise ValueError(f"{path} records no observation size")
    return int(want), where


def _objects_in_weights(path: Path) -> UnsafeModelError:
    return UnsafeModelError(f"{path}: a weights file (.pth) in it holds Python objects beside "
                            f"tensors; pneugym loads tensors only and does not unpickle them")


class _WeightsTooSmall(ValueError):
    """``policy.pth`` is smaller than the network the model describes."""


def _weights_hold_objects(raw: bytes) -> bool:
    """True if the (small) ``policy.pth`` of the SB3 zip ``raw`` holds Python objects: read
    with ``torch.load(weights_only=True)``, which unpickles nothing but tensors."""
    import torch

    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        pth = z.read("policy.pth")
    try:
        torch.load(io.BytesIO(pth), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        return True
    except Exception:  # noqa: BLE001 - damaged: reported as too small by the caller
        return False
    return False


def _check_decision(path: Path, algo: str, decision: Any) -> None:
    """The decision rule a model records (``pneugym_decision``), checked for its algorithm."""
    from .learned import check_decision

    if decision is None:
        return
    d = check_decision(decision, f"{path}: pneugym_decision")
    if d["rule"] in ("quantile", "hazard") and algo == "dqn":
        raise ValueError(f"{path}: pneugym_decision: the {d['rule']} rule needs a stochastic "
                         f"policy (PPO, A2C); this is a DQN model")
    if d["rule"] == "advantage" and algo != "dqn":
        raise ValueError(f"{path}: pneugym_decision: the advantage rule needs a Q-network "
                         f"(DQN); this is a {algo.upper()} model")
    if d["rule"] != "argmax" and "value" not in d:
        raise ValueError(f"{path}: pneugym_decision has the {d['rule']} rule without a value")


def _check_action_space(path: Path, entry: Any) -> None:
    """Refuse a model whose action space is not the cut-off's Discrete(2)."""
    if not isinstance(entry, dict):
        return
    kind = entry.get(":type:")
    if isinstance(kind, str) and "Discrete" not in kind:
        raise ValueError(f"{path}: the model's action space is {kind}; the cut-off environment's "
                         f"is Discrete(2) (keep, cut)")
    for key, want in (("n", 2), ("start", 0)):
        if key in entry:
            try:
                got = int(str(entry[key]))
            except ValueError:
                raise ValueError(f"{path}: action_space.{key} = {entry[key]!r} is not an "
                                 f"integer") from None
            if got != want:
                raise ValueError(f"{path}: the model's action space has {key} = {got}; the "
                                 f"cut-off environment's is Discrete(2) (keep, cut)")


#: ``policy_kwargs`` entries that hold a class, rebuilt from the name SB3 records beside the pickle
CLASS_KWARGS = ("activation_fn", "optimizer_class", "features_extractor_class")


def _allowed_classes() -> dict[str, type]:
    """The classes a model's ``policy_kwargs`` may name, by their recorded ``str`` (imported
    here, never by a name read from a file)."""
    from stable_baselines3.common.torch_layers import FlattenExtractor
    from torch import nn, optim

    return {str(c): c for c in (nn.ReLU, nn.Tanh, nn.SiLU, nn.ELU, nn.LeakyReLU, nn.GELU,
                                optim.Adam, optim.AdamW, optim.RMSprop, optim.SGD,
                                FlattenExtractor)}


def _policy_kwargs(path: Path, entry: Any) -> dict[str, Any]:
    """A model's ``policy_kwargs`` as plain values. A pickled dict (A2C's RMSprop, an activation
    class) is rebuilt from the JSON SB3 writes beside the pickle, its classes from
    :func:`_allowed_classes`; anything else is refused."""
    if not is_serialized(entry):
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: policy_kwargs is {entry!r}, expected an object")
        if _nested_pickle(entry):
            raise _refuse_pickle(path, "policy_kwargs")
        return entry
    hint = ("pneugym loads policy_kwargs of plain values (net_arch, actor_inputs, ...) and the "
            "classes " + ", ".join(c.__name__ for c in _allowed_classes().values()))
    if entry.get(":type:") != "<class 'dict'>":
        raise _refuse_pickle(path, "policy_kwargs", f"a {entry.get(':type:')}; {hint}")
    allowed = _allowed_classes()
    out: dict[str, Any] = {}
    for key, value in entry.items():
        if key in (":type:", SERIALIZED):
            continue
        if key in CLASS_KWARGS or (isinstance(value, str) and value.startswith("<")):
            if not isinstance(value, str) or value not in allowed:
                raise _refuse_pickle(path, "policy_kwargs", f"its {key} is "
                                     f"{value if isinstance(value, str) else repr(value)}, which "
                                     f"pneugym does not rebuild; {hint}")
            value = allowed[value]
        elif _nested_pickle(value):
            raise _refuse_pickle(path, "policy_kwargs")
        out[key] = value
    return out


def _layers(path: Path, key: str, v: Any) -> list[int]:
    if not (isinstance(v, list) and len(v) <= 64 and all(
            isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in v)):
        raise ValueError(f"{path}: policy_kwargs.{key} is {v!r}; expected a list of layer "
                         f"widths (positive integers, e.g. [64, 64])")
    return v


def _min_parameters(path: Path, algo: str, pkw: Mapping[str, Any], n_obs: int) -> int:
    """A lower bound of the parameters of the network ``policy_kwargs`` describe for ``n_obs``
    inputs: the critic's (PPO, A2C: value net) or the Q-network's MLP. Its weights must be in
    the file, so a larger count than the file holds is refused before anything is built."""
    arch = pkw.get("net_arch")
    if arch is None:
        layers = [64, 64]
    elif isinstance(arch, dict) and algo != "dqn":
        extra = sorted(set(arch) - {"pi", "vf"}, key=str)
        if extra:
            raise ValueError(f"{path}: policy_kwargs.net_arch has {extra}; expected 'pi' and "
                             f"'vf' (the actor's and the critic's layers)")
        layers = _layers(path, "net_arch.vf", arch.get("vf", []))
        _layers(path, "net_arch.pi", arch.get("pi", []))
    else:
        layers = _layers(path, "net_arch", arch)
    widths = [n_obs, *layers, 1 if algo != "dqn" else 2]
    return sum(a * b + b for a, b in zip(widths, widths[1:]))


def _policy_class(path: Path, algo: str, pkw: Mapping[str, Any], cls):
    """The policy class from the allowlist: ``cls``'s ``MlpPolicy``, or pneugym's asymmetric
    actor-critic (never a module named in the file)."""
    if "actor_inputs" in pkw:
        if algo == "dqn":
            raise ValueError(f"{path}: policy_kwargs has actor_inputs (an asymmetric "
                             f"actor-critic), which a DQN model cannot have")
        from .learned import AsymmetricActorCriticPolicy

        return AsymmetricActorCriticPolicy
    return cls.policy_aliases["MlpPolicy"]  # a class: SB3's load sets it as given


def _default(cls, key: str) -> Any:
    """The SB3 constructor's default for ``key`` (None if it has none)."""
    p = inspect.signature(cls.__init__).parameters.get(key)
    return None if p is None or p.default is inspect.Parameter.empty else p.default


def replacements(path: str | Path, algo: str, data: Mapping[str, Any], cls=None, env=None,
                 obs_size: int | None = None,
                 schedules: Mapping[str, Any] | None = None,
                 layout: Mapping[str, Any] | None = None,
                 weights_bytes: int | None = None) -> dict[str, Any]:
    """SB3 ``custom_objects`` that replace every pickled entry of ``data`` with a plain value.

    ``env`` (an SB3 VecEnv, for resuming) or ``obs_size`` (the environment's observation size,
    used if the file records neither a size nor a layout) fix the observation space;
    ``layout`` is the observation layout recorded beside the model (its run.json's), used when
    the file has no ``pneugym_layout``; ``schedules`` override :data:`SCHEDULES` (a resumed
    run's config); ``weights_bytes``, the inflated size of ``policy.pth``, bounds the network
    ``policy_kwargs`` may describe. The recorded layout and decision rule are checked, and
    every size before anything is built. Raises :class:`UnsafeModelError` for a pickled
    entry without a safe replacement, :class:`LayoutMismatchError` for a size or layout the
    environment does not have, ValueError for another action space or a malformed entry."""
    from gymnasium import spaces

    from pneugym.envs.cutoff import OBS_BOUND

    path = Path(path)
    cls = cls or algo_class(algo)
    schedules = dict(schedules or {})
    for key in ("policy_class", "observation_space", "action_space"):
        if key not in data:
            raise ValueError(f"{path}: the model's data has no {key!r}; not a complete "
                             f"stable-baselines3 model")
    bad = [k for k in NEVER_SAVED if k in data]
    if bad:
        raise UnsafeModelError(f"{path} holds {bad}, which stable-baselines3 never saves: the "
                               f"file was altered; pneugym does not load it")
    for key in ("pneugym_layout", "pneugym_decision"):  # plain JSON, checked below
        if _nested_pickle(data.get(key)):
            raise _refuse_pickle(path, key)
    pkw = _policy_kwargs(path, data.get("policy_kwargs", {}))
    out: dict[str, Any] = {"policy_class": _policy_class(path, algo, pkw, cls)}
    if "policy_kwargs" in data:
        out["policy_kwargs"] = pkw
    lay = recorded_layout(path, data, layout)
    _check_decision(path, algo, data.get("pneugym_decision"))
    env_size = int(env.observation_space.shape[0]) if env is not None else obs_size
    n, where = _obs_size(path, data, lay, env_size)
    if weights_bytes is not None:
        need = 4 * _min_parameters(path, algo, pkw, n)
        if need > weights_bytes:
            raise _WeightsTooSmall(
                f"{path}: its policy_kwargs (net_arch {pkw.get('net_arch')}) and observation "
                f"size {n} describe a network of at least {need:,} bytes of weights, but "
                f"policy.pth holds {weights_bytes:,}: the file was altered or is damaged; "
                f"pneugym does not build it")
    if env is not None:
        shape = tuple(env.observation_space.shape)
        if shape != (n,):
            raise LayoutMismatchError(f"{path}: the model takes observations of size {n} "
                                      f"({where}), the environment gives {shape}: their "
                                      f"observation layouts differ")
        out["observation_space"] = env.observation_space
    else:
        out["observation_space"] = spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(n,),
                                              dtype=np.float32)
    _check_action_space(path, data["action_space"])
    out["action_space"] = spaces.Discrete(2)
    for key in REBUILT:
        if key in data:
            out[key] = None
    for key in SCHEDULES:
        if key in data and (key in schedules or is_serialized(data[key])):
            out[key] = schedules[key] if key in schedules else _default(cls, key)
    for key, value in data.items():
        if key not in out and _nested_pickle(value):
            raise _refuse_pickle(path, key)
    return out


def load_sb3(path: str | Path, algo: str | None = None, *, cls=None, env=None,
             obs_size: int | None = None, schedules: Mapping[str, Any] | None = None,
             layout: Mapping[str, Any] | None = None, **kwargs: Any):
    """The SB3 model at ``path`` (``algo``: ``ppo``, ``dqn``, ``a2c``; None: told by its
    hyperparameters), loaded on the CPU with no pickled entry unpickled.

    ``cls`` overrides the SB3 class (a subclass of ``algo``'s, e.g. train.py's DQN); ``env``
    attaches an environment (resuming); ``obs_size`` is the fallback observation size;
    ``schedules`` replace :data:`SCHEDULES`, ``layout`` is the layout recorded beside the
    model (see :func:`replacements`); ``kwargs`` go to ``cls.load``."""
    path = Path(path)
    raw, data = read_model_data(path)
    algo = algo or guess_algo(data)
    if algo not in ALGOS:
        raise ValueError(f"{path}: cannot tell whether it is a PPO, DQN or A2C model; name the "
                         f"algorithm (got {algo!r})")
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        names = z.namelist()
        weights = z.getinfo("policy.pth").file_size if "policy.pth" in names else None
    if weights is None:
        raise ValueError(f"{path} has no policy.pth (the network's weights): not a complete "
                         f"stable-baselines3 model")
    cls = cls or algo_class(algo)
    try:
        custom = replacements(path, algo, data, cls, env, obs_size, schedules, layout, weights)
    except _WeightsTooSmall:
        if _weights_hold_objects(raw):
            raise _objects_in_weights(path) from None
        raise
    left = sorted(k for k, v in data.items() if is_serialized(v) and k not in custom)
    if left:  # never reached (replacements refuses first); kept as the last line of defence
        raise _refuse_pickle(path, left[0])
    import warnings

    try:
        with warnings.catch_warnings():  # n-step DQN: its buffer kwargs are saved, the warning is moot
            warnings.filterwarnings("ignore", message=".*n_steps=.*is ignored")
            return cls.load(io.BytesIO(raw), env=env, device="cpu", custom_objects=custom,
                            **kwargs)
    except LayoutMismatchError:
        raise
    except RuntimeError as exc:
        if "size mismatch" in str(exc):
            n = custom["observation_space"].shape[0]
            raise LayoutMismatchError(
                f"{path}: the network's weights do not fit {n} observations and 2 actions (the "
                f"size the file records): it was trained on another observation layout, or the "
                f"file is damaged. {str(exc).splitlines()[0]}") from None
        raise ValueError(f"{path}: stable-baselines3 could not load it as "
                         f"{algo.upper()}: {exc}") from exc
    except pickle.UnpicklingError:  # torch.load(weights_only=True) met an object
        raise _objects_in_weights(path) from None
    except (KeyError, TypeError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: stable-baselines3 could not load it as "
                         f"{algo.upper()}: {type(exc).__name__}: {exc}") from exc


# ------------------------------------------------------------------------------------------------
# replay buffers as plain arrays
# ------------------------------------------------------------------------------------------------
def save_replay_buffer(buffer, path: str | Path) -> Path:
    """Write an SB3 ``ReplayBuffer``'s arrays and counters (``pos``, ``full``) to ``path``
    (``.npz``), atomically. No object is pickled: ``np.load(allow_pickle=False)`` reads it."""
    path = Path(path)
    arrays = {k: getattr(buffer, k) for k in REPLAY_ARRAYS if getattr(buffer, k, None) is not None}
    for k, a in arrays.items():
        if not isinstance(a, np.ndarray) or a.dtype == object:
            raise TypeError(f"replay buffer {k} is {type(a).__name__}; only numeric arrays are "
                            f"saved")
    # a temporary beside it, created as any file is (the umask's mode, as the checkpoints)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, pos=np.int64(buffer.pos), full=np.bool_(buffer.full), **arrays)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def load_replay_buffer(buffer, path: str | Path) -> int:
    """Fill the SB3 ``ReplayBuffer`` ``buffer`` from :func:`save_replay_buffer`'s ``path``, after
    checking every array's shape and dtype against it; returns the transitions restored.
    ValueError names the file and what differs (e.g. another ``buffer_size`` or ``num_envs``)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            got = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path} is not a readable replay buffer (.npz of arrays): {exc}"
                         ) from None
    new: dict[str, np.ndarray] = {}
    for k in REPLAY_ARRAYS:
        want = getattr(buffer, k, None)
        if want is None:
            continue
        if k not in got:
            raise ValueError(f"{path} has no {k!r} array")
        a = got[k]
        if a.shape != want.shape or a.dtype != want.dtype:
            raise ValueError(f"{path}: {k} is {a.dtype}{list(a.shape)}, the model's buffer "
                             f"{want.dtype}{list(want.shape)}: keep algo.buffer_size and "
                             f"env.num_envs as in the run, or delete the file to resume with an "
                             f"empty buffer")
        new[k] = a
    pos, full = got.get("pos"), got.get("full")
    if (pos is None or full is None or pos.shape != () or full.shape != ()
            or pos.dtype.kind not in "iu" or full.dtype != np.bool_
            or not 0 <= int(pos) < buffer.buffer_size):
        raise ValueError(f"{path}: pos/full are missing or invalid (pos must be an integer in "
                         f"[0, {buffer.buffer_size}))")
    for k, a in new.items():
        getattr(buffer, k)[...] = a
    buffer.pos, buffer.full = int(pos), bool(full)
    return (buffer.buffer_size if buffer.full else buffer.pos) * buffer.n_envs
