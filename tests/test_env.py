"""Tests of :class:`pneugym.envs.cutoff.CutOffEnv` (``pneugym/CutOff-v0``): registration and
options, both environment checkers, seeding, the reward and its objective, the end of an
episode, latched and reversible cut-offs, observations and rendering.

Episodes are short (a conventional stroke is ~240 control steps, ~15 ms of wall time)."""
from __future__ import annotations

import math
import warnings
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import pytest

import pneugym  # noqa: F401  (registers pneugym/CutOff-v0)
from pneugym.envs import ENV_ID, MAX_EPISODE_STEPS, OBSERVATION, PARAM_OBSERVATION, Conditions
from pneugym.envs.cutoff import OBS_BOUND, CutOffEnv
from pneugym.physics import layout as L
from pneugym.physics import system as K

STEP_KEYS = {"time_s", "position_m", "p_drive_pa", "p_exhaust_pa", "supply_cut", "measured_x_m",
             "measured_p_drive_pa", "measured_p_exhaust_pa"}
FINAL_KEYS = {"saving_ratio", "energy_wasted_j", "energy_conventional_j", "air_mass_kg", "free_air_nl",
              "stroke_time_s", "conventional_stroke_time_s", "time_increase", "cutoff_time_s",
              "stalled", "stick_slip_events", "completed"}
NF = len(OBSERVATION)

Policy = Callable[[int, np.ndarray, dict], int]


def never(k, obs, info):
    return 0


def always(k, obs, info):
    return 1


def cut_at(t_s: float) -> Policy:
    return lambda k, obs, info: int(info["time_s"] >= t_s - 1e-9)


def end_stroke(k, obs, info):
    return int(info["position_m"] >= 0.18 - 2e-4)


def run(env, policy: Policy = never, seed: int | None = 0,
        options: dict | None = None) -> dict[str, Any]:
    """One episode; returns observations, rewards, infos, and how it ended."""
    obs, info = env.reset(seed=seed, options=options)
    out = {"obs": [obs], "rewards": [], "infos": [info], "actions": []}
    k = 0
    while True:
        a = policy(k, obs, info)
        obs, r, term, trunc, info = env.step(a)
        out["obs"].append(obs)
        out["rewards"].append(r)
        out["infos"].append(info)
        out["actions"].append(a)
        k += 1
        if term or trunc:
            out.update(terminated=term, truncated=trunc, final=info,
                       ret=float(math.fsum(out["rewards"])))
            return out


def objective_from_info(fi: dict, time_limit_s: float, w_time=0.3, w_stall=2.0, w_stick=0.5):
    """The issue's objective, recomputed from the final info."""
    t = fi["stroke_time_s"] if fi["completed"] else time_limit_s
    return (-fi["energy_wasted_j"] / fi["energy_conventional_j"]
            - w_time * max(0.0, t / fi["conventional_stroke_time_s"] - 1.0)
            - w_stick * fi["stick_slip_events"] - w_stall * (not fi["completed"]))


# --- registration and options ---------------------------------------------------------------
@pytest.mark.parametrize("config", [
    {}, {"preset": "thesis-1.5bar"}, {"preset": "randomized", "history": 3},
    {"conditions": {"load_mass_kg": (5.0, 15.0)}, "reward_mode": "sparse"},
    {"control_period_s": 0.01, "time_limit_s": 3.0, "w_time": 0.0},
    {"preset": Conditions(load_mass_kg=20.0), "reversible": True, "sensor_lag_s": 0.002},
])
def test_make_with_configs(config):
    env = gym.make(ENV_ID, **config)
    assert env.spec.max_episode_steps == MAX_EPISODE_STEPS == 800
    assert isinstance(env.unwrapped, CutOffEnv)
    obs, info = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    obs, r, term, trunc, info = env.step(0)
    assert env.observation_space.contains(obs)
    assert isinstance(r, float) and isinstance(term, bool) and isinstance(trunc, bool)


def test_unknown_option_is_named():
    with pytest.raises(ValueError, match="contol_period_s"):
        gym.make(ENV_ID, contol_period_s=0.01)
    with pytest.raises(ValueError, match="render_mode"):
        CutOffEnv(render_mode="ansi")  # (gym.make wraps "human" around rgb_array itself)


