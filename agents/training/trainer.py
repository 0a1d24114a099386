"""One training run, from its configuration to a finished ``run.json`` (:func:`train`): the
configuration checked whole, the run folder checked (new, ``--resume`` or ``--force``), the run
recorded, and PPO, DQN (:mod:`~agents.training.sb3`) or ESAC (:mod:`~agents.training.esac`)
trained with SIGINT and SIGTERM turned into a clean stop."""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from .config import ALGOS, load_config
from .resume import config_changes, occupied, resumable, resume_seed, start_over
from .rundir import RUN_FILE, atomic_write_json, read_run
from .seeds import MAX_TRAINING_SEED, check_seed
from .signals import StopRequest, TrainingInterrupted, stop_on_signals


def command_line(algo: str, out: str | Path, seed: int, train_kw: Mapping[str, Any]) -> list[str]:
    """The ``pneugym train`` command line that trains this one run: what a run of a seed sweep or
    a tuning trial records as its command (not the worker process's). ``train_kw`` as
    :func:`train` takes them; a rig given as a mapping is not on it (``config.rig`` has it)."""
    cmd = ["pneugym train", "--algo", algo, "--seed", str(seed), "--out", str(out)]
    for option, key in (("--preset", "preset"), ("--timesteps", "timesteps"), ("--budget", "budget"),
                        ("--config", "config"), ("--rig", "rig")):
        value = train_kw.get(key)
        if value is None or (key == "budget" and value == "default") or (
                key == "rig" and not isinstance(value, (str, Path))):
            continue
        cmd += [option, str(value)]
    for o in train_kw.get("overrides", ()):
        cmd += ["--set", str(o)]
    return cmd


def _threads(cfg: Mapping[str, Any]) -> None:
    """One thread each for numba and torch unless configured (the machine is small and shared;
    numba's parallel batch kernel is slower than one thread on a busy machine)."""
    import numba
    import torch

    numba.set_num_threads(max(1, min(int(cfg.get("numba_threads", 1)), numba.config.NUMBA_NUM_THREADS)))
    torch.set_num_threads(int(cfg.get("torch_threads", 1)))


def _warn_outside(cfg: dict[str, Any]) -> None:
    """A :class:`~agents.training.validation.TrainingRangeWarning` when the rig's own operating
    point lies outside the conditions the run trains on."""
    import warnings

    from .validation import RETRAIN_OVER_RANGE, TrainingRangeWarning, operating_point_outside

    if cfg.get("rig") is None:
        return
    what = operating_point_outside(cfg["preset"], cfg["rig"],
                                   (cfg.get("env") or {}).get("conditions"))
    if what:
        warnings.warn(f"the rig's own operating point lies outside the conditions this run "
                      f"trains on (preset {cfg['preset']}): {what}; train over the range the "
                      f"rig runs at, e.g. {RETRAIN_OVER_RANGE}", TrainingRangeWarning,
                      stacklevel=3)


