"""The deployable controller (pneugym/deploy): raw samples in, the valve command out, the same
decisions as the policy inside the environment (bit for bit), refusals of bad samples."""
import json
import math
import warnings

import numpy as np
import pytest

from agents import make_policy
from agents.base import Policy
from agents.evaluation.suites import suite_episodes
from agents.registry import load_policy
from pneugym.deploy import Controller, SampleError
from pneugym.deploy.check import check_equivalence, environment_trace
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv
from pneugym.params import RigParams
from training_helpers import trained_runs

PA = 101_325.0


def conditions(suite, seed, n=None):
    conds = [c for _, c in suite_episodes(suite, 1, seed)]
    return conds[:n] if n else conds


def assert_same(res):
    assert res["decisions"] > 100 * res["episodes"]
    assert res["observations_differing"] == 0 and res["commands_differing"] == 0, res["first"]


@pytest.mark.parametrize("name", ["conventional", "endstroke", "gaslaw"])
@pytest.mark.parametrize("suite", ["robustness", "transfer"])
def test_baselines_decide_as_in_the_environment(name, suite):
    """Sensor noise, supply dips, rigs of their own (transfer): fed what the environment's
    sensors read, the controller builds the same observation and gives the same command."""
    assert_same(check_equivalence(lambda env: make_policy(name, env), conditions(suite, 11),
                                  seed=5))


def test_model_predictive_policy_decides_as_in_the_environment():
    res = check_equivalence(lambda env: make_policy("mpc", env, prior_members=0),
                            conditions("transfer", 12, n=2), seed=2)
    assert_same(res)


def test_gaslaw_per_rig_decides_as_in_the_environment():
    res = check_equivalence(lambda env: make_policy("gaslaw-rig", env),
                            conditions("nominal", 3, n=2), seed=2)
    assert_same(res)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return trained_runs(tmp_path_factory)


@pytest.mark.parametrize("algo, over", [("esac", {}), ("ppo", {}), ("dqn", {}),
                                        ("ppo", {"decision": {"rule": "quantile", "value": 0.3}}),
                                        ("ppo", {"decision": {"rule": "hazard", "value": 0.4}}),
                                        ("dqn", {"decision": {"rule": "advantage", "value": 0.0}})])