@pytest.mark.parametrize("config, name", [
    ({"control_period_s": -0.005}, "control_period_s"), ({"control_period_s": 0.0}, "control_period_s"),
    ({"time_limit_s": 0.0}, "time_limit_s"), ({"decision_window_s": -1.0}, "decision_window_s"),
    ({"w_time": -0.1}, "w_time"), ({"w_stall": math.nan}, "w_stall"), ({"w_stick": -1}, "w_stick"),
    ({"sensor_lag_s": -0.01}, "sensor_lag_s"), ({"history": 0}, "history"),
    ({"history": 1.5}, "history"), ({"reward_mode": "shaped"}, "reward_mode"),
    ({"preset": "thesis-3bar"}, "thesis-3bar"), ({"conditions": {"load_mass_kg": -5.0}}, "load_mass_kg"),
    ({"conditions": {"friction_scale": (1.3, 0.7)}}, "friction_scale"),
    ({"conditions": {"payload": 3.0}}, "payload"),
])
def test_bad_values_are_named(config, name):
    with pytest.raises(ValueError, match=name):
        gym.make(ENV_ID, **config)


def test_bad_reset_conditions_are_named():
    env = CutOffEnv()
    with pytest.raises(ValueError, match="dip_depth"):
        env.reset(options={"conditions": {"dip_depth": 1.5}})
    with pytest.raises(RuntimeError, match="reset"):
        CutOffEnv().step(0)


# --- checkers -------------------------------------------------------------------------------
CHECK_CONFIGS = [{}, {"history": 4, "observe_params": True, "preset": "randomized"},
                 {"reversible": True}, {"render_mode": "rgb_array"}]


@pytest.mark.parametrize("config", CHECK_CONFIGS)
def test_gymnasium_and_sb3_checkers_pass_without_warnings(config):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = gym.make(ENV_ID, **config)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gym_check(env.unwrapped, skip_render_check=False)
        sb3_check(env.unwrapped, warn=True)
        # through the registered wrappers too (the passive checker runs on first calls)
        env.reset(seed=0)
        env.step(env.action_space.sample())
    msgs = [str(w.message) for w in caught]
    assert msgs == [], msgs


# --- seeding --------------------------------------------------------------------------------
def _same(a: dict, b: dict) -> None:
    assert len(a["obs"]) == len(b["obs"])
    for oa, ob in zip(a["obs"], b["obs"]):
        np.testing.assert_array_equal(oa, ob)
    assert a["rewards"] == b["rewards"]
    assert a["infos"] == b["infos"]


@pytest.mark.parametrize("preset", ["thesis-2.5bar", "randomized"])
def test_same_seed_same_episode(preset):
    noisy = {"position_noise_m": 3e-5, "pressure_noise_pa": 400.0}
    env = gym.make(ENV_ID, preset=preset, conditions=noisy, time_limit_s=0.5)
    a = run(env, cut_at(0.3), seed=11)
    b = run(env, cut_at(0.3), seed=11)
    _same(a, b)
    # a second environment instance too
    _same(a, run(gym.make(ENV_ID, preset=preset, conditions=noisy, time_limit_s=0.5),
                 cut_at(0.3), seed=11))


def test_different_seeds_differ_in_randomized_preset():
    env = CutOffEnv(preset="randomized")
    conds = {repr(env.reset(seed=s)[1]["conditions"]) for s in range(5)}
    assert len(conds) == 5
    # and unseeded resets continue the stream
    env.reset(seed=3)
    c1 = env.reset()[1]["conditions"]
    c2 = env.reset()[1]["conditions"]
    assert c1 != c2


def test_noise_differs_between_seeds_but_not_the_plant():
    env = CutOffEnv(conditions={"pressure_noise_pa": 400.0, "position_noise_m": 3e-5},
                    time_limit_s=0.4)
    a, b = run(env, seed=1), run(env, seed=2)
    assert not np.array_equal(a["obs"][-1], b["obs"][-1])
    assert [i["position_m"] for i in a["infos"]] == [i["position_m"] for i in b["infos"]]


# --- reward and objective -------------------------------------------------------------------
SCHEMES = {"conventional": never, "end_stroke": end_stroke, "cut_0.9": cut_at(0.9),
           "cut_0.6": cut_at(0.6), "stall": always}


