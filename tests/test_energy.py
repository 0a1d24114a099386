"""Air energy accounting (pneugym/physics/energy.py): thesis eq. 5.9, flow exergy, eq. 5.10."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from pneugym.physics.energy import flow_exergy, potential_energy, saving_ratio

PA = 101_325.0
R, T = 287.0, 293.15


def expansion_work(p, V, pa):
    """Work an isothermal expansion of (p, V) down to pa delivers against the atmosphere,
    integrated numerically: ∫ (p V / V' - pa) dV' from V to V p / pa."""
    v_end = V * p / pa
    w, _ = quad(lambda v: p * V / v - pa, V, v_end, epsabs=0, epsrel=1e-12, limit=200)
    return w


@pytest.mark.parametrize("p,V", [(2.5e5, 1e-3), (3.5e5, 2.3e-3), (1.2e5, 5e-4), (1e6, 1e-5)])
def test_eq_5_9_closed_form_and_expansion_work(p, V):
    expected = p * V * (math.log(p / PA) + PA / p - 1.0)
    assert potential_energy(p, V, PA) == pytest.approx(expected, rel=1e-14)
    assert potential_energy(p, V, PA) == pytest.approx(expansion_work(p, V, PA), rel=1e-9)


def test_zero_at_ambient_and_guarded_at_non_positive_pressure():
    assert potential_energy(PA, 1e-3, PA) == 0.0
    assert potential_energy(0.0, 1e-3, PA) == 0.0
    assert potential_energy(-1e5, 1e-3, PA) == 0.0


@settings(max_examples=200, deadline=None)
@given(p=st.floats(1e3, 2e6), V=st.floats(1e-7, 1e-1))
def test_eq_5_9_is_positive_away_from_ambient(p, V):
    e = potential_energy(p, V, PA)
    assert e >= 0.0
    if abs(p / PA - 1.0) > 1e-3:
        assert e > 0.0


def test_eq_5_9_linear_in_volume_and_increasing_in_pressure_above_ambient():
    assert potential_energy(3e5, 2e-3, PA) == pytest.approx(2 * potential_energy(3e5, 1e-3, PA), rel=1e-14)
    es = [potential_energy(p, 1e-3, PA) for p in (1.1e5, 1.5e5, 2.5e5, 3.5e5, 6e5)]
    assert all(a < b for a, b in zip(es, es[1:]))
    # dE/dp = V ln(p/pa)
    p, V, h = 3e5, 1e-3, 1.0
    dedp = (potential_energy(p + h, V, PA) - potential_energy(p - h, V, PA)) / (2 * h)
    assert dedp == pytest.approx(V * math.log(p / PA), rel=1e-6)


def test_flow_exergy():
    m, p = 0.01, 3.5e5
    assert flow_exergy(m, p, PA, R, T) == pytest.approx(m * R * T * math.log(p / PA), rel=1e-14)
    assert flow_exergy(m, PA, PA, R, T) == 0.0
    assert flow_exergy(2 * m, p, PA, R, T) == pytest.approx(2 * flow_exergy(m, p, PA, R, T), rel=1e-14)
    assert flow_exergy(m, 0.5 * PA, PA, R, T) < 0.0


@pytest.mark.parametrize("p", [1.5e5, 2.5e5, 3.5e5, 8e5])
def test_flow_exergy_exceeds_stored_energy_by_the_flow_work(p):
    """Delivered air carries its flow work p V on top of what it can do expanding in a closed
    volume: exergy(m) - E_5.9(p, V) = (p - pa) V with m = p V / (R T)."""
    V = 1e-3
    m = p * V / (R * T)
    diff = flow_exergy(m, p, PA, R, T) - potential_energy(p, V, PA)
    assert diff == pytest.approx((p - PA) * V, rel=1e-10)


def test_saving_ratio_eq_5_10():
    assert saving_ratio(100.0, 40.0) == pytest.approx(0.6)
    assert saving_ratio(100.0, 100.0) == 0.0
    assert saving_ratio(100.0, 0.0) == 1.0
    assert saving_ratio(80.0, 100.0) < 0.0


def test_a_conventional_episode_on_a_rebounding_rig_saves_nothing():
    """A family rig whose stiff exhaust cushion pushes the piston back from the end: with the
    supply kept, the wasted energy is the filled driving side at the full stroke (where the
    supply brings the piston back), so a never-cut episode saves nothing and returns -1."""
    from pneugym.envs.cutoff import CutOffEnv

    env = CutOffEnv(preset="family")
    env.reset(seed=105)
    done, ret = False, 0.0
    while not done:
        _, r, term, trunc, info = env.step(0)
        ret += r
        done = term or trunc
    assert info["position_m"] < env.rig.cylinder.stroke_m - 1e-3  # the rebound this test needs
    assert info["saving_ratio"] == 0.0
    assert ret == pytest.approx(-1.0 - env.weights["w_stick"] * info["stick_slip_events"], abs=1e-12)
