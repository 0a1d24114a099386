"""A run folder: the files a training run writes there (:data:`RUN_FILES`, :func:`run_files`), its
record ``run.json`` (:func:`read_run`), and the atomic writes that keep every file in it complete
(written to a temporary name, then renamed)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

RUN_FILE = "run.json"


#: the files train.py writes into a run directory, by exact name or pattern (``--force``
#: removes these, and only these): the run record, models, ESAC's reports, logs, and the
#: temporaries of atomic writes a killed run may leave
RUN_FILES = (RUN_FILE, "model.zip", "best_model.zip", "model.pt", "accuracy.json",
             "accuracy.png", "rule_sweep.json", "progress.csv")
RUN_PATTERNS = (r"progress\.\d+\.csv",  # the earlier parts of a resumed run's log
                r"events\.out\.tfevents\.\d+\.[\w.-]+",  # TensorBoard, runs before tb/
                r"\.(model|best_model)\.\d+\.tmp\.zip",  # atomic_save_sb3
                r"model\.pt\.\d+\.tmp",  # esac.save
                r"\.(run|accuracy|rule_sweep)\.json\.[\w.-]+\.tmp")  # atomic JSON
#: sub-folders train.py writes, and their files (the folder goes too once it is empty)
RUN_FOLDERS = {
    "checkpoints": (r"ckpt_\d{9}\.zip", r"replay_\d{9}\.(npz|pkl)",
                    r"\.ckpt_\d{9}\.\d+\.tmp\.zip", r"\.replay_\d{9}\.npz\.[\w.-]+\.tmp"),
    "tb": (r"events\.out\.tfevents\.\d+\.[\w.-]+",),
}


def atomic_write_json(path: Path, obj: Any) -> None:
    """Write JSON to a temporary file and rename it over ``path``
    (:func:`pneugym.outputs.atomic_write_json`, numpy values and paths converted)."""
    from pneugym.outputs import atomic_write_json as write

    write(path, obj, default=_jsonable)


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    return repr(v)


def atomic_save_sb3(model, path: Path) -> None:
    """``model.save`` to a temporary name, then rename (never a half-written zip at ``path``;
    the temporary file is removed if the save is interrupted)."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.zip")
    try:
        model.save(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_run(out: Path) -> dict[str, Any] | None:
    """``out/run.json``, checked (:func:`agents.learned.load_run_file`), or None if absent."""
    from agents.learned import load_run_file

    f = Path(out) / RUN_FILE
    return load_run_file(f) if f.is_file() else None


def replay_file(ckpt: Path, suffix: str = ".npz") -> Path:
    """The replay buffer saved with checkpoint ``ckpt`` (``replay_<steps>.npz``; ``.pkl``:
    the pickled format of older runs)."""
    return ckpt.with_name(ckpt.name.replace("ckpt_", "replay_", 1)).with_suffix(suffix)


def run_files(out: Path) -> list[Path]:
    """The files in ``out`` that train.py writes for a run (:data:`RUN_FILES`,
    :data:`RUN_PATTERNS`, :data:`RUN_FOLDERS`): files or links with exactly those names, never
    a folder's other contents."""
    import re

    def ours(p: Path, names: Sequence[str], patterns: Sequence[str]) -> bool:
        return (p.is_file() or p.is_symlink()) and (
            p.name in names or any(re.fullmatch(pat, p.name) for pat in patterns))

    found = [p for p in out.iterdir() if ours(p, RUN_FILES, RUN_PATTERNS)]
    for sub, patterns in RUN_FOLDERS.items():
        d = out / sub
        if d.is_dir() and not d.is_symlink():
            found += [p for p in d.iterdir() if ours(p, (), patterns)]
    return sorted(found)


def checkpoint_of(out: Path, run: Mapping[str, Any]) -> Path | None:
    """The checkpoint ``run.json`` records (confined to ``out``), or None."""
    from agents.learned import run_member

    name = run.get("checkpoint")
    return None if name is None else run_member(out, name, "checkpoint")
