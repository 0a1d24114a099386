"""The configuration of ``train.py``: ``configs/<algo>.yaml`` merged with a budget and ``--set``
overrides, and checked whole (known keys at every level, SB3 keywords against the algorithm's
constructor, types, ranges, seeds, decision rules, environment options) before a run writes
anything. Raises :class:`ConfigError` naming where a bad value came from."""
from __future__ import annotations

import copy
import inspect
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "configs"
ALGOS = ("ppo", "dqn", "esac")
MAX_TRAINING_SEED = 1_000_000  # evaluation seeds start here


# ------------------------------------------------------------------------------------------------
# configuration and files
# ------------------------------------------------------------------------------------------------
def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) \
            else copy.deepcopy(v)
    return out


class ConfigError(ValueError):
    """A training configuration train.py cannot use: an unreadable file, an unknown key, a value of
    the wrong type or out of range. Raised before anything is written; the message names where
    the entry came from (the YAML file or the ``--set`` item), the key, the value, what was
    expected and the likely mistake."""


def load_config(algo: str, budget: str = "default", path: str | Path | None = None,
                overrides: Sequence[str] = (), *, preset: str | None = None,
                timesteps: int | None = None, seed: int | None = None,
                check: bool = True) -> dict[str, Any]:
    """The configuration of ``algo``: ``configs/<algo>.yaml``'s ``default`` section, merged with the
    ``budget`` section (e.g. ``quick``), then ``overrides`` (``"a.b=value"``, value parsed as YAML),
    ``preset`` and ``timesteps`` (``--preset``, ``--timesteps``). With ``check`` the whole merged
    configuration is checked (:func:`check_config`; ``seed``: the training seed, for the seed
    ranges); any problem is a :class:`ConfigError`."""
    import yaml

    path = Path(path) if path else CONFIG_DIR / f"{algo}.yaml"
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise ConfigError(f"--config {path} cannot be read: {exc.strerror or exc}; give the path "
                          f"of a YAML file like configs/{algo}.yaml") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"--config {path} is not UTF-8 text ({exc.reason}): is it a YAML "
                          f"file?") from None
    except yaml.YAMLError as exc:
        why = ("plain YAML only: tags such as !!python/... are refused" if isinstance(
            exc, yaml.constructor.ConstructorError) else "not valid YAML")
        raise ConfigError(f"--config {path}: {why}: {' '.join(str(exc).split())}") from None
    if not isinstance(doc, Mapping) or not isinstance(doc.get("default"), Mapping):
        raise ConfigError(f"{path}: expected a mapping with a 'default' section (key: value "
                          f"entries), as configs/{algo}.yaml; got {type(doc).__name__}")
    if budget != "default" and budget not in doc:
        from pneugym.params import did_you_mean

        raise ConfigError(f"{path} has no budget {budget!r}{did_you_mean(budget, doc)}; it has "
                          f"{sorted(map(str, doc))}")
    over = doc.get(budget, {}) if budget != "default" else {}
    if not isinstance(over, Mapping):
        raise ConfigError(f"{path}: the {budget!r} budget is {over!r}; expected a section of "
                          f"overrides (key: value entries)")
    cfg = _merge(doc["default"], over)
    origins: dict[str, str] = {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key.sub=value (e.g. "
                              f"algo.learning_rate=1e-4)")
        key, val = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {item!r}: the key {key!r} has an empty part; expected "
                              f"key.sub=value (e.g. env.history=8)")
        node = cfg
        for i, part in enumerate(parts[:-1]):
            if node.get(part) is None:
                node[part] = {}
            node = node[part]
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {'.'.join(parts[:i + 1])} is {node!r}, not "
                                  f"a section with entries")
        try:
            node[parts[-1]] = _parse_value(val)
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item!r}: the value {val!r} is not valid YAML "
                              f"({' '.join(str(exc).split())})") from None
        origins[".".join(parts)] = f"--set {item}"
    for key, flag in (("algo_name", "--algo"), ("budget", "--budget")):
        if key in cfg:  # train.py records them: a value from the file or --set would be lost
            raise ConfigError(f"{origins.get(key, str(path))}: {key} is set by train.py (give "
                              f"{flag}); remove it")
    if preset is not None:
        cfg["preset"], origins["preset"] = preset, "--preset"
    if timesteps is not None:
        cfg["timesteps"], origins["timesteps"] = timesteps, "--timesteps"
    cfg["algo_name"] = algo
    cfg["budget"] = budget
    if check:
        check_config(cfg, algo, seed, origins, str(path))
    return cfg


