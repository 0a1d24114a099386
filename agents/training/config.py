"""The configuration of a training run: ``configs/<algo>.yaml`` merged with a budget and ``--set``
overrides (:func:`load_config`), and checked whole (:func:`check_config`: known keys at every
level, SB3 keywords against the algorithm's constructor, types, ranges, seeds, decision rules,
environment options) before a run writes anything. Raises :class:`ConfigError` naming where a
bad value came from. Which key takes which value: :mod:`agents.training.schema`."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from .checks import Bad, Section
from .schema import config_schema
from .seeds import check_seed

ROOT = Path(__file__).resolve().parents[2]
CONFIG_DIR = ROOT / "configs"
#: Where rollouts and validation references are cached unless ``cache_dir`` says otherwise.
DEFAULT_CACHE_DIR = "runs/.cache"
ALGOS = ("ppo", "dqn", "esac")


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
                rig: Any = None, check: bool = True) -> dict[str, Any]:
    """The configuration of ``algo``: ``configs/<algo>.yaml``'s ``default`` section, merged with the
    ``budget`` section (e.g. ``quick``), then ``overrides`` (``"a.b=value"``, value parsed as YAML),
    ``preset``, ``timesteps`` and ``rig`` (``--preset``, ``--timesteps``, ``--rig``: a rig file's
    path, a mapping or a :class:`~pneugym.params.RigParams`; recorded whole). With ``check`` the whole merged
    configuration is checked (:func:`check_config`; ``seed``: the training seed, for the seed
    ranges); any problem is a :class:`ConfigError`."""
    import yaml

    path = Path(path) if path else CONFIG_DIR / f"{algo}.yaml"
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        doc = yaml.safe_load(text)
        _refuse_yaml11_ints(yaml.compose(text), path)
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
        except ConfigError as exc:
            raise ConfigError(f"--set {item!r}: {exc}") from None
        origins[".".join(parts)] = f"--set {item}"
    for key, flag in (("algo_name", "--algo"), ("budget", "--budget")):
        if key in cfg:  # train.py records them: a value from the file or --set would be lost
            raise ConfigError(f"{origins.get(key, str(path))}: {key} is set by train.py (give "
                              f"{flag}); remove it")
    if preset is not None:
        cfg["preset"], origins["preset"] = preset, "--preset"
    if timesteps is not None:
        cfg["timesteps"], origins["timesteps"] = timesteps, "--timesteps"
    if rig is not None:
        from pneugym.params import RigParams

        over = [o for o in origins if o == "rig" or o.startswith("rig.")]
        if over:
            raise ConfigError(f"{origins[over[0]]}: --rig replaces the configuration's rig "
                              f"section, so this override would be lost: write the value in "
                              f"the rig file, or leave out --rig")
        cfg["rig"] = rig.to_dict() if isinstance(rig, RigParams) else rig
        origins["rig"] = f"--rig {rig}" if not isinstance(rig, (RigParams, Mapping)) else "--rig"
    cfg["algo_name"] = algo
    cfg["budget"] = budget
    if check:
        check_config(cfg, algo, seed, origins, str(path))
    return cfg


def _refuse_yaml11_ints(root: Any, path: Path | str) -> None:
    """Refuse plain integers YAML 1.1 reads in another base (``010`` is 8) anywhere in a
    config file or ``--set`` value (``path``: what the message names)."""
    import yaml

    from pneugym.rigfile import yaml11_int

    stack = [root]
    while stack:
        node = stack.pop()
        if isinstance(node, yaml.MappingNode):
            stack += [v for kv in node.value for v in kv]
        elif isinstance(node, yaml.SequenceNode):
            stack += node.value
        elif isinstance(node, yaml.ScalarNode) and node.style is None:
            bad = yaml11_int(node.value)
            if bad is not None:
                line = f" line {node.start_mark.line + 1}:" if isinstance(path, Path) else ""
                raise ConfigError(f"{path}:{line} {node.value} would be read as {bad} (YAML 1.1 "
                                  f"reads a leading 0 as octal, 0x as hex, 1:30 as base 60): "
                                  f"write it in decimal")


def _parse_value(text: str) -> Any:
    """A ``--set`` value as YAML, with numbers like ``1e-4`` (a string in YAML 1.1) as floats;
    YAML 1.1's integers in another base (``010`` read as 8, ``0x10``, ``1:30``) are refused."""
    import yaml

    _refuse_yaml11_ints(yaml.compose(text), "the value")
    v = yaml.safe_load(text)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            pass
    return v


def _elsewhere(key: Any, sec: Section, path: str = "") -> list[str]:
    """The dotted paths where ``key`` is a known entry of ``sec``'s sections."""
    out = [f"{path}{key}"] if key in sec.fields and path else []
    for name, sub in sec.fields.items():
        if isinstance(sub, Section):
            out += _elsewhere(key, sub, f"{path}{name}.")
    return out


def _walk(node: Any, sec: Section, path: str, where, root: Section | None = None) -> None:
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
        if isinstance(spec, Section):
            _walk(node[key], spec, full, where, root)
            continue
        try:
            node[key] = spec(node[key])
        except Bad as bad:
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
        below = [v for k, v in origins.items() if k.startswith(key + ".")]
        return "; ".join(below) if below else source  # a section set entry by entry

    _walk(cfg, config_schema(algo), "", where)

    def fail(key: str, msg: str) -> ConfigError:
        return ConfigError(f"{where(key)}: {msg}")

    val = cfg["validation"]
    try:
        check_seed("validation", val["seed"], val["episodes"])
        if algo == "esac":
            test = cfg["test"]
            check_seed("test", test["seed"], test["episodes"])
    except ValueError as exc:
        sec = "validation" if "validation" in str(exc) else "test"
        key = f"{sec}.seed" if where(f"{sec}.seed") != source else f"{sec}.episodes"
        raise fail(key, str(exc)) from None
    if algo == "esac":
        n, test = cfg["timesteps"], cfg["test"]
        if seed is not None:
            try:
                check_seed("training", seed, n)
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
        _check_env(cfg, fail, privileged=False)
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
    if seed is not None and isinstance(n_env, int):
        try:  # environment i of the vector trains on seed + i
            check_seed("training", seed, max(n_env, 1))
        except ValueError as exc:
            raise fail("env.num_envs", f"{exc} (the {n_env} training environments take "
                                       f"--seed {seed} + 0..{n_env - 1})") from None
    if algo == "ppo" and cfg.get("algo", {}).get("n_steps", 2048) * n_env <= 1:
        raise fail("algo.n_steps", "algo.n_steps x env.num_envs must be > 1 (PPO's rollout)")
    _check_env(cfg, fail, privileged=bool(cfg.get("privileged_critic")))
    return cfg


def _check_env(cfg: Mapping[str, Any], fail: Callable[[str, str], Exception],
               privileged: bool) -> None:
    """The environment checks its own options (``env``, the preset and the rig)."""
    from pneugym.envs.cutoff import CutOffVectorEnv

    opts = {k: v for k, v in (cfg.get("env") or {}).items() if k != "num_envs"}
    try:
        CutOffVectorEnv(num_envs=1, preset=cfg["preset"], rig=cfg.get("rig"),
                        observe_params=privileged, **opts)
    except (ValueError, TypeError) as exc:
        keys = [k for k in opts if k in str(exc)] or list(opts) or ["env"]
        raise fail(f"env.{keys[0]}", f"env: {exc}") from None