def test_learned_policies_decide_as_in_the_environment(runs, algo, over):
    """Trained models (history stacked by the policy, rig columns dropped for models that never
    saw them), over noisy conditions and rigs of their own."""
    conds = conditions("robustness", 4, n=6) + conditions("transfer", 4, n=6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (trained on the thesis rig, run on others)
        res = check_equivalence(lambda env: load_policy(runs[algo], env, **over), conds, seed=9)
    assert_same(res)


def test_the_check_sees_a_difference():
    """Fed what the sensors read, the first observation is the environment's; 1 µm off in
    position, it differs there and only there: the comparison can fail."""
    cond = Conditions(supply_pressure_gauge_pa=3e5, load_mass_kg=10.0, position_noise_m=3e-5)
    tr = environment_trace(make_policy("endstroke", CutOffVectorEnv(observe_rig=True)), [cond],
                           0, {"observe_rig": True})[0]
    env = CutOffVectorEnv(observe_rig=True)
    ctl = Controller(make_policy("endstroke", env), env)
    names = env.observation_names
    for dx, differing in ((0.0, []), (1e-6, ["position"])):
        ctl.reset(3e5 + PA, 10.0)
        ctl.step(tr["t"][0], tr["x"][0] + dx, tr["p_drive"][0], tr["p_exhaust"][0])
        diff = np.flatnonzero(ctl.observation.view(np.uint32) != tr["obs"][0].view(np.uint32))
        assert [names[i] for i in diff] == differing


class Flicker(Policy):
    """Cuts at every other decision (a latched controller must hold the cut)."""

    n = 0

    def act(self, obs):
        self.n += 1
        return np.array([self.n % 2 == 0], dtype=np.int64)


def test_the_cut_is_latched_and_timed():
    env = CutOffVectorEnv(observe_rig=True)
    ctl = Controller(Flicker.for_env(env), env)
    ctl.reset(3.5e5 + PA)
    cmds = [ctl.step(k * 0.005, 0.0, PA, PA) for k in range(4)]
    assert cmds == [0, 1, 1, 1] and ctl.cut and ctl.cut_time_s == 0.005
    ctl.reset(3.5e5 + PA)
    assert not ctl.cut and ctl.cut_time_s is None and ctl.step(0.0, 0.0, PA, PA) == 0


@pytest.fixture
def ctl():
    c = Controller.load("endstroke")
    c.reset(2.5e5 + PA, 10.0)
    c.step(0.0, 0.0, PA, PA)
    return c


@pytest.mark.parametrize("t, x, pd, pe, match", [
    (0.005, 0.0, math.nan, PA, "p_drive_pa = nan is not a finite number"),
    (0.005, "0.1", PA, PA, "x_m = '0.1' is not a finite number"),
    (0.0, 0.0, PA, PA, "out of order"),
    (0.010, 0.0, PA, PA, "comes 10 ms after the last; .* 5 ms"),
    (5.0, 0.0, PA, PA, "comes 5000 ms after"),
    (0.005, 120.0, PA, PA, r"mm given as m\?"),
    (0.005, 0.0, 3.5, PA, r"bar given as Pa\?"),
    (0.005, 0.0, PA, 350.0, r"kPa given as Pa\?"),
    (0.005, 0.0, 2.5e5, 0.0, r"gauge pressure\? give it absolute"),
    (0.005, 0.0, 8e6, PA, "not a plausible absolute pressure"),
])
def test_bad_samples_are_refused(ctl, t, x, pd, pe, match):
    with pytest.raises(SampleError, match=match):
        ctl.step(t, x, pd, pe)
    assert ctl.step(0.005, 0.0, PA, PA) == 0  # a refusal changes nothing


def test_timing_and_setpoint_refusals():
    c = Controller.load("gaslaw")
    with pytest.raises(RuntimeError, match="call reset"):
        c.step(0.0, 0.0, PA, PA)
    for sp, match in ((3.5, r"bar given as Pa\?"), (5e4, r"a gauge pressure\?")):
        with pytest.raises(SampleError, match=match):
            c.reset(sp)
    c.reset(3.5e5)
    with pytest.raises(SampleError, match="first sample after reset.*within one control period"):
        c.step(0.2, 0.0, PA, PA)
    assert c.step(0.001, 0.0, PA, PA) == 0
    assert c.step(0.006 + 0.0002, 0.0, PA, PA) == 0  # 4 % late: within the tolerance


def test_load_refuses_the_oracle_and_unknown_sources(tmp_path):
    with pytest.raises(ValueError, match="'oracle' cannot be deployed: it reads each episode's "
                                         "hidden conditions"):
        Controller.load("oracle")
    with pytest.raises(FileNotFoundError, match="neither a baseline"):
        Controller.load(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="no trained run at"):
        Controller.load("esac", runs=tmp_path)
    with pytest.raises(ValueError, match="backend = 'tensorflow'"):
        Controller.load("gaslaw", backend="tensorflow")
    with pytest.raises(ValueError, match="has no network"):
        Controller.load("gaslaw", backend="onnx")


def test_load_takes_the_rig_file_and_the_trained_period(runs, tmp_path):
    rig = RigParams().with_(cylinder={"bore_m": 0.08, "stroke_m": 0.3})
    f = tmp_path / "rig.json"
    rig.save(f)
    c = Controller.load("gaslaw", rig=f)
    assert c.rig.cylinder.stroke_m == 0.3 and c.policy.rig == c.rig
    c.reset(4e5 + PA, 20.0)
    with pytest.raises(SampleError, match=r"outside the stroke \(0.3 m"):
        c.step(0.0, 0.4, PA, PA)
    run = tmp_path / "ppo"
    import shutil

    shutil.copytree(runs["ppo"], run)
    meta = json.loads((run / "run.json").read_text())
    assert meta["env_config"].get("control_period_s", 0.005) == 0.005
    c = Controller.load(run)
    assert c.period_s == 0.005 and "ppo" in c.source
    c = Controller.load("ppo", runs=tmp_path)
    assert c.layout["rig_features"] and c.period_s == 0.005


def test_a_controller_runs_the_stroke_of_a_plant():
    """Closed loop on the plant: the Gas-Law controller cuts during the stroke and the stroke
    completes (the README's example in miniature)."""
    from pneugym.plant import Plant

    rig = RigParams()
    plant = Plant(rig)
    ctl = Controller.load("gaslaw", rig=rig)
    ctl.reset(rig.supply_pressure_pa)
    plant.command(1)
    cmd = 0
    for k in range(800):
        pd, pe = plant.sensor_pressures_pa
        cmd = ctl.step(plant.time_s, plant.position_m, pd, pe)
        plant.command(1 - cmd)
        plant.advance(0.005)
        if plant.arrival_time_s is not None and cmd:
            break
    assert cmd == 1 and 0.3 < ctl.cut_time_s < plant.arrival_time_s


# -- replay over measured runs ---------------------------------------------------------------
@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """The thesis protocol's three runs (conventional, end-stroke, early cut), noisy, on a rig
    whose friction differs from the one the controller is told."""
    from pneugym.data import thesis_protocol, write_run

    truth = RigParams().with_(friction={"static_n": 400.0})
    d = tmp_path_factory.mktemp("measured")
    for r in thesis_protocol(truth, known=RigParams(), seed=3):
        write_run(r, d / r.name)
    return d


def test_replay_reports_the_cut_and_its_predicted_saving(measured, tmp_path):
    from pneugym.cli import main
    from pneugym.deploy.replay import predict_cuts

    assert main(["replay", str(measured), "--policy", "gaslaw", "--out", str(tmp_path)]) == 0
    res = {r["run"]: r for r in json.loads((tmp_path / "replay.json").read_text())["runs"]}
    conv, early = res["conventional"], res["early_cutoff"]
    # on the never-cut run the controller's decision is exact: it cuts mid-stroke, and the
    # prediction is the environment's outcome of that cut
    assert 0.3 < conv["cut_time_s"] < 1.1 and conv["recorded_cut_time_s"] is None
    assert not conv["after_recorded_cut"]
    assert conv["predicted"] == predict_cuts(RigParams(), [conv["cut_time_s"]], 0.005)[0]
    assert 0.3 < conv["predicted"]["saving_ratio"] < 1 and not conv["predicted"]["stalled"]
    assert conv["predicted_conventional"]["saving_ratio"] == 0.0
    # the early run cut before the controller would: flagged, its own cut predicted
    assert early["after_recorded_cut"] and early["recorded_cut_time_s"] < conv["cut_time_s"]
    assert early["predicted"] is None and early["predicted_recorded"]["saving_ratio"] > 0.8
    rows = (tmp_path / "replay.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("run,description,")
    assert (tmp_path / "replay.png").stat().st_size > 10_000


def test_replay_refuses_runs_of_another_cylinder_and_two_policies(measured, tmp_path, capsys):
    """Runs of a 300 mm stroke replayed on the thesis rig's controller (an end-stroke rule would
    cut mid-stroke and report a saving): refused, naming --rig; so is a second --policy (only
    the last one ran), and a refused model is exit status 2, not a traceback."""
    from pneugym.cli import main
    from pneugym.data import simulate_run, write_run

    longer = RigParams().with_(cylinder={"stroke_m": 0.3})
    write_run(simulate_run(longer, t_end=2.0, noise="default", name="long"), tmp_path / "long")
    assert main(["replay", str(tmp_path / "long.csv"), "--policy", "endstroke"]) == 2
    assert "--rig" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["replay", str(measured), "--policy", "gaslaw", "--policy", "endstroke"])
    assert main(["replay", str(measured), "--policy", str(tmp_path / "none.pt")]) == 2


def test_replay_decides_as_fed_live(measured):
    """Replaying a run is feeding the controller its samples at the period: the same cut as a
    controller fed by hand."""
    from pneugym.data import read_run
    from pneugym.deploy.replay import replay

    run = read_run(measured / "conventional")
    ctl = Controller.load("gaslaw")
    (res,) = replay(ctl, [run])
    ctl.reset(2.5e5 + PA, 10.0)
    k = 0
    while not ctl.step(k * 0.005, *(np.interp(k * 0.005, run.t, getattr(run, c))
                                     for c in ("x", "p_drive", "p_exhaust"))):
        k += 1
    assert ctl.cut_time_s == res["cut_time_s"]


def test_replay_refuses_a_coarse_recording(measured):
    from pneugym.data import read_run
    from pneugym.deploy.replay import replay

    run = read_run(measured / "conventional")
    run.t, run.x, run.p_drive, run.p_exhaust, run.valve = (a[::10] for a in (
        run.t, run.x, run.p_drive, run.p_exhaust, run.valve))
    with pytest.raises(ValueError, match="sampled every 10 ms, coarser than the controller's "
                                         "period"):
        replay(Controller.load("gaslaw"), [run])


def test_replay_refuses_a_run_recorded_from_later(measured):
    from pneugym.data import read_run
    from pneugym.deploy.replay import replay

    run = read_run(measured / "conventional")
    keep = run.t >= 0.02
    run.t, run.x, run.p_drive, run.p_exhaust, run.valve = (a[keep] for a in (
        run.t, run.x, run.p_drive, run.p_exhaust, run.valve))
    with pytest.raises(ValueError, match="conventional: its first sample is 0.02 s after"):
        replay(Controller.load("gaslaw"), [run])
    keep = run.t >= 0.0255  # first sample just past one period: the grid's first at two
    run.t, run.x, run.p_drive, run.p_exhaust, run.valve = (a[keep] for a in (
        run.t - 0.0209, run.x, run.p_drive, run.p_exhaust, run.valve))
    with pytest.raises(ValueError, match="conventional: its first sample is 0.0051 s after"):
        replay(Controller.load("gaslaw"), [run])


def test_replay_gives_a_policy_the_commissioning_stroke_of_each_run(measured):
    """A policy that reads a commissioning stroke gets the one at the run's operating point;
    without one, or with one at another point, the run is refused."""
    from pneugym.data import read_run, simulate_run
    from pneugym.deploy.replay import replay
    from pneugym.envs.commissioning import run_features
    from pneugym.envs.cutoff import COMMISSIONING_OBSERVATION, CutOffVectorEnv

    class Reads:  # a stand-in for esac-family: reads the stroke's features, never cuts
        model_layout = {"rig_features": [{"name": COMMISSIONING_OBSERVATION[0].name}]}

        def begin_episodes(self, conds):
            pass

        def predict(self, obs):
            return np.zeros(1, np.int64), None

    env = CutOffVectorEnv(num_envs=1, observe_rig=True, observe_commissioning=True)
    ctl = Controller(Reads(), env)
    run = read_run(measured / "conventional")
    with pytest.raises(ValueError, match="reads a commissioning stroke.*--commissioning RUN"):
        replay(ctl, [run])
    other = simulate_run(RigParams().with_(supply_pressure_gauge_pa=4e5), cut_on_arrival=True,
                         t_end=3.0, seed=1)
    with pytest.raises(ValueError, match="those given are at 4 bar g / 10 kg"):
        replay(ctl, [run], commissioning=[other])
    stroke = simulate_run(RigParams(), cut_on_arrival=True, t_end=3.0, seed=1)
    (res,) = replay(ctl, [run], commissioning=[other, stroke])
    assert res["cut_time_s"] is None
    np.testing.assert_allclose(ctl.observation[-6:],
                               run_features(stroke, RigParams().cylinder.stroke_m), rtol=1e-6)
    fresh = Controller(Reads(), env)  # a stroke set on the controller serves every run
    fresh.set_commissioning(stroke)
    replay(fresh, [run])
    np.testing.assert_array_equal(fresh.observation, ctl.observation)


def test_load_takes_a_gaslaw_calibration_file():
    from pathlib import Path

    import agents

    f = Path(agents.__file__).parent / "gaslaw_k.json"
    c = Controller.load(f)
    assert "Gas-Law calibration" in c.source
    c.reset(2.5e5 + PA)
    assert c.step(0.0, 0.0, PA, PA) == 0


#: decision rules that make the small test models cut (the DQN one at once: its Q-values barely
#: trained)
CUTTING = {"esac": {"margin": 0.5, "max_time_increase": 2.0},
           "ppo": {"decision": {"rule": "quantile", "value": 0.05}},
           "dqn": {"decision": {"rule": "advantage", "value": -0.1}}}


@pytest.mark.parametrize("algo", ["esac", "ppo", "dqn"])
@pytest.mark.parametrize("backend", ["onnx", "numpy"])
def test_an_exported_controller_commands_as_the_torch_policy_in_the_environment(runs, algo,
                                                                              backend, tmp_path):
    """Exported (with a decision rule that cuts), then ``Controller.load(export_dir,
    backend=...)`` without PyTorch in the loop: fed the environment's sensor readings, the same
    valve commands as the trained model (torch) inside the environment."""
    from pneugym.deploy.export import export

    conds = conditions("robustness", 6, n=8)
    cfg = {"observe_rig": True}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export(Controller.load(runs[algo], **CUTTING[algo]).policy, tmp_path / "x")
        env = CutOffVectorEnv(num_envs=len(conds), **cfg)
        traces = environment_trace(load_policy(runs[algo], env, **CUTTING[algo]), conds, 3, cfg)
        ctl = Controller.load(tmp_path / "x", backend=backend)
    assert ctl.policy.backend_name == backend
    cuts = 0
    for cond, tr in zip(conds, traces):
        ctl.reset(cond.supply_pressure_gauge_pa + PA, cond.load_mass_kg)
        cmds = [ctl.step(*(tr[k][j] for k in ("t", "x", "p_drive", "p_exhaust")))
                for j in range(tr["t"].size)]
        assert cmds == tr["command"].tolist()
        cuts += ctl.cut
    assert cuts >= 2  # (the commands compared include cuts)


def test_pneugym_export_writes_a_controller(runs, tmp_path, capsys):
    from pneugym.cli import main

    assert main(["export", str(runs["ppo"]), "--out", str(tmp_path / "x")]) == 0
    out = capsys.readouterr().out
    assert "onnx : max |difference| from torch" in out and "of the tolerance" in out
    assert {p.name for p in (tmp_path / "x").iterdir()} == {"model.onnx", "weights.npz",
                                                            "controller.json"}
    assert main(["export", "gaslaw", "--out", str(tmp_path / "y")]) == 2  # named, no traceback
    assert "has no neural network" in capsys.readouterr().err


def test_a_retract_rig_is_refused():
    from pneugym import thesis_rig

    with pytest.raises(ValueError, match="stroke_direction is 'retract'; the controller runs "
                                         "extension strokes"):
        Controller.load("gaslaw", rig=thesis_rig(2.5, stroke_direction="retract"))


def test_the_quantile_rule_restarts_with_every_stroke(runs):
    """A stroke whose first sample comes 2 ms after the extend command (not at t = 0) starts
    the quantile rule afresh: two identical strokes, identical commands."""
    ctl = Controller.load(runs["ppo"], decision={"rule": "quantile", "value": 0.05})
    strokes = []
    for _ in range(2):
        ctl.reset(3.5e5 + PA)
        strokes.append([ctl.step(0.002 + k * 0.005, min(k * 1e-3, 0.18), 2e5 + PA, 1.5e5 + PA)
                        for k in range(120)])
    assert strokes[0] == strokes[1] and 0 < sum(strokes[0]) < 120
