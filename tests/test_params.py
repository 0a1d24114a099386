"""Rig parameters (pneugym/params.py): validation, copies, dict round trips, the measured-run
``rig`` section (MEASUREMENT_FORMAT.md) and the pressure-dependent valve delay."""
from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest

from pneugym import (
    CylinderParams, EffectParams, FrictionParams, GasParams, LineParams, RigParams, SolverParams,
    ValveParams, thesis_rig,
)
from pneugym.params import THESIS_VALVE_DELAY

NAN, INF = float("nan"), float("inf")

# ------------------------------------------------------------------------------------------
# validation: (class, field, bad value); the ValueError must name "Class.field"
# ------------------------------------------------------------------------------------------
BAD_VALUES = [
    # gas
    (GasParams, "gas_constant_j_per_kg_k", 0.0),
    (GasParams, "gas_constant_j_per_kg_k", -287.0),
    (GasParams, "gamma", 1.0),
    (GasParams, "gamma", 2.0),
    (GasParams, "gamma", NAN),
    (GasParams, "ambient_temperature_k", 0.0),
    (GasParams, "ambient_temperature_k", INF),
    (GasParams, "ambient_pressure_pa", -1.0),
    (GasParams, "ambient_pressure_pa", NAN),
    (GasParams, "viscosity_pa_s", 0.0),
    # cylinder
    (CylinderParams, "bore_m", 0.0),
    (CylinderParams, "bore_m", -0.1),
    (CylinderParams, "bore_m", NAN),
    (CylinderParams, "bore_m", INF),
    (CylinderParams, "stroke_m", 0.0),
    (CylinderParams, "stroke_m", -INF),
    (CylinderParams, "rod_m", -0.01),
    (CylinderParams, "dead_volume_m3", 0.0),
    (CylinderParams, "dead_volume_m3", -1e-5),
    (CylinderParams, "port_area_m2", 0.0),
    (CylinderParams, "cushion_length_m", -0.001),
    (CylinderParams, "cushion_factor_drive", 0.0),
    (CylinderParams, "cushion_factor_drive", 1.5),
    (CylinderParams, "cushion_factor_exhaust", -0.1),
    (CylinderParams, "cushion_factor_exhaust", 1.01),
    (CylinderParams, "cushion_ramp_m", 0.0),
    (CylinderParams, "moving_mass_extra_kg", -1.0),
    (CylinderParams, "moving_mass_extra_kg", NAN),
    # line
    (LineParams, "length_m", 0.0),
    (LineParams, "length_m", NAN),
    (LineParams, "diameter_m", -0.005),
    (LineParams, "n_cells", 0),
    (LineParams, "n_cells", -3),
    (LineParams, "n_cells", 5000),
    (LineParams, "n_cells", 2.5),
    (LineParams, "model", "moc"),
    (LineParams, "model", "FD"),
    # valve
    (ValveParams, "area_m2", 0.0),
    (ValveParams, "area_m2", INF),
    (ValveParams, "exhaust_area_m2", -1e-6),
    (ValveParams, "discharge_coefficient", 0.0),
    (ValveParams, "discharge_coefficient", 1.2),
    (ValveParams, "discharge_coefficient", NAN),
    (ValveParams, "delay_s", -0.01),
    (ValveParams, "delay_s", 10.0),
    (ValveParams, "delay_s", NAN),
    (ValveParams, "ramp_s", 0.0),
    (ValveParams, "flow_model", "iso"),
    (ValveParams, "flow_model", ""),
    (ValveParams, "iso_b", 1.0),
    (ValveParams, "iso_b", -0.1),
    (ValveParams, "linear_ratio", 0.0),
    (ValveParams, "linear_ratio", 5e-5),
    (ValveParams, "linear_ratio", 0.5),
    (ValveParams, "linear_ratio", NAN),
    # friction
    (FrictionParams, "static_n", -1.0),
    (FrictionParams, "coulomb_n", -126.0),
    (FrictionParams, "viscous_n_s_per_m", -1.0),
    (FrictionParams, "static_n", NAN),
    (FrictionParams, "viscous_n_s_per_m", INF),
    # effects
    (EffectParams, "leak_drive_area_m2", -1e-7),
    (EffectParams, "leak_piston_area_m2", -1e-7),
    (EffectParams, "leak_drive_laminar_m3", -1e-15),
    (EffectParams, "heat_transfer_time_constant_s", -1.0),
    (EffectParams, "stribeck_force_n", -10.0),
    (EffectParams, "stribeck_velocity_m_s", 0.0),
    (EffectParams, "stribeck_velocity_m_s", -0.01),
    (EffectParams, "sensor_lag_s", -0.015),
    (EffectParams, "dead_volume_m3", -1e-5),
    (EffectParams, "dead_volume_m3", NAN),
    # solver
    (SolverParams, "dt_s", 0.0),
    (SolverParams, "dt_s", -1e-4),
    (SolverParams, "dt_s", NAN),
    (SolverParams, "safety", 0.0),
    (SolverParams, "safety", 1.5),
    (SolverParams, "min_dt_s", 0.0),
    # rig
    (RigParams, "supply_pressure_gauge_pa", 0.0),
    (RigParams, "supply_pressure_gauge_pa", -50_000.0),
    (RigParams, "supply_pressure_gauge_pa", 5e6),
    (RigParams, "supply_pressure_gauge_pa", NAN),
    (RigParams, "supply_pressure_gauge_pa", INF),
    (RigParams, "load_mass_kg", -1.0),
    (RigParams, "load_mass_kg", NAN),
]


