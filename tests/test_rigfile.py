"""Rig files (pneugym/rigfile.py): both forms in JSON and YAML, exact round trips, the discrepancy
workflow's updated_model.json, every refusal (naming the file, the key and the likely mistake),
as_rig, rig_difference and the ``pneugym rig`` command."""
from __future__ import annotations

import inspect
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from pneugym import RigParams, thesis_rig
from pneugym import rigfile
from pneugym.data import read_run, simulate_run, write_run
from pneugym.discrepancy.report import _clean
from pneugym.outputs import OutputError
from pneugym.rigfile import RigFileError, as_rig, describe_difference, rig_difference

ROOT = Path(__file__).resolve().parents[1]

#: a rig far from the defaults in every kind of field: floats, None, a tuple, text, ints
ODD = thesis_rig(1.5, load_mass_kg=23.7,
                 gas={"ambient_temperature_k": 301.3},
                 cylinder={"bore_m": 0.1, "dead_volume_m3": 1.234567890123e-4},
                 line={"length_m": 2.5, "n_cells": 7, "model": "lumped",
                       "tee_volumes": ((0.3, 1e-6), (1.1, 2.5e-6))},
                 valve={"delay_s": 0.0123, "flow_model": "iso6358"},
                 friction={"static_n": 300.1},
                 effects={"leak_drive_area_m2": 3e-7, "sensor_lag_s": 0.015},
                 solver={"dt_s": 2e-5})


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def refused(path_or_value, match: str, **kw) -> str:
    """The message of the RigFileError that loading ``path_or_value`` raises; it must match."""
    with pytest.raises(RigFileError) as exc:
        if isinstance(path_or_value, Path):
            RigParams.load(path_or_value, **kw)
        else:
            as_rig(path_or_value, **kw)
    msg = str(exc.value)
    assert re.search(match, msg), msg
    return msg


# ------------------------------------------------------------------------------------------
# round trips and the forms
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["rig.json", "rig.yaml", "rig.yml", "RIG.JSON", "rig.Yaml"])
@pytest.mark.parametrize("rig", [RigParams(), ODD], ids=["thesis", "odd"])
def test_save_then_load_gives_the_same_rig(tmp_path, name, rig):
    path = rig.save(tmp_path / name)
    assert path == tmp_path / name
    back = RigParams.load(path)
    assert back == rig and rig_difference(back, rig, rel_tol=0.0) == {}
    assert isinstance(back.line.tee_volumes, tuple) and back.valve.delay_s == rig.valve.delay_s
    text = path.read_text(encoding="utf-8")
    doc = json.loads(text) if name.lower().endswith(".json") else yaml.safe_load(text)
    assert doc["format"] == rigfile.FORMAT and doc["cylinder"] == _clean(rig.to_dict())["cylinder"]


def test_save_replaces_a_file_and_refuses_folders_and_other_extensions(tmp_path):
    path = tmp_path / "sub" / "rig.json"
    RigParams().save(path)
    ODD.save(path)  # atomic replace
    assert RigParams.load(path) == ODD
    assert not [p for p in path.parent.iterdir() if p.name != "rig.json"]  # no temporary left
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(OutputError, match=r"dir.yaml is a folder"):
        RigParams().save(tmp_path / "dir.yaml")
    with pytest.raises(RigFileError, match=r"rig.txt: a rig file must end in .json, .yaml or .yml"):
        RigParams().save(tmp_path / "rig.txt")
    assert not (tmp_path / "rig.txt").exists()


def test_a_partial_file_keeps_the_base_for_what_it_does_not_give(tmp_path):
    p = write(tmp_path, "partial.yaml", "supply_pressure_gauge_pa: 150000.0\n"
                                        "line:\n  length_m: 2.5   # m\n"
                                        "valve: {delay_s: 0.2}\n")
    assert RigParams.load(p) == thesis_rig(1.5, line={"length_m": 2.5}, valve={"delay_s": 0.2})
    assert RigParams.load(p, base=ODD) == ODD.with_(supply_pressure_gauge_pa=150000.0,
                                                    line={"length_m": 2.5}, valve={"delay_s": 0.2})
    assert RigParams.load(write(tmp_path, "empty.json", "{}")) == RigParams()
    tee = write(tmp_path, "tee.json", '{"line": {"tee_volumes": [[0.3, 1.0e-6]]}}')
    assert RigParams.load(tee).line.tee_volumes == ((0.3, 1e-6),)


