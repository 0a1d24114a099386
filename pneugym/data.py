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
import difflib
import io
import itertools
import json
import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .params import CYLINDER_DESIGNS, STROKE_DIRECTIONS, RigParams, did_you_mean
from .plant import Plant

FORMAT = "pneugym-measurement/1"
REQUIRED_COLUMNS = ("t", "valve", "x", "p_drive", "p_exhaust")
#: the largest run JSON read [bytes] (the metadata; the samples are in the CSV)
MAX_JSON_BYTES = 1_000_000
OPTIONAL_COLUMNS = ("p_supply", "mdot_supply", "T_drive")
PRESSURE_COLUMNS = ("p_drive", "p_exhaust", "p_supply")
#: Absolute pressures outside this range [Pa] are refused (bar or gauge by mistake).
PRESSURE_RANGE_PA = (1e3, 2e6)
#: Pressures below this fraction of the run's ambient pressure are refused (gauge by mistake).
GAUGE_FRACTION = 0.5
#: Drive temperatures outside this range [K] are refused (°C by mistake).
TEMPERATURE_RANGE_K = (150.0, 500.0)
#: Relative tolerance on the sampling step (uniform sampling) and on ``sample_rate_hz``.
SAMPLING_TOLERANCE = 0.01
#: Coarsest sampling step [s] accepted (20 Hz): slower sampling cannot resolve a stroke, and a
#: step of 1 usually means ``t`` in ms by mistake.
MAX_SAMPLE_STEP_S = 0.05
#: Positions may exceed [0, stroke] by this fraction of the stroke (sensor noise, offsets).
POSITION_TOLERANCE = 0.05
#: CSV rows converted at a time (streamed reading keeps memory to the arrays it returns).
CSV_CHUNK_ROWS = 16384
#: ``t`` is the time since the extend command: a first sample further than this [s] from
#: ``t = 0`` is refused (epoch time, or a clock started long before the run).
FIRST_SAMPLE_MAX_S = 60.0


@dataclass(frozen=True)
class Plausible:
    """Plausible range of a JSON number and the unit mistakes that explain a value outside it.

    ``mistakes``: ``(unit, size in SI)``; a value ``v`` outside ``[lo, hi]`` for which
    ``v * size`` is inside is reported as "``unit`` given as ``self.unit``?" (the candidate
    nearest to ``typical`` on a log scale wins). ``lo_open``: ``lo`` itself is refused."""

    lo: float
    hi: float
    what: str
    unit: str  # SI unit of the key ("" for a dimensionless factor)
    typical: float
    mistakes: tuple[tuple[str, float], ...] = ()
    lo_open: bool = False
    hint: str = ""  # the likely mistake when no unit conversion explains the value

    def ok(self, v: float) -> bool:
        return (v > self.lo if self.lo_open else v >= self.lo) and v <= self.hi

    def problem(self, v: float) -> str:
        """Why ``v`` is refused, with the likely mistake."""
        u = f" {self.unit}" if self.unit else ""
        lo = f"{self.lo:g} (excluded)" if self.lo_open else f"{self.lo:g}"
        msg = f"{v:g}{u} is not a plausible {self.what} (expected {lo} to {self.hi:g}{u})"
        fits = [(abs(math.log(v * size / self.typical)), unit, v * size)
                for unit, size in self.mistakes if v > 0 and self.ok(v * size)]
        if fits:
            _, unit, conv = min(fits)
            if self.unit:
                return f"{msg}; {unit} given as {self.unit}? ({conv:.4g} {self.unit} = {v:.4g} {unit})"
            return f"{msg}; percent given as a fraction? ({conv:.4g} = {v:.4g} %)"
        if self.hint:
            return f"{msg}; {self.hint}"
        return msg + (f"; check the unit ({self.unit})" if self.unit else "")


_LENGTH = (("mm", 1e-3), ("cm", 1e-2))
_AREA = (("mm²", 1e-6), ("cm²", 1e-4))
_VOLUME = (("cm³", 1e-6), ("litres", 1e-3), ("mm³", 1e-9))
_FRACTION = (("%", 1e-2),)
_PRESSURE = (("bar", 1e5), ("kPa", 1e3), ("psi", 6894.757), ("MPa", 1e6))