@pytest.mark.parametrize("cls,name,value", BAD_VALUES,
                         ids=[f"{c.__name__}.{n}={v!r}" for c, n, v in BAD_VALUES])
def test_bad_value_raises_valueerror_naming_the_field(cls, name, value):
    with pytest.raises(ValueError, match=re.escape(f"{cls.__name__}.{name}")):
        cls(**{name: value})


@pytest.mark.parametrize("rod", [0.125, 0.2])
def test_rod_not_smaller_than_bore_is_refused(rod):
    with pytest.raises(ValueError, match=r"CylinderParams\.rod_m"):
        CylinderParams(bore_m=0.125, rod_m=rod)


def test_cushion_zone_must_be_shorter_than_half_the_stroke():
    with pytest.raises(ValueError, match=r"CylinderParams\.cushion_length_m"):
        CylinderParams(stroke_m=0.1, cushion_length_m=0.05)
    CylinderParams(stroke_m=0.1, cushion_length_m=0.049)  # just inside: fine


@pytest.mark.parametrize("tees", [((-0.1, 1e-6),), ((2.0, 1e-6),), ((0.5, -1e-6),),
                                  ((NAN, 1e-6),), ((0.5, INF),), ((0.2, 1e-6), (0.5, NAN))])
def test_bad_tee_volume_is_refused(tees):
    with pytest.raises(ValueError, match="tee_volumes"):
        LineParams(length_m=1.0, tee_volumes=tees)


def test_tee_volumes_are_normalised_to_float_tuples():
    ln = LineParams(length_m=1.0, tee_volumes=((0, 1e-6), (1, 0)))
    assert ln.tee_volumes == ((0.0, 1e-6), (1.0, 0.0))
    assert all(isinstance(v, float) for pair in ln.tee_volumes for v in pair)


def test_edge_values_that_are_valid():
    CylinderParams(rod_m=0.0, cushion_length_m=0.0, moving_mass_extra_kg=0.0)
    ValveParams(delay_s=0.0, iso_b=0.0, linear_ratio=1e-4, discharge_coefficient=1.0)
    ValveParams(delay_s=5.0, linear_ratio=0.2, iso_b=0.99)
    FrictionParams(static_n=0.0, coulomb_n=0.0, viscous_n_s_per_m=0.0)
    LineParams(n_cells=1, model="lumped")
    LineParams(n_cells=4096)
    SolverParams(dt_s=1e-5, safety=1.0)
    RigParams(supply_pressure_gauge_pa=1e4, load_mass_kg=0.0, friction=FrictionParams(static_n=100.0))


def test_rig_validation_error_message_says_what_is_wrong():
    with pytest.raises(ValueError) as exc:
        RigParams(supply_pressure_gauge_pa=0.0)
    msg = str(exc.value)
    assert "RigParams.supply_pressure_gauge_pa = 0.0" in msg and "ambient" in msg


def test_params_are_frozen():
    p = RigParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.load_mass_kg = 3.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.cylinder.bore_m = 0.1  # type: ignore[misc]


