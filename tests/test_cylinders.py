"""The cylinders users have: single-rod cylinders, mounting angles (gravity), an external force,
the retract stroke; checked against static force balances, symmetry and conservation."""
import math

import numpy as np
import pytest

from pneugym import Plant, RigParams, thesis_rig
from pneugym.params import STANDARD_GRAVITY
from pneugym.physics import layout as L

PA = 101_325.0
SINGLE = {"design": "single-rod", "bore_m": 0.05, "rod_m": 0.02, "stroke_m": 0.2,
          "dead_volume_m3": 2e-5, "port_area_m2": 1.5e-5, "cushion_length_m": 0.012}


def single_rod(**changes):
    """An ISO 15552-like 50 mm single-rod cylinder on a 1 m, 6 mm line."""
    cyl = {**SINGLE, **changes.pop("cylinder", {})}
    valve = {"delay_s": 0.02, **changes.pop("valve", {})}
    return RigParams(supply_pressure_gauge_pa=5e5, load_mass_kg=5.0).with_(
        cylinder=cyl, line={"length_m": 1.0, "diameter_m": 0.006},
        friction={"static_n": 80.0, "coulomb_n": 40.0, "viscous_n_s_per_m": 200.0},
        valve=valve, **changes)


def test_the_thesis_rig_keeps_its_packed_parameters():
    """Double-rod and horizontal: both piston faces are the annulus, no constant load, so the
    kernels compute (p_d - p_e) A_p as before (bit for bit; measured against the previous
    version on trajectories and whole suites)."""
    P = Plant(thesis_rig(2.5)).P
    assert P[L.P_AE] == P[L.P_AP] == RigParams().cylinder.piston_area_m2
    assert P[L.P_FLOAD] == 0.0 and P[L.P_V0E] == RigParams().cylinder.dead_volume_m3


def test_single_rod_areas_and_loads():
    rig = single_rod(cylinder={"mounting_angle_deg": 30.0}, external_force_n=50.0)
    cap, ann = math.pi / 4 * 0.05**2, math.pi / 4 * (0.05**2 - 0.02**2)
    assert rig.drive_piston_area_m2 == pytest.approx(cap) and rig.exhaust_piston_area_m2 == pytest.approx(ann)
    weight = rig.moving_mass_kg * STANDARD_GRAVITY
    assert rig.load_force_n == pytest.approx(-0.5 * weight - 50.0)
    back = rig.with_(stroke_direction="retract")
    assert back.drive_piston_area_m2 == pytest.approx(ann) and back.exhaust_piston_area_m2 == pytest.approx(cap)
    assert back.load_force_n == pytest.approx(0.5 * weight - 50.0)  # gravity helps it down


def test_the_validation_rows_of_the_cylinders_pass():
    """``pneugym validate``'s cylinder rows: single-rod breakaway at its static force balance
    (horizontal and rod up, within 2 %), a vertical cylinder holding its load on trapped air,
    the double-rod retract stroke equal to its extension (symmetry, exactly), mass balance, the
    free fall of an unpressurised vertical piston, the size sweep."""
    from pneugym.validate import check_cylinders

    rows = check_cylinders()
    assert len(rows) == 10 and all(r.passed for r in rows), [r for r in rows if not r.passed]
    assert rows[4].quantity.startswith("double-rod retract") and rows[4].simulated == 0.0


def test_breakaway_follows_the_load():
    """Rod up, the breakaway needs M g / A_cap more pressure; an external force F / A_cap."""
    from pneugym.validate import breakaway_gauge_pa, single_rod_rig

    flat, _ = breakaway_gauge_pa(single_rod_rig())
    up, _ = breakaway_gauge_pa(single_rod_rig(cylinder={"mounting_angle_deg": 90.0}))
    pushed, pe = breakaway_gauge_pa(single_rod_rig(external_force_n=100.0))
    area = single_rod_rig().drive_piston_area_m2
    assert up - flat == pytest.approx(6.0 * STANDARD_GRAVITY / area, rel=0.05)
    assert pushed - flat == pytest.approx(100.0 / area, rel=0.05)
    assert pe == pytest.approx(PA, rel=1e-3)


def test_gravity_slows_a_lift_and_speeds_a_lowering():
    times = {}
    for name, angle, direction in (("flat", 0.0, "extend"), ("lift", 90.0, "extend"),
                                   ("lower", 90.0, "retract"), ("flat back", 0.0, "retract")):
        plant = Plant(single_rod(cylinder={"mounting_angle_deg": angle},
                                 stroke_direction=direction))
        plant.run(3.0)
        times[name] = plant.arrival_time_s
    assert times["lift"] > times["flat"] and times["lower"] < times["flat back"]


