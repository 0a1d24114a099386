"""The discrepancy workflow (pneugym.discrepancy): statistics, phases and noise, the decision
rules, end-to-end cases on plant-generated data (a hidden leak that also reproduces the
thesis's expansion-index puzzle; a control with mis-set nominal parameters only), the CLI and
the friction-only path on thesis Table 5.1.

The full confusion matrix (>= 3 cases per effect plus controls) is in
``benchmarks/bench_discrepancy.py``; these tests use fewer starts to stay fast."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pneugym import RigParams, thesis_rig
from pneugym.data import (
    DEFAULT_NOISE,
    MeasuredRun,
    read_run,
    simulate_run,
    thesis_protocol,
    write_run,
)
from pneugym.discrepancy import (
    CANDIDATES,
    MORE_CANDIDATES,
    Discrepancy,
    effective_sample_size,
    nrmse,
    run_phases,
    separating_experiment,
)
from pneugym.discrepancy.__main__ import main
from pneugym.discrepancy.candidates import (
    EXPOSING_EXPERIMENTS,
    Candidate,
    FitParam,
    apply,
    exposing_experiment,
    nominal_params,
)
from pneugym.discrepancy.expansion import expansion_index
from pneugym.discrepancy.friction import FrictionDiscrepancy
from pneugym.discrepancy.prepare import (
    MAX_WINDOW_S,
    SETTLE_MARGIN_S,
    block_average,
    prepare,
)
from pneugym.discrepancy.residuals import PHASES, RunPhases, estimate_noise, replay
from pneugym.discrepancy.stats import ar_whitener, f_test, lr_test, standard_errors, whiten
from pneugym.discrepancy.workflow import LINE_DELTA, CandidateResult, null_start
from pneugym.plant import SimulationError

FAST = {"n_starts": 2, "n_probe": 6, "max_nfev": 25, "seed": 0, "n_jobs": 1}


def perturbed(known: RigParams, rng: np.random.Generator, frac: float = 0.05, **effects) -> RigParams:
    """``known`` with the calibrated nominal parameters off by up to ``frac`` and ``effects``."""
    def f() -> float:
        return 1.0 + rng.uniform(-frac, frac)

    fr = known.friction
    return known.with_(valve={"discharge_coefficient": known.valve.discharge_coefficient * f()},
                       friction={"static_n": fr.static_n * f(), "coulomb_n": fr.coulomb_n * f(),
                                 "viscous_n_s_per_m": fr.viscous_n_s_per_m * f()},
                       effects=effects)


# -- statistics --------------------------------------------------------------------------------
def test_effective_sample_size_white_and_ar1():
    rng = np.random.default_rng(0)
    n = 20000
    assert effective_sample_size(rng.normal(size=n)) == pytest.approx(n, rel=0.15)
    phi = 0.8
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert effective_sample_size(x) == pytest.approx(n * (1 - phi) / (1 + phi), rel=0.2)
    assert effective_sample_size(np.ones(10)) == 10.0


def test_ar_whitener_recovers_an_ar2_and_whitens_it():
    rng = np.random.default_rng(2)
    n = 20000
    e = rng.normal(size=n)
    x = np.zeros(n)
    for i in range(2, n):
        x[i] = 1.5 * x[i - 1] - 0.6 * x[i - 2] + e[i]
    filt = ar_whitener(x, 5)
    np.testing.assert_allclose(filt, [1.0, -1.5, 0.6], atol=0.02)  # BIC picks the order 2
    w = whiten(x, filt)
    assert w.size == n - 2 and effective_sample_size(w) == pytest.approx(n - 2, rel=0.15)
    np.testing.assert_allclose(w, e[2:], atol=0.1)
    # white noise needs no filter; the rows of a matrix are filtered like a series
    assert ar_whitener(rng.normal(size=5000)).size == 1
    np.testing.assert_allclose(whiten(np.c_[x, 3 * x], filt)[:, 1], 3 * w)
    assert ar_whitener(np.arange(7.0)).size == 1  # too short to carry an order


def test_f_and_lr_tests():
    F, p = f_test(200.0, 100.0, 2, 4, 104.0)
    assert F == pytest.approx(50.0) and p < 1e-12
    assert f_test(100.0, 100.0, 1, 3, 50.0) == (0.0, 1.0)
    assert f_test(100.0, 120.0, 1, 3, 50.0) == (0.0, 1.0)
    s, p = lr_test(110.0, 100.0, 100.0)
    assert s == pytest.approx(100 * np.log(1.1)) and 0.002 < p < 0.003


def test_standard_errors_match_linear_regression():
    rng = np.random.default_rng(1)
    X = np.c_[np.ones(50), np.linspace(0, 1, 50)]
    y = X @ [1.0, 2.0] + rng.normal(0, 0.1, 50)
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ beta
    ssr = float(r @ r)
    classic = np.sqrt(np.diag(ssr / 48 * np.linalg.inv(X.T @ X)))
    np.testing.assert_allclose(standard_errors(X, ssr, 50, 1.0), classic)
    np.testing.assert_allclose(standard_errors(X, ssr, 50, 4.0), 2 * classic)
    assert np.isinf(standard_errors(np.c_[X, np.zeros(50)], ssr, 50, 1.0)[2])


def test_fit_param_transforms_and_candidates():
    p = FitParam("effects.sensor_lag_s", 0.0, 0.2, 0.01, null=0.0)
    assert p.from_u(p.to_u(0.013)) == pytest.approx(0.013) and p.to_u(1.0) == p.u_bounds[1]
    q = FitParam("friction.static_n", 100.0, 1000.0, 359.0, log=True, log_step=0.1)
    assert q.from_u(q.to_u(420.0)) == pytest.approx(420.0)
    assert q.dvalue_du(q.to_u(420.0)) == pytest.approx(42.0)
    with pytest.raises(ValueError):
        FitParam("effects.x", 0.0, 1.0, 1.0, log=True)
    assert set(CANDIDATES) >= {"leakage", "heat_transfer", "stribeck_friction", "sensor_lag", "dead_volume"}
    for c in CANDIDATES.values():  # every candidate's effect is a real EffectParams field
        rig = thesis_rig(2.5).with_(effects={q.name: q.draw(np.random.default_rng(0)) for q in c.params})
        assert c.name in rig.effects.active
    assert separating_experiment("leakage", "heat_transfer") == separating_experiment("heat_transfer", "leakage")
    assert "longer hold" in separating_experiment("leakage", "heat_transfer")
    basic = ["discharge_coefficient", "static_n", "coulomb_n", "viscous_n_s_per_m"]
    assert [p.name for p in nominal_params(thesis_rig(2.5), extended=False)] == basic
    ext = nominal_params(thesis_rig(2.5))
    assert [p.name for p in ext] == basic + ["delay_scale", "exhaust_area_m2", "port_area_m2", "cushion_length_m"]
    # the extended ones are factors on each run's own stated value: the delay keeps the
    # thesis's pressure-dependent law at every supply (ValveParams.delay_scale)
    rel = [p for p in ext if p.relative]
    for bar in (1.5, 2.5):
        rig = thesis_rig(bar)
        assert [p.stated(rig) for p in rel] == [1.0] * 4
        out = apply(rig, rel, [1.1, 0.8, 1.2, 0.9])
        assert out.valve_delay_s == pytest.approx(1.1 * rig.valve_delay_s)
        assert out.valve.delay_s is None and out.with_(supply_pressure_gauge_pa=2e5).valve_delay_s \
            == pytest.approx(1.1 * rig.with_(supply_pressure_gauge_pa=2e5).valve_delay_s)
        assert out.valve.exhaust_area_m2 == pytest.approx(0.8 * rig.valve.exhaust_area_m2)
        assert out.cylinder.port_area_m2 == pytest.approx(1.2 * rig.cylinder.port_area_m2)
        assert out.cylinder.cushion_length_m == pytest.approx(0.9 * rig.cylinder.cushion_length_m)
    # every candidate, the valve's included, says what would expose it
    assert set(EXPOSING_EXPERIMENTS) == set(CANDIDATES) | set(MORE_CANDIDATES)
    valve = apply(thesis_rig(2.0), MORE_CANDIDATES["valve_delay"].params, [1.3])
    assert valve.valve_delay_s == pytest.approx(1.3 * thesis_rig(2.0).valve_delay_s)
    assert "hold" in exposing_experiment("leakage") and "slow strokes" in exposing_experiment("stribeck_friction")


def test_a_candidates_null_start():
    """The start at the model without the effect: calibrated values, magnitudes at their null,
    shape parameters typical; none where the null lies outside the bounds."""
    nom = np.array([0.7, 359.0])
    s = null_start(nom, CANDIDATES["stribeck_friction"].params, [100.0, 0.02])
    assert list(s) == [0.7, 359.0, 0.0, 0.02]
    assert list(null_start(nom, CANDIDATES["leakage"].params, [1e-7, 1e-7])) == [0.7, 359.0, 0.0, 0.0]
    assert null_start(nom, CANDIDATES["heat_transfer"].params, [0.5]) is None  # 0 s: not in 1 ms-20 s


class _Quadratic:
    """A stand-in fit problem: residuals are the distance of the values from ``target``."""

    def __init__(self, params, target):
        self.params, self.target = params, np.asarray(target, float)

    def residuals(self, u):
        return np.array([q.from_u(x) for q, x in zip(self.params, u)]) - self.target


def test_the_null_start_joins_only_where_every_start_begins_worse():
    """Least squares never raises its start's SSR: with the null start among the starts where
    every screened one begins worse, no candidate's fit ends worse than the model without it."""
    nominal = FitParam("friction.coulomb_n", 10.0, 400.0, 126.0)
    effect = FitParam("effects.stribeck_force_n", 0.0, 1000.0, 100.0, null=0.0, start=(300.0, 900.0))
    d = Discrepancy(n_starts=2, n_probe=5)
    guard = null_start(np.array([126.0]), (effect,), [100.0])
    firsts = [np.array([126.0, 300.0])]
    no_effect = _Quadratic((nominal, effect), [126.0, 0.0])  # every drawn start is worse
    st = d._starts(no_effect, firsts, [(nominal,), (effect,)], np.random.default_rng(0), guard=guard)
    assert len(st) == 3 and list(st[-1]) == [126.0, 0.0]
    big = _Quadratic((nominal, effect), [126.0, 600.0])  # a drawn start begins better
    st = d._starts(big, firsts, [(nominal,), (effect,)], np.random.default_rng(0), guard=guard)
    assert len(st) == 2 and not any(list(s) == [126.0, 0.0] for s in st)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="unknown candidate"):
        Discrepancy(["leak"])
    with pytest.raises(ValueError, match="alpha"):
        Discrepancy(alpha=2.0)
    with pytest.raises(ValueError, match="calibrate"):
        Discrepancy(calibrate="everything")
    with pytest.raises(ValueError, match="discrepancy_term"):
        Discrepancy(discrepancy_term="gp")
    # a slower valve is a candidate only where the calibration leaves the delay as stated
    with pytest.raises(ValueError, match="valve_delay.*valve.delay_scale.*calibrate='basic'"):
        Discrepancy(["leakage", "valve_delay"])
    assert Discrepancy(["leakage", "valve_delay"], calibrate="basic").candidates[1].name == "valve_delay"
    # a parameter calibrated besides the nominal ones is fitted once, and is a FitParam
    valve = MORE_CANDIDATES["valve_delay"].params
    with pytest.raises(ValueError, match="calibrate_also: valve.delay_scale is fitted already"):
        Discrepancy(["leakage"], calibrate_also=valve)  # the extended calibration frees it
    with pytest.raises(ValueError, match="calibrate_also: valve.delay_scale"):
        Discrepancy(["valve_delay"], calibrate="basic", calibrate_also=valve)
    with pytest.raises(ValueError, match="FitParam"):
        Discrepancy(calibrate_also=["valve.delay_scale"])
    d = Discrepancy(["leakage"], calibrate="basic", calibrate_also=valve)
    assert d.config()["calibrate_also"] == ["valve.delay_scale"]
    # the line models to try
    with pytest.raises(ValueError, match="unknown line model 'pipe'.*'fd', 'lumped'"):
        Discrepancy(line_models=("fd", "pipe"))
    for bad in ("lumped", ()):
        with pytest.raises(ValueError, match="line_models.*sequence"):
            Discrepancy(line_models=bad)
    assert Discrepancy(line_models=["lumped", "fd", "lumped"]).config()["line_models"] == ["lumped", "fd"]
    assert Discrepancy().config()["line_models"] is None
    # the orifice laws to try
    with pytest.raises(ValueError, match="unknown orifice law 'sharp'.*'thesis', 'iso6358'"):
        Discrepancy(orifice_models=("thesis", "sharp"))
    with pytest.raises(ValueError, match="orifice_models.*sequence"):
        Discrepancy(orifice_models="iso6358")
    assert Discrepancy(orifice_models=["iso6358", "thesis"]).config()["orifice_models"] == ["iso6358", "thesis"]
    assert Discrepancy().config()["orifice_models"] is None