# ------------------------------------------------------------------------------------------
# derived quantities
# ------------------------------------------------------------------------------------------
def test_derived_quantities():
    p = RigParams(supply_pressure_gauge_pa=150_000.0, load_mass_kg=7.0,
                  gas=GasParams(ambient_pressure_pa=100_000.0),
                  cylinder=CylinderParams(bore_m=0.1, rod_m=0.02, moving_mass_extra_kg=1.5),
                  line=LineParams(diameter_m=0.004))
    assert p.supply_pressure_pa == pytest.approx(250_000.0, rel=1e-15)
    assert p.moving_mass_kg == pytest.approx(8.5, rel=1e-15)
    assert p.cylinder.piston_area_m2 == pytest.approx(math.pi / 4 * (0.1**2 - 0.02**2), rel=1e-14)
    assert p.line.area_m2 == pytest.approx(math.pi / 4 * 0.004**2, rel=1e-14)
    assert p.gas.sound_speed_isothermal_m_s == pytest.approx(
        math.sqrt(p.gas.gas_constant_j_per_kg_k * p.gas.ambient_temperature_k), rel=1e-15)


def test_thesis_rig_sets_supply_and_changes():
    p = thesis_rig(1.5, load_mass_kg=5.0, friction={"static_n": 300.0})
    assert p.supply_pressure_gauge_pa == pytest.approx(150_000.0)
    assert p.load_mass_kg == 5.0
    assert p.friction.static_n == 300.0
    assert p.friction.coulomb_n == FrictionParams().coulomb_n


# ------------------------------------------------------------------------------------------
# with_, to_dict / from_dict
# ------------------------------------------------------------------------------------------
def test_with_nested_dicts_changes_only_what_is_named():
    base = RigParams()
    new = base.with_(load_mass_kg=3.0, friction={"static_n": 300.0},
                     cylinder={"bore_m": 0.1, "stroke_m": 0.2}, effects={"sensor_lag_s": 0.01})
    assert new.load_mass_kg == 3.0
    assert new.friction == dataclasses.replace(base.friction, static_n=300.0)
    assert new.cylinder == dataclasses.replace(base.cylinder, bore_m=0.1, stroke_m=0.2)
    assert new.effects == dataclasses.replace(base.effects, sensor_lag_s=0.01)
    for g in ("gas", "line", "valve", "solver"):
        assert getattr(new, g) == getattr(base, g)
    assert new.supply_pressure_gauge_pa == base.supply_pressure_gauge_pa
    assert base == RigParams(), "with_ must not modify the original"


def test_with_accepts_a_group_instance():
    fr = FrictionParams(static_n=1.0, coulomb_n=0.5, viscous_n_s_per_m=2.0)
    assert RigParams().with_(friction=fr).friction is fr


def test_with_validates_and_names_the_field():
    with pytest.raises(ValueError, match=r"FrictionParams\.static_n"):
        RigParams().with_(friction={"static_n": -5.0})
    with pytest.raises(ValueError, match=r"CylinderParams\.rod_m"):
        RigParams().with_(cylinder={"rod_m": 1.0})
    with pytest.raises(ValueError, match=r"RigParams\.load_mass_kg"):
        RigParams().with_(load_mass_kg=-2.0)


def test_with_unknown_top_level_key_raises_valueerror():
    with pytest.raises(ValueError, match="nonexistent"):
        RigParams().with_(nonexistent=1.0)


def test_from_dict_unknown_nested_key_raises_valueerror():
    with pytest.raises(ValueError):
        RigParams.from_dict({"cylinder": {"no_such_field": 1.0}})


