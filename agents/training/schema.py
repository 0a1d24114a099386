"""Which keys a training configuration may hold, and the check of each (:func:`config_schema`):
the shared entries, ESAC's sections, and for PPO and DQN the keywords of the SB3 class and its
policy, read from their signatures."""
from __future__ import annotations

import math
from typing import Any, Mapping

from .checks import (Bad, Section, anything, boolean, choice, integer, is_real, list_of, mapping,
                     number, optional, signature_section, text, type_hint)
from .seeds import MAX_TRAINING_SEED


def _learning_rate(v: Any) -> Any:
    expected = "a finite number > 0, or lin_<x> (a linear decay from x > 0 to 0)"
    if isinstance(v, str) and v.startswith("lin_"):
        try:
            x = float(v[4:])
        except ValueError:
            x = math.nan
        if math.isfinite(x) and x > 0:
            return v
        raise Bad(expected, f"{v[4:]!r} after lin_ is not a number > 0")
    if not is_real(v) or v <= 0:
        raise Bad(expected, type_hint(v))
    return v


def _train_freq(v: Any) -> Any:
    expected = "an integer >= 1 (steps) or [n, 'step' | 'episode']"
    if isinstance(v, list) and len(v) == 2 and v[1] in ("step", "episode"):
        integer(1)(v[0])
        return v
    try:
        return integer(1)(v)
    except Bad:
        raise Bad(expected, type_hint(v, "integer")) from None


def _net_arch(algo: str):
    layers = list_of(integer(1, 4096), 0, 16, "layer widths (integers from 1 to 4096)")

    def check(v: Any) -> Any:
        if isinstance(v, Mapping) and algo != "dqn":
            extra = sorted(set(v) - {"pi", "vf"}, key=str)
            if extra:
                raise Bad("a list of layer widths, or {pi: [...], vf: [...]}",
                          f"{extra} are not 'pi' (actor) or 'vf' (critic)")
            return {k: layers(x) for k, x in v.items()}
        return layers(v)
    return check


#: SB3 hyperparameters: the valid values (others are checked by their default's type)
_SB3_SPECS = {
    "learning_rate": _learning_rate, "n_steps": integer(1), "batch_size": integer(2),
    "n_epochs": integer(1), "gamma": number(0, 1), "gae_lambda": number(0, 1),
    "clip_range": number(0, lo_open=True), "clip_range_vf": optional(number(0, lo_open=True)),
    "normalize_advantage": boolean, "ent_coef": number(), "vf_coef": number(0),
    "max_grad_norm": number(0, lo_open=True), "use_sde": boolean, "sde_sample_freq": integer(-1),
    "target_kl": optional(number(0, lo_open=True)), "stats_window_size": integer(1),
    "rollout_buffer_kwargs": mapping, "replay_buffer_kwargs": mapping,
    "buffer_size": integer(1), "learning_starts": integer(0), "tau": number(0, 1, lo_open=True),
    "train_freq": _train_freq, "gradient_steps": integer(-1), "optimize_memory_usage": boolean,
    "target_update_interval": integer(1), "exploration_fraction": number(0, 1),
    "exploration_initial_eps": number(0, 1), "exploration_final_eps": number(0, 1),
}


def _rig(v: Any) -> Any:
    """The rig to train on: a rig file's path or a mapping of its fields, normalised to
    :meth:`pneugym.params.RigParams.to_dict` (so that ``run.json`` records the whole rig)."""
    from pneugym.rigfile import as_rig

    if v is None:
        return None
    try:
        return as_rig(v, "rig").to_dict()
    except ValueError as exc:
        raise Bad(f"a rig file or a mapping of rig fields ({exc})") from None


#: ConditionSpace fields that a training configuration's ``env.conditions`` cannot set
_NOT_CONDITIONS = {"family": "is set by the preset (family, family-cylinders)",
                   "rig_changes": "is the top-level rig (or --rig)"}


def _conditions(v: Any) -> Any:
    """``env.conditions``: overrides of the preset's condition ranges
    (:class:`~pneugym.envs.conditions.ConditionSpace` fields, SI units: a number or a
    ``[low, high]`` pair), e.g. ``{supply_pressure_gauge_pa: [150000, 600000]}``; checked by
    the space itself."""
    from pneugym.envs.conditions import ConditionSpace

    if v is None:
        return None
    expected = ("a section of ConditionSpace fields, each a number or [low, high] in SI units "
                "(e.g. supply_pressure_gauge_pa: [150000, 600000], load_mass_kg: [2, 40])")
    if not isinstance(v, Mapping):
        raise Bad(expected, type_hint(v))
    for k in v:
        if k in _NOT_CONDITIONS:
            raise Bad(expected, f"{k} {_NOT_CONDITIONS[k]}")
    try:
        ConditionSpace().with_(**{str(k): x for k, x in v.items()})
    except (ValueError, TypeError) as exc:
        raise Bad(expected, str(exc)) from None
    return {str(k): list(x) if isinstance(x, (list, tuple)) else x for k, x in v.items()}