def _parse_value(text: str) -> Any:
    """A ``--set`` value as YAML, with numbers like ``1e-4`` (a string in YAML 1.1) as floats."""
    import yaml

    v = yaml.safe_load(text)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            pass
    return v


# ------------------------------------------------------------------------------------------------
# checking a configuration: every key known, every value of its type and in its range
# ------------------------------------------------------------------------------------------------
class _Bad(Exception):
    """A value failed its check: what was expected, and the likely mistake."""

    def __init__(self, expected: str, hint: str = ""):
        super().__init__(expected)
        self.expected, self.hint = expected, hint


def _real(v: Any) -> bool:
    try:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    except OverflowError:  # an integer beyond any float
        return False


def _type_hint(v: Any, what: str = "number") -> str:
    """The likely mistake behind ``v`` where a ``what`` was expected."""
    if isinstance(v, bool):
        return f"true/false is not a {what}"
    if v is None:
        return "the entry is empty (null)"
    if isinstance(v, str):
        try:
            float(v)
        except ValueError:
            return f"it is text, not a {what}"
        return (f"YAML 1.1 reads {v} as text: in a YAML file write a decimal point and a signed "
                f"exponent (1.0e-4, 1.0e+6) or the plain number; --set reads it as a number")
    if isinstance(v, float) and not math.isfinite(v):
        return "not a finite number"
    if isinstance(v, (list, dict)):
        return f"a {type(v).__name__}, not a single {what}"
    return ""


def _bounds(lo: float | None, hi: float | None, lo_open: bool = False,
            hi_open: bool = False, integer: bool = False) -> str:
    if integer and lo is not None and hi is not None:
        return f" from {lo:,} to {hi:,}"
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""


def _int(lo: int | None = None, hi: int | None = None):
    expected = "an integer" + _bounds(lo, hi, integer=True)

    def check(v: Any) -> int:
        if isinstance(v, float) and v.is_integer():  # 1e5 from --set: a whole number
            v = int(v)
        if not isinstance(v, int) or isinstance(v, bool):
            raise _Bad(expected, _type_hint(v, "integer")
                       or (f"{v!r} is not a whole number" if _real(v) else ""))
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise _Bad(expected)
        return v
    return check


def _num(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
         hi_open: bool = False):
    expected = "a finite number" + _bounds(lo, hi, lo_open, hi_open)

    def check(v: Any) -> float:
        if not _real(v):
            raise _Bad(expected, _type_hint(v))
        if lo is not None and (v < lo or (lo_open and v == lo)) or hi is not None and (
                v > hi or (hi_open and v == hi)):
            raise _Bad(expected)
        return v
    return check


def _bool(v: Any) -> bool:
    if not isinstance(v, bool):
        raise _Bad("true or false", "text: write true or false without quotes"
                   if isinstance(v, str) else "")
    return v


def _choice(options: Sequence[str]):
    def check(v: Any) -> str:
        if not isinstance(v, str) or v not in options:
            from pneugym.params import did_you_mean

            raise _Bad(f"one of {list(options)}", did_you_mean(v, options).strip(" ()"))
        return v
    return check


def _optional(spec):
    def check(v: Any) -> Any:
        return None if v is None else spec(v)
    return check


def _list_of(spec, lo: int = 1, hi: int = 1000, what: str = "values"):
    def check(v: Any) -> list:
        if not isinstance(v, list) or not lo <= len(v) <= hi:
            raise _Bad(f"a list of {lo} to {hi} {what}", _type_hint(v, "list")
                       if not isinstance(v, list) else f"it has {len(v)}")
        out = []
        for i, x in enumerate(v):
            try:
                out.append(spec(x))
            except _Bad as bad:
                raise _Bad(f"a list of {what}; item {i} ({x!r}) is not {bad.expected}",
                           bad.hint) from None
        return out
    return check


def _mapping(v: Any) -> Any:
    if v is not None and not isinstance(v, Mapping):
        raise _Bad("a section (key: value entries) or null")
    return v


def _anything(v: Any) -> Any:
    return v