def test_too_heavy_to_lift_is_said():
    rig = single_rod(cylinder={"mounting_angle_deg": 90.0}, load_mass_kg=200.0,
                     supply_pressure_gauge_pa=2e5)
    assert "gravity and external force" in rig.cannot_move()
    from pneugym.plant import RigWarning

    with pytest.warns(RigWarning, match="can never move"):
        plant = Plant(rig)
    plant.run(1.0)
    assert plant.position_m == 0.0


def test_mass_is_conserved_in_a_single_rod_inclined_stroke():
    plant = Plant(single_rod(cylinder={"mounting_angle_deg": -45.0}, external_force_n=30.0,
                             effects={"leak_piston_area_m2": 1e-7}))
    plant.run(2.0, [(0.0, 1), (0.25, 0)])
    assert abs(plant.mass_balance_error_kg) < 1e-12 * max(plant.total_air_mass_kg, 1e-3) * 1e3


@pytest.mark.parametrize("changes, match", [
    ({"cylinder": {"design": "single"}}, r"design = 'single' is invalid: must be one of "
                                         r"\['double-rod', 'single-rod'\] \(did you mean"),
    ({"cylinder": {"design": "single-rod", "rod_m": 0.0}}, "rod_m = 0.0 is invalid: must be > 0"),
    ({"cylinder": {"mounting_angle_deg": 180.0}}, r"in \[-90, 90\] degrees \(0 horizontal, "
                                                  r"\+90 rod pointing up"),
    ({"cylinder": {"mounting_angle_deg": 1.57}}, None),
    ({"stroke_direction": "out"}, r"stroke_direction = 'out' is invalid: must be one of "
                                  r"\['extend', 'retract'\]"),
    ({"external_force_n": 5e6}, "at most 1e6 N in size"),
    ({"cylinder": {"dead_volume_rod_m3": 2.0}}, "litres or cm³ given as m³"),
])
def test_bad_cylinder_values_are_refused(changes, match):
    if match is None:
        RigParams().with_(**changes)  # a small angle is a valid angle
        return
    with pytest.raises(ValueError, match=match):
        RigParams().with_(**changes)


def test_measured_runs_describe_single_rod_vertical_retract_strokes(tmp_path):
    """New optional keys (rig.cylinder_design, rig.dead_volume_rod_m3, rig.mounting_angle_deg,
    top-level stroke_direction and external_force_n) round-trip; a double-rod horizontal
    extension writes the keys it always had."""
    from pneugym.data import read_run, simulate_run, write_run

    rig = single_rod(cylinder={"mounting_angle_deg": 90.0, "dead_volume_rod_m3": 3e-5},
                     stroke_direction="retract", external_force_n=20.0)
    write_run(simulate_run(rig, t_end=1.0), tmp_path / "up")
    run = read_run(tmp_path / "up")
    assert run.meta["stroke_direction"] == "retract" and run.meta["external_force_n"] == 20.0
    assert run.meta["rig"]["cylinder_design"] == "single-rod"
    assert run.rig() == rig
    plain = simulate_run(thesis_rig(2.5), t_end=0.2).meta
    assert "stroke_direction" not in plain and "cylinder_design" not in plain["rig"]


def test_a_bad_text_key_in_a_measured_run_is_refused(tmp_path):
    import json

    from pneugym.data import MeasurementFormatError, read_run, simulate_run, write_run

    write_run(simulate_run(thesis_rig(2.5), t_end=0.2), tmp_path / "r")
    meta = json.loads((tmp_path / "r.json").read_text())
    meta["rig"]["cylinder_design"] = "single"
    (tmp_path / "r.json").write_text(json.dumps(meta))
    with pytest.raises(MeasurementFormatError, match=r"'rig.cylinder_design' = 'single'; "
                                                     r"expected one of"):
        read_run(tmp_path / "r")


def test_a_rig_file_takes_the_new_keys_in_both_forms(tmp_path):
    import json

    rig = single_rod(cylinder={"mounting_angle_deg": -30.0}, stroke_direction="retract")
    rig.save(tmp_path / "a.yaml")
    assert RigParams.load(tmp_path / "a.yaml") == rig
    (tmp_path / "m.json").write_text(json.dumps({
        "supply_pressure_gauge_pa": 3e5, "stroke_direction": "retract",
        "rig": {"bore_m": 0.05, "rod_m": 0.02, "cylinder_design": "single-rod",
                "mounting_angle_deg": 90}}))
    m = RigParams.load(tmp_path / "m.json")
    assert m.cylinder.design == "single-rod" and m.stroke_direction == "retract"
    assert m.cylinder.mounting_angle_deg == 90.0


