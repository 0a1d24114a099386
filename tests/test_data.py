"""Measured runs (pneugym.data): round trip, strict validation with file/row/key in every
refusal, and the simulated export (noise, lag, sampling, valve column)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pneugym import Plant, thesis_rig
from pneugym.data import (
    FORMAT,
    MeasuredRun,
    MeasurementFormatError,
    read_run,
    read_runs,
    simulate_run,
    thesis_protocol,
    write_run,
)
from pneugym.discrepancy.residuals import replay


@pytest.fixture(scope="module")
def clean_run() -> MeasuredRun:
    """A short noise-free conventional run at 1 kHz with every optional column."""
    return simulate_run(thesis_rig(2.5), t_end=0.6, noise=None, name="clean",
                        optional=("p_supply", "mdot_supply", "T_drive"))


@pytest.fixture()
def run_files(tmp_path, clean_run) -> Path:
    return write_run(clean_run, tmp_path / "clean")


def _rewrite_csv(stem: Path, edit) -> None:
    p = stem.with_suffix(".csv")
    lines = p.read_text().splitlines()
    p.write_text("\n".join(edit(lines)) + "\n")


def _rewrite_json(stem: Path, edit) -> None:
    p = stem.with_suffix(".json")
    meta = json.loads(p.read_text())
    edit(meta)
    p.write_text(json.dumps(meta))


def _refused(stem: Path, *patterns: str) -> str:
    with pytest.raises(MeasurementFormatError) as e:
        read_run(stem)
    msg = str(e.value)
    for pat in patterns:
        assert re.search(pat, msg), f"{pat!r} not in {msg!r}"
    return msg


# -- round trip ----------------------------------------------------------------------------
def test_round_trip_is_exact(run_files, clean_run):
    back = read_run(run_files)
    assert back.name == "clean" and back.source == run_files
    assert set(back.columns) == set(clean_run.columns)
    for c, a in clean_run.columns.items():
        np.testing.assert_array_equal(back.columns[c], a, err_msg=c)
    assert back.meta["format"] == FORMAT
    assert back.meta["rig"] == json.loads(json.dumps(clean_run.meta["rig"]))


@pytest.mark.parametrize("suffix", ["", ".csv", ".json"])
def test_read_by_stem_csv_or_json(run_files, suffix):
    assert len(read_run(str(run_files) + suffix)) == 601


def test_read_folder_sorted_and_unique_names(tmp_path):
    for name in ("b", "a"):
        write_run(simulate_run(thesis_rig(2.5), t_end=0.05, noise=None, name=name), tmp_path / name)
    (tmp_path / "notes.json").write_text("{}")  # a JSON without a CSV in a folder is not a run
    runs = read_runs([tmp_path])
    assert [r.name for r in runs] == ["a", "b"]
    with pytest.raises(MeasurementFormatError, match="unique"):
        read_runs([tmp_path / "a", tmp_path / "a.csv"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(MeasurementFormatError, match="no run"):
        read_runs([tmp_path / "empty"])


def test_unknown_columns_and_top_level_keys_are_kept_and_ignored(run_files):
    _rewrite_csv(run_files, lambda ls: [ls[0] + ",operator,temp_note"]
                 + [l + ",42,ok" for l in ls[1:]])
    _rewrite_json(run_files, lambda m: m.update(lab="B12", operator="jo", description_long="x",
                                                format_version=2))
    run = read_run(run_files)
    assert np.all(run.extra["operator"] == 42.0) and run.extra["temp_note"][0] == "ok"
    assert run.meta["lab"] == "B12" and "simulation" in run.meta  # the simulator's key is kept
    assert run.rig().cylinder.bore_m == 0.125


# -- refusals: every message names the file and the row or key -------------------------------
def test_missing_json_or_csv(run_files):
    run_files.with_suffix(".json").unlink()
    _refused(run_files, re.escape(str(run_files.with_suffix(".json"))), "not found", "refused")
    run_files.with_suffix(".csv").unlink()
    _refused(run_files, re.escape(str(run_files.with_suffix(".csv"))), "not found")


def _set_cell(lines: list[str], k: int, column: str, value: str) -> list[str]:
    """Lines with the cell of line index ``k`` (0 = header) in ``column`` replaced."""
    i = lines[0].split(",").index(column)
    f = lines[k].split(",")
    f[i] = value
    return lines[:k] + [",".join(f)] + lines[k + 1:]


@pytest.mark.parametrize("edit, patterns", [
    (lambda ls: [ls[0].replace("p_exhaust", "p_exh")] + ls[1:], [r"line 1", r"missing required column.*p_exhaust"]),
    (lambda ls: [ls[0] + ",t"] + [l + ",0" for l in ls[1:]], [r"line 1", r"appear twice"]),
    (lambda ls: _set_cell(ls, 5, "x", "abc"), [r"line 6", r"column 'x'", r"not a number"]),
    (lambda ls: _set_cell(ls, 7, "p_drive", "nan"), [r"line 8", r"column 'p_drive'", r"not finite"]),
    (lambda ls: ls[:10] + [ls[10] + ",1"] + ls[11:], [r"line 11", r"fields"]),
    (lambda ls: ls[:20] + [ls[19]] + ls[21:], [r"line 21", r"column 't'", r"increase"]),
    (lambda ls: ls[:30] + ls[31:], [r"line 31", r"uniform sampling"]),
    (lambda ls: ls[:1], [r"at least 2 samples"]),
    (lambda ls: [], [r"empty file"]),
])
def test_csv_refusals(run_files, edit, patterns):
    _rewrite_csv(run_files, edit)
    _refused(run_files, re.escape(str(run_files.with_suffix(".csv"))), *patterns)


def _scale_column(name: str, factor: float, offset: float = 0.0):
    def edit(ls):
        i = ls[0].split(",").index(name)
        out = [ls[0]]
        for l in ls[1:]:
            f = l.split(",")
            f[i] = repr(float(f[i]) * factor + offset)
            out.append(",".join(f))
        return out
    return edit


@pytest.mark.parametrize("column, factor, offset, pattern", [
    ("p_exhaust", 1e-5, 0.0, r"p_exhaust.*bar or gauge"),  # bar instead of Pa
    ("p_drive", 1.0, -101325.0, r"line 2, column 'p_drive'.*bar or gauge"),  # gauge: 0 Pa at rest
    ("p_supply", 10.0, 0.0, r"p_supply.*2e\+06"),
    ("x", 1000.0, 0.0, r"column 'x'.*mm by mistake"),
    ("T_drive", 1.0, -273.15, r"T_drive.*°C"),
    ("valve", 0.5, 0.0, r"valve.*0 or 1"),
])
def test_value_refusals(run_files, column, factor, offset, pattern):
    _rewrite_csv(run_files, _scale_column(column, factor, offset))
    _refused(run_files, r"line \d+", pattern)


@pytest.mark.parametrize("edit, pattern", [
    (lambda m: m.pop("format"), r"key 'format'"),
    (lambda m: m.update(format="pneugym-measurement/2"), r"key 'format'.*pneugym-measurement/1"),
    (lambda m: m.pop("supply_pressure_gauge_pa"), r"supply_pressure_gauge_pa' is missing"),
    (lambda m: m.update(supply_pressure_gauge_pa=2.5), r"supply_pressure_gauge_pa.*bar given as Pa"),
    (lambda m: m.update(load_mass_kg="10"), r"load_mass_kg.*finite number"),
    (lambda m: m.update(ambient_temperature_k=20.0), r"ambient_temperature_k.*°C"),
    (lambda m: m.update(sample_rate_hz=500.0), r"sampled at 1000 Hz.*sample_rate_hz.*500"),
    (lambda m: m["rig"].update(bore_m=-0.1), r"rig\.bore_m"),
    (lambda m: m["rig"].update(friction=[1, 2]), r"rig\.friction. must be an object"),
    (lambda m: m["rig"]["friction"].update(coulomb_n=None), r"rig\.friction\.coulomb_n"),
    (lambda m: m["rig"].update(rod_m=0.2), r"rig it describes is invalid.*rod_m"),
    (lambda m: m.update(rig=5), r"key 'rig' must be an object"),
    (lambda m: m.update(description=3), r"description"),
])
def test_json_refusals(run_files, edit, pattern):
    _rewrite_json(run_files, edit)
    _refused(run_files, re.escape(str(run_files.with_suffix(".json"))), pattern)


def test_invalid_json_text(run_files):
    run_files.with_suffix(".json").write_text("{\"format\": ")
    _refused(run_files, "not valid JSON")
    run_files.with_suffix(".json").write_text("[1, 2]")
    _refused(run_files, "JSON object")
    run_files.with_suffix(".json").write_text('{"format": "pneugym-measurement/1", "supply_pressure_gauge_pa": NaN}')
    _refused(run_files, "NaN")


def test_partial_rig_takes_the_default(run_files):
    _rewrite_json(run_files, lambda m: m.update(rig={"stroke_m": 0.2}))
    rig = read_run(run_files).rig()
    assert rig.cylinder.stroke_m == 0.2
    assert rig.cylinder.bore_m == thesis_rig(2.5).cylinder.bore_m
    _rewrite_json(run_files, lambda m: m.pop("rig"))
    assert read_run(run_files).rig().line == thesis_rig(2.5).line


# -- simulated export --------------------------------------------------------------------------
def test_noise_is_seeded_and_at_the_requested_level():
    rig = thesis_rig(2.5)
    a = simulate_run(rig, t_end=1.0, noise="default", seed=7)
    b = simulate_run(rig, t_end=1.0, noise="default", seed=7)
    c = simulate_run(rig, t_end=1.0, noise="default", seed=8)
    clean = simulate_run(rig, t_end=1.0, noise=None)
    np.testing.assert_array_equal(a.p_drive, b.p_drive)
    assert not np.array_equal(a.p_drive, c.p_drive)
    assert np.std(a.p_drive - clean.p_drive) == pytest.approx(400.0, rel=0.1)
    assert np.std(a.x - clean.x) == pytest.approx(3e-5, rel=0.1)
    np.testing.assert_array_equal(a.t, clean.t)


def test_sampling_and_sensor_lag():
    rig = thesis_rig(2.5)
    r = simulate_run(rig, t_end=0.5, sample_rate_hz=500.0, sensor_lag_s=0.015, noise=None)
    assert r.sample_dt_s == pytest.approx(2e-3) and len(r) == 251
    assert r.meta["sample_rate_hz"] == 500.0
    lagged = Plant(rig.with_(effects={"sensor_lag_s": 0.015})).run(0.5, record_dt=2e-3)
    np.testing.assert_allclose(r.p_drive, lagged["p_drive_sensor"])
    assert np.max(np.abs(r.p_drive - lagged["p_drive"])) > 1e4  # the lag matters on the rise


def test_valve_column_and_cut_on_arrival_replay_exactly():
    rig = thesis_rig(2.5)
    r = simulate_run(rig, t_end=1.6, cut_on_arrival=True, noise=None)
    arrival = r.meta["simulation"]["arrival_time_s"]
    sched = r.schedule()
    assert sched[0] == (0.0, 1) and sched[1][1] == 0
    assert arrival <= sched[1][0] < arrival + 1e-3 + 1e-12  # the first sample at/after arrival
    sim = replay(r, rig)  # replaying the CSV's command reproduces the run exactly
    for c in ("x", "p_drive", "p_exhaust"):
        np.testing.assert_allclose(sim[c], getattr(r, c), rtol=0, atol=1e-9 * np.abs(getattr(r, c)).max())


def test_known_rig_is_what_the_json_states():
    truth = thesis_rig(2.5, friction={"coulomb_n": 150.0}, effects={"leak_drive_area_m2": 1e-7})
    known = thesis_rig(2.5)
    runs = thesis_protocol(truth, known, t_end=2.0)
    assert [r.description for r in runs] == ["conventional", "end_stroke_cutoff", "early_cutoff"]
    for r in runs:
        assert r.rig().with_(valve={"delay_s": None}) == known
        assert r.rig().valve_delay_s == known.valve_delay_s
        assert r.meta["simulation"]["params"]["effects"]["leak_drive_area_m2"] == 1e-7
    early = runs[2].schedule()
    assert len(early) == 2 and 0.3 < early[1][0] < runs[1].schedule()[1][0]


def test_bad_export_arguments():
    with pytest.raises(ValueError, match="sample_rate_hz"):
        simulate_run(thesis_rig(2.5), sample_rate_hz=0.0)
    with pytest.raises(ValueError, match="optional"):
        simulate_run(thesis_rig(2.5), optional=("p_port",))
    with pytest.raises(ValueError, match="noise"):
        simulate_run(thesis_rig(2.5), noise={"pressure": 1.0})
    for bad, match in (({"valve": 0.05}, "the time and the valve command are exact"),
                       ({"t": 1e-4}, "only measured channels"),
                       ({"x": -1e-5}, r"noise\['x'\] = -1e-05 must be a standard deviation"),
                       ({"p_drive": float("nan")}, "standard deviation"),
                       ({"p_drive": True}, "standard deviation")):
        with pytest.raises(ValueError, match=match):
            simulate_run(thesis_rig(2.5), t_end=0.1, noise=bad)


def test_write_run_writes_both_files_or_neither(tmp_path):
    """A run whose metadata cannot be JSON leaves no file (and not a new CSV beside an old
    JSON); numpy numbers in the metadata (a seed from np.arange) are written as numbers."""
    run = simulate_run(thesis_rig(2.5), t_end=0.2, noise="default", seed=np.int64(3))
    write_run(run, tmp_path / "a")
    assert read_run(tmp_path / "a").meta["simulation"]["seed"] == 3
    old = (tmp_path / "a.csv").read_text(), (tmp_path / "a.json").read_text()
    other = simulate_run(thesis_rig(5.0), t_end=0.2)
    other.meta["simulation"]["seed"] = float("nan")
    with pytest.raises(ValueError, match="'simulated': its metadata cannot be written as JSON"):
        write_run(other, tmp_path / "a")
    assert ((tmp_path / "a.csv").read_text(), (tmp_path / "a.json").read_text()) == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "a.json"]


def test_a_run_json_over_its_size_limit_is_refused(run_files, monkeypatch):
    import pneugym.data as data

    monkeypatch.setattr(data, "MAX_JSON_BYTES", 100)
    with pytest.raises(MeasurementFormatError, match="a run's JSON holds its metadata only"):
        read_run(run_files)


# -- plausibility of the JSON: the likely unit mistake is named -------------------------------------
@pytest.mark.parametrize("key, value, pattern", [
    ("stroke_m", 180, r"180 m is not a plausible stroke.*mm given as m\? \(0\.18 m = 180 mm\)"),
    ("bore_m", 125, r"plausible bore.*mm given as m\? \(0\.125 m"),
    ("rod_m", 32, r"rod diameter.*mm given as m"),
    ("line_length_m", 1200, r"line length.*mm given as m\? \(1\.2 m"),
    ("line_diameter_m", 5, r"line inner diameter.*mm given as m\? \(0\.005 m"),
    ("valve_area_m2", 19.6, r"valve orifice area.*mm² given as m²\? \(1\.96e-05 m²"),
    ("port_area_m2", 0.5, r"port orifice area.*cm² given as m²\? \(5e-05 m²"),
    ("exhaust_area_m2", 0.0, r"exhaust orifice area \(expected 1e-09 to"),
    ("dead_volume_m3", 50, r"dead volume.*cm³ given as m³\? \(5e-05 m³ = 50 cm³\)"),
    ("dead_volume_m3", 0.05, r"dead volume.*litres given as m³\? \(5e-05 m³"),
    ("cushion_length_m", 15, r"cushion length.*mm given as m\? \(0\.015 m"),
    ("cushion_factor_drive", 30, r"cushion area factor.*percent given as a fraction\? \(0\.3 = 30 %\)"),
    ("cushion_factor_exhaust", 0.0, r"expected 0 \(excluded\) to 1"),
    ("discharge_coefficient", 72, r"discharge coefficient.*percent given as a fraction\? \(0\.72"),
    ("valve_delay_s", 185, r"valve delay.*ms given as s\? \(0\.185 s = 185 ms\)"),
    ("moving_mass_extra_kg", 5000, r"moving mass.*expected 0 to 2000 kg"),
    ("friction.coulomb_n", -5, r"rig\.friction\.coulomb_n.*Coulomb friction \(expected 0 to"),
    ("friction.viscous_n_s_per_m", 1e7, r"viscous friction"),
])
def test_implausible_rig_values_name_the_unit_mistake(run_files, key, value, pattern):
    def edit(m):
        section = m["rig"]
        *outer, last = key.split(".")
        for k in outer:
            section = section[k]
        section[last] = value
    _rewrite_json(run_files, edit)
    msg = _refused(run_files, re.escape(str(run_files.with_suffix(".json"))),
                   re.escape(f"key 'rig.{key}' = {value!r}"), pattern)
    assert "rig it describes is invalid" not in msg  # refused here, before RigParams


@pytest.mark.parametrize("key, value, pattern", [
    ("supply_pressure_gauge_pa", 36.0, r"psi given as Pa"),
    ("supply_pressure_gauge_pa", 250.0, r"kPa given as Pa\? \(2\.5e\+05 Pa = 250 kPa\)"),
    ("supply_pressure_gauge_pa", 5e3, r"expected 10000 to"),  # RigParams refuses < 1e4 too
    ("ambient_pressure_pa", 1013.25, r"mbar given as Pa|hPa given as Pa"),
    ("sample_rate_hz", 0.0, r"sample rate"),
    pytest.param("load_mass_kg", 10**400, r"finite number", id="int-beyond-float"),
    ("load_mass_kg", None, r"finite number"),
])
def test_implausible_top_level_values(run_files, key, value, pattern):
    _rewrite_json(run_files, lambda m: m.update({key: value}))
    _refused(run_files, re.escape(str(run_files.with_suffix(".json"))), f"key '{key}'", pattern)


# -- key typos -------------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, pattern", [
    (lambda m: m["rig"].update(bore=0.1), r"key 'rig\.bore' is not a rig key \(did you mean 'bore_m'\?\)"),
    (lambda m: m["rig"].update(stroke_mm=180), r"'rig\.stroke_mm'.*did you mean 'stroke_m'"),
    (lambda m: m["rig"].update(colour="blue"), r"'rig\.colour' is not a rig key; known: bore_m"),
    (lambda m: m["rig"]["friction"].update(coulomb=100), r"'rig\.friction\.coulomb'.*did you mean 'coulomb_n'"),
    (lambda m: m.update(load_mass=10), r"key 'load_mass'.*did you mean 'load_mass_kg'"),
    (lambda m: m.update(supply_pressure_gauge=2e5), r"did you mean 'supply_pressure_gauge_pa'"),
    (lambda m: m.update(supply_pressure_bar=2.5), r"did you mean 'supply_pressure_gauge_pa'"),
    (lambda m: m.update(Sample_Rate=1000), r"did you mean 'sample_rate_hz'"),
])
def test_key_typos_are_refused_with_the_nearest_name(run_files, edit, pattern):
    _rewrite_json(run_files, edit)
    _refused(run_files, re.escape(str(run_files.with_suffix(".json"))), pattern)


# -- time in ms, gauge instead of absolute ---------------------------------------------------------
def test_time_in_ms_is_refused(run_files):
    _rewrite_csv(run_files, _scale_column("t", 1000.0))
    _rewrite_json(run_files, lambda m: m.pop("sample_rate_hz"))
    _refused(run_files, re.escape(str(run_files.with_suffix(".csv"))), r"column 't'",
             r"step 1 s .*cannot resolve a stroke; t in ms by mistake\?")
    _rewrite_json(run_files, lambda m: m.update(sample_rate_hz=1000))  # cross-checked: same hint
    _refused(run_files, r"sampled at 1 Hz.*says 1000 Hz; t in ms by mistake\?")


def test_slow_sampling_is_refused(tmp_path):
    stem = write_run(simulate_run(thesis_rig(2.5), t_end=2.0, sample_rate_hz=10.0, noise=None),
                     tmp_path / "slow")
    _refused(stem, r"step 0\.1 s \(10 Hz\) is coarser than 0\.05 s")
    stem = write_run(simulate_run(thesis_rig(2.5), t_end=0.5, sample_rate_hz=25.0, noise=None),
                     tmp_path / "ok")
    assert len(read_run(stem)) == 13


def test_gauge_pressure_is_refused(run_files, clean_run):
    # a gauge transducer with a +3 kPa offset: every value passes the 1 kPa absolute bound ...
    assert (clean_run.p_drive - 101325.0 + 3000.0).min() > 1e3
    _rewrite_csv(run_files, _scale_column("p_drive", 1.0, -101325.0 + 3000.0))
    _refused(run_files, r"line 2, column 'p_drive'",
             r"below 0\.5 x the ambient pressure \(101325 Pa absolute\): gauge instead of absolute\?")
    # ... and the threshold follows the run's own ambient pressure: 41.3 kPa at rest is fine
    # at 60 kPa ambient (a rig high in the mountains would be ~70 kPa)
    _rewrite_csv(run_files, _scale_column("p_drive", 1.0, 101325.0 - 3000.0 - 60000.0))
    _refused(run_files, r"column 'p_drive'.*gauge instead of absolute")
    _rewrite_json(run_files, lambda m: m.update(ambient_pressure_pa=60000.0))
    assert len(read_run(run_files)) == 601


# -- files: case of the extension, BOM, dots in names, streamed reading ---------------------------
def test_extensions_are_case_insensitive(tmp_path, run_files):
    csv_p, json_p = run_files.with_suffix(".csv"), run_files.with_suffix(".json")
    csv_p.rename(tmp_path / "clean.CSV")
    json_p.rename(tmp_path / "clean.Json")
    for p in (run_files, tmp_path / "clean.CSV", tmp_path / "clean.Json", tmp_path / "clean.csv"):
        assert len(read_run(p)) == 601
    assert [r.name for r in read_runs([tmp_path])] == ["clean"]
    (tmp_path / "clean.JSON").write_text("{}")  # two JSONs differing in case only
    _refused(run_files, "ambiguous", "clean.JSON", "clean.Json")
    (tmp_path / "clean.json").write_text((tmp_path / "clean.Json").read_text())
    assert len(read_run(run_files)) == 601  # the exact name wins


def test_utf8_bom_is_accepted(run_files, clean_run):
    for ext in (".csv", ".json"):
        p = run_files.with_suffix(ext)
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())  # Excel's "CSV UTF-8"
    back = read_run(run_files)
    np.testing.assert_array_equal(back.t, clean_run.t)
    run_files.with_suffix(".csv").write_bytes(b"\xff\xfe" + b"t,valve")  # UTF-16: refused cleanly
    _refused(run_files, "not UTF-8")


def test_dotted_run_names(tmp_path, clean_run):
    stem = write_run(clean_run, tmp_path / "run.v2")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["run.v2.csv", "run.v2.json"]
    assert read_run(tmp_path / "run.v2.csv").name == "run.v2" and read_run(stem).name == "run.v2"


def test_streamed_reading_across_chunks(run_files, clean_run, monkeypatch):
    from pneugym import data
    monkeypatch.setattr(data, "CSV_CHUNK_ROWS", 7)  # 601 samples: 86 chunks, odd boundaries
    back = read_run(run_files)
    for c, a in clean_run.columns.items():
        np.testing.assert_array_equal(back.columns[c], a, err_msg=c)
    _rewrite_csv(run_files, lambda ls: ls + ["", " ", ""])  # trailing blank lines: dropped
    assert len(read_run(run_files)) == 601
    _rewrite_csv(run_files, lambda ls: ls[:300] + [""] + ls[300:])  # a blank line inside the data
    _refused(run_files, r"line 301: blank line inside the data")
    _rewrite_csv(run_files, lambda ls: [l for l in ls if l.strip()])
    _rewrite_csv(run_files, lambda ls: _set_cell(ls, 500, "p_exhaust", "1,0"))  # 1 field too many
    _refused(run_files, r"line 501: 7 fields, the header has 6|line 501: \d+ fields")


# -- t is the time since the extend command; the moving mass; duplicate JSON keys -----------------
@pytest.mark.parametrize("offset, pattern", [
    (1.7e9, r"line 2, column 't': the first sample is at t = 1700000000 s, more than 60 s"),
    (100.0, r"line 2, column 't': the first sample is at t = 100 s"),
    (-61.0, r"line 2, column 't': the first sample is at t = -61 s"),
    (-5.0, r"line 602, column 't': the last sample is at t = -4\.4 s, so the whole run lies before"),
])
def test_time_not_since_the_extend_command_is_refused(run_files, offset, pattern):
    _rewrite_csv(run_files, _scale_column("t", 1.0, offset))
    _rewrite_json(run_files, lambda m: m.pop("sample_rate_hz"))  # epoch floats lose the rate
    _refused(run_files, re.escape(str(run_files.with_suffix(".csv"))), pattern,
             re.escape("t must be the time since the extend command (t = 0); epoch time or a "
                       "clock offset?"))


def test_valve_open_before_the_extend_command_is_refused(run_files):
    _rewrite_csv(run_files, _scale_column("t", 1.0, -0.5))  # the clock started 0.5 s late
    _refused(run_files, re.escape(str(run_files.with_suffix(".csv"))),
             r"line 2, column 'valve': 1 \(supply connected\) at t = -0\.5 s, before the extend "
             r"command", r"\(500 such rows\)", r"t offset by a pre-trigger or clock\?")


def test_pre_trigger_samples_with_the_valve_closed_are_read(run_files, clean_run):
    def pre(ls):
        first = ls[1].split(",")
        rows = []
        for k in range(5, 0, -1):  # 5 samples before the extend command, valve closed
            f = list(first)
            f[0], f[1] = repr(-k * 1e-3), "0"
            rows.append(",".join(f))
        return ls[:1] + rows + ls[1:]
    _rewrite_csv(run_files, pre)
    run = read_run(run_files)
    assert len(run) == len(clean_run) + 5 and run.t[0] == pytest.approx(-5e-3)
    assert run.schedule() == [(0.0, 0), (0.0, 1)]


@pytest.mark.parametrize("text, key, values", [
    ('"load_mass_kg": 10.0, "load_mass_kg": 1000', "load_mass_kg", "10.0, 1000"),
    ('"rig": {"bore_m": 0.125, "friction": {"static_n": 359, "static_n": 400}}',
     "rig.friction.static_n", "359, 400"),
])
def test_duplicate_json_keys_are_refused(run_files, text, key, values):
    p = run_files.with_suffix(".json")
    p.write_text('{"format": "pneugym-measurement/1", "supply_pressure_gauge_pa": 250000, '
                 + text + "}")
    _refused(run_files, re.escape(str(p)), re.escape(f"key '{key}' appears 2 times (values {values})"),
             "keeps only the last one silently")


def test_zero_moving_mass_is_refused(run_files, clean_run):
    _rewrite_json(run_files, lambda m: (m.update(load_mass_kg=0), m["rig"].update(moving_mass_extra_kg=0)))
    _refused(run_files, re.escape(str(run_files.with_suffix(".json"))),
             r"key 'load_mass_kg' = 0 and key 'rig\.moving_mass_extra_kg' = 0: the moving mass "
             r"load_mass_kg \+ rig\.moving_mass_extra_kg = 0 kg must be > 0")
    _rewrite_json(run_files, lambda m: m["rig"].pop("moving_mass_extra_kg"))
    assert read_run(run_files).rig().moving_mass_kg == 1.0  # the default rig's 1 kg moves
    # a run built in Python (not read) is checked when its rig is made
    meta = json.loads(json.dumps(clean_run.meta))
    meta["load_mass_kg"] = 0.0
    meta["rig"]["moving_mass_extra_kg"] = 0.0
    with pytest.raises(MeasurementFormatError, match=r"run 'clean'.*moving mass"):
        MeasuredRun(name="clean", t=clean_run.t, valve=clean_run.valve, x=clean_run.x,
                    p_drive=clean_run.p_drive, p_exhaust=clean_run.p_exhaust, meta=meta).rig()


def test_a_simulated_runs_valve_column_is_the_command_the_plant_took():
    """Of two commands at one time the last holds, in the plant and in the recorded column
    (the column said open while the plant had cut)."""
    run = simulate_run(thesis_rig(2.5), schedule=[(0.0, 1), (0.4, 1), (0.4, 0)], t_end=1.0)
    assert run.valve[-1] == 0.0 and run.schedule() == [(0.0, 1), (0.4, 0)]
