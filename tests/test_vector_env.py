"""Tests of the batched :class:`pneugym.envs.cutoff.CutOffVectorEnv` (the ``vector_entry_point``
of ``pneugym/CutOff-v0``) and of its stable-baselines3 adapter
:class:`pneugym.envs.sb3.CutOffVecEnv`."""
from __future__ import annotations

import math

import gymnasium as gym
import numba
import numpy as np
import pytest

import pneugym  # noqa: F401
from agents import EndStrokePolicy
from agents.base import run_first_episodes
from pneugym.envs import ENV_ID, Conditions
from pneugym.envs.cutoff import CutOffEnv, CutOffVectorEnv
from pneugym.envs.sb3 import CutOffVecEnv

FINAL_KEYS = {"saving_ratio", "energy_wasted_j", "energy_conventional_j", "air_mass_kg", "free_air_nl",
              "stroke_time_s", "conventional_stroke_time_s", "time_increase", "cutoff_time_s",
              "stalled", "stick_slip_events", "completed", "objective"}
QUIET = {"position_noise_m": 0.0, "pressure_noise_pa": 0.0}


@pytest.fixture(autouse=True)
def one_numba_thread():
    """Step the batches on one numba thread: on a loaded 2-core machine, the parallel kernel's
    barrier makes 2 threads several times slower. ``prange`` results do not depend on it;
    :func:`test_sub_env_i_reproduces_single_env_seeded_s_plus_i` runs on all threads."""
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(prev)


def make_vec(n: int, **config) -> CutOffVectorEnv:
    return gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", **config)


def test_make_vec_returns_the_batched_env():
    env = make_vec(3, preset="randomized", history=2)
    assert type(env) is CutOffVectorEnv
    assert env.num_envs == 3 and env.max_episode_steps == 800
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert env.observation_space.shape == (3, 14) and env.observation_space.dtype == np.float32
    assert env.single_action_space == gym.spaces.Discrete(2)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert set(info["conditions"]) == set(Conditions.__dataclass_fields__)
    obs, rew, term, trunc, info = env.step(np.zeros(3, dtype=np.int64))
    assert env.observation_space.contains(obs)
    assert rew.shape == term.shape == trunc.shape == (3,)
    assert term.dtype == bool and trunc.dtype == bool
    for k in ("time_s", "position_m", "p_drive_pa", "p_exhaust_pa", "supply_cut"):
        assert info[k].shape == (3,) and info["_" + k].all()
    with pytest.raises(ValueError, match="num_envs"):
        CutOffVectorEnv(num_envs=0)
    with pytest.raises(ValueError, match="histroy"):
        CutOffVectorEnv(num_envs=2, histroy=2)
    with pytest.raises(ValueError, match="list of 2 such seeds"):
        CutOffVectorEnv(num_envs=2).reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="conditions"):
        CutOffVectorEnv(num_envs=2).reset(options={"conditions": [Conditions()]})
    with pytest.raises(RuntimeError, match="reset"):
        CutOffVectorEnv(num_envs=2).step([0, 0])


