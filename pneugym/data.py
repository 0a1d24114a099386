"""Measured runs in the ``pneugym-measurement/1`` format: read, validate, write, simulate.

A run is two files with the same stem, ``NAME.csv`` (samples) and ``NAME.json`` (what the
experimenter knows); see ``MEASUREMENT_FORMAT.md``. Everything is SI, pressures absolute.

>>> from pneugym.data import read_runs, simulate_run, write_run
>>> run = simulate_run(thesis_rig(2.5), t_end=1.0, seed=0)   # doctest: +SKIP
>>> write_run(run, "runs/conventional")                      # doctest: +SKIP
>>> runs = read_runs(["runs"])                                # doctest: +SKIP

Reading is strict: a file that breaks the format raises :class:`MeasurementFormatError` naming
the file, the row (CSV line) or key, and what is wrong. Nothing half-read is returned.
"""
from __future__ import annotations

import csv
import io
import json
import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from .params import RigParams
from .plant import Plant

FORMAT = "pneugym-measurement/1"
REQUIRED_COLUMNS = ("t", "valve", "x", "p_drive", "p_exhaust")
OPTIONAL_COLUMNS = ("p_supply", "mdot_supply", "T_drive")
PRESSURE_COLUMNS = ("p_drive", "p_exhaust", "p_supply")
#: Absolute pressures outside this range [Pa] are refused (bar or gauge by mistake).
PRESSURE_RANGE_PA = (1e3, 2e6)
#: Drive temperatures outside this range [K] are refused (°C by mistake).
TEMPERATURE_RANGE_K = (150.0, 500.0)
#: Relative tolerance on the sampling step (uniform sampling) and on ``sample_rate_hz``.
SAMPLING_TOLERANCE = 0.01
#: Positions may exceed [0, stroke] by this fraction of the stroke (sensor noise, offsets).
POSITION_TOLERANCE = 0.05

#: Top-level JSON keys that must be finite numbers, with their check.
_JSON_NUMBERS = {
    "supply_pressure_gauge_pa": (lambda v: 1e3 <= v <= 1.9e6,
                                 "in [1e3, 1.9e6] Pa gauge (bar by mistake?)"),
    "load_mass_kg": (lambda v: 0.0 <= v <= 1e4, "in [0, 1e4] kg"),
    "ambient_pressure_pa": (lambda v: 5e4 <= v <= 1.2e5, "in [5e4, 1.2e5] Pa absolute"),
    "ambient_temperature_k": (lambda v: 200.0 <= v <= 400.0, "in [200, 400] K (°C by mistake?)"),
    "sample_rate_hz": (lambda v: 0.0 < v <= 1e7, "> 0 Hz"),
}
_RIG_KEYS = ("bore_m", "rod_m", "stroke_m", "dead_volume_m3", "line_length_m", "line_diameter_m",
             "valve_area_m2", "port_area_m2", "exhaust_area_m2", "cushion_length_m",
             "cushion_factor_drive", "cushion_factor_exhaust", "discharge_coefficient",
             "valve_delay_s", "moving_mass_extra_kg")
_FRICTION_KEYS = ("static_n", "coulomb_n", "viscous_n_s_per_m")


class MeasurementFormatError(ValueError):
    """A measured run breaks ``pneugym-measurement/1``; the message names file, row/key, reason."""


