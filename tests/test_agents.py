"""Tests of the baselines in ``agents/``: the common ``predict`` interface, the conventional and
end-stroke schemes, the Gas-Law rule (eq. 5.1) and its calibration, the timed cut-off and the
privileged oracle (the best latched single cut-off at control-step resolution)."""
from __future__ import annotations

import math

import numba
import numpy as np
import pytest

import pneugym  # noqa: F401
from agents import (
    BASELINES, ConventionalPolicy, EndStrokePolicy, GasLawPolicy, ObservationReader, OraclePolicy,
    make_policy,
)
from agents.base import run_first_episodes
from agents.gaslaw import THESIS_K, calibrate, load_calibration, sweep
from agents.oracle import TimedCutPolicy
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffEnv, CutOffVectorEnv

NOMINAL = {"2.5": Conditions(), "1.5": Conditions(supply_pressure_gauge_pa=1.5e5)}


@pytest.fixture(scope="module", autouse=True)
def one_numba_thread():
    """One numba thread for the batched runs (see tests/test_vector_env.py)."""
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(prev)


def episode(env: CutOffEnv, policy, cond: Conditions, seed: int = 0) -> tuple[float, dict, list]:
    """Run ``policy`` for one episode under ``cond``: (return, final info, actions)."""
    obs, _ = env.reset(seed=seed, options={"conditions": cond})
    policy.begin_episodes([cond])
    rewards, actions = [], []
    while True:
        a, _ = policy.predict(obs)
        actions.append(int(a))
        obs, r, term, trunc, info = env.step(a)
        rewards.append(r)
        if term or trunc:
            return math.fsum(rewards), info, actions


def batch_returns(policy_cls, conds, **kwargs) -> np.ndarray:
    env = CutOffVectorEnv(num_envs=len(conds))
    pol = policy_cls(env.observation_layout(), **kwargs)
    return run_first_episodes(env, pol, conds, seed=0)["objective"]


@pytest.fixture(scope="module")
def oracle() -> OraclePolicy:
    """One oracle, with the nominal plans computed once (~0.4 s per condition)."""
    pol = OraclePolicy.for_env(CutOffEnv())
    for c in NOMINAL.values():
        pol.plan(c)
    return pol