def test_sub_env_i_reproduces_single_env_seeded_s_plus_i():
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)  # the parallel path, all threads
    n, seed = 3, 40
    # conditions (noise included) come from the sub-environment's own generator
    vec = CutOffVectorEnv(num_envs=n, preset="randomized")
    _, info = vec.reset(seed=seed)
    for i in range(n):
        c = CutOffEnv(preset="randomized").reset(seed=seed + i)[1]["conditions"]
        assert {k: info["conditions"][k][i] for k in c} == c
    # noise-free: the whole trajectory (observations, rewards) is the single environment's
    vec = CutOffVectorEnv(num_envs=n, preset="randomized", conditions=QUIET, time_limit_s=0.9)
    singles = [CutOffEnv(preset="randomized", conditions=QUIET, time_limit_s=0.9)
               for _ in range(n)]
    obs, _ = vec.reset(seed=seed)
    for i, e in enumerate(singles):
        np.testing.assert_array_equal(obs[i], e.reset(seed=seed + i)[0])
    done = np.zeros(n, dtype=bool)
    for k in range(200):
        a = np.array([int(k >= 100 + 20 * i) for i in range(n)])
        obs, rew, term, trunc, info = vec.step(a)
        for i, e in enumerate(singles):
            if done[i]:
                continue
            o, r, t1, t2, inf = e.step(a[i])
            assert rew[i] == r and term[i] == t1 and trunc[i] == t2
            if t1 or t2:
                np.testing.assert_array_equal(info["final_obs"][i], o)
                assert {k: info["final_info"][k][i] for k in FINAL_KEYS} == \
                    {k: inf[k] for k in FINAL_KEYS}
                done[i] = True
            else:
                np.testing.assert_array_equal(obs[i], o)
                assert info["position_m"][i] == inf["position_m"]
        if done.all():
            break
    assert done.all()


def test_same_step_autoreset_with_final_masks():
    vec = CutOffVectorEnv(num_envs=2)
    vec.reset(seed=0)
    for k in range(100):
        obs, rew, term, trunc, info = vec.step(np.array([1, 0]))  # env 0 stalls at once
        if term.any():
            break
    assert term.tolist() == [True, False] and not trunc.any()
    assert info["_final_obs"].tolist() == [True, False]
    assert info["_final_info"].tolist() == [True, False]
    assert info["final_obs"][1] is None
    fo = info["final_obs"][0]
    assert fo.dtype == np.float32 and fo[6] == 1.0 and fo[5] > 0.0  # cut, time > 0
    # the observation is already the next episode's first one
    assert obs[0][5] == 0.0 and obs[0][6] == 0.0 and obs[0][0] == 0.0
    fi = info["final_info"]
    assert fi["stalled"][0] and not fi["completed"][0] and fi["cutoff_time_s"][0] == 0.0
    for key in FINAL_KEYS:
        assert fi["_" + key].tolist() == [True, False]
    # the next step goes on from the reset state
    obs, _, term, trunc, info = vec.step(np.array([0, 0]))
    assert info["time_s"][0] == pytest.approx(0.005) and info["time_s"][1] > 0.1
    assert not info["supply_cut"][0]


def test_vector_returns_equal_objectives_over_many_autoresets():
    """Random latched policies on a randomized batch: every episode's dense return is its
    final objective, through same-step autoresets."""
    n = 8
    vec = CutOffVectorEnv(num_envs=n, preset="randomized")
    vec.reset(seed=5)
    rng = np.random.default_rng(0)
    ret = np.zeros(n)
    ended = 0
    for k in range(700):
        a = (rng.random(n) < 0.01).astype(np.int64)
        obs, rew, term, trunc, info = vec.step(a)
        ret += rew
        assert vec.single_observation_space.contains(obs[0])
        for i in np.flatnonzero(term | trunc):
            assert ret[i] == pytest.approx(info["final_info"]["objective"][i], abs=1e-9)
            ret[i] = 0.0
            ended += 1
    assert ended >= n


def test_vector_figures_equal_single_env_figures():
    conds = [Conditions(), Conditions(supply_pressure_gauge_pa=1.5e5),
             Conditions(load_mass_kg=25.0, friction_scale=1.2),
             Conditions(dip_start_s=0.4, dip_duration_s=0.3, dip_depth=0.3)]
    vec = CutOffVectorEnv(num_envs=len(conds))
    pol = EndStrokePolicy.for_env(vec)
    figs = run_first_episodes(vec, pol, conds, seed=0)
    assert FINAL_KEYS <= set(figs)
    single = CutOffEnv()
    for i, c in enumerate(conds):
        obs, _ = single.reset(seed=0, options={"conditions": c})
        while True:
            obs, _, term, trunc, info = single.step(pol.predict(obs)[0])
            if term or trunc:
                break
        for k in FINAL_KEYS:
            assert figs[k][i] == info[k], (i, k)


