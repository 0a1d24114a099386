"""Tests of :mod:`pneugym.envs.conditions`: validation of :class:`Conditions` and
:class:`ConditionSpace`, the presets' ranges, seeded draws, and that every condition reaches the
plant the environment steps."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pneugym import RigParams
from pneugym.envs import PRESETS, Conditions, ConditionSpace, conventional_figures
from pneugym.envs.conditions import fixed, resolve
from pneugym.envs.cutoff import CutOffEnv
from pneugym.physics import layout as L


# --- Conditions -----------------------------------------------------------------------------
@pytest.mark.parametrize("field, value", [
    ("supply_pressure_gauge_pa", 0.0), ("supply_pressure_gauge_pa", -1e5),
    ("load_mass_kg", -1.0), ("friction_scale", -0.1), ("valve_delay_scale", 0.0),
    ("dip_start_s", -0.1), ("dip_duration_s", -0.1), ("dip_depth", 1.0), ("dip_depth", -0.1),
    ("position_noise_m", -1e-5), ("pressure_noise_pa", -1.0), ("load_mass_kg", math.nan),
    ("supply_pressure_gauge_pa", math.inf),
])
def test_conditions_reject_bad_fields_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        Conditions(**{field: value})


def test_conditions_reject_non_numbers_with_value_error():
    with pytest.raises(ValueError, match="load_mass_kg"):
        Conditions(load_mass_kg="10")


def test_conditions_defaults_are_the_nominal_rig():
    c = Conditions()
    assert c.supply_bar_gauge == pytest.approx(2.5)
    assert c.load_mass_kg == 10.0
    assert c.dip == (0.0, 0.0, 0.0)
    assert Conditions(**c.to_dict()) == c
    # noise does not change the motion
    assert Conditions(pressure_noise_pa=100.0).physics_key() == c.physics_key()
    assert Conditions(load_mass_kg=11.0).physics_key() != c.physics_key()


def test_noise_free_keeps_the_physics_and_drops_only_the_noise():
    c = Conditions(load_mass_kg=12.0, position_noise_m=3e-5, pressure_noise_pa=400.0,
                   rig_changes=(("line.length_m", 2.0),))
    q = c.noise_free()
    assert (q.position_noise_m, q.pressure_noise_pa) == (0.0, 0.0)
    assert q.physics_key() == c.physics_key()
    assert q == Conditions(**{**c.to_dict(), "position_noise_m": 0.0, "pressure_noise_pa": 0.0})


def test_conditions_rig_scales_friction_and_valve_delay():
    base = RigParams()
    rig = Conditions(supply_pressure_gauge_pa=3e5, load_mass_kg=20.0, friction_scale=1.3,
                     valve_delay_scale=0.8).rig(base)
    assert rig.supply_pressure_gauge_pa == 3e5
    assert rig.load_mass_kg == 20.0
    assert rig.friction.static_n == pytest.approx(1.3 * base.friction.static_n)
    assert rig.friction.coulomb_n == pytest.approx(1.3 * base.friction.coulomb_n)
    assert rig.friction.viscous_n_s_per_m == pytest.approx(1.3 * base.friction.viscous_n_s_per_m)
    # the delay is scaled at the episode's own supply pressure
    at3 = base.with_(supply_pressure_gauge_pa=3e5)
    assert rig.valve_delay_s == pytest.approx(0.8 * at3.valve_delay_s)


# --- ConditionSpace -------------------------------------------------------------------------
def test_space_rejects_bad_ranges_by_name():
    with pytest.raises(ValueError, match="load_mass_kg"):
        ConditionSpace(load_mass_kg=(30.0, 5.0))
    with pytest.raises(ValueError, match="friction_scale"):
        ConditionSpace(friction_scale=(0.5, math.nan))
    with pytest.raises(ValueError, match="dip_probability"):
        ConditionSpace(dip_probability=1.5)
    with pytest.raises(ValueError, match="dip_depth"):  # an extreme that is no valid Conditions
        ConditionSpace(dip_depth=(0.0, 1.2))
    with pytest.raises(ValueError, match="supply_pressure_gauge_pa"):
        ConditionSpace(supply_pressure_gauge_pa="high")
    with pytest.raises(ValueError, match="nonsense"):
        ConditionSpace().with_(nonsense=1.0)


def test_space_sample_is_seeded_and_fixed_space_is_constant():
    space = PRESETS["randomized"]
    a = [space.sample(np.random.default_rng(7)) for _ in range(3)]
    b = [space.sample(np.random.default_rng(7)) for _ in range(3)]
    assert a == b
    rng = np.random.default_rng(7)
    assert space.sample(rng) != space.sample(rng)
    c = Conditions(load_mass_kg=12.0, dip_start_s=0.2, dip_duration_s=0.1, dip_depth=0.2)
    sp = fixed(c)
    rng = np.random.default_rng(0)
    assert all(sp.sample(rng) == c for _ in range(5))
    rng = np.random.default_rng(1)
    assert len({PRESETS["thesis-1.5bar"].sample(rng) for _ in range(5)}) == 1
    assert len({PRESETS["randomized"].sample(rng) for _ in range(5)}) == 5


def test_randomized_preset_stays_in_the_issue_ranges():
    space = PRESETS["randomized"]
    rng = np.random.default_rng(123)
    draws = [space.sample(rng) for _ in range(400)]
    load = np.array([c.load_mass_kg for c in draws])
    supply = np.array([c.supply_pressure_gauge_pa for c in draws])
    fric = np.array([c.friction_scale for c in draws])
    depth = np.array([c.dip_depth for c in draws])
    dur = np.array([c.dip_duration_s for c in draws])
    assert load.min() >= 5.0 and load.max() <= 30.0
    assert supply.min() >= 1.5e5 and supply.max() <= 5e5
    assert fric.min() >= 0.7 and fric.max() <= 1.3
    assert depth.min() >= 0.0 and depth.max() <= 0.3
    assert dur.max() <= 0.3
    # the ranges are actually covered, not just respected
    assert load.min() < 7 and load.max() > 28
    assert supply.min() < 1.8e5 and supply.max() > 4.7e5
    assert fric.min() < 0.75 and fric.max() > 1.25
    dipped = dur > 0
    assert 0.35 < dipped.mean() < 0.65
    assert depth[dipped].max() > 0.25 and dur[dipped].max() > 0.25
    assert np.all(depth[~dipped] == 0.0)


def test_thesis_presets():
    assert PRESETS["thesis-1.5bar"].sample(np.random.default_rng(0)) == \
        Conditions(supply_pressure_gauge_pa=1.5e5)
    assert PRESETS["thesis-2.5bar"].sample(np.random.default_rng(0)) == Conditions()


def test_resolve():
    assert resolve(None) == PRESETS["thesis-2.5bar"]
    assert resolve("randomized") is PRESETS["randomized"]
    c = Conditions(load_mass_kg=20.0)
    assert resolve(c).sample(np.random.default_rng(0)) == c
    sp = resolve("thesis-1.5bar", {"load_mass_kg": (5.0, 6.0)})
    assert sp.load_mass_kg == (5.0, 6.0)
    assert sp.supply_pressure_gauge_pa == (1.5e5, 1.5e5)
    with pytest.raises(ValueError, match="thesis-9bar"):
        resolve("thesis-9bar")
    with pytest.raises(ValueError, match="preset"):
        resolve(42)


# --- conditions reach the plant -------------------------------------------------------------
def test_dip_slows_the_conventional_stroke():
    rig = Conditions().rig()
    t0, e0 = conventional_figures(rig)
    t_dip, e_dip = conventional_figures(rig, (0.3, 0.3, 0.3))
    assert t_dip > t0 + 0.01
    assert e_dip == pytest.approx(e0)  # closed form: filled to the (restored) supply
    assert conventional_figures(rig, (0.3, 0.3, 0.3)) == (t_dip, e_dip)  # cached, deterministic


def _conventional_episode(cond: Conditions) -> tuple[CutOffEnv, dict]:
    env = CutOffEnv()
    env.reset(seed=0, options={"conditions": cond})
    while True:
        _, _, term, trunc, info = env.step(0)
        if term or trunc:
            return env, info


def test_conditions_reach_the_env_plant():
    nominal, info0 = _conventional_episode(Conditions())
    t0 = info0["stroke_time_s"]
    env, info = _conventional_episode(Conditions(friction_scale=1.3))
    assert env.P[0, L.P_FS] == pytest.approx(1.3 * nominal.P[0, L.P_FS])
    # (a higher breakaway force builds up more pressure first: the stroke is not slower)
    assert abs(info["stroke_time_s"] - t0) > 1e-3
    env, info = _conventional_episode(Conditions(valve_delay_scale=1.2))
    assert env.P[0, L.P_DELAY] == pytest.approx(1.2 * nominal.P[0, L.P_DELAY])
    assert info["stroke_time_s"] > t0
    env, info = _conventional_episode(Conditions(dip_start_s=0.3, dip_duration_s=0.3,
                                                 dip_depth=0.3))
    assert (env.P[0, L.P_DIP_T0], env.P[0, L.P_DIP_DUR], env.P[0, L.P_DIP_DEPTH]) == \
        pytest.approx((0.3, 0.3, 0.3))
    assert info["stroke_time_s"] > t0 + 0.01
    # the conventional figures follow the episode's own conditions: still no time increase
    assert info["conventional_stroke_time_s"] == pytest.approx(info["stroke_time_s"], rel=1e-3)
    env, info = _conventional_episode(Conditions(load_mass_kg=25.0, supply_pressure_gauge_pa=2e5))
    assert env.P[0, L.P_MASS] > nominal.P[0, L.P_MASS]
    assert info["energy_conventional_j"] < info0["energy_conventional_j"]


def test_an_operating_point_outside_a_space_is_named():
    space = PRESETS["randomized"]
    assert space.outside(250_000.0, 10.0) == []
    assert space.outside(500_000.0, 30.0) == []           # the edges are inside
    assert space.outside(600_000.0, 40.0) == ["supply 6 bar g outside 1.5-5",
                                              "load 40 kg outside 5-30"]
    assert space.outside(100_000.0, 10.0) == ["supply 1 bar g outside 1.5-5"]
    assert resolve("family", {"load_mass_kg": [2.0, 50.0]}).outside(250_000.0, 45.0) == []
