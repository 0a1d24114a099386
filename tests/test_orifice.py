"""Orifice mass flow (pneugym/physics/orifice.py): thesis eqs. 4.1-4.3 and ISO 6358.

The reference formulas are written here again with numpy, independently of the kernel."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pneugym.physics import orifice as O

GAMMA, R, T = 1.4, 287.0, 293.15
SQRT_T = math.sqrt(T)
LIN = 0.02
CDA = 0.72 * 1.9635e-5
OC = O.orifice_constants(GAMMA, R, 0.0, 0.528, LIN)


def cm_thesis(r):
    """Thesis eq. 4.2 flow parameter (numpy, independent of the kernel)."""
    r = np.asarray(r, dtype=float)
    return np.sqrt(2.0 * GAMMA / (R * (GAMMA - 1.0)) * (r ** (2.0 / GAMMA) - r ** ((GAMMA + 1.0) / GAMMA)))


CM_STAR = float(cm_thesis(0.528))


def flow(p_up, p_dn, oc=OC, cda=CDA, sTa=SQRT_T, sTb=SQRT_T):
    return O.mass_flow(float(p_up), float(p_dn), cda, sTa, sTb, oc)


def test_choked_flow_parameter_is_00404_thesis_00405():
    assert OC[O.OC_CM_STAR] == pytest.approx(CM_STAR, rel=1e-12)
    assert OC[O.OC_CM_STAR] == pytest.approx(0.0404, abs=1e-4)
    assert OC[O.OC_CM_STAR] == pytest.approx(0.0405, rel=5e-3)  # thesis's rounded value


@pytest.mark.parametrize("r", [1e-6, 0.01, 0.2, 0.4, 0.5, 0.527, 0.528])
@pytest.mark.parametrize("p_up", [2e5, 6e5, 1.5e6])
def test_choked_flow(r, p_up):
    expected = CDA * CM_STAR * p_up / SQRT_T
    assert flow(p_up, r * p_up) == pytest.approx(expected, rel=1e-12)
    assert flow(p_up, 0.0) == pytest.approx(expected, rel=1e-12)  # vacuum downstream


@pytest.mark.parametrize("r", np.linspace(0.5285, 1.0 - LIN, 25))
def test_subsonic_flow_matches_thesis_eq_4_2(r):
    p_up = 4e5
    expected = CDA * p_up / SQRT_T * cm_thesis(r)
    assert flow(p_up, r * p_up) == pytest.approx(float(expected), rel=1e-10)


def test_flow_scales_with_area_and_upstream_temperature():
    p_up, p_dn = 5e5, 4e5
    base = flow(p_up, p_dn)
    assert flow(p_up, p_dn, cda=2 * CDA) == pytest.approx(2 * base, rel=1e-14)
    # upstream temperature 4x -> flow / 2; downstream temperature is irrelevant
    assert flow(p_up, p_dn, sTa=2 * SQRT_T) == pytest.approx(base / 2, rel=1e-14)
    assert flow(p_up, p_dn, sTb=2 * SQRT_T) == base
    # reversed: the upstream side is now b
    assert flow(p_dn, p_up, sTb=2 * SQRT_T) == pytest.approx(-base / 2, rel=1e-14)
    assert flow(p_up, p_dn, cda=0.0) == 0.0


def test_continuity_at_the_critical_ratio():
    p_up = 5e5
    at = flow(p_up, 0.528 * p_up)
    for eps in (1e-6, 1e-9, 1e-12):
        assert flow(p_up, (0.528 + eps) * p_up) == pytest.approx(at, rel=1e-7)
        assert flow(p_up, (0.528 - eps) * p_up) == pytest.approx(at, rel=1e-12)


@pytest.mark.parametrize("lin", [1e-3, 0.02, 0.1])
def test_linear_zone_is_continuous_and_linear(lin):
    oc = O.orifice_constants(GAMMA, R, 0.0, 0.528, lin)
    p_up = 3e5
    edge = 1.0 - lin
    at = flow(p_up, edge * p_up, oc=oc)
    assert at == pytest.approx(CDA * p_up / SQRT_T * float(cm_thesis(edge)), rel=1e-10)
    for eps in (1e-7, 1e-10):
        assert flow(p_up, (edge - eps) * p_up, oc=oc) == pytest.approx(at, rel=1e-4)
        assert flow(p_up, (edge + eps) * p_up, oc=oc) == pytest.approx(at, rel=1e-4)
    # straight line from the edge to zero at equal pressure
    for r in np.linspace(edge, 1.0, 7):
        assert flow(p_up, r * p_up, oc=oc) == pytest.approx(at * (1.0 - r) / lin, rel=1e-9, abs=1e-18)


def test_linear_conductance_is_the_slope_in_the_linear_zone_and_an_upper_bound():
    p_up = 4e5
    g = O.linear_conductance(p_up, CDA, T, OC)
    h = 1.0
    p_dn = 0.995 * p_up
    slope = -(flow(p_up, p_dn + h) - flow(p_up, p_dn - h)) / (2 * h)
    assert slope == pytest.approx(g, rel=1e-6)
    r = np.linspace(0.3, 1.0, 2001)
    f = np.array([flow(p_up, x * p_up) for x in r])
    slopes = -np.diff(f) / np.diff(r * p_up)
    assert slopes.max() <= g * (1 + 1e-6)


@pytest.mark.parametrize("p", [1e3, 101_325.0, 5e5, 2e6])
def test_zero_flow_at_equal_pressure(p):
    assert flow(p, p) == 0.0
    assert flow(p, p, sTa=10.0, sTb=20.0) == 0.0


pressures = st.floats(min_value=1e3, max_value=2e6, allow_nan=False, allow_infinity=False)
sqrt_temps = st.floats(min_value=math.sqrt(200.0), max_value=math.sqrt(500.0))


@settings(max_examples=300, deadline=None)
@given(a=pressures, b=pressures, sTa=sqrt_temps, sTb=sqrt_temps,
       model=st.sampled_from([0.0, 1.0]), iso_b=st.floats(0.0, 0.9))
def test_antisymmetry(a, b, sTa, sTb, model, iso_b):
    oc = O.orifice_constants(GAMMA, R, model, iso_b, LIN)
    fwd = O.mass_flow(a, b, CDA, sTa, sTb, oc)
    assert fwd == -O.mass_flow(b, a, CDA, sTb, sTa, oc)
    assert np.sign(fwd) == np.sign(a - b)


@settings(max_examples=300, deadline=None)
@given(p_up=pressures, r1=st.floats(0.0, 1.0), r2=st.floats(0.0, 1.0),
       model=st.sampled_from([0.0, 1.0]), iso_b=st.floats(0.0, 0.9),
       lin=st.floats(1e-4, 0.2))
def test_monotone_in_downstream_pressure(p_up, r1, r2, model, iso_b, lin):
    """More downstream pressure never gives more flow. Tolerance 2e-7 relative: with the thesis
    law the flow rises by up to 1.74e-7 between r = 0.528 and the true critical ratio 0.52828
    (see test_thesis_law_sliver_above_0528; the former 1e-7 failed on a random draw)."""
    oc = O.orifice_constants(GAMMA, R, model, iso_b, lin)
    lo, hi = sorted((r1, r2))
    f_lo = O.mass_flow(p_up, lo * p_up, CDA, SQRT_T, SQRT_T, oc)
    f_hi = O.mass_flow(p_up, hi * p_up, CDA, SQRT_T, SQRT_T, oc)
    assert f_hi <= f_lo * (1.0 + 2e-7)
    assert f_hi >= 0.0


@settings(max_examples=200, deadline=None)
@given(p_dn=pressures, k1=st.floats(1.0, 20.0), k2=st.floats(1.0, 20.0),
       model=st.sampled_from([0.0, 1.0]))
def test_monotone_in_upstream_pressure(p_dn, k1, k2, model):
    oc = O.orifice_constants(GAMMA, R, model, 0.528, LIN)
    lo, hi = sorted((k1, k2))
    assert flow(hi * p_dn, p_dn, oc=oc) >= flow(lo * p_dn, p_dn, oc=oc)


@pytest.mark.xfail(strict=True, reason="SUSPICIOUS (tiny): thesis law chokes at r = 0.528 but "
                   "eq. 4.2 peaks at (2/(γ+1))^(γ/(γ-1)) = 0.52828, so the flow rises by up to 1.7e-7 "
                   "relative when the downstream pressure rises across (0.528, 0.52828)")
def test_thesis_law_sliver_above_0528():
    p_up = 5e5
    assert flow(p_up, 0.5281 * p_up) <= flow(p_up, 0.528 * p_up)


# ------------------------------------------------------------------------------------------
# ISO 6358
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("b", [0.2, 0.3, 0.528])
def test_iso6358(b):
    oc = O.orifice_constants(GAMMA, R, 1.0, b, LIN)
    p_up = 5e5
    choked = CDA * CM_STAR * p_up / SQRT_T
    # choked region: the thesis choked value
    for r in np.linspace(0.0, b, 9):
        assert flow(p_up, r * p_up, oc=oc) == pytest.approx(choked, rel=1e-12)
    # elliptic above b (outside the linear zone)
    for r in np.linspace(b + 1e-3, 1.0 - LIN, 17):
        expected = choked * math.sqrt(1.0 - ((r - b) / (1.0 - b)) ** 2)
        assert flow(p_up, r * p_up, oc=oc) == pytest.approx(expected, rel=1e-10)
    # continuous at b and at the linear-zone edge, zero at r = 1
    assert flow(p_up, (b + 1e-9) * p_up, oc=oc) == pytest.approx(choked, rel=1e-6)
    edge = flow(p_up, (1 - LIN) * p_up, oc=oc)
    assert flow(p_up, (1 - LIN + 1e-9) * p_up, oc=oc) == pytest.approx(edge, rel=1e-5)
    assert flow(p_up, p_up, oc=oc) == 0.0


def test_iso6358_at_the_thesis_ratio_differs_from_the_thesis_law_only_in_shape():
    oc_iso = O.orifice_constants(GAMMA, R, 1.0, 0.528, LIN)
    p_up = 5e5
    for r in (0.1, 0.528):
        assert flow(p_up, r * p_up, oc=oc_iso) == pytest.approx(flow(p_up, r * p_up), rel=1e-12)
    # same endpoints, different curve in between
    assert flow(p_up, 0.8 * p_up, oc=oc_iso) != pytest.approx(flow(p_up, 0.8 * p_up), rel=1e-3)


def test_flow_parameter_matches_mass_flow_outside_the_linear_zone():
    for model, b in ((0.0, 0.528), (1.0, 0.35)):
        oc = O.orifice_constants(GAMMA, R, model, b, LIN)
        for r in np.linspace(0.05, 1 - LIN, 12):
            assert flow(2e5, r * 2e5, oc=oc) == pytest.approx(
                CDA * 2e5 / SQRT_T * O.flow_parameter(r, oc), rel=1e-14)


# --- derivatives and the implicit stage solve (the plant's IMEX substep) ---------------------
@pytest.mark.parametrize("model", [0.0, 1.0])
@pytest.mark.parametrize("r", [0.2, 0.6, 0.8, 0.9, 0.97, 0.995])
def test_flow_derivatives_match_finite_differences(model, r):
    oc = O.orifice_constants(GAMMA, R, model, 0.45, LIN)
    pu = 4e5
    pd = r * pu
    q, d_up, d_dn = O.flow_deriv_fwd(pu, pd, CDA, SQRT_T, oc, 0)
    assert q == pytest.approx(flow(pu, pd, oc), rel=1e-12)
    h = 1e-3
    assert d_up == pytest.approx((flow(pu + h, pd, oc) - flow(pu - h, pd, oc)) / (2 * h), rel=1e-6, abs=1e-16)
    assert d_dn == pytest.approx((flow(pu, pd + h, oc) - flow(pu, pd - h, oc)) / (2 * h), rel=1e-6, abs=1e-16)


@pytest.mark.parametrize("model", [0.0, 1.0])
@pytest.mark.parametrize("pa,pb", [(3.5e5, 1.0e5), (3.5e5, 3.0e5), (3.0e5, 2.95e5), (1.2e5, 3.4e5),
                                   (2e5, 2e5)])
@pytest.mark.parametrize("hg", [1e-6, 1e-4, 1e-3, 1e-1])
@pytest.mark.parametrize("ka,kb", [(2e10, 3e8), (0.0, 2e10)])
def test_implicit_flow_solves_its_stage_equation(model, pa, pb, hg, ka, kb):
    """q = flow(pa - hg ka q, pb + hg kb q), whatever the guess, without crossing the pressures."""
    oc = O.orifice_constants(GAMMA, R, model, 0.45, LIN)
    for guess in (0.0, 1.0, -1.0, 1e-3):
        q = O.implicit_flow(pa, pb, ka, kb, hg, CDA, SQRT_T, SQRT_T, oc, 0, guess)
        a, b = pa - hg * ka * q, pb + hg * kb * q
        f = flow(a, b, oc)
        assert q == pytest.approx(f, rel=1e-6, abs=1e-15)
        assert (a - b) * (pa - pb) >= -1e-9 * pa  # the pressures keep their order
        if pa == pb:
            assert q == 0.0