def test_vector_time_limit_and_forced_conditions():
    vec = CutOffVectorEnv(num_envs=2, time_limit_s=0.3)
    obs, info = vec.reset(seed=0, options={"conditions": [Conditions(load_mass_kg=5.0),
                                                           {"load_mass_kg": 20.0}]})
    assert info["conditions"]["load_mass_kg"].tolist() == [5.0, 20.0]
    for _ in range(60):
        obs, rew, term, trunc, info = vec.step(np.zeros(2, dtype=np.int64))
    # 0.3 s / 5 ms = 60 steps: both were truncated on the 60th
    assert trunc.all() and not term.any()
    assert not info["final_info"]["completed"].any()


def test_step_count_truncation_reports_real_figures():
    """A stroke at 1 ms needs ~1200 steps: the registered 800 truncate it, and the episode's
    books are closed (real wasted energy, the not-completed penalty in the return)."""
    vec = make_vec(1, control_period_s=0.001)
    vec.reset(seed=0)
    ret = 0.0
    for _ in range(800):
        _, rew, term, trunc, info = vec.step(np.zeros(1, dtype=np.int64))
        ret += rew[0]
    assert trunc[0] and not term[0]
    fi = info["final_info"]
    assert fi["energy_wasted_j"][0] > 0.0 and fi["saving_ratio"][0] < 1.0
    assert not fi["completed"][0] and fi["stroke_time_s"][0] is None
    assert fi["objective"][0] < -2.0  # not completed: w_stall applies
    assert ret == pytest.approx(fi["objective"][0], abs=1e-9)


def test_final_info_none_stays_none():
    """Sub-environments ending in the same step, one cut and one not: ``None`` stays ``None``
    whatever the order."""
    for actions in ([1, 0], [0, 1]):
        vec = CutOffVectorEnv(num_envs=2, time_limit_s=0.1)
        vec.reset(seed=0)
        for _ in range(20):
            _, _, term, trunc, info = vec.step(np.array(actions))
        assert trunc.all()
        cut = info["final_info"]["cutoff_time_s"]
        assert cut[actions.index(1)] == 0.0 and cut[actions.index(0)] is None
        assert info["final_info"]["stalled"].dtype == bool
        assert info["final_info"]["stick_slip_events"].dtype == np.int64


def test_info_after_autoreset_is_the_new_episode():
    """As in gymnasium's SyncVectorEnv (same-step): the step's info of a reset sub-environment
    is its new episode's, conditions included (a privileged policy needs them)."""
    vec = CutOffVectorEnv(num_envs=2, preset="randomized", conditions=QUIET)
    vec.reset(seed=0)
    while True:
        obs, _, term, trunc, info = vec.step(np.array([1, 0]))
        if term[0] or trunc[0]:
            break
    assert info["time_s"][0] == 0.0 and info["position_m"][0] == 0.0
    assert info["time_s"][1] > 0.0
    assert info["_conditions"].tolist() == [True, False]
    new = {k: info["conditions"][k][0] for k in Conditions.__dataclass_fields__}
    assert new == vec.conditions[0].to_dict()


def test_autoreset_off_idles_finished_sub_envs():
    vec = CutOffVectorEnv(num_envs=2, autoreset=False)
    assert vec.metadata["autoreset_mode"] == gym.vector.AutoresetMode.DISABLED
    vec.reset(seed=0)
    ends = 0
    for k in range(300):
        obs, rew, term, trunc, info = vec.step(np.array([1, 0]))
        if "final_info" in info:
            ends += int(info["_final_info"].sum())
        if term.all():
            break
    assert term.all() and ends == 2  # each reported once
    frozen = obs.copy()
    obs, rew, term, _, info = vec.step(np.array([1, 1]))
    assert term.all() and not rew.any() and "final_info" not in info
    np.testing.assert_array_equal(obs, frozen)


