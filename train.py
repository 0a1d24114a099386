"""Train learned cut-off policies: stable-baselines3 PPO and DQN on the batched environment, and
the ESAC neural predictor (thesis 6.8).

    python train.py --algo ppo  --preset randomized --timesteps 1500000 --seed 0 --out runs/ppo
    python train.py --algo dqn  --out runs/dqn
    python train.py --algo esac --out runs/esac          # --timesteps = rollouts of training data
    python train.py --algo ppo --out runs/ppo --resume   # continue from the last checkpoint
    python train.py --algo ppo --budget quick            # the quick budget of configs/ppo.yaml
    python train.py --algo ppo --set algo.learning_rate=1e-4 --set env.history=8

Hyperparameters live in ``configs/<algo>.yaml`` (a ``default`` budget and a ``quick`` one that
overrides it); ``--set key.sub=value`` overrides single entries. Every run directory holds
``run.json`` (configuration, seed, package versions, observation layout, status, validation
history), the model (``model.zip`` / ``best_model.zip`` for SB3, ``model.pt`` for ESAC), the last
checkpoints and the logs (``progress.csv``; TensorBoard event files under ``tb/`` when
``tensorboard`` is installed). Files are written to a temporary name and renamed, so an interrupted run leaves its last
good checkpoint usable. Training seeds stay below 1,000,000; evaluation uses the seeds above.

Runs are never lost: a run folder that holds anything is refused unless ``--resume`` (continue its
last checkpoint; an error if there is none) or ``--force`` (start over a folder that holds a
train.py ``run.json``: lists the files train.py wrote there, then removes exactly those; other
files stay, and a non-empty folder without ``run.json`` is refused even with ``--force``). The
whole configuration (YAML file, budget, ``--set``) is checked before anything is written: unknown
keys (with the nearest known name), SB3 keywords against the algorithm's constructor, types and
ranges. SIGINT or SIGTERM stop training at the next step with a checkpoint and
``status: "interrupted"`` in ``run.json``; ``--resume`` continues from it (a second signal stops
at once; a run whose seed is not a training seed is not resumed). Checkpoints are loaded without
unpickling anything (``agents/safe_load.py``); DQN replay buffers are saved as plain arrays
(``replay_*.npz``), and the pickled ``replay_*.pkl`` of older runs are loaded only with
``--trust-pickled-replay-buffer`` (only for your own runs).
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from agents.train_config import (  # noqa: F401  (train.load_config etc. are public here too)
    ALGOS, CONFIG_DIR, MAX_TRAINING_SEED, ConfigError, _check_seed, check_config, load_config,
)

ROOT = Path(__file__).resolve().parent
DEFAULT_POLICIES = ("esac", "ppo", "dqn")  # what evaluate.py trains on demand
RUN_FILE = "run.json"


def atomic_write_json(path: Path, obj: Any) -> None:
    """Write JSON to a temporary file and rename it over ``path``
    (:func:`pneugym.outputs.atomic_write_json`, numpy values and paths converted)."""
    from pneugym.outputs import atomic_write_json as write

    write(path, obj, default=_jsonable)


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    return repr(v)


def atomic_save_sb3(model, path: Path) -> None:
    """``model.save`` to a temporary name, then rename (never a half-written zip at ``path``;
    the temporary file is removed if the save is interrupted)."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.zip")
    try:
        model.save(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_run(out: Path) -> dict[str, Any] | None:
    """``out/run.json``, checked (:func:`agents.learned.load_run_file`), or None if absent."""
    from agents.learned import load_run_file

    f = Path(out) / RUN_FILE
    return load_run_file(f) if f.is_file() else None


def replay_file(ckpt: Path, suffix: str = ".npz") -> Path:
    """The replay buffer saved with checkpoint ``ckpt`` (``replay_<steps>.npz``; ``.pkl``:
    the pickled format of older runs)."""
    return ckpt.with_name(ckpt.name.replace("ckpt_", "replay_", 1)).with_suffix(suffix)


def _threads(cfg: Mapping[str, Any]) -> None:
    """One thread each for numba and torch unless configured (the machine is small and shared;
    numba's parallel batch kernel is slower than one thread on a busy machine)."""
    import numba
    import torch

    numba.set_num_threads(max(1, min(int(cfg.get("numba_threads", 1)), numba.config.NUMBA_NUM_THREADS)))
    torch.set_num_threads(int(cfg.get("torch_threads", 1)))


# ------------------------------------------------------------------------------------------------
# validation conditions and their references
# ------------------------------------------------------------------------------------------------
def validation_conditions(preset: str, n: int, seed: int) -> list:
    """``n`` fixed conditions drawn from ``preset`` (each from ``default_rng([seed, i])``)."""
    from pneugym.envs.conditions import resolve

    space = resolve(preset)
    return [space.sample(np.random.default_rng([seed, i])) for i in range(n)]


def validation_references(conds: Sequence[Any], env_config: Mapping[str, Any], seed: int,
                          cache_dir: Path | None) -> dict[str, float]:
    """Mean returns of the conventional scheme and the (privileged) oracle on the validation
    conditions, for the oracle fraction in the logs; cached on disk."""
    from agents.esac import source_hash

    key = hashlib.sha256(json.dumps([[c.to_dict() for c in conds], sorted(
        (k, repr(v)) for k, v in env_config.items() if k != "history"), seed, source_hash()],
        sort_keys=True).encode()).hexdigest()[:16]
    path = cache_dir / f"validation-references-{key}.json" if cache_dir else None
    if path is not None and path.is_file():
        return json.loads(path.read_text())
    from agents import ConventionalPolicy, OraclePolicy
    from agents.base import run_first_episodes
    from pneugym.envs.cutoff import CutOffVectorEnv

    cfg = {k: v for k, v in env_config.items() if k not in ("preset", "conditions")}
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **cfg)
    refs = {}
    for name, pol in (("conventional", ConventionalPolicy.for_env(env)),
                      ("oracle", OraclePolicy.for_env(env))):
        refs[name] = float(np.mean(run_first_episodes(env, pol, conds, seed)["objective"]))
    if path is not None:
        atomic_write_json(path, refs)
    return refs