def test_the_measurement_form(tmp_path):
    doc = {"supply_pressure_gauge_pa": 150000, "load_mass_kg": 20.0, "ambient_temperature_k": 298.15,
           "rig": {"bore_m": 0.1, "line_length_m": 2.0, "valve_delay_s": 0.05,
                   "friction": {"static_n": 250}}}
    want = thesis_rig(1.5, load_mass_kg=20.0, gas={"ambient_temperature_k": 298.15},
                      cylinder={"bore_m": 0.1}, line={"length_m": 2.0}, valve={"delay_s": 0.05},
                      friction={"static_n": 250.0})
    assert RigParams.load(write(tmp_path, "m.json", json.dumps(doc))) == want
    assert RigParams.load(write(tmp_path, "m.yaml", yaml.safe_dump(doc))) == want
    assert as_rig(doc) == want == RigParams.from_measurement(doc)
    # the whole rig section of a rig gives back that rig (valve delay resolved)
    full = {"rig": ODD.to_measurement_rig(), "supply_pressure_gauge_pa": 150000.0}
    assert as_rig(full, base=ODD) == ODD.with_(valve={"delay_s": ODD.valve_delay_s})


def test_a_whole_measured_run_json_loads_as_its_rig(tmp_path):
    known = thesis_rig(1.5, line={"length_m": 1.2}, cylinder={"dead_volume_m3": 1e-4})
    run = simulate_run(thesis_rig(1.5, effects={"leak_drive_area_m2": 3e-7}), t_end=0.3,
                       sample_rate_hz=200, known=known, name="run", description="conventional")
    stem = write_run(run, tmp_path / "run")
    meta = json.loads((tmp_path / "run.json").read_text())
    assert {"format", "sample_rate_hz", "description", "simulation"} <= set(meta)
    rig = RigParams.load(tmp_path / "run.json")
    assert rig == read_run(stem).rig() == known.with_(valve={"delay_s": known.valve_delay_s})
    # the format's rule: unknown keys are ignored, unless they look like a misspelt known one
    meta["operator"] = "A. Engineer"
    assert RigParams.load(write(tmp_path, "op.json", json.dumps(meta))) == rig
    meta["load_mas_kg"] = 3.0
    refused(write(tmp_path, "typo.json", json.dumps(meta)),
            r"typo.json: key 'load_mas_kg' is unknown \(did you mean 'load_mass_kg'\?\)")


def test_updated_model_json_of_the_discrepancy_workflow_loads_unchanged(tmp_path):
    """write_report writes json.dumps(_clean(updated_model.to_dict()), indent=2): no format key,
    tuples as lists, delay_s null."""
    for model in (RigParams(), ODD, thesis_rig(2.5, effects={"leak_drive_area_m2": 2.9e-7,
                                                            "heat_transfer_time_constant_s": 1.5})):
        p = tmp_path / "updated_model.json"
        p.write_text(json.dumps(_clean(model.to_dict()), indent=2, allow_nan=False) + "\n")
        assert RigParams.load(p) == model


def test_the_example_of_docs_rigs_md_is_the_thesis_rig_and_marks_the_calibrated_fields():
    text = (ROOT / "docs" / "rigs.md").read_text(encoding="utf-8")
    example = re.search(r"```yaml\n(.*?)```", text, re.S).group(1)
    assert as_rig(yaml.safe_load(example), "docs/rigs.md") == RigParams()
    group, marked = "", set()
    for line in example.splitlines():
        m = re.match(r"(\s*)(\w+):.*#.*calibrated", line)
        group = re.match(r"(\w+):\s*$", line).group(1) if re.match(r"(\w+):\s*$", line) else group
        if m:
            marked.add(f"{group}.{m.group(2)}" if m.group(1) else m.group(2))
    calibrated = {f"{group}.{name}" for group, cls in rigfile.GROUPS.items()
                  for name in re.findall(r"^    (\w+): .*# calibrated", inspect.getsource(cls), re.M)}
    assert len(calibrated) == 8 and marked == calibrated
    measurement = re.search(r"```json\n(.*?)```", text, re.S).group(1)
    assert as_rig(json.loads(measurement)).cylinder.bore_m == 0.1


