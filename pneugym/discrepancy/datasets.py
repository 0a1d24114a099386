"""Public measured data sets, read into the workflow's records (SI units, absolute pressures).

- :func:`zillen_chamber`: hold tests of seven compressed-air chambers (TU Delft, CC0 1.0), the
  files shipped unchanged in ``pneugym/discrepancy/data/zillen/`` with their README and licence.
"""
from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

import numpy as np

from .hold import HoldRecord

ZILLEN_CHAMBERS = ("Aluminium", "Formlabs", "Prusa", "Ultimaker_006", "Ultimaker_010",
                   "Ultimaker_015", "Ultimaker_020")
ZILLEN_SOURCE = ("Zillen, Vallery, Smit (TU Delft), github.com/EvaZillen/3D-printed-pneumatic-actuator "
                 "@6e0bcb4, appendix_compressed-air_chamber/data; CC0 1.0")
#: the files' time [ms]: groups of three digits joined by dots, the last group its decimals
_TIME = re.compile(r"\d{1,3}(\.\d{3})+")
#: assumed: the ambient pressure was not logged
AMBIENT_PA = 101_325.0


def zillen_chamber(name: str, path: str | Path | None = None) -> HoldRecord:
    """The hold test of chamber ``name`` (one of :data:`ZILLEN_CHAMBERS`), or of the file
    ``path`` in the same format: ``time_ms;volt;bar_gauge`` rows, the time in ms written with
    ``.`` between groups of three digits, the last group its decimals (``12.345.678`` is
    12,345.678 ms); another time is refused."""
    if path is None:
        if name not in ZILLEN_CHAMBERS:
            raise ValueError(f"unknown chamber {name!r}; choose from {ZILLEN_CHAMBERS}")
        path = resources.files("pneugym.discrepancy") / "data" / "zillen" / f"{name}.csv"
    t, p = [], []
    with open(path, encoding="utf-8") as f:  # type: ignore[arg-type]
        for k, line in enumerate(f, 1):
            parts = line.strip().split(";")
            if len(parts) < 3:
                continue
            try:
                if not _TIME.fullmatch(parts[0]):
                    raise ValueError(parts[0])
                t.append(float(parts[0].replace(".", "")) / 1e6)  # ms, 3 decimals -> s
                p.append(float(parts[2]) * 1e5 + AMBIENT_PA)  # bar gauge -> Pa absolute
            except ValueError:
                raise ValueError(f"{path}: line {k} is not 'time_ms;volt;bar': {line.strip()!r}") from None
    return HoldRecord(name, np.array(t), np.array(p), AMBIENT_PA, source=ZILLEN_SOURCE)
