"""What a result file records about how it was made: versions, commit, machine."""
from __future__ import annotations

import datetime
import importlib.metadata
import platform
import subprocess
from pathlib import Path

PACKAGES = ("pneugym", "numpy", "numba", "scipy", "gymnasium", "stable-baselines3", "torch",
            "matplotlib")


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def git_commit() -> str | None:
    try:
        root = Path(__file__).resolve().parent.parent
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=5).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def provenance() -> dict:
    return {"versions": versions(), "git_commit": git_commit(),
            "machine": {"platform": platform.platform(), "processor": platform.machine()},
            "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat()}
