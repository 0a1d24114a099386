"""Parallel work (pneugym.parallel): training seeds, evaluation and tuning give the same numbers
serially, in local processes and on a Ray cluster started here (``ray start --head`` on
127.0.0.1 with 2 CPUs)."""
from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agents.evaluation.run import evaluate
from agents.training import sweep
from agents.training.tune import load_space
from pneugym.parallel import backend_name, run_tasks
from training_helpers import small, trained_runs

pytest.importorskip("ray")  # installed by the test extra; the marker only keeps a bare env clear

EVAL = dict(policies=["endstroke", "gaslaw"], suites=["nominal"], episodes=1, seed=1_000_000,
            progress=False)


def _figures(results):
    return {name: (p["return_mean"], p["oracle_fraction"], p["stall_rate"], p["saving_mean"])
            for name, p in results["suites"]["nominal"]["policies"].items()}


def _seed_figures(sw):
    return {k: (r["validation_return"], r["oracle_fraction"], r["stall_rate"])
            for k, r in sw["runs"].items()}


def _train_kw(root: Path) -> dict:
    # the session's small ESAC run (seed 1, rollouts 1-48) filled this cache: seeds 1 and 2 need
    # one new rollout between them
    return dict(timesteps=48, overrides=small("esac", root), budget="default")


@pytest.mark.parametrize("text, seeds", [("0-3", [0, 1, 2, 3]), ("4", [4]),
                                         ("0-1,7, 9", [0, 1, 7, 9])])
def test_parse_seeds(text, seeds):
    assert sweep.parse_seeds(text) == seeds


@pytest.mark.parametrize("text, msg", [("3-1", "expected seeds like"), ("a", "expected seeds"),
                                       ("1,1", "given twice"), ("999999999", "training")])
def test_parse_seeds_refuses(text, msg):
    with pytest.raises(ValueError, match=msg):
        sweep.parse_seeds(text)


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_workers_must_be_positive_int(workers):
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        backend_name(workers)


def test_backend_names():
    assert backend_name() == "serial"
    assert backend_name(2) == "processes"
    assert backend_name(1, "auto") == "ray"


@pytest.mark.parametrize("space, msg", [
    ("algo.gamma: {normal: [0, 1]}", "expected one of"),
    ("algo.gamma: {uniform: [0.99, 0.9]}", "needs low < high"),
    ("algo.gamma: {uniform: [0.9]}", "takes a list of 2 values"),
    ("[1, 2]", "expected a mapping"),
    ("fit.lr: {loguniform: [0, 1.0e-3]}", "needs 0 < low < high"),
    ("fit.lr: {uniform: [a, 1]}", "takes numbers"),
    ("env.history: {randint: [2.5, 9]}", "takes integers")])
def test_tune_space_refused(tmp_path, space, msg):
    f = tmp_path / "space.yaml"
    f.write_text(space)
    with pytest.raises(ValueError, match=msg):
        load_space(f)


def test_tune_space_reads_yaml_numbers(tmp_path):
    f = tmp_path / "space.yaml"
    f.write_text("fit.lr: {loguniform: [1e-5, 5e-4]}\nenv.history: {randint: [3, 9]}\n"
                 "fit.hidden: {choice: [[16], [32, 32]]}\n")  # YAML reads 1e-5 as text
    assert load_space(f) == {"fit.lr": {"loguniform": [1e-5, 5e-4]},
                             "env.history": {"randint": [3, 9]},
                             "fit.hidden": {"choice": [[16], [32, 32]]}}
    with pytest.raises(ValueError, match="cannot read it"):
        load_space(tmp_path / "missing.yaml")


def test_portable_options_make_every_path_absolute(tmp_path, monkeypatch):
    from pneugym import thesis_rig

    monkeypatch.chdir(tmp_path)
    thesis_rig().save("rig.json")
    shutil.copy(Path(__file__).resolve().parents[1] / "configs" / "esac.yaml", "esac.yaml")
    kw = sweep.portable("esac", {"rig": "rig.json", "config": "esac.yaml", "overrides": []}, [0, 5])
    assert kw["rig"] == str(tmp_path / "rig.json") and kw["config"] == str(tmp_path / "esac.yaml")
    assert kw["overrides"] == [f"cache_dir={tmp_path / 'runs' / '.cache'}"]
    with pytest.raises(ValueError, match="training"):  # every seed is checked, not only the first
        sweep.portable("esac", {}, [0, 10**9])


def test_sweep_refuses_a_seed_folder_in_use(tmp_path):
    (tmp_path / "seed_3").mkdir()
    (tmp_path / "seed_3" / "model.pt").write_text("x")
    with pytest.raises(ValueError, match="seed_3 is not empty"):
        sweep.train_seeds("esac", tmp_path, [2, 3], progress=False, timesteps=48)


