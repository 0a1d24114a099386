"""The model-predictive cut-off (agents/mpc.py) and the traces it fits (pneugym/envs/rollout.py)."""
import math

import numpy as np
import pytest

from agents.base import run_first_episodes
from agents.mpc import (
    HIDDEN, ModelPredictivePolicy, fit_trace, from_unit, hidden_members, nominal, rig_changes,
    expected_best, robust_best, to_unit, with_changes,
)
from agents.oracle import OraclePolicy
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv
from pneugym.envs.family import RigFamily
from pneugym.envs.rollout import keep_traces
from pneugym.params import RigParams

PERIOD = 0.005


def test_keep_traces_are_the_environments_samples():
    """Same kernels, same sensors: the trace equals what a noise-free episode observes with the
    supply kept (to the observation's float32)."""
    cond = Conditions(supply_pressure_gauge_pa=3e5, load_mass_kg=12.0)
    env = CutOffVectorEnv(num_envs=1, autoreset=False)
    obs, _ = env.reset(seed=0, options={"conditions": [cond]})
    lay = env.observation_layout()
    names = [f["name"] for f in lay["features"]]
    scale = {f["name"]: f["scale"] for f in lay["features"]}
    rows = []
    for _ in range(100):
        rows.append([obs[0, names.index(k)] * scale[k] for k in ("position", "p_drive",
                                                                   "p_exhaust")])
        obs, *_ = env.step(np.zeros(1, dtype=np.int64))
    sim = keep_traces([cond.rig()], PERIOD, 99)[0]
    np.testing.assert_allclose(sim[:, 0], np.array(rows)[:, 0], atol=1e-6)
    np.testing.assert_allclose(sim[:, 1:], np.array(rows)[:, 1:], atol=0.1)
    assert sim[-1, 0] > 2e-3 and sim[-1, 1] > 1e5  # it moved, the driving side filled


def test_keep_traces_marks_what_cannot_run():
    out = keep_traces([None, RigParams()], PERIOD, 3)
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()
    assert np.isnan(keep_traces([None], PERIOD, 2)).all()
    with pytest.raises(ValueError, match="n_steps"):
        keep_traces([RigParams()], PERIOD, -1)
    with pytest.raises(ValueError, match="period_s"):
        keep_traces([RigParams()], 0.0, 3)


def test_unit_cube_round_trip_and_the_coulomb_bound():
    theta = nominal(RigParams())
    np.testing.assert_allclose(from_unit(to_unit(theta)), theta, rtol=1e-12)
    ch = rig_changes(np.array([0.1, 200.0, 300.0, 1000.0, 2.0, 1.0, 0.5]), RigParams())
    assert ch["friction.coulomb_n"] == pytest.approx(180.0)  # below breakaway
    assert ch["valve.area_m2"] == pytest.approx(2 * RigParams().valve.area_m2)


def test_robust_best_steps_back_from_a_cliff():
    """The best return sits next to a stall: the robust choice takes a slightly worse cut whose
    neighbours are safe; without a margin it takes the best."""
    p = PERIOD
    returns = {k * p: j for k, j in enumerate([-3.0, -3.0, -0.10, -0.12, -0.13, -0.14, -0.2])}
    returns[math.inf] = -1.0
    assert robust_best(returns, 0.0) == pytest.approx(2 * p)
    assert robust_best(returns, p) == pytest.approx(3 * p)  # its neighbours 2p, 4p are safe
    assert robust_best({math.inf: -1.0, p: -2.0}, p) == math.inf


def test_expected_best_takes_the_widest_good_window_not_a_lone_peak():
    """A lone best cut between stalls, a wide window of good cuts, and a flat late plateau (a
    stick-slip): the mean within the margin takes the window; the worst within it the plateau,
    as one stall inside any window rules it out."""
    p = PERIOD
    js = [-0.05, -3.0, -0.1, -0.12, -3.0, -0.11, -0.1, -0.1, -0.1, -0.12, -3.0, -0.6, -0.6, -0.6,
          -0.6]
    returns = {k * p: j for k, j in enumerate(js)}
    returns[math.inf] = -0.7
    assert expected_best(returns, 0.0) == robust_best(returns, 0.0) == 0.0  # the lone peak
    assert expected_best(returns, p) == pytest.approx(7 * p)  # the window's middle
    assert robust_best(returns, p) == pytest.approx(7 * p)
    assert 5 * p <= expected_best(returns, 3 * p) <= 9 * p  # still in the window
    assert robust_best(returns, 3 * p) == pytest.approx(14 * p)  # the plateau
    assert expected_best({math.inf: -1.0, p: -2.0}, p) == math.inf


