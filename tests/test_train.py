"""train.py: smoke runs of every algorithm (a few hundred steps): run directory, checkpoints,
resume, loading through agents.registry into evaluate.py, and the refusals."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import train  # noqa: E402

from agents.learned import LayoutMismatchError  # noqa: E402
from agents.registry import load_policy  # noqa: E402
from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: E402

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


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for algo in train.ALGOS:
        d = root / algo
        train.train(algo, d, timesteps=STEPS[algo], seed=1, progress=False,
                    overrides=SMALL[algo] + [f"cache_dir={root / 'cache'}"])
        out[algo] = d
    return out


@pytest.mark.parametrize("algo", train.ALGOS)
def test_run_directory_records_everything(runs, algo):
    run = json.loads((runs[algo] / "run.json").read_text())
    assert run["status"] == "finished" and run["algo"] == algo and run["seed"] == 1
    assert run["observation_layout"]["history"] == 3
    assert {"numpy", "torch", "stable-baselines3"} <= set(run["provenance"]["versions"])
    assert run["config"]["preset"] == "randomized" and run["train_wall_s"] > 0
    assert (runs[algo] / run["model"]).is_file()
    assert not list(runs[algo].rglob("*.tmp*"))  # atomic writes leave no temporaries
    if algo == "esac":
        assert {"completion_accuracy", "stroke_time_mae_ms"} <= set(run["accuracy"])
        for f in ("accuracy.png", "accuracy.json", "rule_sweep.json"):
            assert (runs[algo] / f).stat().st_size > 100
    else:
        assert run["validation"] and run["checkpoint"].startswith("checkpoints/")
        assert (runs[algo] / run["checkpoint"]).is_file()
        assert (runs[algo] / "progress.csv").is_file()


@pytest.mark.parametrize("algo", train.ALGOS)
def test_trained_model_runs_in_evaluate(runs, algo):
    """Through evaluate.py's loader: a history=1 environment, the model stacks its own 3."""
    import evaluate

    env = CutOffVectorEnv(num_envs=1)
    pol = load_policy(runs[algo], env)
    conds = [c for _, c in evaluate.suite_episodes("nominal", 1, evaluate.EVAL_SEED)]
    out = evaluate.run_policy(pol, conds, {}, evaluate.EVAL_SEED)
    assert len(out["objective"]) == 2 and np.all(np.isfinite(out["objective"]))


@pytest.mark.parametrize("algo", ["ppo", "esac"])
def test_mismatched_layout_is_refused(runs, algo):
    run = json.loads((runs[algo] / "run.json").read_text())
    with pytest.raises(LayoutMismatchError, match="history 3 .model. vs 2 .env."):
        load_policy(runs[algo] / run["model"], CutOffVectorEnv(num_envs=1, history=2))
    with pytest.raises(LayoutMismatchError, match="time_limit_s"):
        load_policy(runs[algo], CutOffVectorEnv(num_envs=1, time_limit_s=6.0))


@pytest.mark.parametrize("algo", ["ppo", "dqn"])
def test_resume_continues_from_the_last_checkpoint(runs, algo):
    before = json.loads((runs[algo] / "run.json").read_text())
    train.train(algo, runs[algo], timesteps=1024, seed=1, resume=True, progress=False,
                overrides=SMALL[algo] + [f"cache_dir={runs[algo].parent / 'cache'}"])
    after = json.loads((runs[algo] / "run.json").read_text())
    assert before["timesteps_done"] < 1024 <= after["timesteps_done"]
    assert len(after["validation"]) > len(before["validation"])
    assert (runs[algo] / "progress.1.csv").is_file()  # the first part of the log is kept


def test_configs_and_refusals(tmp_path):
    for algo in train.ALGOS:
        d, q = train.load_config(algo), train.load_config(algo, "quick")
        assert q["timesteps"] < d["timesteps"]
    # PPO's checkpoint and decision choice needs a large validation set (144 chose by noise)
    assert train.load_config("ppo")["validation"]["episodes"] >= 1024
    cfg = train.load_config("ppo", overrides=["algo.learning_rate=1e-4", "env.history=8"])
    assert cfg["algo"]["learning_rate"] == 1e-4 and cfg["env"]["history"] == 8
    with pytest.raises(ValueError, match="no budget"):
        train.load_config("ppo", "huge")
    with pytest.raises(ValueError, match="reserved for evaluation"):
        train.train("ppo", tmp_path / "x", seed=1_000_000, progress=False)
    with pytest.raises(ValueError, match="unknown algorithm"):
        train.train("sac", tmp_path / "x", progress=False)
    with pytest.raises(SystemExit):
        train.main(["--algo", "ppo", "--seed", "2000000", "--out", str(tmp_path / "y")])


