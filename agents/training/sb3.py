"""Training PPO and DQN (stable-baselines3) on the batched environment: :func:`train_sb3`, with
:class:`LatchedDQN` (exploration that knows the cut-off is latched) and :class:`TrainingVecEnv`
(one class for the training and the validation environments)."""
from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.callbacks import EvalCallback

from pneugym.envs.sb3 import CutOffVecEnv

from .callbacks import AfterEval, Checkpoints, ProgressBar, StopOnRequest
from .checkpoints import load_checkpoint, restore_replay_buffer
from .config import DEFAULT_CACHE_DIR
from .rundir import atomic_save_sb3, checkpoint_of, read_run
from .seeds import MAX_TRAINING_SEED, check_seed
from .signals import StopRequest, TrainingInterrupted
from .validation import validation_conditions, validation_references


class LatchedDQN(DQN):
    """DQN whose exploration knows the cut-off is latched: a random action is a cut only
    with probability ``explore_cut_prob`` (else keep), drawn per environment, so that a
    random early cut does not end the useful part of most episodes. Loads as a plain DQN."""

    explore_cut_prob = 0.02  # train_sb3 sets each model's from the configuration

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "explore_cut_prob"]  # not in the model file

    def _random_actions(self, n: int) -> np.ndarray:
        return (np.random.rand(n) < self.explore_cut_prob).astype(np.int64)

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        action, state = self.policy.predict(observation, state, episode_start, deterministic)
        if not deterministic:
            action = np.array(action)
            if action.ndim:
                rnd = np.random.rand(action.shape[0]) < self.exploration_rate
                action[rnd] = self._random_actions(int(rnd.sum()))
            elif np.random.rand() < self.exploration_rate:
                action = self._random_actions(1)[0]
        return action, state

    def _sample_action(self, learning_starts, action_noise=None, n_envs=1):
        if self.num_timesteps < learning_starts:
            a = self._random_actions(n_envs)
            return a, a
        return super()._sample_action(learning_starts, action_noise, n_envs)


class TrainingVecEnv(CutOffVecEnv):
    """:class:`CutOffVecEnv`; with ``conditions`` and ``seed`` it always resets to them (the
    validation set). One class for both, so that SB3's EvalCallback sees the same type."""

    def __init__(self, num_envs=8, conditions=None, seed=None, **config):
        n = len(conditions) if conditions is not None else num_envs
        super().__init__(num_envs=n, **config)
        self._fixed = None if conditions is None else list(conditions)
        self._fixed_seed = seed

    def reset(self):
        if self._fixed is None:
            return super().reset()
        obs, _ = self.venv.reset(seed=self._fixed_seed, options={"conditions": self._fixed})
        self._reset_seeds()
        self._reset_options()
        return obs


def _schedule(v: Any):
    """A learning rate: a number, or ``"lin_<x>"`` for a linear decay from ``x`` to 0 (held at
    0 past the budget: SB3's last rollout may overshoot it)."""
    if isinstance(v, str) and v.startswith("lin_"):
        x = float(v[4:])
        return lambda progress: max(progress, 0.0) * x
    return float(v)


def _logger(out: Path, resume: bool):
    """SB3's logger: ``progress.csv`` in ``out``, TensorBoard event files in ``out/tb`` when
    ``tensorboard`` is installed."""
    from stable_baselines3.common.logger import Logger, make_output_format

    formats = ["csv"]
    try:
        import tensorboard  # noqa: F401
        formats.append("tensorboard")
    except ImportError:
        pass
    if resume and (out / "progress.csv").exists():  # keep the first part of the log
        n = 1
        while (out / f"progress.{n}.csv").exists():
            n += 1
        os.replace(out / "progress.csv", out / f"progress.{n}.csv")
    writers = [make_output_format(f, str(out / "tb") if f == "tensorboard" else str(out))
               for f in formats]
    return Logger(str(out), writers), formats


