"""evaluate.py: suites, the results.json schema the issue fixes, oracle_fraction, outputs, and the
refusals before any work (specs, models, overrides, --seed, --runs, --out)."""
import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import evaluate as ev  # noqa: E402

KEYS = {"episodes", "saving_mean", "time_increase_mean", "stall_rate", "stick_slip_rate",
        "completion_rate", "oracle_fraction"}


@pytest.fixture(scope="module")
def nominal(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    res = ev.main(["--policies", "conventional", "endstroke", "gaslaw", "oracle", "--suite",
                   "nominal", "--episodes", "1", "--out", str(out)])
    return res, out


def test_suites_cover_the_issue_grid():
    rob = dict(ev.suite_cells("robustness"))
    for m in (5, 10, 15, 20, 30):
        for b in (1.5, 2, 2.5, 3, 4, 5):
            assert f"{b:g}bar-{m:g}kg" in rob
    assert any("dip" in k for k in rob) and any("friction" in k for k in rob)
    assert any("valve-delay" in k for k in rob)
    assert [lab for lab, _ in ev.suite_cells("nominal")] == ["1.5bar-10kg", "2.5bar-10kg"]
    with pytest.raises(ValueError, match="unknown suite"):
        ev.suite_cells("nope")


def test_episodes_are_seeded_and_distinct():
    a = ev.suite_episodes("robustness", 2, 1_000_000)
    b = ev.suite_episodes("robustness", 2, 1_000_000)
    c = ev.suite_episodes("robustness", 2, 1_000_001)
    assert a == b
    dips_a = [cond.dip for lab, cond in a if "dip" in lab]
    dips_c = [cond.dip for lab, cond in c if "dip" in lab]
    assert dips_a != dips_c and all(cond.dip_depth >= 0.1 for cond in [x[1] for x in a
                                                                        if "dip" in x[0]])


def test_results_schema_and_reference_fractions(nominal):
    res, out = nominal
    assert set(res) >= {"suites", "config", "versions", "seed"}
    pols = res["suites"]["nominal"]["policies"]
    assert set(pols) == {"conventional", "endstroke", "gaslaw", "oracle"}
    for p in pols.values():
        assert KEYS <= set(p)
        assert p["episodes"] == 2
    assert pols["conventional"]["oracle_fraction"] == pytest.approx(0.0)
    assert pols["oracle"]["oracle_fraction"] == pytest.approx(1.0)
    assert pols["conventional"]["saving_mean"] == pytest.approx(0.0, abs=1e-9)
    # the oracle is the best latched single cut-off: no baseline beats it
    for name in ("endstroke", "gaslaw"):
        assert pols[name]["return_mean"] <= pols["oracle"]["return_mean"] + 1e-12
        assert pols[name]["oracle_fraction"] <= 1.0 + 1e-9
    # the end-stroke cut saves energy without slowing the stroke (thesis 5.7)
    assert 0.3 < pols["endstroke"]["saving_mean"] < 0.6
    assert abs(pols["endstroke"]["time_increase_mean"]) < 0.01


def test_outputs_written(nominal):
    res, out = nominal
    data = json.loads((out / "results.json").read_text())
    assert data["suites"]["nominal"]["policies"]["oracle"]["oracle_fraction"] == pytest.approx(1)
    eps = data["suites"]["nominal"]["episodes"]
    assert len(eps) == 8 and {"policy", "condition", "saving_ratio", "objective"} <= set(eps[0])
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 9
    for png in ("nominal_saving_vs_time.png", "example_trajectories.png"):
        assert (out / png).stat().st_size > 1000


def test_per_condition_fractions(nominal):
    res, _ = nominal
    pc = res["suites"]["nominal"]["policies"]["gaslaw"]["per_condition"]
    assert set(pc) == {"1.5bar-10kg", "2.5bar-10kg"}
    for v in pc.values():
        assert v["episodes"] == 1 and (v["oracle_fraction"] is None
                                       or math.isfinite(v["oracle_fraction"]))


def test_learned_names_resolve_to_trained_models(tmp_path, monkeypatch):
    import train

    seen = {}

    def fake(names, runs, budget):
        seen.update(names=list(names), runs=runs, budget=budget)
        return {n: Path(runs) / n / "model.zip" for n in names}

    monkeypatch.setattr(train, "ensure_trained", fake)
    out = ev.resolve_learned(["conventional", "ppo", "esac", "x=m.zip"], str(tmp_path), "quick")
    assert out == ["conventional", f"ppo={tmp_path / 'ppo' / 'model.zip'}",
                   f"esac={tmp_path / 'esac' / 'model.zip'}", "x=m.zip"]
    assert seen == {"names": ["ppo", "esac"], "runs": str(tmp_path), "budget": "quick"}
    assert ev.resolve_learned(["gaslaw"], str(tmp_path), "quick") == ["gaslaw"]


def test_unknown_policy_and_bad_path_are_refused_before_any_work(tmp_path, capsys):
    for spec, msg in (("nope", "unknown policy 'nope'"),
                      (f"x={tmp_path / 'missing.zip'}", "no saved model at")):
        with pytest.raises(SystemExit):
            ev.main(["--policies", "gaslaw", spec, "--suite", "nominal", "--out", str(tmp_path)])
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()
    bad = tmp_path / "bad.zip"
    bad.write_text("not a zip")
    with pytest.raises(SystemExit):
        ev.main(["--policies", f"x={bad}", "--suite", "nominal", "--out", str(tmp_path)])
    assert "bad.zip is not a stable-baselines3 model" in capsys.readouterr().err


@pytest.mark.parametrize("specs,msg", [
    (["conventional={model}"], "'conventional' is a reference of every suite"),
    (["oracle={model}"], "'oracle' is a reference"),
    (["gaslaw={model}"], "'gaslaw' is a baseline"),
    (["ppo={model}", "ppo={model}"], "'ppo' is given twice"),
    (["gaslaw", "gaslaw"], "'gaslaw' is given twice"),
    (["a b={model}"], "policy name 'a b'"),
    (["x="], "no model path"),
])
def test_names_that_would_give_a_wrong_table_are_refused(tmp_path, specs, msg):
    model = tmp_path / "m.zip"
    model.write_bytes(b"")
    specs = [s.format(model=model) for s in specs]
    with pytest.raises(ValueError, match=msg):
        ev.check_policy_specs(specs)


def test_out_that_is_a_file_is_refused_before_any_work(tmp_path, capsys):
    f = tmp_path / "results"
    f.write_text("")
    with pytest.raises(SystemExit):
        ev.main(["--policies", "gaslaw", "--suite", "nominal", "--out", str(f)])
    assert "exists and is not a folder" in capsys.readouterr().err


def test_a_failed_write_leaves_the_previous_results(tmp_path, monkeypatch, nominal):
    res, _ = nominal
    ev.write_outputs(res, tmp_path)
    before = (tmp_path / "results.json").read_bytes()

    def boom(results, out):
        raise RuntimeError("disk full")

    monkeypatch.setattr(ev, "plot_results", boom)
    changed = dict(res, seed=res["seed"] + 1)
    with pytest.raises(RuntimeError, match="disk full"):
        ev.write_outputs(changed, tmp_path)
    assert (tmp_path / "results.json").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".staging")]