@dataclass
class MeasuredRun:
    """One measured (or simulated) extension stroke.

    Arrays are float64 of equal length: ``t`` [s] since the extend command, ``valve`` command
    (0/1), ``x`` [m], ``p_drive``/``p_exhaust`` [Pa absolute] at the cylinder ports; optional
    ``p_supply`` [Pa], ``mdot_supply`` [kg/s], ``T_drive`` [K] (``None`` when absent). ``extra``
    holds unknown CSV columns (kept, ignored), ``meta`` the whole JSON.
    """

    name: str
    t: np.ndarray
    valve: np.ndarray
    x: np.ndarray
    p_drive: np.ndarray
    p_exhaust: np.ndarray
    meta: dict[str, Any]
    p_supply: np.ndarray | None = None
    mdot_supply: np.ndarray | None = None
    T_drive: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    source: Path | None = None

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def description(self) -> str:
        return str(self.meta.get("description", ""))

    @property
    def sample_dt_s(self) -> float:
        """Sampling step [s]."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def columns(self) -> dict[str, np.ndarray]:
        """Every present data column by its CSV name (required, optional, then extra)."""
        out = {c: getattr(self, c) for c in REQUIRED_COLUMNS}
        out.update({c: getattr(self, c) for c in OPTIONAL_COLUMNS if getattr(self, c) is not None})
        out.update(self.extra)
        return out

    def schedule(self) -> list[tuple[float, int]]:
        """Valve commands ``(time_s, value)`` for :meth:`pneugym.plant.Plant.run`: the first
        sample's command (at ``max(t0, 0)``) and every change, at the sample where it is seen."""
        v = self.valve.astype(int)
        out = [(max(float(self.t[0]), 0.0), int(v[0]))]
        for i in np.flatnonzero(np.diff(v)) + 1:
            out.append((max(float(self.t[i]), 0.0), int(v[i])))
        return out

    def rig(self, base: RigParams | None = None) -> RigParams:
        """The nominal rig of this run: its JSON over ``base`` (default: the project's rig)."""
        try:
            return RigParams.from_measurement(self.meta, base)
        except ValueError as exc:
            raise MeasurementFormatError(f"{self._where()}: the rig it describes is invalid: {exc}") from None

    def _where(self) -> str:
        return str(self.source.with_suffix(".json")) if self.source else f"run {self.name!r}"


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------
def _stem(path: str | Path) -> Path:
    p = Path(path)
    return p.with_suffix("") if p.suffix.lower() in (".csv", ".json") else p


def read_run(path: str | Path, base: RigParams | None = None) -> MeasuredRun:
    """Read one run from ``NAME.csv``, ``NAME.json`` or the stem ``NAME``; strict validation.

    ``base`` is the default rig that fills what the JSON does not give (for the position check
    against the stroke). Raises :class:`MeasurementFormatError`.
    """
    stem = _stem(path)
    csv_path, json_path = stem.with_suffix(".csv"), stem.with_suffix(".json")
    if not csv_path.is_file():
        raise MeasurementFormatError(f"{csv_path}: file not found (a run is NAME.csv + NAME.json)")
    if not json_path.is_file():
        raise MeasurementFormatError(
            f"{json_path}: file not found; the run {csv_path} is refused without its JSON")
    meta = _read_json(json_path)
    rig = _rig_from_meta(json_path, meta, base)
    cols, extra = _read_csv(csv_path, rig.cylinder.stroke_m, meta.get("sample_rate_hz"))
    return MeasuredRun(name=stem.name, meta=meta, extra=extra, source=stem, **cols)


