"""What one recorded stroke tells a policy (pneugym.envs.commissioning, observe_commissioning):
the features against a hand-built trace, the environment's against a simulated measured run, the
deployable controller told the stroke as the environment is, refusals."""
import warnings

import numpy as np
import pytest

from agents.evaluation.suites import suite_episodes
from agents.registry import load_policy
from pneugym.data import simulate_run
from pneugym.deploy import Controller
from pneugym.deploy.check import check_equivalence
from pneugym.envs import Conditions
from pneugym.envs.commissioning import (condition_features, run_features, scaled,
                                        simulated_features, trace_features)
from pneugym.envs.cutoff import COMMISSIONING_OBSERVATION, CutOffEnv, CutOffVectorEnv
from pneugym.params import RigParams
from training_helpers import small

PA = 101_325.0


def test_features_of_a_hand_built_stroke():
    """A piston breaking away at 0.3 s and arriving at 1.1 s (0.1 m stroke), 2 bar driving and
    0.5 bar exhaust while moving, then the driving side decaying linearly from 3 bar."""
    t = np.arange(0.0, 3.0, 1e-3)
    x = np.clip((t - 0.29) / 0.81, 0.0, 1.0) * 0.1
    pd = np.where(t < 1.1, 2e5, 3e5 - 1e4 * (t - 1.1))
    pe = np.where(t < 1.1, 0.5e5, 0.0)
    f = trace_features(t, x, pd, pe, 0.1)
    k = int(np.flatnonzero(x >= 0.1 - 5e-4)[0])
    kb = int(np.flatnonzero(x > 2e-3)[0])
    assert f[0] == pytest.approx(t[k]) and f[1] == pytest.approx(t[k] - t[kb])
    assert f[2] == pytest.approx(2e5) and f[3] == pytest.approx(0.5e5)
    assert f[4] == pytest.approx(1.5e5)
    p0, p1 = 3e5 - 1e4 * (t[k] + 0.5 - 0.005 - 1.1), 3e5 - 1e4 * (t[k] + 1.5 - 0.005 - 1.1)
    assert f[5] == pytest.approx((p0 - p1) / p0, rel=1e-3)
    assert scaled(f)[2] == pytest.approx(2e5 / 6e5)
    with pytest.raises(ValueError, match="never reaches the end of stroke"):
        trace_features(t, 0.5 * x, pd, pe, 0.1)
    with pytest.raises(ValueError, match="record at least 1.5 s of hold"):
        trace_features(t[t < 2.0], x[t < 2.0], pd[t < 2.0], pe[t < 2.0], 0.1)


def test_the_environment_observes_the_stroke_a_user_would_record():
    """The episode's features are those of its rig's stroke at the operating point (nominal
    friction and valve delay, whatever the episode draws), as a measured run gives them; they
    hold through the episode; without observe_rig they are refused."""
    env = CutOffVectorEnv(num_envs=3, preset="family", observe_rig=True,
                          observe_commissioning=True, history=2)
    obs, _ = env.reset(seed=4)
    names = env.observation_names
    cols = [names.index(f.name) for f in COMMISSIONING_OBSERVATION]
    assert cols == list(range(len(names) - 6, len(names)))
    for i, cond in enumerate(env.conditions):
        rig = Conditions(supply_pressure_gauge_pa=cond.supply_pressure_gauge_pa,
                         load_mass_kg=cond.load_mass_kg, rig_changes=cond.rig_changes).rig()
        t_end = simulated_features(rig)[0] + 1.6
        run = simulate_run(rig, cut_on_arrival=True, t_end=t_end, noise=None)
        measured = run_features(run, rig.cylinder.stroke_m)
        np.testing.assert_allclose(obs[i, cols], measured, rtol=2e-3, atol=2e-3)
        np.testing.assert_array_equal(obs[i, cols], condition_features(cond, RigParams())
                                      .astype(np.float32))
    first = obs[:, cols].copy()
    for _ in range(40):
        obs, *_ = env.step(np.zeros(3, dtype=np.int64))
    np.testing.assert_array_equal(obs[:, cols], first)
    with pytest.raises(ValueError, match="needs observe_rig=True"):
        CutOffEnv(observe_commissioning=True)


@pytest.fixture(scope="module")
def told_run(tmp_path_factory):
    """A small ESAC trained on the rig family with the commissioning stroke observed."""
    from agents import training

    root = tmp_path_factory.mktemp("told")
    training.train("esac", root / "esac", preset="family", timesteps=48, seed=1, progress=False,
                   overrides=small("esac", root) + ["env.observe_rig=true",
                                                    "env.observe_commissioning=true"])
    return root / "esac"


