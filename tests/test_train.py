"""train.py: smoke runs of every algorithm (a few hundred steps): run directory, checkpoints,
resume, loading through agents.registry into evaluate.py, and the refusals."""
import json
import shutil
import signal
import subprocess
import sys
import time
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


# ------------------------------------------------------------------------------------------------
# runs are never lost
# ------------------------------------------------------------------------------------------------
def _small(algo, root):
    return SMALL[algo] + [f"cache_dir={root / 'cache'}"]


def test_a_run_is_never_overwritten(runs, tmp_path, capsys):
    d = tmp_path / "ppo"
    shutil.copytree(runs["ppo"], d)
    before = (d / "best_model.zip").read_bytes()
    with pytest.raises(ValueError, match=r"holds a ppo run \(finished\): continue it with "
                                         r"--resume, start it over with --force"):
        train.train("ppo", d, timesteps=256, seed=1, progress=False, overrides=_small("ppo", d))
    with pytest.raises(SystemExit):
        train.main(["--algo", "dqn", "--out", str(d), "--timesteps", "64"])
    assert "holds a ppo run" in capsys.readouterr().err
    assert (d / "best_model.zip").read_bytes() == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    for force in (False, True):  # not a train.py run: refused, even with --force
        with pytest.raises(ValueError, match=r"other is not empty \(1 entries: notes.txt\) and "
                                             r"holds no run.json: it is not a train.py run, so "
                                             r"nothing in it is removed \(not even with "
                                             r"--force\)"):
            train.train("ppo", other, timesteps=256, seed=1, progress=False, force=force,
                        overrides=_small("ppo", d))
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    # --force starts over: lists what it removes first, then removes exactly train.py's files
    mine = {"notes.txt": "mine", "progress_notes.csv": "a,b", "draft.tmp": "x",
            "tb/mine.txt": "y", "checkpoints/notes.txt": "z", "model.zip.bak": "w",
            "events.out.tfevents.mine": "v"}
    for name, text in mine.items():
        (d / name).parent.mkdir(exist_ok=True)
        (d / name).write_text(text)
    (d / "progress.1.csv").write_text("old log")          # train.py's: removed
    (d / ".run.json.x1y2z3.tmp").write_text("{")          # a killed atomic write: removed
    (d / "tb" / "events.out.tfevents.1700000000.host.1.0").write_text("tb")
    printed_before_removal = []
    real_unlink = Path.unlink

    def unlink(self, *a, **k):
        if not printed_before_removal:
            printed_before_removal.append(capsys.readouterr().out)
        return real_unlink(self, *a, **k)

    import unittest.mock
    with unittest.mock.patch.object(Path, "unlink", unlink):
        train.train("ppo", d, timesteps=256, seed=2, force=True, progress=False,
                    overrides=_small("ppo", tmp_path))
    listed = printed_before_removal[0]
    assert "removing the previous run's" in listed
    for f in ("run.json", "best_model.zip", "model.zip", "progress.csv", "progress.1.csv",
              ".run.json.x1y2z3.tmp", "tb/events.out.tfevents.1700000000.host.1.0"):
        assert f in listed
    assert "checkpoints/ckpt_" in listed
    for name in mine:  # never removed, never listed as removed
        assert name not in listed.split("removing the previous run's", 1)[1].split("\n")[0]
    out = capsys.readouterr().out
    assert "kept " in out and "notes.txt" in out and "tb/mine.txt" in out
    for name, text in mine.items():
        assert (d / name).read_text() == text
    assert not (d / "progress.1.csv").exists() and not (d / ".run.json.x1y2z3.tmp").exists()
    run = json.loads((d / "run.json").read_text())
    assert run["seed"] == 2 and run["status"] == "finished" and run["timesteps_done"] == 256
    assert len(run["validation"]) == 1 and not (d / "progress.1.csv").exists()
    assert (d / "notes.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="give one"):
        train.train("ppo", d, resume=True, force=True, progress=False)


def test_resume_needs_something_to_resume(runs, tmp_path):
    def resume(algo, d):
        train.train(algo, d, timesteps=1024, seed=1, resume=True, progress=False,
                    overrides=_small(algo, tmp_path))

    with pytest.raises(ValueError, match="nothing to resume in .*none: the folder does not "
                                         "exist. Start a new run without --resume"):
        resume("ppo", tmp_path / "none")
    assert not (tmp_path / "none").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="nothing to resume .*it has no run.json"):
        resume("ppo", tmp_path / "empty")
    with pytest.raises(ValueError, match="ESAC trains in one piece and keeps no checkpoints"):
        resume("esac", runs["esac"])
    with pytest.raises(ValueError, match="holds a ppo run, not dqn"):
        resume("dqn", runs["ppo"])
    d = tmp_path / "ppo"
    shutil.copytree(runs["ppo"], d)
    run = json.loads((d / "run.json").read_text())
    (d / "run.json").write_text(json.dumps({**run, "checkpoint": "checkpoints/gone.zip"}))
    with pytest.raises(ValueError, match="names the checkpoint checkpoints/gone.zip, which does "
                                         "not exist"):
        resume("ppo", d)
    del run["checkpoint"]
    (d / "run.json").write_text(json.dumps(run))
    with pytest.raises(ValueError, match="records no checkpoint"):
        resume("ppo", d)
    assert json.loads((d / "run.json").read_text()) == run  # untouched


