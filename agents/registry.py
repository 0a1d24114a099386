"""Build a policy by name for an environment, or load a trained one from disk."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .base import Policy
from .baselines import ConventionalPolicy, EndStrokePolicy
from .gaslaw import GasLawPerRigPolicy, GasLawPolicy
from .learned import LayoutMismatchError, SB3Policy, read_run, run_member
from .mpc import ModelPredictivePolicy
from .mpc_rig import RigModelPolicy
from .oracle import OraclePolicy
from pneugym.params import RigParams

BASELINES: dict[str, type[Policy]] = {
    "conventional": ConventionalPolicy, "endstroke": EndStrokePolicy, "gaslaw": GasLawPolicy,
    "gaslaw-rig": GasLawPerRigPolicy, "mpc": ModelPredictivePolicy, "mpc-rig": RigModelPolicy,
    "oracle": OraclePolicy,
}


def make_policy(name: str, env, **kwargs: Any) -> Policy:
    """The baseline ``name`` for ``env`` (a ``pneugym/CutOff-v0`` env, single or vector)."""
    if name not in BASELINES:
        raise ValueError(f"unknown policy {name!r}; baselines are {sorted(BASELINES)} "
                         f"(saved models are given as NAME=PATH)")
    return BASELINES[name].for_env(env, **kwargs)


def _model_file(p: Path) -> Path:
    """A run directory's model (``run.json``'s ``model``, which must lie inside the directory),
    or the file itself."""
    if p.is_dir():
        run = read_run(p)
        if run is None or "model" not in run:
            raise FileNotFoundError(f"{p} is a directory without a finished run.json (train.py "
                                    f"writes one); give the model file instead")
        f = run_member(p, run["model"], "model")
        if not f.is_file():
            raise FileNotFoundError(f"{p}/run.json names {run['model']}, which does not exist")
        return f
    return p


def _decision(f: Path, saved: Any, override: Any) -> Any:
    """The decision rule of the SB3 model ``f``: the one saved with it (``pneugym_decision``,
    checked on load), with ``override`` (``rule`` and/or ``value``) applied and checked."""
    from .learned import DECISION_VALUES, check_decision

    if override is None:
        return saved
    if not isinstance(override, dict):
        raise ValueError(f"decision override {override!r} for {f}: expected rule= and/or value=")
    base = dict(saved or {"rule": "argmax"})
    over = dict(override)
    rule = over.setdefault("rule", base["rule"])
    check_decision({"rule": rule}, f"{f}: the decision override")  # a known rule first
    if "value" not in over:
        if rule == base["rule"] and "value" in base:
            over["value"] = base["value"]
        elif rule != "argmax":
            raise ValueError(f"{f}: the decision override sets the {rule!r} rule without a "
                             f"value; give value= too ({DECISION_VALUES.get(rule, '')})")
    elif rule == "argmax":
        raise ValueError(f"{f}: the decision override gives value={over['value']!r} for the "
                         f"argmax rule, which has no value; give rule= too (quantile, hazard "
                         f"or advantage)")
    return check_decision(over, f"{f}: the decision override")


class RigMismatchWarning(UserWarning):
    """A trained policy is run on a rig other than the one it was trained on."""


def trained_rig(policy: Policy, run: dict | None):
    """The rig ``policy`` was trained on: its ESAC metadata's, else its run's ``config.rig``, else
    the thesis rig (a run without a rig trained on the thesis rig)."""
    from pneugym.params import RigParams
    from pneugym.rigfile import as_rig

    rig = getattr(policy, "trained_rig", None)
    if rig is None:
        rig = ((run or {}).get("config") or {}).get("rig")
    try:
        return as_rig(rig) if rig is not None else RigParams()
    except ValueError as exc:
        raise ValueError(f"{getattr(policy, 'source', 'the model')}: the rig it records is not a "
                         f"valid rig: {exc}") from None


def check_rig(policy: Policy, run: dict | None, env) -> None:
    """Warn (:class:`RigMismatchWarning`) when ``env``'s rig lies outside what ``policy`` was
    trained on, naming the differences: another rig than its own, or, for a policy trained on
    the rig family (preset ``family``), a rig outside the family's ranges or differing in what
    the family does not vary. Operating-point fields (supply, load) are not part of a rig's
    identity (the conditions set them)."""
    import warnings

    from pneugym.envs.conditions import PRESETS
    from pneugym.envs.family import apply_changes
    from pneugym.rigfile import describe_difference, rig_fields

    trained = trained_rig(policy, run)
    policy.trained_rig = trained
    here = env.unwrapped.rig
    point = _operating_point(here)
    preset = trained_preset(policy, run)
    family = PRESETS[preset].family if preset in PRESETS else None
    outside: list[str] = []
    if family is not None:  # the family's own fields may differ, within its ranges
        mine = rig_fields(here)
        trained = apply_changes(trained, tuple((k, mine[k]) for k in family.fields))
        outside = family.outside(here, trained)
    diff = describe_difference(trained.with_(**point), here, largest_first=True)
    if diff or outside:
        what = "; ".join(x for x in (diff, ", ".join(outside)) if x)
        warnings.warn(f"{getattr(policy, 'source', 'the model')} was trained on "
                      f"{'the rig family' if family else 'another rig'}; this environment's rig "
                      f"lies outside it: {what} (retrain it for this rig: pneugym train --rig "
                      f"FILE)", RigMismatchWarning, stacklevel=3)


def _operating_point(rig: RigParams) -> dict[str, Any]:
    """The fields of ``rig`` that are not part of its identity (the conditions set them)."""
    return {"supply_pressure_gauge_pa": rig.supply_pressure_gauge_pa,
            "load_mass_kg": rig.load_mass_kg, "effects": {"sensor_lag_s": rig.effects.sensor_lag_s}}


def _check_commissioned_rig(policy: Policy, env) -> None:
    """Warn (:class:`RigMismatchWarning`) when a commissioned model's rig file is not the
    environment's rig: ``mpc-rig`` plans on the model's rig whatever rig it runs on."""
    import warnings

    from pneugym.rigfile import describe_difference

    here = env.unwrapped.rig
    diff = describe_difference(policy.model.stated.with_(**_operating_point(here)), here,
                               largest_first=True)
    if diff:
        warnings.warn(f"{policy.source} was commissioned on another rig; this environment's rig "
                      f"differs: {diff} (commission it on this rig: pneugym commission RUNS "
                      f"--rig FILE)", RigMismatchWarning, stacklevel=3)


def trained_preset(policy: Policy, run: dict | None) -> str | None:
    """The condition preset ``policy`` was trained on (its run's, or ESAC metadata's)."""
    return getattr(policy, "trained_preset", None) or ((run or {}).get("config") or {}).get(
        "preset")


def _run_conditions(run: dict | None) -> Any:
    """The ``env.conditions`` overrides a run's ``run.json`` records (None: none)."""
    return (((run or {}).get("config") or {}).get("env") or {}).get("conditions")


