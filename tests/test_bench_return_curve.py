"""benchmarks/bench_return_curve.py (issue 12's diagnosis of learned cut-offs) on a small budget:
the same code paths as the published figures."""
import json
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def bench(monkeypatch):
    # imported by its name from its folder (it imports `common` beside it), as spawned workers
    # import it to run its tasks
    import importlib

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    return importlib.import_module("bench_return_curve")


def test_static_columns_are_what_a_policy_may_read_before_the_stroke(bench):
    from agents.base import ObservationReader
    from agents.evaluation.suites import family_draws
    from pneugym.envs.cutoff import CutOffVectorEnv

    env = CutOffVectorEnv(num_envs=2, autoreset=False, **bench.env_config())
    conds = family_draws(300_000, 2)
    obs, _ = env.reset(seed=1, options={"conditions": conds})
    layout = env.observation_layout()
    cols = bench.static_columns(layout)
    read = ObservationReader(layout)
    names = ["supply_setpoint"] + [f["name"] for f in layout["rig_features"]
                                   if f["name"] not in bench.EVENT_FEATURES]
    assert len(cols) == len(names) == 11
    for c, name in zip(cols, names):
        k, scale = read._index[name]
        assert c == k
    # the supply set-point column is each draw's own supply (gauge, scaled)
    sup = read(obs, "supply_setpoint")
    assert sup == pytest.approx([c.supply_pressure_gauge_pa for c in conds], rel=1e-6)


def test_fraction_targets_divide_by_the_best_gain_and_clip(bench):
    R = np.array([[-5.0, -0.5, 0.0, -0.8], [-1.0, -0.99, -0.98, -1.0]])
    RC = np.array([-1.0, -1.0])
    y = bench.fraction_targets(R, RC)
    # row 0: best gain 1.0; -5 -> -4 clipped to -3
    assert y[0] == pytest.approx([-3.0, 0.5, 1.0, 0.2])
    # row 1: best gain 0.02 < MIN_GAIN: divided by 0.05
    assert y[1] == pytest.approx([0.0, 0.2, 0.4, 0.0])


def test_scores_repeat_and_do_not_depend_on_the_workers(bench):
    from agents.evaluation.suites import family_draws

    conds = family_draws(300_000, 6)
    a = bench.score_draws(conds, 7, bench.GRID, workers=1, desc="", chunk=3, progress=False)
    b = bench.score_draws(conds, 7, bench.GRID, workers=2, desc="", chunk=3, progress=False)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["R"].shape == (6, len(bench.GRID)) and np.isfinite(a["R"]).all()
    assert a["T"].shape[0] == 6 and np.isfinite(a["T"]).all()
    # cutting before the valve has even opened stalls: worse than never cutting
    assert (a["R"][:, 0] < a["RC"]).all()


def test_small_run_writes_the_figures_and_repeats_them(bench, tmp_path, monkeypatch):
    argv = ["--draws", "32", "--sizes", "16", "32", "--val", "16", "--held-out", "16",
            "--fit-seeds", "1", "--epochs", "2", "--transfer-episodes", "1", "--out",
            str(tmp_path), "--no-progress"]
    res = bench.main(argv)
    for name in ("return_curve.json", "return_curve.csv", "return_curve.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert len(list(tmp_path.glob("scores-*.npz"))) == 4  # train, validation, held-out, suite
    saved = json.loads((tmp_path / "return_curve.json").read_text())
    rows = saved["learning_curve"]
    assert {(r["input"], r["draws"]) for r in rows} == {
        (k, n) for k in ("observed", "truth") for n in (16, 32)}
    assert all(np.isfinite([r["validation"], r["held-out"]]).all() for r in rows)
    tr = res["transfer"]
    assert tr["episodes"] == 60 and len(tr["per_rig"]) == 15
    # the grid of cut-off times holds a cut within a few percent of the oracle's on the suite
    assert tr["grid_best"]["oracle_fraction"] > 0.95
    assert saved["config"]["seed"] == 300_000 and "git_commit" in saved["provenance"]
    # again, from the kept scores (scoring anew would fail): the same numbers
    def no_scoring(*a, **k):
        raise AssertionError("scored again instead of reusing the kept scores")

    monkeypatch.setattr(bench, "score_draws", no_scoring)
    again = bench.main(argv + ["--transfer-episodes", "0"])  # (the last one counts)
    assert again["learning_curve"] == res["learning_curve"]
    assert "transfer" not in again


def test_bad_sizes_are_refused(bench, capsys):
    with pytest.raises(SystemExit):
        bench.main(["--draws", "10", "--sizes", "20"])
    assert "--sizes" in capsys.readouterr().err
