"""agents.evaluation.specs: policy specs (names, NAME=PATH, decision overrides), names that would
give a wrong table, and every saved model loaded and checked before any episode or training."""
import json
import math
from pathlib import Path

import pytest

from agents import training
from agents.evaluation import cli, run, specs
from agents.training import ondemand


def test_learned_names_resolve_to_trained_models(tmp_path, monkeypatch):
    seen = {}

    def fake(names, runs, budget, progress=True, rig=None):
        seen.update(names=list(names), runs=runs, budget=budget, progress=progress, rig=rig)
        return {n: Path(runs) / n / "model.zip" for n in names}

    monkeypatch.setattr(training, "ensure_trained", fake)
    out = specs.resolve_learned(["conventional", "ppo", "esac", "x=m.zip"], str(tmp_path), "quick")
    assert out == ["conventional", f"ppo={tmp_path / 'ppo' / 'model.zip'}",
                   f"esac={tmp_path / 'esac' / 'model.zip'}", "x=m.zip"]
    assert seen == {"names": ["ppo", "esac"], "runs": str(tmp_path), "budget": "quick",
                    "progress": True, "rig": None}
    specs.resolve_learned(["ppo"], str(tmp_path), "quick", progress=False)  # --no-progress
    assert seen["progress"] is False
    specs.resolve_learned(["ppo"], str(tmp_path), "quick", rig="my_rig.yaml")  # --rig
    assert seen["rig"] == "my_rig.yaml"
    assert specs.resolve_learned(["gaslaw"], str(tmp_path), "quick") == ["gaslaw"]


@pytest.mark.parametrize("given,msg", [
    (["conventional={model}"], "'conventional' is a reference of every suite"),
    (["oracle={model}"], "'oracle' is a reference"),
    (["gaslaw={model}"], "'gaslaw' is a baseline"),
    (["ppo={model}", "ppo={model}"], "'ppo' is given twice"),
    (["gaslaw", "gaslaw"], "'gaslaw' is given twice"),
    (["a b={model}"], "policy name 'a b'"),
    (["x="], "no model path"),
])
def test_names_that_would_give_a_wrong_table_are_refused(tmp_path, given, msg):
    model = tmp_path / "m.zip"
    model.write_bytes(b"")
    given = [s.format(model=model) for s in given]
    with pytest.raises(ValueError, match=msg):
        specs.check_policy_specs(given)