# --- the SB3 adapter ------------------------------------------------------------------------
def test_sb3_adapter_vecenv_interface():
    from stable_baselines3.common.vec_env import VecMonitor
    from stable_baselines3.common.vec_env.util import obs_space_info

    venv = CutOffVecEnv(num_envs=4, preset="randomized", time_limit_s=1.0)
    keys, shapes, dtypes = obs_space_info(venv.observation_space)
    assert shapes[None] == venv.observation_space.shape and dtypes[None] == np.float32
    mon = VecMonitor(venv)
    mon.seed(3)
    obs = mon.reset()
    assert obs.shape == (4, venv.observation_space.shape[0])
    mon.seed(3)
    np.testing.assert_array_equal(mon.reset(), obs)  # seeded resets repeat
    seen = 0
    for k in range(300):
        obs, rew, done, infos = mon.step(np.full(4, int(k > 150)))
        assert rew.dtype == np.float32 and done.dtype == bool and len(infos) == 4
        for i in np.flatnonzero(done):
            d = infos[i]
            assert d["terminal_observation"].shape == obs[i].shape
            assert isinstance(d["TimeLimit.truncated"], bool)
            assert d["episode_return"] == d["objective"]
            assert d["episode"]["r"] == pytest.approx(d["objective"], abs=1e-5)
            assert FINAL_KEYS <= set(d)
            seen += 1
    assert seen >= 4
    assert venv.get_attr("num_envs") == [4] * 4
    assert venv.env_is_wrapped(gym.Wrapper) == [False] * 4
    assert venv.observation_layout()["size"] == venv.observation_space.shape[0]
    mon.close()


def test_sb3_adapter_steps_exactly_as_the_vector_env():
    """The adapter's lean step (no per-step state info) gives the vector env's observations,
    rewards, dones and final figures, bit for bit."""
    vec = CutOffVectorEnv(num_envs=4, preset="randomized", time_limit_s=1.0)
    ada = CutOffVecEnv(num_envs=4, preset="randomized", time_limit_s=1.0)
    ada.seed(5)
    np.testing.assert_array_equal(ada.reset(), vec.reset(seed=5)[0])
    rng, ended = np.random.default_rng(0), 0
    for _ in range(400):
        a = (rng.random(4) < 0.02).astype(np.int64)
        obs, rew, term, trunc, info = vec.step(a)
        ada.step_async(a)
        obs2, rew2, done2, infos2 = ada.step_wait()
        np.testing.assert_array_equal(obs2, obs)
        np.testing.assert_array_equal(rew2, rew.astype(np.float32))
        np.testing.assert_array_equal(done2, term | trunc)
        for i in np.flatnonzero(done2):
            assert {k: infos2[i][k] for k in FINAL_KEYS} == {
                k: info["final_info"][k][i] for k in FINAL_KEYS}
            ended += 1
    assert ended >= 4


def test_a_noise_free_episode_after_noisy_ones_reads_its_sensors_exactly():
    env = CutOffVectorEnv(num_envs=2, time_limit_s=1.0)
    noisy = Conditions(position_noise_m=1e-4, pressure_noise_pa=500.0)
    env.reset(seed=0, options={"conditions": [noisy, Conditions()]})
    _, _, _, _, info = env.step(np.zeros(2, dtype=np.int64))
    assert info["measured_x_m"][0] != info["position_m"][0]
    assert info["measured_x_m"][1] == info["position_m"][1]
    env.reset(seed=0, options={"conditions": [Conditions(), Conditions()]})
    for _ in range(3):
        _, _, _, _, info = env.step(np.zeros(2, dtype=np.int64))
        np.testing.assert_array_equal(info["measured_x_m"], info["position_m"])
        np.testing.assert_array_equal(info["measured_p_drive_pa"] > 0, True)