def test_policy_specs_with_decision_overrides():
    assert ev.parse_spec("gaslaw") == ("gaslaw", None, {})
    assert ev.parse_spec("esac=runs/esac") == ("esac", "runs/esac", {})
    assert ev.parse_spec("e10=runs/esac:max_time_increase=0.1,lookahead=1") == (
        "e10", "runs/esac", {"max_time_increase": 0.1, "lookahead": 1.0})
    assert ev.parse_spec("p=runs/ppo/model.zip:rule=quantile,value=0.3") == (
        "p", "runs/ppo/model.zip", {"decision": {"rule": "quantile", "value": 0.3}})
    with pytest.raises(ValueError, match="rule and value only"):
        ev.parse_spec("p=runs/ppo:rule=quantile,margin=0.1")
    with pytest.raises(ValueError, match="key=value"):
        ev.parse_spec("p=runs/ppo:margin=0.1,oops")
    with pytest.raises(ValueError, match="margin= has no value; give one"):
        ev.parse_spec("e=runs/esac:margin=")
    with pytest.raises(ValueError, match="margin is given twice"):
        ev.parse_spec("e=runs/esac:margin=0.1,margin=0.2")
    assert ev.parse_spec("e=runs/esac:margin=nan")[2] == {"margin": pytest.approx(math.nan,
                                                                                  nan_ok=True)}


# ------------------------------------------------------------------------------------------------
# saved models and overrides are loaded and checked before any work
# ------------------------------------------------------------------------------------------------
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
    pols = ev.load_models([f"p={models['ppo']}", f"p3={models['ppo']}:value=0.5",
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
        ev.load_models([spec])
    assert str(exc.value).startswith(repr(spec))


def test_unusable_models_stop_evaluate_before_any_episode_or_training(models, tmp_path,
                                                                       monkeypatch, capsys):
    """A damaged, unsafe or mismatched model, or a run folder without a model: exit 2 with the
    message, before the reference policies run and before anything is trained."""
    import zipfile

    import train

    def never(*args, **kwargs):
        raise AssertionError("work started before the models were checked")

    monkeypatch.setattr(ev, "run_policy", never)
    monkeypatch.setattr(train, "train", never)
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
            ev.main(["--policies", "gaslaw", "ppo", spec, "--suite", "nominal",
                     "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, err
    assert not (tmp_path / "out" / "results.json").exists()
    assert not (tmp_path / "runs").exists()  # nothing trained on demand


def test_seed_runs_and_out_are_checked_before_any_work(tmp_path, monkeypatch, capsys):
    import pneugym.outputs

    monkeypatch.setattr(ev, "run_policy", lambda *a, **k: pytest.fail("episodes ran"))
    with pytest.raises(SystemExit):
        ev.main(["--policies", "gaslaw", "--seed", "-1", "--out", str(tmp_path)])
    assert "--seed -1: episode seeds must be integers from 0" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(SystemExit):
        ev.main(["--policies", "gaslaw", "ppo", "--runs", str(afile), "--out", str(tmp_path)])
    assert f"--runs {afile} is a file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        ev.main(["--policies", "esac", "--runs", str(tmp_path / "r"), "--budget", "quik",
                 "--out", str(tmp_path)])
    assert "has no budget 'quik' (did you mean 'quick'?)" in capsys.readouterr().err
    # --out "" reaches check_output_dir as given (not as Path("") == "."), which refuses it
    seen = []
    real = pneugym.outputs.check_output_dir
    monkeypatch.setattr(ev, "check_output_dir", lambda p, what: seen.append(p) or real(p, what))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        ev.main(["--policies", "gaslaw", "--suite", "nominal", "--out", ""])
    assert seen == [""] and "--out is empty" in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()
