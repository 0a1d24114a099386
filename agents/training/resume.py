"""A run folder that already holds something: ``--resume`` continues its run from the last
checkpoint (:func:`resumable`, :func:`resume_seed`, :func:`config_changes`), ``--force`` starts a
train.py run over (:func:`start_over`: removes exactly the files train.py wrote), and otherwise
the folder is refused (:func:`occupied` says why and what to do)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from .config import ALGOS
from .rundir import RUN_FILE, RUN_FOLDERS, checkpoint_of, run_files
from .seeds import MAX_TRAINING_SEED, check_seed


def resumable(out: Path, prev: Mapping[str, Any] | None, algo: str) -> Path:
    """The checkpoint ``--resume`` continues from, or a ValueError saying what to do."""
    if prev is None:
        why = "the folder does not exist" if not out.exists() else f"it has no {RUN_FILE}"
        raise ValueError(f"--resume: nothing to resume in {out}: {why}. Start a new run "
                         f"without --resume.")
    if prev.get("algo") != algo:
        raise ValueError(f"--resume: {out} holds a {prev.get('algo')} run, not {algo}")
    if algo == "esac":
        raise ValueError(f"--resume: ESAC trains in one piece and keeps no checkpoints; start "
                         f"{out} over with --force, or train into another --out")
    ckpt = checkpoint_of(out, prev)
    if ckpt is None:
        raise ValueError(f"--resume: {out / RUN_FILE} records no checkpoint (the run stopped "
                         f"before its first, due after checkpoint_every steps); start it over "
                         f"with --force")
    if not ckpt.is_file():
        raise ValueError(f"--resume: {out / RUN_FILE} names the checkpoint {prev['checkpoint']},"
                         f" which does not exist; start the run over with --force")
    return ckpt


def resume_seed(out: Path, prev: Mapping[str, Any]) -> int:
    """The training seed a run to resume records, checked: a training seed (below
    :data:`MAX_TRAINING_SEED`), else a ValueError saying the run cannot be continued."""
    old = prev.get("seed")
    if not isinstance(old, int) or isinstance(old, bool):
        raise ValueError(f"--resume: {out / RUN_FILE} records no training seed (seed: {old!r}); "
                         f"it cannot be resumed: start it over with --force")
    try:
        check_seed("training", old)
    except ValueError as exc:
        raise ValueError(f"--resume: {out / RUN_FILE} records seed {old}: {exc}; that run cannot "
                         f"be continued: start it over with --force and a seed below "
                         f"{MAX_TRAINING_SEED:,}") from None
    return old


def occupied(out: Path, prev: Mapping[str, Any] | None) -> str:
    """Why a new run may not start in the non-empty ``out``, and what to do."""
    if prev is not None:
        status = prev.get("status")
        how = {"finished": "finished",
               "interrupted": f"interrupted at {prev.get('timesteps_done', 0)} timesteps",
               "running": "running, or killed",
               "failed": f"failed: {str(prev.get('error', ''))[:200]}"}.get(
                   str(status), f"status {status!r}")
        again = "" if prev.get("algo") == "esac" else \
            "continue it with --resume, "  # (ESAC keeps no checkpoints)
        return (f"{out} holds a {prev.get('algo')} run ({how}): {again}start it over with "
                f"--force (removes its model, checkpoints and logs), or choose another --out")
    names = sorted(p.name for p in out.iterdir())
    return (f"{out} is not empty ({len(names)} entries: {', '.join(names[:5])}"
            f"{', ...' if len(names) > 5 else ''}) and holds no {RUN_FILE}: it is not a train.py "
            f"run, so nothing in it is removed (not even with --force); choose a new or empty "
            f"--out")


def start_over(out: Path, prev: Mapping[str, Any] | None) -> list[str]:
    """``--force``: remove the previous run's files from ``out`` (:func:`run_files`: exactly
    what train.py writes), listing them first; anything else stays. Only a folder holding a
    train.py ``run.json`` is started over: another non-empty folder is refused (ValueError)."""
    if not out.is_dir() or not any(out.iterdir()):
        return []
    if prev is None:
        raise ValueError(occupied(out, None))
    if prev.get("algo") not in ALGOS:
        raise ValueError(f"--force: {out / RUN_FILE} records algo {prev.get('algo')!r}, not one "
                         f"of {list(ALGOS)}: not a train.py run; nothing in {out} is removed. "
                         f"Choose a new or empty --out")
    gone = run_files(out)
    names = [p.relative_to(out).as_posix() for p in gone]
    print(f"--force: starting {out} over; removing the previous run's "
          f"{', '.join(names) if names else 'files (none found)'}", flush=True)
    for p in gone:
        p.unlink(missing_ok=True)
    for sub in RUN_FOLDERS:
        d = out / sub
        if d.is_dir() and not d.is_symlink() and not any(d.iterdir()):
            d.rmdir()
    kept = []
    for p in sorted(out.iterdir()):
        if p.name in RUN_FOLDERS and p.is_dir() and not p.is_symlink():
            kept += [f"{p.name}/{q.name}" for q in sorted(p.iterdir())]
        else:
            kept.append(p.name + ("/" if p.is_dir() else ""))
    if kept:
        print(f"--force: kept {', '.join(kept)} (not written by train.py)", flush=True)
    return names


def config_changes(old: Any, new: Any, prefix: str = "") -> list[str]:
    """The entries (``a.b: old -> new``) where a resumed run's config differs from the run's."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        return [c for k in sorted(set(old) | set(new), key=str)
                if k not in ("timesteps", "budget") or prefix
                for c in config_changes(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix[:-1]}: {old!r} -> {new!r}"]