# -- phases, noise, NRMSE ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def protocol_runs():
    known = thesis_rig(2.5)
    return known, thesis_protocol(known, known, t_end=2.0, seed=5)


def test_phases_and_noise(protocol_runs):
    known, runs = protocol_runs
    conv, end, early = runs
    pc, pe, pk = (run_phases(r, known) for r in runs)
    assert pc.t_cut_effective_s is None and pc.t_arrival_s is not None
    assert [s[0] for s in pc.spans(conv.t)] == ["before_motion", "stroke", "end_supply"]
    t_cmd = early.schedule()[1][0]
    assert pk.t_cut_effective_s == pytest.approx(t_cmd + known.valve_delay_s + known.valve.ramp_s, abs=1.5e-3)
    assert [s[0] for s in pk.spans(early.t)] == ["before_motion", "stroke", "trapped"]
    assert [s[0] for s in pe.spans(end.t)] == ["before_motion", "stroke", "end_supply", "trapped"]
    assert set(PHASES) == {"before_motion", "stroke", "trapped", "end_supply"}
    sigma = estimate_noise(runs)
    assert sigma["p_drive"] == pytest.approx(400.0, rel=0.15)
    assert sigma["p_exhaust"] == pytest.approx(400.0, rel=0.15)
    assert sigma["x"] == pytest.approx(3e-5, rel=0.15)


def test_nrmse_definition(protocol_runs):
    _, runs = protocol_runs
    exact = [{c: getattr(r, c).copy() for c in ("x", "p_drive", "p_exhaust")} for r in runs]
    assert nrmse(runs, exact)["overall"] == 0.0
    off = [{**s, "x": s["x"] + 0.001} for s in exact]  # 1 mm everywhere
    rng_x = max(r.x.max() for r in runs) - min(r.x.min() for r in runs)
    g = nrmse(runs, off)
    assert g["x"] == pytest.approx(0.001 / rng_x) and g["overall"] == pytest.approx(g["x"] / 3)


# -- decision rules -------------------------------------------------------------------------------
def _cand(name, ssr, passed=True):
    return CandidateResult(
        name=name, values={}, effect={}, stderr={}, z={}, at_bound=[], ssr_fit=ssr, ssr0_fit=1e5,
        n_fit=10000, kappa=1.0, n_eff=10000.0, F=1e3, p_value=0.0, ssr_holdout=ssr / 2,
        ssr0_holdout=5e4, n_eff_holdout=5000.0, holdout_stat=1e3, holdout_p=0.0,
        improvement_fit=0.9, improvement_holdout=0.9, score=1 - 1.5 * ssr / 1.5e5, by_phase={"stroke": 1 - 1.5 * ssr / 1.5e5},
        checks={"significant": passed}, passed=passed, reasons=[], nfev=1, start_ssr=[ssr],
        ssr_test=ssr, ssr_test_holdout=ssr / 2, material_fit=0.9, material_holdout=0.9)