def oracle_fraction(ret: float, refs: Mapping[str, float]) -> float | None:
    gap = refs["oracle"] - refs["conventional"]
    return (ret - refs["conventional"]) / gap if abs(gap) > 1e-12 else None


# ------------------------------------------------------------------------------------------------
# stable-baselines3
# ------------------------------------------------------------------------------------------------
def _sb3_parts():
    """SB3 classes and the callbacks (imported lazily: ``import train`` stays light)."""
    from stable_baselines3 import DQN, PPO
    from stable_baselines3.common.callbacks import BaseCallback, EvalCallback

    from pneugym.envs.sb3 import CutOffVecEnv

    class LatchedDQN(DQN):
        """DQN whose exploration knows the cut-off is latched: a random action is a cut only
        with probability ``explore_cut_prob`` (else keep), drawn per environment, so that a
        random early cut does not end the useful part of most episodes. Loads as a plain DQN."""

        explore_cut_prob = 0.02

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

    class ProgressBar(BaseCallback):
        """A tqdm bar over the run's timesteps (SB3's own needs ``rich``)."""

        def __init__(self, total: int, disable: bool = False):
            super().__init__()
            self.total, self.disable, self.bar = total, disable, None

        def _on_training_start(self):
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, initial=min(self.num_timesteps, self.total),
                            unit="step", desc="train", disable=self.disable, smoothing=0.05)

        def _on_step(self):
            self.bar.update(self.training_env.num_envs)
            return True

        def _on_training_end(self):
            self.bar.close()

    class Checkpoints(BaseCallback):
        """Save the model (and DQN's replay buffer if asked) every ``every`` steps, atomically;
        ``run.json`` then names the new checkpoint; the oldest beyond ``keep`` are removed."""

        def __init__(self, out: Path, every: int, keep: int, replay: bool, record):
            super().__init__()
            self.out, self.every, self.keep, self.replay = out, every, keep, replay
            self.record = record
            self._next = None

        def _on_training_start(self):
            self._next = (self.num_timesteps // self.every + 1) * self.every

        def _on_step(self):
            if self.num_timesteps >= self._next:
                self._next += self.every
                self.save()
            return True

        def save(self):
            from agents.safe_load import save_replay_buffer

            d = self.out / "checkpoints"
            d.mkdir(parents=True, exist_ok=True)
            path = d / f"ckpt_{self.num_timesteps:09d}.zip"
            atomic_save_sb3(self.model, path)
            if self.replay and getattr(self.model, "replay_buffer", None) is not None:
                save_replay_buffer(self.model.replay_buffer, replay_file(path))
            self.record(checkpoint=path.relative_to(self.out).as_posix(),
                        timesteps_done=int(self.num_timesteps))
            ckpts = sorted(d.glob("ckpt_*.zip"))
            for old in ckpts[:-self.keep]:
                old.unlink(missing_ok=True)
                for suffix in (".npz", ".pkl"):
                    replay_file(old, suffix).unlink(missing_ok=True)

    class StopOnRequest(BaseCallback):
        """Ends ``learn`` at the next environment step once a stop is requested (a signal)."""

        def __init__(self, stop: StopRequest):
            super().__init__()
            self.stop = stop

        def _on_step(self):
            return self.stop.signal is None

    class AfterEval(BaseCallback):
        """After each validation of the EvalCallback (SB3's argmax decision): validate the
        configured decision rule over its grid (one batched run), log the best return and its
        oracle fraction, save a new best model atomically (with its decision), and record the
        history in ``run.json``."""

        def __init__(self, out: Path, refs, record, layout, conds, env_cfg, seed, decision):
            super().__init__()
            self.out, self.refs, self.record, self.layout = out, refs, record, layout
            self.conds, self.env_cfg, self.seed = conds, env_cfg, seed
            self.rules = decision_grids(decision)
            self.rule = "/".join(self.rules)
            self.tolerance = float(decision.get("prefer_saving_within", 0.0))
            self.history: list[dict[str, Any]] = []
            self.best = -math.inf

        def _on_step(self):
            self.report(float(self.parent.last_mean_reward))
            return True

        def report(self, argmax_return: float | None) -> None:
            rows = [r for rule, grid in self.rules.items() for r in sweep_decisions(
                self.model, self.layout, self.conds, self.env_cfg, self.seed, rule, grid)]
            top = choose_decision(rows, self.tolerance)
            ret = top["return"]
            frac = oracle_fraction(ret, self.refs)
            self.logger.record("validation/return", ret)
            self.logger.record("validation/stall_rate", top["stall_rate"])
            self.logger.record("validation/decision_value", top["value"])
            if frac is not None:
                self.logger.record("validation/oracle_fraction", frac)
            self.logger.dump(self.num_timesteps)
            decision = {"rule": top["rule"], "value": top["value"]}
            row = {"timesteps": int(self.num_timesteps), "return": ret, "oracle_fraction": frac,
                   "stall_rate": top["stall_rate"], "decision": decision,
                   "argmax_return": argmax_return, "grid": rows}
            self.history.append(row)
            self.model.pneugym_layout = self.layout
            self.model.pneugym_decision = decision  # the latest weights' tuned decision
            if ret > self.best:
                self.best = ret
                atomic_save_sb3(self.model, self.out / "best_model.zip")
                row["new_best"] = True
            self.record(validation=self.history,
                        best=max(self.history, key=lambda r: r["return"]))
            from tqdm import tqdm
            fr = f"{frac:.3f}" if frac is not None else "-"
            tqdm.write(f"validation @ {self.num_timesteps}: return {ret:.4f} ({top['rule']} "
                       f"{top['value']:g}), oracle fraction {fr}, stall {top['stall_rate']:.3f}, "
                       f"saving {top['saving']:.3f}"
                       f"{'  (new best)' if row.get('new_best') else ''}")

    return dict(PPO=PPO, DQN=LatchedDQN, EvalCallback=EvalCallback, VecEnv=TrainingVecEnv,
                ProgressBar=ProgressBar, Checkpoints=Checkpoints, AfterEval=AfterEval,
                StopOnRequest=StopOnRequest)


def sweep_decisions(model, layout: Mapping[str, Any], conds: Sequence[Any],
                    env_cfg: Mapping[str, Any], seed: int, rule: str, grid: Sequence[float]
                    ) -> list[dict[str, Any]]:
    """Mean return and stall rate of ``model`` on ``conds`` under each value of its decision
    ``rule`` (:class:`agents.learned.SB3Policy`), all in one batched run."""
    from agents.base import run_first_episodes
    from agents.learned import SB3Policy
    from pneugym.envs.cutoff import CutOffVectorEnv

    n = len(conds)
    env = CutOffVectorEnv(num_envs=n * len(grid), autoreset=False, **env_cfg)
    pol = SB3Policy(env.observation_layout(), model, layout,
                    decision={"rule": rule, "value": np.repeat(np.asarray(grid, float), n)})
    out = run_first_episodes(env, pol, list(conds) * len(grid), seed)
    return [{"rule": rule, "value": float(v),
             "return": float(np.mean(out["objective"][k * n:(k + 1) * n])),
             "stall_rate": float(np.mean(out["stalled"][k * n:(k + 1) * n])),
             "saving": float(np.mean(out["saving_ratio"][k * n:(k + 1) * n]))}
            for k, v in enumerate(grid)]


def decision_grids(decision: Mapping[str, Any]) -> dict[str, list[float]]:
    """The decision rules to tune and their grids: ``decision["rules"]`` (``{rule: grid}``), or
    the single ``decision["rule"]`` over ``decision["grid"]``."""
    if decision.get("rules"):
        return {str(k): [float(x) for x in v] for k, v in decision["rules"].items()}
    return {str(decision["rule"]): [float(x) for x in decision.get("grid", [0.5])]}


def choose_decision(rows: Sequence[Mapping[str, Any]], prefer_saving_within: float = 0.0,
                    max_stall_rate: float = math.inf) -> dict[str, Any]:
    """The validation row (``return``, ``saving``, ``stall_rate``) to act by: among the rows that
    stall at most ``max_stall_rate`` (all, if none does), the best mean return; or, with
    ``prefer_saving_within > 0``, the row that saves most among those within that much of the
    best return and stalling no more often. The objective is flat near its optimum and its
    near-ties are noise; the saving is the thesis's aim."""
    if not rows:
        raise ValueError("no validation rows to choose from")
    if prefer_saving_within < 0:
        raise ValueError(f"prefer_saving_within = {prefer_saving_within} must be >= 0")
    ok = [r for r in rows if r["stall_rate"] <= max_stall_rate] or list(rows)
    top = max(ok, key=lambda r: r["return"])
    if prefer_saving_within <= 0:
        return dict(top)
    near = [r for r in ok if r["return"] >= top["return"] - prefer_saving_within
            and r["stall_rate"] <= top["stall_rate"]]
    return dict(max(near, key=lambda r: (r.get("saving", 0.0), r["return"])))


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


def _resume_schedules(kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """The schedules a resumed model takes from its run's config (``kwargs``: the algorithm's
    keywords, ``learning_rate`` already through :func:`_schedule`); the others get SB3's
    defaults (:func:`agents.safe_load.replacements`)."""
    out = {k: kwargs[k] for k in ("learning_rate", "clip_range", "clip_range_vf") if k in kwargs}
    if "train_freq" in kwargs:
        tf = kwargs["train_freq"]
        out["train_freq"] = tuple(tf) if isinstance(tf, list) else tf
    return out


def load_checkpoint(cls, algo: str, path: Path, venv, kwargs: Mapping[str, Any],
                    layout: Mapping[str, Any]):
    """The checkpoint at ``path`` on ``venv``, loaded without unpickling anything
    (:func:`agents.safe_load.load_sb3`), its schedules from the run's config; refused with a
    :class:`~agents.learned.LayoutMismatchError` if it was trained on another layout."""
    from agents.learned import check_layout
    from agents.safe_load import load_sb3

    model = load_sb3(path, algo, cls=cls, env=venv, schedules=_resume_schedules(kwargs))
    old = model.__dict__.get("pneugym_layout")
    if old is not None and old != layout:
        check_layout(old, layout, f"checkpoint {path}")
    return model


def restore_replay_buffer(model, ckpt: Path, trust_pickle: bool = False) -> None:
    """Refill a resumed DQN's replay buffer from the arrays saved with checkpoint ``ckpt``. A
    pickled buffer (``.pkl``, older runs) is loaded only with ``trust_pickle`` (a pickle can run
    code); otherwise the run continues with an empty buffer, and says so."""
    from agents.safe_load import load_replay_buffer

    npz, pkl = replay_file(ckpt), replay_file(ckpt, ".pkl")
    if npz.is_file():
        n = load_replay_buffer(model.replay_buffer, npz)
        print(f"replay buffer restored from {npz} ({n} transitions)", flush=True)
    elif pkl.is_file() and trust_pickle:
        print(f"loading the pickled replay buffer {pkl} (--trust-pickled-replay-buffer)",
              flush=True)
        model.load_replay_buffer(pkl)
    elif pkl.is_file():
        print(f"{pkl} is a pickled replay buffer (older pneugym), which can run code when "
              f"loaded: not loaded; continuing with an empty replay buffer. If the run is your "
              f"own, pass --trust-pickled-replay-buffer to load it.", flush=True)


def train_sb3(cfg: dict[str, Any], out: Path, seed: int, resume: bool, progress: bool,
              record, stop: StopRequest | None = None, trust_pickle: bool = False
              ) -> dict[str, Any]:
    """PPO or DQN per ``cfg``; returns the summary written into ``run.json``. When ``stop``
    receives a signal, training ends at the next step with a checkpoint (atomically) and
    :class:`TrainingInterrupted` is raised; so it is on a KeyboardInterrupt."""
    import torch

    P = _sb3_parts()
    algo = cfg["algo_name"]
    env_cfg = dict(cfg.get("env", {}))
    num_envs = int(env_cfg.pop("num_envs", 16))
    env_cfg["preset"] = cfg["preset"]
    asym = bool(cfg.get("privileged_critic", False))
    if asym and algo != "ppo":
        raise ValueError("privileged_critic needs an actor-critic (ppo)")
    if asym:  # the critic sees the episode's conditions, the actor does not
        env_cfg["observe_params"] = True
    venv = P["VecEnv"](num_envs=num_envs, **env_cfg)
    layout = venv.observation_layout()
    # the decision sweep runs the policy as evaluate.py does: without privileged features
    sweep_cfg = {k: v for k, v in env_cfg.items() if k != "observe_params"}
    val = cfg["validation"]
    _check_seed("validation", int(val["seed"]), int(val["episodes"]))
    conds = validation_conditions(cfg["preset"], int(val["episodes"]), int(val["seed"]))
    eval_env = P["VecEnv"](conditions=conds, seed=int(val["seed"]), **env_cfg)
    print(f"validation references ({len(conds)} conditions, conventional and oracle) ...",
          flush=True)
    refs = validation_references(conds, sweep_cfg, int(val["seed"]),
                                 Path(cfg.get("cache_dir", "runs/.cache")))
    record(validation_references=refs)
    cls = P["PPO"] if algo == "ppo" else P["DQN"]
    total = int(cfg["timesteps"])
    kwargs = dict(cfg.get("algo", {}))
    if "learning_rate" in kwargs:
        kwargs["learning_rate"] = _schedule(kwargs["learning_rate"])
    if algo == "dqn":
        P["DQN"].explore_cut_prob = float(cfg.get("explore_cut_prob", 0.02))
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
        venv.seed(seed + 7919 * (model.num_timesteps // 1000 + 1) % 100_000)
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
    model.set_logger(logger)
    model.pneugym_layout = layout
    model.pneugym_decision = {"rule": "argmax"}
    done0 = int(model.num_timesteps)
    remaining = max(0, total - done0)
    after = P["AfterEval"](out, refs, record, layout, conds, sweep_cfg, int(val["seed"]),
                           cfg.get("decision", {"rule": "argmax", "grid": [0.0]}))
    if resume and run.get("validation"):
        after.history = list(run["validation"])
        after.best = max(r["return"] for r in after.history)
    every = max(1, int(cfg["eval_every"]) // num_envs)
    evalcb = P["EvalCallback"](eval_env, n_eval_episodes=len(conds), eval_freq=every,
                               deterministic=True, callback_after_eval=after, verbose=0,
                               warn=False)
    ck = P["Checkpoints"](out, int(cfg["checkpoint_every"]), int(cfg.get("keep_checkpoints", 2)),
                          bool(cfg.get("save_replay_buffer", False)), record)
    bar = P["ProgressBar"](total, disable=not progress)
    stop = stop or StopRequest()
    t0 = time.perf_counter()
    record(status="running", timesteps=total)
    try:
        if remaining:
            model.learn(remaining, callback=[evalcb, ck, bar, P["StopOnRequest"](stop)],
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


# ------------------------------------------------------------------------------------------------
# ESAC
# ------------------------------------------------------------------------------------------------
def train_esac(cfg: dict[str, Any], out: Path, seed: int, progress: bool, record
               ) -> dict[str, Any]:
    """Rollouts (cached), the predictor, its accuracy on held-out conditions, the rule tuned on the
    validation conditions; writes ``model.pt``, ``accuracy.json``, ``accuracy.png``,
    ``rule_sweep.json``."""
    import itertools

    from agents import esac
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    history = int(cfg["env"]["history"])
    cache = Path(cfg.get("cache_dir", "runs/.cache"))
    n_train = int(cfg["timesteps"])
    test = cfg["test"]
    val = cfg["validation"]
    _check_seed("training", seed, n_train)
    _check_seed("test", int(test["seed"]), int(test["episodes"]))
    _check_seed("validation", int(val["seed"]), int(val["episodes"]))
    if seed < int(test["seed"]) + int(test["episodes"]) and int(test["seed"]) < seed + n_train:
        raise ValueError(f"training seeds {seed}..{seed + n_train - 1} overlap the held-out test "
                         f"seeds from {test['seed']}: choose another --seed")
    env_cfg = {"history": history}
    layout = CutOffVectorEnv(num_envs=1, **env_cfg).observation_layout()
    t0 = time.perf_counter()
    print(f"rollouts: {n_train} for training, {test['episodes']} held out (cached in {cache})",
          flush=True)
    lags = tuple(int(k) for k in cfg.get("lags", esac.LAGS))
    data = esac.rollouts(cache, n_train, seed, history, cfg["preset"], lags=lags,
                         progress=progress)
    held = esac.rollouts(cache, int(test["episodes"]), int(test["seed"]), history, cfg["preset"],
                         lags=lags, progress=progress)
    t_data = time.perf_counter() - t0
    stroke = float(layout["features"][0]["scale"])
    fit = cfg["fit"]
    delay_input = bool(fit.get("delay_input", False))
    x, y, mask, episode = esac.samples(data, stroke, delay_input)
    lookahead_s = [float(d) for d in data["lag_s"] if d > 0] if delay_input else []
    net, hist = esac.fit(x, y, mask, hidden=tuple(fit["hidden"]),
                         epochs=int(fit["epochs"]), batch_size=int(fit["batch_size"]),
                         lr=float(fit["lr"]), weight_decay=float(fit.get("weight_decay", 0.0)),
                         seed=seed, patience=int(fit.get("patience", 15)),
                         time_loss=fit.get("time_loss", "mse"), groups=episode,
                         progress=progress)
    pred = esac.ESACPredictor(net, layout, delay_input, lookahead_s)
    acc = esac.accuracy(pred, held)
    atomic_write_json(out / "accuracy.json", acc)
    esac.plot_accuracy(pred, held, out / "accuracy.png",
                       title=f"ESAC on {acc['samples']} held-out rollouts (history {history})")
    print("held-out accuracy: " + ", ".join(
        f"{k} {v:.4g}" for k, v in acc.items() if isinstance(v, float)), flush=True)
    # the rule: tuned on the validation conditions
    conds = validation_conditions(cfg["preset"], int(val["episodes"]), int(val["seed"]))
    grid_cfg = cfg["rule_grid"]
    keys = list(grid_cfg)
    grid = [dict(zip(keys, vals)) for vals in itertools.product(*(grid_cfg[k] for k in keys))]
    t1 = time.perf_counter()
    sweep = esac.sweep_rule(pred, conds, grid, seed=int(val["seed"]))
    refs = validation_references(conds, {**env_cfg, "preset": cfg["preset"]}, int(val["seed"]),
                                 cache)
    best = choose_decision(sweep, float(cfg.get("prefer_saving_within", 0.0)),
                           float(cfg.get("max_stall_rate", 0.0)))
    rule = {**esac.RULE_DEFAULTS, **{k: best[k] for k in keys}}
    for r in sweep:
        r["oracle_fraction"] = oracle_fraction(r["return"], refs)
    atomic_write_json(out / "rule_sweep.json", {"grid": sweep, "chosen": best,
                                                "references": refs})
    t_sweep = time.perf_counter() - t1
    meta = {"n_in": int(x.shape[1]), "hidden": list(fit["hidden"]), "layout": layout,
            "delay_input": delay_input, "lookahead_s": lookahead_s,
            "rule": rule, "accuracy": acc, "fit": {k: v for k, v in hist.items()
                                                    if k not in ("train", "val")},
            "data": {"train_rollouts": int(data["obs"].shape[0]), "samples": int(x.shape[0]),
                     "seed": seed,
                     "test_rollouts": int(held["obs"].shape[0]), "test_seed": int(test["seed"]),
                     "preset": cfg["preset"], "pneugym_sources": esac.source_hash()},
            "provenance": provenance()}
    esac.save(out / "model.pt", net, meta)
    best_frac = oracle_fraction(best["return"], refs)
    print(f"rule tuned on {len(conds)} validation conditions: {rule} -> return "
          f"{best['return']:.4f} (oracle fraction "
          f"{best_frac if best_frac is None else round(best_frac, 3)}), stall "
          f"{best['stall_rate']:.3f}", flush=True)
    return {"model": "model.pt", "train_wall_s": time.perf_counter() - t0,
            "data_wall_s": t_data, "fit_wall_s": hist["fit_wall_s"], "sweep_wall_s": t_sweep,
            "accuracy": acc, "rule": rule, "validation_references": refs,
            "best": {"return": best["return"], "oracle_fraction": best_frac,
                     "stall_rate": best["stall_rate"]},
            "fit": {k: v for k, v in hist.items() if k not in ("train", "val")},
            "loss_history": {"train": hist["train"], "val": hist["val"]},
            "observation_layout": layout, "env_config": env_cfg}


# ------------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------------
class StopRequest:
    """A request to stop training: the name of the signal that asked (None: none yet)."""

    def __init__(self) -> None:
        self.signal: str | None = None


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by a signal (or Ctrl-C); ``run.json`` records ``status: "interrupted"``
    and the last checkpoint, from which ``--resume`` continues."""

    def __init__(self, signal_name: str, timesteps_done: int, run: dict[str, Any] | None = None):
        super().__init__(f"training interrupted by {signal_name} after {timesteps_done} "
                         f"timesteps")
        self.signal_name, self.timesteps_done, self.run = signal_name, timesteps_done, run


@contextlib.contextmanager
def stop_on_signals(stop: StopRequest, graceful: bool = True):
    """SIGINT and SIGTERM, while the block runs, request a stop (``stop.signal``): with
    ``graceful`` the first only sets it (training ends at its next step and checkpoints), a
    second raises KeyboardInterrupt; without, the first raises it. The previous handlers are
    restored after the block (handlers exist only in the main thread: elsewhere, a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        first = stop.signal is None
        stop.signal = stop.signal or name
        if graceful and first:
            print(f"\n{name}: stopping at the next step and saving a checkpoint (send it again to "
                  f"stop at once)", file=sys.stderr, flush=True)
            return
        raise KeyboardInterrupt(name)

    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.getsignal(s) for s in sigs}
    try:
        for s in sigs:
            signal.signal(s, handler)
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


#: the files train.py writes into a run directory, by exact name or pattern (``--force``
#: removes these, and only these): the run record, models, ESAC's reports, logs, and the
#: temporaries of atomic writes a killed run may leave
RUN_FILES = (RUN_FILE, "model.zip", "best_model.zip", "model.pt", "accuracy.json",
             "accuracy.png", "rule_sweep.json", "progress.csv")
RUN_PATTERNS = (r"progress\.\d+\.csv",  # the earlier parts of a resumed run's log
                r"events\.out\.tfevents\.\d+\.[\w.-]+",  # TensorBoard, runs before tb/
                r"\.(model|best_model)\.\d+\.tmp\.zip",  # atomic_save_sb3
                r"model\.pt\.\d+\.tmp",  # esac.save
                r"\.(run|accuracy|rule_sweep)\.json\.[\w.-]+\.tmp")  # atomic JSON
#: sub-folders train.py writes, and their files (the folder goes too once it is empty)
RUN_FOLDERS = {
    "checkpoints": (r"ckpt_\d{9}\.zip", r"replay_\d{9}\.(npz|pkl)",
                    r"\.ckpt_\d{9}\.\d+\.tmp\.zip", r"\.replay_\d{9}\.npz\.[\w.-]+\.tmp"),
    "tb": (r"events\.out\.tfevents\.\d+\.[\w.-]+",),
}


def run_files(out: Path) -> list[Path]:
    """The files in ``out`` that train.py writes for a run (:data:`RUN_FILES`,
    :data:`RUN_PATTERNS`, :data:`RUN_FOLDERS`): files or links with exactly those names, never
    a folder's other contents."""
    import re

    def ours(p: Path, names: Sequence[str], patterns: Sequence[str]) -> bool:
        return (p.is_file() or p.is_symlink()) and (
            p.name in names or any(re.fullmatch(pat, p.name) for pat in patterns))

    found = [p for p in out.iterdir() if ours(p, RUN_FILES, RUN_PATTERNS)]
    for sub, patterns in RUN_FOLDERS.items():
        d = out / sub
        if d.is_dir() and not d.is_symlink():
            found += [p for p in d.iterdir() if ours(p, (), patterns)]
    return sorted(found)


def checkpoint_of(out: Path, run: Mapping[str, Any]) -> Path | None:
    """The checkpoint ``run.json`` records (confined to ``out``), or None."""
    from agents.learned import run_member

    name = run.get("checkpoint")
    return None if name is None else run_member(out, name, "checkpoint")


def _resumable(out: Path, prev: Mapping[str, Any] | None, algo: str) -> Path:
    """The checkpoint ``--resume`` continues from, or a ValueError saying what to do."""
    if prev is None:
        why = "the folder does not exist" if not out.exists() else f"it has no {RUN_FILE}"
        raise ValueError(f"--resume: nothing to resume in {out}: {why}. Start a new run "
                         f"without --resume.")
    if prev.get("algo") != algo:
        raise ValueError(f"--resume: {out} holds a {prev.get('algo')} run, not {algo}")
    if algo == "esac":
        raise ValueError(f"--resume: ESAC trains in one piece and keeps no checkpoints; start "
                         f"{out} over with --force, or train into another --out")
    ckpt = checkpoint_of(out, prev)
    if ckpt is None:
        raise ValueError(f"--resume: {out / RUN_FILE} records no checkpoint (the run stopped "
                         f"before its first, due after checkpoint_every steps); start it over "
                         f"with --force")
    if not ckpt.is_file():
        raise ValueError(f"--resume: {out / RUN_FILE} names the checkpoint {prev['checkpoint']},"
                         f" which does not exist; start the run over with --force")
    return ckpt


def _resume_seed(out: Path, prev: Mapping[str, Any]) -> int:
    """The training seed a run to resume records, checked: a training seed (below
    :data:`MAX_TRAINING_SEED`), else a ValueError saying the run cannot be continued."""
    old = prev.get("seed")
    if not isinstance(old, int) or isinstance(old, bool):
        raise ValueError(f"--resume: {out / RUN_FILE} records no training seed (seed: {old!r}); "
                         f"it cannot be resumed: start it over with --force")
    try:
        _check_seed("training", old)
    except ValueError as exc:
        raise ValueError(f"--resume: {out / RUN_FILE} records seed {old}: {exc}; that run cannot "
                         f"be continued: start it over with --force and a seed below "
                         f"{MAX_TRAINING_SEED:,}") from None
    return old


def _occupied(out: Path, prev: Mapping[str, Any] | None) -> str:
    """Why a new run may not start in the non-empty ``out``, and what to do."""
    if prev is not None:
        status = prev.get("status")
        how = {"finished": "finished",
               "interrupted": f"interrupted at {prev.get('timesteps_done', 0)} timesteps",
               "running": "running, or killed"}.get(str(status), f"status {status!r}")
        return (f"{out} holds a {prev.get('algo')} run ({how}): continue it with --resume, start "
                f"it over with --force (removes its model, checkpoints and logs), or choose "
                f"another --out")
    names = sorted(p.name for p in out.iterdir())
    return (f"{out} is not empty ({len(names)} entries: {', '.join(names[:5])}"
            f"{', ...' if len(names) > 5 else ''}) and holds no {RUN_FILE}: it is not a train.py "
            f"run, so nothing in it is removed (not even with --force); choose a new or empty "
            f"--out")


def _start_over(out: Path, prev: Mapping[str, Any] | None) -> list[str]:
    """``--force``: remove the previous run's files from ``out`` (:func:`run_files`: exactly
    what train.py writes), listing them first; anything else stays. Only a folder holding a
    train.py ``run.json`` is started over: another non-empty folder is refused (ValueError)."""
    if not out.is_dir() or not any(out.iterdir()):
        return []
    if prev is None:
        raise ValueError(_occupied(out, None))
    if prev.get("algo") not in ALGOS:
        raise ValueError(f"--force: {out / RUN_FILE} records algo {prev.get('algo')!r}, not one "
                         f"of {list(ALGOS)}: not a train.py run; nothing in {out} is removed. "
                         f"Choose a new or empty --out")
    gone = run_files(out)
    names = [p.relative_to(out).as_posix() for p in gone]
    print(f"--force: starting {out} over; removing the previous run's "
          f"{', '.join(names) if names else 'files (none found)'}", flush=True)
    for p in gone:
        p.unlink(missing_ok=True)
    for sub in RUN_FOLDERS:
        d = out / sub
        if d.is_dir() and not d.is_symlink() and not any(d.iterdir()):
            d.rmdir()
    kept = []
    for p in sorted(out.iterdir()):
        if p.name in RUN_FOLDERS and p.is_dir() and not p.is_symlink():
            kept += [f"{p.name}/{q.name}" for q in sorted(p.iterdir())]
        else:
            kept.append(p.name + ("/" if p.is_dir() else ""))
    if kept:
        print(f"--force: kept {', '.join(kept)} (not written by train.py)", flush=True)
    return names


def _config_changes(old: Any, new: Any, prefix: str = "") -> list[str]:
    """The entries (``a.b: old -> new``) where a resumed run's config differs from the run's."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        return [c for k in sorted(set(old) | set(new), key=str)
                if k not in ("timesteps", "budget") or prefix
                for c in _config_changes(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix[:-1]}: {old!r} -> {new!r}"]


def train(algo: str, out: str | Path, preset: str | None = None, timesteps: int | None = None,
          seed: int = 0, resume: bool = False, budget: str = "default",
          config: str | Path | None = None, overrides: Sequence[str] = (),
          progress: bool = True, force: bool = False,
          trust_pickled_replay_buffer: bool = False) -> dict[str, Any]:
    """Train ``algo`` into ``out``; returns the final ``run.json`` content.

    The configuration is checked whole before anything is written (:func:`check_config`).
    ``out`` must be new or empty unless ``resume`` (continue from its last checkpoint; an error
    if there is none, or if the run's seed is not a training seed) or ``force`` (start over a
    folder holding a train.py ``run.json``: the files train.py wrote there, :func:`run_files`,
    are listed, then removed; anything else stays, and a non-empty folder without
    ``run.json`` is refused).
    SIGINT or SIGTERM stop training at the next step: the last checkpoint is saved, ``run.json``
    records ``status: "interrupted"`` and :class:`TrainingInterrupted` is raised. DQN replay
    buffers of older runs (pickles) are loaded on resume only with
    ``trust_pickled_replay_buffer`` (only for your own runs)."""
    from pneugym.outputs import check_output_dir
    from pneugym.provenance import provenance

    if algo not in ALGOS:
        raise ValueError(f"unknown algorithm {algo!r}; choose one of {ALGOS}")
    if resume and force:
        raise ValueError("--resume continues the run in --out, --force starts it over: give one")
    _check_seed("training", seed)
    # the whole configuration, checked before anything is written
    cfg = load_config(algo, budget, config, overrides, preset=preset, timesteps=timesteps,
                      seed=None if resume else seed)
    raw_out, out = out, Path(out)
    if out.exists() or not resume:
        check_output_dir(raw_out, "run folder (--out)")
    prev = read_run(out) if out.is_dir() else None
    if resume:
        _resumable(out, prev, algo)
        old = _resume_seed(out, prev)
        if old != seed:
            print(f"--resume: using the run's seed {old} (not {seed})", flush=True)
            seed = old
        changes = _config_changes(prev.get("config", {}), cfg)
        if changes:
            print("--resume: the configuration differs from the run's (the new values apply): "
                  + "; ".join(changes), flush=True)
    elif force:
        _start_over(out, prev)
        prev = None
    elif any(out.iterdir()):
        raise ValueError(_occupied(out, prev))
    _threads(cfg)
    from agents.esac import source_hash
    from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: F401  (load the plant's code now)
    source_hash()  # ... and key caches by these sources, even if the files change meanwhile
    run: dict[str, Any] = dict(prev) if resume else {}
    if "interrupted" in run:
        run["interruptions"] = [*run.get("interruptions", []), run.pop("interrupted")]
    run.update({"algo": algo, "seed": seed, "preset": cfg["preset"], "budget": budget,
                "config": cfg, "command": [Path(sys.argv[0]).name, *sys.argv[1:]],
                "provenance": provenance(), "pneugym_sources": source_hash(),
                "training_seeds_below": MAX_TRAINING_SEED})
    run.setdefault("started_utc", run["provenance"]["created_utc"])

    def record(**kw: Any) -> None:
        run.update(kw)
        atomic_write_json(out / RUN_FILE, run)

    record(status="running")
    t0 = time.perf_counter()
    stop = StopRequest()
    try:
        with stop_on_signals(stop, graceful=algo != "esac"):
            if algo == "esac":
                summary = train_esac(cfg, out, seed, progress, record)
            else:
                summary = train_sb3(cfg, out, seed, resume, progress, record, stop,
                                    trust_pickled_replay_buffer)
    except KeyboardInterrupt as exc:
        sig = getattr(exc, "signal_name", None) or stop.signal or "SIGINT"
        done = int(run.get("timesteps_done", 0)) if algo != "esac" else 0
        record(status="interrupted", interrupted={
            "signal": sig, "timesteps_done": done, "checkpoint": run.get("checkpoint")
            if algo != "esac" else None, "wall_s": time.perf_counter() - t0})
        raise TrainingInterrupted(sig, done, run) from None
    summary["total_wall_s"] = time.perf_counter() - t0 + (
        float(prev.get("total_wall_s", 0.0)) if resume else 0.0)
    record(status="finished", **summary)
    return run


def model_path(run_dir: str | Path) -> Path | None:
    """The model file of a finished run directory (inside it), or None."""
    from agents.learned import run_member

    run = read_run(Path(run_dir))
    if not run or run.get("status") != "finished" or "model" not in run:
        return None
    p = run_member(Path(run_dir), run["model"], "model")
    return p if p.is_file() else None


def training_plan(names: Sequence[str] = DEFAULT_POLICIES, runs_dir: str | Path = "runs",
                  budget: str = "quick") -> dict[str, tuple[str, Path]]:
    """What :func:`ensure_trained` will do for each of ``names``: ``("ready", model file)``,
    ``("train", run dir)`` or ``("resume", run dir)``, checked before any training starts:
    ``runs_dir`` and each run folder must be folders, a run to train must have a usable folder
    and configuration (``budget``), a run to resume a checkpoint and a training seed. Raises
    ValueError (a :class:`~agents.learned.RunFileError` for a damaged run.json) naming what is
    wrong."""
    runs = Path(runs_dir)
    if runs.exists() and not runs.is_dir():
        raise ValueError(f"--runs {runs_dir} is a file; learned policies live in (and are "
                         f"trained into) folders under --runs: give a folder")
    plan: dict[str, tuple[str, Path]] = {}
    for name in names:
        if name not in ALGOS:
            raise ValueError(f"unknown learned policy {name!r}; choose from {list(ALGOS)}")
        d = runs / name
        if d.exists() and not d.is_dir():
            raise ValueError(f"{d} is a file; the {name} run lives in the folder {d}: move the "
                             f"file, or give another --runs")
        p = model_path(d) if d.is_dir() else None
        # a budget or configuration train() would refuse (checked whole only if it will train)
        load_config(name, budget, seed=0, check=p is None)
        if p is not None:
            plan[name] = ("ready", p)
            continue
        prev = read_run(d) if d.is_dir() else None
        resume = bool(prev and name != "esac" and prev.get("algo") == name
                      and prev.get("checkpoint"))
        try:
            if resume:
                _resumable(d, prev, name)
                _resume_seed(d, prev)
            elif d.is_dir() and any(d.iterdir()):
                raise ValueError(_occupied(d, prev))
        except ValueError as exc:
            raise ValueError(f"cannot train {name} on demand into {d}: {exc}") from None
        plan[name] = ("resume" if resume else "train", d)
    return plan


def ensure_trained(names: Sequence[str] = DEFAULT_POLICIES, runs_dir: str | Path = "runs",
                   budget: str = "quick", seed: int = 0, progress: bool = True
                   ) -> dict[str, Path]:
    """The model of each of ``names`` under ``runs_dir/<name>``, training those that are missing
    with ``budget`` (evaluate.py's train-on-demand; an interrupted run is resumed). Every run is
    checked (:func:`training_plan`) before the first training starts."""
    paths = {}
    for name, (what, p) in training_plan(names, runs_dir, budget).items():
        if what == "ready":
            paths[name] = p
            continue
        print(f"== no trained {name} under {p}: "
              f"{'resuming' if what == 'resume' else 'training'} it ({budget} budget)",
              flush=True)
        train(name, p, seed=seed, budget=budget, progress=progress, resume=what == "resume")
        m = model_path(p)
        if m is None:
            raise RuntimeError(f"training {name} into {p} did not leave a finished model")
        paths[name] = m
    return paths


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--algo", required=True, choices=ALGOS)
    ap.add_argument("--preset", default=None, help="condition preset (default: the config's)")
    ap.add_argument("--timesteps", type=int, default=None,
                    help="environment steps (ppo, dqn) or training rollouts (esac)")
    ap.add_argument("--seed", type=int, default=0, help="training seed (< 1,000,000)")
    ap.add_argument("--out", default=None, help="run directory (default runs/<algo>)")
    ap.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    ap.add_argument("--budget", default="default", help="section of the config (default, quick)")
    ap.add_argument("--config", default=None, help="YAML file (default configs/<algo>.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config entry, e.g. algo.learning_rate=1e-4")
    ap.add_argument("--force", action="store_true",
                    help="start over in a run folder that holds a train.py run.json (lists, then "
                         "removes the files train.py wrote there; keeps anything else)")
    ap.add_argument("--trust-pickled-replay-buffer", action="store_true",
                    help="--resume of a DQN run from an older pneugym: load its pickled replay "
                         "buffer (a pickle can run code: only for your own runs)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    out = args.out if args.out is not None else f"runs/{args.algo}"  # "" is refused, not replaced
    try:
        run = train(args.algo, out, args.preset, args.timesteps, args.seed, args.resume,
                    args.budget, args.config, args.set, not args.no_progress, args.force,
                    args.trust_pickled_replay_buffer)
    except ValueError as exc:
        ap.error(str(exc))
    except TrainingInterrupted as exc:
        where = f"; last checkpoint {out}/{exc.run['checkpoint']}" if (
            exc.run and exc.run.get("checkpoint")) else ""
        again = (f"continue with: python train.py --algo {args.algo} --out {out} --resume"
                 if args.algo != "esac" else "ESAC has no checkpoints: rerun with --force")
        print(f"{exc}: {out}/{RUN_FILE} records it{where}; {again}", file=sys.stderr,
              flush=True)
        raise SystemExit(128 + signal.Signals[exc.signal_name].value) from None
    best = run.get("best", {})
    frac = best.get("oracle_fraction")
    print(f"done in {run['total_wall_s']:.0f} s: {out}/{run['model']}"
          f" (validation return {best.get('return', float('nan')):.4f}, oracle fraction "
          f"{'-' if frac is None else f'{frac:.3f}'})")
    return run


if __name__ == "__main__":
    main()
