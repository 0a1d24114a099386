"""Fuzz test of the measured-run reader: random and mutated CSV and JSON contents either give a
valid :class:`MeasuredRun` or a :class:`MeasurementFormatError`, never another exception. A run
that is read obeys the format's rules: ``t`` is the time since the extend command (first sample
near 0, the valve never open before it), the moving mass is positive, no JSON key is repeated."""
from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pneugym import thesis_rig
from pneugym.data import (
    FIRST_SAMPLE_MAX_S,
    REQUIRED_COLUMNS,
    MeasuredRun,
    MeasurementFormatError,
    read_run,
    simulate_run,
    write_run,
)

FUZZ = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _base_files() -> tuple[bytes, bytes]:
    with tempfile.TemporaryDirectory() as d:
        run = simulate_run(thesis_rig(2.5), t_end=0.03, noise="default", seed=1,
                           optional=("p_supply", "T_drive"))
        stem = write_run(run, Path(d) / "r")
        return stem.with_suffix(".csv").read_bytes(), stem.with_suffix(".json").read_bytes()


CSV0, JSON0 = _base_files()

#: values at the edges: huge, tiny, an int beyond float range, typical unit mistakes
EDGES = [0, 1, -1, 1e308, -1e308, 5e-324, 101325, 2.5, 180, 1e400, 10**400, -10**400]
edge = st.sampled_from(EDGES)
numbers = st.one_of(edge, st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**30, 10**30))
cells = st.one_of(numbers.map(repr), st.text(max_size=6),
                  st.sampled_from(["", " ", "nan", "NaN", "inf", "-inf", "1e999", "0x10", "1_0",
                                   '"1"', "\x00", "1;2", "\ufeff1"]))
finite = numbers.filter(lambda v: not (isinstance(v, float) and not math.isfinite(v)))
json_values = st.recursive(
    st.none() | st.booleans() | finite | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8)
json_keys = st.sampled_from(["format", "supply_pressure_gauge_pa", "load_mass_kg", "ambient_pressure_pa",
                             "ambient_temperature_k", "sample_rate_hz", "rig", "description", "load_mass",
                             "extra", "rig.bore_m", "rig.stroke_m", "rig.friction", "rig.friction.coulomb_n",
                             "rig.bore", "rig.valve_delay_s", "rig.moving_mass_extra_kg"])
#: shifts of the time column: epoch time, clock offsets, a pre-trigger
T_SHIFTS = [1.7e9, 1.7e12, 100.0, 61.0, 59.0, 0.5, 1e-3, -1e-3, -0.02, -0.5, -59.0, -61.0, -1e9]


@st.composite
def csv_bytes(draw) -> bytes:
    lines = CSV0.decode().splitlines()
    for _ in range(draw(st.integers(0, 4))):
        op = draw(st.sampled_from(["cell", "drop_line", "dup_line", "add_col", "drop_col", "blank",
                                   "swap", "shift_t", "close_valve"]))
        i = draw(st.integers(0, len(lines) - 1)) if lines else 0
        if not lines:
            break
        f = lines[i].split(",")
        j = draw(st.integers(0, len(f) - 1))
        if op == "cell":
            f[j] = draw(cells)
            lines[i] = ",".join(f)
        elif op == "drop_line":
            del lines[i]
        elif op == "dup_line":
            lines.insert(i, lines[i])
        elif op == "add_col":
            lines = [ln + "," + draw(cells) for ln in lines]
        elif op == "drop_col":
            lines = [",".join(c for k, c in enumerate(ln.split(",")) if k != j) for ln in lines]
        elif op == "blank":
            lines.insert(i, "")
        elif op == "swap" and i + 1 < len(lines):
            lines[i], lines[i + 1] = lines[i + 1], lines[i]
        elif op == "shift_t":  # epoch time, a clock offset, a pre-trigger
            dt = draw(st.sampled_from(T_SHIFTS))
            lines = lines[:1] + [_shift_t(ln, dt) for ln in lines[1:]]
        elif op == "close_valve":  # the valve closed before t = 0 (a pre-trigger done right)
            lines = lines[:1] + [_close_before_0(ln) for ln in lines[1:]]
    data = ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")
    return _byte_ops(draw, data)


def _shift_t(line: str, dt: float) -> str:
    """``line`` with ``dt`` added to its first cell (``t`` unless a column was dropped)."""
    f = line.split(",")
    try:
        f[0] = repr(float(f[0]) + dt)
    except ValueError:
        pass
    return ",".join(f)


def _close_before_0(line: str) -> str:
    """``line`` with its second cell (``valve``) 0 if its first (``t``) is negative."""
    f = line.split(",")
    try:
        if len(f) > 1 and float(f[0]) < 0:
            f[1] = "0"
    except ValueError:
        pass
    return ",".join(f)