#: Plausible ranges of the JSON numbers (SI), generous on purpose: any real pneumatic cylinder
#: rig meets them (bores 2.5-500 mm, strokes 1 mm-5 m, tubes 0.5-80 mm, orifices 1e-3-5000
#: mm², dead volumes 1 mm³-20 L, valve delays up to 2 s, friction up to 1e5 N), so a value
#: outside is a unit mistake, named in the refusal. The ranges are at least as tight as those
#: of :class:`~pneugym.params.RigParams`, so a value out of range is refused here, naming this
#: file and key; relations between keys (rod < bore, cushion < half the stroke) are left to
#: RigParams, whose refusal is reported with the file. Keys: top level, ``rig.KEY`` and
#: ``rig.friction.KEY``.
PLAUSIBLE: dict[str, Plausible] = {
    "supply_pressure_gauge_pa": Plausible(1e4, 1.9e6, "supply pressure (gauge)", "Pa", 2.5e5, _PRESSURE),
    "load_mass_kg": Plausible(0.0, 1e4, "payload", "kg", 10.0),
    "ambient_pressure_pa": Plausible(5e4, 1.2e5, "ambient pressure (absolute)", "Pa", 101325.0,
                                     (("bar", 1e5), ("kPa", 1e3), ("mbar", 1e2), ("hPa", 1e2))),
    "ambient_temperature_k": Plausible(200.0, 400.0, "ambient temperature", "K", 293.15,
                                       hint="°C given as K? (20 °C = 293.15 K)"),
    "sample_rate_hz": Plausible(0.0, 1e7, "sample rate", "Hz", 1000.0, (("kHz", 1e3),), lo_open=True),
    "rig.bore_m": Plausible(2.5e-3, 0.5, "bore", "m", 0.125, _LENGTH),
    "rig.rod_m": Plausible(0.0, 0.3, "rod diameter", "m", 0.032, _LENGTH),
    "rig.stroke_m": Plausible(1e-3, 5.0, "stroke", "m", 0.18, _LENGTH),
    "rig.dead_volume_m3": Plausible(1e-9, 0.02, "dead volume", "m³", 2.4e-4, _VOLUME),
    "rig.line_length_m": Plausible(1e-3, 50.0, "line length", "m", 1.0, _LENGTH),
    "rig.line_diameter_m": Plausible(5e-4, 0.08, "line inner diameter", "m", 0.005, _LENGTH),
    "rig.valve_area_m2": Plausible(1e-9, 5e-3, "valve orifice area", "m²", 2e-5, _AREA),
    "rig.port_area_m2": Plausible(1e-9, 5e-3, "port orifice area", "m²", 2e-5, _AREA),
    "rig.exhaust_area_m2": Plausible(1e-9, 5e-3, "exhaust orifice area", "m²", 2e-5, _AREA),
    "rig.cushion_length_m": Plausible(0.0, 0.2, "cushion length", "m", 0.015, _LENGTH),
    "rig.cushion_factor_drive": Plausible(0.0, 1.0, "cushion area factor", "", 0.3, _FRACTION, lo_open=True),
    "rig.cushion_factor_exhaust": Plausible(0.0, 1.0, "cushion area factor", "", 0.08, _FRACTION, lo_open=True),
    "rig.discharge_coefficient": Plausible(0.0, 1.0, "discharge coefficient", "", 0.72, _FRACTION, lo_open=True),
    "rig.valve_delay_s": Plausible(0.0, 2.0, "valve delay", "s", 0.185, (("ms", 1e-3),)),
    "rig.moving_mass_extra_kg": Plausible(0.0, 2000.0, "moving mass besides the payload", "kg", 1.0),
    "rig.friction.static_n": Plausible(0.0, 1e5, "breakaway friction", "N", 359.0),
    "rig.friction.coulomb_n": Plausible(0.0, 1e5, "Coulomb friction", "N", 126.0),
    "rig.friction.viscous_n_s_per_m": Plausible(0.0, 1e6, "viscous friction", "N s/m", 1557.0),
    "rig.dead_volume_rod_m3": Plausible(1e-9, 0.02, "rod-side dead volume", "m³", 2.4e-4, _VOLUME),
    "rig.mounting_angle_deg": Plausible(-90.0, 90.0, "mounting angle", "deg", 0.0,
                                        hint="0 horizontal, 90 rod up, -90 rod down"),
    "external_force_n": Plausible(-1e6, 1e6, "external force opposing the stroke", "N", 0.0),
}
#: Keys whose values are text, checked against their choices.
TEXT_KEYS = {"stroke_direction": STROKE_DIRECTIONS, "rig.cylinder_design": CYLINDER_DESIGNS}
#: Top-level JSON keys the format defines (others are kept and ignored unless they look like a
#: misspelling of one of these).
TOP_KEYS = ("format", "supply_pressure_gauge_pa", "load_mass_kg", "ambient_pressure_pa",
            "ambient_temperature_k", "sample_rate_hz", "rig", "description", "stroke_direction",
            "external_force_n")
