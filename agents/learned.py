"""What every learned policy shares: the observation layout it was trained on, checked against the
environment it is run in, and the sample history it needs, rebuilt from single samples.

A model trained with ``history=k`` sees the last ``k`` sensor samples. It runs unchanged in an
environment with the same layout, and also in one with ``history=1`` (as evaluate.py builds it):
:class:`LearnedPolicy` then stacks the samples itself, exactly as the environment would (a new
episode starts with its first sample repeated). Any other difference (features, their scales, the
time limit that scales ``time``, the control period, privileged features) is refused with a
:class:`LayoutMismatchError` that names it.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .base import Policy

#: The per-run record written by train.py next to every model.
RUN_FILE = "run.json"


class LayoutMismatchError(ValueError):
    """A saved model and an environment disagree on the observation layout."""


#: bounds of a recorded observation layout: far above any real one, low enough that a crafted
#: file cannot make a loader allocate gigabytes from a few bytes
MAX_HISTORY = 1000
MAX_FEATURES = 64
#: features every learned policy reads (the cut-off latch, the episode clock, ESAC's stroke)
REQUIRED_FEATURES = ("position", "time", "supply_cut")


def is_finite_number(v: Any) -> bool:
    """True for one finite real number (a bool, text, NaN, an integer beyond floats is not)."""
    import math

    try:
        return (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                and math.isfinite(float(v)))
    except OverflowError:  # an integer beyond any float
        return False


def _count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_features(value: Any, key: str, where: str, allow_empty: bool) -> list[str]:
    if not isinstance(value, list) or (not value and not allow_empty) \
            or len(value) > MAX_FEATURES:
        raise LayoutMismatchError(
            f"{where}: {key} is {_short(value)}; expected a list of up to {MAX_FEATURES} "
            f"features ({{'name', 'unit', 'scale', 'offset'}} objects, as observation_layout() "
            f"writes them)")
    names = []
    for i, f in enumerate(value):
        if not isinstance(f, dict):
            raise LayoutMismatchError(f"{where}: {key}[{i}] is {_short(f)}; expected a feature "
                                      f"object with 'name' and 'scale'")
        name = f.get("name")
        if not isinstance(name, str) or not name:
            raise LayoutMismatchError(f"{where}: {key}[{i}].name is {_short(name)}; expected "
                                      f"the feature's name (text)")
        if not is_finite_number(f.get("scale")) or not float(f["scale"]) > 0:
            raise LayoutMismatchError(f"{where}: {key}[{i}] ({name!r}).scale is "
                                      f"{_short(f.get('scale'))}; expected a finite number > 0")
        for opt in ("unit", "offset"):
            if opt in f and not isinstance(f[opt], str):
                raise LayoutMismatchError(f"{where}: {key}[{i}] ({name!r}).{opt} is "
                                          f"{_short(f[opt])}; expected text")
        if name in names:
            raise LayoutMismatchError(f"{where}: {key} names {name!r} twice")
        names.append(name)
    return names


def _short(v: Any, n: int = 80) -> str:
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def check_layout_record(layout: Any, where: str) -> dict[str, Any]:
    """A recorded observation layout (an SB3 zip's ``pneugym_layout``, ESAC's metadata, a
    run.json's ``observation_layout``), checked for structure and types before anything is
    built from it: ``features`` (names, finite scales > 0; ``position``, ``time`` and
    ``supply_cut`` among them), ``param_features``, ``history`` (1 to :data:`MAX_HISTORY`),
    ``size`` (= history x features + privileged features) and ``control_period_s``.
    Raises :class:`LayoutMismatchError` naming ``where`` (file and key) and the entry."""
    if not isinstance(layout, dict):
        raise LayoutMismatchError(f"{where} is {_short(layout)}; expected an object (the "
                                  f"observation_layout() of the environment it was trained on)")
    for key in ("features", "history", "size", "control_period_s"):
        if key not in layout:
            raise LayoutMismatchError(f"{where} has no {key!r}; expected the observation_layout() "
                                      f"of the environment it was trained on (features, "
                                      f"history, size, control_period_s)")
    names = _check_features(layout["features"], "features", where, allow_empty=False)
    missing = [n for n in REQUIRED_FEATURES if n not in names]
    if missing:
        raise LayoutMismatchError(f"{where}: features {names} lack {missing}; a cut-off policy "
                                  f"reads them (not a pneugym/CutOff-v0 layout)")
    params = layout.get("param_features", [])
    if params is None:
        params = []
    _check_features(params, "param_features", where, allow_empty=True)
    rig = layout.get("rig_features") or []
    _check_features(rig, "rig_features", where, allow_empty=True)
    h = layout["history"]
    if not _count(h) or not 1 <= h <= MAX_HISTORY:
        raise LayoutMismatchError(f"{where}: history is {_short(h)}; expected an integer from 1 "
                                  f"to {MAX_HISTORY} (sensor samples per observation)")
    size = layout["size"]
    want = h * len(names) + len(rig) + len(params)
    if not _count(size) or size != want:
        rig_part = f" + {len(rig)} rig features" if rig else ""
        raise LayoutMismatchError(f"{where}: size is {_short(size)}; expected {want} (history "
                                  f"{h} x {len(names)} features{rig_part} + {len(params)} "
                                  f"privileged features): the layout is inconsistent (altered "
                                  f"or damaged)")
    cp = layout["control_period_s"]
    if not is_finite_number(cp) or not float(cp) > 0:
        raise LayoutMismatchError(f"{where}: control_period_s is {_short(cp)}; expected a "
                                  f"finite number of seconds > 0")
    return layout


def _feature_key(f: Mapping[str, Any]) -> tuple:
    return (f["name"], f.get("unit"), round(float(f["scale"]), 12), f.get("offset", "0"))


def layout_differences(model: Mapping[str, Any], env: Mapping[str, Any]) -> list[str]:
    """What differs between a model's observation layout and an environment's, history aside
    (empty: compatible up to the history)."""
    diffs = []
    mf = [_feature_key(f) for f in model["features"]]
    ef = [_feature_key(f) for f in env["features"]]
    if [k[0] for k in mf] != [k[0] for k in ef]:
        diffs.append(f"features {[k[0] for k in mf]} (model) vs {[k[0] for k in ef]} (env)")
    else:
        for a, b in zip(mf, ef):
            if a != b:
                diffs.append(f"feature {a[0]!r}: unit/scale/offset {a[1:]} (model) vs {b[1:]} "
                             f"(env)" + ("; the time scale is time_limit_s" if a[0] == "time"
                                         else ""))
    mr = [_feature_key(f) for f in model.get("rig_features") or []]
    er = [_feature_key(f) for f in env.get("rig_features") or []]
    if mr != er:
        diffs.append(f"rig features {[k[0] for k in mr]} (model) vs {[k[0] for k in er]} (env): "
                     f"observe_rig or observe_commissioning differs")
    mp = [_feature_key(f) for f in model.get("param_features", [])]
    ep = [_feature_key(f) for f in env.get("param_features", [])]
    if mp != ep:
        diffs.append(f"privileged features {[k[0] for k in mp]} (model) vs {[k[0] for k in ep]} "
                     f"(env): observe_params differs")
    if abs(float(model["control_period_s"]) - float(env["control_period_s"])) > 1e-12:
        diffs.append(f"control_period_s {model['control_period_s']} (model) vs "
                     f"{env['control_period_s']} (env)")
    return diffs


def check_layout(model: Mapping[str, Any], env: Mapping[str, Any], source: str = "the model"
                 ) -> int:
    """Raise :class:`LayoutMismatchError` unless a model trained on layout ``model`` can run in an
    environment of layout ``env``. Returns the history the policy must stack itself (0: none,
    the environment's observation is the model's)."""
    diffs = layout_differences(model, env)
    hm, he = int(model["history"]), int(env["history"])
    if hm != he and he != 1:
        diffs.append(f"history {hm} (model) vs {he} (env); a model stacks single samples itself "
                     f"only in an environment with history=1")
    if diffs:
        stroke = [d for d in diffs if d.startswith("feature 'position'")]
        hint = (" The position is scaled by the rig's stroke: this model runs on rigs of its "
                "own stroke only; retrain it for this rig (pneugym train --rig FILE), or use "
                "mpc-rig (no training)." if stroke else
                " Build the environment with the options recorded in the model's run.json "
                "(env_config), or retrain.")
        raise LayoutMismatchError(
            f"{source} was trained on a different observation layout than this environment's: "
            + "; ".join(diffs) + "." + hint)
    return hm if hm != he else 0


class HistoryStack:
    """Rebuilds ``history``-sample observations from single-sample ones (``history=1``),
    exactly as the environment stacks them. Call once per environment step."""

    def __init__(self, history: int, n_features: int, n_extra: int):
        self.history, self.nf, self.n_extra = int(history), int(n_features), int(n_extra)
        self._buf: np.ndarray | None = None
        self._fresh: np.ndarray | None = None

    def reset(self, rows: np.ndarray | None = None) -> None:
        """Mark rows (default: all) as starting a new episode at their next observation."""
        if self._fresh is None:
            return
        if rows is None:
            self._fresh[:] = True
        else:
            self._fresh[np.asarray(rows)] = True

    def __call__(self, obs: np.ndarray, time_index: int) -> np.ndarray:
        b = obs.shape[0]
        if self._buf is None or self._buf.shape[0] != b:
            self._buf = np.zeros((b, self.history, self.nf), dtype=obs.dtype)
            self._fresh = np.ones(b, dtype=bool)
        sample = obs[:, :self.nf]
        # a new episode: told so, or its time feature is 0 (the reset sample)
        fresh = self._fresh | (sample[:, time_index] == 0.0)
        self._buf[~fresh, :-1] = self._buf[~fresh, 1:]
        self._buf[~fresh, -1] = sample[~fresh]
        self._buf[fresh] = sample[fresh, None, :]
        self._fresh[:] = False
        return np.concatenate([self._buf.reshape(b, -1), obs[:, self.nf:]], axis=1)


class LearnedPolicy(Policy):
    """Base of trained policies: checks the layout and stacks the history when needed.
    Subclasses implement :meth:`act_model` on observations in the model's layout."""

    name = "learned"

    def __init__(self, env_layout: Mapping[str, Any], model_layout: Mapping[str, Any],
                 source: str = "the model"):
        super().__init__(env_layout)
        self.source = source
        self.model_layout = dict(model_layout)
        nf = len(env_layout["features"])
        env_rig = list(env_layout.get("rig_features") or [])
        keep = len(model_layout.get("rig_features") or [])
        self._rig_cols: np.ndarray | None = None
        if keep < len(env_rig) and [f["name"] for f in env_rig[:keep]] == [
                f["name"] for f in model_layout.get("rig_features") or []]:
            # the environment observes rig features the model never learned to read (its
            # datasheet values, a commissioning stroke's): their columns are dropped before the
            # model sees the observation
            start = int(env_layout["history"]) * nf
            self._rig_cols = np.arange(start + keep, start + len(env_rig))
            env_layout = {**env_layout, "rig_features": env_rig[:keep],
                          "size": int(env_layout["size"]) - (len(env_rig) - keep)}
        stack = check_layout(model_layout, env_layout, source)
        extra = len(env_layout.get("param_features", [])) + len(env_layout.get("rig_features")
                                                                   or [])
        self._stack = HistoryStack(stack, nf, extra) if stack else None
        self._time_index = [f["name"] for f in env_layout["features"]].index("time")

    def begin_episodes(self, conditions) -> None:
        if self._stack is not None:
            self._stack.reset()

    def predict(self, obs: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        if self._stack is not None and episode_start is not None:
            self._stack.reset(np.flatnonzero(np.asarray(episode_start, dtype=bool).reshape(-1)))
        return super().predict(obs, state, episode_start, deterministic)

    def model_obs(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` (B, env size) in the model's layout (stacked when needed)."""
        if obs.ndim != 2 or obs.shape[1] != self.read.size:
            raise LayoutMismatchError(f"{self.source} was built for observations of size "
                                      f"{self.read.size}, got shape {obs.shape}: load it for "
                                      f"the environment it runs in")
        if self._rig_cols is not None:
            obs = np.delete(obs, self._rig_cols, axis=1)
        if self._stack is None:
            return obs
        return self._stack(obs, self._time_index)

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.act_model(self.model_obs(obs))

    def act_model(self, obs: np.ndarray) -> np.ndarray:
        raise NotImplementedError


#: How an SB3 model's network becomes a deterministic cut-off decision (see :class:`SB3Policy`).
DECISION_RULES = ("argmax", "quantile", "hazard", "advantage")
#: what each rule's ``value`` means, and its valid range
DECISION_VALUES = {
    "argmax": "a finite number (argmax does not use it)",
    "quantile": "a probability in (0, 1] (cut once P(cut by now) >= value)",
    "hazard": "a probability in (0, 1] (cut at the first step with p_cut >= value)",
    "advantage": "a finite number (cut once Q(cut) - Q(keep) >= value)",
}


def decision_value_problem(rule: str, value: Any) -> str | None:
    """What is wrong with ``value`` for the decision ``rule`` (None: nothing). ``value`` is one
    number (a bool, text, a list or NaN is not)."""
    if not is_finite_number(value):
        return f"expected {DECISION_VALUES[rule]}"
    if rule in ("quantile", "hazard") and not 0.0 < float(value) <= 1.0:
        return f"expected {DECISION_VALUES[rule]}"
    return None


def check_decision(decision: Any, where: str, per_row: bool = False) -> dict[str, Any]:
    """A decision rule (``{"rule": ..., "value": ...}``; an SB3 zip's ``pneugym_decision``, an
    override, a config entry), checked: ``rule`` one of :data:`DECISION_RULES`, ``value`` a
    finite number in the rule's range (:data:`DECISION_VALUES`), optional for ``argmax``. With
    ``per_row``, ``value`` may also be an array of such numbers (one per observation row).
    Raises ValueError naming ``where``."""
    if not isinstance(decision, Mapping):
        raise ValueError(f"{where} is {_short(decision)}; expected an object "
                         f"{{'rule': one of {list(DECISION_RULES)}, 'value': number}}")
    extra = sorted(set(decision) - {"rule", "value"}, key=str)
    if extra:
        raise ValueError(f"{where} has {extra}; a decision has only 'rule' and 'value'")
    rule = decision.get("rule")
    if not isinstance(rule, str) or rule not in DECISION_RULES:
        from pneugym.params import did_you_mean

        raise ValueError(f"{where}: the decision rule is {_short(rule)}; expected one of "
                         f"{list(DECISION_RULES)}{did_you_mean(rule, DECISION_RULES)}")
    out = {"rule": rule}
    if "value" in decision:
        value = decision["value"]
        if per_row and not isinstance(value, (str, bytes, Mapping)) and np.ndim(value) == 1:
            values = list(np.asarray(value).tolist())
        else:
            values = [value]
        for v in values:
            problem = decision_value_problem(rule, v)
            if problem:
                raise ValueError(f"{where}: the decision value is {_short(value)} for the "
                                 f"{rule} rule; {problem}")
        out["value"] = value
    return out


class SB3Policy(LearnedPolicy):
    """A saved stable-baselines3 model (PPO, DQN, A2C) behind the common interface, acting
    deterministically by one of three ``decision`` rules (``{"rule": ..., "value": ...}``):

    - ``argmax`` (default): SB3's deterministic ``predict``;
    - ``quantile`` (PPO, A2C): cut once the stochastic policy would have cut by now with
      probability ``value``, i.e. ``1 - prod(1 - p_cut) >= value`` over the episode's steps. A
      latched cut is a stopping time: this is the ``value``-quantile of the policy's own
      stopping-time distribution, where ``argmax`` (``p_cut > 0.5`` in one step) may never cut
      when the policy spreads its hazard over several steps;
    - ``hazard`` (PPO, A2C): cut at the first step whose own ``p_cut >= value`` (``argmax`` is
      ``hazard`` at 0.5);
    - ``advantage`` (DQN): cut once ``Q(cut) - Q(keep) >= value``.

    ``value`` may be an array with one entry per observation row (sweeps).

    Every rule reads the network through :meth:`network_outputs` alone: the action
    probabilities (keep, cut) of PPO's and A2C's actor, or DQN's Q-values; ``argmax`` is their
    argmax (SB3's deterministic ``predict``: the mode of the categorical distribution, the
    greedy Q action; ties go to the first, keep). ``backend`` evaluates the network (default
    the torch model, :meth:`torch_outputs`; :mod:`pneugym.deploy.export` swaps it). ``model``
    is read for ``observation_space.shape``, ``policy.actor_inputs`` (asymmetric models) and
    what its network gives (:func:`network_outputs_of`).
    """

    name = "sb3"

    def __init__(self, env_layout: Mapping[str, Any], model, model_layout: Mapping[str, Any] |
                 None = None, source: str = "the model",
                 decision: Mapping[str, Any] | None = None):
        if model_layout is None:  # an SB3 zip from elsewhere: only the size can be checked
            shape = tuple(model.observation_space.shape)
            if shape != (int(env_layout["size"]),):
                raise LayoutMismatchError(
                    f"{source} expects observations of shape {shape}, the environment gives "
                    f"({env_layout['size']},): its observation layout differs")
            model_layout = env_layout
        # an asymmetric actor-critic (critic on privileged features, actor without): it runs
        # in an environment without them, which then get zeros the actor never reads
        self.actor_inputs = getattr(model.policy, "actor_inputs", None)
        n_priv = len(model_layout.get("param_features", []))
        full = dict(model_layout)
        self._pad = 0
        if (n_priv and self.actor_inputs is not None and not env_layout.get("param_features")
                and self.actor_inputs == int(full["size"]) - n_priv):
            model_layout = actor_only_layout(full)
            self._pad = n_priv
        super().__init__(env_layout, model_layout, source)
        self.full_layout = full
        shape = tuple(model.observation_space.shape)
        if shape != (int(full["size"]),):
            raise LayoutMismatchError(f"{source}: the network takes {shape}, its recorded layout "
                                      f"has size {full['size']}")
        self.model = model
        self.outputs = network_outputs_of(model)
        if self.outputs is None:
            raise ValueError(f"{source}: {type(model).__name__} is neither an actor-critic (PPO, "
                             f"A2C) nor a Q-network (DQN) model")
        self.decision = check_decision(decision or {"rule": "argmax"},
                                       f"{source}: decision", per_row=True)
        rule = self.decision["rule"]
        if rule in ("quantile", "hazard") and self.outputs != "probs":
            raise ValueError(f"{source}: the {rule} rule needs a stochastic policy (PPO, A2C)")
        if rule == "advantage" and self.outputs != "q_values":
            raise ValueError(f"{source}: the advantage rule needs a Q-network (DQN)")
        self._backend: Callable[[np.ndarray], np.ndarray] | None = None
        self.value = np.asarray(self.decision.get("value", 0.5), dtype=float)
        names = [f["name"] for f in self.model_layout["features"]]
        base = (int(self.model_layout["history"]) - 1) * len(names)
        self._t_idx = base + names.index("time")
        self._cut_idx = base + names.index("supply_cut")
        self._log_survival: np.ndarray | None = None

    def begin_episodes(self, conditions) -> None:
        """New episodes: the history restarts, and so does the quantile rule's running survival
        (an episode whose first sample is not at time 0, on a rig, would otherwise inherit the
        last one's)."""
        super().begin_episodes(conditions)
        self._log_survival = None

    def model_obs(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` in the network's layout: stacked when needed, and zeros in the privileged
        columns of an asymmetric model's critic (its actor does not read them)."""
        x = super().model_obs(obs)
        if self._pad:
            x = np.concatenate([x, np.zeros((x.shape[0], self._pad), dtype=x.dtype)], axis=1)
        return x

    @property
    def backend(self) -> Callable[[np.ndarray], np.ndarray]:
        """The network evaluation: float32 observations in the network's layout (B, size) ->
        float32 outputs (B, 2) (see :meth:`network_outputs`)."""
        return self._backend if self._backend is not None else self.torch_outputs

    @backend.setter
    def backend(self, fn: Callable[[np.ndarray], np.ndarray] | None) -> None:
        self._backend = fn

    def torch_outputs(self, x: np.ndarray) -> np.ndarray:
        """The torch model's outputs (B, 2) [float32] for float32 observations ``x`` (B, size):
        the actor's action probabilities (PPO, A2C), the Q-values (DQN)."""
        import torch

        with torch.no_grad():
            t = torch.as_tensor(x)
            if self.outputs == "q_values":
                return self.model.q_net(t).numpy()
            return self.model.policy.get_distribution(t).distribution.probs.numpy()

    def network_outputs(self, obs: np.ndarray) -> np.ndarray:
        """The network's outputs (B, 2) [float32] for observations ``obs`` in its layout:
        probabilities of (keep, cut) for PPO and A2C, Q-values of (keep, cut) for DQN."""
        return np.asarray(self.backend(np.ascontiguousarray(obs, dtype=np.float32)),
                          dtype=np.float32)

    def act_model(self, obs: np.ndarray) -> np.ndarray:
        rule = self.decision["rule"]
        out = self.network_outputs(obs)
        if rule == "argmax":  # np.argmax, as torch's, takes the first of equal values
            return np.argmax(out, axis=1).astype(np.int64)
        if rule == "advantage":
            a = (out[:, 1] - out[:, 0]) >= self.value
        else:
            p = out[:, 1].astype(np.float64)
            if rule == "hazard":
                return ((p >= self.value) | (obs[:, self._cut_idx] > 0.5)).astype(np.int64)
            b = obs.shape[0]
            if self._log_survival is None or self._log_survival.shape[0] != b:
                self._log_survival = np.zeros(b)
            self._log_survival[obs[:, self._t_idx] == 0.0] = 0.0  # a new episode
            self._log_survival += np.log1p(-np.minimum(p, 1.0 - 1e-12))
            a = 1.0 - np.exp(self._log_survival) >= self.value
        return (a | (obs[:, self._cut_idx] > 0.5)).astype(np.int64)


def network_outputs_of(model: Any) -> str | None:
    """What an SB3 model's network gives: ``"q_values"`` (DQN: ``q_net``), ``"probs"`` (an
    actor-critic, PPO or A2C: ``policy.get_distribution``), or None. A stand-in for a model
    (an exported network, :func:`pneugym.deploy.export.load_exported`) declares it as
    ``pneugym_outputs``."""
    declared = getattr(model, "pneugym_outputs", None)
    if declared in ("probs", "q_values"):
        return declared
    if hasattr(model, "q_net"):
        return "q_values"
    if hasattr(getattr(model, "policy", None), "get_distribution"):
        return "probs"
    return None


class RunFileError(ValueError):
    """A run directory's ``run.json`` is malformed, or names a file outside the directory."""


#: ``run.json`` entries that name files of the run (relative to its directory)
RUN_PATH_KEYS = ("model", "final_model", "checkpoint")
#: other ``run.json`` entries whose type the readers rely on
_RUN_TYPES = {"algo": str, "status": str, "observation_layout": dict, "env_config": dict,
              "timesteps_done": int, "seed": int}


def load_run_file(f: Path) -> dict[str, Any]:
    """``run.json`` at ``f``, checked: a JSON object whose file entries are strings.
    Raises :class:`RunFileError` naming the file and the entry."""
    try:
        run = json.loads(Path(f).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise RunFileError(f"{f} cannot be read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise RunFileError(f"{f} is not valid JSON ({exc.msg}, line {exc.lineno}): train.py "
                           f"writes it whole; restore it, or train again into a new folder"
                           ) from None
    except RecursionError:
        raise RunFileError(f"{f} is not a run record: its JSON is nested too deeply (train.py "
                           f"writes a few levels); restore it, or train again into a new "
                           f"folder") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit
        raise RunFileError(f"{f} is not a run record train.py wrote: {exc}") from None
    if not isinstance(run, dict):
        raise RunFileError(f"{f} holds a JSON {type(run).__name__}, expected an object (the "
                           f"run record train.py writes)")
    for key in RUN_PATH_KEYS:
        if key in run and run[key] is not None and not isinstance(run[key], str):
            raise RunFileError(f"{f}: {key!r} is {run[key]!r}; expected the name of a file in "
                               f"the run directory (a string)")
    for key, kind in _RUN_TYPES.items():
        if key in run and run[key] is not None and (
                not isinstance(run[key], kind) or isinstance(run[key], bool)):
            raise RunFileError(f"{f}: {key!r} is {run[key]!r}; expected a JSON "
                               f"{'object' if kind is dict else kind.__name__}")
    return run


def read_run(path: Path) -> dict[str, Any] | None:
    """The ``run.json`` of a run directory, or of a model file's directory (its folder), if any
    (checked by :func:`load_run_file`)."""
    path = Path(path)
    p = path if path.is_dir() else path.parent
    f = p / RUN_FILE
    return load_run_file(f) if f.is_file() else None


def run_member(run_dir: Path, name: Any, key: str = "model") -> Path:
    """``run_dir / name`` for a file that ``run.json``'s ``key`` names, refused with a
    :class:`RunFileError` unless it stays inside ``run_dir``: no absolute path, no ``..``, no
    symbolic link leading out of it."""
    from pathlib import PurePosixPath, PureWindowsPath

    run_dir = Path(run_dir)
    where = f"{run_dir / RUN_FILE}: {key!r}"
    if not isinstance(name, str) or not name.strip() or "\x00" in name:
        raise RunFileError(f"{where} is {name!r}; expected the name of a file in the run "
                           f"directory")
    if (PurePosixPath(name).is_absolute() or PureWindowsPath(name).is_absolute()
            or PureWindowsPath(name).drive or ".." in PurePosixPath(name.replace("\\", "/")).parts):
        raise RunFileError(f"{where} is {name!r}, a path outside the run directory; run.json may "
                           f"only name files inside it (relative, without '..')")
    f = run_dir / name
    root = run_dir.resolve()
    if not f.resolve().is_relative_to(root):
        raise RunFileError(f"{where} is {name!r}, which leads to {f.resolve()} through a "
                           f"symbolic link: outside the run directory {root}; pneugym loads only "
                           f"files inside it")
    return f


# ------------------------------------------------------------------------------------------------
# an actor-critic whose critic alone sees the privileged features (asymmetric actor-critic)
# ------------------------------------------------------------------------------------------------
def actor_only_layout(layout: Mapping[str, Any]) -> dict[str, Any]:
    """``layout`` without its privileged features: what an asymmetric policy's actor sees."""
    out = dict(layout)
    n = len(layout.get("param_features", []))
    out["param_features"] = []
    out["size"] = int(layout["size"]) - n
    return out


def _build_asymmetric_policy():
    """The SB3 classes, built on first use (``import agents`` stays free of torch and SB3)."""
    import torch as th
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.torch_layers import MlpExtractor
    from torch import nn

    class AsymmetricMlpExtractor(nn.Module):
        """Actor MLP on the first ``actor_inputs`` features only, critic MLP on all of them."""

        def __init__(self, feature_dim: int, actor_inputs: int, net_arch, activation_fn,
                     device="auto"):
            super().__init__()
            self.actor_inputs = int(actor_inputs)
            actor = MlpExtractor(self.actor_inputs, net_arch, activation_fn, device)
            critic = MlpExtractor(feature_dim, net_arch, activation_fn, device)
            self.policy_net, self.value_net = actor.policy_net, critic.value_net
            self.latent_dim_pi, self.latent_dim_vf = actor.latent_dim_pi, critic.latent_dim_vf

        def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
            return self.forward_actor(features), self.forward_critic(features)

        def forward_actor(self, features: th.Tensor) -> th.Tensor:
            return self.policy_net(features[..., :self.actor_inputs])

        def forward_critic(self, features: th.Tensor) -> th.Tensor:
            return self.value_net(features)

    class AsymmetricActorCriticPolicy(ActorCriticPolicy):
        """SB3 ``ActorCriticPolicy`` for observations ``[public | privileged]``: the actor uses
        the first ``actor_inputs`` columns only, the critic (training only) all of them, so that
        the advantage ``J - V(s)`` of PPO loses the variance the conditions explain. The action
        never depends on the privileged columns: at evaluation they may be zeros."""

        def __init__(self, observation_space, action_space, lr_schedule, *args,
                     actor_inputs: int | None = None, **kwargs):
            n = int(observation_space.shape[0])
            self.actor_inputs = n if actor_inputs is None else int(actor_inputs)
            if not 0 < self.actor_inputs <= n:
                raise ValueError(f"actor_inputs {actor_inputs} must lie in 1..{n}")
            kwargs.setdefault("share_features_extractor", True)
            super().__init__(observation_space, action_space, lr_schedule, *args, **kwargs)

        def _build_mlp_extractor(self) -> None:
            self.mlp_extractor = AsymmetricMlpExtractor(
                self.features_dim, self.actor_inputs, self.net_arch, self.activation_fn,
                self.device)

        def _get_constructor_parameters(self) -> dict[str, Any]:
            data = super()._get_constructor_parameters()
            data["actor_inputs"] = self.actor_inputs
            return data

    AsymmetricActorCriticPolicy.__module__ = __name__
    AsymmetricActorCriticPolicy.__qualname__ = "AsymmetricActorCriticPolicy"
    AsymmetricMlpExtractor.__module__ = __name__
    AsymmetricMlpExtractor.__qualname__ = "AsymmetricMlpExtractor"
    return {"AsymmetricActorCriticPolicy": AsymmetricActorCriticPolicy,
            "AsymmetricMlpExtractor": AsymmetricMlpExtractor}


_LAZY: dict[str, Any] = {}


def __getattr__(name: str):
    """``agents.learned.AsymmetricActorCriticPolicy`` (and its extractor), built on first access
    (:mod:`agents.safe_load` names it for models trained with it; nothing is looked up by a
    name read from a file)."""
    if name in ("AsymmetricActorCriticPolicy", "AsymmetricMlpExtractor"):
        if not _LAZY:
            _LAZY.update(_build_asymmetric_policy())
        return _LAZY[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