# ------------------------------------------------------------------------------------------
# refusals: each names the file and the key
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text, match", [
    ("bore.yaml", "cylinder:\n  bore_m: 125\n",
     r"bore.yaml: key 'cylinder.bore_m': CylinderParams.bore_m = 125.0 is not plausible.*mm given as m\?"),
    ("stroke.json", '{"cylinder": {"stroke_m": 180}}',
     r"stroke.json: key 'cylinder.stroke_m': .*180.*mm given as m\?"),
    ("supply.yaml", "supply_pressure_gauge_pa: 2.5\n",
     r"supply.yaml: key 'supply_pressure_gauge_pa': .*bar given as Pa\?"),
    ("rod.yaml", "cylinder: {rod_m: 0.2}\n", r"rod.yaml: key 'cylinder.rod_m': .*must be < bore_m"),
    ("rigbore.yaml", "rig: {bore_m: 125}\n",
     r"rigbore.yaml: key 'rig.bore_m' = 125: .*not a plausible bore.*mm given as m\?"),
    ("rigrod.yaml", "rig: {rod_m: 0.2}\n", r"rigrod.yaml: key 'rig.rod_m': .*must be < bore_m"),
    ("line.yaml", "rig: {line_length_m: 2500}\n", r"line.yaml: key 'rig.line_length_m'.*mm given as m\?"),
    ("tee.yaml", "line: {tee_volumes: [[0.3, 1.0]]}\n", r"tee.yaml: key 'line.tee_volumes': .*cm³ given as m³\?"),
    ("model.yaml", "line: {model: fast}\n", r"model.yaml: key 'line.model': .*'fd' or 'lumped'"),
    ("delay.yaml", "valve: {delay_s: 4.9}\n",
     r"delay.yaml: key 'valve.delay_s' = 4.9: .*valve delay.*ms given as s\?"),
    ("octal.yaml", "load_mass_kg: 010\n", r"octal.yaml: line 1: load_mass_kg = 010: .*read as 8"),
    ("sexa.yaml", "cylinder: {bore_m: 0.125}\nload_mass_kg: 1:05\n",
     r"sexa.yaml: line 2: load_mass_kg = 1:05: .*base 60 .*read as 65"),
    ("hex.yaml", "load_mass_kg: 0x10\n", r"hex.yaml: .*0x as hex"),
])
def test_implausible_values_are_refused_naming_file_key_and_likely_unit(tmp_path, name, text, match):
    refused(write(tmp_path, name, text), match)


@pytest.mark.parametrize("name, text, match", [
    ("a.yaml", "cylinder: {bore: 0.1}\n", r"a.yaml: key 'cylinder.bore' is unknown \(did you mean 'bore_m'\?\)"),
    ("b.yaml", "cylinderr: {bore_m: 0.1}\n", r"b.yaml: key 'cylinderr' is unknown \(did you mean 'cylinder'\?\)"),
    ("c.yaml", "bore_m: 0.1\n", r"c.yaml: key 'bore_m' is unknown \(it belongs in a group: cylinder.bore_m\)"),
    ("d.json", '{"rig": {"bore_mm": 0.1}}', r"d.json: key 'rig.bore_mm' is unknown \(did you mean 'bore_m'\?\)"),
    ("e.json", '{"rig": {"friction": {"static": 1}}}',
     r"e.json: key 'rig.friction.static' is unknown \(did you mean 'static_n'\?\)"),
    ("f.json", '{"rig": {}, "sample_rate_hz": 1000}', r"f.json: key 'sample_rate_hz' is unknown"),
    ("g.json", '{"rig": {}, "bore_m": 0.1}', r"g.json: key 'bore_m' is unknown \(in the measurement form it belongs in 'rig'"),
    ("h.yaml", "line: {lenght_m: 2}\n", r"h.yaml: key 'line.lenght_m' is unknown \(did you mean 'length_m'\?\)"),
])
def test_unknown_keys_are_refused_with_the_nearest_known_name(tmp_path, name, text, match):
    refused(write(tmp_path, name, text), match)