def test_sb3_ppo_smoke():
    pytest.importorskip("torch")
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    venv = VecMonitor(CutOffVecEnv(num_envs=4, time_limit_s=1.5))
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(256)
    act, _ = model.predict(venv.reset(), deterministic=True)
    assert act.shape == (4,) and set(np.unique(act)) <= {0, 1}
    d = model.logger.name_to_value  # (the last update's figures: an update did run)
    assert d["train/n_updates"] >= 1 and math.isfinite(float(d["train/loss"]))


# --- careless input: batched actions and reset options -----------------------------------------
@pytest.mark.parametrize("actions,msg", [
    (np.array([0, 1, 1]), r"shape \(2,\)"), (np.array([[0, 1]]), r"shape \(2,\)"),
    (np.array([0, 2]), "integers 0 .keep. or 1"), (np.array([0.0, 1.0]), "dtype float64"),
    (np.array([-1, 0]), "integers 0"), (np.array(["0", "1"]), "integers 0"), (1, r"shape \(2,\)"),
])
def test_vector_actions_of_the_wrong_shape_or_value_are_refused(actions, msg):
    env = CutOffVectorEnv(num_envs=2)
    env.reset(seed=0)
    t0 = env._batch_info()["time_s"].copy()
    with pytest.raises(ValueError, match=msg):
        env.step(actions)
    assert np.array_equal(env._batch_info()["time_s"], t0)


def test_vector_actions_as_a_list_of_ints_are_taken():
    env = CutOffVectorEnv(num_envs=2)
    env.reset(seed=0)
    info = env.step([0, 1])[4]
    assert list(info["supply_cut"]) == [False, True]


@pytest.mark.parametrize("options,msg", [
    ({"condition": [Conditions()] * 2}, "did you mean 'conditions'"),
    ({"conditions": Conditions()}, "a list of one Conditions"),
    ({"conditions": [Conditions()]}, "a list of one Conditions"),
    ({"conditions": [Conditions(), {"load": 3}]}, r"options\['conditions'\]\[1\].*no field 'load'"),
])
def test_vector_reset_options_are_checked(options, msg):
    with pytest.raises(ValueError, match=msg):
        CutOffVectorEnv(num_envs=2).reset(seed=0, options=options)


@pytest.mark.parametrize("seed", [1.5, {}, "a", -1, True])
def test_vector_reset_refuses_bad_seeds(seed):
    with pytest.raises(ValueError, match="seed = "):
        CutOffVectorEnv(num_envs=2).reset(seed=seed)


def test_vector_reset_takes_numpy_integer_seeds():
    a, _ = CutOffVectorEnv(num_envs=2, preset="randomized").reset(seed=np.int64(5))
    b, _ = CutOffVectorEnv(num_envs=2, preset="randomized").reset(seed=5)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("kw,msg", [
    ({"max_episode_steps": "10"}, "max_episode_steps"), ({"max_episode_steps": -1}, "max_episode_steps"),
    ({"max_episode_steps": 0.5}, "max_episode_steps"), ({"autoreset": "no"}, "autoreset"),
    ({"observe_params": "no"}, "observe_params"), ({"reversible": "False"}, "reversible"),
    ({"history": 10**9}, "history"), ({"control_period_s": 5.0}, "control_period_s.*ms given as s"),
    ({"decision_window_s": 20.0}, "decision_window_s.*ms given as s"),
    ({"conditions": {"load_mass_kg": "15"}}, "load_mass_kg must be a number"),
    ({"conditions": {"dip_probability": None}}, "dip_probability"),
    ({"conditions": {"dip_probability": "0.5"}}, "dip_probability"),
])
def test_options_that_would_be_guessed_are_refused(kw, msg):
    with pytest.raises(ValueError, match=msg):
        CutOffVectorEnv(num_envs=1, **kw)


def test_numpy_numbers_are_good_options():
    env = CutOffVectorEnv(num_envs=1, control_period_s=np.float32(0.005),
                          conditions={"load_mass_kg": np.float32(12.0)}, reversible=np.bool_(False))
    assert env.space.load_mass_kg == (12.0, 12.0) and env.control_period_s == pytest.approx(0.005)