@pytest.mark.parametrize("rule", [expected_best, robust_best])
def test_a_coarse_search_judges_the_chosen_cut_by_its_whole_window(rule):
    """Good cuts with rough neighbours at every fourth step, and a lone good cut between two
    stick-slips: the coarse grid never tries the stick-slips, so without settling the window the
    rule would take the lone cut. Settled, the choice is the exhaustive search's."""
    from agents.oracle import search_cuts, settle_windows

    j = {k: -1.0 for k in range(33)}
    j.update({k: -0.1 for k in (8, 12, 16)})
    j.update({k: -0.3 for k in (7, 9, 11, 13, 15, 17)})
    j[24] = -0.15
    calls = []

    def score(cands):
        calls.append({key: len(ts) for key, ts in cands.items()})
        return {key: {t: (j[round(t / PERIOD)] if math.isfinite(t) else -2.0) for t in ts}
                for key, ts in cands.items()}

    def chosen(coarse, settle):
        scores = search_cuts(score, {0: (0, 32)}, PERIOD, coarse)
        if not settle:
            return rule(scores[0], PERIOD)
        return settle_windows(score, scores, lambda k: rule(scores[k], PERIOD), {0: (0, 32)},
                              PERIOD, 1)[0]

    full = chosen(1, False)
    assert round(full / PERIOD) in (8, 12, 16)
    assert round(chosen(4, False) / PERIOD) == 24  # judged by itself alone
    calls.clear()
    assert chosen(4, True) == full
    assert len(calls) >= 3  # the search's two rounds, then the window's missing steps
    # nothing to settle without a margin, or when never cutting is chosen
    scores = {0: {0.0: -3.0, math.inf: -1.0}}
    assert settle_windows(score, scores, lambda k: math.inf, {0: (0, 32)}, PERIOD, 1) == {
        0: math.inf}


def test_rules_choose_among_the_allowed_cuts_only():
    """``allowed`` restricts the choice, not the windows: the best allowed cut by its window
    over every tried cut; an empty choice is refused."""
    p = PERIOD
    returns = {k * p: j for k, j in enumerate([-0.1, -0.2, -3.0, -0.3, -0.25])}
    returns[math.inf] = -0.28
    later = [3 * p, 4 * p, math.inf]
    assert expected_best(returns, 0.0) == 0.0
    assert expected_best(returns, 0.0, later) == pytest.approx(4 * p)
    assert robust_best(returns, 0.0, later) == pytest.approx(4 * p)
    assert robust_best(returns, p, later) == math.inf  # 4p's window holds -0.3 < -0.28
    assert expected_best(returns, p, later) == pytest.approx(4 * p)  # its mean -0.275
    with pytest.raises(ValueError, match="no allowed"):
        expected_best(returns, p, [])


def test_fit_recovers_a_rig_from_its_stroke():
    """A stroke of a rig with a slower valve, more friction and a wider valve than the rig file
    says: the fit recovers the delay and reproduces the trace far better than the rig file."""
    base = RigParams()
    load, supply = 10.0, 3e5
    truth = np.array([0.12, 420.0, 160.0, 1500.0, 1.8, 1.0, 0.7])

    def make(theta):
        c = Conditions(supply_pressure_gauge_pa=supply, load_mass_kg=load,
                       rig_changes=tuple(sorted(rig_changes(theta, base).items())))
        return c.rig(base)

    n = int(0.45 / PERIOD)
    measured = keep_traces([make(truth)], PERIOD, n)[0]
    start = to_unit(nominal(base))
    err0 = np.abs(keep_traces([make(from_unit(start))], PERIOD, n)[0] - measured)[:, 1].max()
    theta, u = fit_trace(measured, make, PERIOD, start, 12)
    err = np.abs(keep_traces([make(theta)], PERIOD, n)[0] - measured)[:, 1].max()
    assert abs(theta[0] - truth[0]) < 0.01
    assert err < 0.2 * err0
    np.testing.assert_allclose(from_unit(u), theta)


def _episodes(policy, conds, cfg):
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **cfg)
    return run_first_episodes(env, policy, conds, 7)


def test_mpc_on_the_thesis_rig_near_the_oracle():
    """On the rig it is told about (no hidden change), planning on the rig file's cushions alone,
    the plan is close to the oracle's."""
    cfg = {"observe_rig": True}
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    conds = [Conditions(supply_pressure_gauge_pa=2.5e5, load_mass_kg=10.0,
                        position_noise_m=3e-5, pressure_noise_pa=400.0),
             Conditions(supply_pressure_gauge_pa=1.5e5, load_mass_kg=5.0,
                        position_noise_m=3e-5, pressure_noise_pa=400.0)]
    mpc = _episodes(ModelPredictivePolicy.for_env(probe, prior_members=0), conds, cfg)
    orc = _episodes(OraclePolicy.for_env(probe), conds, cfg)
    conv = [-1.0, -1.0]  # a conventional stroke wastes all: J = -1 (no stick-slip here)
    frac = (mpc["objective"] - conv) / (orc["objective"] - conv)
    assert (frac > 0.9).all(), frac
    assert mpc["completed"].all() and not mpc["stalled"].any()
    # a second run of the same policy object restarts its rows: the same figures
    again = _episodes(ModelPredictivePolicy.for_env(probe, prior_members=0), conds, cfg)
    np.testing.assert_array_equal(again["objective"], mpc["objective"])