def test_a_told_model_decides_in_the_controller_as_in_the_environment(told_run):
    """Told the stroke the environment observes, the controller builds the same observation and
    gives the same commands, bit for bit, on rigs of the transfer suite; a model that reads a
    stroke is refused one without it, and reads a measured run."""
    conds = [c for _, c in suite_episodes("transfer", 1, 4)][::10]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (trained on a family, run on other rigs)
        res = check_equivalence(lambda env: load_policy(told_run, env, margin=0.5,
                                                        max_time_increase=2.0), conds, seed=9)
    assert res["observations_differing"] == 0 and res["commands_differing"] == 0, res["first"]
    assert res["decisions"] > 100 * res["episodes"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ctl = Controller.load(told_run)
    assert ctl.reads_commissioning
    with pytest.raises(ValueError, match="reads a commissioning stroke"):
        ctl.reset(2.5e5 + PA, 10.0)
    with pytest.raises(ValueError, match="6 finite numbers"):
        ctl.set_commissioning([1.0, 2.0])
    rig = RigParams()
    run = simulate_run(rig, cut_on_arrival=True, t_end=3.0, noise="default", seed=3)
    ctl.reset(2.5e5 + PA, 10.0, commissioning=run)
    ctl.step(0.0, 0.0, PA, 2.5e5 + PA)
    cols = slice(-6, None)
    np.testing.assert_allclose(ctl.observation[cols], simulated_features(rig), atol=2e-3)
    short = simulate_run(rig, cut_on_arrival=True, t_end=1.5, noise=None)
    with pytest.raises(ValueError, match="of hold after it"):
        ctl.set_commissioning(short)


def test_models_that_read_no_stroke_ignore_it():
    """Baselines under a controller built to observe the stroke run without one."""
    from agents import make_policy

    env = CutOffVectorEnv(num_envs=1, observe_rig=True, observe_commissioning=True)
    ctl = Controller(make_policy("gaslaw", env), env)
    assert not ctl.reads_commissioning
    ctl.reset(2.5e5 + PA, 10.0)
    assert ctl.step(0.0, 0.0, PA, 2.5e5 + PA) == 0


def test_a_told_model_operates_on_the_stroke_of_the_lifes_start(told_run, tmp_path,
                                                                 monkeypatch):
    """`pneugym operate` runs a model that reads the stroke, frozen and adapting, and tells it
    the stroke the rig made at the start of its life: a leak that opens later changes what
    the environment would simulate, not what the controller observes."""
    from agents.oracle import TimedCutPolicy
    from pneugym.operation import run as R
    from pneugym.operation.scenarios import Scenario

    sc = Scenario("leak", drift={"leak_drive_area_m2": [(0, 0.0), (9, 0.0), (10, 6e-7)]})
    late, start = sc.conditions(15, 0), sc.conditions(0, 0)
    base = RigParams()
    told = R.commissioned(sc, 0, late, base)
    np.testing.assert_array_equal(told, condition_features(start, base))
    assert abs(condition_features(late, base)[5] - told[5]) > 0.01  # the leak shows in the hold
    seen = []
    act = R._Stepper.act

    def spy(self, obs):  # the controller's observations (not the references' timed cuts)
        if not isinstance(self.policy, TimedCutPolicy):
            seen.append(obs[:, -len(told):].copy())  # (the commissioning features end the row)
        return act(self, obs)

    monkeypatch.setattr(R._Stepper, "act", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (trained on a family, run on the thesis rig)
        for kind in ("esac", "esac-adaptive"):
            R.operate(sc, f"{kind}={told_run}", strokes=20, db=tmp_path / "ops.duckdb",
                      block=10, progress=False)
    assert len(seen) > 40
    assert R.ENV_CONFIG["observe_commissioning"]
    for obs in seen:
        np.testing.assert_array_equal(obs, np.broadcast_to(told.astype(obs.dtype), obs.shape))


def test_reset_tells_an_episode_a_stroke():
    """``reset(options={"commissioning": ...})``: the features, a measured run or ``None`` per
    sub-environment replace the simulated stroke for the episodes that reset starts; bad values
    and environments that observe no stroke are refused."""
    rig = RigParams()
    sim = simulated_features(rig)
    env = CutOffEnv(observe_rig=True, observe_commissioning=True)
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs[-6:], sim.astype(np.float32))
    obs, _ = env.reset(seed=0, options={"commissioning": 1.5 * sim})
    np.testing.assert_array_equal(obs[-6:], (1.5 * sim).astype(np.float32))
    obs, _ = env.reset(seed=0)  # the next episode observes its own stroke again
    np.testing.assert_array_equal(obs[-6:], sim.astype(np.float32))
    run = simulate_run(rig, cut_on_arrival=True, t_end=3.0, noise=None)
    obs, _ = env.reset(seed=0, options={"commissioning": run})
    np.testing.assert_allclose(obs[-6:], run_features(run, rig.cylinder.stroke_m), rtol=1e-6)
    venv = CutOffVectorEnv(num_envs=2, observe_rig=True, observe_commissioning=True)
    obs, _ = venv.reset(seed=0, options={"commissioning": [None, 2.0 * sim]})
    np.testing.assert_array_equal(obs[:, -6:], np.stack([sim, 2.0 * sim]).astype(np.float32))
    for bad in ([1.0, 2.0], [np.nan] * 6, "not a stroke"):
        with pytest.raises(ValueError):
            env.reset(options={"commissioning": bad})
    with pytest.raises(ValueError, match="one commissioning stroke .* per environment"):
        venv.reset(options={"commissioning": [sim]})
    with pytest.raises(ValueError, match="does not observe a commissioning stroke"):
        CutOffEnv(observe_rig=True).reset(options={"commissioning": sim})
    with pytest.raises(ValueError, match="does not observe a commissioning stroke"):
        CutOffVectorEnv(num_envs=1).reset(options={"commissioning": [sim]})