#: Every field set to a valid non-default value (fields added later keep their default here).
NON_DEFAULT = {
    "supply_pressure_gauge_pa": 180_000.0, "load_mass_kg": 4.5,
    "gas": dict(gas_constant_j_per_kg_k=288.0, gamma=1.39, ambient_temperature_k=300.0,
                ambient_pressure_pa=99_000.0, viscosity_pa_s=1.9e-5),
    "cylinder": dict(bore_m=0.1, rod_m=0.025, stroke_m=0.2, dead_volume_m3=4e-5,
                     port_area_m2=2.1e-5, cushion_length_m=0.012, cushion_factor_drive=0.25,
                     cushion_factor_exhaust=0.1, cushion_ramp_m=0.003, moving_mass_extra_kg=1.5),
    "line": dict(length_m=1.3, diameter_m=0.006, n_cells=6, model="lumped",
                 tee_volumes=((0.4, 1e-6), (1.3, 2e-6))),
    "valve": dict(area_m2=2.0e-5, exhaust_area_m2=2.2e-5, discharge_coefficient=0.7, delay_s=0.2,
                  ramp_s=0.02, flow_model="iso6358", iso_b=0.4, linear_ratio=0.03),
    "friction": dict(static_n=300.0, coulomb_n=110.0, viscous_n_s_per_m=1400.0),
    "effects": dict(leak_drive_area_m2=1e-8, leak_piston_area_m2=2e-8,
                    heat_transfer_time_constant_s=0.5, stribeck_force_n=50.0,
                    stribeck_velocity_m_s=0.02, sensor_lag_s=0.015, dead_volume_m3=1e-5),
    "solver": dict(dt_s=1e-5, safety=0.8, min_dt_s=1e-8),
}


def _non_default_rig() -> RigParams:
    """A rig in which every listed field differs from the default (so a lost field shows)."""
    return RigParams().with_(**NON_DEFAULT)


def test_non_default_rig_really_differs_where_listed():
    a, b = _non_default_rig(), RigParams()
    for k, v in NON_DEFAULT.items():
        if isinstance(v, dict):
            for kk, vv in v.items():
                assert getattr(getattr(a, k), kk) != getattr(getattr(b, k), kk), f"{k}.{kk}"
        else:
            assert getattr(a, k) != getattr(b, k), k


def test_to_dict_from_dict_round_trip():
    p = _non_default_rig()
    d = p.to_dict()
    assert isinstance(d["cylinder"], dict) and d["cylinder"]["bore_m"] == 0.1
    assert RigParams.from_dict(d) == p
    assert RigParams.from_dict(RigParams().to_dict()) == RigParams()


def test_from_dict_partial_keeps_defaults():
    p = RigParams.from_dict({"load_mass_kg": 2.0, "valve": {"ramp_s": 0.02}})
    assert p == RigParams().with_(load_mass_kg=2.0, valve={"ramp_s": 0.02})


def test_from_dict_unknown_key_raises_valueerror():
    with pytest.raises(ValueError):
        RigParams.from_dict({"no_such_group": {}})


def test_to_dict_survives_a_json_round_trip():
    p = _non_default_rig()
    assert RigParams.from_dict(json.loads(json.dumps(p.to_dict()))) == p


# ------------------------------------------------------------------------------------------
# measured-run format: the rig section
# ------------------------------------------------------------------------------------------
#: MEASUREMENT_FORMAT.md `rig` keys -> (group, field), written from the format document.
RIG_KEYS = {
    "bore_m": ("cylinder", "bore_m", 0.1),
    "rod_m": ("cylinder", "rod_m", 0.025),
    "stroke_m": ("cylinder", "stroke_m", 0.2),
    "dead_volume_m3": ("cylinder", "dead_volume_m3", 4.2e-5),
    "line_length_m": ("line", "length_m", 1.2),
    "line_diameter_m": ("line", "diameter_m", 0.006),
    "valve_area_m2": ("valve", "area_m2", 2.3e-5),
    "port_area_m2": ("cylinder", "port_area_m2", 2.4e-5),
    "exhaust_area_m2": ("valve", "exhaust_area_m2", 2.5e-5),
    "cushion_length_m": ("cylinder", "cushion_length_m", 0.011),
    "cushion_factor_drive": ("cylinder", "cushion_factor_drive", 0.27),
    "cushion_factor_exhaust": ("cylinder", "cushion_factor_exhaust", 0.09),
    "discharge_coefficient": ("valve", "discharge_coefficient", 0.69),
    "valve_delay_s": ("valve", "delay_s", 0.17),
    "moving_mass_extra_kg": ("cylinder", "moving_mass_extra_kg", 1.7),
}
FRICTION_KEYS = {"static_n": 310.0, "coulomb_n": 111.0, "viscous_n_s_per_m": 1401.0}