@pytest.mark.parametrize("name, text, match", [
    ("dup.yaml", "cylinder:\n  bore_m: 0.1\n  bore_m: 0.2\n",
     r"dup.yaml: key 'cylinder.bore_m' appears twice \(line 2, then line 3\)"),
    ("dup.json", '{"cylinder": {"bore_m": 0.1, "bore_m": 0.2}}',
     r"dup.json: key 'cylinder.bore_m' appears more than once"),
    ("nan.json", '{"cylinder": {"bore_m": NaN}}', r"nan.json: key 'cylinder.bore_m' = nan is not a finite number"),
    ("inf.json", '{"load_mass_kg": -Infinity}', r"inf.json: key 'load_mass_kg' = -inf is not a finite number"),
    ("big.json", '{"load_mass_kg": 1e999}', r"big.json: key 'load_mass_kg' = inf is not a finite number"),
    ("bigint.json", '{"load_mass_kg": 1' + "0" * 400 + "}", r"bigint.json: key 'load_mass_kg' = 1000.* is not a finite"),
    ("nan.yaml", "valve: {area_m2: .nan}\n", r"nan.yaml: key 'valve.area_m2' = nan is not a finite number"),
    ("empty.yaml", "", r"empty.yaml: the file is empty"),
    ("blank.json", " \n\n", r"blank.json: the file is empty"),
    ("comments.yaml", "# nothing\n", r"comments.yaml: the top level must be a mapping.*got nothing"),
    ("list.json", "[1, 2]", r"list.json: the top level must be a mapping.*got \[1, 2\] \(list\)"),
    ("number.yaml", "3\n", r"number.yaml: the top level must be a mapping.*got 3 \(int\)"),
    ("bool.yaml", "cylinder: {bore_m: yes}\n", r"bool.yaml: key 'cylinder.bore_m': .*True is invalid: must be a finite number"),
    ("text.json", '{"cylinder": {"bore_m": "0.125"}}',
     r"text.json: key 'cylinder.bore_m' = '0.125' is text, not a number: write 0.125"),
    ("yaml11.yaml", "valve: {area_m2: 2e-5}\n",
     r"yaml11.yaml: key 'valve.area_m2' = '2e-5' is text, not a number: write 2.0e-05 .*YAML 1.1"),
    ("word.yaml", "load_mass_kg: ten\n", r"word.yaml: key 'load_mass_kg': .*'ten' is invalid: must be a finite number"),
    ("group.yaml", "line: 3\n", r"group.yaml: key 'line': RigParams.line = 3 is invalid: must be a dict of LineParams fields"),
    ("rigsec.yaml", "rig: [1]\n", r"rigsec.yaml: key 'rig' = \[1\] must be a mapping"),
    ("format.json", '{"format": "pneugym-rig/2"}', r"format.json: key 'format' = 'pneugym-rig/2' is not a rig file's"),
    ("mixed.yaml", "rig: {bore_m: 0.1}\ncylinder: {bore_m: 0.1}\n",
     r"mixed.yaml: mixes the two forms of a rig file: 'rig' of the measurement form .* 'cylinder' of the parameter form"),
    ("mixed2.json", '{"format": "pneugym-rig/1", "ambient_pressure_pa": 1e5}', r"mixed2.json: mixes the two forms"),
    ("mixed3.json", '{"format": "pneugym-measurement/1", "gas": {}}', r"mixed3.json: mixes the two forms"),
    ("alias.yaml", "a: &x {bore_m: 0.1}\ncylinder: *x\n", r"alias.yaml: line \d: anchors and aliases"),
    ("tag.yaml", "cylinder: !!python/object/apply:os.system ['true']\n", r"tag.yaml: plain YAML only"),
    ("broken.yaml", "cylinder: {bore_m: 0.1\n", r"broken.yaml: not valid YAML: .*line"),
    ("broken.json", '{"cylinder": ', r"broken.json: not valid JSON"),
    ("deep.json", "[" * 100_000 + "]" * 100_000, r"deep.json: not valid JSON: nested too deeply"),
    ("boolkey.yaml", "on: 1\n", r"boolkey.yaml: key True in the top level is not text \(YAML reads yes/no/on/off"),
])
def test_malformed_files_are_refused_naming_the_file(tmp_path, name, text, match):
    refused(write(tmp_path, name, text), match)