def test_sb3_adapter_calls_the_batched_env_once_and_refuses_partial_indices():
    venv = CutOffVecEnv(num_envs=3)
    venv.reset()
    with pytest.raises(ValueError, match="one batched env"):
        venv.env_method("step", np.zeros(3, dtype=np.int64), indices=[0, 1])
    with pytest.raises(ValueError, match="one batched env"):
        venv.set_attr("w_time", 1.0, indices=0)
    t0 = venv.unwrapped._batch_info()["time_s"].copy()
    out = venv.env_method("step", np.zeros(3, dtype=np.int64))
    assert len(out) == 3 and out[0] is out[1]
    assert np.allclose(venv.unwrapped._batch_info()["time_s"], t0 + 0.005)  # stepped once
    with pytest.raises(ValueError, match="seed"):
        venv.seed("a")


def test_sb3_adapter_takes_per_environment_conditions():
    venv = CutOffVecEnv(num_envs=2)
    c = [Conditions(load_mass_kg=5.0), Conditions(load_mass_kg=20.0)]
    venv.set_options([{"conditions": c[0]}, {"conditions": c[1]}])
    venv.reset()
    assert list(venv.unwrapped.conditions) == c
    venv.set_options([{"conditions": c[0]}, {"other": 1}])
    with pytest.raises(ValueError, match="unknown reset option 'other'"):
        venv.reset()
    # SB3's set_options(dict) gives every sub-environment the same conditions
    venv.set_options({"conditions": c[1]})
    venv.reset()
    assert list(venv.unwrapped.conditions) == [c[1], c[1]]


def test_vector_reset_without_a_seed_goes_on_with_the_seeded_streams():
    """reset(seed=s) then reset(): the second episodes' conditions repeat from run to run (as a
    gymnasium env's do), not drawn from the OS."""
    def second():
        v = CutOffVectorEnv(num_envs=2, preset="randomized")
        _, first = v.reset(seed=0)
        _, info = v.reset()
        return first["conditions"]["load_mass_kg"], info["conditions"]["load_mass_kg"]

    (a1, a2), (b1, b2) = second(), second()
    assert np.array_equal(a1, b1) and np.array_equal(a2, b2) and not np.array_equal(a1, a2)


def test_settings_changed_between_episodes_apply_to_the_next_one():
    """Episode starts are cached per conditions; the env's settings (weights, time limit, SB3's
    set_attr) are not part of that cache and apply to every episode started after the change."""
    c = Conditions(load_mass_kg=10.0)
    env = CutOffVectorEnv(num_envs=1, autoreset=False)
    env.reset(seed=0, options={"conditions": [c]})
    row = env.E[0].copy()
    env.weights = {**env.weights, "w_time": env.weights["w_time"] * 2}
    env.time_limit_s = 3.0
    env.reset(seed=0, options={"conditions": [c]})
    from pneugym.envs import episode as EP

    assert env.E[0, EP.E_W_TIME] == 2 * row[EP.E_W_TIME] and env.E[0, EP.E_T_LIMIT] == 3.0
    assert env.E[0, EP.E_T_CONV] == row[EP.E_T_CONV]  # the cached conventional stroke stays


def test_an_idle_sub_environment_keeps_its_last_observation():
    """autoreset=False: an ended sub-environment is not stepped; its observation stays (its
    history did shift, with fresh noise)."""
    env = CutOffVectorEnv(num_envs=2, autoreset=False, history=2,
                          conditions={"pressure_noise_pa": 400.0, "position_noise_m": 3e-5})
    env.reset(seed=0)
    done = np.zeros(2, dtype=bool)
    while not done[0]:
        obs, _, term, trunc, _ = env.step(np.array([1, 0]))
        done = term | trunc
    last = obs[0].copy()
    for _ in range(5):
        obs, *_ = env.step(np.array([1, 0]))
    assert np.array_equal(obs[0], last)
