"""agents.training.rundir and .resume: runs are never lost. A run folder that holds anything is
refused unless --resume (something to resume, a training seed) or --force (only a train.py run,
only train.py's files); run files are written atomically through pneugym.outputs."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from training_helpers import small, trained_runs

from agents import training
from agents.training import cli, rundir, sb3, trainer


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return trained_runs(tmp_path_factory)


def test_a_run_is_never_overwritten(runs, tmp_path, capsys):
    d = tmp_path / "ppo"
    shutil.copytree(runs["ppo"], d)
    before = (d / "best_model.zip").read_bytes()
    with pytest.raises(ValueError, match=r"holds a ppo run \(finished\): continue it with "
                                         r"--resume, start it over with --force"):
        training.train("ppo", d, timesteps=256, seed=1, progress=False, overrides=small("ppo", d))
    with pytest.raises(SystemExit):
        cli.main(["--algo", "dqn", "--out", str(d), "--timesteps", "64"])
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
            training.train("ppo", other, timesteps=256, seed=1, progress=False, force=force,
                           overrides=small("ppo", d))
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
        training.train("ppo", d, timesteps=256, seed=2, force=True, progress=False,
                       overrides=small("ppo", tmp_path))
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
        training.train("ppo", d, resume=True, force=True, progress=False)


def test_resume_needs_something_to_resume(runs, tmp_path):
    def resume(algo, d):
        training.train(algo, d, timesteps=1024, seed=1, resume=True, progress=False,
                       overrides=small(algo, tmp_path))

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

    monkeypatch.setattr(sb3, "train_sb3", never)
    monkeypatch.setattr(trainer, "_threads", never)
    from pneugym.outputs import OutputError
    with pytest.raises(OutputError, match=f"run folder .--out. {f} exists and is not a folder"):
        training.train("ppo", f, progress=False)
    with pytest.raises(SystemExit):
        cli.main(["--algo", "ppo", "--out", str(f)])
    assert "is not a folder" in capsys.readouterr().err
    assert f.read_text() == "x"


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
            training.train("ppo", d, timesteps=1024, seed=1, resume=True, progress=False,
                           overrides=small("ppo", tmp_path))
        assert json.loads((d / "run.json").read_text())["seed"] == bad  # untouched
    (d / "run.json").write_text(json.dumps({**run, "seed": 1_000_000}))
    with pytest.raises(SystemExit):
        cli.main(["--algo", "ppo", "--out", str(d), "--resume", "--timesteps", "1024"])
    assert "cannot be continued" in capsys.readouterr().err


def test_force_refuses_a_run_json_train_py_did_not_write(tmp_path):
    d = tmp_path / "run"
    d.mkdir()
    (d / "run.json").write_text(json.dumps({"algo": "sac", "status": "finished"}))
    (d / "model.zip").write_text("someone else's")
    with pytest.raises(ValueError, match="records algo 'sac'.*not a train.py run; nothing in"):
        training.train("ppo", d, timesteps=256, seed=1, force=True, progress=False)
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
    rundir.atomic_write_json(tmp_path / "run.json", {"a": np.float32(1.5)})
    assert seen == ["run.json"]
    assert json.loads((tmp_path / "run.json").read_text()) == {"a": 1.5}
    mask = os.umask(0)
    os.umask(mask)
    for f in ("run.json", "progress.csv"):
        assert (runs["ppo"] / f).stat().st_mode & 0o777 == 0o666 & ~mask, f