def _byte_ops(draw, data: bytes) -> bytes:
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data
    if draw(st.integers(0, 3)) == 0:
        data = data[:draw(st.integers(0, len(data)))]  # truncated
    if draw(st.integers(0, 4)) == 0:
        k = draw(st.integers(0, len(data)))
        data = data[:k] + draw(st.binary(max_size=6)) + data[k:]
    return data


@st.composite
def json_bytes(draw) -> bytes:
    meta = json.loads(JSON0)
    for _ in range(draw(st.integers(0, 3))):
        *outer, last = draw(json_keys).split(".")
        d = meta
        for k in outer:
            if not isinstance(d.get(k), dict):
                d[k] = {}
            d = d[k]
        if draw(st.booleans()):
            d[last] = draw(st.one_of(finite, json_values))
        else:
            d.pop(last, None)
    text = json.dumps(meta) if draw(st.integers(0, 5)) else draw(st.text(max_size=40))
    if draw(st.integers(0, 5)) == 0 and text.startswith("{"):  # a repeated key
        key = draw(st.sampled_from(["format", "load_mass_kg", "supply_pressure_gauge_pa", "note"]))
        text = "{" + json.dumps(key) + ": " + json.dumps(draw(st.one_of(finite, json_values))) + ", " + text[1:]
    return _byte_ops(draw, text.encode("utf-8", "surrogatepass"))


def _check(csv_data: bytes, json_data: bytes) -> MeasuredRun | None:
    with tempfile.TemporaryDirectory() as d:
        stem = Path(d) / "fuzz"
        stem.with_suffix(".csv").write_bytes(csv_data)
        stem.with_suffix(".json").write_bytes(json_data)
        try:
            run = read_run(stem)
        except MeasurementFormatError as exc:
            assert str(exc).startswith(d), exc  # every refusal names the file
            return None
    n = len(run)
    assert n >= 2
    for c in REQUIRED_COLUMNS:
        a = getattr(run, c)
        assert a.shape == (n,) and a.dtype == float and np.isfinite(a).all()
    assert np.all(np.diff(run.t) > 0)
    assert set(np.unique(run.valve)) <= {0.0, 1.0}
    # t is the time since the extend command: no epoch time or clock offset, no open valve before it
    assert abs(run.t[0]) <= FIRST_SAMPLE_MAX_S and run.t[-1] > 0
    assert not np.any((run.valve == 1.0) & (run.t < -1e-9))
    rig = run.rig()  # the rig it describes is valid ...
    assert rig.moving_mass_kg > 0  # ... and has something to move
    pairs = json.loads(json_data.decode("utf-8-sig"), object_pairs_hook=lambda p: p)
    assert _no_repeated_keys(pairs)
    return run


def _no_repeated_keys(o) -> bool:
    """Whether no object in ``o`` (parsed with ``object_pairs_hook=list``) repeats a key."""
    stack = [o]
    while stack:
        o = stack.pop()
        if isinstance(o, list) and all(isinstance(p, tuple) and len(p) == 2 for p in o):
            keys = [k for k, _ in o]
            if len(keys) != len(set(keys)):
                return False
            stack += [v for _, v in o]
        elif isinstance(o, list):
            stack += o
    return True


def test_unmutated_files_read():
    assert _check(CSV0, JSON0) is not None


@FUZZ
@given(csv_bytes(), json_bytes())
def test_mutated_runs_are_read_or_refused(csv_data, json_data):
    _check(csv_data, json_data)


@FUZZ
@given(st.binary(max_size=200), st.binary(max_size=200))
def test_random_bytes_are_refused(csv_data, json_data):
    assert _check(csv_data, json_data) is None


@FUZZ
@given(st.lists(st.lists(cells, min_size=5, max_size=7), min_size=1, max_size=6))
def test_random_cells_under_a_valid_header(rows):
    text = "t,valve,x,p_drive,p_exhaust\n" + "\n".join(",".join(r) for r in rows) + "\n"
    _check(text.encode("utf-8", "surrogatepass"), JSON0)


@FUZZ
@given(st.lists(st.tuples(json_keys, st.one_of(edge, finite, finite.map(str), st.none(), st.booleans())),
                min_size=1, max_size=3))
def test_json_numbers_of_any_size_and_type(changes):
    meta = json.loads(JSON0)
    for key, value in changes:
        *outer, last = key.split(".")
        d = meta
        for k in outer:
            d = d.setdefault(k, {}) if isinstance(d.get(k, {}), dict) else {}
        d[last] = value
    _check(CSV0, json.dumps(meta).encode())


@pytest.mark.parametrize("json_text", ["[" * 100_000, '{"a": ' * 50_000, "1e400", '"\\ud800"'])
def test_pathological_json(json_text):
    assert _check(CSV0, json_text.encode()) is None
