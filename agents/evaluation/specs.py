"""The policies an evaluation runs, given as specs: a baseline's name, a learned policy's bare
name (``esac``, ``ppo``, ``dqn``: its model under ``--runs``, trained on demand) or
``NAME=PATH[:key=value,...]`` of a saved model with its decision overridden (:func:`parse_spec`).
Specs that would give a wrong table are refused (:func:`check_policy_specs`), and every saved
model is loaded, and so checked, before any work (:func:`load_models`)."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Mapping, Sequence

from agents import BASELINES, make_policy
from agents.base import Policy
from agents.registry import load_policy
from pneugym.envs.cutoff import CutOffVectorEnv

DEFAULT_POLICIES = ["conventional", "endstroke", "gaslaw", "gaslaw-rig", "esac", "ppo",
                    "esac-family", "oracle"]
#: a bare name: the model under --runs, trained if missing (agents.training.NAMED_RUNS)
LEARNED = ("esac", "ppo", "dqn", "esac-family", "ppo-family")


def evaluation_env_config(env_config: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The environment options every evaluation runs with: ``env_config`` and the rig's
    datasheet values and its commissioning stroke observed (``observe_rig``,
    ``observe_commissioning``), which models trained on a family of rigs read and the others
    never see (:class:`agents.learned.LearnedPolicy` drops their columns)."""
    return {"observe_rig": True, "observe_commissioning": True, **dict(env_config or {})}


def parse_spec(spec: str) -> tuple[str, str | None, dict[str, Any]]:
    """``NAME``, or ``NAME=PATH[:key=value,...]`` of a saved model with its decision overridden:
    ESAC rule parameters (``esac10=runs/esac:max_time_increase=0.1``), or an SB3 model's
    ``rule`` and ``value`` (``ppo3=runs/ppo:rule=quantile,value=0.3``). Numbers are read as
    numbers, anything else as text; the values are checked when the model is loaded
    (:func:`agents.registry.load_policy`)."""
    if "=" not in spec:
        return spec, None, {}
    name, path = spec.split("=", 1)
    over: dict[str, Any] = {}
    head, sep, tail = path.rpartition(":")
    if sep and "=" in tail:
        path = head
        for item in tail.split(","):
            key, eq, val = (x.strip() for x in item.partition("="))
            if not eq or not key:
                raise ValueError(f"{spec!r}: overrides are key=value pairs separated by commas "
                                 f"(e.g. {name}={path}:margin=0.05,max_time_increase=0.1)")
            if not val:
                raise ValueError(f"{spec!r}: {key}= has no value; give one, e.g. {key}=0.1")
            if key in over:
                raise ValueError(f"{spec!r}: {key} is given twice")
            try:
                over[key] = float(val)
            except ValueError:
                over[key] = val
    if {"rule", "value"} & set(over):
        if set(over) - {"rule", "value"}:
            raise ValueError(f"{spec!r}: an SB3 decision override takes rule and value only; "
                             f"{sorted(set(over) - {'rule', 'value'})} are ESAC rule parameters")
        over = {"decision": over}
    return name, path, over


#: Names a saved model may not take: the references every suite runs, and the baselines.
RESERVED = ("conventional", "oracle")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


def check_policy_specs(specs: Sequence[str]) -> list[str]:
    """Refuse what would give a wrong table: a saved model under a baseline's or a reference's
    name (``conventional=runs/ppo`` would replace the reference of every oracle fraction), a
    name given twice (rows would overwrite each other), an empty or odd name. Returns the
    names in order."""
    names = []
    for spec in specs:
        name, path, _ = parse_spec(spec)
        if path is not None:
            if name in BASELINES:
                role = "a reference of every suite" if name in RESERVED else "a baseline"
                raise ValueError(f"{spec!r}: {name!r} is {role}; give the saved model another "
                                 f"name (e.g. {name}_model={path})")
            if not path:
                raise ValueError(f"{spec!r}: no model path after '='")
            if not Path(path).exists():
                hint = (" (overrides follow the path as :key=value, e.g. "
                        f"{path.rpartition(':')[0]}:margin=0.05)"
                        if ":" in path and "=" not in path.rpartition(":")[2] else "")
                raise FileNotFoundError(f"{spec!r}: no saved model at {path}{hint}")
        elif name not in BASELINES and name not in LEARNED:
            raise ValueError(f"unknown policy {spec!r}: baselines are {sorted(BASELINES)}, "
                             f"learned ones {list(LEARNED)} (trained on demand under --runs), "
                             f"saved models are given as NAME=PATH")
        if not _NAME.match(name):
            raise ValueError(f"{spec!r}: policy name {name!r} must start with a letter or digit "
                             f"and hold only letters, digits and _ . + -")
        if name in names:
            raise ValueError(f"policy name {name!r} is given twice: its rows would overwrite "
                             f"each other; give each policy its own name")
        names.append(name)
    return names


def load_models(specs: Sequence[str], runs: str | Path = "runs", budget: str = "quick",
                env_config: dict | None = None) -> dict[str, Policy]:
    """Load, and so check, every saved model the run needs before any episode or training:
    each ``NAME=PATH`` (file, layout, decision override) and each bare learned name whose run
    under ``runs`` is finished; for the others, check that train.py can train or resume them
    (:func:`agents.training.training_plan`). Returns the loaded policies by name; raises ValueError
    naming the spec and what is wrong."""
    probe = CutOffVectorEnv(num_envs=1, **evaluation_env_config(env_config))
    out: dict[str, Policy] = {}
    bare = [s for s in specs if s in LEARNED]
    todo: list[tuple[str, str, Path | str, dict[str, Any]]] = []
    if bare:
        from agents import training

        rig = (env_config or {}).get("rig")
        for name, (what, p) in training.training_plan(bare, runs, budget, rig).items():
            if what == "ready":
                todo.append((name, name, p, {}))
    for spec in specs:
        name, path, over = parse_spec(spec)
        if path is not None:
            todo.append((spec, name, path, over))
    for spec, name, path, over in todo:
        try:
            out[name] = load_policy(path, probe, **over)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{spec!r}: {exc}") from None
    return out


def resolve_learned(policies: Sequence[str], runs: str, budget: str, progress: bool = True,
                    rig: Any = None) -> list[str]:
    """Bare names of learned policies become ``NAME=PATH`` of their model under ``runs``,
    trained first (train.py's ``budget``, on ``rig``) where none is there yet."""
    names = [p for p in policies if p in LEARNED]
    if not names:
        return list(policies)
    from agents import training

    paths = training.ensure_trained(names, runs, budget, progress=progress, rig=rig)
    return [f"{p}={paths[p]}" if p in paths else p for p in policies]


def make_named_policy(spec: str, env) -> tuple[str, Policy]:
    """``(name, policy)`` of ``spec`` for ``env``: a saved model loaded, or a baseline built."""
    name, path, over = parse_spec(spec)
    if path is not None:
        return name, load_policy(path, env, **over)
    if spec not in BASELINES:
        raise SystemExit(f"unknown policy {spec!r}: baselines are {sorted(BASELINES)}, learned "
                         f"ones {list(LEARNED)}, saved models are given as NAME=PATH")
    return spec, make_policy(spec, env)
