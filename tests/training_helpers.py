"""Shared by the tests of agents/training/: small configurations of every algorithm, the
finished runs they train (once per test session), and a hook into every training step."""
from __future__ import annotations

from pathlib import Path

from agents import training

SMALL = {
    "ppo": ["env.num_envs=4", "env.history=3", "algo.n_steps=64", "algo.batch_size=128",
            "algo.n_epochs=2", "eval_every=256", "checkpoint_every=256", "validation.episodes=2"],
    "dqn": ["env.num_envs=4", "env.history=3", "algo.learning_starts=100",
            "algo.buffer_size=2000", "algo.batch_size=32", "eval_every=256",
            "checkpoint_every=256", "validation.episodes=2", "save_replay_buffer=true"],
    "esac": ["env.history=3", "test.episodes=24", "validation.episodes=2", "fit.epochs=2",
             "fit.hidden=[16]", "rule_grid={margin: [0.05], max_time_increase: [0.1, 0.5]}"],
}
STEPS = {"ppo": 512, "dqn": 512, "esac": 48}
_RUNS: dict[str, Path] = {}


def small(algo: str, root: Path) -> list[str]:
    """:data:`SMALL` for ``algo``, its caches under ``root``."""
    return SMALL[algo] + [f"cache_dir={root / 'cache'}"]


def trained_runs(tmp_path_factory) -> dict[str, Path]:
    """A finished small run of every algorithm (trained once per test session; tests that
    change a run work on a copy, except the resume test, which continues them)."""
    if not _RUNS:
        root = tmp_path_factory.mktemp("runs")
        for algo in training.ALGOS:
            training.train(algo, root / algo, timesteps=STEPS[algo], seed=1, progress=False,
                           overrides=small(algo, root))
            _RUNS[algo] = root / algo
    return dict(_RUNS)


def hook_training(monkeypatch, hook) -> None:
    """Run ``hook(callback)`` at every training step (through the progress bar callback)."""
    from agents.training import sb3

    class Hooked(sb3.ProgressBar):
        def _on_step(self):
            hook(self)
            return super()._on_step()

    monkeypatch.setattr(sb3, "ProgressBar", Hooked)