def test_a_run_of_many_records_the_command_that_trains_it(tmp_path):
    """A sweep's or a tuning trial's run records the ``pneugym train`` line of that one run (the
    command line parses it back to the same options), not the worker process's command."""
    from agents.training.cli import parser
    from agents.training.trainer import command_line

    kw = {"budget": "quick", "config": "/c/ppo-family.yaml", "rig": "/c/rig.json",
          "timesteps": 400, "preset": "family", "progress": False,
          "overrides": ["algo.learning_rate=0.0001", "policy_kwargs.net_arch=[256, 256]"]}
    cmd = command_line("ppo", tmp_path / "seed_3", 3, kw)
    assert cmd[0] == "pneugym train"
    a = parser().parse_args(cmd[1:])
    assert (a.algo, a.seed, a.out, a.budget, a.config, a.rig, a.timesteps, a.preset, a.set) == (
        "ppo", 3, str(tmp_path / "seed_3"), "quick", "/c/ppo-family.yaml", "/c/rig.json", 400,
        "family", kw["overrides"])
    # the default budget and a rig given as a mapping (config.rig records it) stay off the line
    assert command_line("esac", "o", 0, {"budget": "default", "rig": {"valve": {}}}) == [
        "pneugym train", "--algo", "esac", "--seed", "0", "--out", "o"]


def test_task_failure_is_raised():
    with pytest.raises(ValueError, match="unknown algorithm"):
        run_tasks(sweep._one_seed, [{"algo": "nope", "out": "x", "seed": 0, "train_kw": {}}],
                  progress=False)


def test_evaluation_in_processes_matches_serial():
    serial = evaluate(**EVAL)
    par = evaluate(**EVAL, workers=2)
    assert _figures(par) == _figures(serial)
    assert par["suites"]["nominal"]["episodes"] == serial["suites"]["nominal"]["episodes"]


def test_learned_model_in_processes_matches_serial(tmp_path_factory, monkeypatch):
    """A saved ESAC model, named by a relative path (workers resolve it from this folder),
    evaluated in 2 processes as in this one (preloaded, as the command line does)."""
    from agents.evaluation.specs import load_models

    run = trained_runs(tmp_path_factory)["esac"]
    monkeypatch.chdir(run.parent)
    kw = {**EVAL, "policies": [f"{run.name}={run.name}", "gaslaw"]}
    serial = evaluate(**kw, preloaded=load_models(kw["policies"]))
    par = evaluate(**kw, workers=2)
    assert _figures(par) == _figures(serial) and run.name in _figures(par)