def training_space(policy: Policy, run: dict | None):
    """The :class:`~pneugym.envs.ConditionSpace` ``policy`` was trained on: its preset (its
    run's or ESAC metadata's) with the ``env.conditions`` overrides it recorded, on the rig it
    was trained on; None when the model records no preset."""
    from pneugym.envs.conditions import resolve

    preset = trained_preset(policy, run)
    if preset is None:
        return None
    conditions = getattr(policy, "trained_conditions", None)
    if conditions is None:
        conditions = _run_conditions(run)
    try:
        return resolve(preset, conditions or None, rig=trained_rig(policy, run))
    except ValueError as exc:
        raise ValueError(f"{getattr(policy, 'source', 'the model')}: the training conditions it "
                         f"records are not valid: {exc}") from None


def check_operating_point(policy: Policy, env) -> None:
    """Warn (:class:`~agents.training.TrainingRangeWarning`) when the operating point of
    ``env``'s rig (the supply and load its rig file states) lies outside the conditions
    ``policy`` was trained on (its ``training_space``), naming what lies outside."""
    import warnings

    from agents.training.validation import RETRAIN_OVER_RANGE, TrainingRangeWarning

    space = getattr(policy, "training_space", None)
    if space is None:
        return
    rig = env.unwrapped.rig
    what = space.outside(rig.supply_pressure_gauge_pa, rig.load_mass_kg)
    if what:
        warnings.warn(f"{getattr(policy, 'source', 'the model')}: this rig's operating point "
                      f"lies outside the conditions it was trained on ({'; '.join(what)}); "
                      f"there its decisions extrapolate (retrain it over them: pneugym train "
                      f"... {RETRAIN_OVER_RANGE})", TrainingRangeWarning, stacklevel=3)