@pytest.mark.parametrize("preset", ["thesis-2.5bar", "thesis-1.5bar"])
def test_dense_return_equals_objective_equals_sparse_return(preset):
    dense, sparse = CutOffEnv(preset=preset), CutOffEnv(preset=preset, reward_mode="sparse")
    for name, pol in SCHEMES.items():
        d, s = run(dense, pol), run(sparse, pol)
        assert d["actions"] == s["actions"], name
        fi = d["final"]
        assert d["ret"] == pytest.approx(fi["objective"], abs=1e-9), name
        assert s["ret"] == pytest.approx(fi["objective"], abs=1e-9), name
        assert all(r == 0.0 for r in s["rewards"][:-1]), name
        assert fi["objective"] == pytest.approx(objective_from_info(fi, 4.0), abs=1e-9), name
        # the same figures either way
        assert {k: fi[k] for k in FINAL_KEYS} == {k: s["final"][k] for k in FINAL_KEYS}, name


def test_objective_follows_the_weights():
    w = {"w_time": 1.0, "w_stall": 5.0, "w_stick": 0.1}
    env = CutOffEnv(time_limit_s=2.0, **w)
    for pol in (never, cut_at(0.9), always):
        out = run(env, pol)
        fi = out["final"]
        assert out["ret"] == pytest.approx(objective_from_info(fi, 2.0, **w), abs=1e-9)


@pytest.mark.parametrize("preset", ["thesis-2.5bar", "thesis-1.5bar"])
def test_conventional_episode_is_the_reference(preset):
    out = run(CutOffEnv(preset=preset), never)
    fi = out["final"]
    assert out["terminated"] and not out["truncated"]
    assert fi["saving_ratio"] == pytest.approx(0.0, abs=1e-9)
    assert fi["time_increase"] == pytest.approx(0.0, abs=1e-4)
    assert fi["stroke_time_s"] == pytest.approx(fi["conventional_stroke_time_s"], rel=1e-4)
    assert out["ret"] == pytest.approx(-1.0, abs=1e-6)
    assert fi["cutoff_time_s"] is None and fi["completed"] and not fi["stalled"]


@pytest.mark.parametrize("config", [
    {"preset": "thesis-2.5bar"}, {"preset": "thesis-1.5bar"},
    {"preset": Conditions(load_mass_kg=30.0, supply_pressure_gauge_pa=1.5e5)},
    {"preset": Conditions(load_mass_kg=5.0, supply_pressure_gauge_pa=5e5, friction_scale=0.7)},
    {"preset": "thesis-2.5bar", "w_time": 0.0},
])
def test_stalling_pays_less_than_conventional(config):
    env = CutOffEnv(**config)
    conv = run(env, never)
    stall = run(env, always)
    assert stall["final"]["stalled"] and not stall["final"]["completed"]
    assert stall["terminated"]
    assert stall["ret"] < conv["ret"] - 0.5
    # a stall later in the stroke (the piston moved, then stuck) pays no more
    late = run(env, cut_at(0.45))
    if late["final"]["stalled"]:
        assert late["ret"] < conv["ret"] - 0.5


def test_time_out_is_penalised():
    env = CutOffEnv(time_limit_s=0.6)  # the stroke takes ~1.2 s
    out = run(env, never)
    fi = out["final"]
    assert out["truncated"] and not out["terminated"]
    assert not fi["completed"] and not fi["stalled"] and fi["stroke_time_s"] is None
    assert fi["time_increase"] is None
    assert out["ret"] < -1.0 - 1.0  # conventional: -1
    assert out["ret"] == pytest.approx(objective_from_info(fi, 0.6), abs=1e-9)
    assert out["final"]["time_s"] == pytest.approx(0.6)


