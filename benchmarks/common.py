"""What every pneugym benchmark shares: timing (round-robin), statistics, plain-text tables,
machine information, package versions and the goals the figures are held against.

Importing it puts the repository root on ``sys.path``, so that a benchmark measures the checkout
it lives in.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numba  # noqa: E402

import pneugym  # noqa: E402

GOAL_RTF = 1000.0
GOAL_ERR_PCT = 0.5
GOAL_SCIPY_RATIO = 50.0


# ------------------------------------------------------------------------------------------
# commissioning options (mpc-rig's benchmarks)
# ------------------------------------------------------------------------------------------
def add_commission_args(ap) -> None:
    """``--commission-starts``, ``--commission-nfev`` and ``--commission-refit`` on parser ``ap``:
    the commissioning fit's options, each ``mpc-rig``'s when not given."""
    ap.add_argument("--commission-starts", type=_at_least(1), default=None,
                    help="least-squares starts per line model (default: mpc-rig's)")
    ap.add_argument("--commission-nfev", type=_at_least(1), default=None,
                    help="evaluations per least-squares start (default: mpc-rig's)")
    ap.add_argument("--commission-refit", type=_at_least(0), default=None,
                    help="more starts per line model where a fit's misfit is flagged "
                         "(default: mpc-rig's)")


def _at_least(lo: int):
    """An argparse type: an integer >= ``lo``."""
    def parse(text: str) -> int:
        v = int(text)
        if v < lo:
            raise argparse.ArgumentTypeError(f"{v} is below {lo}")
        return v
    parse.__name__ = f"integer >= {lo}"
    return parse


def commission_overrides(args) -> dict:
    """The commissioning options given on the command line (:func:`add_commission_args`), as
    :func:`pneugym.commission.commission`'s keywords."""
    return {k: v for k, v in (("starts", args.commission_starts),
                              ("max_nfev", args.commission_nfev),
                              ("refit_starts", args.commission_refit)) if v is not None}


# ------------------------------------------------------------------------------------------
# timing
# ------------------------------------------------------------------------------------------
def timeit(fn, setup=None, repeats=11, warmup=1):
    """Wall times [s] of ``fn()`` (``setup()`` before each call, untimed); returns the list."""
    for _ in range(warmup):
        if setup is not None:
            setup()
        fn()
    out = []
    for _ in range(repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def interleaved(cases, reps, cpu=None):
    """Time several ``(name, fn, setup)`` cases round-robin (one call of each per round, after
    one warm-up round), so that load from other processes hits every case alike. If ``cpu`` is
    a dict, it receives the same calls' CPU times of this thread (``time.thread_time``): a
    single-threaded call's CPU time does not count the time the process waits for a core."""
    for _, fn, setup in cases:
        setup()
        fn()
    times = {name: [] for name, _, _ in cases}
    if cpu is not None:
        cpu.update({name: [] for name, _, _ in cases})
    for _ in range(reps):
        for name, fn, setup in cases:
            setup()
            c0 = time.thread_time()
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
            if cpu is not None:
                cpu[name].append(time.thread_time() - c0)
    return times


def stats(times):
    a = np.asarray(times, float)
    return {"median_s": float(np.median(a)), "min_s": float(a.min()), "max_s": float(a.max()),
            "n": int(a.size)}


# ------------------------------------------------------------------------------------------
# tables and number formatting
# ------------------------------------------------------------------------------------------
def rel_pct(x, ref):
    return 100.0 * (x - ref) / ref


def fmt_table(headers, rows, title=None):
    """Plain-text table (strings are left-aligned, numbers right-aligned)."""
    cells = [[str(h) for h in headers]] + [[c if isinstance(c, str) else f"{c}" for c in r]
                                           for r in rows]
    w = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    if title:
        lines.append(title)
    sep = "  "
    lines.append(sep.join(h.ljust(w[i]) for i, h in enumerate(cells[0])))
    lines.append(sep.join("-" * w[i] for i in range(len(w))))
    for r in cells[1:]:
        lines.append(sep.join(c.rjust(w[i]) if _numeric(c) else c.ljust(w[i])
                              for i, c in enumerate(r)))
    return "\n".join(lines)


def _numeric(s):
    try:
        float(s.replace("%", "").replace("x", "").replace("+", ""))
        return True
    except ValueError:
        return False


def g(x, nd=4):
    """Short number formatting for tables."""
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if not math.isfinite(x):
        return str(x)
    return f"{x:.{nd}g}"


def pct(x, nd=3):
    return "-" if x is None else f"{x:+.{nd}f}%"


# ------------------------------------------------------------------------------------------
# machine, versions, JSON
# ------------------------------------------------------------------------------------------
def machine_info():
    info = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "loadavg_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "numba_num_threads": numba.config.NUMBA_NUM_THREADS,
    }
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        with open("/proc/meminfo") as fh:
            info["mem_total"] = fh.readline().split(":", 1)[1].strip()
    except OSError:
        pass
    return info


def versions():
    import scipy
    v = {"pneugym": pneugym.__version__, "numpy": np.__version__, "numba": numba.__version__,
         "scipy": scipy.__version__, "llvmlite": __import__("llvmlite").__version__}
    import hashlib
    h = hashlib.sha256()
    # the figures follow the policies and their configurations as well as the plant
    for f in sorted(f for d in ("pneugym", "agents", "configs") for f in (ROOT / d).rglob("*")
                    if f.suffix in (".py", ".yaml", ".json") and "__pycache__" not in f.parts):
        h.update(str(f.relative_to(ROOT)).encode())
        h.update(f.read_bytes())
    v["pneugym_source_sha256"] = h.hexdigest()[:16]  # (pneugym/, agents/ and configs/)
    v["pneugym_path"] = str(Path(pneugym.__file__).resolve().parent)
    try:
        v["git_commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                         text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--",
                                "pneugym", "agents", "configs"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        v["pneugym_dirty"] = bool(dirty)
    except (OSError, subprocess.CalledProcessError):
        pass
    return v


def json_default(o):
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