@pytest.mark.parametrize("cands, named, ambiguous", [
    ([_cand("leakage", 10000.0), _cand("heat_transfer", 10000.5)], "ambiguous", ["leakage", "heat_transfer"]),
    ([_cand("leakage", 10000.0), _cand("heat_transfer", 12000.0)], "leakage", []),
    ([_cand("leakage", 10000.0), _cand("heat_transfer", 10010.0, passed=False)], "leakage", []),
    ([_cand("leakage", 10000.0, passed=False)], "none", []),
])
def test_decision(cands, named, ambiguous):
    d = Discrepancy()
    d.candidates_ = sorted(cands, key=lambda c: -c.score)
    d._decide()
    assert d.named_effect_ == named and d.ambiguous_ == ambiguous
    if named == "ambiguous":
        assert "longer hold" in d.suggestion_ and "ambiguous" in d.decision_
    assert d.suggested_for_ == ambiguous  # the runs to measure expose both, or nothing is asked
    if named == "leakage":  # every candidate here was tested on a held-out run: it says so
        assert "held-out run included" in d.decision_, d.decision_


def test_short_evidence_names_the_candidate_and_the_experiment():
    """No candidate passes; one removes a material share and improves the held-out run: the
    answer stays none, and the decision says which, where, why not and what to measure."""
    near = _cand("heat_transfer", 60000.0, passed=False)
    near.checks = {"significant": False, "material": True, "improves_holdout": False}
    near.by_phase = {"trapped": 0.3, "stroke": 0.05}
    weak = _cand("leakage", 99000.0, passed=False)
    weak.checks = {"significant": False, "material": False}
    d = Discrepancy()
    d.candidates_ = [near, weak]
    d._decide()
    assert d.named_effect_ == "none" and d.suggestion_ == exposing_experiment("heat_transfer")
    assert "evidence short for heat_transfer" in d.decision_ and "trapped air" in d.decision_
    assert "fails: significant, improves_holdout" in d.decision_
    d.rigs_ = [thesis_rig(2.5)]
    assert d.suggested_for_ == ["heat_transfer"] and [p.name for p in d.suggested_runs()] == ["hold"]
    near.improvement_holdout = -0.2  # a held-out run made worse is no lead
    d._decide()
    assert d.suggestion_ is None and "evidence short" not in d.decision_
    assert d.suggested_for_ == [] and d.suggested_runs() == []
    d.suggested_for_ = ["valve_delay"]  # a lead no stroke is planned for keeps only its text
    assert d.suggested_runs() == []


def test_decision_without_a_held_out_run_says_so():
    c = _cand("leakage", 10000.0)
    c.checks = {"significant": True, "material": True, "away_from_null": True,
                "not_on_bound": True, "improves_holdout": None}  # no held-out run
    d = Discrepancy()
    d.candidates_ = [c]
    d._decide()
    assert d.named_effect_ == "leakage"
    assert "passes every check" not in d.decision_
    assert "passes the 4 checks it could take" in d.decision_
    assert "not tested on a held-out run" in d.decision_ and "not validated" in d.decision_


def test_own_phase_evidence():
    """A leak and Stribeck friction must improve the fit in the trapped air after cut-off,
    where they show and the line's and orifices' form matters least; a candidate without an
    own phase, or runs without that phase, are not checked."""
    assert CANDIDATES["leakage"].phase == CANDIDATES["stribeck_friction"].phase == "trapped"
    assert CANDIDATES["sensor_lag"].phase is None
    d = Discrepancy()
    cut = np.array([0, 1, 1, 2, 2, 3])  # before motion, stroke, trapped, end of stroke
    d.phases_ = [RunPhases(np.array([0, 1, 1, 3]), 0.1, 0.5, None), RunPhases(cut, 0.1, 0.5, 0.3)]
    leak, lag = CANDIDATES["leakage"], CANDIDATES["sensor_lag"]
    reasons: list[str] = []
    bent = {"before_motion": 0.05, "stroke": 0.21, "trapped": -0.012, "end_supply": 0.16}
    assert d._own_phase(leak, bent, reasons) is False  # bends the supply phases only
    assert reasons == ["removes nothing in the trapped air after cut-off, where leakage shows "
                       "(-1.2% of the calibrated model's misfit)"]
    assert d._own_phase(leak, {**bent, "trapped": 0.03}, []) is True
    assert d._own_phase(leak, {**bent, "trapped": 0.0}, []) is False
    assert d._own_phase(lag, bent, []) is None
    d.phases_ = d.phases_[:1]  # no run cut off: nothing to check against
    assert d._own_phase(leak, bent, []) is None
    with pytest.raises(ValueError, match="phase 'hold'"):
        Candidate("x", (), phase="hold")


# -- end to end: a hidden leak, which is also the thesis's expansion-index puzzle -----------------
@pytest.fixture(scope="module")
def leak_case(tmp_path_factory):
    """1.5 bar, late cut-off (the piston creeps through the end cushion, as in the thesis's
    expansion experiment), a hidden 3e-7 m² leak and nominal parameters off by a few percent."""
    known = thesis_rig(1.5)
    truth = perturbed(known, np.random.default_rng(11), leak_drive_area_m2=3e-7)
    runs = thesis_protocol(truth, known, early_cutoff_s=0.95, seed=21)
    d = Discrepancy(**FAST).fit(runs)
    out = tmp_path_factory.mktemp("leak_report")
    d.report(out)
    return known, truth, runs, d, out


def test_leak_is_named_and_the_gap_shrinks(leak_case):
    _, truth, runs, d, _ = leak_case
    assert d.named_effect_ == "leakage", d.summary()
    assert [r.name for r in d.holdout_runs_] == ["end_stroke_cutoff"]
    best = d.candidates_[0]
    assert best.name == "leakage" and best.passed and all(best.checks.values())
    assert best.effect["leak_drive_area_m2"] == pytest.approx(3e-7, rel=0.1)
    # the nominal parameters come back too (discharge coefficient within 1 %)
    assert d.fitted_params_["valve.discharge_coefficient"] == pytest.approx(
        truth.valve.discharge_coefficient, rel=0.01)
    assert d.gap_reduction >= 0.5
    for s in ("fit", "holdout"):  # the effect, not only the calibration, shrinks the gap
        assert d.gaps_["updated"][s]["overall"] < 0.5 * d.gaps_["calibrated"][s]["overall"]
    # the calibrated nominal model fails where a leak shows: the trapped air after cut-off
    # (the extended calibration, valve delay and areas freed, takes up part of it)
    worst = d.findings_["calibrated"][0]
    assert worst.phase == "trapped" and worst.rms_z > 5
    assert all(f.rms_z < 3 for f in d.findings_["updated"] if f.phase == "trapped" and f.channel != "x")
    assert d.score(runs) == pytest.approx(d.gap_after)
    # where the evidence comes from: the shares per phase sum to the score, mostly trapped air
    assert sum(best.by_phase.values()) == pytest.approx(best.score)
    assert max(best.by_phase, key=best.by_phase.get) == "trapped"
    # the default reads the raw residuals: their autocorrelation deflates the sample size, and
    # an effect must remove 10 % of the whole misfit
    assert d.config()["discrepancy_term"] is None and d.whiteners_ is None
    assert d.min_improvement == 0.1
    assert best.material_fit == pytest.approx(best.improvement_fit) and best.n_eff < best.n_fit
    assert "above the noise" not in " ".join(c for cand in d.candidates_ for c in cand.reasons)