def _full_meta() -> dict:
    rig = {k: v for k, (_, _, v) in RIG_KEYS.items()}
    rig["friction"] = dict(FRICTION_KEYS)
    return {"format": "pneugym-measurement/1", "supply_pressure_gauge_pa": 150_000,
            "load_mass_kg": 7.0, "ambient_pressure_pa": 100_500, "ambient_temperature_k": 296.0,
            "sample_rate_hz": 1000, "rig": rig, "description": "conventional"}


def test_from_measurement_maps_every_rig_key():
    p = RigParams.from_measurement(_full_meta())
    for key, (group, name, value) in RIG_KEYS.items():
        assert getattr(getattr(p, group), name) == value, key
        assert getattr(getattr(RigParams(), group), name) != value, f"test value for {key} is the default"
    for key, value in FRICTION_KEYS.items():
        assert getattr(p.friction, key) == value
    assert p.supply_pressure_gauge_pa == 150_000.0
    assert p.load_mass_kg == 7.0
    assert p.gas.ambient_pressure_pa == 100_500.0
    assert p.gas.ambient_temperature_k == 296.0
    assert p.valve_delay_s == 0.17
    assert p.moving_mass_kg == pytest.approx(7.0 + 1.7)
    # what the format does not describe keeps the default
    d = RigParams()
    assert p.line.n_cells == d.line.n_cells and p.line.model == d.line.model
    assert p.effects == d.effects and p.solver == d.solver
    assert p.cylinder.cushion_ramp_m == d.cylinder.cushion_ramp_m
    assert p.gas.gamma == d.gas.gamma


def test_from_measurement_matches_the_documented_example():
    meta = {"format": "pneugym-measurement/1", "supply_pressure_gauge_pa": 250000,
            "load_mass_kg": 10.0, "rig": {"bore_m": 0.125, "rod_m": 0.032, "stroke_m": 0.18,
                                          "friction": {"static_n": 359}}}
    p = RigParams.from_measurement(meta)
    assert (p.cylinder.bore_m, p.cylinder.rod_m, p.cylinder.stroke_m) == (0.125, 0.032, 0.18)
    assert p.friction.static_n == 359


@pytest.mark.parametrize("rig", [None, {}, "absent"])
def test_from_measurement_without_rig_keeps_defaults(rig):
    meta = {"format": "pneugym-measurement/1"}
    if rig != "absent":
        meta["rig"] = rig
    assert RigParams.from_measurement(meta) == RigParams()


def test_from_measurement_partial_rig_keeps_the_rest():
    p = RigParams.from_measurement({"rig": {"bore_m": 0.1, "friction": {"coulomb_n": 100.0}}})
    assert p == RigParams().with_(cylinder={"bore_m": 0.1}, friction={"coulomb_n": 100.0})


def test_from_measurement_keeps_the_given_base():
    base = RigParams().with_(line={"n_cells": 8}, friction={"static_n": 200.0}, load_mass_kg=3.0)
    p = RigParams.from_measurement({"rig": {"stroke_m": 0.15}}, base=base)
    assert p == base.with_(cylinder={"stroke_m": 0.15})


def test_from_measurement_ignores_unknown_top_level_keys_but_refuses_unknown_rig_keys():
    meta = _full_meta()
    meta["unknown_top"] = 1.0
    assert RigParams.from_measurement(meta) == RigParams.from_measurement(_full_meta())
    for section, key, nearest in (("rig", "bore", "bore_m"), ("rig", "n_cells", None),
                                  ("friction", "static", "static_n")):
        meta = _full_meta()
        (meta["rig"] if section == "rig" else meta["rig"]["friction"])[key] = 3.0
        with pytest.raises(ValueError, match=rf"{key} is unknown" + (
                rf".*did you mean '{nearest}'" if nearest else "")):
            RigParams.from_measurement(meta)


@pytest.mark.parametrize("meta,pattern", [
    ({"supply_pressure_gauge_pa": "2e5"}, r"supply_pressure_gauge_pa = '2e5'.*finite number"),
    ({"load_mass_kg": None}, r"load_mass_kg = None"),
    ({"rig": [1]}, r"key 'rig' must be an object"),
    ({"rig": {"friction": 3}}, r"rig.friction' must be an object"),
    ([("rig", {})], r"must be an object"),
])
def test_from_measurement_refuses_strings_none_and_wrong_types(meta, pattern):
    with pytest.raises(ValueError, match=pattern):
        RigParams.from_measurement(meta)