@pytest.fixture(scope="module")
def ray_head():
    """A Ray head on 127.0.0.1 with 2 CPUs and token authentication (a fresh token in the
    environment of the head and of the clients) for this module's tests: ``(address, env)``.
    Ray reads its token settings when it is imported, so clients run as subprocesses. The head
    runs with ``--block`` in a process group of its own, and only that group is stopped."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ray_bin = Path(sys.executable).with_name("ray")
    temp = Path("/tmp") / f"rt{os.getpid()}"  # Ray's socket paths must stay short
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    head = subprocess.Popen(
        [str(ray_bin), "start", "--head", "--block", "--node-ip-address", "127.0.0.1", "--port",
         str(port), "--num-cpus", "2", "--include-dashboard", "false", "--disable-usage-stats",
         "--temp-dir", str(temp)], env=env, start_new_session=True,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        address = f"127.0.0.1:{port}"
        for _ in range(60):  # until the head answers
            if subprocess.run([str(ray_bin), "status", "--address", address], env=env,
                              capture_output=True, timeout=60).returncode == 0:
                break
            assert head.poll() is None, "ray start --head exited"
            time.sleep(1)
        yield address, env
    finally:  # Ray's graceful stop takes about 30 s; its workers exit with their raylet
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait(timeout=60)
        shutil.rmtree(temp, ignore_errors=True)


def test_ray_head_refuses_a_client_without_the_token(ray_head):
    address, env = ray_head
    wrong = {**env, "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    r = subprocess.run([sys.executable, "-c", f"import ray; ray.init(address={address!r})"],
                       env=wrong, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0
    assert "InvalidAuthToken" in r.stderr or "Failed to connect" in r.stderr, r.stderr[-2000:]


def _pneugym(env, *args):
    """``pneugym ARGS`` in a subprocess with ``env``; fails the test with its output."""
    r = subprocess.run([sys.executable, "-m", "pneugym.cli", *map(str, args), "--no-progress"],
                       capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def _small_args(root):
    return ["--timesteps", "48", *[a for o in small("esac", root) for a in ("--set", o)]]


def test_seed_sweep_on_ray_matches_local(ray_head, tmp_path, tmp_path_factory):
    address, env = ray_head
    root = trained_runs(tmp_path_factory)["esac"].parent
    local = sweep.train_seeds("esac", tmp_path / "local", [1, 2], progress=False,
                              **_train_kw(root))
    _pneugym(env, "train", "--algo", "esac", "--seeds", "1-2", "--ray-address", address,
             "--out", tmp_path / "ray", *_small_args(root))
    on_ray = json.loads((tmp_path / "ray" / sweep.SWEEP_FILE).read_text())
    assert on_ray["backend"] == "ray" and local["backend"] == "serial"
    assert _seed_figures(on_ray) == _seed_figures(local)
    assert on_ray["summary"]["validation_return"] == local["summary"]["validation_return"]
    for s in (1, 2):  # every run is a complete run folder, as train.py writes it, the same rule
        for where in ("ray", "local"):  # ... recording the command that trains that one run
            run = json.loads((tmp_path / where / f"seed_{s}" / "run.json").read_text())
            assert run["seed"] == s and run["command"][:7] == [
                "pneugym train", "--algo", "esac", "--seed", str(s), "--out",
                str((tmp_path / where / f"seed_{s}").resolve())]
        a = (tmp_path / "local" / f"seed_{s}" / "rule_sweep.json").read_text()
        assert (tmp_path / "ray" / f"seed_{s}" / "rule_sweep.json").read_text() == a


def test_evaluation_on_ray_matches_serial(ray_head, tmp_path):
    address, env = ray_head
    _pneugym(env, "evaluate", "--policies", *EVAL["policies"], "--suite", "nominal",
             "--episodes", 1, "--seed", EVAL["seed"], "--ray-address", address,
             "--out", tmp_path)
    on_ray = json.loads((tmp_path / "results.json").read_text())
    assert _figures(on_ray) == _figures(evaluate(**EVAL))


def test_tune_on_ray(ray_head, tmp_path, tmp_path_factory):
    from agents.training import train
    from agents.training.tune import TUNE_FILE

    address, env = ray_head
    root = trained_runs(tmp_path_factory)["esac"].parent
    space = tmp_path / "space.yaml"
    space.write_text("rule_grid.margin: {choice: [[0.05], [0.1]]}\n")
    r = _pneugym(env, "train", "--algo", "esac", "--tune", space, "--trials", 2, "--seed", 1,
                 "--workers", 2, "--ray-address", address, "--out", tmp_path / "tune",
                 *_small_args(root))
    res = json.loads((tmp_path / "tune" / TUNE_FILE).read_text())
    assert len(res["results"]) == 2 and res["best"] == res["results"][0]
    assert f"(its run: {tmp_path / 'tune'}/trials/{res['best']['trial']})" in r.stdout
    assert {r["overrides"][0] for r in res["results"]} <= {"rule_grid.margin=[0.05]",
                                                          "rule_grid.margin=[0.1]"}
    for d in (tmp_path / "tune" / "trials").iterdir():  # each trial records its own command
        cmd = json.loads((d / "run.json").read_text())["command"]
        assert cmd[:5] == ["pneugym train", "--algo", "esac", "--seed", "1"]
        assert cmd[-2] == "--set" and cmd[-1].startswith("rule_grid.margin=")
    # a trial is a training run with the trial's overrides: seed 1 with the best margin
    run = train("esac", tmp_path / "direct", seed=1, progress=False,
                **{**_train_kw(root), "overrides": [*small("esac", root), *res["best"]["overrides"]]})
    assert run["best"]["return"] == res["best"]["validation_return"]


@pytest.mark.parametrize("args, msg", [
    (["--seeds", "0-1", "--workers", "0"], "--workers 0: must be >= 1"),
    (["--seeds", "0-1", "--seed", "3"], "list the seeds there"),
    (["--workers", "2"], "give --seeds"),
    (["--seeds", "0-1", "--resume"], "--resume and --force take one run"),
    (["--tune", "missing.yaml"], "cannot read it"),
    (["--seeds", "2-1"], "expected seeds like")])
def test_train_command_line_refuses(tmp_path, capsys, args, msg):
    from agents.training.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--algo", "esac", "--out", str(tmp_path / "out"), *args])
    assert exc.value.code == 2 and msg in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["train", "--algo", "esac", "--seeds", "0-1", "--ray-address", "local"],
    ["evaluate", "--policies", "gaslaw", "--ray-address", "local"],
])
def test_ray_address_without_ray_is_refused_before_any_work(argv, tmp_path, monkeypatch, capsys):
    """Without Ray installed, --ray-address exits 2 with how to install it, before training or
    evaluating anything (it raised ModuleNotFoundError after the work)."""
    import importlib.util

    from pneugym.cli import main

    find = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "ray" else find(name, *a))
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert '--ray-address needs Ray: pip install -e ".[ray]"' in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