def test_no_candidate_ends_worse_than_the_model_without_it(leak_case):
    """Without the null start, a Stribeck force fitted to this leak ended at 2.4 times the
    calibrated model's SSR (every screened start began worse; on rigs of another form up to 21
    times): a candidate that cannot fit is then judged as if it made things worse."""
    _, _, _, d, _ = leak_case
    guarded = [c for c in d.candidates_ if null_start(np.zeros(0), CANDIDATES[c.name].params,
                                                      [1.0] * len(CANDIDATES[c.name].params)) is not None]
    assert "stribeck_friction" in {c.name for c in guarded}
    for c in guarded:
        assert c.ssr_fit <= c.ssr0_fit * (1 + 1e-9), (c.name, c.ssr_fit / c.ssr0_fit)


def test_with_the_discrepancy_term_the_leak_is_named_too(leak_case):
    """``discrepancy_term="ar"``: the residuals whitened by the calibrated model's AR filters (the
    missing leak is structure too), nearly their full sample size, and the material check on
    the misfit above the noise (30 %)."""
    _, _, runs, _, _ = leak_case
    d = Discrepancy(["leakage", "sensor_lag"], discrepancy_term="ar", **FAST).fit(runs)
    assert d.whiteners_ is not None and d.min_improvement == 0.3
    assert d.config()["discrepancy_term"] == "ar"
    assert d.named_effect_ == "leakage", d.summary()
    best = d.candidates_[0]
    assert best.material_fit >= best.improvement_fit and best.n_eff > 0.5 * best.n_fit


def test_autoregressive_discrepancy_term_on_a_rig_of_another_form(tmp_path):
    """A leak on a rig whose line, orifices and cushions differ from the model's: with the
    autoregressive discrepancy term the tests read whitened residuals (nearly white: their
    effective size near the sample count, where the raw residuals' is a few dozen), the
    material check reads the misfit above the noise, and the leak is named."""
    from pneugym.discrepancy.cases import make_case
    _, truth, runs = make_case("leakage", 1000, "mismatched")
    assert truth.line.model != "fd" or truth.line.n_cells != 3  # another form than the model's
    d = Discrepancy(["leakage", "heat_transfer"], discrepancy_term="ar", **FAST).fit(runs)
    assert d.config()["discrepancy_term"] == "ar" and d.min_improvement == 0.3
    assert set(d.whiteners_) == {(r.name, c) for r in d.runs_ for c in ("x", "p_drive", "p_exhaust")}
    assert all(f[0] == 1.0 and 1 < f.size <= 6 for f in d.whiteners_.values())  # structure: an order >= 1
    assert d.named_effect_ == "leakage", d.summary()
    best = d.candidates_[0]
    assert best.n_eff > 0.5 * best.n_fit and best.ssr_test < best.ssr_fit
    assert best.material_fit >= 0.3 and best.material_fit >= best.improvement_fit
    raw = [r - s["p_drive"] for r, s in zip((r.p_drive for r in d.runs_), d.sims_["calibrated"])]
    assert min(effective_sample_size(r) for r in raw) < 0.05 * min(r.size for r in raw)
    d.report(tmp_path)
    assert (tmp_path / "candidates.png").stat().st_size > 10_000


def test_the_line_model_is_chosen_by_the_runs(tmp_path):
    """``line_models=("fd", "lumped")``: a 20 ms transducer lag on a rig whose supply line is
    lumped (4 volumes) and whose JSON states the default finite-difference line. On the stated
    line the lag is hidden behind the line's structural error (the workflow says `none`, as the
    default does, to the last digit); run again on the lumped line it is named, that model fits
    clearly better, and the report and the updated model state the lumped line."""
    known = thesis_rig(2.5)
    truth = perturbed(known, np.random.default_rng(3), sensor_lag_s=0.02).with_(
        line={"model": "lumped", "n_cells": 4})
    runs = thesis_protocol(truth, known, t_end=2.0, seed=4)
    cands = ["sensor_lag"]
    d0 = Discrepancy(cands, **FAST).fit(runs)
    d = Discrepancy(cands, line_models=("fd", "lumped"), **FAST).fit(runs)
    fd, lumped = d.form_fits_["fd"], d.form_fits_["lumped"]
    assert list(d.form_fits_) == ["fd", "lumped"]  # the stated line first
    assert lumped["kept"] and not fd["kept"]
    # the stated line's run is the default run
    assert fd["named"] == d0.named_effect_ and fd["gap_after"] == d0.gap_after
    assert d0.line_model_ == "fd" and d0.form_fits_ == {}
    assert d.line_model_ == "lumped" and lumped["aic_above_best"] == 0.0
    assert fd["aic_above_best"] >= LINE_DELTA
    assert d.named_effect_ == "sensor_lag", d.summary()
    assert d.candidates_[0].effect["sensor_lag_s"] == pytest.approx(0.02, rel=0.25)
    assert d.gap_after < 0.75 * d0.gap_after
    assert d.gap_before == d0.gap_before  # the nominal model is the JSON's, as stated
    assert d.updated_model.line.model == "lumped" and d.updated_rig(runs[0]).line.model == "lumped"
    assert d.score(runs) == pytest.approx(d.gap_after)
    assert "model form: lumped line, thesis law (each form tried: fd -> " in d.summary()
    d.report(tmp_path)
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["line_model"] == "lumped" and set(rep["form_fits"]) == {"fd", "lumped"}
    assert rep["orifice_model"] == "thesis"
    assert rep["config"]["line_models"] == ["fd", "lumped"]
    assert "**`lumped` fits clearly better than the stated `fd`**" in (tmp_path / "report.md").read_text()
    assert json.loads((tmp_path / "updated_model.json").read_text())["line"]["model"] == "lumped"


def test_the_orifice_law_is_chosen_by_the_runs(tmp_path):
    """``orifice_models=("thesis", "iso6358")``: a rig whose valve follows ISO 6358 with a
    critical ratio of 0.25 while its JSON states the thesis's law, with a hidden leak. On the
    stated law the leak hides in the law's structural error (`none`, the default's answer to
    the last digit); the ISO law fits clearly better, its critical ratio (freed: the JSON does
    not give it) is found, the leak is named on it, and the updated model states the law."""
    known = thesis_rig(1.5)
    truth = perturbed(known, np.random.default_rng(5), leak_drive_area_m2=3e-7).with_(
        valve={"flow_model": "iso6358", "iso_b": 0.25})
    runs = thesis_protocol(truth, known, t_end=2.0, seed=6)
    d0 = Discrepancy(["leakage"], **FAST).fit(runs)
    d = Discrepancy(["leakage"], orifice_models=("thesis", "iso6358"), **FAST).fit(runs)
    thesis, iso = d.form_fits_["thesis"], d.form_fits_["iso6358"]
    assert thesis["named"] == d0.named_effect_ == "none" and thesis["gap_after"] == d0.gap_after
    assert "valve.iso_b" not in d0.fitted_params_
    assert iso["kept"] and thesis["aic_above_best"] >= LINE_DELTA, d.form_fits_
    assert iso["n_params"] == len(d.fitted_params_)  # the critical ratio among them
    assert d.orifice_model_ == "iso6358" and d.line_model_ == "fd"
    assert d.named_effect_ == "leakage", d.summary()
    # the least-squares path follows the linear algebra's last bits: 0.25 +- 0.05 on one
    # machine, 0.306 on another (2-core AMD EPYC); the ratio's bounds are 0.1-0.6
    assert d.fitted_params_["valve.iso_b"] == pytest.approx(0.25, abs=0.08)
    assert d.fitted_params_["effects.leak_drive_area_m2"] == pytest.approx(3e-7, rel=0.3)
    assert d.gap_after < 0.5 * d0.gap_after, d.form_fits_
    rig = d.updated_rig(runs[0])
    assert rig.valve.flow_model == "iso6358" and rig.valve.iso_b == d.fitted_params_["valve.iso_b"]
    assert d.score(runs) == pytest.approx(d.gap_after)
    d.report(tmp_path, plots=False)
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["orifice_model"] == "iso6358" and rep["config"]["orifice_models"] == ["thesis", "iso6358"]
    assert "**`iso6358` fits clearly better than the stated `thesis`**" in (tmp_path / "report.md").read_text()
    assert json.loads((tmp_path / "updated_model.json").read_text())["valve"]["flow_model"] == "iso6358"


