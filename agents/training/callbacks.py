"""The stable-baselines3 callbacks of a training run: a tqdm :class:`ProgressBar`, atomic
:class:`Checkpoints` recorded in ``run.json``, :class:`StopOnRequest` (a signal ends ``learn`` at
the next step) and :class:`AfterEval`, which tunes the decision rule after each validation and
keeps the best model."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback

from .rundir import atomic_save_sb3, replay_file
from .signals import StopRequest
from .validation import choose_decision, decision_grids, oracle_fraction, sweep_decisions


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
