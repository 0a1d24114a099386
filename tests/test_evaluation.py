"""agents.evaluation: the results.json schema the issue fixes, oracle_fraction, the outputs
(written as a set), and the command line's refusals before any work (specs, models, --seed,
--runs, --out)."""
import json
import math
import re

import pytest

from agents.evaluation import cli, outputs, run

KEYS = {"episodes", "saving_mean", "time_increase_mean", "stall_rate", "stick_slip_rate",
        "completion_rate", "oracle_fraction"}


@pytest.fixture(scope="module")
def nominal(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    res = cli.main(["--policies", "conventional", "endstroke", "gaslaw", "oracle", "--suite",
                   "nominal", "--episodes", "1", "--out", str(out)])
    return res, out


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


def test_oracle_fraction_of_mean_returns():
    assert run.oracle_fraction(-0.5, -1.0, 0.0) == pytest.approx(0.5)
    assert run.oracle_fraction(-1.0, -1.0, 0.0) == 0.0
    assert run.oracle_fraction(-0.5, -1.0, -1.0) is None  # the oracle gains nothing


def test_family_draws_are_seeded_noisy_and_nested():
    from agents.evaluation.suites import NOISE, family_draws

    a, b = family_draws(3_000_000, 3), family_draws(3_000_000, 2)
    assert a[:2] == b and a != family_draws(4_000_000, 3)
    assert all(c.rig_changes and c.position_noise_m == NOISE["position_noise_m"]
               and c.pressure_noise_pa == NOISE["pressure_noise_pa"] for c in a)


def test_unknown_policy_and_bad_path_are_refused_before_any_work(tmp_path, capsys):
    for spec, msg in (("nope", "unknown policy 'nope'"),
                      (f"x={tmp_path / 'missing.zip'}", "no saved model at")):
        with pytest.raises(SystemExit):
            cli.main(["--policies", "gaslaw", spec, "--suite", "nominal", "--out", str(tmp_path)])
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()
    bad = tmp_path / "bad.zip"
    bad.write_text("not a zip")
    with pytest.raises(SystemExit):
        cli.main(["--policies", f"x={bad}", "--suite", "nominal", "--out", str(tmp_path)])
    assert "bad.zip is not a stable-baselines3 model" in capsys.readouterr().err


def test_out_that_is_a_file_is_refused_before_any_work(tmp_path, capsys):
    f = tmp_path / "results"
    f.write_text("")
    with pytest.raises(SystemExit):
        cli.main(["--policies", "gaslaw", "--suite", "nominal", "--out", str(f)])
    assert "exists and is not a folder" in capsys.readouterr().err


def test_a_failed_write_leaves_the_previous_results(tmp_path, monkeypatch, nominal):
    res, _ = nominal
    outputs.write_outputs(res, tmp_path)
    before = (tmp_path / "results.json").read_bytes()

    def boom(results, out):
        raise RuntimeError("disk full")

    monkeypatch.setattr(outputs, "plot_results", boom)
    changed = dict(res, seed=res["seed"] + 1)
    with pytest.raises(RuntimeError, match="disk full"):
        outputs.write_outputs(changed, tmp_path)
    assert (tmp_path / "results.json").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".staging")]


def test_seed_runs_and_out_are_checked_before_any_work(tmp_path, monkeypatch, capsys):
    import pneugym.outputs

    monkeypatch.setattr(run, "run_policy", lambda *a, **k: pytest.fail("episodes ran"))
    with pytest.raises(SystemExit):
        cli.main(["--policies", "gaslaw", "--seed", "-1", "--out", str(tmp_path)])
    assert "--seed -1: episode seeds must be integers from 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["--policies", "mpc-rig", "--commission-refit", "-1", "--out", str(tmp_path)])
    assert "--commission-refit -1: must be >= 0" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(SystemExit):
        cli.main(["--policies", "gaslaw", "ppo", "--runs", str(afile), "--out", str(tmp_path)])
    assert f"--runs {afile} is a file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["--policies", "esac", "--runs", str(tmp_path / "r"), "--budget", "quik",
                 "--out", str(tmp_path)])
    assert "has no budget 'quik' (did you mean 'quick'?)" in capsys.readouterr().err
    # --out "" reaches check_output_dir as given (not as Path("") == "."), which refuses it
    seen = []
    real = pneugym.outputs.check_output_dir
    monkeypatch.setattr(cli, "check_output_dir", lambda p, what: seen.append(p) or real(p, what))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        cli.main(["--policies", "gaslaw", "--suite", "nominal", "--out", ""])
    assert seen == [""] and "--out is empty" in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()


def test_no_progress_hides_the_progress_bars(tmp_path, capsys):
    """--no-progress, as pneugym train has it: no bar over the suite's policies (the figures are
    the same)."""
    argv = ["--policies", "gaslaw", "--suite", "nominal", "--episodes", "1"]
    with_bar = cli.main(argv + ["--out", str(tmp_path / "a")])
    assert "nominal suite" in capsys.readouterr().err
    without = cli.main(argv + ["--out", str(tmp_path / "b"), "--no-progress"])
    assert "nominal suite" not in capsys.readouterr().err
    assert without["suites"]["nominal"]["episodes"] == with_bar["suites"]["nominal"]["episodes"]


def test_the_points_suite_takes_the_users_operating_points(tmp_path, capsys):
    res = cli.main(["--policies", "endstroke", "--suite", "points", "--points", "4:20", "6:40",
                    "--episodes", "1", "--out", str(tmp_path), "--no-progress"])
    suite = res["suites"]["points"]
    assert suite["conditions"] == ["4bar-20kg", "6bar-40kg"]
    assert res["config"]["points"] == [[4.0, 20.0], [6.0, 40.0]]
    eps = [e for e in suite["episodes"] if e["policy"] == "endstroke"]
    assert [(e["supply_pressure_gauge_pa"], e["load_mass_kg"]) for e in eps] == \
        [(4e5, 20.0), (6e5, 40.0)]
    for argv, match in (
            (["--suite", "nominal", "--points", "4:20"], "give --suite points"),
            (["--suite", "points", "--points", "4-20"], "expected BAR:KG"),
            (["--suite", "points", "--points", "25:5"], r"operating point 25 bar g / 5 kg: "
                                                      r"RigParams.supply_pressure_gauge_pa"),
            (["--suite", "points", "--points", "4:20", "4:20"], "given twice")):
        with pytest.raises(SystemExit) as exc:
            cli.main(["--policies", "endstroke", "--out", str(tmp_path / "x"), *argv])
        assert exc.value.code == 2 and re.search(match, capsys.readouterr().err)
        assert not (tmp_path / "x").exists()