def train(algo: str, out: str | Path, preset: str | None = None, timesteps: int | None = None,
          seed: int = 0, resume: bool = False, budget: str = "default",
          config: str | Path | None = None, overrides: Sequence[str] = (),
          progress: bool = True, force: bool = False,
          trust_pickled_replay_buffer: bool = False, rig: Any = None,
          command: Sequence[str] | None = None) -> dict[str, Any]:
    """Train ``algo`` into ``out``; returns the final ``run.json`` content.

    The configuration is checked whole before anything is written
    (:func:`~agents.training.config.check_config`). ``out`` must be new or empty unless
    ``resume`` (continue from its last checkpoint; an error if there is none, or if the run's
    seed is not a training seed) or ``force`` (start over a folder holding a train.py
    ``run.json``: the files train.py wrote there, :func:`~agents.training.rundir.run_files`, are
    listed, then removed; anything else stays, and a non-empty folder without ``run.json`` is
    refused).
    SIGINT or SIGTERM stop training at the next step: the last checkpoint is saved, ``run.json``
    records ``status: "interrupted"`` and :class:`TrainingInterrupted` is raised. DQN replay
    buffers of older runs (pickles) are loaded on resume only with
    ``trust_pickled_replay_buffer`` (only for your own runs). ``rig``: the rig to train on (a rig
    file, a mapping or a :class:`~pneugym.params.RigParams`; default the configuration's, else
    the thesis rig), recorded whole in ``run.json``'s ``config.rig``. ``command``: the command
    line ``run.json`` records (default this process's; a sweep or a tuning trial gives the
    ``pneugym train`` line of its one run, :func:`command_line`)."""
    from pneugym.outputs import check_output_dir
    from pneugym.provenance import provenance

    if algo not in ALGOS:
        raise ValueError(f"unknown algorithm {algo!r}; choose one of {ALGOS}")
    if resume and force:
        raise ValueError("--resume continues the run in --out, --force starts it over: give one")
    check_seed("training", seed)
    # the whole configuration, checked before anything is written
    cfg = load_config(algo, budget, config, overrides, preset=preset, timesteps=timesteps,
                      seed=None if resume else seed, rig=rig)
    raw_out, out = out, Path(out)
    if out.exists() or not resume:
        check_output_dir(raw_out, "run folder (--out)")
    prev = read_run(out) if out.is_dir() else None
    if resume and rig is None and "rig" not in cfg and (prev or {}).get("config", {}).get("rig"):
        # the run's rig stays: resuming without --rig must not switch to the thesis rig
        cfg = load_config(algo, budget, config, overrides, preset=preset, timesteps=timesteps,
                          rig=prev["config"]["rig"])
    if resume:
        resumable(out, prev, algo)
        old = resume_seed(out, prev)
        if old != seed:
            print(f"--resume: using the run's seed {old} (not {seed})", flush=True)
            seed = old
        changes = config_changes(prev.get("config", {}), cfg)
        if changes:
            print("--resume: the configuration differs from the run's (the new values apply): "
                  + "; ".join(changes), flush=True)
    elif force:
        start_over(out, prev)
        prev = None
    elif any(out.iterdir()):
        raise ValueError(occupied(out, prev))
    _warn_outside(cfg)
    _threads(cfg)
    from agents import esac
    from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: F401  (load the plant's code now)
    esac.source_hash()  # ... and key caches by these sources, even if the files change meanwhile
    run: dict[str, Any] = dict(prev) if resume else {}
    if "interrupted" in run:
        run["interruptions"] = [*run.get("interruptions", []), run.pop("interrupted")]
    run.update({"algo": algo, "seed": seed, "preset": cfg["preset"], "budget": budget,
                "config": cfg,
                "command": list(command) if command is not None
                else [Path(sys.argv[0]).name, *sys.argv[1:]],
                "provenance": provenance(), "pneugym_sources": esac.source_hash(),
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
                from .esac import train_esac

                summary = train_esac(cfg, out, seed, progress, record)
            else:
                from .sb3 import train_sb3  # imported here: SB3 loads only to train

                summary = train_sb3(cfg, out, seed, resume, progress, record, stop,
                                    trust_pickled_replay_buffer)
    except KeyboardInterrupt as exc:
        sig = getattr(exc, "signal_name", None) or stop.signal or "SIGINT"
        done = int(run.get("timesteps_done", 0)) if algo != "esac" else 0
        record(status="interrupted", interrupted={
            "signal": sig, "timesteps_done": done, "checkpoint": run.get("checkpoint")
            if algo != "esac" else None, "wall_s": time.perf_counter() - t0})
        raise TrainingInterrupted(sig, done, run) from None
    except Exception as exc:  # the folder says so (not "running" for ever)
        record(status="failed", error=f"{type(exc).__name__}: {exc}"[:2000],
               wall_s=time.perf_counter() - t0)
        raise
    summary["total_wall_s"] = time.perf_counter() - t0 + (
        float(prev.get("total_wall_s", 0.0)) if resume else 0.0)
    record(status="finished", **summary)
    return run