_RIG_KEYS = ("bore_m", "rod_m", "stroke_m", "dead_volume_m3", "line_length_m", "line_diameter_m",
             "valve_area_m2", "port_area_m2", "exhaust_area_m2", "cushion_length_m",
             "cushion_factor_drive", "cushion_factor_exhaust", "discharge_coefficient",
             "valve_delay_s", "moving_mass_extra_kg", "cylinder_design", "dead_volume_rod_m3",
             "mounting_angle_deg")
_FRICTION_KEYS = ("static_n", "coulomb_n", "viscous_n_s_per_m")
#: an unknown top-level key this similar (difflib ratio, lower case) to a known one is refused
NEAR_MISS_RATIO = 0.75


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
    #: samples averaged into each row (1 = as measured; > 1: a block-averaged run, see
    #: :mod:`pneugym.discrepancy.prepare`; its ``valve`` is the fraction of the block commanded)
    block: int = 1
    #: valve commands ``(time_s, value)`` when the ``valve`` column cannot carry them exactly
    #: (a block-averaged run); ``None``: from the ``valve`` column
    commands: tuple[tuple[float, int], ...] | None = None

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
        if self.commands is not None:
            return [(float(t), int(v)) for t, v in self.commands]
        v = self.valve.astype(int)
        out = [(max(float(self.t[0]), 0.0), int(v[0]))]
        for i in np.flatnonzero(np.diff(v)) + 1:
            out.append((max(float(self.t[i]), 0.0), int(v[i])))
        return out

    def rig(self, base: RigParams | None = None) -> RigParams:
        """The nominal rig of this run: its JSON over ``base`` (default: the project's rig)."""
        _check_moving_mass(self._where(), self.meta, base)
        try:
            return RigParams.from_measurement(self.meta, base)
        except ValueError as exc:
            raise MeasurementFormatError(f"{self._where()}: the rig it describes is invalid: {exc}") from None

    def _where(self) -> str:
        return str(_with_ext(self.source, ".json")) if self.source else f"run {self.name!r}"


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------
def _stem(path: str | Path) -> Path:
    p = Path(path)
    return p.with_suffix("") if p.suffix.lower() in (".csv", ".json") else p


def _with_ext(stem: Path, ext: str) -> Path:
    return stem.with_name(stem.name + ext)


def _find(stem: Path, ext: str) -> Path:
    """``stem`` + ``ext`` with the extension matched case-insensitively (``NAME.CSV``,
    ``NAME.Json``); the lower-case name when no such file exists."""
    exact = _with_ext(stem, ext)
    if exact.is_file():
        return exact
    try:
        found = sorted(f for f in stem.parent.iterdir()
                       if f.stem == stem.name and f.suffix.lower() == ext and f.is_file())
    except OSError:
        return exact
    if len(found) > 1:
        raise MeasurementFormatError(
            f"{exact}: ambiguous, several files differ only in the case of the extension: "
            f"{[f.name for f in found]}")
    return found[0] if found else exact


def read_run(path: str | Path, base: RigParams | None = None) -> MeasuredRun:
    """Read one run from ``NAME.csv``, ``NAME.json`` or the stem ``NAME``; strict validation.

    Extensions are matched case-insensitively; a UTF-8 byte-order mark is accepted. ``base``
    is the default rig that fills what the JSON does not give (for the position check against
    the stroke, the ambient pressure). The CSV is streamed: memory is that of the arrays
    returned. Raises :class:`MeasurementFormatError`, and no other exception for bad content.
    """
    stem = _stem(path)
    csv_path, json_path = _find(stem, ".csv"), _find(stem, ".json")
    if not csv_path.is_file():
        raise MeasurementFormatError(f"{csv_path}: file not found (a run is NAME.csv + NAME.json)")
    if not json_path.is_file():
        raise MeasurementFormatError(
            f"{json_path}: file not found; the run {csv_path} is refused without its JSON")
    meta = _read_json(json_path)
    _check_moving_mass(json_path, meta, base)
    rig = _rig_from_meta(json_path, meta, base)
    cols, extra = _read_csv(csv_path, json_path, rig.cylinder.stroke_m, meta.get("sample_rate_hz"),
                            rig.gas.ambient_pressure_pa)
    return MeasuredRun(name=stem.name, meta=meta, extra=extra, source=stem, **cols)


