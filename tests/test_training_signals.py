"""agents.training.signals: SIGINT and SIGTERM stop a run at the next step with a checkpoint and
``status: "interrupted"``; --resume continues it. ESAC, which has no checkpoints, stops at once."""
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from training_helpers import hook_training, small

from agents import training
from agents.training import esac
from pneugym.envs.cutoff import CutOffVectorEnv

ROOT = Path(__file__).resolve().parents[1]


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
    ov = small("ppo", tmp_path) + ["algo.learning_rate=lin_0.001", "algo.clip_range=0.15",
                                   "privileged_critic=false"]
    before = signal.getsignal(signal.SIGTERM)

    def hook(cb):
        if cb.num_timesteps >= 256 and not fired:
            fired.append(cb.num_timesteps)
            assert signal.getsignal(signal.SIGTERM) is not before, "no handler installed"
            signal.raise_signal(signal.SIGTERM)

    fired: list[int] = []
    hook_training(monkeypatch, hook)
    with pytest.raises(training.TrainingInterrupted, match="SIGTERM after 256 timesteps"):
        training.train("ppo", d, timesteps=768, seed=1, progress=False, overrides=ov)
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
        training.train("ppo", d, timesteps=768, seed=1, progress=False, overrides=ov)
    monkeypatch.undo()
    training.train("ppo", d, timesteps=768, seed=1, resume=True, progress=False, overrides=ov)
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

    hook_training(monkeypatch, hook)
    d = tmp_path / "ppo"
    with pytest.raises(training.TrainingInterrupted, match="SIGINT after 300 timesteps"):
        training.train("ppo", d, timesteps=768, seed=1, progress=False,
                       overrides=small("ppo", tmp_path))
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGINT"
    assert run["checkpoint"] == "checkpoints/ckpt_000000300.zip"
    pol = load_policy(d / run["checkpoint"], CutOffVectorEnv(num_envs=1))
    assert pol.model.num_timesteps == 300


def test_sigterm_to_a_training_process(tmp_path):
    """A real ``python train.py`` process: SIGTERM once it has a checkpoint; it exits 143, its
    run.json says interrupted, and --resume finishes the run."""
    d = tmp_path / "ppo"
    ov = small("ppo", tmp_path)
    cmd = [sys.executable, str(ROOT / "train.py"), "--algo", "ppo", "--out", str(d),
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
    assert f"continue with: python train.py --algo ppo --out {d} --resume" in err
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGTERM"
    done = run["timesteps_done"]
    assert 256 <= done < 100000 and (d / run["checkpoint"]).is_file()
    training.train("ppo", d, timesteps=done + 64, seed=1, resume=True, progress=False,
                   overrides=ov)
    run = json.loads((d / "run.json").read_text())
    assert run["status"] == "finished" and run["timesteps_done"] >= done + 64


def test_sigterm_interrupts_esac_at_once(tmp_path, monkeypatch):
    """ESAC has no checkpoints: the first signal stops it at once, and run.json says so."""
    before = signal.getsignal(signal.SIGTERM)

    def esac_run(*args, **kwargs):
        assert signal.getsignal(signal.SIGTERM) is not before, "no handler installed"
        signal.raise_signal(signal.SIGTERM)
        raise AssertionError("the signal did not stop training")

    monkeypatch.setattr(esac, "train_esac", esac_run)
    with pytest.raises(training.TrainingInterrupted, match="SIGTERM"):
        training.train("esac", tmp_path / "esac", progress=False, overrides=small("esac", tmp_path))
    assert signal.getsignal(signal.SIGTERM) is before
    run = json.loads((tmp_path / "esac" / "run.json").read_text())
    assert run["status"] == "interrupted" and run["interrupted"]["signal"] == "SIGTERM"
    with pytest.raises(ValueError, match="ESAC trains in one piece"):
        training.train("esac", tmp_path / "esac", resume=True, progress=False)