def test_mpc_with_the_prior_hedges_and_completes():
    """With the default prior over cushions and leaks the plan pays for the rigs that would
    stall: the stroke completes, saves air, and cuts no earlier than on the rig file alone."""
    cfg = {"observe_rig": True}
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    cond = [Conditions(supply_pressure_gauge_pa=2.5e5, load_mass_kg=10.0)]
    hedged = _episodes(ModelPredictivePolicy.for_env(probe), cond, cfg)
    alone = _episodes(ModelPredictivePolicy.for_env(probe, prior_members=0), cond, cfg)
    assert hedged["completed"].all() and not hedged["stalled"].any()
    assert hedged["saving_ratio"][0] > 0.3 and hedged["objective"][0] > -0.8
    # the draws of what the stroke cannot show move the cut later (1.025 s against 0.95 s)
    assert len(ModelPredictivePolicy.for_env(probe).members) == 6
    assert hedged["cutoff_time_s"][0] > alone["cutoff_time_s"][0] + 0.02


def test_hidden_members_and_changes():
    base = RigParams()
    assert hidden_members(RigFamily(), 0, base, 0) == [()]
    m = hidden_members(RigFamily(), 3, base, 5)
    assert len(m) == 3 and m == hidden_members(RigFamily(), 3, base, 5)  # seeded
    assert all([k for k, _ in h] == list(HIDDEN) for h in m)
    assert all(0.005 <= dict(h)["cylinder.cushion_length_m"] <= 0.025 for h in m)
    c = Conditions(rig_changes=(("cylinder.cushion_length_m", 0.01), ("line.length_m", 2.0)))
    merged = dict(with_changes(c, m[0]).rig_changes)
    assert merged["line.length_m"] == 2.0
    assert merged["cylinder.cushion_length_m"] == dict(m[0])["cylinder.cushion_length_m"]
    assert with_changes(c, ()) is c


def test_observation_reader_reads_the_rig_features():
    env = CutOffVectorEnv(num_envs=1, observe_rig=True)
    cond = Conditions(load_mass_kg=17.0, rig_changes=(("line.length_m", 2.5),))
    obs, _ = env.reset(seed=0, options={"conditions": [cond]})
    read = ModelPredictivePolicy.for_env(env, prior_members=0).read
    assert read(obs, "payload")[0] == pytest.approx(17.0, rel=1e-6)
    assert read(obs, "line_length")[0] == pytest.approx(2.5, rel=1e-6)


def test_mpc_needs_the_rig_features_and_valid_options():
    with pytest.raises(ValueError, match="observe_rig=True"):
        ModelPredictivePolicy.for_env(CutOffVectorEnv(num_envs=1))
    probe = CutOffVectorEnv(num_envs=1, observe_rig=True)
    for bad in ({"replan_periods": 0}, {"margin_periods": -1}, {"fit_evals": 1.5},
                {"coarse": True}, {"prior_members": -1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            ModelPredictivePolicy.for_env(probe, **bad)


def test_mpc_plans_on_the_drive_chambers_dead_volume_and_the_episodes_cylinder():
    """The observed dead volume is the driving side's in all: a rig file's extra volume at the
    port is not counted twice, and on the retract stroke it is the rod side's; a cylinder of
    the episode's own (rig_changes: design, mounting angle) is the one planned on."""
    for rig in (RigParams().with_(effects={"dead_volume_m3": 3e-4}),
                RigParams().with_(stroke_direction="retract", cylinder={"dead_volume_rod_m3": 1e-4}),
                RigParams().with_(stroke_direction="retract", cylinder={"dead_volume_m3": 1e-4})):
        env = CutOffVectorEnv(num_envs=1, observe_rig=True, rig=rig)
        obs, _ = env.reset(seed=1)
        pol = ModelPredictivePolicy.for_env(env, prior_members=0)
        planned = pol._conditions(obs, 0, nominal(pol.base)).rig(pol.base)
        for side in ("drive_dead_volume_m3", "exhaust_dead_volume_m3"):
            assert getattr(planned, side) == pytest.approx(getattr(env.rig, side), rel=1e-4)
        assert planned.effects.dead_volume_m3 == env.rig.effects.dead_volume_m3
    env = CutOffVectorEnv(num_envs=1, observe_rig=True)
    pol = ModelPredictivePolicy.for_env(env, prior_members=0)
    tilted = Conditions(rig_changes=(("cylinder.design", "single-rod"),
                                     ("cylinder.mounting_angle_deg", 60.0)))
    obs, _ = env.reset(seed=1, options={"conditions": [tilted]})
    pol.begin_episodes([tilted])
    planned = pol._conditions(obs, 0, nominal(pol.base)).rig(pol.base)
    assert planned.cylinder.design == "single-rod" and planned.cylinder.mounting_angle_deg == 60.0
