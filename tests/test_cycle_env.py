"""The cycle mode of the environment (``pneugym/CutOffCycle-v0``): extend then retract, one
cut-off decision per stroke direction, accounted per stroke and per cycle."""
import gymnasium as gym
import pytest
from gymnasium.utils.env_checker import check_env

import pneugym  # noqa: F401  (registers the environments)
from pneugym import thesis_rig
from pneugym.cycle import run_cycle
from pneugym.envs import CutOffCycleEnv, CutOffEnv
from pneugym.units import free_air_nl

RIG = thesis_rig(2.5).with_(cylinder={"design": "single-rod"})


def play(env, cut_extend, cut_retract, seed=1):
    """Cut each stroke at the first period at or after its time [s] (None: never)."""
    obs, info = env.reset(seed=seed)
    ret, steps, done = 0.0, 0, False
    while not done:
        cut = cut_extend if obs[-1] == 0 else cut_retract
        obs, r, term, trunc, info = env.step(int(cut is not None and info["time_s"] >= cut - 1e-9))
        ret, steps, done = ret + r, steps + 1, term or trunc
    return ret, info, term


def test_the_cycle_env_passes_gymnasiums_checker_and_is_registered():
    env = CutOffCycleEnv(rig=RIG)
    check_env(env, skip_render_check=True)
    assert env.observation_space.shape[0] == CutOffEnv(rig=RIG).observation_space.shape[0] + 1
    assert env.observation_names[-1] == "stroke"
    made = gym.make("pneugym/CutOffCycle-v0", rig=RIG)
    assert made.spec.max_episode_steps == 1600


def test_sb3_trains_on_the_cycle_env():
    """SB3's own checker passes, and PPO takes a few steps through whole cycles."""
    import stable_baselines3
    from stable_baselines3.common.env_checker import check_env as sb3_check

    sb3_check(CutOffCycleEnv(rig=RIG), warn=True)
    model = stable_baselines3.PPO("MlpPolicy", CutOffCycleEnv(rig=RIG), n_steps=64,
                                  batch_size=64, n_epochs=1, seed=0)
    model.learn(total_timesteps=128)
    assert model.num_timesteps == 128


@pytest.mark.filterwarnings("ignore:.*registered TimeLimit")
def test_the_cycle_env_reproduces_the_plants_cycle():
    """Cut each stroke at the same times as :func:`pneugym.cycle.run_cycle`: the same strokes,
    savings, air and cycle time (to the substeps' landing on control periods, 1e-3)."""
    env = CutOffCycleEnv(rig=RIG, dwell_s=0.3, time_limit_s=10.0)
    ret, info, term = play(env, 0.7, 0.65)
    ref = run_cycle(RIG, cut_extend_s=0.7, cut_retract_s=0.65, dwell_s=0.3)
    assert term and info["cycle_completed"] and ref.completed
    assert info["cycle_time_s"] == pytest.approx(ref.cycle_time_s, rel=1e-3)
    assert info["free_air_nl"] == pytest.approx(ref.free_air_nl, rel=1e-3)
    for side in ("extend", "retract"):
        mine, theirs = info[side], getattr(ref, side)
        assert mine["saving_ratio"] == pytest.approx(theirs.saving_ratio, abs=1e-3)
        assert mine["stroke_time_s"] == pytest.approx(theirs.arrival_time_s, rel=1e-3)
        assert mine["free_air_nl"] == pytest.approx(theirs.free_air_nl, rel=1e-3)
    # per cycle: the strokes add up, the return is the cycle's objective
    assert info["air_mass_kg"] == info["extend"]["air_mass_kg"] + info["retract"]["air_mass_kg"]
    assert info["free_air_nl"] == pytest.approx(free_air_nl(info["air_mass_kg"]))
    assert ret == pytest.approx(info["objective"], abs=1e-12)
    assert info["objective"] == info["extend"]["objective"] + info["retract"]["objective"]
    ew = info["extend"]["energy_wasted_j"] + info["retract"]["energy_wasted_j"]
    ec = info["extend"]["energy_conventional_j"] + info["retract"]["energy_conventional_j"]
    assert info["saving_ratio"] == pytest.approx(1.0 - ew / ec)


def test_a_conventional_cycle_saves_nothing_and_fills_both_sides():
    env = CutOffCycleEnv(rig=RIG)
    ret, info, _ = play(env, None, None)
    assert info["saving_ratio"] == 0.0 and ret == pytest.approx(-2.0)
    ref = run_cycle(RIG, dwell_s=0.2)
    assert info["free_air_nl"] == pytest.approx(ref.free_air_nl, rel=1e-3)