def test_engineers_units():
    """1 g of air is 0.774 NL; 1 Nm³ at 0.1 kWh/Nm³; a year of cycles priced."""
    from pneugym.units import air_cost, compressor_energy_kwh, free_air_nl

    assert free_air_nl(1e-3) == pytest.approx(0.7739, abs=1e-4)
    assert compressor_energy_kwh(1.2922) == pytest.approx(0.1)
    c = air_cost(1.2922e-3, cycles_per_minute=10, hours_per_year=4000, price_per_kwh=0.2)
    assert c.free_air_nl_per_cycle == pytest.approx(1.0)
    assert c.cycles_per_year == 2.4e6 and c.energy_kwh_per_year == pytest.approx(240.0)
    assert c.cost_per_year == pytest.approx(48.0)
    plant = Plant(thesis_rig(2.5))
    plant.run(2.0)
    assert 5.0 < free_air_nl(plant.air_mass_in_kg) < 9.0  # a conventional thesis stroke: 7.2 NL
    for bad in (-1.0, float("nan"), "1"):
        with pytest.raises(ValueError, match="must be a finite number"):
            free_air_nl(bad)
    with pytest.raises(ValueError, match="specific_kwh_per_nm3 = 0.0 must be a finite number > 0"):
        compressor_energy_kwh(1.0, 0.0)


def test_the_environment_runs_a_single_rod_vertical_retract_stroke():
    """Everything downstream of the plant takes the new cylinders: the environment, its
    conventional figures, the Gas-Law rule (the driving face area and dead volume)."""
    import gymnasium as gym

    from agents import make_policy
    from pneugym.validate import single_rod_rig

    rig = single_rod_rig(cylinder={"mounting_angle_deg": 60.0}, stroke_direction="retract",
                         valve={"area_m2": 1.5e-5})
    env = gym.make("pneugym/CutOff-v0", rig=rig)
    policy = make_policy("gaslaw", env)
    assert float(np.ravel(policy._area)[0]) == pytest.approx(rig.drive_piston_area_m2)
    endstroke = make_policy("endstroke", env)
    obs, info = env.reset(seed=0)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(endstroke.predict(obs)[0])
        done = term or trunc
    assert info["completed"] and 0.0 < info["saving_ratio"] < 1.0 and info["cutoff_time_s"]


def test_the_jit_cache_is_keyed_on_every_jitted_source(tmp_path, monkeypatch):
    """A change to any file with numba code moves the cache to a new folder; caches of other
    versions are removed once unused for a week, never while fresh."""
    import os
    import time

    from pneugym import _jitcache

    tag = _jitcache.sources_hash()
    assert len(tag) == 16 and tag == _jitcache.sources_hash()
    import shutil

    copy = tmp_path / "pkg"
    shutil.copytree(_jitcache.PACKAGE / "physics", copy / "physics",
                    ignore=shutil.ignore_patterns("__pycache__"))
    before = _jitcache.sources_hash(copy)
    layout = copy / "physics" / "layout.py"  # no numba in it: its indices are read by kernels
    assert b"numba" not in layout.read_bytes()
    layout.write_text(layout.read_text().replace("P_AE = 51", "P_AE = 52"))
    changed = _jitcache.sources_hash(copy)
    assert changed != before
    (copy / "notes.py").write_text("x = 1\n")  # a file outside physics without numba: no change
    assert _jitcache.sources_hash(copy) == changed
    tmp_path = tmp_path / "cache"
    tmp_path.mkdir()
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("PNEUGYM_NUMBA_CACHE", str(tmp_path))
    fresh, stale = tmp_path / ("a" * 16), tmp_path / ("b" * 16)
    for d in (fresh, stale):
        (d / "x").mkdir(parents=True)
        (d / "x" / "k.nbi").write_bytes(b"")
    week = time.time() - 8 * 86400
    os.utime(stale / "x" / "k.nbi", (week, week))
    os.utime(stale / "x", (week, week))
    os.utime(stale, (week, week))
    assert _jitcache.cache_dir() == tmp_path / tag
    assert fresh.exists() and not stale.exists()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    assert _jitcache.cache_dir() is None  # the user's own choice stands