def test_from_measurement_validates_values():
    with pytest.raises(ValueError, match=r"CylinderParams\.bore_m"):
        RigParams.from_measurement({"rig": {"bore_m": -0.1}})
    with pytest.raises(ValueError, match=r"RigParams\.supply_pressure_gauge_pa"):
        RigParams.from_measurement({"supply_pressure_gauge_pa": -1e5})


def test_to_measurement_rig_has_exactly_the_documented_keys():
    rig = RigParams().to_measurement_rig()
    assert set(rig) == set(RIG_KEYS) | {"friction"}
    assert set(rig["friction"]) == set(FRICTION_KEYS)


def test_to_measurement_rig_round_trips_through_from_measurement():
    p = _non_default_rig()  # explicit valve delay
    meta = {"supply_pressure_gauge_pa": p.supply_pressure_gauge_pa, "load_mass_kg": p.load_mass_kg,
            "ambient_pressure_pa": p.gas.ambient_pressure_pa,
            "ambient_temperature_k": p.gas.ambient_temperature_k,
            "rig": json.loads(json.dumps(p.to_measurement_rig()))}
    back = RigParams.from_measurement(meta, base=p.with_(cylinder={"bore_m": 0.3, "rod_m": 0.0},
                                                         friction={"static_n": 1.0}, load_mass_kg=0.0))
    assert back == p


def test_to_measurement_rig_round_trip_with_interpolated_delay():
    """A default rig (delay from the supply pressure) comes back with the delay made explicit:
    every rig value is the same, and so is the delay the plant will use."""
    p = RigParams()
    back = RigParams.from_measurement({"rig": p.to_measurement_rig()})
    assert back.to_measurement_rig() == p.to_measurement_rig()
    assert back.valve_delay_s == p.valve_delay_s
    assert back == p.with_(valve={"delay_s": p.valve_delay_s})


# ------------------------------------------------------------------------------------------
# valve delay (thesis Fig. 3.6)
# ------------------------------------------------------------------------------------------
def test_thesis_valve_delay_points():
    assert THESIS_VALVE_DELAY == ((150_000.0, 0.215), (250_000.0, 0.185))
    assert RigParams(supply_pressure_gauge_pa=150_000.0).valve_delay_s == pytest.approx(0.215, abs=1e-12)
    assert RigParams(supply_pressure_gauge_pa=250_000.0).valve_delay_s == pytest.approx(0.185, abs=1e-12)


@pytest.mark.parametrize("gauge", [150_000.0, 175_000.0, 200_000.0, 212_345.0, 250_000.0])
def test_valve_delay_is_linear_between_the_thesis_points(gauge):
    expected = np.interp(gauge, [150_000.0, 250_000.0], [0.215, 0.185])
    assert ValveParams().delay_for(gauge) == pytest.approx(expected, abs=1e-12)
    assert RigParams(supply_pressure_gauge_pa=gauge).valve_delay_s == pytest.approx(expected, abs=1e-12)


def test_valve_delay_extrapolates_then_clips_to_its_bounds():
    v = ValveParams()
    slope = (0.185 - 0.215) / 100_000.0
    # linear outside the thesis points (documented: "linear, clipped to [0.05, 0.4] s") ...
    assert v.delay_for(100_000.0) == pytest.approx(0.215 - 50_000.0 * slope, abs=1e-12)
    assert v.delay_for(400_000.0) == pytest.approx(0.185 + 150_000.0 * slope, abs=1e-12)
    # ... and clipped
    assert v.delay_for(1.9e6) == 0.05
    assert v.delay_for(-1e7) == 0.4
    gauges = np.linspace(-2e6, 2e6, 401)
    delays = np.array([v.delay_for(g) for g in gauges])
    assert np.all((delays >= 0.05) & (delays <= 0.4))
    assert np.all(np.diff(delays) <= 0.0), "delay falls with supply pressure"


def test_explicit_delay_overrides_interpolation():
    for gauge in (1e5, 1.5e5, 2.5e5, 6e5):
        p = RigParams(supply_pressure_gauge_pa=gauge, valve=ValveParams(delay_s=0.123))
        assert p.valve_delay_s == 0.123
    assert ValveParams(delay_s=0.0).delay_for(2e5) == 0.0