def test_info_keys_and_types():
    out = run(CutOffEnv(), end_stroke)
    assert set(out["infos"][0]) == STEP_KEYS | {"conditions"}
    for info in out["infos"][1:-1]:
        assert set(info) == STEP_KEYS
    assert set(out["final"]) == STEP_KEYS | FINAL_KEYS | {"objective"}
    types = {"saving_ratio": float, "energy_wasted_j": float, "energy_conventional_j": float,
             "air_mass_kg": float, "free_air_nl": float, "stroke_time_s": float, "conventional_stroke_time_s": float,
             "time_increase": float, "cutoff_time_s": float, "stalled": bool,
             "stick_slip_events": int, "completed": bool, "objective": float,
             "time_s": float, "position_m": float, "p_drive_pa": float, "p_exhaust_pa": float,
             "supply_cut": bool, "measured_x_m": float, "measured_p_drive_pa": float,
             "measured_p_exhaust_pa": float}
    for info in out["infos"]:
        for k, v in info.items():
            if k != "conditions":
                assert type(v) is types[k], (k, type(v))
    fi = out["final"]
    assert 0.0 < fi["saving_ratio"] < 1.0
    assert fi["saving_ratio"] == pytest.approx(1.0 - fi["energy_wasted_j"] / fi["energy_conventional_j"])
    assert fi["air_mass_kg"] > 0
    # never cut, not completed: the optional figures are None
    stall = run(CutOffEnv(time_limit_s=0.3), never)["final"]
    assert stall["cutoff_time_s"] is None and stall["stroke_time_s"] is None
    assert stall["time_increase"] is None


# --- end of an episode ----------------------------------------------------------------------
def test_end_stroke_cut_ends_once_the_valve_has_closed():
    env = CutOffEnv()
    out = run(env, end_stroke)
    fi = out["final"]
    delay = float(env.P[0, L.P_DELAY])
    assert out["terminated"] and fi["completed"]
    assert fi["stroke_time_s"] - 0.02 <= fi["cutoff_time_s"] <= fi["stroke_time_s"] + 0.005
    assert fi["time_s"] >= fi["cutoff_time_s"] + delay
    assert K.valve_closed(env.D[0], env.P[0])
    # the step before the last, the valve had not closed yet
    assert out["infos"][-2]["time_s"] < fi["cutoff_time_s"] + delay + 0.02
    assert fi["saving_ratio"] > 0.0


@pytest.mark.parametrize("window", [0.0, 0.02, 0.1])
def test_no_cut_ends_within_the_decision_window(window):
    out = run(CutOffEnv(decision_window_s=window), never)
    fi = out["final"]
    assert out["terminated"]
    wait = fi["time_s"] - fi["stroke_time_s"]
    assert window - 1e-9 <= wait <= window + 0.005 + 1e-9


def test_stall_termination():
    env = CutOffEnv()
    out = run(env, cut_at(0.3))
    fi = out["final"]
    assert out["terminated"] and fi["stalled"] and not fi["completed"]
    assert fi["position_m"] < 0.18
    assert fi["cutoff_time_s"] == pytest.approx(0.3)
    assert 0.15 > fi["position_m"] > 0.01  # it moved, then stuck partway (~0.1 m of 0.18)
    assert fi["time_s"] < 3.5  # before the 4 s limit
    early = run(env, always)["final"]  # cut before it ever moved
    assert early["stalled"] and early["position_m"] == 0.0 and early["time_s"] < 0.5


def test_truncation_at_time_limit():
    out = run(CutOffEnv(time_limit_s=0.25, control_period_s=0.01), never)
    assert out["truncated"] and not out["terminated"]
    assert len(out["rewards"]) == 25
    assert out["final"]["time_s"] == pytest.approx(0.25)


def test_step_after_end_raises():
    env = CutOffEnv(time_limit_s=0.05)
    run(env, never)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_warns_when_the_time_limit_needs_more_steps_than_registered():
    with pytest.warns(UserWarning, match="max_episode_steps=4000"):
        CutOffEnv(control_period_s=0.001)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        CutOffEnv(control_period_s=0.005, time_limit_s=4.0)  # exactly 800: no warning
    # passing max_episode_steps to gymnasium.make gives complete episodes
    with pytest.warns(UserWarning):
        env = gym.make(ENV_ID, control_period_s=0.002, max_episode_steps=2000)
    out = run(env, never)
    assert out["terminated"] and out["ret"] == pytest.approx(out["final"]["objective"], abs=1e-9)


def test_registered_time_limit_is_the_default_time_limit():
    # gym.make's TimeLimit (800 steps) and the env's own time limit coincide at the defaults;
    # other periods must pass max_episode_steps (warned above), the env cannot see the wrapper
    env = gym.make(ENV_ID)
    u = env.unwrapped
    assert env.spec.max_episode_steps * u.control_period_s == pytest.approx(u.time_limit_s)