def load_policy(path: str | Path, env, **kwargs: Any) -> Policy:
    """A trained policy for ``env``: a run directory of train.py, an ESAC model (``.pt``), a
    stable-baselines3 ``.zip`` (PPO, DQN or A2C), a Gas-Law K calibration (``.json``, from
    ``python -m agents.gaslaw --out``) or a commissioned rig model (a folder of ``pneugym
    commission``, planned on by ``mpc-rig``). A model trained on another rig than ``env``'s is loaded
    with a :class:`RigMismatchWarning` naming the differences. The model's observation layout (recorded in the
    file, or in its run's ``run.json``) must match the environment's up to the history, else a
    :class:`~agents.learned.LayoutMismatchError` says what differs. ``kwargs`` override the ESAC
    rule's parameters, or (``decision=``, a dict of ``rule`` and/or ``value``, and nothing
    else) an SB3 model's decision rule (default: the one train.py tuned and saved with the
    model); both are checked, and an override meant for the other kind of model is refused.

    Nothing in the file is unpickled (:mod:`agents.safe_load`): a model holding a pickled object
    pneugym cannot replace by a plain value is refused (:class:`~agents.safe_load.
    UnsafeModelError`)."""
    import zipfile

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no saved model at {path}")
    if (p / "commissioning.json").is_file() or p.name == "commissioning.json":
        if kwargs:  # a commissioned rig model (pneugym commission): mpc-rig plans on it
            raise ValueError(f"{p} is a commissioned rig model: it takes no overrides, got "
                             f"{sorted(kwargs)}")
        pol = RigModelPolicy.for_env(env, model=p)
        _check_commissioned_rig(pol, env)
        return pol
    f = _model_file(p)
    layout = env.unwrapped.observation_layout()
    if f.suffix.lower() == ".json":  # a Gas-Law K calibration (python -m agents.gaslaw --out)
        from .gaslaw import k_table, read_calibration, rule_options

        if kwargs:
            raise ValueError(f"{f} is a Gas-Law calibration: it takes no overrides, got "
                             f"{sorted(kwargs)}")
        data = read_calibration(f)
        pol = GasLawPolicy.for_env(env, k=k_table(data), **rule_options(data))  # its formula
        pol.source, pol.trained_rig = f"Gas-Law calibration {f}", data.get("rig")
        check_rig(pol, None, env)
        return pol
    run = read_run(f.parent)
    from . import esac

    if f.suffix == ".pt" or (run or {}).get("algo") == "esac":
        if "decision" in kwargs:
            raise ValueError(f"{f} is an ESAC model: rule= and value= override the decision "
                             f"of a stable-baselines3 model; ESAC's rule parameters are "
                             f"{sorted(esac.RULE_PARAMETERS)}")
        pol = esac.load_policy(f, layout, **kwargs)
        check_rig(pol, run, env)
        pol.training_space = training_space(pol, run)
        check_operating_point(pol, env)
        return pol
    if not zipfile.is_zipfile(f):
        raise ValueError(f"{path} is not a stable-baselines3 model (.zip), nor an ESAC model "
                         f"(.pt)")
    extra = sorted(set(kwargs) - {"decision"})
    if extra:
        esac_keys = [k for k in extra if k in esac.RULE_PARAMETERS]
        raise ValueError(f"{f} is a stable-baselines3 model: its decision override takes rule= "
                         f"and value= only, not {extra}"
                         + (f" ({esac_keys} are ESAC rule parameters)" if esac_keys else ""))
    from .safe_load import ALGOS, load_sb3

    algo = (run or {}).get("algo")
    run_layout = (run or {}).get("observation_layout")
    model = load_sb3(f, algo if algo in ALGOS else None, obs_size=int(layout["size"]),
                     layout=run_layout)
    model_layout = model.__dict__.get("pneugym_layout") or run_layout
    decision = _decision(f, model.__dict__.get("pneugym_decision"), kwargs.get("decision"))
    pol = SB3Policy(layout, model, model_layout, source=f"model {f}", decision=decision)
    check_rig(pol, run, env)
    pol.trained_preset = trained_preset(pol, run)
    pol.trained_conditions = _run_conditions(run)
    pol.training_space = training_space(pol, run)
    check_operating_point(pol, env)
    return pol


__all__ = ["BASELINES", "make_policy", "load_policy", "SB3Policy", "LayoutMismatchError",
           "RigMismatchWarning", "check_rig", "trained_rig"]
