"""agents.evaluation.suites: the issue's condition grid, seeded episodes."""
import pytest

from agents.evaluation.suites import suite_cells, suite_episodes


def test_suites_cover_the_issue_grid():
    rob = dict(suite_cells("robustness"))
    for m in (5, 10, 15, 20, 30):
        for b in (1.5, 2, 2.5, 3, 4, 5):
            assert f"{b:g}bar-{m:g}kg" in rob
    assert any("dip" in k for k in rob) and any("friction" in k for k in rob)
    assert any("valve-delay" in k for k in rob)
    assert [lab for lab, _ in suite_cells("nominal")] == ["1.5bar-10kg", "2.5bar-10kg"]
    with pytest.raises(ValueError, match="unknown suite"):
        suite_cells("nope")


def test_episodes_are_seeded_and_distinct():
    a = suite_episodes("robustness", 2, 1_000_000)
    b = suite_episodes("robustness", 2, 1_000_000)
    c = suite_episodes("robustness", 2, 1_000_001)
    assert a == b
    dips_a = [cond.dip for lab, cond in a if "dip" in lab]
    dips_c = [cond.dip for lab, cond in c if "dip" in lab]
    assert dips_a != dips_c and all(cond.dip_depth >= 0.1 for cond in [x[1] for x in a
                                                                       if "dip" in x[0]])


def test_the_retraining_benchmark_trains_over_the_operating_points(tmp_path, monkeypatch):
    """benchmarks/bench_transfer.py's retraining, on a small budget: the ESAC trained for a
    transfer rig learns over a range holding every operating point of the suite, records it,
    and a finished run is reused."""
    import json
    import sys
    from pathlib import Path

    from agents import training
    from agents.esac.modelfile import load
    from agents.evaluation.suites import TRANSFER_POINTS, transfer_rigs
    from pneugym.envs.family import apply_changes
    from pneugym.params import RigParams

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    sys.modules.pop("bench_transfer", None)
    import bench_transfer

    rng = bench_transfer.points_range()
    for bar, kg in TRANSFER_POINTS:
        assert rng["supply_pressure_gauge_pa"][0] <= bar * 1e5 <= rng["supply_pressure_gauge_pa"][1]
        assert rng["load_mass_kg"][0] <= kg <= rng["load_mass_kg"][1]
    rig = apply_changes(RigParams(), transfer_rigs()["heldout-1"])
    tiny = ("timesteps=48", "env.history=3", "test.episodes=24", "validation.episodes=2",
            "fit.epochs=2", "fit.hidden=[16]", "rule_grid={margin: [0.05], max_time_increase: [0.1]}",
            f"cache_dir={tmp_path / 'cache'}")
    spec = bench_transfer.retrain("heldout-1", rig, tmp_path, "quick", "points", False, tiny)
    name, path = spec.split("=", 1)
    assert name == "esac_retrained" and Path(path).is_file()
    run = json.loads((tmp_path / "heldout-1" / "esac" / "run.json").read_text())
    assert run["config"]["env"]["conditions"] == rng
    assert load(path)[1]["data"]["conditions"] == rng

    def never(*args, **kwargs):
        raise AssertionError("trained again")

    monkeypatch.setattr(training, "train", never)
    assert bench_transfer.retrain("heldout-1", rig, tmp_path, "quick", "points", False,
                                  tiny) == spec
    for other in (("default", "points", tiny), ("quick", "preset", tiny), ("quick", "points", ())):
        with pytest.raises(AssertionError, match="trained again"):  # other options: not reused
            bench_transfer.retrain("heldout-1", rig, tmp_path, other[0], other[1], False, other[2])