def train_sb3(cfg: dict[str, Any], out: Path, seed: int, resume: bool, progress: bool,
              record, stop: StopRequest | None = None, trust_pickle: bool = False
              ) -> dict[str, Any]:
    """PPO or DQN per ``cfg``; returns the summary written into ``run.json``. When ``stop``
    receives a signal, training ends at the next step with a checkpoint (atomically) and
    :class:`TrainingInterrupted` is raised; so it is on a KeyboardInterrupt."""
    algo = cfg["algo_name"]
    env_cfg = dict(cfg.get("env", {}))
    num_envs = int(env_cfg.pop("num_envs", 16))
    env_cfg["preset"] = cfg["preset"]
    if cfg.get("rig") is not None:
        env_cfg["rig"] = cfg["rig"]
    asym = bool(cfg.get("privileged_critic", False))
    if asym and algo != "ppo":
        raise ValueError("privileged_critic needs an actor-critic (ppo)")
    if asym:  # the critic sees the episode's conditions, the actor does not
        env_cfg["observe_params"] = True
    venv = TrainingVecEnv(num_envs=num_envs, **env_cfg)
    layout = venv.observation_layout()
    # the decision sweep runs the policy as evaluate.py does: without privileged features
    sweep_cfg = {k: v for k, v in env_cfg.items() if k != "observe_params"}
    val = cfg["validation"]
    check_seed("validation", int(val["seed"]), int(val["episodes"]))
    conds = validation_conditions(cfg["preset"], int(val["episodes"]), int(val["seed"]),
                                  cfg.get("rig"), env_cfg.get("conditions"))
    eval_env = TrainingVecEnv(conditions=conds, seed=int(val["seed"]), **env_cfg)
    print(f"validation references ({len(conds)} conditions, conventional and oracle) ...",
          flush=True)
    refs = validation_references(conds, sweep_cfg, int(val["seed"]),
                                 Path(cfg.get("cache_dir", DEFAULT_CACHE_DIR)))
    record(validation_references=refs)
    cls = PPO if algo == "ppo" else LatchedDQN
    total = int(cfg["timesteps"])
    kwargs = dict(cfg.get("algo", {}))
    if "learning_rate" in kwargs:
        kwargs["learning_rate"] = _schedule(kwargs["learning_rate"])
    run = read_run(out) or {}
    ckpt = checkpoint_of(out, run) if resume else None
    logger, formats = _logger(out, ckpt is not None)
    record(log_formats=formats)
    if ckpt:
        print(f"resuming from {ckpt}", flush=True)
        model = load_checkpoint(cls, algo, ckpt, venv, kwargs, layout)
        if algo == "dqn":
            restore_replay_buffer(model, ckpt, trust_pickle)
        # a fresh stream of training conditions after the resume
        # (environment i takes seed + i: all of them stay training seeds)
        venv.seed((seed + 7919 * (model.num_timesteps // 1000 + 1) % 100_000)
                  % (MAX_TRAINING_SEED - num_envs))
        model._last_obs = None
    else:
        policy, pkw = "MlpPolicy", dict(cfg.get("policy_kwargs") or {})
        if asym:
            from agents.learned import AsymmetricActorCriticPolicy
            policy = AsymmetricActorCriticPolicy
            pkw["actor_inputs"] = int(layout["size"]) - len(layout["param_features"])
        model = cls(policy, venv, seed=seed, device="cpu", verbose=0,
                    policy_kwargs=pkw or None, **kwargs)
        p_cut = cfg.get("init_cut_prob")
        if algo == "ppo" and p_cut:  # start from a policy that cuts rarely (latched action)
            with torch.no_grad():
                model.policy.action_net.bias[:] = torch.tensor(
                    [0.0, math.log(float(p_cut) / (1.0 - float(p_cut)))])
        venv.seed(seed)
    if algo == "dqn":
        model.explore_cut_prob = float(cfg.get("explore_cut_prob", 0.02))
    model.set_logger(logger)
    model.pneugym_layout = layout
    model.pneugym_decision = {"rule": "argmax"}
    done0 = int(model.num_timesteps)
    remaining = max(0, total - done0)
    after = AfterEval(out, refs, record, layout, conds, sweep_cfg, int(val["seed"]),
                      cfg.get("decision", {"rule": "argmax", "grid": [0.0]}))
    if resume and run.get("validation"):
        after.history = list(run["validation"])
        after.best = max(r["return"] for r in after.history)
    every = max(1, int(cfg["eval_every"]) // num_envs)
    evalcb = EvalCallback(eval_env, n_eval_episodes=len(conds), eval_freq=every,
                          deterministic=True, callback_after_eval=after, verbose=0, warn=False)
    ck = Checkpoints(out, int(cfg["checkpoint_every"]), int(cfg.get("keep_checkpoints", 2)),
                     bool(cfg.get("save_replay_buffer", False)), record)
    bar = ProgressBar(total, disable=not progress)
    stop = stop or StopRequest()
    t0 = time.perf_counter()
    record(status="running", timesteps=total)
    try:
        if remaining:
            model.learn(remaining, callback=[evalcb, ck, bar, StopOnRequest(stop)],
                        reset_num_timesteps=False, progress_bar=False)
    except KeyboardInterrupt:
        stop.signal = stop.signal or "SIGINT"
        if bar.bar is not None:
            bar.bar.close()
    wall = time.perf_counter() - t0
    prev_wall = float(run.get("train_wall_s", 0.0)) if ckpt else 0.0
    try:
        if stop.signal is not None:  # keep what was trained: an interruption checkpoint
            ck.init_callback(model)
            ck.save()
            record(train_wall_s=prev_wall + wall)
            raise TrainingInterrupted(stop.signal, int(model.num_timesteps))
        if not after.history or after.history[-1]["timesteps"] != model.num_timesteps:
            # validate the final model too, so that the best model is chosen among all
            after.init_callback(model)
            after.report(None)
        atomic_save_sb3(model, out / "model.zip")
        ck.init_callback(model)
        ck.save()
    finally:
        logger.close()  # progress.csv (and the TensorBoard writer) closed, not left to the GC
    best = max(after.history, key=lambda r: r["return"])
    return {"model": "best_model.zip", "final_model": "model.zip", "timesteps_done":
            int(model.num_timesteps), "train_wall_s": prev_wall + wall,
            "steps_per_s": (model.num_timesteps - done0) / wall if wall > 0 else None,
            "best": best, "decision": best["decision"], "observation_layout": layout,
            "env_config": {**env_cfg, "num_envs": num_envs}}