def _text(v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise _Bad("a non-empty path (text)")
    return v


def _learning_rate(v: Any) -> Any:
    expected = "a finite number > 0, or lin_<x> (a linear decay from x > 0 to 0)"
    if isinstance(v, str) and v.startswith("lin_"):
        try:
            x = float(v[4:])
        except ValueError:
            x = math.nan
        if math.isfinite(x) and x > 0:
            return v
        raise _Bad(expected, f"{v[4:]!r} after lin_ is not a number > 0")
    if not _real(v) or v <= 0:
        raise _Bad(expected, _type_hint(v))
    return v


def _train_freq(v: Any) -> Any:
    expected = "an integer >= 1 (steps) or [n, 'step' | 'episode']"
    if isinstance(v, list) and len(v) == 2 and v[1] in ("step", "episode"):
        _int(1)(v[0])
        return v
    try:
        return _int(1)(v)
    except _Bad:
        raise _Bad(expected, _type_hint(v, "integer")) from None


def _net_arch(algo: str):
    layers = _list_of(_int(1, 4096), 0, 16, "layer widths (integers from 1 to 4096)")

    def check(v: Any) -> Any:
        if isinstance(v, Mapping) and algo != "dqn":
            extra = sorted(set(v) - {"pi", "vf"}, key=str)
            if extra:
                raise _Bad("a list of layer widths, or {pi: [...], vf: [...]}",
                           f"{extra} are not 'pi' (actor) or 'vf' (critic)")
            return {k: layers(x) for k, x in v.items()}
        return layers(v)
    return check


#: SB3 hyperparameters: the valid values (others are checked by their default's type)
_SB3_SPECS = {
    "learning_rate": _learning_rate, "n_steps": _int(1), "batch_size": _int(2),
    "n_epochs": _int(1), "gamma": _num(0, 1), "gae_lambda": _num(0, 1),
    "clip_range": _num(0, lo_open=True), "clip_range_vf": _optional(_num(0, lo_open=True)),
    "normalize_advantage": _bool, "ent_coef": _num(), "vf_coef": _num(0),
    "max_grad_norm": _num(0, lo_open=True), "use_sde": _bool, "sde_sample_freq": _int(-1),
    "target_kl": _optional(_num(0, lo_open=True)), "stats_window_size": _int(1),
    "rollout_buffer_kwargs": _mapping, "replay_buffer_kwargs": _mapping,
    "buffer_size": _int(1), "learning_starts": _int(0), "tau": _num(0, 1, lo_open=True),
    "train_freq": _train_freq, "gradient_steps": _int(-1), "optimize_memory_usage": _bool,
    "target_update_interval": _int(1), "exploration_fraction": _num(0, 1),
    "exploration_initial_eps": _num(0, 1), "exploration_final_eps": _num(0, 1),
}


def _by_default(default: Any):
    """A check from a keyword's default value (for keywords without an entry in _SB3_SPECS)."""
    if isinstance(default, bool):
        return _bool
    if isinstance(default, int):
        return _int()
    if isinstance(default, float):
        return _num()
    return _anything


class _Section:
    """A configuration section: its keys and their checks (a check, or a nested section), the
    keys it must have, keys that are refused with a reason, and what its keys are."""

    def __init__(self, fields: Mapping[str, Any], what: str, required: Sequence[str] = (),
                 refused: Mapping[str, str] | None = None, nullable: bool = False):
        self.fields, self.what, self.required = dict(fields), what, tuple(required)
        self.refused, self.nullable = dict(refused or {}), nullable


def _signature_section(cls, what: str, refused: Mapping[str, str], skip: Sequence[str] = (),
                       specs: Mapping[str, Any] | None = None) -> _Section:
    """A section of the keyword arguments of ``cls`` (minus ``refused`` and ``skip``), each
    checked by ``specs`` or by its default's type."""

    fields = {}
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name == "self" or name in refused or name in skip or p.kind in (
                p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        fields[name] = (specs or {}).get(name) or _by_default(p.default)
    return _Section(fields, what, refused=refused)


def config_schema(algo: str) -> _Section:
    """Every key a configuration of ``algo`` may hold, with its check."""
    from agents.esac import RULE_DEFAULTS, RULE_PARAMETERS
    from agents.learned import MAX_HISTORY
    from pneugym.envs.conditions import PRESETS

    seed_spec = _int(0, MAX_TRAINING_SEED - 1)
    common = {
        "preset": _choice(sorted(PRESETS)), "timesteps": _int(1, 10 ** 12),
        "validation": _Section({"episodes": _int(1, 100_000), "seed": seed_spec},
                               "validation entry", required=("episodes", "seed")),
        "numba_threads": _int(1, 1024), "torch_threads": _int(1, 1024), "cache_dir": _text,
        "algo_name": _anything, "budget": _anything,  # set by load_config
    }
    if algo == "esac":
        def rule_value(name):
            def check(v):
                from agents.esac import _rule_number

                try:
                    return _rule_number(name, v)
                except ValueError:
                    raise _Bad(RULE_PARAMETERS[name][2]) from None
            return check

        fields = {
            **common,
            "env": _Section({"history": _int(1, MAX_HISTORY)}, "ESAC environment option "
                            "(ESAC trains on the environment's defaults: only history is "
                            "configurable)", required=("history",)),
            "test": _Section({"episodes": _int(1, 100_000), "seed": seed_spec},
                             "test entry", required=("episodes", "seed")),
            "fit": _Section({"hidden": _list_of(_int(1, 4096), 0, 16,
                                                "layer widths (integers from 1 to 4096)"),
                             "epochs": _int(1), "batch_size": _int(1),
                             "lr": _num(0, lo_open=True), "weight_decay": _num(0),
                             "patience": _int(1), "time_loss": _choice(["mse", "l1"]),
                             "delay_input": _bool}, "fit entry (agents.esac.fit)",
                            required=("hidden", "epochs", "batch_size", "lr")),
            "rule_grid": _Section({k: _list_of(rule_value(k), 1, 1000, "values")
                                   for k in RULE_DEFAULTS}, "ESAC rule parameter",
                                  refused={"time_demand_s": "is not tuned (the grid tunes "
                                           "the time demand as max_time_increase); give it "
                                           "when evaluating: evaluate.py NAME=PATH:"
                                           "time_demand_s=1.2"}),
            "max_stall_rate": _num(0, 1), "prefer_saving_within": _num(0),
            "lags": _list_of(_int(0, 100_000), 1, 1000, "lags (control periods)"),
        }
        return _Section(fields, "configuration entry", required=(
            "preset", "timesteps", "env", "test", "validation", "fit", "rule_grid"))
    from stable_baselines3 import DQN, PPO
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.dqn.policies import DQNPolicy

    from pneugym.envs.cutoff import _DEFAULTS as ENV_OPTIONS

    cls, pol = (PPO, ActorCriticPolicy) if algo == "ppo" else (DQN, DQNPolicy)
    rules = ("argmax", "quantile", "hazard") if algo == "ppo" else ("argmax", "advantage")
    env_refused = {
        "preset": "is the top-level preset (or --preset)",
        "observe_params": "is set by privileged_critic (the critic's privileged features)",
        "rig": "cannot be given in a config (the environment's rig is the thesis's)"}
    # the values of the other options are checked by the environment (check_config builds it)
    env = {k: _anything for k in ENV_OPTIONS if k not in env_refused}
    env.update(num_envs=_int(1, 4096), history=_int(1, MAX_HISTORY),
               conditions=_mapping)
    no_class = "is a class, which a YAML config cannot give (train.py uses SB3's default)"
    fields = {
        **common,
        "env": _Section(env, "environment option (pneugym/CutOff-v0)", refused=env_refused),
        "eval_every": _int(1), "checkpoint_every": _int(1), "keep_checkpoints": _int(1, 1000),
        "decision": _Section({"rule": _choice(rules),
                              "grid": _list_of(_num(), 1, 1000, "decision values"),
                              "rules": _mapping, "prefer_saving_within": _num(0)},
                             "decision entry"),
        "algo": _signature_section(cls, f"keyword of stable_baselines3.{cls.__name__}", {
            "policy": "is chosen by train.py (MlpPolicy; privileged_critic: the asymmetric "
                      "actor-critic)",
            "env": "is built by train.py (the env section)", "seed": "is --seed",
            "device": "is the CPU (train.py)", "verbose": "is set by train.py",
            "policy_kwargs": "is the top-level policy_kwargs section",
            "tensorboard_log": "is --out (train.py writes its logs there)",
            "_init_setup_model": "is set by train.py",
            "rollout_buffer_class": no_class, "replay_buffer_class": no_class},
            specs=_SB3_SPECS),
        "policy_kwargs": _signature_section(
            pol, f"keyword of {pol.__name__}", {
                "activation_fn": no_class, "optimizer_class": no_class,
                "features_extractor_class": no_class,
                "actor_inputs": "is set by train.py (privileged_critic)"},
            skip=("observation_space", "action_space", "lr_schedule"),
            specs={"net_arch": _net_arch(algo), "features_extractor_kwargs": _mapping,
                   "optimizer_kwargs": _mapping}),
        "privileged_critic": _bool,
    }
    fields["policy_kwargs"].nullable = True
    if algo == "ppo":
        fields["init_cut_prob"] = _optional(_num(0, 1, hi_open=True))
    else:
        fields["explore_cut_prob"] = _num(0, 1)
        fields["save_replay_buffer"] = _bool
    return _Section(fields, "configuration entry", required=(
        "preset", "timesteps", "validation", "eval_every", "checkpoint_every"))


def _elsewhere(key: Any, sec: _Section, path: str = "") -> list[str]:
    """The dotted paths where ``key`` is a known entry of ``sec``'s sections."""
    out = [f"{path}{key}"] if key in sec.fields and path else []
    for name, sub in sec.fields.items():
        if isinstance(sub, _Section):
            out += _elsewhere(key, sub, f"{path}{name}.")
    return out


def _walk(node: Any, sec: _Section, path: str, where, root: _Section | None = None) -> None:
    """Check ``node`` (a section of the configuration at dotted ``path``) against ``sec``, in
    place (values normalised, e.g. ``1e5`` -> ``100000`` for an integer)."""
    from pneugym.params import did_you_mean

    root = root or sec

    if node is None and sec.nullable:
        return
    if not isinstance(node, Mapping):
        raise ConfigError(f"{where(path)}: {path} = {node!r}: expected a section (key: value "
                          f"entries)")
    for key in list(node):
        full = f"{path}.{key}" if path else str(key)
        if key in sec.refused:
            raise ConfigError(f"{where(full)}: {full} {sec.refused[key]}; remove it")
        if key not in sec.fields:
            near = did_you_mean(key, sec.fields)
            other = [o for o in _elsewhere(key, root) if o != full]
            if not near and other:
                near = f" (did you mean {other[0]!r}?)"
            raise ConfigError(f"{where(full)}: {full!r} is not a known {sec.what}{near}; known: "
                              f"{', '.join(sorted(sec.fields))}")
        spec = sec.fields[key]
        if isinstance(spec, _Section):
            _walk(node[key], spec, full, where, root)
            continue
        try:
            node[key] = spec(node[key])
        except _Bad as bad:
            raise ConfigError(f"{where(full)}: {full} = {node[key]!r}: expected {bad.expected}"
                              + (f" ({bad.hint})" if bad.hint else "")) from None
    for key in sec.required:
        if key not in node:
            full = f"{path}.{key}" if path else key
            raise ConfigError(f"{where(full)}: {full} is missing (see configs/ for the entries "
                              f"train.py needs)")


def check_config(cfg: dict[str, Any], algo: str, seed: int | None = None,
                 origins: Mapping[str, str] | None = None, source: str = "the configuration"
                 ) -> dict[str, Any]:
    """Check a merged configuration of ``algo`` before anything is written: every key known at
    every level (the nearest known name for a typo), SB3 hyperparameters against the
    algorithm's constructor, types and ranges, the seed ranges (with the training ``seed``),
    the decision rules and grids, and the environment options (by building the environment
    once). ``origins`` maps dotted keys to where they were set (``--set ...``); other entries
    come from ``source`` (the YAML file). Raises :class:`ConfigError`; returns ``cfg``
    (normalised in place)."""
    origins = dict(origins or {})

    def where(key: str) -> str:
        parts = key.split(".")
        for n in range(len(parts), 0, -1):
            if ".".join(parts[:n]) in origins:
                return origins[".".join(parts[:n])]
        return source

    _walk(cfg, config_schema(algo), "", where)

    def fail(key: str, msg: str) -> ConfigError:
        return ConfigError(f"{where(key)}: {msg}")

    val = cfg["validation"]
    try:
        _check_seed("validation", val["seed"], val["episodes"])
        if algo == "esac":
            test = cfg["test"]
            _check_seed("test", test["seed"], test["episodes"])
    except ValueError as exc:
        sec = "validation" if "validation" in str(exc) else "test"
        key = f"{sec}.seed" if where(f"{sec}.seed") != source else f"{sec}.episodes"
        raise fail(key, str(exc)) from None
    if algo == "esac":
        n, test = cfg["timesteps"], cfg["test"]
        if seed is not None:
            try:
                _check_seed("training", seed, n)
            except ValueError as exc:
                raise fail("timesteps", f"{exc} (training rollouts: --timesteps {n} from --seed "
                                        f"{seed})") from None
            if seed < test["seed"] + test["episodes"] and test["seed"] < seed + n:
                raise fail("timesteps", f"training seeds {seed}..{seed + n - 1} overlap the "
                                        f"held-out test seeds {test['seed']}.."
                                        f"{test['seed'] + test['episodes'] - 1}: choose another "
                                        f"--seed or fewer --timesteps")
        lags = cfg.get("lags")
        if lags is not None and (lags[0] != 0 or any(b <= a for a, b in zip(lags, lags[1:]))):
            raise fail("lags", f"lags = {lags}: expected increasing control periods starting "
                               f"at 0 (as agents.esac.LAGS)")
        looks = cfg["rule_grid"].get("lookahead", [0])
        if any(looks) and not cfg["fit"].get("delay_input", False):
            raise fail("rule_grid.lookahead", "rule_grid.lookahead has 1, but the lookahead "
                       "needs a predictor trained with fit.delay_input: true")
        return cfg
    # stable-baselines3
    from agents.learned import decision_value_problem

    if cfg.get("privileged_critic") and algo != "ppo":
        raise fail("privileged_critic", "privileged_critic: true needs an actor-critic (ppo); "
                                        f"{algo} has none: set it false")
    decision = cfg.get("decision") or {"rule": "argmax", "grid": [0.0]}
    if decision.get("rules") and ({"rule", "grid"} & set(decision)):
        raise fail("decision.rule" if "rule" in decision else "decision.grid",
                   "decision has rules and rule/grid: rules tunes several rules together "
                   "and would ignore rule/grid; give one of them (to replace rules from --set: "
                   "--set decision.rules=null)")
    allowed = ("argmax", "quantile", "hazard") if algo == "ppo" else ("argmax", "advantage")
    if decision.get("rules"):
        grids = dict(decision["rules"])
        key = "decision.rules"
    elif "rule" in decision:
        grids = {decision["rule"]: decision.get("grid", [0.5])}
        key = "decision.grid"
    else:
        raise fail("decision", "decision has neither rule (with grid) nor rules: give one, "
                               "e.g. decision.rule=quantile and decision.grid=[0.2, 0.4]")
    for rule, grid in grids.items():
        if rule not in allowed:
            from pneugym.params import did_you_mean

            raise fail(key, f"{key}: rule {rule!r} is not one of {list(allowed)} for "
                            f"{algo}{did_you_mean(rule, allowed)}")
        if not isinstance(grid, list) or not grid:
            raise fail(key, f"{key}: the grid of {rule} is {grid!r}; expected a list of values")
        for v in grid:
            problem = decision_value_problem(rule, v)
            if problem:
                raise fail(key, f"{key}: {rule} value {v!r}: {problem}")
    env = cfg.get("env") or {}
    n_env = env.get("num_envs", 16)
    if algo == "ppo" and cfg.get("algo", {}).get("n_steps", 2048) * n_env <= 1:
        raise fail("algo.n_steps", "algo.n_steps x env.num_envs must be > 1 (PPO's rollout)")
    from pneugym.envs.cutoff import CutOffVectorEnv

    opts = {k: v for k, v in env.items() if k != "num_envs"}
    try:  # the environment checks its own options
        CutOffVectorEnv(num_envs=1, preset=cfg["preset"],
                        observe_params=bool(cfg.get("privileged_critic")), **opts)
    except (ValueError, TypeError) as exc:
        keys = [k for k in opts if k in str(exc)] or list(opts) or ["env"]
        raise fail(f"env.{keys[0]}", f"env: {exc}") from None
    return cfg


def _check_seed(name: str, seed: int, span: int = 1) -> None:
    if not (0 <= seed and seed + span <= MAX_TRAINING_SEED):
        what = f"seed {seed}" if span == 1 else f"seeds {seed}..{seed + span - 1}"
        raise ValueError(f"{name} {what} must lie in [0, {MAX_TRAINING_SEED}): the seeds from "
                         f"{MAX_TRAINING_SEED} up are reserved for evaluation"
                         + (", and seeds are never negative" if seed < 0 else ""))