# ------------------------------------------------------------------------------------------
# effects
# ------------------------------------------------------------------------------------------
def test_effects_default_is_all_off():
    assert EffectParams().active == ()


@pytest.mark.parametrize("changes,name", [
    ({"leak_drive_area_m2": 1e-8}, "leakage"),
    ({"leak_piston_area_m2": 1e-8}, "leakage"),
    ({"leak_drive_laminar_m3": 1e-15}, "leakage"),
    ({"heat_transfer_time_constant_s": 0.5}, "heat_transfer"),
    ({"stribeck_force_n": 50.0}, "stribeck_friction"),
    ({"sensor_lag_s": 0.015}, "sensor_lag"),
    ({"dead_volume_m3": 1e-5}, "dead_volume"),
])
def test_effects_active_names(changes, name):
    assert EffectParams(**changes).active == (name,)


def test_effects_active_lists_all_and_ignores_secondary_parameters():
    assert EffectParams(stribeck_velocity_m_s=0.5).active == ()
    e = EffectParams(leak_drive_area_m2=1e-8, leak_piston_area_m2=1e-8,
                     heat_transfer_time_constant_s=1.0, stribeck_force_n=1.0, sensor_lag_s=0.01,
                     dead_volume_m3=1e-6)
    assert set(e.active) == {"leakage", "heat_transfer", "stribeck_friction", "sensor_lag",
                             "dead_volume"}
    assert len(e.active) == 5


# ------------------------------------------------------------------------------------------
# careless input: None, wrong group types, typos, unit slips (each refused with a clear message)
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls,name", [(RigParams, "load_mass_kg"), (CylinderParams, "bore_m"),
                                      (FrictionParams, "static_n"), (GasParams, "gamma")])
def test_none_in_a_number_field_is_a_valueerror_naming_it(cls, name):
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.{name} = None.*finite number"):
        cls(**{name: None})


def test_none_in_a_string_field_says_string():
    with pytest.raises(ValueError, match=r"LineParams\.model = None.*a string"):
        LineParams(model=None)


def test_none_where_allowed_is_accepted():
    assert ValveParams(delay_s=None).delay_s is None and SolverParams(dt_s=None).dt_s is None


@pytest.mark.parametrize("group,value", [("cylinder", 0.1), ("friction", None), ("gas", "air"),
                                         ("valve", FrictionParams())])
def test_a_group_that_is_not_its_dataclass_or_a_dict_is_refused(group, value):
    with pytest.raises(ValueError, match=rf"RigParams\.{group} = .*must be"):
        RigParams.from_dict({group: value})
    with pytest.raises(ValueError, match=rf"RigParams\.{group} = "):
        RigParams(**{group: value})


def test_a_number_field_given_a_dict_is_refused():
    with pytest.raises(ValueError, match=r"RigParams\.load_mass_kg"):
        RigParams().with_(load_mass_kg={"kg": 3})


@pytest.mark.parametrize("d,nearest", [({"load_mass": 3.0}, "load_mass_kg"),
                                       ({"cylinder": {"bore": 0.1}}, "bore_m"),
                                       ({"friction": {"static": 300.0}}, "static_n"),
                                       ({"cylindre": {}}, "cylinder")])
def test_typos_are_refused_with_the_nearest_name(d, nearest):
    with pytest.raises(ValueError, match=rf"did you mean '{nearest}'"):
        RigParams.from_dict(d)


def test_from_dict_of_a_non_mapping_is_a_valueerror():
    with pytest.raises(ValueError, match="mapping"):
        RigParams.from_dict([("load_mass_kg", 2.0)])