def read_runs(paths: str | Path | Iterable[str | Path], base: RigParams | None = None) -> list[MeasuredRun]:
    """Read runs from files/stems and folders (every ``*.csv`` in a folder, sorted by name).

    Raises :class:`MeasurementFormatError` on the first bad run, or if nothing is found."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    runs: list[MeasuredRun] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(p.glob("*.csv"))
            if not found:
                raise MeasurementFormatError(f"{p}: folder holds no run (no NAME.csv)")
            runs += [read_run(f, base) for f in found]
        else:
            runs.append(read_run(p, base))
    if not runs:
        raise MeasurementFormatError("no run given")
    names = [r.name for r in runs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise MeasurementFormatError(f"run names must be unique; given twice: {dup}")
    return runs


def _read_json(path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"),
                          parse_constant=lambda c: _raise(path, f"non-JSON constant {c}"))
    except json.JSONDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not valid JSON: {exc}") from None
    except UnicodeDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not UTF-8 text: {exc}") from None
    if not isinstance(meta, dict):
        raise MeasurementFormatError(f"{path}: the top level must be a JSON object")
    fmt = meta.get("format")
    if fmt != FORMAT:
        raise MeasurementFormatError(f"{path}: key 'format' = {fmt!r}; expected {FORMAT!r}")
    if "supply_pressure_gauge_pa" not in meta:
        raise MeasurementFormatError(f"{path}: key 'supply_pressure_gauge_pa' is missing")
    for key, (ok, what) in _JSON_NUMBERS.items():
        if key in meta:
            _check_number(path, key, meta[key], ok, what)
    if "description" in meta and not isinstance(meta["description"], str):
        raise MeasurementFormatError(f"{path}: key 'description' must be a string")
    rig = meta.get("rig")
    _check_section(path, "rig", rig, _RIG_KEYS)
    if rig is not None:
        _check_section(path, "rig.friction", rig.get("friction"), _FRICTION_KEYS)
    return meta


def _check_section(path: Path, name: str, section: Any, keys: Sequence[str]) -> None:
    """An optional object whose known keys must be numbers >= 0 (SI)."""
    if section is None:
        return
    if not isinstance(section, dict):
        raise MeasurementFormatError(f"{path}: key {name!r} must be an object (or absent)")
    for key in keys:
        if key in section:
            _check_number(path, f"{name}.{key}", section[key], lambda v: v >= 0.0, ">= 0")


def _raise(path: Path, msg: str):
    raise MeasurementFormatError(f"{path}: {msg}")


def _check_number(path: Path, key: str, value: Any, ok, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise MeasurementFormatError(f"{path}: key {key!r} = {value!r} must be a finite number")
    if not ok(float(value)):
        raise MeasurementFormatError(f"{path}: key {key!r} = {value!r} must be {what}")


def _rig_from_meta(path: Path, meta: Mapping[str, Any], base: RigParams | None) -> RigParams:
    try:
        return RigParams.from_measurement(meta, base)
    except ValueError as exc:
        raise MeasurementFormatError(f"{path}: the rig it describes is invalid: {exc}") from None


def _read_csv(path: Path, stroke_m: float, rate_hz: float | None):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not UTF-8 text: {exc}") from None
    rows = list(csv.reader(io.StringIO(text)))
    while rows and not any(c.strip() for c in rows[-1]):
        rows.pop()  # trailing blank lines
    if not rows:
        raise MeasurementFormatError(f"{path}: empty file (expected a header row)")
    header = [h.strip() for h in rows[0]]
    for i, h in enumerate(header):
        if not h:
            raise MeasurementFormatError(f"{path}: line 1 (header): column {i + 1} has no name")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise MeasurementFormatError(f"{path}: line 1 (header): column(s) {dup} appear twice")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise MeasurementFormatError(
            f"{path}: line 1 (header): missing required column(s) {missing}; has {header}")
    body = rows[1:]
    if len(body) < 2:
        raise MeasurementFormatError(f"{path}: needs at least 2 samples, has {len(body)}")
    known = set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS)
    raw: dict[str, list[str]] = {h: [] for h in header}
    for k, row in enumerate(body):
        if len(row) != len(header):
            raise MeasurementFormatError(
                f"{path}: line {k + 2}: {len(row)} fields, the header has {len(header)}")
        for h, cell in zip(header, row):
            raw[h].append(cell.strip())
    cols: dict[str, np.ndarray] = {}
    for h in header:
        if h in known:
            cols[h] = _numeric_column(path, h, raw[h])
    extra: dict[str, np.ndarray] = {}
    for h in header:
        if h not in known:
            try:
                extra[h] = np.array([float(c) for c in raw[h]])
            except ValueError:
                extra[h] = np.array(raw[h], dtype=object)
    _check_columns(path, cols, stroke_m, rate_hz)
    return {c: cols.get(c) for c in REQUIRED_COLUMNS + OPTIONAL_COLUMNS}, extra


def _numeric_column(path: Path, name: str, cells: Sequence[str]) -> np.ndarray:
    out = np.empty(len(cells))
    for k, c in enumerate(cells):
        try:
            v = float(c)
        except ValueError:
            raise MeasurementFormatError(
                f"{path}: line {k + 2}, column {name!r}: {c!r} is not a number") from None
        if not math.isfinite(v):
            raise MeasurementFormatError(
                f"{path}: line {k + 2}, column {name!r}: {c!r} is not finite (NaN/inf)")
        out[k] = v
    return out


def _first_bad(path: Path, name: str, values: np.ndarray, bad: np.ndarray, what: str,
               first_sample: int = 0) -> None:
    """Refuse at the first ``bad`` value; ``values[k]`` is sample ``first_sample + k``."""
    idx = np.flatnonzero(bad)
    if idx.size:
        k = int(idx[0])
        more = f" ({idx.size} such rows)" if idx.size > 1 else ""
        raise MeasurementFormatError(
            f"{path}: line {k + first_sample + 2}, column {name!r}: {float(values[k])!r} {what}{more}")


def _check_columns(path: Path, cols: dict[str, np.ndarray], stroke_m: float,
                   rate_hz: float | None) -> None:
    t = cols["t"]
    dt = np.diff(t)
    _first_bad(path, "t", t[1:], dt <= 0.0, "is not after the previous time (t must increase strictly)",
               first_sample=1)
    step = float(np.median(dt))
    _first_bad(path, "t", t[1:], np.abs(dt - step) > SAMPLING_TOLERANCE * step,
               f"breaks the uniform sampling (step {step:.6g} s, tolerance "
               f"{SAMPLING_TOLERANCE:.0%})", first_sample=1)
    if rate_hz is not None and abs(1.0 / step - rate_hz) > SAMPLING_TOLERANCE * rate_hz:
        raise MeasurementFormatError(
            f"{path}: column 't' is sampled at {1.0 / step:.6g} Hz but {path.with_suffix('.json')} "
            f"key 'sample_rate_hz' says {rate_hz:.6g} Hz")
    v = cols["valve"]
    _first_bad(path, "valve", v, (v != 0.0) & (v != 1.0), "is not a valve command (0 or 1)")
    lo, hi = PRESSURE_RANGE_PA
    for name in PRESSURE_COLUMNS:
        if name in cols:
            p = cols[name]
            _first_bad(path, name, p, (p < lo) | (p > hi),
                       f"is outside [{lo:g}, {hi:g}] Pa absolute (bar or gauge by mistake?)")
    tol = POSITION_TOLERANCE * stroke_m
    x = cols["x"]
    _first_bad(path, "x", x, (x < -tol) | (x > stroke_m + tol),
               f"is outside the stroke [0, {stroke_m:g}] m (+-{tol:.3g} m; mm by mistake?)")
    if "T_drive" in cols:
        lo_t, hi_t = TEMPERATURE_RANGE_K
        T = cols["T_drive"]
        _first_bad(path, "T_drive", T, (T < lo_t) | (T > hi_t),
                   f"is outside [{lo_t:g}, {hi_t:g}] K (°C by mistake?)")


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------
def write_run(run: MeasuredRun, path: str | Path) -> Path:
    """Write ``run`` as ``PATH.csv`` + ``PATH.json`` (``PATH`` a stem; a .csv/.json suffix is
    dropped). Floats are written with ``repr`` so that reading gives the same numbers back.
    Returns the stem."""
    stem = _stem(path)
    stem.parent.mkdir(parents=True, exist_ok=True)
    cols = run.columns
    names = list(cols)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    arrays = [cols[n] for n in names]
    for i in range(len(run)):
        w.writerow([_fmt(a[i]) for a in arrays])
    stem.with_suffix(".csv").write_text(buf.getvalue(), encoding="utf-8")
    meta = dict(run.meta)
    meta.setdefault("format", FORMAT)
    stem.with_suffix(".json").write_text(json.dumps(meta, indent=2, allow_nan=False) + "\n",
                                         encoding="utf-8")
    return stem


def _fmt(v: Any) -> str:
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return str(int(f)) if f.is_integer() and abs(f) < 1e15 else repr(f)
    return str(v)


# ------------------------------------------------------------------------------------------
# simulated runs
# ------------------------------------------------------------------------------------------
#: Default measurement noise (standard deviations) of :func:`simulate_run`'s ``noise="default"``.
DEFAULT_NOISE = {"p_drive": 400.0, "p_exhaust": 400.0, "p_supply": 400.0, "x": 3e-5,
                 "mdot_supply": 0.0, "T_drive": 0.0}


def simulate_run(params: RigParams, schedule: Sequence[tuple[float, int]] = ((0.0, 1),),
                 t_end: float = 3.0, sample_rate_hz: float = 1000.0,
                 cut_on_arrival: bool = False, noise: Mapping[str, float] | str | None = None,
                 sensor_lag_s: float | None = None, known: RigParams | None = None,
                 seed: int | None = 0, name: str = "simulated", description: str = "",
                 optional: Sequence[str] = ()) -> MeasuredRun:
    """Run the plant and export the run in the measured-run format.

    - ``params``: the rig simulated (the truth: hidden effects and all).
    - ``schedule``, ``cut_on_arrival``: valve commands as for :meth:`Plant.run`. The CSV
      ``valve`` column is the command in force at each sample; a cut-off on arrival is given
      at the first sample at or after the arrival, as a sampling controller would.
    - ``sample_rate_hz``: sampling of the CSV; the plant records at exactly this rate.
    - ``noise``: Gaussian noise standard deviations by column (Pa, m, kg/s, K); ``"default"``
      is :data:`DEFAULT_NOISE` (400 Pa, 0.03 mm); ``None`` = none.
    - ``sensor_lag_s``: first-order lag [s] of the pressure transducers, applied in the plant
      (``EffectParams.sensor_lag_s``); pressures are always the transducer channels.
    - ``known``: the rig the experimenter believes in, written to the JSON ``rig`` section
      (default ``params``); lets test data hide effects and mis-set parameters.
    - ``optional``: optional columns to include (``p_supply``, ``mdot_supply``, ``T_drive``).

    The truth (``params``, noise, seed) is kept in the JSON under ``"simulation"``; readers
    ignore that key and the discrepancy workflow never reads it.
    """
    if sample_rate_hz <= 0 or not math.isfinite(sample_rate_hz):
        raise ValueError(f"sample_rate_hz = {sample_rate_hz} must be > 0")
    bad = sorted(set(optional) - set(OPTIONAL_COLUMNS))
    if bad:
        raise ValueError(f"unknown optional column(s) {bad}; choose from {OPTIONAL_COLUMNS}")
    if sensor_lag_s is not None:
        params = params.with_(effects={"sensor_lag_s": float(sensor_lag_s)})
    sd = dict(DEFAULT_NOISE) if noise == "default" else dict(noise or {})
    unknown = sorted(set(sd) - set(REQUIRED_COLUMNS) - set(OPTIONAL_COLUMNS))
    if unknown:
        raise ValueError(f"noise given for unknown column(s) {unknown}")
    dt = 1.0 / sample_rate_hz
    schedule = [(float(t), int(v)) for t, v in schedule]
    if cut_on_arrival:
        # a controller acts on samples: the cut-off goes out at the first sample at or after
        # the arrival, so that the recorded command is exactly the one the plant got
        probe = Plant(params)
        probe.run(t_end, schedule, record_dt=dt, cut_on_arrival=True)
        if probe.arrival_time_s is not None:
            t_cut = math.ceil(probe.arrival_time_s / dt - 1e-9) * dt
            if t_cut < t_end:
                schedule = schedule + [(t_cut, 0)]
    plant = Plant(params)
    traj = plant.run(t_end, schedule, record_dt=dt)
    rng = np.random.default_rng(seed)
    n = len(traj)
    t = np.round(traj["t"] / dt) * dt
    valve = np.zeros(n)
    for ts, v in sorted(schedule):  # the command in force at each sample (acts from its time on)
        valve[t >= ts - 1e-9] = float(v)
    cols = {
        "t": t,
        "valve": valve,
        "x": traj["x"].copy(),
        "p_drive": traj["p_drive_sensor"].copy(),
        "p_exhaust": traj["p_exhaust_sensor"].copy(),
    }
    if "p_supply" in optional:
        cols["p_supply"] = np.full(n, params.supply_pressure_pa)
    if "mdot_supply" in optional:
        cols["mdot_supply"] = traj["mdot_supply"].copy()
    if "T_drive" in optional:
        cols["T_drive"] = traj["T_drive"].copy()
    for c, s in sd.items():
        if c in cols and s > 0:
            cols[c] = cols[c] + rng.normal(0.0, s, n)
    rig_known = known or params
    meta = {
        "format": FORMAT,
        "supply_pressure_gauge_pa": params.supply_pressure_gauge_pa,
        "load_mass_kg": params.load_mass_kg,
        "ambient_pressure_pa": params.gas.ambient_pressure_pa,
        "ambient_temperature_k": params.gas.ambient_temperature_k,
        "sample_rate_hz": sample_rate_hz,
        "rig": rig_known.to_measurement_rig(),
        "description": description,
        "simulation": {"params": params.to_dict(), "noise": sd, "seed": seed,
                       "schedule": [list(s) for s in schedule], "cut_on_arrival": cut_on_arrival,
                       "arrival_time_s": plant.arrival_time_s},
    }
    return MeasuredRun(name=name, meta=meta, **cols)


def thesis_protocol(params: RigParams, known: RigParams | None = None, *, t_end: float = 3.0,
                    sample_rate_hz: float = 1000.0, noise: Mapping[str, float] | str | None = "default",
                    early_fraction: float = 0.6, early_cutoff_s: float | None = None,
                    seed: int = 0, prefix: str = "") -> list[MeasuredRun]:
    """The three runs of the test protocol on one rig: ``conventional`` (never cut),
    ``end_stroke_cutoff`` (cut on arrival) and ``early_cutoff`` (the valve closes when the
    *nominal* rig ``known`` would have the piston at ``early_fraction`` of the stroke, or the
    cut-off is commanded at ``early_cutoff_s`` if given).

    Each run gets its own noise stream (``seed``, ``seed + 1``, ``seed + 2``)."""
    known = known or params
    dt = 1.0 / sample_rate_hz
    if early_cutoff_s is None:
        ref = Plant(known).run(t_end, [(0.0, 1)], record_dt=dt)
        target = early_fraction * known.cylinder.stroke_m
        reached = np.flatnonzero(ref["x"] >= target)
        if reached.size == 0:
            raise ValueError(f"the nominal rig never reaches {early_fraction:.0%} of the stroke "
                             f"within {t_end} s; no early cut-off can be placed")
        early_cutoff_s = max(float(ref["t"][reached[0]]) - known.valve_delay_s - known.valve.ramp_s, 0.0)
    t_cut = round(early_cutoff_s / dt) * dt
    kw = dict(t_end=t_end, sample_rate_hz=sample_rate_hz, noise=noise, known=known)
    return [
        simulate_run(params, [(0.0, 1)], seed=seed, name=f"{prefix}conventional",
                     description="conventional", **kw),
        simulate_run(params, [(0.0, 1)], cut_on_arrival=True, seed=seed + 1,
                     name=f"{prefix}end_stroke_cutoff", description="end_stroke_cutoff", **kw),
        simulate_run(params, [(0.0, 1), (t_cut, 0)], seed=seed + 2, name=f"{prefix}early_cutoff",
                     description="early_cutoff", **kw),
    ]
