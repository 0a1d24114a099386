"""Learned policies on demand (``pneugym evaluate``'s bare ``esac``, ``ppo``, ``dqn``): the model
of a finished run (:func:`model_path`), what would be done for each policy, checked before any
training (:func:`training_plan`), and the training of those missing (:func:`ensure_trained`)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from .config import CONFIG_DIR, load_config
from .resume import occupied, resumable, resume_seed
from .rundir import read_run
from .trainer import train

#: the learned policies evaluate.py trains on demand: name -> (algorithm, its configs/ file). The
#: ``-family`` ones learn on the rig family (preset ``family``) and read the rig's datasheet values
NAMED_RUNS: dict[str, tuple[str, str]] = {
    "esac": ("esac", "esac.yaml"), "ppo": ("ppo", "ppo.yaml"), "dqn": ("dqn", "dqn.yaml"),
    "esac-family": ("esac", "esac-family.yaml"), "ppo-family": ("ppo", "ppo-family.yaml")}
DEFAULT_POLICIES = ("esac", "ppo", "esac-family")  # what evaluate.py trains on demand


def model_path(run_dir: str | Path) -> Path | None:
    """The model file of a finished run directory (inside it), or None."""
    from agents.learned import run_member

    run = read_run(Path(run_dir))
    if not run or run.get("status") != "finished" or "model" not in run:
        return None
    p = run_member(Path(run_dir), run["model"], "model")
    return p if p.is_file() else None


def training_plan(names: Sequence[str] = DEFAULT_POLICIES, runs_dir: str | Path = "runs",
                  budget: str = "quick", rig: Any = None) -> dict[str, tuple[str, Path]]:
    """What :func:`ensure_trained` will do for each of ``names``: ``("ready", model file)``,
    ``("train", run dir)`` or ``("resume", run dir)``, checked before any training starts:
    ``runs_dir`` and each run folder must be folders, a run to train must have a usable folder
    and configuration (``budget``), a run to resume a checkpoint and a training seed. Raises
    ValueError (a :class:`~agents.learned.RunFileError` for a damaged run.json) naming what is
    wrong. ``rig``: the rig a missing policy is trained on (a finished run is used as it is)."""
    runs = Path(runs_dir)
    if runs.exists() and not runs.is_dir():
        raise ValueError(f"--runs {runs_dir} is a file; learned policies live in (and are "
                         f"trained into) folders under --runs: give a folder")
    plan: dict[str, tuple[str, Path]] = {}
    for name in names:
        if name not in NAMED_RUNS:
            raise ValueError(f"unknown learned policy {name!r}; choose from {list(NAMED_RUNS)}")
        algo, config = NAMED_RUNS[name][0], CONFIG_DIR / NAMED_RUNS[name][1]
        d = runs / name
        if d.exists() and not d.is_dir():
            raise ValueError(f"{d} is a file; the {name} run lives in the folder {d}: move the "
                             f"file, or give another --runs")
        p = model_path(d) if d.is_dir() else None
        # a budget or configuration train() would refuse (checked whole only if it will train)
        load_config(algo, budget, config, seed=0, rig=rig, check=p is None)
        if p is not None:
            plan[name] = ("ready", p)
            continue
        prev = read_run(d) if d.is_dir() else None
        resume = bool(prev and algo != "esac" and prev.get("algo") == algo
                      and prev.get("checkpoint"))
        try:
            if resume:
                resumable(d, prev, algo)
                resume_seed(d, prev)
            elif d.is_dir() and any(d.iterdir()):
                raise ValueError(occupied(d, prev))
        except ValueError as exc:
            raise ValueError(f"cannot train {name} on demand into {d}: {exc}") from None
        plan[name] = ("resume" if resume else "train", d)
    return plan


def ensure_trained(names: Sequence[str] = DEFAULT_POLICIES, runs_dir: str | Path = "runs",
                   budget: str = "quick", seed: int = 0, progress: bool = True,
                   rig: Any = None) -> dict[str, Path]:
    """The model of each of ``names`` under ``runs_dir/<name>``, training those that are missing
    with ``budget`` (evaluate.py's train-on-demand; an interrupted run is resumed). Every run is
    checked (:func:`training_plan`) before the first training starts. ``rig``: the rig to train
    the missing ones on (default the thesis rig)."""
    paths = {}
    for name, (what, p) in training_plan(names, runs_dir, budget, rig).items():
        if what == "ready":
            paths[name] = p
            continue
        print(f"== no trained {name} under {p}: "
              f"{'resuming' if what == 'resume' else 'training'} it ({budget} budget)",
              flush=True)
        algo, config = NAMED_RUNS[name]
        train(algo, p, seed=seed, budget=budget, progress=progress, resume=what == "resume",
              rig=rig, config=CONFIG_DIR / config)
        m = model_path(p)
        if m is None:
            raise RuntimeError(f"training {name} into {p} did not leave a finished model")
        paths[name] = m
    return paths