def test_the_retraction_starts_from_the_extensions_chambers():
    """An extension cut off early leaves its cap side below supply: the retraction starts with
    that back-pressure (not the supply a lone retract episode assumes), and so is quicker."""
    env = CutOffCycleEnv(rig=RIG)
    obs, info = env.reset(seed=0)
    while obs[-1] == 0:
        obs, _, _, _, info = env.step(int(info["time_s"] >= 0.7))
    cap_then = info["extend"]
    assert info["stroke"] == "retract" and info["time_s"] == 0.0 and cap_then["cutoff_time_s"]
    lone = CutOffEnv(rig=RIG.with_(stroke_direction="retract"))
    _, lone_info = lone.reset(seed=0)
    assert info["p_exhaust_pa"] < 0.8 * lone_info["p_exhaust_pa"]
    assert info["p_drive_pa"] >= lone_info["p_drive_pa"]  # the rod side still venting
    _, cut_cycle, _ = play(CutOffCycleEnv(rig=RIG), 0.7, None)
    _, conv_cycle, _ = play(CutOffCycleEnv(rig=RIG), None, None)
    assert cut_cycle["retract"]["stroke_time_s"] < conv_cycle["retract"]["stroke_time_s"]


def test_a_stalled_extension_ends_the_cycle():
    ret, info, term = play(CutOffCycleEnv(rig=RIG), 0.3, None)
    assert term and info["extend"]["stalled"] and info["retract"] is None
    assert info["cycle_time_s"] is None and not info["cycle_completed"]
    assert info["saving_ratio"] is None  # no saving is claimed for a cycle not made
    # the retraction that never ran: all its air wasted and the stall penalty
    assert info["objective"] == info["extend"]["objective"] - 3.0
    assert ret == pytest.approx(info["objective"], abs=1e-12)
    assert "energy_wasted_j" not in info and "stalled" not in info  # per stroke only
    with pytest.raises(RuntimeError, match="reset"):
        CutOffCycleEnv(rig=RIG).step(0)


def test_the_cycle_env_is_reproducible_under_a_seed():
    kw = dict(rig=RIG, preset="randomized", conditions={"pressure_noise_pa": 2000.0})
    a = play(CutOffCycleEnv(**kw), 0.8, 0.8, seed=7)
    b = play(CutOffCycleEnv(**kw), 0.8, 0.8, seed=7)
    assert a[0] == b[0] and a[1]["free_air_nl"] == b[1]["free_air_nl"]
    c = play(CutOffCycleEnv(**kw), 0.8, 0.8, seed=8)
    assert c[1]["free_air_nl"] != a[1]["free_air_nl"]


def test_a_lone_retract_stroke_of_the_double_rod_rig_is_its_extension():
    """By symmetry (both faces the annulus, equal dead volumes), bit for bit."""
    out = []
    for d in ("extend", "retract"):
        env = CutOffEnv(rig=thesis_rig(2.5).with_(stroke_direction=d))
        obs, info = env.reset(seed=3)
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(int(info["time_s"] >= 0.9))
            done = term or trunc
        out.append(info)
    assert out[0]["objective"] == out[1]["objective"]
    assert out[0]["free_air_nl"] == out[1]["free_air_nl"] > 0


@pytest.mark.parametrize("kw, match", [
    (dict(dwell_s=-1.0), "dwell_s"), (dict(dwell_s=float("nan")), "dwell_s"),
    (dict(rig=thesis_rig().with_(effects={"dead_volume_m3": 1e-5})), "per side"),
    (dict(dwel_s=0.1), "unknown"),
])
def test_bad_cycle_options_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        CutOffCycleEnv(**kw)


def test_the_cycle_time_is_the_simulated_time():
    """With no dwell and a cut at the arrival, a stroke ends when its valve has closed: the
    cycle's time counts that, not only the arrivals."""
    env = CutOffCycleEnv(rig=RIG, dwell_s=0.0)
    obs, info = env.reset(seed=0)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(int(info["position_m"] >= RIG.cylinder.stroke_m))
        done = term or trunc
    e, r = info["extend"], info["retract"]
    assert e["end_time_s"] > e["stroke_time_s"] + 0.15  # the valve's delay after the cut
    assert info["cycle_time_s"] == e["end_time_s"] + r["end_time_s"]
    assert info["cycle_time_s"] > e["stroke_time_s"] + r["stroke_time_s"] + 0.3


def test_a_retraction_that_cannot_complete_is_refused_at_reset():
    from pneugym.presets import cylinder_rig

    env = CutOffCycleEnv(rig=cylinder_rig(8, 300, load_kg=20.0, mounting_angle_deg=-90.0))
    with pytest.raises(ValueError, match="retract stroke"):
        env.reset(seed=0)


def test_run_cycle_checks_its_time_limit_and_cuts_at_zero():
    """A NaN limit is refused (it skipped both strokes); a cut at 0 s runs (it failed inside
    the plant) and, the supply taken back at once, leaves the piston short of the end."""
    with pytest.raises(ValueError, match="t_max_s"):
        run_cycle(thesis_rig(2.5), t_max_s=float("nan"))
    res = run_cycle(thesis_rig(2.5), cut_extend_s=0.0, t_max_s=2.0)
    assert res.extend.arrival_time_s is None


def test_the_cycle_env_refuses_a_commissioning_option_and_hints_its_own_step_limit():
    env = CutOffCycleEnv(observe_rig=True, observe_commissioning=True)
    with pytest.raises(ValueError, match="commissioning"):
        env.reset(seed=0, options={"commissioning": [1.0] * 6})
    with pytest.warns(UserWarning, match="max_episode_steps=2000"):
        CutOffCycleEnv(time_limit_s=5.0)
