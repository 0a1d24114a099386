"""Where numba caches pneugym's compiled kernels: a folder named by a hash of every source file
that holds jitted code.

numba keys a cached function on its own file's modification time only. A kernel that inlines a
function or reads a layout constant from another module keeps its stale machine code when only
that other module changes (an index shifted in :mod:`pneugym.physics.layout`, a force term
added to :mod:`pneugym.physics.cylinder`): wrong numbers, or NaN, with no error. Keying the whole
cache on all the jitted sources together recompiles everything once after any of them changes.

``NUMBA_CACHE_DIR``, if the user set it, is left alone. ``PNEUGYM_NUMBA_CACHE`` chooses the base
folder (default: ``pneugym/__pycache__/numba`` if writable, else ``~/.cache/pneugym/numba``);
caches of other source versions there, unused for :data:`KEEP_DAYS` days, are removed (a
process still running older sources keeps its own).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
KEEP_DAYS = 7.0


def sources_hash(package: Path = PACKAGE) -> str:
    """SHA-256 (16 hex digits) of the sources the kernels are compiled from, in path order: every
    file of ``pneugym/physics`` (the kernels, and the layout whose indices they read) and every
    other pneugym file that uses numba."""
    h = hashlib.sha256()
    for f in sorted(package.rglob("*.py")):
        text = f.read_bytes()
        rel = f.relative_to(package).as_posix()
        if rel.startswith("physics/") or b"numba" in text:
            h.update(rel.encode() + b"\0" + text + b"\0")
    return h.hexdigest()[:16]


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def cache_dir() -> Path | None:
    """The cache folder for these sources (created; others beside it removed), or None when
    the user set ``NUMBA_CACHE_DIR`` or no folder is writable (numba then decides)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    bases = [Path(os.environ["PNEUGYM_NUMBA_CACHE"])] if os.environ.get("PNEUGYM_NUMBA_CACHE") \
        else [PACKAGE / "__pycache__" / "numba", Path.home() / ".cache" / "pneugym" / "numba"]
    tag = sources_hash()
    for base in bases:
        if _writable(base):
            for old in base.iterdir():
                if old.is_dir() and old.name != tag and len(old.name) == 16 and _unused(old):
                    shutil.rmtree(old, ignore_errors=True)
            return base / tag
    return None


def _unused(folder: Path) -> bool:
    """Nothing in ``folder`` was written for :data:`KEEP_DAYS` days."""
    newest = max((f.stat().st_mtime for f in folder.rglob("*")), default=folder.stat().st_mtime)
    return time.time() - newest > KEEP_DAYS * 86400.0


def configure() -> None:
    """Point numba's cache at :func:`cache_dir` (before any pneugym kernel is defined)."""
    folder = cache_dir()
    if folder is None:
        return
    os.environ["NUMBA_CACHE_DIR"] = str(folder)  # for numba imported later, and subprocesses
    import numba

    numba.config.CACHE_DIR = str(folder)  # for numba imported already