def config_schema(algo: str) -> Section:
    """Every key a configuration of ``algo`` may hold, with its check."""
    from agents import esac
    from agents.learned import MAX_HISTORY
    from pneugym.envs.conditions import PRESET_NAMES

    seed_spec = integer(0, MAX_TRAINING_SEED - 1)
    common = {
        "preset": choice(PRESET_NAMES), "timesteps": integer(1, 10 ** 12), "rig": _rig,
        "validation": Section({"episodes": integer(1, 100_000), "seed": seed_spec},
                              "validation entry", required=("episodes", "seed")),
        "numba_threads": integer(1, 1024), "torch_threads": integer(1, 1024), "cache_dir": text,
        "algo_name": anything, "budget": anything,  # set by load_config
    }
    if algo == "esac":
        def rule_value(name):
            def check(v):
                try:
                    return esac.check_rule({name: v}, name)[name]
                except ValueError:
                    raise Bad(esac.RULE_PARAMETERS[name][2]) from None
            return check

        fields = {
            **common,
            "env": Section({"history": integer(1, MAX_HISTORY), "observe_rig": boolean,
                            "observe_commissioning": boolean, "conditions": _conditions},
                           "ESAC environment option (ESAC trains on the environment's defaults: "
                           "only history, observe_rig, observe_commissioning and conditions are "
                           "configurable)",
                           required=("history",)),
            "test": Section({"episodes": integer(1, 100_000), "seed": seed_spec},
                            "test entry", required=("episodes", "seed")),
            "fit": Section({"hidden": list_of(integer(1, 4096), 0, 16,
                                              "layer widths (integers from 1 to 4096)"),
                            "epochs": integer(1), "batch_size": integer(1),
                            "lr": number(0, lo_open=True), "weight_decay": number(0),
                            "patience": integer(1), "time_loss": choice(["mse", "l1"]),
                            "delay_input": boolean,
                            "ensemble": integer(1, esac.MAX_MEMBERS)},
                           "fit entry (agents.esac.fit)",
                           required=("hidden", "epochs", "batch_size", "lr")),
            "rule_grid": Section({k: list_of(rule_value(k), 1, 1000, "values")
                                  for k in esac.RULE_DEFAULTS}, "ESAC rule parameter",
                                 refused={"time_demand_s": "is not tuned (the grid tunes "
                                          "the time demand as max_time_increase); give it "
                                          "when evaluating: evaluate.py NAME=PATH:"
                                          "time_demand_s=1.2"}),
            "max_stall_rate": number(0, 1), "prefer_saving_within": number(0),
            "lags": list_of(integer(0, 100_000), 1, 1000, "lags (control periods)"),
        }
        return Section(fields, "configuration entry", required=(
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
        "rig": "is the top-level rig (or --rig)"}
    # the values of the other options are checked by the environment (check_config builds it)
    env = {k: anything for k in ENV_OPTIONS if k not in env_refused}
    env.update(num_envs=integer(1, 4096), history=integer(1, MAX_HISTORY),
               conditions=_conditions)
    no_class = "is a class, which a YAML config cannot give (train.py uses SB3's default)"
    fields = {
        **common,
        "env": Section(env, "environment option (pneugym/CutOff-v0)", refused=env_refused),
        "eval_every": integer(1), "checkpoint_every": integer(1), "keep_checkpoints": integer(1, 1000),
        "decision": Section({"rule": choice(rules),
                             "grid": list_of(number(), 1, 1000, "decision values"),
                             "rules": mapping, "prefer_saving_within": number(0)},
                            "decision entry"),
        "algo": signature_section(cls, f"keyword of stable_baselines3.{cls.__name__}", {
            "policy": "is chosen by train.py (MlpPolicy; privileged_critic: the asymmetric "
                      "actor-critic)",
            "env": "is built by train.py (the env section)", "seed": "is --seed",
            "device": "is the CPU (train.py)", "verbose": "is set by train.py",
            "policy_kwargs": "is the top-level policy_kwargs section",
            "tensorboard_log": "is --out (train.py writes its logs there)",
            "_init_setup_model": "is set by train.py",
            "rollout_buffer_class": no_class, "replay_buffer_class": no_class},
            specs=_SB3_SPECS),
        "policy_kwargs": signature_section(
            pol, f"keyword of {pol.__name__}", {
                "activation_fn": no_class, "optimizer_class": no_class,
                "features_extractor_class": no_class,
                "actor_inputs": "is set by train.py (privileged_critic)"},
            skip=("observation_space", "action_space", "lr_schedule"),
            specs={"net_arch": _net_arch(algo), "features_extractor_kwargs": mapping,
                   "optimizer_kwargs": mapping}),
        "privileged_critic": boolean,
    }
    fields["policy_kwargs"].nullable = True
    if algo == "ppo":
        fields["init_cut_prob"] = optional(number(0, 1, hi_open=True))
    else:
        fields["explore_cut_prob"] = number(0, 1)
        fields["save_replay_buffer"] = boolean
    return Section(fields, "configuration entry", required=(
        "preset", "timesteps", "validation", "eval_every", "checkpoint_every"))