def test_the_stated_line_stays_when_it_is_right(protocol_runs):
    """Runs of the model's own form: the lumped line fits no better, the stated result stands."""
    known, _ = protocol_runs
    truth = perturbed(known, np.random.default_rng(8))
    runs = thesis_protocol(truth, known, t_end=2.0, seed=9)
    d0 = Discrepancy(["sensor_lag"], **FAST).fit(runs)
    d = Discrepancy(["sensor_lag"], line_models=("lumped", "fd"), **FAST).fit(runs)
    assert d.line_model_ == "fd" and d.form_fits_["lumped"]["aic_above_best"] > 6.0
    assert d.named_effect_ == d0.named_effect_ == "none"
    assert d.fitted_params_ == d0.fitted_params_ and d.gap_after == d0.gap_after
    assert d.updated_model.line.model == "fd"


def test_expansion_index_puzzle(leak_case):
    known, _, runs, d, _ = leak_case
    early = runs[2]
    apparent = expansion_index(early, known)
    assert apparent.n > 2.0 and apparent.volume_ratio > 1.01  # thesis: 2.7, "far from" 1.0-1.4
    corrected = expansion_index(early, known, model=d.updated_rig(early))
    assert 0.9 <= corrected.n <= 1.4  # the air that stays expands (near-)isothermally: physical
    no_leak = expansion_index(early, known, model=d.updated_rig(early).with_(
        effects={"leak_drive_area_m2": 0.0, "leak_piston_area_m2": 0.0}))
    assert no_leak.n == pytest.approx(apparent.n, rel=0.05)  # a leak-free model explains nothing