def read_runs(paths: str | Path | Iterable[str | Path], base: RigParams | None = None) -> list[MeasuredRun]:
    """Read runs from files/stems and folders (every ``*.csv``, any case, in a folder, sorted by
    name). Raises :class:`MeasurementFormatError` on the first bad run, or if nothing is found."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    runs: list[MeasuredRun] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() == ".csv" and f.is_file())
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
        if path.stat().st_size > MAX_JSON_BYTES:
            raise MeasurementFormatError(f"{path}: {path.stat().st_size:,} bytes; a run's JSON "
                                         f"holds its metadata only (at most {MAX_JSON_BYTES:,})")
        meta = json.loads(path.read_text(encoding="utf-8-sig"), object_pairs_hook=_no_duplicates,
                          parse_constant=lambda c: _raise(path, f"non-JSON constant {c}"))
    except json.JSONDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not valid JSON: {exc}") from None
    except UnicodeDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not UTF-8 text: {exc}") from None
    except RecursionError:
        raise MeasurementFormatError(f"{path}: not valid JSON: nested too deeply") from None
    except OSError as exc:
        raise MeasurementFormatError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    _refuse_duplicates(path, meta)
    if not isinstance(meta, dict):
        raise MeasurementFormatError(f"{path}: the top level must be a JSON object")
    fmt = meta.get("format")
    if fmt != FORMAT:
        raise MeasurementFormatError(f"{path}: key 'format' = {fmt!r}; expected {FORMAT!r}")
    for key in meta:
        near = None if key in TOP_KEYS else _near_miss(key, TOP_KEYS)
        if near:
            raise MeasurementFormatError(
                f"{path}: key {key!r} is not a key of {FORMAT} (did you mean {near!r}?); unknown "
                f"keys are ignored, so a misspelt one would be lost (rename it if it is a note)")
    if "supply_pressure_gauge_pa" not in meta:
        raise MeasurementFormatError(f"{path}: key 'supply_pressure_gauge_pa' is missing")
    for key in TOP_KEYS:
        if key in meta and key in PLAUSIBLE:
            _check_plausible(path, key, meta[key])
    if "description" in meta and not isinstance(meta["description"], str):
        raise MeasurementFormatError(f"{path}: key 'description' must be a string")
    rig = meta.get("rig")
    _check_section(path, "rig", rig, _RIG_KEYS + ("friction",))
    for key, choices in TEXT_KEYS.items():
        where = rig if key.startswith("rig.") else meta
        name = key.removeprefix("rig.")
        if isinstance(where, Mapping) and name in where and where[name] not in choices:
            raise MeasurementFormatError(f"{path}: key {key!r} = {where[name]!r:.60}; expected "
                                         f"one of {list(choices)}")
    if rig is not None:
        _check_section(path, "rig.friction", rig.get("friction"), _FRICTION_KEYS)
    return meta


class _Duplicated(dict):
    """A JSON object in which a key appears more than once (``dups``: key -> every value)."""

    dups: dict[str, list[Any]]


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook``: a plain dict, or a :class:`_Duplicated` one that records every
    value of a repeated key (``json`` itself keeps the last one silently)."""
    out = dict(pairs)
    if len(out) == len(pairs):
        return out
    dup = _Duplicated(out)
    dup.dups = {}
    for k, v in pairs:
        dup.dups.setdefault(k, []).append(v)
    dup.dups = {k: vs for k, vs in dup.dups.items() if len(vs) > 1}
    return dup