# --- latched / reversible -------------------------------------------------------------------
def _pulse(t_on: float, t_off: float) -> Policy:
    return lambda k, obs, info: int(t_on - 1e-9 <= info["time_s"] < t_off - 1e-9)


def test_latched_cut_stays_cut():
    out = run(CutOffEnv(), _pulse(0.8, 0.85))
    after = [i for i in out["infos"][1:] if i["time_s"] > 0.8 + 1e-9]
    assert after and all(i["supply_cut"] for i in after)
    assert all(o[6] == 1.0 for o, i in zip(out["obs"], out["infos"]) if i["time_s"] > 0.8 + 1e-9)
    assert out["final"]["cutoff_time_s"] == pytest.approx(0.8)


def test_reversible_cut_reopens():
    env = CutOffEnv(reversible=True)
    out = run(env, _pulse(0.8, 0.85))
    cut = [i["supply_cut"] for i in out["infos"][1:]]
    t = [i["time_s"] for i in out["infos"][1:]]
    assert any(cut) and not cut[-1]
    assert all(not c for c, tt in zip(cut, t) if tt > 0.85 + 1e-9)
    fi = out["final"]
    assert fi["completed"] and fi["cutoff_time_s"] == pytest.approx(0.8)
    # re-opened: ends like a conventional stroke (filled to supply)
    assert fi["saving_ratio"] == pytest.approx(0.0, abs=1e-9)
    # latched with the same actions: a cut-off stroke that saves air
    latched = run(CutOffEnv(), _pulse(0.8, 0.85))["final"]
    assert latched["saving_ratio"] > 0.05


# --- observations ---------------------------------------------------------------------------
@pytest.mark.parametrize("config", [{}, {"history": 3}, {"observe_params": True},
                                    {"history": 2, "observe_params": True, "preset": "randomized"}])
def test_observation_shape_bounds_dtype(config):
    env = CutOffEnv(**config)
    lay = env.observation_layout()
    size = lay["history"] * NF + (len(PARAM_OBSERVATION) if env.observe_params else 0)
    assert lay["size"] == size == env.observation_space.shape[0] == len(env.observation_names)
    assert env.observation_space.dtype == np.float32
    out = run(env, cut_at(1.0), seed=4)
    obs = np.array(out["obs"])
    assert obs.dtype == np.float32 and obs.shape[1] == size
    assert np.all(np.abs(obs) <= OBS_BOUND)
    assert np.abs(obs).max() < 2.0  # scaled to about [-1, 1]
    for o in out["obs"]:
        assert env.observation_space.contains(o)


def test_observation_features_in_physical_units():
    env = CutOffEnv()
    out = run(env, end_stroke)
    lay = env.observation_layout()
    scale = {f["name"]: f["scale"] for f in lay["features"]}
    pa = float(env.P[0, L.P_PA])
    for o, i in zip(out["obs"], out["infos"]):
        assert o[0] * scale["position"] == pytest.approx(i["position_m"], abs=1e-6)
        assert o[5] * scale["time"] == pytest.approx(i["time_s"], abs=1e-6)
        assert o[6] == float(i["supply_cut"])
        assert o[4] * scale["supply_setpoint"] == pytest.approx(2.5e5, rel=1e-6)
    # pressures: gauge, at the ports (close to the chambers once the line settles)
    o, i = out["obs"][-1], out["infos"][-1]
    assert o[2] * scale["p_drive"] == pytest.approx(i["p_drive_pa"] - pa, rel=0.05)
    # velocity estimate = difference of the measured positions / period
    v = [o[1] * scale["velocity"] for o in out["obs"]]
    x = [i["position_m"] for i in out["infos"]]
    assert v[100] == pytest.approx((x[100] - x[99]) / 0.005, rel=1e-4, abs=1e-6)
    assert v[0] == 0.0