# --- interface ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(set(BASELINES) - {"mpc-rig"}))  # (needs a rig model:
def test_predict_on_one_observation_and_a_batch(name):                 # tests/test_commission.py)
    rig = name == "mpc"  # it reads the rig's datasheet values
    env = CutOffEnv(history=2, observe_rig=rig)
    pol = make_policy(name, env)
    assert pol.name == name
    obs, info = env.reset(seed=0)
    if pol.needs_conditions:  # the oracle and gaslaw-rig plan on each episode's conditions
        with pytest.raises(RuntimeError, match="begin_episodes"):
            pol.predict(obs)
        pol.begin_episodes([Conditions(**info["conditions"])])
    a, state = pol.predict(obs, state="s", episode_start=np.array([True]))
    assert isinstance(a, (int, np.integer)) and a in (0, 1) and state == "s"
    with pytest.raises(ValueError, match="another environment's layout"):
        pol.predict(obs[: pol.read.size // 2])
    with pytest.raises(ValueError, match="NaN"):
        pol.predict(np.full_like(obs, np.nan))
    batch = np.stack([obs] * 5)
    if pol.needs_conditions:  # one condition per row
        with pytest.raises(ValueError, match="told 1 episodes"):
            pol.predict(batch)
        pol.begin_episodes([Conditions(**info["conditions"])] * 5)
    acts, _ = pol.predict(batch)
    assert acts.shape == (5,) and acts.dtype == np.int64
    assert np.array_equal(acts, np.full(5, a))
    vec = CutOffVectorEnv(num_envs=3, history=2, observe_rig=rig)
    assert make_policy(name, vec).read.size == pol.read.size


def test_make_policy_unknown_name():
    with pytest.raises(ValueError, match="ppo_best"):
        make_policy("ppo_best", CutOffEnv())


def test_observation_reader_reads_the_newest_sample():
    env = CutOffEnv(history=3, observe_params=True)
    read = ObservationReader(env.observation_layout())
    obs, _ = env.reset(seed=0)
    for _ in range(80):
        obs, _, _, _, info = env.step(0)
    assert read(obs[None], "time")[0] == pytest.approx(info["time_s"], abs=1e-6)
    assert read(obs[None], "position")[0] == pytest.approx(info["position_m"], abs=1e-6)
    with pytest.raises(KeyError, match="load_mass"):
        read(obs[None], "load_mass")


# --- conventional and end-stroke ------------------------------------------------------------
def test_conventional_never_cuts():
    env = CutOffEnv(preset="randomized")
    pol = ConventionalPolicy.for_env(env)
    for seed in range(3):
        ret, fi, actions = episode(env, pol, env.space.sample(np.random.default_rng(seed)))
        assert not any(actions) and fi["cutoff_time_s"] is None
        assert ret == pytest.approx(-1.0 - 0.5 * fi["stick_slip_events"], abs=1e-4)


def test_end_stroke_cuts_once_at_the_stroke():
    env = CutOffEnv(history=2)
    pol = EndStrokePolicy.for_env(env)
    lay = env.observation_layout()
    stroke = lay["features"][0]["scale"]
    assert pol.stroke_m == stroke
    obs = np.zeros((4, lay["size"]), dtype=np.float32)
    obs[:, 7] = [0.0, 0.5, (stroke - 1e-3) / stroke, 1.0]  # newest sample's position
    obs[3, 0] = 0.0  # an old sample does not count
    assert pol.act(obs).tolist() == [0, 0, 0, 1]
    obs[:, 7] = 0.0
    obs[:, 0] = 1.0
    assert pol.act(obs).tolist() == [0, 0, 0, 0]
    ret, fi, actions = episode(env, pol, Conditions())
    first = actions.index(1)
    assert all(actions[first:]) and not any(actions[:first])
    assert fi["completed"] and fi["stroke_time_s"] - 0.02 <= fi["cutoff_time_s"]
    with pytest.raises(ValueError, match="tolerance_m"):
        EndStrokePolicy(lay, tolerance_m=-1.0)


# --- Gas-Law --------------------------------------------------------------------------------
def test_gaslaw_huge_k_never_cuts_and_zero_k_cuts_on_pressure():
    env = CutOffEnv()
    ret, fi, actions = episode(env, GasLawPolicy.for_env(env, k=1e9), Conditions())
    assert not any(actions) and ret == pytest.approx(-1.0, abs=1e-6)
    zero = GasLawPolicy.for_env(env, k=0.0)
    obs, _ = env.reset(seed=0)
    seen = []
    while True:
        p = float(zero.read(obs[None], "p_drive")[0])
        a, _ = zero.predict(obs)
        assert a == int(p > 0.0)
        seen.append(a)
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    assert seen[0] == 0 and 1 in seen  # cuts once the driving port sees pressure
    assert fi is not None and info["cutoff_time_s"] is not None
    assert info["cutoff_time_s"] < 0.3


def test_gaslaw_k_table_and_options():
    env = CutOffEnv()
    table = load_calibration()
    assert set(table) >= {1.5, 2.5} and all(k > 0 for k in table.values())
    pol = GasLawPolicy.for_env(env)
    np.testing.assert_allclose(pol.k_for(np.array([1.5e5, 2.5e5])), [table[1.5], table[2.5]])
    mid = pol.k_for(np.array([2.25e5]))[0]
    assert min(table[2.0], table[2.5]) <= mid <= max(table[2.0], table[2.5])
    assert THESIS_K["experiment"] == {1.5: 0.1, 2.5: 0.2}
    per_row = GasLawPolicy.for_env(env, k=np.array([0.0, 1e9]))
    obs, _ = env.reset(seed=0)
    for _ in range(70):
        obs, *_ = env.step(0)
    assert per_row.act(np.stack([obs, obs])).tolist() == [1, 0]
    for bad in ({"pressure": "psi"}, {"volume": "bore"}, {"n": -1.0}, {"k": -0.5},
                {"k": {2.5: math.nan}}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            GasLawPolicy.for_env(env, **bad)


def test_gaslaw_sweep_and_calibrate_smoke():
    ks = [0.5, 2.0, 1e9]
    j = sweep(2.5, ks)
    assert j.shape == (3,)
    assert j[2] == pytest.approx(-1.0, abs=1e-6)  # never cuts: conventional
    # the same as running the policy by hand
    env = CutOffEnv()
    ret, *_ = episode(env, GasLawPolicy.for_env(env, k=2.0), Conditions())
    assert j[1] == pytest.approx(ret, abs=1e-9)
    res = calibrate(supplies_bar=(2.5,), ks=ks)
    row = res["table"][0]
    assert row["supply_bar_gauge"] == 2.5 and row["k"] == ks[int(np.argmax(j))]
    assert row["return"] == pytest.approx(float(np.max(j)))
    assert res["returns"]["2.5"] == pytest.approx(list(j))


def test_gaslaw_calibration_file_is_current():
    """The shipped K table reproduces its own recorded returns (re-run ``python -m
    agents.gaslaw`` after a change of the plant or the reward)."""
    import json

    from agents.gaslaw import CALIBRATION_FILE

    data = json.loads(CALIBRATION_FILE.read_text())
    row = next(r for r in data["table"] if r["supply_bar_gauge"] == 2.5)
    assert sweep(2.5, [row["k"]])[0] == pytest.approx(row["return"], abs=1e-6)


# --- timed cut-off and oracle ---------------------------------------------------------------
def test_timed_cut_policy_cuts_from_its_time():
    env = CutOffEnv()
    ret, fi, actions = episode(env, TimedCutPolicy.for_env(env, t_cut_s=0.9), Conditions())
    assert fi["cutoff_time_s"] == pytest.approx(0.9)
    assert actions.index(1) == 180 and all(actions[180:])
    ret, fi, actions = episode(env, TimedCutPolicy.for_env(env), Conditions())
    assert not any(actions)


@pytest.mark.parametrize("bar", sorted(NOMINAL))
def test_oracle_beats_every_timed_cut_and_the_baselines(oracle, bar):
    cond = NOMINAL[bar]
    t_best, j_best = oracle.plan(cond)
    assert math.isfinite(t_best) and j_best > -1.0
    # every 10th control step, never, and the steps next to the oracle's
    grid = np.concatenate([np.arange(0, 260, 10) * 0.005, [math.inf],
                           t_best + 0.005 * np.array([-2, -1, 1, 2])])
    j_grid = batch_returns(TimedCutPolicy, [cond] * grid.size, t_cut_s=grid)
    assert j_best >= j_grid.max() - 1e-12
    assert j_grid[np.isinf(grid)][0] == pytest.approx(-1.0, abs=1e-6)
    for cls in (ConventionalPolicy, EndStrokePolicy, GasLawPolicy):
        assert j_best >= batch_returns(cls, [cond])[0] - 1e-12, cls.name
    # running the oracle's own plan gives the return it promised
    env = CutOffEnv()
    ret, fi, _ = episode(env, oracle, cond)
    assert ret == pytest.approx(j_best, abs=1e-9)
    assert fi["cutoff_time_s"] == pytest.approx(t_best)


def test_oracle_is_privileged(oracle):
    env = CutOffEnv()
    lay = env.observation_layout()
    fresh = OraclePolicy(lay)
    assert fresh.privileged
    # without the conditions it has no plan: it refuses to act (it never cut, silently)
    obs, _ = env.reset(seed=0)
    with pytest.raises(RuntimeError, match="begin_episodes"):
        fresh.predict(obs)
    # told the conditions, it cuts at its planned time
    t_best, _ = oracle.plan(NOMINAL["2.5"])
    oracle.begin_episodes([NOMINAL["2.5"], NOMINAL["1.5"]])
    np.testing.assert_allclose(oracle.t_cut_s, [t_best, oracle.plan(NOMINAL["1.5"])[0]])
    obs = np.zeros((2, lay["size"]), dtype=np.float32)
    obs[:, 5] = (t_best + 0.001) / lay["features"][5]["scale"]
    assert oracle.predict(obs)[0][0] == 1
    obs[:, 5] = (t_best - 0.01) / lay["features"][5]["scale"]
    assert oracle.predict(obs)[0][0] == 0
    # the plan depends on the conditions (more load: a different cut-off)
    heavy = Conditions(load_mass_kg=25.0)
    assert oracle.plan(heavy) != oracle.plan(NOMINAL["2.5"])
    # noise does not change the plan (cached per physics)
    noisy = Conditions(pressure_noise_pa=300.0)
    assert oracle.plan(noisy) == oracle.plan(NOMINAL["2.5"])
    with pytest.raises(ValueError, match="coarse"):
        OraclePolicy(lay, coarse=0)


def test_every_step_search_tries_every_control_step(oracle):
    """``returns_many`` with ``coarse=1``: every control step up to the conventional stroke's
    end and the window, and never cutting; its best is the default search's plan or better, and
    equals it where the returns are smooth (the thesis rig at 2.5 bar)."""
    env = CutOffEnv()
    full = OraclePolicy(env.observation_layout(), coarse=1)
    cond = NOMINAL["2.5"]
    (js,) = full.returns_many([cond])
    steps = sorted(round(t / full.period) for t in js if math.isfinite(t))
    assert math.inf in js and steps == list(range(steps[-1] + 1)) and steps[-1] > 150
    t_best, j_best = oracle.plan(cond)
    assert max(js.values()) == pytest.approx(j_best, abs=1e-12) and js[t_best] == j_best
    (coarse,) = oracle.returns_many([cond])  # the default search tries fewer
    assert set(coarse) < set(js) and all(js[t] == v for t, v in coarse.items())


def test_a_gas_law_calibration_file_loads_with_the_formula_it_was_made_for(tmp_path):
    """K holds for the rule's options it was calibrated with (recorded as ``policy``)."""
    import json

    from agents.gaslaw import CALIBRATION_FILE
    from agents.registry import load_policy

    data = json.loads(CALIBRATION_FILE.read_text())
    data["policy"] = {"pressure": "absolute", "volume": "position", "n": 1.4}
    f = tmp_path / "k.json"
    f.write_text(json.dumps(data))
    pol = load_policy(f, CutOffEnv())
    assert (pol.pressure, pol.volume, pol.n) == ("absolute", "position", 1.4)
    data["policy"] = {"exponent": 2}
    f.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="policy"):
        load_policy(f, CutOffEnv())