def test_policy_specs_with_decision_overrides():
    assert specs.parse_spec("gaslaw") == ("gaslaw", None, {})
    assert specs.parse_spec("esac=runs/esac") == ("esac", "runs/esac", {})
    assert specs.parse_spec("e10=runs/esac:max_time_increase=0.1,lookahead=1") == (
        "e10", "runs/esac", {"max_time_increase": 0.1, "lookahead": 1.0})
    assert specs.parse_spec("p=runs/ppo/model.zip:rule=quantile,value=0.3") == (
        "p", "runs/ppo/model.zip", {"decision": {"rule": "quantile", "value": 0.3}})
    with pytest.raises(ValueError, match="rule and value only"):
        specs.parse_spec("p=runs/ppo:rule=quantile,margin=0.1")
    with pytest.raises(ValueError, match="key=value"):
        specs.parse_spec("p=runs/ppo:margin=0.1,oops")
    with pytest.raises(ValueError, match="margin= has no value; give one"):
        specs.parse_spec("e=runs/esac:margin=")
    with pytest.raises(ValueError, match="margin is given twice"):
        specs.parse_spec("e=runs/esac:margin=0.1,margin=0.2")
    assert specs.parse_spec("e=runs/esac:margin=nan")[2] == {"margin": pytest.approx(math.nan,
                                                                                     nan_ok=True)}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A small PPO, DQN (SB3 zips, their layout recorded) and ESAC model (.pt)."""
    from stable_baselines3 import DQN, PPO

    from agents import esac
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.envs.sb3 import CutOffVecEnv

    root = tmp_path_factory.mktemp("models")
    venv = CutOffVecEnv(num_envs=2)
    lay = venv.observation_layout()
    ppo = PPO("MlpPolicy", venv, n_steps=8, batch_size=16, device="cpu", seed=0,
              policy_kwargs={"net_arch": [8]})
    ppo.pneugym_layout, ppo.pneugym_decision = lay, {"rule": "quantile", "value": 0.3}
    ppo.save(root / "ppo.zip")
    dqn = DQN("MlpPolicy", venv, learning_starts=0, buffer_size=100, device="cpu", seed=0,
              policy_kwargs={"net_arch": [8]})
    dqn.pneugym_layout, dqn.pneugym_decision = lay, {"rule": "advantage", "value": 0.0}
    dqn.save(root / "dqn.zip")
    elay = CutOffVectorEnv(num_envs=1, history=2).observation_layout()
    esac.save(root / "esac.pt", esac.make_net(elay["size"], (8,)),
              {"n_in": elay["size"], "hidden": [8], "layout": elay, "rule": {"margin": 0.05}})
    return {"ppo": root / "ppo.zip", "dqn": root / "dqn.zip", "esac": root / "esac.pt"}


def test_genuine_models_and_valid_overrides_load_up_front(models):
    pols = specs.load_models([f"p={models['ppo']}", f"p3={models['ppo']}:value=0.5",
                              f"d={models['dqn']}:rule=advantage,value=0.1",
                              f"e={models['esac']}:margin=0.1,lookahead=0", "gaslaw"])
    assert set(pols) == {"p", "p3", "d", "e"}
    assert pols["p"].decision == {"rule": "quantile", "value": 0.3}
    assert pols["p3"].decision == {"rule": "quantile", "value": 0.5}   # the saved rule kept
    assert pols["d"].decision == {"rule": "advantage", "value": 0.1}
    assert pols["e"].rule()["margin"] == 0.1


@pytest.mark.parametrize("spec, match", [
    ("p={ppo}:margin=0.1", r"is a stable-baselines3 model: its decision override takes rule= "
                           r"and value= only, not \['margin'\] \(\['margin'\] are ESAC rule"),
    ("p={ppo}:rule=quantile,value=nan", r"the decision value is nan for the quantile rule; "
                                        r"expected a probability in \(0, 1\]"),
    ("p={ppo}:rule=quantile,value=abc", r"the decision value is 'abc'"),
    ("p={ppo}:rule=quantile,value=5", r"the decision value is 5.0 for the quantile rule"),
    ("p={ppo}:rule=bogus", r"the decision rule is 'bogus'"),
    ("p={ppo}:rule=hazard", r"sets the 'hazard' rule without a value; give value= too"),
    ("p={ppo}:rule=argmax,value=0.2", r"gives value=0.2 for the argmax rule"),
    ("d={dqn}:rule=quantile,value=0.5", r"the quantile rule needs a stochastic policy"),
    ("e={esac}:margin=nan", r"the rule override: margin = nan: expected the accepted predicted "
                            r"risk"),
    ("e={esac}:margin=abc", r"margin = 'abc'"),
    ("e={esac}:lookahead=0.5", r"lookahead = 0.5: expected 0 .* or 1"),
    ("e={esac}:time_demand_s=-1", r"time_demand_s = -1.0: expected an absolute time demand"),
    ("e={esac}:max_stick=-5", r"max_stick = -5.0"),
    ("e={esac}:rule=argmax", r"is an ESAC model: rule= and value= override the decision of a "
                             r"stable-baselines3 model"),
    ("e={esac}:marjin=0.1", r"unknown ESAC rule parameter\(s\) \['marjin'\] \(did you mean "
                            r"'margin'\?\)"),
])
def test_bad_overrides_are_refused_naming_the_spec(models, spec, match):
    spec = spec.format(**models)
    with pytest.raises(ValueError, match=match) as exc:
        specs.load_models([spec])
    assert str(exc.value).startswith(repr(spec))


def test_unusable_models_stop_evaluate_before_any_episode_or_training(models, tmp_path,
                                                                      monkeypatch, capsys):
    """A damaged, unsafe or mismatched model, or a run folder without a model: exit 2 with the
    message, before the reference policies run and before anything is trained."""
    import zipfile


    def never(*args, **kwargs):
        raise AssertionError("work started before the models were checked")

    monkeypatch.setattr(run, "run_policy", never)
    monkeypatch.setattr(ondemand, "train", never)
    cut = tmp_path / "cut.zip"
    cut.write_bytes(models["ppo"].read_bytes()[:300])
    unsafe = tmp_path / "unsafe.zip"
    with zipfile.ZipFile(models["ppo"]) as z, zipfile.ZipFile(unsafe, "w") as w:
        for n in z.namelist():
            data = z.read(n)
            if n == "data":
                d = json.loads(data)
                d["evil"] = {":type:": "<class 'type'>", ":serialized:": "gAR9lC4="}
                data = json.dumps(d).encode()
            w.writestr(n, data)
    (tmp_path / "norun").mkdir()
    for spec, msg in ((f"x={cut}", "cut.zip"),
                      (f"x={unsafe}", "holds a pickled object under 'evil'"),
                      (f"x={tmp_path / 'norun'}", "a directory without a finished run.json")):
        with pytest.raises(SystemExit) as exc:
            cli.main(["--policies", "gaslaw", "ppo", spec, "--suite", "nominal",
                     "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, err
    assert not (tmp_path / "out" / "results.json").exists()
    assert not (tmp_path / "runs").exists()  # nothing trained on demand


def test_points_outside_a_models_training_conditions_are_counted_and_warned_of(models, tmp_path):
    import warnings

    from agents import esac
    from agents.training import TrainingRangeWarning
    from pneugym.envs.cutoff import CutOffVectorEnv

    lay = CutOffVectorEnv(num_envs=1, history=2).observation_layout()
    net = esac.make_net(lay["size"], (8,))
    meta = {"n_in": lay["size"], "hidden": [8], "layout": lay, "rule": {"margin": 0.05}}
    esac.save(tmp_path / "preset.pt", net, {**meta, "data": {"preset": "randomized"}})
    esac.save(tmp_path / "wide.pt", net, {**meta, "data": {"preset": "randomized", "conditions": {
        "supply_pressure_gauge_pa": [150_000, 600_000], "load_mass_kg": [2, 40]}}})
    args = ["--suite", "points", "--points", "4:20", "6:40", "--episodes", "1", "--no-progress",
            "--policies", f"preset={tmp_path / 'preset.pt'}", f"wide={tmp_path / 'wide.pt'}",
            f"bare={models['esac']}"]
    with pytest.warns(TrainingRangeWarning, match=r"preset: 1 of the points suite's 2 episodes "
                      r"lie outside .*\(supply 6 bar g outside 1.5-5; load 40 kg outside 5-30\)"):
        res = cli.main([*args, "--out", str(tmp_path / "out")])
    pols = res["suites"]["points"]["policies"]
    assert pols["preset"]["outside_training_rate"] == 0.5
    assert pols["preset"]["per_condition"]["4bar-20kg"]["outside_training_rate"] == 0.0
    assert pols["wide"]["outside_training_rate"] == 0.0   # trained over the range: inside
    assert pols["bare"]["outside_training_rate"] is None  # records no training conditions
    assert pols["conventional"]["outside_training_rate"] is None  # a baseline
    with warnings.catch_warnings():  # inside every model's range: nothing to say
        warnings.simplefilter("error", TrainingRangeWarning)
        cli.main([*args[:3], "4:20", *args[5:], "--out", str(tmp_path / "in")])


def test_a_model_loaded_for_a_rig_run_outside_its_training_conditions_warns(tmp_path):
    from agents import esac
    from agents.registry import load_policy
    from agents.training import TrainingRangeWarning
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.params import RigParams

    lay = CutOffVectorEnv(num_envs=1, history=2).observation_layout()
    esac.save(tmp_path / "m.pt", esac.make_net(lay["size"], (8,)),
              {"n_in": lay["size"], "hidden": [8], "layout": lay, "rule": {"margin": 0.05},
               "data": {"preset": "randomized"}})
    rig = RigParams().with_(supply_pressure_gauge_pa=250_000.0, load_mass_kg=40.0)
    env = CutOffVectorEnv(num_envs=1, history=2, rig=rig)
    with pytest.warns(TrainingRangeWarning, match=r"this rig's operating point lies outside the "
                                                  r"conditions it was trained on \(load 40 kg "
                                                  r"outside 5-30\)"):
        pol = load_policy(tmp_path / "m.pt", env)
    assert pol.training_space.load_mass_kg == (5.0, 30.0)
