"""Writing results without losing them: output folders checked before the work starts, files
written to a temporary name and renamed, sets of files replaced only once all are written.

>>> from pneugym.outputs import check_output_dir, atomic_write_json
>>> out = check_output_dir("results")              # doctest: +SKIP  (created, writable, or an error)
>>> atomic_write_json(out / "results.json", {"a": 1})  # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence


class OutputError(ValueError):
    """An output path cannot be used (a file where a folder is needed, not writable, ...)."""


def check_output_dir(path: str | Path, what: str = "output folder") -> Path:
    """Create ``path`` if needed and prove it is a writable folder, before any long work starts.

    Raises :class:`OutputError` naming the path when it is a file, or cannot be created or
    written."""
    if str(path).strip() == "":
        raise OutputError(f"{what} is empty: give a folder path (use '.' for this folder)")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{what} {p} exists and is not a folder: give a folder path")
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=p)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{what} {p} cannot be written: {exc.strerror or exc}") from None
    return p


def check_output_file(path: str | Path, what: str = "output file") -> Path:
    """Prove that ``path`` can be written as a file, before any long work starts: its folder is
    created and writable, and ``path`` itself is not a folder. Raises :class:`OutputError`."""
    if str(path).strip() == "":
        raise OutputError(f"{what} is empty: give a file path")
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{what} {p} is a folder: give a file path (e.g. {p / 'out.json'})")
    check_output_dir(p.parent, f"the folder of {what} {p}")
    return p


def _umask_mode() -> int:
    """The mode a new file gets from the process's umask (mkstemp alone gives 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to a temporary file beside ``path`` and rename it over ``path``: a reader
    sees the old file or the new one, never half of one."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return p


def atomic_write_json(path: str | Path, obj: Any, default: Callable[[Any], Any] | None = None,
                      indent: int = 1) -> Path:
    """:func:`atomic_write_text` of ``obj`` as JSON (no NaN: ``allow_nan=False``)."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, allow_nan=False,
                                              default=default) + "\n")


def _blocked(target: Path, dest: Path) -> bool:
    """True when ``target`` is a folder, or a file stands where one of its folders must go."""
    if target.is_dir():
        return True
    return any((dest / q).exists() and not (dest / q).is_dir()
               for q in target.relative_to(dest).parents if q != Path("."))


@contextlib.contextmanager
def staged_files(out: str | Path, replaces: Sequence[str] = ()) -> Iterator[Path]:
    """Write a set of files as a whole: the block writes into a staging folder inside ``out``;
    when it finishes, every staged file is renamed into ``out`` (each rename atomic) after
    checking that no target is a folder; when the block or a check fails, nothing in ``out``
    changes and the staging folder is removed. ``replaces``: glob patterns of the files in
    ``out`` the set replaces whole: those the block did not write again are removed then.

    >>> with staged_files("report") as stage:      # doctest: +SKIP
    ...     (stage / "report.json").write_text("{}")
    """
    dest = check_output_dir(out)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=dest))
    try:
        yield stage
        files = [f for f in sorted(stage.rglob("*")) if f.is_file()]
        for f in files:  # all checks first: a failing rename must not leave half a set
            target = dest / f.relative_to(stage)
            if _blocked(target, dest):
                raise OutputError(f"cannot write {target}: a folder or file is in the way; "
                                  f"nothing in {dest} was changed")
        written = {f.relative_to(stage) for f in files}
        for f in files:
            target = dest / f.relative_to(stage)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(f, target)
        for old in {p for pattern in replaces for p in dest.glob(pattern)}:
            if old.is_file() and old.relative_to(dest) not in written:
                old.unlink()
    finally:
        shutil.rmtree(stage, ignore_errors=True)