def test_paths_that_are_not_rig_files_are_refused(tmp_path):
    refused(tmp_path / "missing.yaml", r"missing.yaml: file not found")
    (tmp_path / "folder.json").mkdir()
    refused(tmp_path / "folder.json", r"folder.json: is a folder")
    refused(write(tmp_path, "rig.txt", "{}"), r"rig.txt: a rig file must end in .json, .yaml or .yml")
    refused(write(tmp_path, "run.csv", "t\n"), r"run.csv: .* \(a measured run's rig is in its .json\)")
    refused("", r"rig file path '' is empty")
    (tmp_path / "latin1.yaml").write_bytes(b"load_mass_kg: 10 # \xe9\n")
    refused(tmp_path / "latin1.yaml", r"latin1.yaml: not UTF-8 text")
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + b'{"load_mass_kg": 3.0}')
    assert RigParams.load(bom).load_mass_kg == 3.0


def test_a_file_over_1_mb_is_refused_before_it_is_read(tmp_path, monkeypatch):
    big = tmp_path / "big.json"
    with open(big, "wb") as fh:
        fh.truncate(rigfile.MAX_BYTES + 1)  # sparse: no MB written
    opened = []
    monkeypatch.setattr("builtins.open", lambda *a, **k: opened.append(a))
    refused(big, r"big.json: 1.0 MB is too large for a rig file \(at most 1 MB")
    assert not opened


# ------------------------------------------------------------------------------------------
# as_rig
# ------------------------------------------------------------------------------------------
def test_save_refuses_a_rig_load_would_refuse(tmp_path):
    with pytest.raises(RigFileError, match=r"cannot save .*r.json: key 'valve.delay_s' = 3.0: "
                                           r".*ms given as s\?"):
        RigParams().with_(valve={"delay_s": 3.0}).save(tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()


def test_as_rig_takes_a_rig_a_mapping_a_path_or_none(tmp_path):
    assert as_rig(ODD) is ODD
    assert as_rig(None) == RigParams() and as_rig(None, base=ODD) is ODD
    assert as_rig(ODD.to_dict()) == ODD
    assert as_rig(json.loads(json.dumps(_clean(ODD.to_dict())))) == ODD
    assert as_rig({"cylinder": ODD.cylinder, "line": {"length_m": 2.5}}) == \
        RigParams(cylinder=ODD.cylinder).with_(line={"length_m": 2.5})
    assert as_rig({"load_mass_kg": np.float64(3.5)}, base=ODD) == ODD.with_(load_mass_kg=3.5)
    path = ODD.save(tmp_path / "odd.yaml")
    assert as_rig(path) == as_rig(str(path)) == ODD
    assert as_rig(write(tmp_path, "p.json", '{"load_mass_kg": 2.0}'), base=ODD) == ODD.with_(load_mass_kg=2.0)


def test_as_rig_refusals_name_what_was_given():
    refused({"cylinder": {"bore": 1}}, r"^--rig: key 'cylinder.bore' is unknown \(did you mean 'bore_m'\?\)",
            what="--rig")
    refused({"cylinder": {"bore_m": 125}}, r"^env rig: key 'cylinder.bore_m': .*mm given as m\?", what="env rig")
    refused({"load_mass_kg": float("nan")}, r"^rig: key 'load_mass_kg' = nan is not a finite number")
    refused({1: 2}, r"^rig: key 1 in the top level is not text")
    for bad in (3, [("bore_m", 0.1)], b"rig.yaml", RigParams):
        refused(bad, r"^--rig = .* is not a rig: give a RigParams, a mapping .* or the path", what="--rig")
    with pytest.raises(TypeError, match="base"):
        as_rig({}, base={"load_mass_kg": 1})


# ------------------------------------------------------------------------------------------
# differences
# ------------------------------------------------------------------------------------------
def test_rig_difference_names_the_fields_that_differ():
    a = RigParams()
    assert rig_difference(a, RigParams()) == {} and describe_difference(a, RigParams()) == ""
    b = a.with_(cylinder={"dead_volume_m3": 1e-4}, line={"length_m": 2.5})
    assert rig_difference(a, b) == {"cylinder.dead_volume_m3": (2.44e-4, 1e-4), "line.length_m": (0.725, 2.5)}
    assert describe_difference(a, b) == "cylinder.dead_volume_m3 2.44e-04 -> 1.00e-04, line.length_m 0.725 -> 2.5"
    c = b.with_(supply_pressure_gauge_pa=150000.0, valve={"delay_s": 0.2}, solver={"dt_s": 1e-5},
                line={"model": "lumped", "tee_volumes": [(0.3, 1e-6)]})
    d = rig_difference(a, c)
    assert list(d) == ["supply_pressure_gauge_pa", "cylinder.dead_volume_m3", "line.length_m", "line.model",
                       "line.tee_volumes", "valve.delay_s", "solver.dt_s"]
    assert d["valve.delay_s"] == (None, 0.2) and d["line.tee_volumes"] == ((), ((0.3, 1e-6),))
    assert describe_difference(a, c, limit=2) == ("supply_pressure_gauge_pa 250000 -> 150000, "
                                                  "cylinder.dead_volume_m3 2.44e-04 -> 1.00e-04 (+5 more)")
    full = describe_difference(a, c, limit=10)
    assert "line.model fd -> lumped" in full and "valve.delay_s None -> 0.2" in full and "more" not in full
    # tolerance, and enough digits to tell close values apart
    e = a.with_(load_mass_kg=10.0 * (1 + 1e-12))
    assert rig_difference(a, e) == {} and list(rig_difference(a, e, rel_tol=0.0)) == ["load_mass_kg"]
    assert describe_difference(a, a.with_(load_mass_kg=10.004)) == "load_mass_kg 10 -> 10.004"
    assert describe_difference(a, a.with_(gas={"viscosity_pa_s": 1.8101e-5})) == \
        "gas.viscosity_pa_s 1.8100e-05 -> 1.8101e-05"


# ------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------
def test_the_command_prints_the_rig_as_a_valid_rig_file_and_the_difference(tmp_path, capsys):
    path = ODD.save(tmp_path / "odd.json")
    assert rigfile.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"# {path}: a valid rig\n")
    assert re.search(r"\n  bore_m: 0.1 +# m; the thesis rig: 0.125\n", out)
    assert re.search(r"\nsupply_pressure_gauge_pa: 150000.0 +# Pa gauge; the thesis rig: 250000.0\n", out)
    assert re.search(r"\n  ambient_pressure_pa: 101325.0 +# Pa absolute\n", out)
    assert re.search(r"\n  delay_s: 0.0123 +# s; the thesis rig: null\n", out)
    n = len(rig_difference(RigParams(), ODD))
    assert f"# differs from the thesis rig in {n} of 52 fields: supply_pressure_gauge_pa 250000 -> 150000" in out
    assert as_rig(yaml.safe_load(out)) == ODD  # the output is itself a rig file