def _refuse_duplicates(path: Path, meta: Any) -> None:
    """Refuse the first object (in document order) with a repeated key, naming its path."""
    stack: list[tuple[str, Any]] = [("", meta)]
    while stack:
        where, o = stack.pop()
        if isinstance(o, _Duplicated):
            key, values = next(iter(o.dups.items()))
            name = f"{where}.{key}" if where else key
            shown = ", ".join(f"{v!r:.40}" for v in values)
            raise MeasurementFormatError(
                f"{path}: key {name!r} appears {len(values)} times (values {shown}); a JSON reader "
                f"keeps only the last one silently, so which one is meant is unclear: remove "
                f"the duplicate (a copied line?)")
        if isinstance(o, dict):
            stack += [(f"{where}.{k}" if where else str(k), v) for k, v in reversed(list(o.items()))]
        elif isinstance(o, list):
            stack += [(f"{where}[{i}]", v) for i, v in reversed(list(enumerate(o)))]


def _check_moving_mass(where: Path | str, meta: Mapping[str, Any], base: RigParams | None) -> None:
    """The moving mass ``load_mass_kg + rig.moving_mass_extra_kg`` must be > 0 (the plant
    divides by it); a key the JSON does not give takes ``base`` (default: the project's rig)."""
    base = base or RigParams()
    rig = meta.get("rig") if isinstance(meta.get("rig"), Mapping) else {}
    given = []
    try:
        if "load_mass_kg" in meta:
            load = float(meta["load_mass_kg"])
            given.append(f"'load_mass_kg' = {meta['load_mass_kg']!r}")
        else:
            load = float(base.load_mass_kg)
            given.append(f"'load_mass_kg' absent (the default rig's {load:g} kg)")
        if "moving_mass_extra_kg" in rig:
            extra = float(rig["moving_mass_extra_kg"])
            given.append(f"'rig.moving_mass_extra_kg' = {rig['moving_mass_extra_kg']!r}")
        else:
            extra = float(base.cylinder.moving_mass_extra_kg)
            given.append(f"'rig.moving_mass_extra_kg' absent (the default rig's {extra:g} kg)")
    except (TypeError, ValueError, OverflowError):
        return  # not numbers: refused by the plausibility checks or by RigParams
    if not load + extra > 0.0:
        raise MeasurementFormatError(
            f"{where}: key {given[0]} and key {given[1]}: the moving mass load_mass_kg + "
            f"rig.moving_mass_extra_kg = {load + extra:g} kg must be > 0 (the piston, rods and "
            f"trolley always move with the payload); give 'rig.moving_mass_extra_kg' (the "
            f"default rig's is {RigParams().cylinder.moving_mass_extra_kg:g} kg)")


def _near_miss(key: str, known: Sequence[str]) -> str | None:
    """The known key that the unknown ``key`` looks like a misspelling of, or ``None``. A key
    extending a known one (``description_long``) is deliberate, not a near miss."""
    k = key.strip().lower()
    if any(k.startswith(n + "_") for n in known):
        return None
    score = {n: difflib.SequenceMatcher(None, k, n).ratio() for n in known}
    best = max(score, key=score.__getitem__)
    return best if score[best] >= NEAR_MISS_RATIO else None


def _check_section(path: Path, name: str, section: Any, keys: Sequence[str]) -> None:
    """An optional object of known keys (an unknown one is a typo) with plausible numbers."""
    if section is None:
        return
    if not isinstance(section, dict):
        raise MeasurementFormatError(f"{path}: key {name!r} must be an object (or absent)")
    for key, value in section.items():
        if key not in keys:
            raise MeasurementFormatError(
                f"{path}: key '{name}.{key}' is not a {name} key{did_you_mean(key, keys)}; "
                f"known: {', '.join(keys)}")
        if key != "friction" and f"{name}.{key}" not in TEXT_KEYS:
            _check_plausible(path, f"{name}.{key}", value)


def _raise(path: Path, msg: str):
    raise MeasurementFormatError(f"{path}: {msg}")


def _check_plausible(path: Path, key: str, value: Any) -> None:
    """``value`` of JSON key ``key`` must be a finite number in its :data:`PLAUSIBLE` range."""
    bad = isinstance(value, bool) or not isinstance(value, numbers.Real)
    try:
        v = math.nan if bad else float(value)
    except OverflowError:  # an integer beyond float range
        v = math.inf
    if not math.isfinite(v):
        raise MeasurementFormatError(f"{path}: key {key!r} = {value!r:.60} must be a finite number")
    spec = PLAUSIBLE[key]
    if not spec.ok(v):
        raise MeasurementFormatError(f"{path}: key {key!r} = {value!r}: {spec.problem(v)}")