def test_out_must_be_a_folder_before_anything_runs(tmp_path, monkeypatch, capsys):
    f = tmp_path / "file"
    f.write_text("x")

    def never(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(train, "train_sb3", never)
    monkeypatch.setattr(train, "_threads", never)
    from pneugym.outputs import OutputError
    with pytest.raises(OutputError, match=f"run folder .--out. {f} exists and is not a folder"):
        train.train("ppo", f, progress=False)
    with pytest.raises(SystemExit):
        train.main(["--algo", "ppo", "--out", str(f)])
    assert "is not a folder" in capsys.readouterr().err
    assert f.read_text() == "x"


def _hook_training(monkeypatch, hook):
    """Run ``hook(callback)`` at every training step (through the progress bar callback)."""
    real = train._sb3_parts

    def parts():
        P = real()

        class Hooked(P["ProgressBar"]):
            def _on_step(self):
                hook(self)
                return super()._on_step()

        P["ProgressBar"] = Hooked
        return P

    monkeypatch.setattr(train, "_sb3_parts", parts)


def _csv_rows(f: Path) -> list[dict[str, str]]:
    import csv

    with open(f) as fh:
        return list(csv.DictReader(fh))


def test_sigterm_checkpoints_and_resume_continues(tmp_path, monkeypatch):
    """SIGTERM (delivered in-process, to the real handler) during training: the run stops at the
    next step with a checkpoint and status "interrupted", the previous handler is back; --resume
    continues from it with the config's schedules (a linear learning rate, a clip range) and
    trains."""
    from agents.safe_load import load_sb3

    d = tmp_path / "ppo"
    ov = _small("ppo", tmp_path) + ["algo.learning_rate=lin_0.001", "algo.clip_range=0.15",
                                    "privileged_critic=false"]
    before = signal.getsignal(signal.SIGTERM)

    def hook(cb):
        if cb.num_timesteps >= 256 and not fired:
            fired.append(cb.num_timesteps)
            assert signal.getsignal(signal.SIGTERM) is not before, "no handler installed"
            signal.raise_signal(signal.SIGTERM)

    fired: list[int] = []
    _hook_training(monkeypatch, hook)
    with pytest.raises(train.TrainingInterrupted, match="SIGTERM after 256 timesteps"):
        train.train("ppo", d, timesteps=768, seed=1, progress=False, overrides=ov)
    assert signal.getsignal(signal.SIGTERM) is before
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "interrupted" and run["timesteps_done"] == 256
    assert run["interrupted"]["signal"] == "SIGTERM"
    assert run["checkpoint"] == run["interrupted"]["checkpoint"] == "checkpoints/ckpt_000000256.zip"
    ckpt = load_sb3(d / run["checkpoint"], "ppo")
    assert ckpt.num_timesteps == 256
    assert not list(d.rglob("*.tmp*"))
    with pytest.raises(ValueError, match=r"interrupted at 256 timesteps\): continue it with "
                                         r"--resume"):
        train.train("ppo", d, timesteps=768, seed=1, progress=False, overrides=ov)
    monkeypatch.undo()
    train.train("ppo", d, timesteps=768, seed=1, resume=True, progress=False, overrides=ov)
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "finished" and run["timesteps_done"] == 768
    assert run["interruptions"][0]["signal"] == "SIGTERM" and "interrupted" not in run
    rows = [r for r in _csv_rows(d / "progress.csv") if r.get("train/learning_rate")]
    # the update at 512 of 768 steps (the last one's values are never dumped): the config's
    # lr = 1e-3 * (1 - 512 / 768), not SB3's default 3e-4; its clip range 0.15, not 0.2
    lrs = [float(r["train/learning_rate"]) for r in rows]
    assert lrs == pytest.approx([1e-3 / 3], abs=1e-12)
    assert {float(r["train/clip_range"]) for r in rows} == {0.15}
    final = load_sb3(d / "model.zip", "ppo")
    moved = [not np.allclose(a, b) for a, b in zip(
        ckpt.policy.state_dict().values(), final.policy.state_dict().values())]
    assert any(moved)  # the resumed run trained


def test_keyboard_interrupt_keeps_a_checkpoint(tmp_path, monkeypatch):
    """Ctrl-C raising inside training (no graceful stop): the weights so far are checkpointed."""
    from agents.registry import load_policy

    def hook(cb):
        if cb.num_timesteps >= 300:
            raise KeyboardInterrupt

    _hook_training(monkeypatch, hook)
    d = tmp_path / "ppo"
    with pytest.raises(train.TrainingInterrupted, match="SIGINT after 300 timesteps"):
        train.train("ppo", d, timesteps=768, seed=1, progress=False,
                    overrides=_small("ppo", tmp_path))
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGINT"
    assert run["checkpoint"] == "checkpoints/ckpt_000000300.zip"
    pol = load_policy(d / run["checkpoint"], CutOffVectorEnv(num_envs=1))
    assert pol.model.num_timesteps == 300


def test_sigterm_to_a_training_process(tmp_path):
    """A real ``python train.py`` process: SIGTERM once it has a checkpoint; it exits 143, its
    run.json says interrupted, and --resume finishes the run."""
    d = tmp_path / "ppo"
    ov = _small("ppo", tmp_path)
    cmd = [sys.executable, str(Path(train.__file__)), "--algo", "ppo", "--out", str(d),
           "--timesteps", "100000", "--seed", "1", "--no-progress"]
    for o in ov:
        cmd += ["--set", o]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            f = d / "run.json"
            if f.is_file() and "checkpoint" in json.loads(f.read_text()):
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "--resume" in err
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGTERM"
    done = run["timesteps_done"]
    assert 256 <= done < 100000 and (d / run["checkpoint"]).is_file()
    train.train("ppo", d, timesteps=done + 64, seed=1, resume=True, progress=False,
                overrides=ov)
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "finished" and run["timesteps_done"] >= done + 64


def test_dqn_resume_restores_the_replay_buffer_exactly(tmp_path):
    from agents.safe_load import REPLAY_ARRAYS

    d = tmp_path / "dqn"
    ov = _small("dqn", tmp_path)
    train.train("dqn", d, timesteps=256, seed=1, progress=False, overrides=ov)
    run = json.loads((d / "run.json").read_text())
    with np.load(train.replay_file(d / run["checkpoint"])) as z:
        old = dict(z)
    train.train("dqn", d, timesteps=512, seed=1, resume=True, progress=False, overrides=ov)
    run = json.loads((d / "run.json").read_text())
    with np.load(train.replay_file(d / run["checkpoint"])) as z:
        new = dict(z)
    k = int(old["pos"])
    assert k == 256 // 4 and int(new["pos"]) == 512 // 4
    for name in REPLAY_ARRAYS:
        np.testing.assert_array_equal(new[name][:k], old[name][:k])
    assert np.abs(new["observations"][k:2 * k]).sum() > 0  # new transitions follow them
    assert not list(d.rglob("*.pkl"))


def test_sigterm_interrupts_esac_at_once(tmp_path, monkeypatch):
    """ESAC has no checkpoints: the first signal stops it at once, and run.json says so."""
    before = signal.getsignal(signal.SIGTERM)

    def esac_run(*args, **kwargs):
        assert signal.getsignal(signal.SIGTERM) is not before, "no handler installed"
        signal.raise_signal(signal.SIGTERM)
        raise AssertionError("the signal did not stop training")

    monkeypatch.setattr(train, "train_esac", esac_run)
    with pytest.raises(train.TrainingInterrupted, match="SIGTERM"):
        train.train("esac", tmp_path / "esac", progress=False, overrides=_small("esac", tmp_path))
    assert signal.getsignal(signal.SIGTERM) is before
    run = json.loads((tmp_path / "esac" / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGTERM"
    with pytest.raises(ValueError, match="ESAC trains in one piece"):
        train.train("esac", tmp_path / "esac", resume=True, progress=False)


# ------------------------------------------------------------------------------------------------
# the configuration is checked whole before anything is written
# ------------------------------------------------------------------------------------------------
@pytest.fixture
def nothing_runs(monkeypatch):
    """Training, thread set-up and run.json writes fail the test if they are reached."""
    def never(*args, **kwargs):
        raise AssertionError("training started")

    for name in ("train_sb3", "train_esac", "_threads", "atomic_write_json"):
        monkeypatch.setattr(train, name, never)


@pytest.mark.parametrize("algo, overrides, match", [
    ("ppo", ["algo.n_stepz=64"], r"--set algo.n_stepz=64: 'algo.n_stepz' is not a known keyword "
                                 r"of stable_baselines3.PPO \(did you mean 'n_steps'\?\)"),
    ("ppo", ["env.num_envs=0"], r"--set env.num_envs=0: env.num_envs = 0: expected an integer "
                                r"from 1 to 4,096"),
    ("ppo", ["algo.learning_rate=abc"], r"algo.learning_rate = 'abc': expected a finite number "
                                        r"> 0, or lin_<x>.*\(it is text, not a number\)"),
    ("ppo", ["algo.learning_rate=lin_abc"], r"'abc' after lin_ is not a number > 0"),
    ("ppo", ["algo.learning_rate=-1"], r"algo.learning_rate = -1: expected a finite number > 0"),
    ("ppo", ["env.histroy=2"], r"'env.histroy' is not a known environment option .*did you "
                               r"mean 'history'"),
    ("ppo", ["eval_everyy=256"], r"--set eval_everyy=256: 'eval_everyy' is not a known "
                                 r"configuration entry \(did you mean 'eval_every'\?\)"),
    ("ppo", ["learning_rate=1e-4"], r"did you mean 'algo.learning_rate'"),
    ("ppo", ["algo.seed=3"], r"algo.seed is --seed"),
    ("ppo", ["env.control_period_s=abc"], r"--set env.control_period_s=abc: env: "
                                          r"control_period_s = 'abc' is invalid"),
    ("ppo", ["validation.episodes=0"], r"validation.episodes = 0: expected an integer"),
    ("ppo", ["validation.seed=999999"], r"--set validation.seed=999999: validation seeds "
                                        r"999999..1001022 must lie in \[0, 1000000\)"),
    ("ppo", ["policy_kwargs.net_arch=[100000]"], r"policy_kwargs.net_arch = \[100000\]: expected "
                                                 r"a list of layer widths"),
    ("ppo", ["policy_kwargs.activation_fn=relu"], r"policy_kwargs.activation_fn is a class"),
    ("ppo", ["decision.rules={quantile: [0.2, 2]}"], r"decision.rules: quantile value 2: "
                                                     r"expected a probability in \(0, 1\]"),
    ("ppo", ["decision.rules={advantage: [0.1]}"], r"rule 'advantage' is not one of"),
    ("ppo", ["decision.rule=quantile"], r"decision has rules and rule/grid"),
    ("ppo", ["algo.n_steps=1.5"], r"algo.n_steps = 1.5: expected an integer >= 1 \(1.5 is "
                                  r"not a whole number\)"),
    ("ppo", ["algo.gamma=true"], r"algo.gamma = True: expected a finite number in \[0, 1\] "
                                 r"\(true/false is not a number\)"),
    ("dqn", ["privileged_critic=true"], r"privileged_critic: true needs an actor-critic"),
    ("dqn", ["algo.train_freq=[4, epoch]"], r"algo.train_freq = \[4, 'epoch'\]"),
    ("esac", ["fit.hidden=[100000]"], r"fit.hidden = \[100000\]"),
    ("esac", ["fit.delay_input=false"], r"rule_grid.lookahead has 1, but the lookahead needs a "
                                        r"predictor trained with fit.delay_input"),
    ("esac", ["rule_grid.margin=[.nan]"], r"rule_grid.margin = \[nan\]: expected a list of "
                                          r"values; item 0 \(nan\) is not the accepted"),
    ("esac", ["env.time_limit_s=6"], r"'env.time_limit_s' is not a known ESAC environment "
                                     r"option"),
    ("esac", ["rule_grid.time_demand_s=[1.0]"], r"rule_grid.time_demand_s is not tuned"),
    ("esac", ["budget=quick"], r"--set budget=quick: budget is set by train.py \(give --budget\)"),
])
def test_config_errors_are_refused_before_anything_is_written(tmp_path, nothing_runs, algo,
                                                              overrides, match):
    d = tmp_path / "run"
    with pytest.raises(train.ConfigError, match=match):
        train.train(algo, d, timesteps=256, seed=1, progress=False, overrides=overrides)
    assert not d.exists()


@pytest.mark.parametrize("argv, match", [
    (["--timesteps", "0"], r"--timesteps: timesteps = 0: expected an integer from 1 to "
                           r"1,000,000,000,000"),
    (["--timesteps", "-5"], r"--timesteps: timesteps = -5: expected an integer from 1"),
    (["--preset", "Randomized"], r"--preset: preset = 'Randomized': expected one of .*did you "
                                 r"mean 'randomized'"),
    (["--budget", "quik"], r"has no budget 'quik' \(did you mean 'quick'\?\)"),
    (["--config", "/nonexistent.yaml"], r"--config /nonexistent.yaml cannot be read: No such "
                                        r"file"),
    (["--set", "algo.n_stepz=64"], r"did you mean 'n_steps'"),
    (["--set", "algo.learning_rate=[1"], r"--set 'algo.learning_rate=\[1': the value '\[1' is "
                                         r"not valid YAML"),
    (["--set", "algo..x=1"], r"has an empty part"),
    (["--out", ""], r"run folder \(--out\) is empty"),
])
def test_cli_config_errors_exit_2_with_the_message(tmp_path, nothing_runs, capsys, argv, match):
    import re

    argv = ["--algo", "ppo", "--out", str(tmp_path / "run"), *argv]
    with pytest.raises(SystemExit) as exc:
        train.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert "Traceback" not in err and not (tmp_path / "run").exists()


def test_config_files_broken_or_with_yaml_1_1_numbers(tmp_path, nothing_runs):
    broken = tmp_path / "broken.yaml"
    broken.write_text("default: [1, 2\n")
    with pytest.raises(train.ConfigError, match=r"broken.yaml: not valid YAML: .*line"):
        train.train("ppo", tmp_path / "a", config=broken, progress=False)
    evil = tmp_path / "evil.yaml"
    evil.write_text(f'default: !!python/object/apply:os.system ["touch {tmp_path}/ran"]\n')
    with pytest.raises(train.ConfigError, match=r"evil.yaml: plain YAML only"):
        train.train("ppo", tmp_path / "a", config=evil, progress=False)
    assert not (tmp_path / "ran").exists()
    # a YAML 1.1 reader takes 1e-4 for text: the likely mistake is named
    text = (train.CONFIG_DIR / "ppo.yaml").read_text().replace("learning_rate: 3.0e-4",
                                                                "learning_rate: 1e-4")
    yaml11 = tmp_path / "ppo.yaml"
    yaml11.write_text(text)
    with pytest.raises(train.ConfigError, match=r"ppo.yaml: algo.learning_rate = '1e-4': "
                                                r".*YAML 1.1 reads 1e-4 as text"):
        train.train("ppo", tmp_path / "a", config=yaml11, progress=False)
    # a key the code needs, missing
    no_val = tmp_path / "noval.yaml"
    no_val.write_text((train.CONFIG_DIR / "dqn.yaml").read_text().replace(
        "  validation:\n    episodes: 48\n    seed: 900000\n", ""))
    with pytest.raises(train.ConfigError, match=r"noval.yaml: validation is missing"):
        train.train("dqn", tmp_path / "a", config=no_val, progress=False)
    assert not (tmp_path / "a").exists()


def test_every_shipped_config_passes_the_check():
    for algo in train.ALGOS:
        for budget in ("default", "quick"):
            train.load_config(algo, budget, seed=0)
    cfg = train.load_config("ppo", overrides=["timesteps=1e5", "algo.n_steps=512.0"])
    assert cfg["timesteps"] == 100_000 and isinstance(cfg["algo"]["n_steps"], int)


def test_resume_refuses_a_seed_outside_the_training_range(runs, tmp_path, capsys):
    d = tmp_path / "ppo"
    shutil.copytree(runs["ppo"], d)
    run = json.loads((d / "run.json").read_text())
    for bad, match in ((1_000_000, r"records seed 1000000: training seed 1000000 must lie in "
                                   r"\[0, 1000000\)"),
                       (-3, r"records seed -3: .*never negative"),
                       (None, r"records no training seed")):
        (d / "run.json").write_text(json.dumps({**run, "seed": bad}))
        with pytest.raises(ValueError, match=match):
            train.train("ppo", d, timesteps=1024, seed=1, resume=True, progress=False,
                        overrides=_small("ppo", tmp_path))
        assert json.loads((d / "run.json").read_text())["seed"] == bad  # untouched
    (d / "run.json").write_text(json.dumps({**run, "seed": 1_000_000}))
    with pytest.raises(SystemExit):
        train.main(["--algo", "ppo", "--out", str(d), "--resume", "--timesteps", "1024"])
    assert "cannot be continued" in capsys.readouterr().err


def test_force_refuses_a_run_json_train_py_did_not_write(tmp_path):
    d = tmp_path / "run"
    d.mkdir()
    (d / "run.json").write_text(json.dumps({"algo": "sac", "status": "finished"}))
    (d / "model.zip").write_text("someone else's")
    with pytest.raises(ValueError, match="records algo 'sac'.*not a train.py run; nothing in"):
        train.train("ppo", d, timesteps=256, seed=1, force=True, progress=False)
    assert (d / "model.zip").read_text() == "someone else's"


def test_run_files_are_written_through_pneugym_outputs(runs, tmp_path, monkeypatch):
    """run.json goes through pneugym.outputs' atomic writer (so it gets the umask's mode, like
    the CSV and PNG files, not mkstemp's 0600)."""
    import os

    import pneugym.outputs as outputs

    seen = []
    real = outputs.atomic_write_text
    monkeypatch.setattr(outputs, "atomic_write_text",
                        lambda path, text: seen.append(Path(path).name) or real(path, text))
    train.atomic_write_json(tmp_path / "run.json", {"a": np.float32(1.5)})
    assert seen == ["run.json"]
    assert json.loads((tmp_path / "run.json").read_text()) == {"a": 1.5}
    mask = os.umask(0)
    os.umask(mask)
    for f in ("run.json", "progress.csv"):
        assert (runs["ppo"] / f).stat().st_mode & 0o777 == 0o666 & ~mask, f
