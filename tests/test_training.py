"""agents.training: smoke runs of every algorithm (a few hundred steps): the run directory,
checkpoints, resume, loading through agents.registry into the evaluation, train-on-demand
(agents.training.ondemand) and the privileged critic."""
import json

import numpy as np
import pytest
from training_helpers import SMALL, STEPS, small, trained_runs

from agents import training
from agents.training import ondemand
from agents.evaluation import EVAL_SEED, run_policy, suite_episodes
from agents.learned import LayoutMismatchError
from agents.registry import load_policy
from pneugym.envs.cutoff import CutOffVectorEnv


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return trained_runs(tmp_path_factory)


@pytest.mark.parametrize("algo", training.ALGOS)
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


@pytest.mark.parametrize("algo", training.ALGOS)
def test_trained_model_runs_in_evaluate(runs, algo):
    """Through the evaluation's loader: a history=1 environment, the model stacks its own 3."""
    env = CutOffVectorEnv(num_envs=1)
    pol = load_policy(runs[algo], env)
    conds = [c for _, c in suite_episodes("nominal", 1, EVAL_SEED)]
    out = run_policy(pol, conds, {}, EVAL_SEED)
    assert len(out["objective"]) == 2 and np.all(np.isfinite(out["objective"]))


def test_esac_trains_an_ensemble(runs, tmp_path):
    """``fit.ensemble: 2``: the run fits two networks on the same rollouts (cached), tunes the
    rule on their combined prediction, records both fits, and the model loads and runs as an
    ensemble."""
    from agents import esac

    out = tmp_path / "esac-ensemble"
    training.train("esac", out, timesteps=STEPS["esac"], seed=1, progress=False,
                   overrides=small("esac", runs["esac"].parent) + ["fit.ensemble=2"])
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["fit"]["ensemble"] == 2 and len(run["fit"]["members"]) == 2
    pred, meta = esac.load(out / "model.pt")
    assert meta["members"] == 2 and esac.is_ensemble(pred.net)
    one = json.loads((runs["esac"] / "run.json").read_text())
    assert run["fit"]["members"][0]["best_val"] == pytest.approx(one["fit"]["best_val"])
    env = CutOffVectorEnv(num_envs=1)
    conds = [c for _, c in suite_episodes("nominal", 1, EVAL_SEED)]
    res = run_policy(load_policy(out, env), conds, {}, EVAL_SEED)
    assert np.all(np.isfinite(res["objective"]))


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
    training.train(algo, runs[algo], timesteps=1024, seed=1, resume=True, progress=False,
                   overrides=SMALL[algo] + [f"cache_dir={runs[algo].parent / 'cache'}"])
    after = json.loads((runs[algo] / "run.json").read_text())
    assert before["timesteps_done"] < 1024 <= after["timesteps_done"]
    assert len(after["validation"]) > len(before["validation"])
    assert (runs[algo] / "progress.1.csv").is_file()  # the first part of the log is kept


def test_ensure_trained_reuses_finished_runs(runs, monkeypatch):
    """The evaluation's train-on-demand: finished runs are used as they are, missing ones
    trained."""
    calls = []
    monkeypatch.setattr(ondemand, "train", lambda name, d, **kw: calls.append((name, kw)))
    root = runs["ppo"].parent
    paths = training.ensure_trained(["ppo", "esac"], root, budget="quick")
    assert calls == []
    assert paths["ppo"].name == "best_model.zip" and paths["esac"].name == "model.pt"
    with pytest.raises(RuntimeError, match="did not leave a finished model"):
        training.ensure_trained(["ppo"], root / "elsewhere", budget="quick")
    assert calls and calls[0][0] == "ppo" and calls[0][1]["budget"] == "quick"


def test_privileged_critic_run_loads_without_privileged_features(tmp_path):
    """privileged_critic: trained with observe_params, evaluated in the evaluation's public
    history-1 environment; several decision rules are tuned together and the choice is recorded."""
    d = tmp_path / "asym"
    training.train("ppo", d, timesteps=512, seed=1, progress=False, overrides=SMALL["ppo"] + [
        f"cache_dir={tmp_path / 'cache'}", "privileged_critic=true",
        "decision.rules={quantile: [0.3, 0.6], hazard: [0.05, 0.5]}",
        "decision.prefer_saving_within=0.01"])
    run = json.loads((d / "run.json").read_text())
    assert len(run["observation_layout"]["param_features"]) == 3
    assert run["best"]["decision"]["rule"] in ("quantile", "hazard")
    assert {r["rule"] for r in run["validation"][0]["grid"]} == {"quantile", "hazard"}
    pol = load_policy(d, CutOffVectorEnv(num_envs=1))
    assert type(pol.model.policy).__name__ == "AsymmetricActorCriticPolicy"
    conds = [c for _, c in suite_episodes("nominal", 1, EVAL_SEED)]
    out = run_policy(pol, conds, {}, EVAL_SEED)
    assert len(out["objective"]) == 2 and np.all(np.isfinite(out["objective"]))
    with pytest.raises(ValueError, match="actor-critic"):
        training.train("dqn", tmp_path / "dqn", timesteps=64, seed=1, progress=False,
                       overrides=SMALL["dqn"] + ["privileged_critic=true"])


def test_dqn_resume_restores_the_replay_buffer_exactly(tmp_path):
    from agents.safe_load import REPLAY_ARRAYS

    d = tmp_path / "dqn"
    ov = small("dqn", tmp_path)
    training.train("dqn", d, timesteps=256, seed=1, progress=False, overrides=ov)
    run = json.loads((d / "run.json").read_text())
    with np.load(training.replay_file(d / run["checkpoint"])) as z:
        old = dict(z)
    training.train("dqn", d, timesteps=512, seed=1, resume=True, progress=False, overrides=ov)
    run = json.loads((d / "run.json").read_text())
    with np.load(training.replay_file(d / run["checkpoint"])) as z:
        new = dict(z)
    k = int(old["pos"])
    assert k == 256 // 4 and int(new["pos"]) == 512 // 4
    for name in REPLAY_ARRAYS:
        np.testing.assert_array_equal(new[name][:k], old[name][:k])
    assert np.abs(new["observations"][k:2 * k]).sum() > 0  # new transitions follow them
    assert not list(d.rglob("*.pkl"))


def test_latched_dqn_explores_with_the_configured_cut_probability(tmp_path, monkeypatch):
    """explore_cut_prob from the run's configuration drives each model's random actions; it is
    neither saved in the model file (which loads as a plain DQN) nor left on the class."""
    import zipfile

    from agents.training.sb3 import LatchedDQN, TrainingVecEnv
    from training_helpers import hook_training

    seen = []
    hook_training(monkeypatch, lambda cb: seen.append(cb.model.explore_cut_prob))
    d = tmp_path / "dqn"
    training.train("dqn", d, timesteps=64, seed=1, progress=False,
                   overrides=small("dqn", tmp_path) + ["explore_cut_prob=0.3"])
    assert seen and set(seen) == {0.3} and LatchedDQN.explore_cut_prob == 0.02
    for f in ("model.zip", "best_model.zip"):
        with zipfile.ZipFile(d / f) as z:
            assert "explore_cut_prob" not in json.loads(z.read("data"))
    model = LatchedDQN("MlpPolicy", TrainingVecEnv(num_envs=2, preset="randomized"),
                       buffer_size=100, device="cpu", policy_kwargs={"net_arch": [8]})
    model.explore_cut_prob = 0.5
    np.random.seed(0)
    assert 0.45 < model._random_actions(10_000).mean() < 0.55