def test_ensure_trained_reuses_finished_runs(runs, monkeypatch):
    """evaluate.py's train-on-demand: finished runs are used as they are, missing ones trained."""
    calls = []
    monkeypatch.setattr(train, "train", lambda name, d, **kw: calls.append((name, kw)))
    root = runs["ppo"].parent
    paths = train.ensure_trained(["ppo", "esac"], root, budget="quick")
    assert calls == []
    assert paths["ppo"].name == "best_model.zip" and paths["esac"].name == "model.pt"
    with pytest.raises(RuntimeError, match="did not leave a finished model"):
        train.ensure_trained(["ppo"], root / "elsewhere", budget="quick")
    assert calls and calls[0][0] == "ppo" and calls[0][1]["budget"] == "quick"


def test_privileged_critic_run_loads_without_privileged_features(tmp_path):
    """privileged_critic: trained with observe_params, evaluated in evaluate.py's public history-1
    environment; several decision rules are tuned together and the choice is recorded."""
    import evaluate

    d = tmp_path / "asym"
    train.train("ppo", d, timesteps=512, seed=1, progress=False, overrides=SMALL["ppo"] + [
        f"cache_dir={tmp_path / 'cache'}", "privileged_critic=true",
        "decision.rules={quantile: [0.3, 0.6], hazard: [0.05, 0.5]}",
        "decision.prefer_saving_within=0.01"])
    run = json.loads((d / "run.json").read_text())
    assert len(run["observation_layout"]["param_features"]) == 3
    assert run["best"]["decision"]["rule"] in ("quantile", "hazard")
    assert {r["rule"] for r in run["validation"][0]["grid"]} == {"quantile", "hazard"}
    pol = load_policy(d, CutOffVectorEnv(num_envs=1))
    assert type(pol.model.policy).__name__ == "AsymmetricActorCriticPolicy"
    conds = [c for _, c in evaluate.suite_episodes("nominal", 1, evaluate.EVAL_SEED)]
    out = evaluate.run_policy(pol, conds, {}, evaluate.EVAL_SEED)
    assert len(out["objective"]) == 2 and np.all(np.isfinite(out["objective"]))
    with pytest.raises(ValueError, match="actor-critic"):
        train.train("dqn", tmp_path / "dqn", timesteps=64, seed=1, progress=False,
                    overrides=SMALL["dqn"] + ["privileged_critic=true"])


def test_choose_decision_prefers_saving_within_tolerance():
    rows = [{"rule": "quantile", "value": 0.2, "return": -0.650, "stall_rate": 0.0, "saving": 0.60},
            {"rule": "quantile", "value": 0.1, "return": -0.653, "stall_rate": 0.0, "saving": 0.63},
            {"rule": "hazard", "value": 0.02, "return": -0.652, "stall_rate": 0.1, "saving": 0.70},
            {"rule": "hazard", "value": 0.05, "return": -0.700, "stall_rate": 0.0, "saving": 0.75}]
    assert train.choose_decision(rows)["value"] == 0.2
    assert train.choose_decision(rows, 0.005)["value"] == 0.1  # the stalling one is not chosen
    assert train.choose_decision(rows, 0.1)["value"] == 0.05
    # ESAC's use: rules that stall on validation are excluded first
    assert train.choose_decision(rows, 0.0, max_stall_rate=0.0)["value"] == 0.2
    assert train.choose_decision(rows[2:3] + rows[3:], 0.0, 0.0)["value"] == 0.05
    assert train.choose_decision(rows[2:3], 0.0, 0.0)["value"] == 0.02  # none without: all
    with pytest.raises(ValueError, match="prefer_saving_within"):
        train.choose_decision(rows, -1.0)
    assert train.decision_grids({"rule": "quantile", "grid": [0.5]}) == {"quantile": [0.5]}