def test_report_files(leak_case):
    *_, out = leak_case
    rep = json.loads((out / "report.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    for key in ("named_effect", "candidates", "fitted_params", "gap_before", "gap_after",
                "gap_reduction", "updated_model", "gaps", "localisation", "provenance", "config"):
        assert key in rep
    assert rep["named_effect"] == "leakage"
    assert rep["gap_reduction"] == pytest.approx(1 - rep["gap_after"] / rep["gap_before"])
    assert rep["relative_params"] == ["valve.delay_scale", "valve.exhaust_area_m2", "cylinder.port_area_m2",
                                      "cylinder.cushion_length_m"]
    for c in rep["candidates"]:
        assert {"name", "parameters", "score", "passed", "checks"} <= set(c)
    rig = RigParams.from_dict(json.loads(Path(rep["updated_model"]).read_text()))
    assert rig.effects.active == ("leakage",)
    md = (out / "report.md").read_text()
    assert "Named effect: `leakage`" in md and "trapped air after cut-off" in md
    assert "| valve.exhaust_area_m2 (x stated) |" in md  # a factor, not an area in m²
    assert "| valve.discharge_coefficient |" in md
    for name in ("overlays.png", "residuals.png", "candidates.png"):
        assert (out / name).stat().st_size > 10_000


def test_report_reads_only_what_a_fitted_discrepancy_has(leak_case):
    """The report's view of the workflow (report.FittedDiscrepancy) names only what a fitted
    Discrepancy has, and report.py does not import workflow.py (which imports it)."""
    import ast

    from pneugym.discrepancy import report
    d = leak_case[3]
    proto = report.FittedDiscrepancy
    names = set(proto.__annotations__) | {n for n in vars(proto) if not n.startswith("_")}
    assert {"runs_", "candidates_", "gap_before", "config"} <= names
    assert [n for n in sorted(names) if not hasattr(d, n)] == []
    tree = ast.parse(Path(report.__file__).read_text(encoding="utf-8"))
    assert "workflow" not in {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}


# -- end to end: control (no effect, nominal parameters a few percent off) through the CLI ---------
def test_control_names_none_through_the_cli(tmp_path, capsys):
    known = thesis_rig(2.5)
    truth = perturbed(known, np.random.default_rng(3))
    for r in thesis_protocol(truth, known, t_end=2.0, seed=31):
        write_run(r, tmp_path / "runs" / r.name)
    rc = main([str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--starts", "1", "--probe", "4",
               "--max-nfev", "25", "--jobs", "1", "--no-plots", "--quiet"])
    assert rc == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["named_effect"] == "none", rep["decision"]
    assert rep["gap_after"] < 0.5 * rep["gap_before"]  # calibration alone closes the gap
    assert rep["fitted_params"]["valve.discharge_coefficient"] == pytest.approx(
        truth.valve.discharge_coefficient, rel=0.01)
    assert "named effect: none" in capsys.readouterr().out


def test_cli_refuses_bad_runs(tmp_path, capsys):
    (tmp_path / "r.csv").write_text("t,valve,x,p_drive\n0,1,0,101325\n")
    assert main([str(tmp_path / "r.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "r.json" in capsys.readouterr().err
    assert main(["--hold", str(tmp_path / "r.csv"), "--out", str(tmp_path / "o"),
                 "--line-models", "fd", "lumped"]) == 2
    assert "--line-models and --orifice-models are for extension strokes" in capsys.readouterr().err
    assert main(["--hold", str(tmp_path / "r.csv"), "--out", str(tmp_path / "o"),
                 "--orifice-models", "iso6358"]) == 2


# -- reports written as a whole; the output folder checked before the fit -------------------------
def test_cli_checks_the_output_folder_before_reading_and_fitting(tmp_path, capsys, monkeypatch):
    from pneugym.discrepancy import workflow
    stem = write_run(simulate_run(thesis_rig(2.5), t_end=0.1, noise=None), tmp_path / "r")
    not_a_folder = tmp_path / "report.txt"
    not_a_folder.write_text("x")
    monkeypatch.setattr(workflow, "read_runs", lambda *a: pytest.fail("runs read before --out was checked"))
    monkeypatch.setattr(Discrepancy, "fit", lambda *a: pytest.fail("fit started before --out was checked"))
    assert main([str(stem), "--out", str(not_a_folder)]) == 2
    err = capsys.readouterr().err
    assert str(not_a_folder) in err and "not a folder" in err
    assert not_a_folder.read_text() == "x"


def _snapshot(folder) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_report_is_replaced_as_a_whole(leak_case, tmp_path, monkeypatch):
    from pneugym.discrepancy import report
    _, _, _, d, _ = leak_case
    out = tmp_path / "out"
    d.report(out, plots=False)
    old = _snapshot(out)
    assert set(old) == {"report.json", "report.md", "updated_model.json"}
    # a later report whose last file fails (e.g. the disk fills up) leaves the old set as it was:
    # no new updated_model.json beside an old report, no staging folder left behind
    monkeypatch.setattr(d, "fitted_params_", {**d.fitted_params_, "marker": 1.0})
    monkeypatch.setattr(d, "updated_rigs_", [g.with_(load_mass_kg=99.0) for g in d.updated_rigs_])
    def full_disk(rep):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(report, "markdown", full_disk)
    with pytest.raises(OSError, match="No space"):
        d.report(out, plots=False)
    assert _snapshot(out) == old
    monkeypatch.undo()
    # a folder that cannot be one is refused before anything is written, naming the path
    with pytest.raises(ValueError, match=str(tmp_path / "out" / "report.json")):
        d.report(out / "report.json")


# -- one run: no held-out check, and a long run cut to what carries information ------------------
@pytest.fixture(scope="module")
def single_long_run(tmp_path_factory):
    """One 2-minute end-stroke cut-off run at 1 kHz (120001 samples), through the CLI with a
    small budget and --max-samples 1000: windowed, then block-averaged."""
    tmp = tmp_path_factory.mktemp("single")
    run = simulate_run(thesis_rig(2.5), cut_on_arrival=True, t_end=120.0, noise="default", seed=4,
                       name="long")
    stem = write_run(run, tmp / "runs" / "long")
    return run, stem, tmp


def test_single_long_run_through_the_cli(single_long_run, capsys):
    _, stem, tmp = single_long_run
    out = tmp / "out"
    rc = main([str(stem), "--out", str(out), "--candidates", "leakage,sensor_lag", "--starts", "1",
               "--probe", "2", "--max-nfev", "10", "--jobs", "1", "--no-plots", "--quiet",
               "--max-samples", "1000"])
    assert rc == 0
    printed = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    md = (out / "report.md").read_text()
    # a single run is never presented as validated
    assert rep["held_out_tested"] is False and rep["holdout"] == []
    assert rep["warnings"] and "not tested on a held-out run" in rep["warnings"][0]
    assert "not tested on a held-out run" in rep["decision"]
    assert "> **Warning: not tested on a held-out run" in md
    assert "WARNING: not tested on a held-out run" in printed
    # the run was windowed and block-averaged, and the report says so
    prep = rep["runs"][0]["preparation"]
    assert prep["windowed"] and not prep["capped"] and prep["samples_measured"] == 120001
    assert prep["t_used_s"][1] < 10.0 and prep["block"] >= 2 and prep["samples_used"] <= 1000
    assert rep["runs"][0]["samples"] == prep["samples_used"]
    for text in (md, printed):
        assert "long: window" in text and f"block-averaged by {prep['block']}" in text
    # the noise is estimated on the averaged data: sigma / sqrt(block) for white noise
    assert rep["noise_sigma"]["p_drive"] == pytest.approx(400.0 / math.sqrt(prep["block"]), rel=0.2)


def test_window_and_decimation(single_long_run):
    run, _, _ = single_long_run
    rig = thesis_rig(2.5)
    (short,), (info,) = prepare([run], [rig], max_samples=100_000)
    assert info.windowed and info.block == 1 and not info.capped
    # the window ends a margin after the last event: the exhaust pressure settling through the
    # cushion, after the arrival and the cut-off reaching the valve
    t_cut = run.schedule()[1][0] + rig.valve_delay_s + rig.valve.ramp_s
    assert t_cut < info.t_events_end_s < info.t_used_s[1] == pytest.approx(
        info.t_events_end_s + SETTLE_MARGIN_S, abs=1.5e-3)
    tail = run.t > info.t_used_s[1]
    assert np.abs(run.p_exhaust[tail] - np.median(run.p_exhaust[tail])).max() < 5 * 400 + 1e3
    np.testing.assert_array_equal(short.p_drive, run.p_drive[: len(short)])
    assert short.schedule() == run.schedule()
    # a run without the noise channels settling (a leak keeps the pressure falling) is capped
    leaky = simulate_run(rig.with_(effects={"leak_drive_area_m2": 2e-7}), cut_on_arrival=True,
                         t_end=60.0, noise="default", known=rig, seed=1)
    (capped,), (info,) = prepare([leaky], [rig], max_samples=100_000)
    assert info.capped and capped.t[-1] == pytest.approx(MAX_WINDOW_S)
    assert "cap" in info.sentence()
    # runs up to the cap come back unchanged (the same objects), settled tail and all
    runs = thesis_protocol(rig, t_end=2.0) + [simulate_run(rig, cut_on_arrival=True, t_end=MAX_WINDOW_S)]
    assert all(a is b for a, b in zip(prepare(runs, [rig] * 4, max_samples=100_000)[0], runs))


def test_block_averaged_replay_is_exact(single_long_run):
    run, _, tmp = single_long_run
    rig = thesis_rig(2.5)
    (w,), _ = prepare([run], [rig], max_samples=100_000)
    b = block_average(w, 5)
    assert b.block == 5 and len(b) == len(w) // 5 and b.schedule() == w.schedule()
    with pytest.raises(ValueError, match="block-averaged"):
        write_run(b, Path(tmp) / "b")
    assert 0.0 < b.valve[np.flatnonzero((b.valve > 0) & (b.valve < 1))].size <= 1  # the cut-off block
    sim, sim_b = replay(w, rig), replay(b, rig)
    for c in ("x", "p_drive", "p_exhaust"):
        np.testing.assert_allclose(sim_b[c], sim[c][: 5 * len(b)].reshape(-1, 5).mean(axis=1),
                                   rtol=1e-12, atol=1e-9)
    # the averaged noise: sigma / sqrt(5) (white noise)
    res = (b.p_drive - sim_b["p_drive"])[b.t > 3.0]
    assert np.std(res) == pytest.approx(DEFAULT_NOISE["p_drive"] / math.sqrt(5), rel=0.15)


def test_prepared_size_is_bounded_for_an_hour_at_1_khz():
    """An hour at 1 kHz (3.6 million samples) is cut to at most max_samples, within seconds."""
    import time
    rig = thesis_rig(2.5)
    base = simulate_run(rig, cut_on_arrival=True, t_end=5.0, noise=None)
    n = 3_600_001
    rng = np.random.default_rng(0)
    cols = {c: np.concatenate([getattr(base, c), np.full(n - len(base), getattr(base, c)[-1])])
            for c in ("valve", "x", "p_drive", "p_exhaust")}
    cols["p_drive"] = cols["p_drive"] + rng.normal(0.0, 400.0, n)
    hour = MeasuredRun(name="hour", t=np.arange(n) * 1e-3, meta=base.meta, **cols)
    t0 = time.perf_counter()
    (p,), (info,) = prepare([hour], [rig], max_samples=5000)
    assert len(p) <= 5000 and info.t_used_s[1] <= MAX_WINDOW_S and info.samples_measured == n
    assert time.perf_counter() - t0 < 20.0  # ~0.3 s here; a generous bound for a loaded machine


# -- the real-data case: thesis Table 5.1 ----------------------------------------------------------
def test_table_5_1_friction():
    # the plant's reading (breakaway at rest, sliding law moving): nothing to add, and the
    # thesis's parameters are the least-squares fit of the moving points
    k = FrictionDiscrepancy(static="breakaway").fit()
    assert k.named_effect_ == "none"
    assert k.nominal_.params["coulomb_n"] == pytest.approx(126.0, abs=1.0)
    assert k.nominal_.params["viscous_n_s_per_m"] == pytest.approx(1557.0, abs=5.0)
    assert not k.checks_["significant"]
    # one friction-velocity curve (thesis Fig. 5.4): the model fails at the lowest velocities,
    # Stribeck friction removes that failure and halves the SSR ...
    c = FrictionDiscrepancy(static="curve").fit()
    bands = {b["band"]: b for b in c.bands_}
    assert c.worst_band_.startswith("at rest")
    low = bands["low, 0 < v < 0.03"]
    mid = bands["mid, 0.03 <= v < 0.15"]
    assert low["rms_stribeck_n"] < 0.4 * low["rms_nominal_n"]
    assert bands["at rest (v = 0)"]["rms_stribeck_n"] < 1.0
    assert abs(mid["rms_stribeck_n"] - mid["rms_nominal_n"]) < 0.1 * mid["rms_nominal_n"]
    assert np.all(c.nominal_.residual_n[1:4] < 0)  # 0.01-0.02 m/s: below the straight line
    assert c.improvement_ > 0.5 and c.stribeck_.params["stribeck_force_n"] == pytest.approx(233, abs=5)
    # ... but 16 points cannot name it under the decision rules: with the residuals'
    # effective sample size the F-test gives p ~ 0.05 > alpha, and no point between 0 and
    # 0.01 m/s resolves the Stribeck velocity
    assert c.checks_["material"] and c.checks_["away_from_null"] and c.checks_["improves_holdout"]
    assert not c.checks_["significant"] and not c.checks_["resolved"]
    assert 0.01 < c.p_value_ < 0.1 and c.p_value_white_ < 0.02
    assert c.named_effect_ == "none"


# -- noise-free runs the JSON's model reproduces: no gap, no division by zero -----------------------
def test_noise_free_runs_without_a_gap(tmp_path, capsys):
    runs = thesis_protocol(thesis_rig(2.5), t_end=2.0, noise=None)
    for r in runs:
        write_run(r, tmp_path / "runs" / r.name)
    rc = main([str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--starts", "1", "--probe",
               "2", "--max-nfev", "2", "--jobs", "1", "--quiet"])
    assert rc == 0
    printed = capsys.readouterr().out
    rep = json.loads((tmp_path / "out" / "report.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert rep["named_effect"] == "none" and rep["no_gap"] is True
    assert rep["gap_before"] == 0.0 and rep["gap_reduction"] is None
    assert rep["gap_reduction_vs_calibrated"] is None and rep["candidates"] == []
    assert "no gap to reduce" in rep["decision"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "**no gap to reduce**" in md and "None fitted: there is no gap to reduce." in md
    assert (tmp_path / "out" / "candidates.png").stat().st_size > 1000
    assert "(no gap to reduce)" in printed and "named effect: none" in printed
    # the noise estimate is the floor, never 0, and the report says the runs look noise-free
    assert set(rep["noise_at_floor"]) == {"x", "p_drive", "p_exhaust"}
    assert all(v > 0 for v in rep["noise_sigma"].values())
    assert any("look noise-free" in w for w in rep["warnings"]) and "look noise-free" in printed
    # the Python API too; the updated model is the JSON's rig
    d = Discrepancy(**FAST).fit(runs)
    assert d.gap_reduction is None and d.named_effect_ == "none" and d.updated_model == runs[0].rig()
    assert "(no gap to reduce)" in d.summary()


def test_ambiguous_when_the_score_and_the_test_disagree():
    """Ranked by the misfit removed, tested through the term: a runner-up fitting the whitened
    residuals clearly better makes the answer ambiguous, and the decision says they disagree."""
    d = Discrepancy()
    a, b = _cand("sensor_lag", 10000.0), _cand("dead_volume", 12000.0)
    a.ssr_test, b.ssr_test = 12000.0, 9000.0
    d.candidates_, d.whiteners_ = [a, b], {}
    d._decide()
    assert d.named_effect_ == "ambiguous" and d.separation_["statistic"] < 0
    assert "disagree: sensor_lag removes more of the misfit, dead_volume fits" in d.decision_
    assert "about equally" not in d.decision_
    d.candidates_ = [_cand("leakage", 10000.0), _cand("heat_transfer", 10000.5)]
    d._decide()
    assert "explain the data about equally" in d.decision_


def test_exact_fits_and_zero_noise_do_not_divide_by_zero(protocol_runs):
    from pneugym.discrepancy.residuals import NOISE_FLOOR, noise_at_floor
    from pneugym.discrepancy.workflow import reduction, z_score
    clean = [simulate_run(thesis_rig(2.5), t_end=0.5, noise=None)]
    sigma = estimate_noise(clean)
    assert sigma == {c: NOISE_FLOOR[c] for c in ("x", "p_drive", "p_exhaust")}
    assert noise_at_floor(sigma) == ["x", "p_drive", "p_exhaust"]
    assert noise_at_floor(estimate_noise(protocol_runs[1])) == []
    # an exact fit of a real misfit is infinitely significant, not "not significant"
    assert f_test(100.0, 0.0, 1, 3, 50.0) == (math.inf, 0.0)
    assert lr_test(100.0, 0.0, 50.0) == (math.inf, 0.0)
    assert f_test(0.0, 0.0, 1, 3, 50.0) == (0.0, 1.0) and lr_test(0.0, 0.0, 50.0) == (0.0, 1.0)
    # a zero standard error: an effect at its null is not away from it
    assert z_score(0.0, 0.0, 0.0) == 0.0 and z_score(1e-7, 0.0, 0.0) == math.inf
    assert z_score(3e-7, 0.0, 1e-7) == pytest.approx(3.0)
    assert reduction(0.0, 0.0) is None and reduction(1e-12, 1e-3) is None
    assert reduction(0.1, 0.025) == pytest.approx(0.75)
    # a candidate fitting exactly is separated from one that does not
    d = Discrepancy()
    d.candidates_ = [_cand("leakage", 0.0), _cand("heat_transfer", 100.0)]
    d._decide()
    assert d.named_effect_ == "leakage"


# -- the CLI: an empty --out, plant failures ------------------------------------------------------
def test_cli_refuses_an_empty_out(tmp_path, capsys, monkeypatch):
    stem = write_run(simulate_run(thesis_rig(2.5), t_end=0.1, noise=None), tmp_path / "runs" / "r")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(Discrepancy, "fit", lambda *a: pytest.fail("fit started with --out ''"))
    for out in ("", "  "):
        assert main([str(stem), "--out", out]) == 2
        err = capsys.readouterr().err
        assert f"--out {out!r} is empty" in err and "current folder" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # nothing written here


def test_report_refuses_an_empty_folder(leak_case, tmp_path, monkeypatch):
    *_, d, _ = leak_case
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="report folder '' is empty"):
        d.report("")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("error", [
    SimulationError("simulation went non-physical at t = 0.3 s: a non-finite value (NaN/inf)"),
    ValueError("schedule[0] time = 1e9 s is more than 3600 s in one call"),
])
def test_cli_turns_plant_failures_into_exit_2_naming_the_run(tmp_path, capsys, monkeypatch, error):
    from pneugym.discrepancy import residuals
    stem = write_run(simulate_run(thesis_rig(2.5), t_end=0.1, noise=None), tmp_path / "r")

    class FailingPlant:
        def __init__(self, params):
            pass

        def run(self, *a, **k):
            raise error
    monkeypatch.setattr(residuals, "Plant", FailingPlant)
    assert main([str(stem), "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: run 'r' (") and str(stem.with_suffix(".csv")) in err
    assert str(error) in err and "Traceback" not in err
    with pytest.raises(type(error), match=r"run 'r' \(.*r\.csv\): "):  # replay names the run
        replay(read_run(stem), thesis_rig(2.5))


# -- predict and score are bounded like the fit -------------------------------------------------------
def test_predict_and_score_are_bounded_like_the_fit(leak_case, single_long_run, monkeypatch):
    from pneugym.discrepancy import residuals
    _, _, runs, d, _ = leak_case
    long_run, _, _ = single_long_run
    simulated = []
    real_plant = residuals.Plant

    class Recording(real_plant):
        def run(self, t_end, *a, **k):
            simulated.append(t_end)
            return super().run(t_end, *a, **k)
    monkeypatch.setattr(residuals, "Plant", Recording)
    p = d.predict(long_run)  # 120 s at 1 kHz: cut and averaged as the fit would
    assert max(simulated) <= MAX_WINDOW_S + 1.0
    assert len(p["t"]) <= d.max_samples and p["t"][-1] <= MAX_WINDOW_S
    assert all(a.shape == p["t"].shape for a in p.values())
    (prep,) = d.prepared([long_run])
    np.testing.assert_array_equal(p["t"], prep.t)
    simulated.clear()
    assert math.isfinite(d.score([long_run])) and max(simulated) <= MAX_WINDOW_S + 1.0
    # a short run is predicted at its own samples, as before
    short = d.predict(runs[0])
    np.testing.assert_array_equal(short["t"], runs[0].t)
    assert short["x"].shape == runs[0].x.shape


def test_each_runs_own_friction_and_a_calibration_on_it():
    """Friction that varies from run to run: :func:`own_friction` fits each run's and states it;
    the workflow then fits one factor on each run's friction (the same transformed variable as
    the absolute fit), and on runs stating one friction it fits the friction itself."""
    from pneugym.discrepancy.fit import own_friction

    known = thesis_rig(2.5)
    absolute = nominal_params(known, extended=False)
    relative = nominal_params(known, extended=False, relative_friction=True)
    for a, r in zip(absolute, relative):
        if a.path.startswith("friction."):
            assert r.relative and r.stated(known) == 1.0 and r.unit == "x stated"
            stated = float(getattr(known.friction, r.name))
            assert r.to_u(1.3) == pytest.approx(a.to_u(1.3 * stated))
            assert (r.lo * stated, r.hi * stated) == pytest.approx((a.lo, a.hi))
        else:
            assert r == a
    runs = []
    for k, f in enumerate((0.8, 1.25)):
        truth = known.with_(friction={"coulomb_n": f * known.friction.coulomb_n,
                                      "viscous_n_s_per_m": f * known.friction.viscous_n_s_per_m})
        runs.append(simulate_run(truth, t_end=1.5, sample_rate_hz=200.0, noise="default",
                                 known=known, seed=k, name=f"f{f}"))
    own = own_friction(runs)
    sigma = estimate_noise(runs)
    for before, after in zip(runs, own):
        rms = [float(np.sqrt(np.mean(((r.x - replay(r, r.rig())["x"]) / sigma["x"]) ** 2)))
               for r in (before, after)]
        assert rms[1] < 0.2 * rms[0], rms  # its own friction reproduces each run's motion
    stated = [r.rig().friction for r in own]
    assert stated[1].viscous_n_s_per_m + 0.2 * stated[1].coulomb_n > \
        stated[0].viscous_n_s_per_m + 0.2 * stated[0].coulomb_n  # more friction where there is
    quick = {**FAST, "n_starts": 1, "n_probe": 2, "max_nfev": 10}
    wf = Discrepancy(["dead_volume"], calibrate="basic", holdout=None, **quick).fit(own)
    assert wf.relative_friction_
    assert all(p.relative for p in wf.nominal_params_ if p.path.startswith("friction."))
    assert wf.named_effect_ == "none", wf.decision_
    assert not Discrepancy(["dead_volume"], calibrate="basic", holdout=None, **quick) \
        .fit(runs[:1]).relative_friction_


def test_the_bench_reads_every_model_form_from_one_run(capsys, load_bench):
    """``bench_discrepancy.py --line-models`` / ``--orifice-models``: every case records each
    model form's answer, so one run gives the matrix of the form chosen and the stated form's
    (the default workflow's); results written before the orifice laws (``line_fits``) read too."""
    bench = load_bench("bench_discrepancy")

    def row(truth, fd, lumped, chosen, old=False):
        fits = {"fd+thesis": {"named": fd, "gap_calibrated": 0.02, "gap_after": 0.01},
                "lumped+iso6358": {"named": lumped, "gap_calibrated": 0.015, "gap_after": 0.004}}
        for m, v in fits.items():
            v["kept"] = m == chosen
        out = {"truth": truth, "named": fits[chosen]["named"], "gap_before": 0.1,
               "gap_calibrated": fits[chosen]["gap_calibrated"], "gap_after": fits[chosen]["gap_after"],
               "gap_reduction": 1 - fits[chosen]["gap_after"] / 0.1,
               "gap_reduction_vs_calibrated": 1 - fits[chosen]["gap_after"] / fits[chosen]["gap_calibrated"],
               "noise_floor": 0.002, "wall_s": 1.0, "line_model": chosen.split("+")[0]}
        if old:  # as bench results of line models only were written
            return {**out, "line_fits": {m.split("+")[0]: {k: x for k, x in v.items() if k != "kept"}
                                         for m, v in fits.items()}}
        return {**out, "form_fits": fits}

    rows = [row("leakage", "none", "leakage", "lumped+iso6358"), row("none", "none", "sensor_lag", "fd+thesis"),
            row("none", "none", "sensor_lag", "lumped+iso6358"), row("none", "none", "leakage", "fd+thesis", old=True)]
    out = bench.summarise(rows)
    assert out["name_accuracy"] == 1.0 and out["control_accuracy"] == 2 / 3
    assert out["form_chosen"] == {"lumped+iso6358": 2, "fd+thesis": 1, "fd": 1}
    stated = out["stated_form_only"]
    assert stated["name_accuracy"] == 0.0 and stated["control_accuracy"] == 1.0
    assert stated["confusion"]["leakage"]["none"] == 1
    assert "the same cases on the stated form only" in capsys.readouterr().out


def test_runs_the_workflow_cannot_fit_honestly_are_refused(protocol_runs, tmp_path):
    """Runs built in Python are checked as the CSV reader checks files (a NaN gave 'no gap'),
    and so is what no file check sees: a run given twice (by name, or a copy under another
    name, which could be held out against itself), runs of two rigs, a supply column far from
    the stated set-point (gauge written as absolute), too few samples to estimate the noise."""
    import dataclasses

    from pneugym.discrepancy.workflow import check_runs

    known, runs = protocol_runs
    check_runs(runs)
    quick = {**FAST, "n_starts": 1, "n_probe": 2, "max_nfev": 5}

    def changed(run, **kw):
        return dataclasses.replace(run, **kw)

    bad_p = runs[0].p_drive.copy()
    bad_p[10] = np.nan
    cases = [
        ([changed(runs[0], p_drive=bad_p), *runs[1:]], "NaN"),
        ([runs[0], changed(runs[1], name=runs[0].name), runs[2]], "same name"),
        ([*runs, changed(runs[0], name="copy")], "same samples"),
        ([changed(r, t=r.t[:20], valve=r.valve[:20], x=r.x[:20], p_drive=r.p_drive[:20],
                  p_exhaust=r.p_exhaust[:20]) for r in runs], "fewer than 50"),
        ([runs[0], changed(runs[1], meta={**runs[1].meta, "rig": {
            **runs[1].meta.get("rig", {}), "line_length_m": 2.0}}), runs[2]],
         "another cylinder or line"),
        ([changed(runs[0], p_supply=np.full(len(runs[0]), known.supply_pressure_gauge_pa)),
          *runs[1:]], "column written as gauge"),
    ]
    for given, msg in cases:
        with pytest.raises(ValueError, match=msg):
            Discrepancy(["leakage"], **quick).fit(given)
    with pytest.raises(ValueError, match="given twice"):
        Discrepancy(["leakage", "leakage"])
    wf = Discrepancy(["leakage"], **quick)
    with pytest.raises(RuntimeError, match="fit"):
        wf.report(tmp_path / "r")
    assert not (tmp_path / "r").exists()
    for what in ("updated_model", "held_out_tested", "gap_before"):
        with pytest.raises(RuntimeError, match="fit"):
            getattr(wf, what)
    wf = Discrepancy(["leakage"], holdout=None, **quick).fit(runs[:1])
    with pytest.raises(ValueError, match="NaN"):
        wf.score([cases[0][0][0]])


def test_runs_stating_their_own_discharge_coefficients_get_one_factor_on_each():
    """As with friction: runs whose JSON state different coefficients keep them, scaled by one
    fitted factor (one absolute value for all made the model 55 times worse than the input)."""
    known = thesis_rig(2.5)
    rel = nominal_params(known, extended=False, relative_cd=0.9)[0]
    assert rel.path == "valve.discharge_coefficient" and rel.relative
    assert rel.stated(known) == 1.0 and rel.hi == pytest.approx(1 / 0.9)
    runs = [simulate_run(known.with_(valve={"discharge_coefficient": cd}), t_end=1.5,
                         sample_rate_hz=200.0, noise="default", seed=k, name=f"run{k}",
                         cut_on_arrival=k == 1)
            for k, cd in enumerate((0.72, 0.55, 0.72))]
    quick = {**FAST, "n_starts": 1, "n_probe": 2, "max_nfev": 10}
    wf = Discrepancy(["dead_volume"], calibrate="basic", holdout=None, **quick).fit(runs)
    assert wf.nominal_params_[0].relative
    assert wf.gap_after < 1.1 * wf.gap_before  # (one value for all: 50 times the gap)
