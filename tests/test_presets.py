"""Standard cylinders at any size: datasheet presets (ISO 6432, ISO 15552), the size sweep on
the automatic substep, the free fall of an unpressurised vertical piston."""
import math

import pytest

from pneugym import Plant, RigParams
from pneugym.presets import BORES, PRESETS, SOURCES, cylinder_rig, moving_mass_kg, preset
from pneugym.rigfile import main as rig_main
from pneugym.validate import check_free_fall, free_fall_time_s, single_rod_rig, size_sweep


def test_every_standard_size_steps_arrives_and_conserves_mass():
    """Bores 8-320 mm, strokes 10-2000 mm: a conventional stroke on the automatic substep, no
    retry, mass to round-off (the validation report's rows)."""
    runs = size_sweep()
    assert len(runs) == len(BORES) * 4 and {r["bore_mm"] for r in runs} >= {8, 320}
    for r in runs:
        assert r["arrival_s"] is not None and r["retries"] == 0, r
        assert r["mass_balance"] < 1e-9, r
        assert r["stick_slips"] <= 1, r
    # bigger is slower for the same stroke, within a catalogue's speeds (0.05-1.5 m/s)
    for r in runs:
        if r["stroke_mm"] >= 100:
            speed = r["stroke_mm"] * 1e-3 / (r["arrival_s"] - 0.02)
            assert 0.05 < speed < 1.5, r


def test_the_presets_state_their_standard_values():
    rig = preset("iso15552-50", stroke_mm=300, load_kg=10.0, supply_bar=6.0)
    c = rig.cylinder
    assert (c.design, c.bore_m, c.rod_m, c.stroke_m) == ("single-rod", 0.05, 0.02, 0.3)
    assert c.cushion_length_m == 0.022 and rig.supply_pressure_gauge_pa == 6e5
    assert rig.load_mass_kg == 10.0 and rig.valve.delay_s == 0.02
    # breakaway at the thesis's measured pressure on the cap face
    thesis = RigParams()
    p_thesis = thesis.friction.static_n / thesis.cylinder.piston_area_m2
    assert rig.friction.static_n / c.cap_area_m2 == pytest.approx(p_thesis)
    # every named preset builds, and the sources are named
    for name in PRESETS:
        assert preset(name).cylinder.bore_m * 1e3 == PRESETS[name]
    assert {"S3", "S4", "S6", "S8", "thesis"} <= set(SOURCES)


def test_the_moving_mass_matches_the_one_datasheet_found():
    """Festo DSNU-S-25: 63.6 g at 0 mm stroke and 6 g per 10 mm (the presets' source S8)."""
    assert moving_mass_kg(25, 0.0) == pytest.approx(0.0636, rel=0.1)
    assert moving_mass_kg(25, 10.0) - moving_mass_kg(25, 0.0) == pytest.approx(0.006, rel=0.1)


def test_a_short_stroke_keeps_its_cushion_inside_it():
    rig = cylinder_rig(125, 10)
    assert rig.cylinder.cushion_length_m == pytest.approx(0.0045)
    assert Plant(rig).dt_s > 0


@pytest.mark.parametrize("call, match", [
    (lambda: cylinder_rig(45, 100), "standard bore"),
    (lambda: cylinder_rig(50, 5), "stroke_mm"),
    (lambda: cylinder_rig(50, 3000), "stroke_mm"),
    (lambda: cylinder_rig(True, 100), "standard bore"),
    (lambda: preset("iso15552-5O"), "did you mean 'iso15552-50'"),
])
def test_bad_sizes_are_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_a_size_that_cannot_be_stepped_says_so():
    rig = cylinder_rig(8, 10).with_(solver={"min_dt_s": 1e-3})
    with pytest.raises(ValueError, match="cannot be stepped.*min_dt_s"):
        Plant(rig)


def test_the_rig_command_writes_a_preset(tmp_path, capsys):
    out = tmp_path / "my_rig.yaml"
    assert rig_main(["--preset", "iso15552-80", "--stroke-mm", "400", "--out", str(out)]) == 0
    assert "a valid rig, written to" in capsys.readouterr().out
    assert RigParams.load(out) == preset("iso15552-80", stroke_mm=400)
    assert rig_main(["--preset", "63", "--stroke-mm", "250"]) == 0
    assert rig_main(["--preset", "63", "--stroke-mm", "5"]) == 2
    assert "stroke_mm" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        rig_main([])


def test_an_unpressurised_vertical_piston_falls_as_friction_allows():
    """The validation row, and the analytic fall itself: with no friction and no damping it
    would be free fall, x = g t² / 2."""
    (row,) = check_free_fall()
    assert row.passed and abs(row.simulated / row.reference - 1.0) < 0.01
    rig = single_rod_rig(friction={"static_n": 0.0, "coulomb_n": 0.0, "viscous_n_s_per_m": 1e-3})
    g_fall = math.sqrt(2 * rig.cylinder.stroke_m / 9.80665)
    assert free_fall_time_s(rig) == pytest.approx(g_fall, rel=1e-4)