def test_the_command_compares_with_a_second_file_and_warns_of_a_rig_that_cannot_move(tmp_path, capsys):
    a = ODD.save(tmp_path / "a.yaml")
    b = ODD.with_(line={"length_m": 3.0}).save(tmp_path / "b.json")
    assert rigfile.main([str(a), str(a)]) == 0
    assert capsys.readouterr().out.endswith(f"# the same rig as {a}\n")
    assert rigfile.main([str(a), str(b)]) == 0
    assert capsys.readouterr().out.endswith(f"# differs from {b} in 1 of 52 fields: line.length_m 3 -> 2.5\n")
    stuck = thesis_rig(0.2, friction={"static_n": 5000.0}).save(tmp_path / "stuck.yaml")
    assert rigfile.main([str(stuck)]) == 0
    assert "# warning: the supply (20000 Pa gauge)" in capsys.readouterr().out


def test_the_command_exits_2_with_the_reason_on_a_bad_file(tmp_path, capsys):
    bad = write(tmp_path, "bad.yaml", "cylinder:\n  bore_m: 125\n")
    assert rigfile.main([str(bad)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith(f"error: {bad}: key 'cylinder.bore_m'") and "mm given as m?" in err
    assert rigfile.main([str(RigParams().save(tmp_path / "ok.yaml")), str(tmp_path / "no.json")]) == 2
    assert "no.json: file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        rigfile.main([])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        rigfile.main(["--help"])
    assert exc.value.code == 0
    assert "examples:\n  pneugym rig my_rig.yaml" in capsys.readouterr().out