def test_history_is_stacked_oldest_first():
    h1, h3 = CutOffEnv(), CutOffEnv(history=3)
    a, b = run(h1, cut_at(1.0)), run(h3, cut_at(1.0))
    assert h3.observation_names[:NF] == [f"{f.name}[-2]" for f in OBSERVATION]
    assert h3.observation_names[-NF:] == [f"{f.name}[0]" for f in OBSERVATION]
    o1, o3 = np.array(a["obs"]), np.array(b["obs"])
    np.testing.assert_array_equal(o3[:, 2 * NF:], o1)           # newest last
    np.testing.assert_array_equal(o3[1:, NF:2 * NF], o1[:-1])   # one sample ago
    np.testing.assert_array_equal(o3[2:, :NF], o1[:-2])         # oldest first
    for k in range(3):                                          # reset: filled with the sample
        np.testing.assert_array_equal(o3[0, k * NF:(k + 1) * NF], o1[0])
    np.testing.assert_array_equal(o3[1, :NF], o1[0])


def test_observe_params_adds_the_true_conditions():
    c = Conditions(load_mass_kg=15.0, friction_scale=1.2, valve_delay_scale=0.9)
    env = CutOffEnv(observe_params=True, history=2)
    obs, _ = env.reset(seed=0, options={"conditions": c})
    names = [f.name for f in PARAM_OBSERVATION]
    assert env.observation_names[-3:] == names
    assert obs.shape[0] == 2 * NF + 3
    delay = float(env.P[0, L.P_DELAY])
    np.testing.assert_allclose(obs[-3:], [15.0 / 30.0, 1.2, delay / 0.4], rtol=1e-6)
    plain = CutOffEnv(history=2).reset(seed=0, options={"conditions": c})[0]
    np.testing.assert_array_equal(obs[:-3], plain)


def test_sensor_noise_changes_observations_not_the_plant():
    quiet = Conditions()
    noisy = Conditions(position_noise_m=3e-5, pressure_noise_pa=400.0)
    env = CutOffEnv(time_limit_s=0.8)
    a = run(env, cut_at(0.6), options={"conditions": quiet})
    b = run(env, cut_at(0.6), options={"conditions": noisy})
    assert [i["position_m"] for i in a["infos"]] == [i["position_m"] for i in b["infos"]]
    assert [i["p_drive_pa"] for i in a["infos"]] == [i["p_drive_pa"] for i in b["infos"]]
    oa, ob = np.array(a["obs"]), np.array(b["obs"])
    assert not np.array_equal(oa[:, 2], ob[:, 2])
    dp = (ob[:, 2] - oa[:, 2]) * 6e5
    assert 200.0 < dp.std() < 800.0
    np.testing.assert_array_equal(oa[:, 5], ob[:, 5])  # time is exact
    assert a["rewards"] == b["rewards"]


def test_sensor_lag_lags_the_pressures():
    fast, slow = CutOffEnv(), CutOffEnv(sensor_lag_s=0.05)
    a, b = run(fast, cut_at(1.0)), run(slow, cut_at(1.0))
    # the plant is the same; only the transducers lag
    assert a["final"]["position_m"] == b["final"]["position_m"]
    pa, pb = np.array(a["obs"])[:, 2], np.array(b["obs"])[:, 2]
    n = min(len(pa), len(pb))
    rising = slice(30, 60)  # the driving port fills after the valve delay
    assert np.all(pb[rising] <= pa[rising] + 1e-6)
    assert (pa[rising] - pb[rising]).max() > 0.05
    assert np.abs(pa[:n] - pb[:n]).max() > 0.05


# --- render ---------------------------------------------------------------------------------
def test_render_rgb_array():
    env = gym.make(ENV_ID, render_mode="rgb_array")
    run(env, end_stroke)
    img = env.render()
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 5  # not blank
    blank = CutOffEnv()
    with pytest.warns(UserWarning, match="rgb_array"):
        assert blank.render() is None


def test_non_number_option_is_a_value_error():
    with pytest.raises(ValueError, match="control_period_s"):
        CutOffEnv(control_period_s="5ms")
    with pytest.raises(ValueError, match="w_time"):
        CutOffEnv(w_time=True)


# --- careless input: actions, reset options, rig (refused, never rounded or ignored) --------
@pytest.mark.parametrize("action", [2, -1, 0.5, 1.7, 1.0, "1", None, np.array([1]),
                                    np.array([[0]]), np.float64(1.0), [1]])