@pytest.mark.parametrize("changes,pattern", [
    ({"cylinder": {"bore_m": 125.0}}, r"bore_m = 125.0 is not plausible.*mm given as m"),
    ({"cylinder": {"stroke_m": 180.0}}, r"stroke_m = 180.0 is not plausible.*mm given as m"),
    ({"cylinder": {"port_area_m2": 38.9}}, r"port_area_m2.*mm² given as m²"),
    ({"cylinder": {"dead_volume_m3": 0.5}}, r"dead_volume_m3.*litres"),
    ({"valve": {"area_m2": 15.6}}, r"ValveParams\.area_m2.*mm² given as m²"),
    ({"valve": {"delay_s": 185.0}}, r"delay_s.*ms given as s"),
    ({"line": {"diameter_m": 5.0}}, r"diameter_m.*mm given as m"),
    ({"gas": {"ambient_pressure_pa": 1.01325}}, r"ambient_pressure_pa.*bar given as Pa"),
    ({"gas": {"ambient_temperature_k": 20.0}}, r"ambient_temperature_k.*°C given as K"),
    ({"supply_pressure_gauge_pa": 2.5}, r"supply_pressure_gauge_pa = 2.5.*2.5 bar = 250000 Pa"),
    ({"load_mass_kg": 1e300}, r"load_mass_kg.*not plausible"),
])
def test_unit_slips_are_refused_with_the_likely_unit(changes, pattern):
    with pytest.raises(ValueError, match=pattern):
        RigParams().with_(**changes)


def test_a_rig_that_can_never_move_says_why():
    """0.2 bar on the thesis rig gives ~230 N, below the 359 N breakaway."""
    assert "can never move" in RigParams(supply_pressure_gauge_pa=20_000.0).cannot_move()
    assert "static friction" in RigParams().with_(friction={"static_n": 1e5}).cannot_move()
    assert RigParams(supply_pressure_gauge_pa=40_000.0).cannot_move() is None  # ~460 N
    assert RigParams().cannot_move() is None


@pytest.mark.parametrize("cls,kw,pattern", [
    (RigParams, {"supply_pressure_gauge_pa": [2.5e5]}, r"supply_pressure_gauge_pa = \[250000.0\]"),
    (RigParams, {"load_mass_kg": (10,)}, r"load_mass_kg = \(10,\)"),
    (CylinderParams, {"bore_m": [0.1]}, r"bore_m = \[0.1\]"),
    (LineParams, {"model": 3}, r"model = 3.*string"),
])
def test_lists_and_wrong_types_in_number_fields_are_a_valueerror(cls, kw, pattern):
    with pytest.raises(ValueError, match=pattern):
        cls(**kw)


def test_numbers_of_any_real_type_are_stored_as_floats():
    from fractions import Fraction

    a = RigParams(supply_pressure_gauge_pa=Fraction(250000), load_mass_kg=np.float32(10))
    assert a == RigParams() and hash(a) == hash(RigParams())
    assert type(a.supply_pressure_gauge_pa) is float and type(a.load_mass_kg) is float
    assert type(LineParams(n_cells=np.int64(3)).n_cells) is int


@pytest.mark.parametrize("changes,pattern", [
    ({"valve": {"ramp_s": 10.0}}, r"ramp_s.*ms given as s"),
    ({"effects": {"sensor_lag_s": 20.0}}, r"sensor_lag_s.*ms given as s"),
    ({"effects": {"leak_drive_area_m2": 1.0}}, r"leak_drive_area_m2.*mm² given as m²"),
    ({"effects": {"leak_drive_laminar_m3": 1e-6}}, r"leak_drive_laminar_m3.*pi d\^4 / \(128 l\)"),
    ({"effects": {"dead_volume_m3": 5.0}}, r"EffectParams.dead_volume_m3.*litres"),
    ({"line": {"tee_volumes": ((0.1, 4.0),)}}, r"tee_volumes\[0\].*cm³ given as m³"),
    ({"gas": {"viscosity_pa_s": 1.81}}, r"viscosity_pa_s"),
    ({"gas": {"gas_constant_j_per_kg_k": 0.287}}, r"gas_constant_j_per_kg_k.*kJ given as J"),
    ({"solver": {"dt_s": 1e-9}}, r"dt_s.*>= min_dt_s"),
    ({"solver": {"min_dt_s": 1e-12}}, r"min_dt_s"),
    ({"load_mass_kg": 0.0, "cylinder": {"moving_mass_extra_kg": 0.0}}, r"moving mass.*must be > 0"),
])
def test_more_unit_slips_and_impossible_values_are_refused(changes, pattern):
    with pytest.raises(ValueError, match=pattern):
        RigParams().with_(**changes)


def test_malformed_tee_volumes_are_a_valueerror():
    with pytest.raises(ValueError, match="tee_volumes"):
        LineParams(tee_volumes=(0.1, 0.2))
