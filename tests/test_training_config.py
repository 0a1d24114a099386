"""agents.training.config (with .schema, .checks, .seeds): the configuration is checked whole
before a run writes anything, and every problem is named with where it came from."""
import pytest

from agents import training
from agents.training import cli, esac, sb3, trainer


@pytest.fixture
def nothing_runs(monkeypatch):
    """Training, thread set-up and run.json writes fail the test if they are reached."""
    def never(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(sb3, "train_sb3", never)
    monkeypatch.setattr(esac, "train_esac", never)
    for name in ("_threads", "atomic_write_json"):
        monkeypatch.setattr(trainer, name, never)


def test_configs_and_refusals(tmp_path):
    for algo in training.ALGOS:
        d, q = training.load_config(algo), training.load_config(algo, "quick")
        assert q["timesteps"] < d["timesteps"]
    # PPO's checkpoint and decision choice needs a large validation set (144 chose by noise)
    assert training.load_config("ppo")["validation"]["episodes"] >= 1024
    cfg = training.load_config("ppo", overrides=["algo.learning_rate=1e-4", "env.history=8"])
    assert cfg["algo"]["learning_rate"] == 1e-4 and cfg["env"]["history"] == 8
    with pytest.raises(ValueError, match="no budget"):
        training.load_config("ppo", "huge")
    with pytest.raises(ValueError, match="reserved for evaluation"):
        training.train("ppo", tmp_path / "x", seed=1_000_000, progress=False)
    with pytest.raises(ValueError, match="unknown algorithm"):
        training.train("sac", tmp_path / "x", progress=False)
    with pytest.raises(SystemExit):
        cli.main(["--algo", "ppo", "--seed", "2000000", "--out", str(tmp_path / "y")])


@pytest.mark.parametrize("algo, overrides, match", [
    ("ppo", ["algo.n_stepz=64"], r"--set algo.n_stepz=64: 'algo.n_stepz' is not a known keyword "
                                 r"of stable_baselines3.PPO \(did you mean 'n_steps'\?\)"),
    ("ppo", ["env.num_envs=0"], r"--set env.num_envs=0: env.num_envs = 0: expected an integer "
                                r"from 1 to 4,096"),
    ("ppo", ["algo.learning_rate=abc"], r"algo.learning_rate = 'abc': expected a finite number "
                                        r"> 0, or lin_<x>.*\(it is text, not a number\)"),
    ("ppo", ["algo.learning_rate=lin_abc"], r"'abc' after lin_ is not a number > 0"),
    ("ppo", ["algo.learning_rate=-1"], r"algo.learning_rate = -1: expected a finite number > 0"),
    ("ppo", ["env.histroy=2"], r"'env.histroy' is not a known environment option .*did you "
                               r"mean 'history'"),
    ("ppo", ["eval_everyy=256"], r"--set eval_everyy=256: 'eval_everyy' is not a known "
                                 r"configuration entry \(did you mean 'eval_every'\?\)"),
    ("ppo", ["learning_rate=1e-4"], r"did you mean 'algo.learning_rate'"),
    ("ppo", ["algo.seed=3"], r"algo.seed is --seed"),
    ("ppo", ["env.control_period_s=abc"], r"--set env.control_period_s=abc: env: "
                                          r"control_period_s = 'abc' is invalid"),
    ("ppo", ["validation.episodes=0"], r"validation.episodes = 0: expected an integer"),
    ("ppo", ["validation.seed=999999"], r"--set validation.seed=999999: validation seeds "
                                        r"999999..1001022 must lie in \[0, 1000000\)"),
    ("ppo", ["policy_kwargs.net_arch=[100000]"], r"policy_kwargs.net_arch = \[100000\]: expected "
                                                 r"a list of layer widths"),
    ("ppo", ["policy_kwargs.activation_fn=relu"], r"policy_kwargs.activation_fn is a class"),
    ("ppo", ["decision.rules={quantile: [0.2, 2]}"], r"decision.rules: quantile value 2: "
                                                     r"expected a probability in \(0, 1\]"),
    ("ppo", ["decision.rules={advantage: [0.1]}"], r"rule 'advantage' is not one of"),
    ("ppo", ["decision.rule=quantile"], r"decision has rules and rule/grid"),
    ("ppo", ["algo.n_steps=1.5"], r"algo.n_steps = 1.5: expected an integer >= 1 \(1.5 is "
                                  r"not a whole number\)"),
    ("ppo", ["algo.gamma=true"], r"algo.gamma = True: expected a finite number in \[0, 1\] "
                                 r"\(true/false is not a number\)"),
    ("dqn", ["privileged_critic=true"], r"privileged_critic: true needs an actor-critic"),
    ("dqn", ["algo.train_freq=[4, epoch]"], r"algo.train_freq = \[4, 'epoch'\]"),
    ("esac", ["fit.hidden=[100000]"], r"fit.hidden = \[100000\]"),
    ("esac", ["fit.delay_input=false"], r"rule_grid.lookahead has 1, but the lookahead needs a "
                                        r"predictor trained with fit.delay_input"),
    ("esac", ["rule_grid.margin=[.nan]"], r"rule_grid.margin = \[nan\]: expected a list of "
                                          r"values; item 0 \(nan\) is not the accepted"),
    ("esac", ["env.time_limit_s=6"], r"'env.time_limit_s' is not a known ESAC environment "
                                     r"option"),
    ("esac", ["rule_grid.time_demand_s=[1.0]"], r"rule_grid.time_demand_s is not tuned"),
    ("esac", ["budget=quick"], r"--set budget=quick: budget is set by train.py \(give --budget\)"),
    ("esac", ["env.conditions.load_mass_kg=[40, 2]"], r"--set env.conditions.load_mass_kg=\[40, "
                                                      r"2\]: env.conditions = .*need finite low "
                                                      r"<= high"),
    ("esac", ["env.conditions.suply_pressure_gauge_pa=3e5"], r"did you mean "
                                                             r"'supply_pressure_gauge_pa'"),
    ("esac", ["env.conditions.family=true"], r"family is set by the preset"),
    ("esac", ["env.conditions=[1, 2]"], r"env.conditions = \[1, 2\]: expected a section of "
                                        r"ConditionSpace fields"),
    ("ppo", ["env.conditions.load_mass_kg=-1"], r"env.conditions = .*load_mass_kg = -1.0 is "
                                                r"invalid"),
    ("esac", ["env.observe_commissioning=true"], r"--set env.observe_commissioning=true: env: "
                                                 r"observe_commissioning=True needs observe_rig"),
    ("ppo", ["env.history=010"], r"--set 'env.history=010': the value: 010 would be read as 8"),
    ("ppo", ["policy_kwargs.net_arch=[64, 010]"], r"010 would be read as 8"),  # inside a list
    ("ppo", ["eval_every=0x100"], r"would be read as 256"),
    ("ppo", ["env.num_envs=16"], None),  # (seed 999,990 below: environments 10-15 would not be)
])
def test_config_errors_are_refused_before_anything_is_written(tmp_path, nothing_runs, algo,
                                                              overrides, match):
    d = tmp_path / "run"
    seed = 1 if match else 999_990
    match = match or r"env.num_envs=16: training seeds 999990..1000005 must lie in \[0, 1000000\)"
    with pytest.raises(training.ConfigError, match=match):
        training.train(algo, d, timesteps=256, seed=seed, progress=False, overrides=overrides)
    assert not d.exists()


def test_a_rig_file_and_rig_overrides_together_are_refused(tmp_path):
    with pytest.raises(training.ConfigError, match=r"--set rig.load_mass_kg=20: --rig replaces "
                                                   r"the configuration's rig section"):
        training.load_config("esac", overrides=["rig.load_mass_kg=20"],
                             rig={"load_mass_kg": 12.0})
    cfg = training.load_config("esac", overrides=["rig.load_mass_kg=20"])  # without --rig: kept
    assert cfg["rig"]["load_mass_kg"] == 20


def test_a_run_that_fails_says_so_in_its_folder(tmp_path, monkeypatch):
    import json

    def broken(*args, **kwargs):
        raise RuntimeError("the disk is full")

    monkeypatch.setattr(esac, "train_esac", broken)
    with pytest.raises(RuntimeError, match="the disk is full"):
        training.train("esac", tmp_path / "run", timesteps=8, seed=1, progress=False)
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["status"] == "failed" and run["error"] == "RuntimeError: the disk is full"
    with pytest.raises(ValueError) as exc:  # ESAC keeps no checkpoints: no --resume advice
        training.train("esac", tmp_path / "run", timesteps=8, seed=1, progress=False)
    assert "failed: RuntimeError" in str(exc.value) and "--resume" not in str(exc.value)


def test_tuned_values_reach_the_config_as_they_were():
    from agents.training.tune import _overrides

    cfg = training.load_config("ppo", overrides=_overrides({"algo.target_kl": None,
                                                           "algo.learning_rate": 1e-4}))
    assert cfg["algo"]["target_kl"] is None and cfg["algo"]["learning_rate"] == 1e-4


@pytest.mark.parametrize("argv, match", [
    (["--timesteps", "0"], r"--timesteps: timesteps = 0: expected an integer from 1 to "
                           r"1,000,000,000,000"),
    (["--timesteps", "-5"], r"--timesteps: timesteps = -5: expected an integer from 1"),
    (["--preset", "Randomized"], r"--preset: preset = 'Randomized': expected one of .*did you "
                                 r"mean 'randomized'"),
    (["--budget", "quik"], r"has no budget 'quik' \(did you mean 'quick'\?\)"),
    (["--config", "/nonexistent.yaml"], r"--config /nonexistent.yaml cannot be read: No such "
                                        r"file"),
    (["--set", "algo.n_stepz=64"], r"did you mean 'n_steps'"),
    (["--set", "algo.learning_rate=[1"], r"--set 'algo.learning_rate=\[1': the value '\[1' is "
                                         r"not valid YAML"),
    (["--set", "algo..x=1"], r"has an empty part"),
    (["--out", ""], r"run folder \(--out\) is empty"),
])
def test_cli_config_errors_exit_2_with_the_message(tmp_path, nothing_runs, capsys, argv, match):
    import re

    argv = ["--algo", "ppo", "--out", str(tmp_path / "run"), *argv]
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert "Traceback" not in err and not (tmp_path / "run").exists()


def test_config_files_broken_or_with_yaml_1_1_numbers(tmp_path, nothing_runs):
    broken = tmp_path / "broken.yaml"
    broken.write_text("default: [1, 2\n")
    with pytest.raises(training.ConfigError, match=r"broken.yaml: not valid YAML: .*line"):
        training.train("ppo", tmp_path / "a", config=broken, progress=False)
    evil = tmp_path / "evil.yaml"
    evil.write_text(f'default: !!python/object/apply:os.system ["touch {tmp_path}/ran"]\n')
    with pytest.raises(training.ConfigError, match=r"evil.yaml: plain YAML only"):
        training.train("ppo", tmp_path / "a", config=evil, progress=False)
    assert not (tmp_path / "ran").exists()
    # a YAML 1.1 reader takes 1e-4 for text: the likely mistake is named
    text = (training.CONFIG_DIR / "ppo.yaml").read_text().replace("learning_rate: 3.0e-4",
                                                                  "learning_rate: 1e-4")
    yaml11 = tmp_path / "ppo.yaml"
    yaml11.write_text(text)
    with pytest.raises(training.ConfigError, match=r"ppo.yaml: algo.learning_rate = '1e-4': "
                       r".*YAML 1.1 reads 1e-4 as text"):
        training.train("ppo", tmp_path / "a", config=yaml11, progress=False)
    # a key the code needs, missing
    no_val = tmp_path / "noval.yaml"
    no_val.write_text((training.CONFIG_DIR / "dqn.yaml").read_text().replace(
        "  validation:\n    episodes: 48\n    seed: 900000\n", ""))
    with pytest.raises(training.ConfigError, match=r"noval.yaml: validation is missing"):
        training.train("dqn", tmp_path / "a", config=no_val, progress=False)
    assert not (tmp_path / "a").exists()


def test_every_shipped_config_passes_the_check():
    for algo in training.ALGOS:
        for budget in ("default", "quick"):
            training.load_config(algo, budget, seed=0)
    cfg = training.load_config("ppo", overrides=["timesteps=1e5", "algo.n_steps=512.0"])
    assert cfg["timesteps"] == 100_000 and isinstance(cfg["algo"]["n_steps"], int)


def test_condition_overrides_reach_training_and_validation():
    """``env.conditions`` narrows or widens the preset's ranges for the rollouts, the held-out
    test and the validation conditions the rule or checkpoint is chosen on."""
    from agents.training.validation import validation_conditions

    cfg = training.load_config("esac", "quick", overrides=[
        "env.conditions.supply_pressure_gauge_pa=[450000, 600000]",
        "env.conditions.load_mass_kg=35"])
    cond = cfg["env"]["conditions"]
    assert cond == {"supply_pressure_gauge_pa": [450000, 600000], "load_mass_kg": 35}
    conds = validation_conditions(cfg["preset"], 20, 900000, None, cond)
    assert all(450000 <= c.supply_pressure_gauge_pa <= 600000 and c.load_mass_kg == 35
               for c in conds)
    plain = validation_conditions(cfg["preset"], 20, 900000)
    assert any(c.supply_pressure_gauge_pa < 450000 for c in plain)
    # the other fields keep the preset's ranges and draws
    assert [c.friction_scale for c in conds] == [c.friction_scale for c in plain]


def test_a_rig_operating_outside_the_training_conditions_is_warned_of(tmp_path, nothing_runs):
    import warnings

    from agents.training import TrainingRangeWarning
    from pneugym.params import RigParams

    rig = RigParams().with_(supply_pressure_gauge_pa=550_000.0, load_mass_kg=35.0)
    with pytest.warns(TrainingRangeWarning, match=r"supply 5.5 bar g outside 1.5-5; load 35 kg "
                                                  r"outside 5-30.*env.conditions"):
        with pytest.raises(AssertionError, match="training started"):
            training.train("esac", tmp_path / "a", budget="quick", rig=rig, progress=False)
    with warnings.catch_warnings():  # trained over the range it runs at: nothing to say
        warnings.simplefilter("error", TrainingRangeWarning)
        with pytest.raises(AssertionError, match="training started"):
            training.train("esac", tmp_path / "b", budget="quick", rig=rig, progress=False,
                           overrides=["env.conditions.supply_pressure_gauge_pa=[150000, 600000]",
                                      "env.conditions.load_mass_kg=[2, 40]"])
