"""Supply line (pneugym/physics/line.py) stepped alone by pneugym/physics/testbed.py, held
against analytic results: wall friction factor, mass conservation, the acoustic fundamental,
Hagen-Poiseuille, observed order of convergence, choked charging and isothermal discharge."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pneugym import RigParams
from pneugym.physics import layout as L
from pneugym.physics import testbed
from pneugym.physics.line import friction_factor, wall_friction
from pneugym.physics.orifice import OC_CM_STAR, orifice_constants
from pneugym.plant import CHAIN_H_LAMBDA, RK3_REAL_LIMIT, pack, stability_limits

CLOSED = np.zeros(6)  # both ends closed


def line_setup(n, length=1.0, diameter=0.005, model="fd", **line):
    prm = RigParams().with_(line=dict(n_cells=n, length_m=length, diameter_m=diameter, model=model,
                                      **line))
    P = pack(prm)
    return prm, P, P[L.NP:L.NP + n].copy()


def rt(prm):
    return prm.gas.gas_constant_j_per_kg_k * prm.gas.ambient_temperature_k


# ------------------------------------------------------------------------------------------
# friction factor
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("re", [1.0, 10.0, 100.0, 1000.0, 2000.0, 2300.0])
def test_friction_factor_laminar(re):
    assert friction_factor(re) == pytest.approx(64.0 / re, rel=1e-14)


@pytest.mark.parametrize("re", [4000.0, 5000.0, 1e4, 1e5])
def test_friction_factor_blasius(re):
    assert friction_factor(re) == pytest.approx(0.3164 * re ** -0.25, rel=1e-14)


def test_friction_factor_continuous_through_transition():
    for edge in (2300.0, 4000.0):
        for eps in (1e-6, 1e-9):
            assert friction_factor(edge + eps) == pytest.approx(friction_factor(edge - eps), rel=1e-6)
    re = np.linspace(2300.0, 4000.0, 200)
    f = np.array([friction_factor(x) for x in re])
    lo, hi = sorted((64.0 / 2300.0, 0.3164 * 4000.0 ** -0.25))
    assert np.all((f >= lo - 1e-15) & (f <= hi + 1e-15))
    assert np.all(np.abs(np.diff(f, 2)) < 1e-12), "linear blend in the transition"
    assert friction_factor(0.0) == 0.0


def test_wall_friction_term_laminar_closed_form_and_continuous():
    A, d, mu, inv_rho = math.pi / 4 * 0.005**2, 0.005, 1.81e-5, 1 / 3.0
    q = 1e-5
    assert wall_friction(q, inv_rho, A, d, mu) == pytest.approx(32 * mu * q * inv_rho / d**2, rel=1e-13)
    assert wall_friction(-q, inv_rho, A, d, mu) == -wall_friction(q, inv_rho, A, d, mu)
    q_crit = 2300.0 * A * mu / d  # Re = 2300
    assert wall_friction(q_crit * (1 + 1e-9), inv_rho, A, d, mu) == pytest.approx(
        wall_friction(q_crit * (1 - 1e-9), inv_rho, A, d, mu), rel=1e-6)


# ------------------------------------------------------------------------------------------
# closed tube: mass conservation and the acoustic fundamental
# ------------------------------------------------------------------------------------------
def cosine_tube(n, p0=3e5, eps=1e-3, length=1.0):
    prm, P, vol = line_setup(n, length)
    x = (np.arange(n) + 0.5) / n * length
    y = np.zeros(2 * n - 1)
    y[:n] = p0 * (1.0 + eps * np.cos(np.pi * x / length)) * vol / rt(prm)
    return prm, P, y, x


def mode_amplitude(p, x, length):
    """Projection of the pressure field on cos(pi x / L)."""
    n = len(x)
    return 2.0 / n * np.sum((p - p.mean()) * np.cos(np.pi * x / length))


def test_closed_tube_conserves_mass():
    prm, P, y, x = cosine_tube(32, eps=0.05)
    m0 = y[:32].sum()
    c = math.sqrt(rt(prm))
    testbed.line_run(y, P, CLOSED, 0.5 * (1.0 / 32) / c, 0.03, 100)
    assert abs(y[:32].sum() - m0) <= 1e-12 * m0
    assert np.all(y[:32] > 0)


@pytest.mark.parametrize("n,length", [(32, 1.0), (48, 1.2)])
def test_closed_tube_fundamental_is_c_over_2L(n, length):
    prm, P, y, x = cosine_tube(n, length=length)
    c = math.sqrt(rt(prm))
    dt = 0.5 * (length / n) / c
    t, p = testbed.line_run(y, P, CLOSED, dt, 8 * 2 * length / c, 1)
    a = np.array([mode_amplitude(row, x, length) for row in p])
    s = np.sign(a)
    i = np.flatnonzero(s[:-1] * s[1:] < 0)
    tz = t[i] - a[i] * (t[i + 1] - t[i]) / (a[i + 1] - a[i])  # zero crossings
    assert len(tz) >= 10
    f = 1.0 / (2.0 * np.mean(np.diff(tz)))
    assert f == pytest.approx(c / (2.0 * length), rel=0.01)
    # the wave is (lightly) damped, never amplified
    assert np.abs(a[len(a) // 2:]).max() <= abs(a[0]) * (1 + 1e-9)


def test_observed_order_of_convergence():
    """Joint grid + timestep refinement at a fixed CFL number (0.26): the cos-mode amplitude at
    a fixed time converges at second order (central differences; SSP-RK3 in time)."""
    t_end, steps16 = 0.0045, 80
    amp = {}
    for n in (16, 32, 64, 128):
        prm, P, y, x = cosine_tube(n)
        steps = steps16 * n // 16
        t, p = testbed.line_run(y, P, CLOSED, t_end / steps, t_end, steps)
        assert t[-1] == pytest.approx(t_end, rel=1e-12)
        amp[n] = mode_amplitude(p[-1], x, 1.0)
    e = [amp[16] - amp[32], amp[32] - amp[64], amp[64] - amp[128]]
    orders = [math.log2(abs(e[0] / e[1])), math.log2(abs(e[1] / e[2]))]
    assert min(orders) >= 1.8, orders
    assert abs(e[2]) < 1e-3 * abs(amp[128])


# ------------------------------------------------------------------------------------------
# steady laminar flow: Hagen-Poiseuille
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n,mdot,diameter", [(16, 2e-5, 0.005), (16, 1e-4, 0.005),
                                              (16, 2e-5, 0.004), (4, 5e-5, 0.005)])
def test_steady_laminar_pressure_drop_is_hagen_poiseuille(n, mdot, diameter):
    """Equal mass flows prescribed in at x = 0 and out at x = L; once steady, the pressure drop
    between the end cells is the tube's Hagen-Poiseuille drop 128 mu L Q / (pi d^4) (the line
    lets its n - 1 interior faces carry the wall friction of the whole length, see line.py)."""
    length, p0 = 1.0, 2e5
    prm, P, vol = line_setup(n, length, diameter)
    mu = prm.gas.viscosity_pa_s
    assert 4 * mdot / (math.pi * diameter * mu) < 2000, "laminar"
    y = np.zeros(2 * n - 1)
    y[:n] = p0 * vol / rt(prm)
    y[n:] = mdot  # start with the flow established; the pressure profile develops
    bc = np.array([1.0, mdot, 0.0, 1.0, mdot, 0.0])  # same mass flow in at 0 and out at L
    dt = 0.5 * (length / n) / math.sqrt(rt(prm))
    t, p = testbed.line_run(y, P, bc, dt, 1.5, 50)
    dp = p[:, 0] - p[:, -1]
    tail = dp[t > 1.3]
    assert np.ptp(tail) < 0.01 * tail.mean(), "steady"
    rho = p[-1].mean() / rt(prm)
    q_vol = mdot / rho
    hp = 128.0 * mu * length * q_vol / (math.pi * diameter**4)
    assert tail.mean() == pytest.approx(hp, rel=0.02)
    # the pressure falls linearly along the tube
    assert np.allclose(np.diff(p[-1]), np.diff(p[-1]).mean(), rtol=0.02)
    # mass conserved: same flow in and out
    assert y[:n].sum() == pytest.approx((p0 * vol / rt(prm)).sum(), rel=1e-12)


# ------------------------------------------------------------------------------------------
# one volume: choked charging ramp, isothermal choked discharge
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("model", ["lumped", "fd"])
def test_single_volume_choked_charging_is_a_linear_ramp(model):
    prm, P, vol = line_setup(1, model=model)
    V = vol[0]
    RT = rt(prm)
    ps, cda, p_start = 5e5, 1e-6, 1e5
    cm = orifice_constants(prm.gas.gamma, prm.gas.gas_constant_j_per_kg_k, 0.0, 0.528, 0.02)[OC_CM_STAR]
    mdot = cda * cm * ps / math.sqrt(prm.gas.ambient_temperature_k)
    t_end = 0.9 * (0.528 * ps - p_start) * V / (RT * mdot)  # stays choked
    y = np.array([p_start * V / RT])
    bc = np.array([2.0, ps, cda, 0.0, 0.0, 0.0])  # orifice from the supply; right end closed
    t, p = testbed.line_run(y, P, bc, t_end / 2000, t_end, 20)
    slope = RT * mdot / V
    assert np.allclose(p[:, 0], p_start + slope * t, rtol=1e-9, atol=0)
    assert p[-1, 0] < 0.528 * ps


def test_single_volume_isothermal_choked_discharge_time_constant():
    """dm/dt = -CdA Cm p / sqrt(T), p = m R T / V  =>  p = p0 exp(-t / tau) with
    tau = V / (CdA Cm R sqrt(T)) = V sqrt(T) / (CdA Cm R T), while p > pa / 0.528."""
    prm, P, vol = line_setup(1, model="lumped")
    V, RT = vol[0], rt(prm)
    T = prm.gas.ambient_temperature_k
    pa, p0, cda = prm.gas.ambient_pressure_pa, 8e5, 1e-6
    cm = orifice_constants(prm.gas.gamma, prm.gas.gas_constant_j_per_kg_k, 0.0, 0.528, 0.02)[OC_CM_STAR]
    tau = V * math.sqrt(T) / (cda * cm * RT)
    t_end = 0.9 * tau * math.log(p0 / (pa / 0.528))
    y = np.array([p0 * V / RT])
    bc = np.array([0.0, 0.0, 0.0, 2.0, pa, cda])  # closed left; orifice to ambient at the right
    t, p = testbed.line_run(y, P, bc, tau / 4000, t_end, 10)
    slope, _ = np.polyfit(t, np.log(p[:, 0]), 1)
    assert -1.0 / slope == pytest.approx(tau, rel=0.01)
    assert p[-1, 0] == pytest.approx(p0 * math.exp(-t[-1] / tau), rel=1e-6)


def test_lumped_and_fd_lines_relax_to_the_same_uniform_pressure():
    """A closed line with a pressure step ends uniform at the mean pressure (mass conserved),
    for both line models."""
    for model in ("fd", "lumped"):
        n = 8
        prm, P, vol = line_setup(n, model=model)
        y = np.zeros(2 * n - 1)
        p_init = np.where(np.arange(n) < n // 2, 4e5, 2e5)
        y[:n] = p_init * vol / rt(prm)
        m0 = y[:n].sum()
        lim = stability_limits(prm)
        # the testbed steps the lumped line explicitly: its explicit bound (SSP-RK3 on the
        # chain's Gershgorin bound), not the plant's implicit-chain limit
        dt = 0.5 * (lim["line CFL"] if model == "fd" else
                    lim["implicit orifice chain of the lumped line"] * RK3_REAL_LIMIT / CHAIN_H_LAMBDA)
        t, p = testbed.line_run(y, P, CLOSED, dt, 1.5, 1000)
        assert y[:n].sum() == pytest.approx(m0, rel=1e-12)
        assert np.allclose(p[-1], 3e5, rtol=2e-3), model


# ------------------------------------------------------------------------------------------
# the plant's implicit orifice chain of the lumped line
# ------------------------------------------------------------------------------------------
def test_implicit_chain_solves_the_stage_equation_to_round_off():
    """``system.implicit_chain`` at a stiff step (valve opening onto a line at ambient): every
    flow equals the orifice law at the pressures it leaves behind, and the flows move mass
    between neighbours only."""
    from pneugym import Plant
    from pneugym.physics import system as K
    from pneugym.physics.orifice import mass_flow
    prm = RigParams().with_(line={"model": "lumped", "n_cells": 5})
    pl = Plant(prm)
    P, n, b = pl.P, pl.n_cells, pl._b
    z = pl.y.copy()
    RT = P[L.P_R] * P[L.P_T]
    vd = P[L.P_V0D]
    kd = P[L.P_R] * z[b + L.Y_TD] / vd
    hg = 0.01  # h lambda of the chain ~ 1000
    ps, cda_v, cda_p, sT = P[L.P_PS], P[L.P_CDA_VALVE], P[L.P_CDA_PORT], P[L.P_SQRT_T]
    qj = np.zeros(n - 1)
    qv, qp = K.implicit_chain(z, P, n, b, hg, ps, cda_v, cda_p, kd, sT, 0.0, 0.0, qj,
                              np.empty(n), np.empty(n - 1))
    q = np.concatenate([[qv], qj, [qp]])
    m = z[:n] + hg * (q[:-1] - q[1:])
    assert np.all(m > 0.0)
    p = m * RT / P[L.NP:]
    pd = (z[b + L.Y_MD] + hg * qp) * kd
    oc = P[L.P_OC:L.P_OC + 7]
    law = [mass_flow(ps, p[0], cda_v, sT, sT, oc)]
    law += [mass_flow(p[i], p[i + 1], P[L.P_CDA_LINE], sT, sT, oc) for i in range(n - 1)]
    law += [mass_flow(p[-1], pd, cda_p, sT, sT, oc)]
    assert np.allclose(q, law, rtol=1e-12, atol=1e-15 * abs(qv))
    assert qv > 0 and np.all(np.diff(p) < 0)  # flow towards the chamber, pressures ordered