def test_actions_other_than_integer_0_or_1_are_refused(action):
    env = CutOffEnv()
    env.reset(seed=0)
    t0 = env._step_info(0)["time_s"]
    with pytest.raises(ValueError, match="Discrete\\(2\\)|shape"):
        env.step(action)
    assert env._step_info(0)["time_s"] == t0  # nothing was stepped


@pytest.mark.parametrize("action", [0, 1, True, np.int64(1), np.int32(0), np.array(1),
                                    np.array(0, dtype=np.uint8)])
def test_integer_actions_of_any_kind_are_taken(action):
    env = CutOffEnv()
    env.reset(seed=0)
    env.step(action)
    assert env._step_info(0)["supply_cut"] == bool(int(action))


def test_a_wrapped_env_refuses_bad_actions_too():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="Discrete"):
        env.step(2)


@pytest.mark.parametrize("options,msg", [
    ({"condition": Conditions()}, r"unknown reset option 'condition'.*did you mean 'conditions'"),
    ({"seed": 3}, "unknown reset option 'seed'"),
    ({"conditions": {"load_mass": 5.0}}, r"no field 'load_mass'.*did you mean 'load_mass_kg'"),
    ({"conditions": 5.0}, "must be Conditions or a dict"),
    ("conditions", "must be a dict"),
])
def test_bad_reset_options_are_refused(options, msg):
    with pytest.raises(ValueError, match=msg):
        CutOffEnv().reset(seed=0, options=options)


def test_rig_is_params_a_dict_or_a_file_and_nothing_else():
    env = CutOffEnv(rig={"load_mass_kg": 3.0})
    assert env.rig.load_mass_kg == 3.0
    assert env.reset(seed=0)[1]["conditions"]["load_mass_kg"] == 3.0  # its operating point
    for bad in (3.0, ["a"], b"rig.json"):
        with pytest.raises(ValueError, match="rig"):
            CutOffEnv(rig=bad)


def test_settings_changed_after_construction_are_checked_and_rescale_time():
    """SB3's set_attr (or a user) may change the settings between episodes: a bad one is
    refused at the next reset, and the time feature follows a new time limit."""
    env = CutOffEnv()
    env.reward_mode = "Dense"
    with pytest.raises(ValueError, match="reward_mode"):
        env.reset(seed=0)
    env.reward_mode = "dense"
    env.time_limit_s = 2.0
    env.reset(seed=0)
    for _ in range(100):
        obs, *_ , info = env.step(0)
    i = env.observation_names.index("time")
    scale = next(f["scale"] for f in env.observation_layout()["features"] if f["name"] == "time")
    assert scale == 2.0 and obs[i] == pytest.approx(info["time_s"] / 2.0, abs=1e-6)


def test_a_reversible_cut_is_not_a_stall_and_a_long_valve_delay_is_refused():
    """With reversible=True a cut that leaves the piston standing may be undone: the episode
    goes on (it ended as a stall); more commands in flight than the valve queues are refused."""
    env = CutOffEnv(reversible=True)
    env.reset(seed=0)
    for k in range(800):
        _, _, term, trunc, info = env.step(1 if k < 60 else 0)  # cut for 0.3 s, then re-open
        if term or trunc:
            break
    assert info["completed"] and not info["stalled"] and info["time_s"] > 0.3
    with pytest.raises(ValueError, match="valve queues"):  # refused when made, not mid-run
        CutOffEnv(reversible=True, control_period_s=0.001,
                  conditions={"valve_delay_scale": (1.5, 1.5)})
    with pytest.raises(ValueError, match="up to 300 ms"):  # the family draws up to 0.3 s
        CutOffEnv(reversible=True, preset="family", control_period_s=0.004)
    env = CutOffEnv(reversible=True, preset="family")  # 0.3 s / 5 ms fits
    with pytest.raises(ValueError, match="valve queues"):  # conditions told at reset
        env.reset(seed=0, options={"conditions": {"valve_delay_scale": 2.0}})


def test_an_unknown_constructor_option_is_named_with_the_nearest_one():
    from pneugym.envs import CutOffCycleEnv
    from pneugym.envs.cutoff import CutOffVectorEnv

    for make in (CutOffEnv, CutOffVectorEnv, CutOffCycleEnv):
        with pytest.raises(ValueError, match="did you mean 'conditions'"):
            make(condition={})