def _rig_from_meta(path: Path, meta: Mapping[str, Any], base: RigParams | None) -> RigParams:
    try:
        return RigParams.from_measurement(meta, base)
    except (ValueError, TypeError) as exc:
        raise MeasurementFormatError(f"{path}: the rig it describes is invalid: {exc}") from None


def _read_csv(path: Path, json_path: Path, stroke_m: float, rate_hz: float | None,
              ambient_pa: float):
    """Stream the CSV in chunks of :data:`CSV_CHUNK_ROWS` rows; validate; return the columns."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            reader = csv.reader(fh)
            try:
                cols, extra = _parse_csv(path, reader)
            except csv.Error as exc:
                raise MeasurementFormatError(f"{path}: line {reader.line_num}: not CSV: {exc}") from None
    except UnicodeDecodeError as exc:
        raise MeasurementFormatError(f"{path}: not UTF-8 text: {exc}") from None
    except OSError as exc:
        raise MeasurementFormatError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    _check_columns(path, json_path, cols, stroke_m, rate_hz, ambient_pa)
    return {c: cols.get(c) for c in REQUIRED_COLUMNS + OPTIONAL_COLUMNS}, extra


def _blank(row: Sequence[str]) -> bool:
    return not any(c.strip() for c in row)


def _parse_csv(path: Path, reader) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    first = next(reader, None)
    if first is None or _blank(first):
        rest = next((k for k, row in enumerate(reader) if not _blank(row)), None)
        if rest is None:
            raise MeasurementFormatError(f"{path}: empty file (expected a header row)")
        raise MeasurementFormatError(f"{path}: line 1 (header) is blank")
    header = [h.strip() for h in first]
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
    known = set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS)
    parts: dict[str, list] = {h: [] for h in header}
    n = 0  # data rows accepted
    blank_at: int | None = None  # line of the first of the trailing blank rows seen so far
    while True:
        block = list(itertools.islice(reader, CSV_CHUNK_ROWS))
        if not block:
            break
        good, blank_at = _good_rows(path, block, len(header), n, blank_at)
        if good:
            for h, cells in zip(header, zip(*good)):
                parts[h].append(_numeric(path, h, cells, n + 2) if h in known else cells)
            n += len(good)
    if n < 2:
        raise MeasurementFormatError(f"{path}: needs at least 2 samples, has {n}")
    # column by column, dropping each one's chunks: peak memory ~ the arrays + one column
    cols = {h: np.concatenate(parts.pop(h)) for h in header if h in known}
    extra = {h: _extra_column([c for cells in parts.pop(h) for c in cells]) for h in list(parts)}
    return cols, extra


def _good_rows(path: Path, block: list[list[str]], width: int, n: int,
               blank_at: int | None) -> tuple[list[list[str]], int | None]:
    """The rows of ``block`` (its first data line is ``n + 2``) before any blank row, and the
    line of the first blank row (trailing blank rows are dropped). Refuses a row of the wrong
    width and data after a blank row."""
    k = 0
    if blank_at is None:
        bad = [k for k, row in enumerate(block) if len(row) != width]
        if not bad:
            return block, None
        k = bad[0]
        if not _blank(block[k]):
            raise MeasurementFormatError(
                f"{path}: line {n + k + 2}: {len(block[k])} fields, the header has {width}")
        blank_at = n + k + 2
    if any(not _blank(row) for row in block[k:]):
        raise MeasurementFormatError(
            f"{path}: line {blank_at}: blank line inside the data (0 fields, the header has {width})")
    return block[:k], blank_at


def _numeric(path: Path, name: str, cells: Sequence[str], first_line: int) -> np.ndarray:
    """Cells of a known column as floats; refuses text and NaN/inf naming the line."""
    try:
        out = np.fromiter(map(float, cells), float, count=len(cells))
    except ValueError:
        for k, c in enumerate(cells):
            try:
                float(c)
            except ValueError:
                raise MeasurementFormatError(
                    f"{path}: line {first_line + k}, column {name!r}: {c.strip()!r:.60} is not a number") from None
        raise
    bad = np.flatnonzero(~np.isfinite(out))
    if bad.size:
        k = int(bad[0])
        raise MeasurementFormatError(
            f"{path}: line {first_line + k}, column {name!r}: {cells[k].strip()!r:.60} is not finite (NaN/inf)")
    return out


def _extra_column(cells: list[str]) -> np.ndarray:
    cells = [c.strip() for c in cells]
    try:
        return np.array([float(c) for c in cells])
    except ValueError:
        return np.array(cells, dtype=object)


def _first_bad(path: Path, name: str, values: np.ndarray, bad: np.ndarray, what: str,
               first_sample: int = 0) -> None:
    """Refuse at the first ``bad`` value; ``values[k]`` is sample ``first_sample + k``."""
    idx = np.flatnonzero(bad)
    if idx.size:
        k = int(idx[0])
        more = f" ({idx.size} such rows)" if idx.size > 1 else ""
        raise MeasurementFormatError(
            f"{path}: line {k + first_sample + 2}, column {name!r}: {float(values[k])!r} {what}{more}")


def _check_columns(path: Path, json_path: Path, cols: dict[str, np.ndarray], stroke_m: float,
                   rate_hz: float | None, ambient_pa: float) -> None:
    with np.errstate(over="ignore", invalid="ignore"):
        _check_time(path, json_path, cols["t"], rate_hz)
    v = cols["valve"]
    _first_bad(path, "valve", v, (v != 0.0) & (v != 1.0), "is not a valve command (0 or 1)")
    t = cols["t"]
    step = float((t[-1] - t[0]) / (t.size - 1))
    early = np.flatnonzero((v == 1.0) & (t < -SAMPLING_TOLERANCE * step))
    if early.size:
        k = int(early[0])
        raise MeasurementFormatError(
            f"{path}: line {k + 2}, column 'valve': 1 (supply connected) at t = {t[k]:.6g} s, "
            f"before the extend command; t is the time since the extend command, so the valve "
            f"cannot be open at t < 0 ({early.size} such rows): t offset by a pre-trigger or "
            f"clock? (shift t so that the extend command, the first valve = 1, is at t = 0)")
    lo, hi = PRESSURE_RANGE_PA
    p_min = GAUGE_FRACTION * ambient_pa
    for name in PRESSURE_COLUMNS:
        if name in cols:
            p = cols[name]
            _first_bad(path, name, p, (p < lo) | (p > hi),
                       f"is outside [{lo:g}, {hi:g}] Pa absolute (bar or gauge by mistake?)")
            _first_bad(path, name, p, p < p_min,
                       f"Pa is below {GAUGE_FRACTION:g} x the ambient pressure ({ambient_pa:g} Pa "
                       f"absolute): gauge instead of absolute?")
    tol = POSITION_TOLERANCE * stroke_m
    x = cols["x"]
    _first_bad(path, "x", x, (x < -tol) | (x > stroke_m + tol),
               f"is outside the stroke [0, {stroke_m:g}] m (+-{tol:.3g} m; mm by mistake?)")
    if "T_drive" in cols:
        lo_t, hi_t = TEMPERATURE_RANGE_K
        T = cols["T_drive"]
        _first_bad(path, "T_drive", T, (T < lo_t) | (T > hi_t),
                   f"is outside [{lo_t:g}, {hi_t:g}] K (°C by mistake?)")


def _check_time(path: Path, json_path: Path, t: np.ndarray, rate_hz: float | None) -> None:
    """Strictly increasing, uniformly sampled, at ``sample_rate_hz`` if given, at least 20 Hz."""
    dt = np.diff(t)
    _first_bad(path, "t", t[1:], ~(dt > 0.0), "is not after the previous time (t must increase strictly)",
               first_sample=1)
    since = ("t must be the time since the extend command (t = 0); epoch time or a clock "
             "offset? (subtract the time of the extend command from t)")
    if not abs(t[0]) <= FIRST_SAMPLE_MAX_S:
        raise MeasurementFormatError(
            f"{path}: line 2, column 't': the first sample is at t = {t[0]:.10g} s, more than "
            f"{FIRST_SAMPLE_MAX_S:g} s from the extend command; {since}")
    if not t[-1] > 0.0:
        raise MeasurementFormatError(
            f"{path}: line {t.size + 1}, column 't': the last sample is at t = {t[-1]:.6g} s, "
            f"so the whole run lies before the extend command (t = 0); {since}")
    step = float(np.median(dt))
    _first_bad(path, "t", t[1:], np.abs(dt - step) > SAMPLING_TOLERANCE * step,
               f"breaks the uniform sampling (step {step:.6g} s, tolerance "
               f"{SAMPLING_TOLERANCE:.0%})", first_sample=1)
    ms = f"; t in ms by mistake? ({step:.6g} ms = {step * 1e-3:.6g} s)"
    if rate_hz is not None and not abs(1.0 / step - rate_hz) <= SAMPLING_TOLERANCE * rate_hz:
        in_ms = abs(1e3 / step - rate_hz) <= SAMPLING_TOLERANCE * rate_hz
        raise MeasurementFormatError(
            f"{path}: column 't' is sampled at {1.0 / step:.6g} Hz but {json_path} key "
            f"'sample_rate_hz' says {rate_hz:.6g} Hz{ms if in_ms else ''}")
    if not step <= MAX_SAMPLE_STEP_S:
        raise MeasurementFormatError(
            f"{path}: lines 2-3, column 't': sampling step {step:.6g} s ({1.0 / step:.3g} Hz) is "
            f"coarser than {MAX_SAMPLE_STEP_S:g} s ({1.0 / MAX_SAMPLE_STEP_S:g} Hz) and cannot "
            f"resolve a stroke{ms}")


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------
def write_run(run: MeasuredRun, path: str | Path) -> Path:
    """Write ``run`` as ``PATH.csv`` + ``PATH.json`` (``PATH`` a stem; a .csv/.json suffix is
    dropped). Floats are written with ``repr`` so that reading gives the same numbers back.
    Returns the stem. A block-averaged run (``run.block > 1``) is refused: its ``valve``
    column is a fraction, not a command."""
    if run.block != 1:
        raise ValueError(f"run {run.name!r} is block-averaged (block = {run.block}); write the "
                         f"run as measured")
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
    meta = dict(run.meta)
    meta.setdefault("format", FORMAT)
    try:  # the JSON text first: a run whose metadata cannot be written leaves no file
        text = json.dumps(meta, indent=2, allow_nan=False, default=_json_number) + "\n"
    except (TypeError, ValueError) as exc:
        raise ValueError(f"run {run.name!r}: its metadata cannot be written as JSON: {exc}"
                         ) from None
    from .outputs import atomic_write_text

    # each file whole (a temporary file renamed); the JSON last, so a new JSON never stands
    # beside an old CSV (a crash between the two renames leaves the new CSV with the old JSON)
    atomic_write_text(_with_ext(stem, ".csv"), buf.getvalue())
    atomic_write_text(_with_ext(stem, ".json"), text)
    return stem


def _json_number(v: Any) -> Any:
    """A numpy scalar or array in the metadata (a seed, a noise level) as a JSON value."""
    if isinstance(v, (np.generic, np.ndarray)):
        return v.tolist()
    raise TypeError(f"Object of type {type(v).__name__} is not JSON serializable")


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
    noisy = sorted(set(REQUIRED_COLUMNS) - {"t", "valve"}) + list(OPTIONAL_COLUMNS)
    unknown = sorted(set(sd) - set(noisy))
    if unknown:
        raise ValueError(f"noise given for column(s) {unknown}: only measured channels carry "
                         f"it ({', '.join(noisy)}); the time and the valve command are exact")
    for c, s in sd.items():
        if isinstance(s, bool) or not (isinstance(s, numbers.Real) and math.isfinite(s)
                                       and s >= 0):
            raise ValueError(f"noise[{c!r}] = {s!r} must be a standard deviation >= 0 "
                             f"(in the column's unit)")
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
    # the command in force at each sample (acts from its time on; of two at one time, the last,
    # as the plant takes them: check_schedule keeps their order)
    for ts, v in sorted(schedule, key=lambda c: c[0]):
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
        **{k: getattr(params, k) for k, default in (("stroke_direction", "extend"),
                                                    ("external_force_n", 0.0))
           if getattr(params, k) != default},
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
    kw = {"t_end": t_end, "sample_rate_hz": sample_rate_hz, "noise": noise, "known": known}
    return [
        simulate_run(params, [(0.0, 1)], seed=seed, name=f"{prefix}conventional",
                     description="conventional", **kw),
        simulate_run(params, [(0.0, 1)], cut_on_arrival=True, seed=seed + 1,
                     name=f"{prefix}end_stroke_cutoff", description="end_stroke_cutoff", **kw),
        simulate_run(params, [(0.0, 1), (t_cut, 0)], seed=seed + 2, name=f"{prefix}early_cutoff",
                     description="early_cutoff", **kw),
    ]
