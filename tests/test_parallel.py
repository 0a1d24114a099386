"""Parallel work (pneugym.parallel): training seeds, evaluation and tuning give the same numbers
serially, in local processes and on a Ray cluster started here (``ray start --head`` on
127.0.0.1 with 2 CPUs)."""
from __future__ import annotations

import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
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
    ("[1, 2]", "expected a mapping")])
def test_tune_space_refused(tmp_path, space, msg):
    f = tmp_path / "space.yaml"
    f.write_text(space)
    with pytest.raises(ValueError, match=msg):
        load_space(f)


def test_task_failure_is_raised():
    with pytest.raises(ValueError, match="unknown algorithm"):
        run_tasks(sweep._one_seed, [{"algo": "nope", "out": "x", "seed": 0, "train_kw": {}}],
                  progress=False)


def test_evaluation_in_processes_matches_serial():
    serial = evaluate(**EVAL)
    par = evaluate(**EVAL, workers=2)
    assert _figures(par) == _figures(serial)
    assert par["suites"]["nominal"]["episodes"] == serial["suites"]["nominal"]["episodes"]


@pytest.fixture(scope="module")
def ray_head():
    """A Ray head on 127.0.0.1 with 2 CPUs and token authentication (a fresh token in the
    environment of the head and of the clients) for this module's tests: ``(address, env)``.
    Ray reads its token settings when it is imported, so clients run as subprocesses."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ray_bin = Path(sys.executable).with_name("ray")
    temp = Path("/tmp") / f"rt{os.getpid()}"  # Ray's socket paths must stay short
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    start = [str(ray_bin), "start", "--head", "--node-ip-address", "127.0.0.1", "--port",
             str(port), "--num-cpus", "2", "--include-dashboard", "false",
             "--disable-usage-stats", "--temp-dir", str(temp)]
    subprocess.run(start, check=True, capture_output=True, env=env, timeout=120)
    try:
        yield f"127.0.0.1:{port}", env
    finally:
        subprocess.run([str(ray_bin), "stop", "--force"], capture_output=True, env=env,
                       timeout=120)
        shutil.rmtree(temp, ignore_errors=True)


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
        assert json.loads((tmp_path / "ray" / f"seed_{s}" / "run.json").read_text())["seed"] == s
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
    _pneugym(env, "train", "--algo", "esac", "--tune", space, "--trials", 2, "--seed", 1,
             "--workers", 2, "--ray-address", address, "--out", tmp_path / "tune",
             *_small_args(root))
    res = json.loads((tmp_path / "tune" / TUNE_FILE).read_text())
    assert len(res["results"]) == 2 and res["best"] == res["results"][0]
    assert {r["overrides"][0] for r in res["results"]} <= {"rule_grid.margin=[0.05]",
                                                          "rule_grid.margin=[0.1]"}
    # a trial is a training run with the trial's overrides: seed 1 with the best margin
    run = train("esac", tmp_path / "direct", seed=1, progress=False,
                **{**_train_kw(root), "overrides": [*small("esac", root), *res["best"]["overrides"]]})
    assert run["best"]["return"] == res["best"]["validation_return"]
