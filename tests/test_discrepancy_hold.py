"""Hold tests (pneugym.discrepancy.hold): warm air settling in the plant against the gas law, leak
against heat settling on simulated records, the public chamber records, and bad input."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from pneugym import RigParams, thesis_rig
from pneugym.discrepancy.__main__ import main
from pneugym.discrepancy.cases import FORM_RANGES, make_case
from pneugym.discrepancy.datasets import ZILLEN_CHAMBERS, zillen_chamber
from pneugym.discrepancy.hold import HoldDiscrepancy, HoldRecord, read_hold
from pneugym.physics import layout as L
from pneugym.plant import Plant

PA = 101_325.0


def test_warm_air_settles_to_the_gas_law():
    """A closed chamber of air 20 K above ambient, with heat transfer, ends at the pressure the
    gas law gives for its mass at ambient temperature (the isothermal line shares it)."""
    rig = thesis_rig(2.5, effects={"heat_transfer_time_constant_s": 0.5})
    pl = Plant(rig)
    p0, T, warm = 6e5, rig.gas.ambient_temperature_k, 20.0
    pl.reset(p_drive_pa=p0, p_exhaust_pa=PA, p_line_pa=p0, position_m=rig.cylinder.stroke_m,
             T_drive_k=T + warm)
    tr = pl.run(10.0, [(0.0, 0)], record_dt=0.01)
    v_ch = pl.P[L.P_V0D] + pl.P[L.P_AP] * rig.cylinder.stroke_m
    v_line = pl.P[L.NP:].sum()
    expected = (p0 * v_ch * T / (T + warm) + p0 * v_line) / (v_ch + v_line)
    assert tr["p_drive"][-1] == pytest.approx(expected, rel=1e-4)
    assert tr["T_drive"][-1] == pytest.approx(T, abs=1e-3)
    # without heat transfer the warm air keeps its temperature and the pressure stays
    pl = Plant(thesis_rig(2.5))
    pl.reset(p_drive_pa=p0, p_exhaust_pa=PA, p_line_pa=p0, position_m=0.18, T_drive_k=T + warm)
    assert pl.run(2.0, [(0.0, 0)])["p_drive"][-1] == pytest.approx(p0, rel=1e-6)
    with pytest.raises(ValueError, match="T_drive_k"):
        pl.reset(T_drive_k=20.0)  # degrees Celsius given as kelvin


def test_a_laminar_leak_drains_a_closed_chamber_as_hagen_poiseuille_says():
    """Isothermal capillary flow q = K (p² - p_a²) / (2 mu R T) out of a closed volume V gives
    dp/dt = -K (p² - p_a²) / (2 mu V): p = p_a (1 + r) / (1 - r), r = r0 exp(-K p_a t / (mu V))."""
    k = 2e-14
    rig = thesis_rig(2.5, effects={"leak_drive_laminar_m3": k})
    pl = Plant(rig)
    p0 = 6e5
    pl.reset(p_drive_pa=p0, p_exhaust_pa=PA, p_line_pa=p0, position_m=rig.cylinder.stroke_m)
    tr = pl.run(8.0, [(0.0, 0)], record_dt=0.5)
    vol = pl.P[L.P_V0D] + pl.P[L.P_AP] * rig.cylinder.stroke_m + pl.P[L.NP:].sum()
    r = (p0 - PA) / (p0 + PA) * np.exp(-k * PA * tr["t"] / (rig.gas.viscosity_pa_s * vol))
    assert tr["p_drive"] == pytest.approx(PA * (1 + r) / (1 - r), rel=1e-6)
    assert tr["p_drive"][-1] < 0.8 * p0  # it did drain
    # the vented air is the air the chamber and line lost
    lost = vol * (p0 - tr["p_drive"][-1]) / (rig.gas.gas_constant_j_per_kg_k
                                             * rig.gas.ambient_temperature_k)
    assert pl.air_mass_out_kg == pytest.approx(lost, rel=1e-3)


def test_a_laminar_leak_flows_at_the_wall_temperature_and_stays_stable_above_supply():
    """The capillary's gas takes the wall's (ambient) temperature: a chamber of warm air loses
    mass at the rate the isothermal law gives at ambient, and the outflow carries the chamber's
    enthalpy. A large leak from a small chamber started at three times the supply pressure
    steps without a warning: its stability limit holds above the supply (taken at the supply
    pressure, this start went non-physical in the first substep)."""
    k = 2e-14
    rig = thesis_rig(2.5, effects={"leak_drive_laminar_m3": k, "heat_transfer_time_constant_s": 50.0})
    T, R, mu = rig.gas.ambient_temperature_k, rig.gas.gas_constant_j_per_kg_k, rig.gas.viscosity_pa_s
    pl = Plant(rig)
    p0 = 6e5
    pl.reset(p_drive_pa=p0, p_exhaust_pa=PA, p_line_pa=p0, position_m=rig.cylinder.stroke_m,
             T_drive_k=T + 30.0)
    pl.run(0.02, [(0.0, 0)])
    m0, p1 = pl.air_mass_out_kg, pl.p_drive_pa
    pl.run(0.04, [(0.0, 0)])
    rate = (pl.air_mass_out_kg - m0) / 0.02
    p_sq = 0.5 * (p1**2 + pl.p_drive_pa**2)  # (the pressure falls 0.3 % meanwhile)
    # (at the chamber's temperature, 30 K above ambient, the rate would be 9 % lower)
    assert rate == pytest.approx(k * (p_sq - PA**2) / (2 * mu * R * T), rel=1e-3)
    assert pl.mass_balance_error_kg < 1e-12
    big = thesis_rig(2.5, effects={"leak_drive_laminar_m3": 1e-10})
    p2 = 3 * big.supply_pressure_pa
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a non-physical state would halve the substep, warning
        pl = Plant(big)
        pl.reset(p_drive_pa=p2, p_exhaust_pa=PA, position_m=0.0)
        tr = pl.run(0.05, [(0.0, 0)], record_dt=0.001)
    assert np.all(np.isfinite(tr["p_drive"])) and PA < tr["p_drive"][-1] < 0.5 * p2


def test_hold_leak_laws_are_checked_and_one_law_alone_works():
    for bad in ("laminar", (), ("orifice", "capillary"), None):
        with pytest.raises(ValueError, match="leak_laws"):
            HoldDiscrepancy(leak_laws=bad)
    rec = _record({"effects.leak_drive_laminar_m3": 1e-14}, seed=5)
    h = HoldDiscrepancy(sigma_pa=50.0, n_starts=1, leak_laws=("laminar",)).fit(rec)
    rep = h.report_dict()
    assert h.named_effect_ == "leakage" and rep["leak_law"] == "laminar"
    assert rep["leak_law_separation"] is None and "(laminar law)" in rep["decision"]
    assert set(rep["leak_law_checks"]) == {"laminar"} and "leak_per_litre_m2" not in rep
    assert rep["leak"]["per_litre"] == rep["laminar_leak_per_litre_m3"]
    json.dumps(rep)


def test_the_leaky_print_is_a_laminar_leak():
    """The public 0.15 mm print: an orifice leaves a structured tail (`none, evidence short` with
    the orifice alone); laminar pores fit it, told from the orifice."""
    rec = zillen_chamber("Ultimaker_015")
    h = HoldDiscrepancy(n_starts=1).fit(rec)
    rep = h.report_dict()
    assert h.named_effect_ == "leakage" and rep["leak_law"] == "laminar", rep["decision"]
    assert rep["leak_law_separation"]["resolved"]
    assert not rep["leak_law_checks"]["orifice"]["passed"]
    assert HoldDiscrepancy(n_starts=1, leak_laws=("orifice",)).fit(rec).named_effect_ == "none"


def _record(values: dict, seed: int, sigma: float = 50.0) -> HoldRecord:
    """A 60 s hold at 5 Hz simulated by the hold model itself, with white noise."""
    t = np.arange(0.0, 60.0, 0.2)
    tmpl = HoldRecord("template", t, np.full(t.size, 7e5))
    p = HoldDiscrepancy().simulate(tmpl, {"hold.p_start_pa": 7e5, "hold.t_close_s": 3.0, **values})
    return HoldRecord(f"sim{seed}", t, p + np.random.default_rng(seed).normal(0.0, sigma, t.size))


@pytest.mark.parametrize("values, named", [
    ({"effects.leak_drive_area_m2": 2e-9}, "leakage"),
    ({"effects.leak_drive_area_m2": 1.5e-7}, "leakage"),
    ({"effects.leak_drive_laminar_m3": 1e-14}, "leakage"),
    ({"effects.heat_transfer_time_constant_s": 8.0, "hold.warm_k": 6.0}, "heat_transfer"),
    ({}, "none"),
])
def test_hold_names_what_drains_the_chamber(values, named):
    h = HoldDiscrepancy(sigma_pa=50.0, n_starts=1).fit(_record(values, seed=len(values)))
    assert h.named_effect_ == named, h.report_dict()
    rep = h.report_dict()
    assert rep["decision"].startswith(named) and rep["holdout_from_s"] == pytest.approx(40.0, abs=0.5)
    if named == "leakage":  # its size on its own law, and the law where the decay shows it
        (path, true), = values.items()
        law = "laminar" if "laminar" in path else "orifice"
        model = ("leakage_laminar",) if law == "laminar" else ("leakage",)
        fitted = h.models_[model].values[path]
        assert fitted == pytest.approx(true, rel=0.05)
        key = "leak_per_litre_m2" if law == "orifice" else "laminar_leak_per_litre_m3"
        assert rep[key] == pytest.approx(fitted / (rep["model_volume_m3"] * 1e3))
        drained = 1 - h.record_.p[-1] / h.record_.p[0]
        if drained > 0.3:  # a long decay: the two laws' shapes differ
            assert rep["leak_law"] == law and rep["leak_law_separation"]["resolved"], rep["decision"]
            assert f"({law} law; the " in rep["decision"]
        else:  # 1 % in a minute: either law bends the decay alike, and the report says so
            assert drained < 0.02 and not rep["leak_law_separation"]["resolved"], rep["decision"]
            assert "law; not told from the" in rep["decision"]
    if named == "heat_transfer":
        v = h.models_[("heat_transfer",)].values
        assert v["effects.heat_transfer_time_constant_s"] == pytest.approx(8.0, rel=0.15)
        assert v["hold.warm_k"] == pytest.approx(6.0, rel=0.15)


def test_public_chamber_records_load_in_si():
    for name in ZILLEN_CHAMBERS:
        rec = zillen_chamber(name)
        assert 1400 <= rec.t.size <= 1600 and 140.0 <= rec.t[-1] <= 152.0  # s, from ms
        assert 8.2e5 <= rec.p[0] <= 9.0e5  # Pa absolute, from bar gauge
        assert "CC0" in rec.source
    assert zillen_chamber("Ultimaker_020").p[-1] == pytest.approx(1.04e5, rel=0.01)
    with pytest.raises(ValueError, match="unknown chamber"):
        zillen_chamber("Steel")


def test_bad_hold_records_are_refused(tmp_path):
    t = np.arange(50.0)
    with pytest.raises(ValueError, match="absolute"):
        HoldRecord("gauge", t, np.full(50, 7.0))  # bar given as Pa
    with pytest.raises(ValueError, match="increase"):
        HoldRecord("time", t[::-1], np.full(50, 7e5))
    with pytest.raises(ValueError, match="litres"):
        HoldRecord("volume", t, np.full(50, 7e5), volume_m3=2.0)
    with pytest.raises(ValueError, match="length"):
        HoldRecord("short", t[:5], np.full(5, 7e5))
    with pytest.raises(ValueError, match="ms given as s"):
        HoldRecord("ms", t * 1000.0, np.full(50, 7e5))
    with pytest.raises(ValueError, match="ambient"):
        HoldRecord("vacuum", t, np.full(50, 9e4))
    bad = tmp_path / "bad.csv"
    bad.write_text("0.000;3.8;7.6\nnot;a;row\n")
    with pytest.raises(ValueError, match="line 2"):
        zillen_chamber("bad", bad)
    bad.write_text("0.000;3.8;7.6\n1.5;3.8;7.6\n")  # a time not in groups of three digits
    with pytest.raises(ValueError, match="line 2"):
        zillen_chamber("bad", bad)
    # dense samples and one far later: the uniform grid would hold millions of samples
    gap = HoldRecord("gap", np.r_[np.arange(30) * 1e-5, 60.0], np.full(31, 7e5))
    with pytest.raises(ValueError, match="far from even.*6,000,001 samples"):
        gap.uniform()
    with pytest.raises(ValueError, match="sigma_pa"):
        HoldDiscrepancy(sigma_pa=0.0)


def test_a_scaled_delay_survives_the_measurement_format():
    """The format writes the delay the plant uses (scale included) and reads it back as the
    delay: read over a base with a scale, it is not scaled twice."""
    rig = thesis_rig(2.5).with_(valve={"delay_scale": 1.2})
    meta = {"rig": rig.to_measurement_rig(), "supply_pressure_gauge_pa": 2.5e5}
    for base in (None, rig):
        assert RigParams.from_measurement(meta, base=base).valve_delay_s == pytest.approx(1.2 * 0.185)


def test_mismatched_cases_differ_in_form_only():
    """A case of one seed shares its effect and offsets across forms; the mismatched one has
    another line, orifice law, cushion, tee and spool (the bench's FORM_RANGES)."""
    known, matched, _ = make_case("leakage", 1000, "matched")
    _, mism, runs = make_case("leakage", 1000, "mismatched")
    assert matched.effects == mism.effects and matched.friction == mism.friction
    assert matched.valve.discharge_coefficient == mism.valve.discharge_coefficient
    assert mism.line != known.line and mism.line.tee_volumes
    assert mism.cylinder.cushion_ramp_m != known.cylinder.cushion_ramp_m
    assert mism.valve.delay_s is not None and mism.valve.ramp_s != known.valve.ramp_s
    assert set(FORM_RANGES) == {"line", "orifices", "cushion", "tee", "spool"}
    stated = known.with_(valve={"delay_s": known.valve_delay_s})  # the JSON writes the delay out
    assert all(r.rig() == stated for r in runs)  # every JSON states the nominal rig
    with pytest.raises(ValueError, match="form"):
        make_case("leakage", 1, "other")


def test_hold_through_the_cli(tmp_path, capsys):
    rec = _record({}, seed=7)
    path = tmp_path / "chamber.csv"
    path.write_text("t,p_drive\n" + "\n".join(f"{a:.3f},{b:.1f}" for a, b in zip(rec.t, rec.p)))
    assert main(["--hold", str(path), "--out", str(tmp_path / "rep"), "--no-progress"]) == 0
    rep = json.loads((tmp_path / "rep" / "chamber" / "hold.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert rep["named_effect"] == "none" and rep["provenance"]["versions"]
    assert (tmp_path / "rep" / "chamber" / "hold.png").stat().st_size > 1000
    assert "Named: `none`" in (tmp_path / "rep" / "chamber" / "hold.md").read_text()
    assert "chamber: none" in capsys.readouterr().out
    excel = tmp_path / "excel.csv"  # a byte-order mark and spaced header names, as Excel writes
    excel.write_text("\ufeff t, p_drive\n" + "\n".join(f"{a:.3f}, {b:.1f}"
                                                     for a, b in zip(rec.t, rec.p)),
                     encoding="utf-8")
    np.testing.assert_array_equal(read_hold(str(excel)).p, read_hold(str(path)).p)
    bad = tmp_path / "bad.csv"
    bad.write_text("time,pressure\n0,1\n")
    assert main(["--hold", str(bad), "--out", str(tmp_path / "rep2")]) == 2
    assert "p_drive" in capsys.readouterr().err
    assert main(["--hold", str(path), "--out", str(tmp_path / "rep3"), "--starts", "0"]) == 2
    assert "n_starts >= 1" in capsys.readouterr().err  # --starts reaches the hold test
    # --leak-laws reaches it too (one law: no separation of laws), and only it
    assert main(["--hold", str(path), "--out", str(tmp_path / "rep4"), "--no-plots", "--starts",
                 "1", "--leak-laws", "laminar"]) == 0
    rep = json.loads((tmp_path / "rep4" / "chamber" / "hold.json").read_text())
    assert rep["leak_law"] == "laminar" and set(rep["leak_law_checks"]) == {"laminar"}
    assert main([str(path), "--out", str(tmp_path / "rep5"), "--leak-laws", "orifice"]) == 2
    assert "--leak-laws is for hold tests" in capsys.readouterr().err