def test_the_discrepancy_workflow_names_a_leak_on_a_vertical_single_rod_cylinder(tmp_path):
    """Measured runs of a single-rod cylinder, rod up, with a seal leak its rig file does not
    state: the workflow names the leak and fits its area."""
    import json

    from pneugym.cli import main
    from pneugym.data import thesis_protocol, write_run
    from pneugym.validate import single_rod_rig

    stated = single_rod_rig(cylinder={"mounting_angle_deg": 90.0}, valve={"area_m2": 1.5e-5},
                            load_mass_kg=10.0)
    truth = stated.with_(effects={"leak_drive_area_m2": 3e-7})
    for run in thesis_protocol(truth, stated, t_end=1.0, seed=3):
        write_run(run, tmp_path / "measured" / run.name)
    assert main(["discrepancy", str(tmp_path / "measured"), "--out", str(tmp_path / "report"),
                 "--candidates", "leakage,sensor_lag", "--starts", "1", "--probe", "2",
                 "--max-nfev", "15", "--jobs", "1", "--no-plots", "--no-progress"]) == 0
    rep = json.loads((tmp_path / "report" / "report.json").read_text())
    assert rep["named_effect"] == "leakage" and rep["gap_reduction"] > 0.9
    fitted = rep["fitted_params"]
    leak = fitted.get("effects.leak_drive_area_m2", fitted.get("leak_drive_area_m2"))
    assert leak == pytest.approx(3e-7, rel=0.05)


def test_a_cycle_extends_and_retracts():
    """Extend, dwell, retract, dwell: both strokes arrive, the cycle's air is both strokes',
    the chambers' air crosses the reversal intact; a cut-off extension saves as a single
    stroke with the same cut does."""
    from pneugym.cycle import run_cycle
    from pneugym.units import free_air_nl

    rig = thesis_rig(2.5)
    conv = run_cycle(rig, dwell_s=0.3)
    assert conv.completed and conv.extend.direction == "extend"
    assert conv.cycle_time_s == pytest.approx(conv.extend.arrival_time_s
                                              + conv.retract.arrival_time_s + 0.6)
    assert conv.air_mass_kg == conv.extend.air_mass_kg + conv.retract.air_mass_kg
    assert conv.free_air_nl == pytest.approx(free_air_nl(conv.air_mass_kg))
    assert conv.mass_balance_error < 1e-12 and conv.extend.saving_ratio == 0.0
    cut = run_cycle(rig, cut_extend_s=0.95, dwell_s=0.3)
    single = Plant(rig)
    single.run(3.0, [(0.0, 1), (0.95, 0)])
    assert cut.extend.saving_ratio == pytest.approx(single.saving_ratio, abs=0.01)
    assert cut.free_air_nl < conv.free_air_nl and cut.completed


def test_a_steady_cycle_starts_where_the_last_ended():
    from pneugym.cycle import run_cycle, steady_cycle

    rig = thesis_rig(2.5)
    first = run_cycle(rig, dwell_s=0.2)
    second = run_cycle(rig, dwell_s=0.2, start_pressures_pa=first.end_pressures_pa)
    assert steady_cycle(rig, cycles=2, dwell_s=0.2) == second
    with pytest.raises(ValueError, match="cycles = 0 must be an integer >= 1"):
        steady_cycle(rig, cycles=0)
    with pytest.raises(ValueError, match="dwell_s = -1.0 must be a finite number >= 0"):
        run_cycle(rig, dwell_s=-1.0)


def test_a_cycle_carries_air_and_heat_across_the_reversal():
    """With heat transfer the chambers' temperatures are not ambient at the reversal: their air
    and temperature are carried, not rebuilt from pressures; effects bound to the driving side
    are refused (a cycle would move them to the other chamber)."""
    from pneugym.cycle import run_cycle

    warm = run_cycle(thesis_rig(2.5, effects={"heat_transfer_time_constant_s": 0.5,
                                              "leak_piston_area_m2": 1e-7}),
                     cut_extend_s=0.9, dwell_s=0.1)
    assert warm.completed and warm.mass_balance_error < 1e-12
    for effect in ({"dead_volume_m3": 1e-4}, {"leak_drive_area_m2": 1e-7},
                   {"leak_drive_laminar_m3": 1e-15}):
        with pytest.raises(ValueError, match="belong to the driving side of one stroke"):
            run_cycle(thesis_rig(2.5, effects=effect))


def test_net_force_is_the_kernels_force_law():
    """``Plant.net_force_n``: (p_d - p_e) A_p on the thesis rig; on a single-rod cylinder, rod
    up, the faces, ambient on the rod's end and gravity."""
    from pneugym.validate import single_rod_rig

    plant = Plant(thesis_rig(2.5))
    assert plant.net_force_n == (plant.p_drive_pa - plant.p_exhaust_pa) * \
        RigParams().cylinder.piston_area_m2
    rig = single_rod_rig(cylinder={"mounting_angle_deg": 90.0})
    plant = Plant(rig)
    pd, pe = plant.p_drive_pa, plant.p_exhaust_pa
    expect = (pd * rig.drive_piston_area_m2 - pe * rig.exhaust_piston_area_m2
              - PA * (rig.drive_piston_area_m2 - rig.exhaust_piston_area_m2)
              - rig.moving_mass_kg * STANDARD_GRAVITY)
    assert plant.net_force_n == pytest.approx(expect, rel=1e-12)
