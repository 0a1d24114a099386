"""Operating life (pneugym.operation, agents.adaptive): scenarios, the DuckDB record (one
transaction per block, resume), the references, the report and the adapting controllers."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("duckdb")

from agents.adaptive import (AdaptiveGasLaw, DemandTuner, make_controller,  # noqa: E402
                             measured_objective)
from pneugym.envs import Conditions  # noqa: E402
from pneugym.envs.cutoff import CutOffVectorEnv  # noqa: E402
from pneugym.operation import SCENARIOS, Scenario, scenario  # noqa: E402
from pneugym.operation.record import Record, export_runs  # noqa: E402
from pneugym.operation.report import (life, recovery, step_changes,  # noqa: E402
                                      summary, write_report)
from pneugym.operation.run import ENV_CONFIG, operate  # noqa: E402


# -- scenarios ---------------------------------------------------------------------------------
def test_knots_are_linear_held_and_stepped_per_drift_step():
    s = Scenario("t", drift={"friction_scale": [(0, 1.0), (100, 2.0)],
                             "load_mass_kg": [(0, 10.0), (49, 10.0), (50, 20.0)]},
                 resolution=10, friction_jitter=0.0)
    assert s.value("friction_scale", 0) == 1.0
    assert s.value("friction_scale", 55) == pytest.approx(1.5)  # its drift step starts at 50
    assert s.value("friction_scale", 59) == s.value("friction_scale", 50)
    assert s.value("friction_scale", 10_000) == 2.0  # held beyond the last knot
    assert s.value("load_mass_kg", 49) == 10.0 and s.value("load_mass_kg", 50) == 20.0
    assert step_changes(s.to_dict()) == [50]


def test_truth_is_seeded_and_hidden_effects_become_rig_changes():
    s = SCENARIOS["leak-onset"]
    a, b = s.truth(2700, seed=3), s.truth(2700, seed=3)
    assert a == b and a != s.truth(2700, seed=4)
    c = s.conditions(2700, seed=3)
    assert dict(c.rig_changes)["effects.leak_drive_area_m2"] == pytest.approx(4e-7)
    assert s.conditions(100, seed=3).rig_changes == ()
    assert c.position_noise_m > 0 and c.pressure_noise_pa > 0


@pytest.mark.parametrize("drift, match", [
    ({"frictoin_scale": 1.0}, "friction_scale"),
    ({"load_mass_kg": [(0, 10.0), (0, 20.0)]}, "strictly increasing"),
    ({"leak_drive_area_m2": 2e-3}, "outside"),
    ({"supply_pressure_gauge_pa": 2.5}, "outside"),  # bar given as Pa
    ({"load_mass_kg": "heavy"}, "knots"),
])
def test_bad_scenarios_are_refused_by_name(drift, match):
    with pytest.raises(ValueError, match=match):
        Scenario("bad", drift=drift)


@pytest.mark.parametrize("name", ["../escaped", "a/b", "", ".hidden", "x" * 65])
def test_scenario_names_that_would_leave_a_folder_are_refused(name):
    with pytest.raises(ValueError, match="Scenario name"):
        Scenario(name)
    assert Scenario("leak-onset@my_rig.v2").name == "leak-onset@my_rig.v2"


def test_unknown_scenario_names_the_nearest():
    with pytest.raises(ValueError, match="leak-onset"):
        scenario("leak-onsett")


# -- the record --------------------------------------------------------------------------------
def test_a_block_is_written_whole_or_not_at_all(tmp_path):
    with Record(tmp_path / "r.duckdb") as rec:
        rec.start_run("r", "healthy", 0, "c", 10, {"a": 1}, {}, "now")
        row = {k: [None] for k in ("hour", "controller_version", "reference", "explore",
                                   "supply_setpoint_pa", "cutoff_time_s", "completed",
                                   "stalled", "stick_slip_events", "stroke_time_s",
                                   "final_position_m", "energy_wasted_j",
                                   "energy_conventional_j", "free_air_nl", "objective",
                                   "saving_ratio", "decision_inputs")}
        tr = {k: np.zeros(3) for k in ("stroke", "t", "x", "p_drive", "p_exhaust", "valve")}
        rec.write_block("r", {**row, "stroke": [0]}, tr, 1, b"s1")
        import duckdb

        # stroke 0 again: the primary key refuses the block (that error, no other)
        with pytest.raises(duckdb.ConstraintException, match="(?i)primary key|duplicate"):
            rec.write_block("r", {k: v * 2 for k, v in row.items()} | {"stroke": [1, 0]}, tr,
                            2, b"s2")
        n = rec.con.execute("SELECT count(*) FROM strokes").fetchone()[0]
        m = rec.con.execute("SELECT count(*) FROM traces").fetchone()[0]
        ck = rec.con.execute("SELECT next_stroke, state FROM checkpoints").fetchone()
        assert (n, m, ck) == (1, 3, (1, b"s1"))
        with pytest.raises(ValueError, match="another configuration"):
            rec.start_run("r", "healthy", 0, "c", 10, {"a": 2}, {}, "now")


@pytest.fixture(scope="module")
def gaslaw_life(tmp_path_factory):
    """60 strokes of the load-change scenario (shifted to a step at stroke 30) under the
    adaptive Gas-Law rule, the oracle and the conventional controller."""
    db = tmp_path_factory.mktemp("ops") / "ops.duckdb"
    sc = Scenario("step", drift={"load_mass_kg": [(0, 10.0), (29, 10.0), (30, 20.0)]})
    ids = {c: operate(sc, c, strokes=60, db=db, seed=1, block=20, progress=False)
           for c in ("gaslaw-adaptive", "oracle", "conventional")}
    return db, sc, ids


def test_references_bound_the_controllers(gaslaw_life):
    db, _, ids = gaslaw_life
    with Record(db, read_only=True) as rec:
        oracle, conv = summary(rec, ids["oracle"]), summary(rec, ids["conventional"])
        ad = summary(rec, ids["gaslaw-adaptive"])
    assert oracle["oracle_fraction"] == pytest.approx(1.0, abs=1e-9)
    assert conv["oracle_fraction"] == pytest.approx(0.0, abs=1e-9)
    assert conv["air_fraction"] == pytest.approx(0.0, abs=1e-9)
    assert ad["strokes"] == 60 and ad["reference_strokes"] == 1  # stroke 0
    assert ad["oracle_fraction"] < 1.0
    assert oracle["oracle_fraction_regular"] == pytest.approx(1.0, abs=1e-9)
    assert oracle["oracle_fraction_last"] == pytest.approx(1.0, abs=1e-9)
    assert conv["oracle_fraction_last"] == pytest.approx(0.0, abs=1e-9)
    assert ad["oracle_fraction_regular"] > ad["oracle_fraction"]  # without the reference
    with Record(db, read_only=True) as rec:
        d = life(rec, ids["gaslaw-adaptive"])
    # the air is counted alike (to the end of each stroke's rest): a cut stroke draws less
    cut = ~d["reference"].astype(bool)
    assert (d["free_air_nl"][cut] < d["conventional_free_air_nl"][cut]).all()


def test_resume_after_an_interruption_gives_the_same_record(gaslaw_life, tmp_path, monkeypatch):
    db, sc, ids = gaslaw_life
    part = tmp_path / "part.duckdb"
    calls = {"n": 0}
    orig = AdaptiveGasLaw.update

    def interrupted(self, rec):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # during the second block, before it is written
        orig(self, rec)

    monkeypatch.setattr(AdaptiveGasLaw, "update", interrupted)
    with pytest.raises(KeyboardInterrupt):
        operate(sc, "gaslaw-adaptive", strokes=60, db=part, seed=1, block=20, progress=False)
    monkeypatch.setattr(AdaptiveGasLaw, "update", orig)
    with Record(part, read_only=True) as rec:
        assert rec.strokes(ids["gaslaw-adaptive"])["stroke"].tolist() == list(range(20))
    operate(sc, "gaslaw-adaptive", strokes=60, db=part, seed=1, block=20, progress=False)
    with Record(part, read_only=True) as a, Record(db, read_only=True) as b:
        ra, rb = a.strokes(ids["gaslaw-adaptive"]), b.strokes(ids["gaslaw-adaptive"])
        for k in rb:
            np.testing.assert_array_equal(ra[k], rb[k], err_msg=k)
        assert a.runs()[0]["status"] == "finished"


def test_adaptive_gaslaw_backs_off_after_a_stall_and_follows_the_better_side():
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    c = AdaptiveGasLaw(env)
    base = {"stroke": np.array([0, 1, 2, 3]), "reference": np.array([True, False, False, False]),
            "completed": np.array([True] * 4), "stick_slip_events": np.zeros(4, int),
            "stroke_time_s": np.array([1.0, 1.1, 1.3, 1.1]),
            "energy_wasted_j": np.array([400.0, 100.0, 80.0, 100.0])}
    c.update(base)
    assert c.conv == (1.0, 400.0)
    # stroke 2 (K up) was slower for little air: the down side wins
    j = measured_objective(base, 1.0, 400.0)
    assert j[2] < j[3]
    assert c.log_g == pytest.approx(-c.step)
    c.update({**base, "reference": np.zeros(4, bool), "completed": np.array([1, 1, 0, 1], bool)})
    assert c.log_g == pytest.approx(-c.step + c.backoff)
    # stick-slip on the K-down strokes only: the objective sends K up, by one step
    c.update({**base, "reference": np.zeros(4, bool),
              "stick_slip_events": np.array([0, 1, 0, 1])})
    assert c.log_g == pytest.approx(c.backoff)
    for _ in range(100):  # stalls for ever: the factor stops at 4
        c.update({**base, "reference": np.zeros(4, bool), "completed": np.zeros(4, bool)})
    assert math.exp(c.log_g) == pytest.approx(4.0)
    c2 = AdaptiveGasLaw(env)
    c2.restore(c.state(), None, "x")
    assert (c2.log_g, c2.conv, c2.version) == (c.log_g, c.conv, c.version)


def test_demand_tuner_moves_only_on_a_clear_difference_and_forgets_old_strokes():
    rng = np.random.default_rng(0)
    grid = np.linspace(0.0, 0.3, 7)
    t = DemandTuner(grid, window=250, bandwidth=0.05, z=2.0)
    assert t.choose(0.1) == 0.1  # no strokes yet
    # regular strokes at 0.1 stick half the time (-0.5 each); explored ones above 0.2 never
    k = np.arange(250)
    explore = k % 5 == 0
    d = np.where(explore, rng.uniform(0.0, 0.3, k.size), 0.1)
    stick = (d < 0.17) & (rng.random(k.size) < 0.5)
    j = -0.3 - 0.2 * d - 0.5 * stick + rng.normal(0.0, 0.01, k.size)
    t.add(k, d, j)
    best = t.choose(0.1)
    assert 0.2 <= best + 1e-9 and best in grid  # a demand whose kernel sees no stick-slip
    m, se, n = t.estimate(0.1)
    assert m == pytest.approx(-0.32 - 0.25, abs=0.08) and n > 150 and 0 < se < 0.05
    # the same spread of outcomes with no difference between demands: it stays
    flat = DemandTuner(grid)
    flat.add(k, d, -0.4 + rng.normal(0.0, 0.05, k.size))
    assert flat.choose(0.1) == 0.1
    # strokes older than the window are forgotten; non-finite outcomes are skipped
    t.add(np.arange(250, 500), np.full(250, 0.1), np.full(250, -0.3))
    assert t.stroke.min() == 250 and t.choose(0.1) == 0.1
    t.add(np.array([500]), np.array([0.1]), np.array([np.nan]))
    assert t.stroke.max() == 499
    u = DemandTuner(grid)
    u.restore(json.loads(json.dumps(t.state())))
    assert u.estimate(0.1) == t.estimate(0.1)
    with pytest.raises(ValueError, match="grid"):
        DemandTuner([0.1])
    with pytest.raises(ValueError, match="bandwidth"):
        DemandTuner(grid, bandwidth=0.0)


def test_parquet_export_writes_the_records_tables_only(tmp_path):
    """A table of the user's own in the file (any name) is left out, not pasted into SQL."""
    from pneugym.operation.record import EXPORTED

    with Record(tmp_path / "r.duckdb") as rec:
        rec.con.execute('CREATE TABLE "per minute" (a INTEGER)')
        rec.con.execute('CREATE TABLE "x\' TO \'/tmp/evil" (a INTEGER)')
        files = rec.export_parquet(tmp_path / "pq")
    assert {f.name for f in files} == {f"{t}.parquet" for t in EXPORTED} - {"monitor.parquet"}
    assert sorted(p.name for p in (tmp_path / "pq").iterdir()) == sorted(f.name for f in files)


def test_exports_parquet_and_measured_runs(gaslaw_life, tmp_path):
    import duckdb

    from pneugym.data import read_run

    db, _, ids = gaslaw_life
    with Record(db, read_only=True) as rec:
        files = rec.export_parquet(tmp_path / "pq")
        n = rec.con.execute("SELECT count(*) FROM traces").fetchone()[0]
        runs = export_runs(rec, ids["gaslaw-adaptive"], tmp_path / "runs", 0, 2)
        tr = rec.trace(ids["gaslaw-adaptive"], 1)
    assert {f.name for f in files} >= {"strokes.parquet", "traces.parquet", "truth.parquet"}
    pq = duckdb.connect().execute(f"SELECT count(*) FROM '{tmp_path / 'pq' / 'traces.parquet'}'")
    assert pq.fetchone()[0] == n
    assert len(runs) == 3
    r0, r1 = read_run(runs[0]), read_run(runs[1])
    assert r0.description == "end_stroke_cutoff" and r1.description == "early_cutoff"
    np.testing.assert_allclose(r1.p_drive, tr["p_drive"])
    assert r1.valve[0] == 1 and r1.valve[-1] == 0 and r1.meta["sample_rate_hz"] == \
        pytest.approx(200.0)


def test_exported_runs_state_the_valve_delay_at_their_supply(tmp_path):
    """The commissioned valve switches faster at a higher supply (thesis Fig. 3.6); the format
    states the delay itself, so each exported stroke states it at that stroke's supply (stated
    at the commissioning supply, a 3 bar stroke read as a valve 8 % slower than it is)."""
    from pneugym.data import read_run
    from pneugym.params import RigParams

    db = tmp_path / "s.duckdb"
    rid = operate(Scenario("three-bar", drift={"supply_pressure_gauge_pa": 3e5}), "gaslaw",
                  strokes=2, db=db, block=2, progress=False)
    with Record(db, read_only=True) as rec:
        run = read_run(export_runs(rec, rid, tmp_path / "runs", 0, 0)[0])
    stated = run.meta["rig"]["valve_delay_s"]
    assert run.meta["supply_pressure_gauge_pa"] == 3e5
    assert stated == pytest.approx(RigParams(supply_pressure_gauge_pa=3e5).valve_delay_s)
    assert stated < 0.95 * RigParams().valve_delay_s  # 0.170 s at 3 bar against 0.185 s


def test_report_tables_plots_and_recovery(gaslaw_life, tmp_path):
    db, _, ids = gaslaw_life
    res = write_report(db, tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "| gaslaw-adaptive | 60 |" in md and (tmp_path / "rep" / "step_seed1.png").is_file()
    s = res["runs"][ids["oracle"]]
    assert set(s["recovery"]) == {"30"}
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["runs"]
    assert s["per_hour"][0]["strokes"] == 60  # 600 strokes per hour


def test_report_names_rollbacks(gaslaw_life, tmp_path):
    """A rollback and a withdrawal in the record's models (written here by hand) are listed in
    the report."""
    import shutil

    db, _, ids = gaslaw_life
    copy = tmp_path / "ops.duckdb"
    shutil.copy(db, copy)
    with Record(copy) as rec:
        rec.con.execute("INSERT INTO models VALUES (?, 'v3', 40, 'rollback', true, NULL, NULL, "
                        "'{}', NULL)", [ids["gaslaw-adaptive"]])
        rec.con.execute("INSERT INTO models VALUES (?, 'v4', 50, 'withdrawn', true, NULL, NULL, "
                        "'{}', NULL)", [ids["gaslaw-adaptive"]])
    res = write_report(copy, tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Models taken back:" in md
    assert ("- gaslaw-adaptive: rolled back to the shipped model (a fine-tuned one had stopped "
            "cutting), at stroke 40") in md
    assert ("- gaslaw-adaptive: withdrew a fine-tuned model that stalled on probation, at "
            "stroke 50") in md
    kinds = [m["kind"] for m in res["runs"][ids["gaslaw-adaptive"]]["models"]]
    assert kinds == ["rollback", "withdrawn"]
    write_report(db, tmp_path / "plain")  # the record without them
    assert "taken back" not in (tmp_path / "plain" / "report.md").read_text()


def test_recovery_counts_strokes_until_the_rolling_fraction_returns():
    k = np.arange(400)
    frac_ok = k < 100
    d = {"stroke": k, "conventional_objective": np.full(400, -1.0),
         "oracle_objective": np.full(400, 0.0),
         "objective": np.where(frac_ok | (k >= 250), 0.0, -0.5)}
    # after the step at 100 every stroke scores half the gap until 249: back to 0.95 once the
    # last 100 strokes hold at most 10 of the bad ones, at stroke 339, the 240th after the step
    assert recovery(d, [100], window=100) == {100: 240}
    assert recovery({**d, "objective": np.where(k < 100, 0.0, -0.5)}, [100]) == {100: None}


def test_operate_refuses_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="strokes"):
        operate("healthy", "gaslaw", strokes=0, db=tmp_path / "a.duckdb", progress=False)
    with pytest.raises(ValueError, match="block"):
        operate("healthy", "gaslaw", strokes=5, block=0, db=tmp_path / "a.duckdb",
                progress=False)
    for seed in (-1, 1.5, True):
        with pytest.raises(ValueError, match="seed"):
            operate("healthy", "gaslaw", strokes=5, seed=seed, db=tmp_path / "b.duckdb",
                    progress=False)
    assert not (tmp_path / "b.duckdb").exists()  # refused before the record is opened
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    with pytest.raises(ValueError, match="not an ESAC model"):
        make_controller("esac-adaptive=agents/gaslaw_k.json", env)


def test_cli_runs_reports_and_exports(tmp_path, capsys):
    from pneugym.cli import main

    db = tmp_path / "c.duckdb"
    assert main(["operate", "--scenario", "healthy", "--policy", "endstroke", "--strokes", "10",
                 "--db", str(db), "--block", "5", "--out", str(tmp_path / "rep"),
                 "--no-progress"]) == 0
    assert main(["operate", "--db", str(db), "--export-runs", str(tmp_path / "runs"), "--run",
                 "healthy/seed0/endstroke", "--first", "3", "--last", "4"]) == 0
    out = capsys.readouterr().out
    assert "healthy/seed0/endstroke: oracle fraction" in out and "wrote 2 measured runs" in out
    with pytest.raises(SystemExit) as exc:
        main(["operate", "--policy", "gaslaw"])
    assert exc.value.code == 2 and "--policy needs --scenario" in capsys.readouterr().err


def test_adaptive_esac_fine_tunes_from_its_record_and_resumes(tmp_path):
    """A small ESAC model, fine-tuned every 40 strokes from the record: each candidate is
    recorded with the scores that decided; the deployed one is the running model from then on,
    and a resumed run rebuilds it from the record. Its time demand moves to where the measured
    outcome is better."""
    from agents import esac

    data = esac.generate_rollouts(384, seed=5, history=2, preset="thesis-2.5bar", batch=384,
                                  progress=False)
    stroke = CutOffVectorEnv(num_envs=1).rig.cylinder.stroke_m
    x, y, mask, ep = esac.samples(data, stroke, delay_input=False)
    net, _ = esac.fit(x, y, mask, hidden=(32,), epochs=30, groups=ep, progress=False)
    layout = CutOffVectorEnv(num_envs=1, history=2).observation_layout()
    model = tmp_path / "esac.pt"
    # a rough model: a permissive rule makes it cut (the mechanics are tested, not its skill)
    esac.save(model, net, {"layout": layout, "n_in": x.shape[1], "hidden": [32],
                           "delay_input": False, "lookahead_s": [],
                           "rule": {"margin": 0.6, "max_time_increase": 1.0, "max_stick": 1.0}})
    import agents.adaptive as A

    sc = Scenario("drift", drift={"friction_scale": [(0, 1.0), (120, 1.3)]})
    orig = A.AdaptiveESAC.__init__

    def small(self, spec, env, seed=0, **kw):
        orig(self, spec, env, seed, adapt_every=40, window=80, epochs=3, explore=0.3,
             explore_range=(0.6, 1.4), reference_every=100)

    A.AdaptiveESAC.__init__ = small
    try:
        db = tmp_path / "e.duckdb"
        rid = operate(sc, f"esac-adaptive={model}", strokes=120, db=db, block=20,
                      progress=False)
        with Record(db, read_only=True) as rec:
            m = rec.frame("SELECT version, stroke, deployed, score_new, score_running "
                          "FROM models ORDER BY stroke")
            s = rec.strokes(rid)
        assert m["stroke"].tolist() == [40, 80]
        assert (m["deployed"] == (m["score_new"] < 0.98 * m["score_running"])).all()
        assert s["explore"].any() and s["reference"][0] and s["reference"][100]
        for k, v, dep in zip(m["stroke"], m["version"], m["deployed"]):
            if dep:  # the running model, then its time demand
                assert {c.split()[0] for c in s["controller_version"][s["stroke"] >= k]} <= (
                    {v} | set(m["version"][m["stroke"] > k]))
        assert all(c.split()[1].startswith("demand=") for c in s["controller_version"])
        # resume a copy cut after stroke 99 (its checkpoint holds the deployed version)
        part = tmp_path / "p.duckdb"
        operate(sc, f"esac-adaptive={model}", strokes=100, db=part, block=20, progress=False)
        operate(sc, f"esac-adaptive={model}", strokes=120, db=part, block=20, progress=False)
        with Record(part, read_only=True) as rec:
            s2 = rec.strokes(rid)
        np.testing.assert_array_equal(s2["cutoff_time_s"], s["cutoff_time_s"])
        assert math.isfinite(float(np.nanmean(s["objective"])))
        # the time demand follows the measured outcome: strokes that ran a demand below 1.15
        # stick, the others do not; the reference strokes give the conventional figures
        c = make_controller(f"esac-adaptive={model}", CutOffVectorEnv(num_envs=1, **ENV_CONFIG))
        assert c.demand == 1.0 and c.version.endswith("demand=1.000")
        told = [Conditions(supply_pressure_gauge_pa=250_000.0, load_mass_kg=10.0)] * 25
        for k0 in range(0, 250, 25):
            ks = np.arange(k0, k0 + 25)
            _, flags = c.plan(ks, told)
            ref = flags["reference"]
            c.update({"stroke": ks, "reference": ref, "completed": np.ones(25, bool),
                      "stick_slip_events": ((c._planned < 1.15) & ~ref).astype(np.int64),
                      "stroke_time_s": np.where(ref, 1.0, 1.05),
                      "energy_wasted_j": np.where(ref, 400.0, 100.0)})
        assert c.demand >= 1.2 and c.version.endswith(f"demand={c.demand:.3f}")
        c2 = make_controller(f"esac-adaptive={model}", CutOffVectorEnv(num_envs=1, **ENV_CONFIG))
        c2.restore(c.state(), None, "x")
        assert (c2.demand, c2.conv, c2.version) == (c.demand, c.conv, c.version)
    finally:
        A.AdaptiveESAC.__init__ = orig


def test_monitor_names_a_leak_with_its_cost_and_nothing_on_a_healthy_rig(tmp_path):
    from pneugym.operation.monitor import alarm, monitor

    db = tmp_path / "m.duckdb"
    fast = {"candidates": ["leakage", "stribeck_friction"], "n_starts": 1, "n_probe": 4,
            "max_nfev": 20}
    verdict = {}
    for leak in (4e-7, 0.0):
        sc = Scenario(f"leak{leak:g}", drift={"leak_drive_area_m2": leak})
        rid = operate(sc, "gaslaw", strokes=12, db=db, block=12, progress=False)
        pts = monitor(str(db), rid, every=12, window=4, progress=False, **fast)
        assert [p["stroke"] for p in pts] == [12]
        verdict[leak] = pts[0], alarm(pts)
    hit, text = verdict[4e-7]
    assert hit["named"] == "leakage"
    assert hit["effect"]["leak_drive_area_m2"] == pytest.approx(4e-7, rel=0.2)
    assert hit["air_cost"]["extra_per_stroke_conventional_nl"] > 0
    leak = hit["effect"]["leak_drive_area_m2"]
    assert text.startswith(f"leakage: leak_drive_area_m2 {leak:.3g}") and "strokes 0-11" in text
    assert verdict[0.0][0]["named"] == "none" and verdict[0.0][1].startswith("no change")
    res = write_report(db, tmp_path / "rep")
    assert any(s.get("monitor") for s in res["runs"].values())
    assert "Condition monitoring" in (tmp_path / "rep" / "report.md").read_text()
    with pytest.raises(ValueError, match="no run"):
        monitor(str(db), "nope/seed0/gaslaw", progress=False)


def test_monitor_names_a_slower_valve_when_asked_to_test_it(tmp_path):
    """Wear slows the valve; with ``valve_delay`` among the candidates the monitor names it
    (the fitted factor on the commissioned delay), and records what it costs in air."""
    from pneugym.operation.monitor import alarm, monitor

    db = tmp_path / "v.duckdb"
    rid = operate(Scenario("slow-valve", drift={"valve_delay_scale": 1.4}), "gaslaw", strokes=12,
                  db=db, block=12, progress=False)
    pts = monitor(str(db), rid, every=12, window=4, progress=False,
                  candidates=["dead_volume", "valve_delay"], n_starts=1, n_probe=4, max_nfev=20)
    hit = pts[0]
    assert hit["named"] == "valve_delay", hit["decision"]
    assert hit["effect"]["valve.delay_scale"] == pytest.approx(1.4, rel=0.05)
    assert set(hit["air_cost"]) >= {"conventional_nl", "extra_per_stroke_conventional_nl"}
    assert alarm(pts).startswith(f"valve_delay: valve.delay_scale {hit['effect']['valve.delay_scale']:.3g},")


def test_a_second_pass_names_the_leak_behind_the_slower_valve(tmp_path):
    """Wear slows the valve and opens a leak: the first pass names the valve; the second, with
    the valve written into the model and each stroke's own friction, names the leak too."""
    from pneugym.operation.monitor import alarm, monitor

    db = tmp_path / "w.duckdb"
    rid = operate(Scenario("worn", drift={"valve_delay_scale": 1.4, "leak_drive_area_m2": 4e-7}),
                  "gaslaw", strokes=12, db=db, block=12, progress=False)
    pts = monitor(str(db), rid, every=12, window=4, progress=False,
                  candidates=["leakage", "valve_delay"], n_starts=1, n_probe=4, max_nfev=20)
    hit = pts[0]
    assert hit["named"] == "valve_delay+leakage", hit["decision"]
    assert hit["effect"]["valve.delay_scale"] == pytest.approx(1.4, rel=0.05)
    assert hit["effect"]["leak_drive_area_m2"] == pytest.approx(4e-7, rel=0.25)
    assert " | then: leakage" in hit["decision"]
    assert hit["air_cost"]["extra_per_stroke_conventional_nl"] > 0
    assert alarm(pts).startswith(
        f"valve_delay+leakage: valve.delay_scale {hit['effect']['valve.delay_scale']:.3g}, "
        f"leak_drive_area_m2 {hit['effect']['leak_drive_area_m2']:.3g}")


def test_a_named_change_is_written_into_the_runs_for_the_next_pass():
    from pneugym.data import simulate_run
    from pneugym.operation.monitor import apply_named
    from pneugym.params import RigParams

    run = simulate_run(RigParams(), t_end=0.5, sample_rate_hz=100.0, name="r")
    (slow,), base = apply_named([run], {"valve.delay_scale": 1.3})
    assert base is None and slow.rig().valve_delay_s == pytest.approx(1.3 * run.rig().valve_delay_s)
    assert run.meta["rig"]["valve_delay_s"] == pytest.approx(RigParams().valve_delay_s)  # a copy
    (same,), base = apply_named([run], {"leak_drive_area_m2": 2e-7, "dead_volume_m3": 1e-5})
    assert same is run and same.rig(base).effects.leak_drive_area_m2 == 2e-7
    assert same.rig(base).effects.dead_volume_m3 == 1e-5
    with pytest.raises(ValueError, match="cylinder.bore_m"):
        apply_named([run], {"cylinder.bore_m": 0.05})


def test_monitor_tests_the_five_effects_and_a_slower_valve_by_default(tmp_path, monkeypatch):
    import pneugym.discrepancy as D
    from pneugym.operation.monitor import MONITORED, monitor

    seen = {}

    class Stop(Exception):
        pass

    def capture(**kw):
        seen.update(kw)
        raise Stop

    import pneugym.discrepancy.fit as F

    fitted = []
    db = tmp_path / "d.duckdb"
    rid = operate("healthy", "gaslaw", strokes=10, db=db, block=10, progress=False)
    monkeypatch.setattr(D, "Discrepancy", capture)
    monkeypatch.setattr(F, "own_friction", lambda runs, base=None: fitted.append(len(runs)) or runs)
    with pytest.raises(Stop):
        monitor(str(db), rid, every=10, window=3, progress=False)
    assert list(seen["candidates"]) == list(MONITORED)
    # the workflow's five effects, in its order, and the slower valve (written out in the
    # monitor, which does not import the workflow until a checkpoint runs)
    assert MONITORED == (*D.CANDIDATES, D.candidates.VALVE_DELAY.name)
    assert seen["calibrate"] == "basic" and seen["discrepancy_term"] is None
    assert seen["calibrate_also"] == ()  # nothing named yet
    assert fitted == [3]  # each stroke's own friction, before the first pass
    with pytest.raises(Stop):  # the extended calibration frees the delay: the five are left
        monitor(str(db), rid, every=10, window=3, progress=False, calibrate="extended")
    assert list(seen["candidates"]) == list(D.CANDIDATES)
    assert "valve_delay" not in seen["candidates"]


def test_cli_checks_its_outputs_before_the_work(tmp_path, monkeypatch):
    import pneugym.operation.run as R
    from pneugym.cli import main

    def no_work(*a, **k):
        raise AssertionError("the work started before the outputs were checked")

    monkeypatch.setattr(R, "operate", no_work)
    with pytest.raises(SystemExit) as exc:  # a change the monitor does not know, refused first
        main(["operate", "--monitor", "x/seed0/gaslaw", "--monitor-candidates", "leakage,valve"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main(["operate", "--monitor", "x/seed0/gaslaw", "--monitor-passes", "0"])
    assert exc.value.code == 2
    (tmp_path / "file").write_text("")
    for argv in (["--out", str(tmp_path / "file")], ["--db", str(tmp_path)]):
        with pytest.raises(SystemExit) as exc:
            main(["operate", "--scenario", "healthy", "--policy", "gaslaw", *argv])
        assert exc.value.code == 2


def test_a_finished_run_extends_to_more_strokes(tmp_path):
    db = tmp_path / "x.duckdb"
    rid = operate("healthy", "endstroke", strokes=30, db=db, block=20, progress=False)
    assert operate("healthy", "endstroke", strokes=30, db=db, block=20, progress=False) == rid
    operate("healthy", "endstroke", strokes=50, db=db, block=20, progress=False)
    with Record(db, read_only=True) as rec:
        assert rec.strokes(rid)["stroke"].tolist() == list(range(50))
        assert rec.runs()[0]["strokes"] == 50
    from pneugym.cli import main

    assert main(["operate", "--db", str(db), "--remove", rid]) == 0
    with Record(db, read_only=True) as rec:
        assert rec.runs() == [] and rec.strokes(rid)["stroke"].size == 0
        assert rec.con.execute("SELECT count(*) FROM truth").fetchone()[0] == 50  # kept


def test_air_cost_of_any_named_effect():
    from pneugym.operation.monitor import air_cost

    leak = air_cost({"leak_drive_area_m2": 4e-7}, 0.9, 2.5e5, 10.0)
    dead = air_cost({"dead_volume_m3": 2e-5}, 0.9, 2.5e5, 10.0)  # not a family rig field
    assert leak["extra_per_stroke_conventional_nl"] > 0
    assert dead["extra_per_stroke_conventional_nl"] > 0  # more volume to fill
    assert leak["conventional_nl"] == dead["conventional_nl"]
    slow = air_cost({"valve.delay_scale": 1.5}, 0.9, 2.5e5, 10.0)  # a rig field, not an effect
    assert slow["conventional_nl"] == leak["conventional_nl"]
    assert slow["cut_with_effect_nl"] < slow["cut_nl"]  # the supply opens later before the cut
    # the fitted factor is on the rig's stated delay: no change on a rig that states it slower
    from pneugym.params import RigParams

    slow_rig = RigParams().with_(valve={"delay_scale": 1.3})
    same = air_cost({"valve.delay_scale": 1.0}, 0.9, 2.5e5, 10.0, rig=slow_rig)
    assert same["extra_per_stroke_conventional_nl"] == 0.0
    assert same["extra_per_stroke_cut_nl"] == 0.0
    never = air_cost({"leak_drive_area_m2": 4e-7}, None, 2.5e5, 10.0)  # no stroke was cut
    assert never["cut_s"] is None and never["cut_nl"] == never["conventional_nl"]
    json.dumps(never, allow_nan=False)


def test_alarm_reads_an_ambiguous_answer_as_a_change():
    from pneugym.operation.monitor import alarm

    pts = [{"stroke": 250, "first_stroke": 0, "named": "none", "effect": {}, "air_cost": {},
            "decision": "none"},
           {"stroke": 500, "first_stroke": 250, "named": "ambiguous", "effect": {},
            "air_cost": {}, "decision": "ambiguous: leakage and dead_volume explain it alike"}]
    assert alarm(pts[:1]).startswith("no change: 1 checkpoints up to stroke 250")
    assert alarm(pts) == ("a change it cannot name (ambiguous: leakage and dead_volume explain "
                          "it alike), first significant in strokes 250-499")


def test_a_block_tells_policies_only_what_is_known_and_records_the_latched_cut():
    from agents.oracle import TimedCutPolicy
    from pneugym.operation.run import run_block

    class Blip(TimedCutPolicy):  # cuts for one period only; the environment latches it
        def begin_episodes(self, conditions):
            self.told = list(conditions)

        def act(self, obs):
            t = self.read(obs, "time")
            return ((t > 0.3) & (t < 0.304)).astype(np.int64)

    env = CutOffVectorEnv(num_envs=1, autoreset=False, **ENV_CONFIG)
    truth = Conditions(friction_scale=1.3, valve_delay_scale=1.2,
                       rig_changes=(("effects.leak_drive_area_m2", 2e-7),))
    pol = Blip(env.observation_layout())
    fig, tr, _ = run_block(env, pol, [truth], np.zeros(1, bool), 0, False, dwell_s=0.1)
    told = pol.told[0]
    assert (told.friction_scale, told.valve_delay_scale, told.rig_changes) == (1.0, 1.0, ())
    assert (told.load_mass_kg, told.supply_pressure_gauge_pa) == (10.0, 250_000.0)
    assert np.all(np.diff(tr["valve"]) <= 0) and tr["valve"][-1] == 0  # never reopened
    assert fig["cutoff_time_s"][0] == pytest.approx(0.3, abs=0.006)


def test_one_scenario_name_holds_one_set_of_knots(tmp_path):
    db = tmp_path / "s.duckdb"
    operate(Scenario("mine", drift={"load_mass_kg": 12.0}), "endstroke", strokes=5, db=db,
            progress=False)
    with pytest.raises(ValueError, match="other knots"):
        operate(Scenario("mine", drift={"load_mass_kg": 20.0}), "gaslaw", strokes=5, db=db,
                progress=False)


def test_a_run_without_strokes_is_reported_not_crashed(tmp_path):
    db = tmp_path / "e.duckdb"
    with Record(db) as rec:
        rec.start_run("healthy/seed0/x", "healthy", 0, "x", 10,
                      {"scenario": SCENARIOS["healthy"].to_dict()}, {}, "now")
    res = write_report(db, tmp_path / "rep")
    assert res["runs"]["healthy/seed0/x"]["strokes"] == 0
    assert "| x | 0 | - | - | - |" in (tmp_path / "rep" / "report.md").read_text()


def test_cli_hands_the_monitor_its_options(tmp_path, monkeypatch):
    import pneugym.operation.monitor as M
    from pneugym.cli import main

    got = {}
    monkeypatch.setattr(M, "monitor", lambda db, rid, **kw: got.update(kw) or [])
    argv = ["operate", "--db", str(tmp_path / "x.duckdb"), "--monitor", "a/seed0/gaslaw",
            "--no-progress"]
    assert main(argv) == 0 and "passes" not in got and "stroke_friction" not in got
    assert main(argv + ["--monitor-passes", "1", "--monitor-friction", "shared"]) == 0
    assert got["passes"] == 1 and got["stroke_friction"] is False


def test_cli_hands_the_adaptive_controllers_the_reference_cut(tmp_path, monkeypatch, capsys):
    """``--reference-cut`` reaches the adaptive controllers only (a frozen one takes no
    options); without an adaptive controller it is refused by name."""
    import pneugym.operation.run as R
    from agents.adaptive import is_adaptive
    from pneugym.cli import main

    got = {}
    monkeypatch.setattr(R, "operate", lambda sc, spec, **kw: got.update({spec: kw["options"]})
                        or f"{sc}/seed0/{spec}")
    argv = ["operate", "--db", str(tmp_path / "x.duckdb"), "--scenario", "healthy",
            "--policy", "gaslaw", "--policy", "gaslaw-adaptive", "--policy",
            "esac-adaptive=runs/esac", "--no-progress"]
    assert main(argv + ["--reference-cut", "never"]) == 0
    assert got == {"gaslaw": None, "gaslaw-adaptive": {"reference_cut": "never"},
                   "esac-adaptive=runs/esac": {"reference_cut": "never"}}
    assert main(argv) == 0 and set(got.values()) == {None}  # the controllers' default
    with pytest.raises(SystemExit):
        main(argv[:7] + ["--reference-cut", "arrival"])
    assert "--reference-cut is an option of the adaptive controllers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(argv + ["--reference-cut", "sometimes"])
    assert [is_adaptive(s) for s in ("gaslaw", "esac=runs/esac", "gaslaw-adaptive",
                                     "esac-adaptive=runs/esac")] == [False, False, True, True]
    from agents.adaptive import REFERENCE_CUTS
    from pneugym.operation.__main__ import build_parser

    (action,) = [a for a in build_parser()._actions if a.dest == "reference_cut"]
    assert tuple(action.choices) == REFERENCE_CUTS  # the command line's twin of the controllers'


def test_the_yardstick_benchmark_scores_runs_against_three_oracles(gaslaw_life, tmp_path, load_bench):
    """benchmarks/bench_operation_oracle.py on a short record: the search oracle's own run
    scores 1 against it and at most 1 against every step's best, the conventional one 0 against
    all; every step's best is never below the search's, the slip-robust cut's return never
    above every step's best."""
    db, _, ids = gaslaw_life
    bench = load_bench("bench_operation_oracle")
    res = bench.main(["--db", str(db), "--out", str(tmp_path), "--no-progress"])
    assert (tmp_path / "oracles.json").exists() and (tmp_path / "oracles.png").exists()
    o, c = res["runs"][ids["oracle"]], res["runs"][ids["conventional"]]
    assert o["search"]["life"] == pytest.approx(1.0, abs=1e-9)
    assert o["every step"]["life"] <= 1.0 + 1e-9
    for y in bench.YARDSTICKS:
        assert c[y]["life"] == pytest.approx(0.0, abs=1e-9)
    (sc,) = res["scenarios"].values()
    assert sc["drift_steps"] == 6 and sc["mean_gain_every_step_over_search"] >= 0.0
    assert sc["mean_loss_slip_robust_against_every_step"] >= 0.0
    with pytest.raises(SystemExit):
        bench.main(["--db", str(db), "--slip", "0"])


class _Record:
    """The part of :class:`Record` the rollback reads: strokes 0-29, a reference at 0, cuts on
    the strokes in ``cuts``."""

    def __init__(self, cuts):
        self.cuts = set(cuts)

    def strokes(self, run_id, first=0, last=None, columns=()):
        k = np.arange(first, min(29, last) + 1)
        return {"stroke": k, "reference": k == 0,
                "cutoff_time_s": np.array([0.5 if i in self.cuts else None for i in k],
                                          dtype=object)}


@pytest.fixture(scope="module")
def tiny_esac(tmp_path_factory):
    """A small ESAC model of the thesis rig (its file, network and training samples)."""
    from agents import esac

    data = esac.generate_rollouts(96, seed=5, history=2, preset="thesis-2.5bar", batch=96,
                                  progress=False)
    stroke = CutOffVectorEnv(num_envs=1).rig.cylinder.stroke_m
    x, y, mask, ep = esac.samples(data, stroke, delay_input=False)
    net, _ = esac.fit(x, y, mask, hidden=(8,), epochs=2, groups=ep, progress=False)
    model = tmp_path_factory.mktemp("esac") / "esac.pt"
    esac.save(model, net, {"layout": CutOffVectorEnv(num_envs=1, history=2).observation_layout(),
                           "n_in": x.shape[1], "hidden": [8], "delay_input": False,
                           "lookahead_s": [], "rule": {"margin": 0.6}})
    return model, net, (x, y, mask, ep)


def test_adaptive_esac_rolls_back_a_model_that_stopped_cutting(tiny_esac):
    """A fine-tuned model that has not cut on its last ``rollback_after`` strokes gives way to
    the shipped one (recorded as a rollback, with its network); one that cut lately, the
    shipped model itself and ``rollback_after=0`` never do."""
    import torch

    from agents import esac
    from agents.adaptive import AdaptiveESAC, _net_from_bytes

    model, net, (x, y, mask, ep) = tiny_esac
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)

    def fine_tuned(**kw):
        c = AdaptiveESAC(f"esac-adaptive={model}", env, **kw)
        c.policy.predictor.net = esac.fit(x, y, mask, hidden=(8,), epochs=1, seed=9,
                                          groups=ep, progress=False, init=net)[0]
        c.generation, c.model_version, c.shipped_runs = 2, f"{c.name}-v2", False
        return c

    def same(a, b):
        return all(torch.equal(p, q) for p, q in zip(a.state_dict().values(),
                                                     b.state_dict().values()))

    c = fine_tuned(rollback_after=10)
    assert not same(c.policy.predictor.net, net)
    assert c.adapt(_Record(range(1, 25)), "x", 30) == []  # a cut among the last 10
    (row,) = c.adapt(_Record(range(1, 15)), "x", 30)
    assert row["kind"] == "rollback" and row["deployed"] and row["version"] == f"{c.name}-v3"
    assert same(c.policy.predictor.net, net) and same(_net_from_bytes(row["blob"]), net)
    assert c.model_version == f"{c.name}-v3" and json.loads(c.state())["deployed_at"] == 30
    assert c.adapt(_Record(()), "x", 35) == []  # (not yet 10 strokes of the shipped model)
    assert c.adapt(_Record(()), "x", 45) == []  # (the shipped model is not rolled back)
    c2 = AdaptiveESAC(f"esac-adaptive={model}", env, rollback_after=10)
    c2.restore(c.state(), None, "x")  # (no record needed: the running model is the shipped)
    assert c2.shipped_runs and c2.adapt(_Record(()), "x", 60) == []
    shipped = AdaptiveESAC(f"esac-adaptive={model}", env, rollback_after=10)
    assert shipped.adapt(_Record(()), "x", 30) == []
    assert fine_tuned(rollback_after=0).adapt(_Record(()), "x", 30) == []
    with pytest.raises(ValueError, match="rollback_after"):
        AdaptiveESAC(f"esac-adaptive={model}", env, rollback_after=-1)
    assert make_controller(f"esac-adaptive={model}", env, rollback_after=0).rollback_after == 0
    assert make_controller(f"esac-adaptive={model}", env).config()["rollback_after"] == 50
    with pytest.raises(ValueError, match="are for esac-adaptive"):
        make_controller("gaslaw", env, rollback_after=0)



class _Stalls:
    """The part of :class:`Record` the probation reads: strokes 0-99, references at multiples
    of 100 (stroke 0), exploring strokes in ``explore``, stalls in ``stalls``."""

    def __init__(self, stalls, explore=()):
        self.stalls, self.explore = set(stalls), set(explore)

    def strokes(self, run_id, first=0, last=None, columns=()):
        k = np.arange(first, min(99, last) + 1)
        return {"stroke": k, "reference": k % 100 == 0,
                "explore": np.isin(k, list(self.explore)),
                "stalled": np.isin(k, list(self.stalls))}


def test_a_fine_tuned_model_that_stalls_on_probation_is_withdrawn(tiny_esac):
    """A freshly deployed model whose first regular strokes stall (3 of up to ``probation``;
    exploring and reference strokes aside) gives way to the model it replaced, recorded as
    ``withdrawn`` with that model's network; fewer stalls, or stalls after the probation,
    leave it running; a checkpoint taken on probation restores the model to go back to."""
    import torch

    from agents import esac
    from agents.adaptive import AdaptiveESAC, _net_from_bytes

    model, net, (x, y, mask, ep) = tiny_esac
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    fresh = esac.fit(x, y, mask, hidden=(8,), epochs=1, seed=9, groups=ep, progress=False,
                     init=net)[0]

    def on_probation(**kw):
        """A controller that deployed ``fresh`` at stroke 1 in place of the shipped model."""
        c = AdaptiveESAC(f"esac-adaptive={model}", env, **kw)
        c.previous = (c.model_version, c.policy.predictor.net, True)
        c.policy.predictor.net = fresh
        c.generation, c.model_version, c.shipped_runs, c.deployed_at = 1, f"{c.name}-v1", False, 1
        return c

    def same(a, b):
        return all(torch.equal(p, q) for p, q in zip(a.state_dict().values(),
                                                     b.state_dict().values()))

    c = on_probation(probation=10)
    assert c.adapt(_Stalls({3, 5}), "x", 8) == []  # two stalls in 7 strokes: on probation
    assert c.previous is not None and same(c.policy.predictor.net, fresh)
    (row,) = c.adapt(_Stalls({3, 5, 7}), "x", 12)
    assert row["kind"] == "withdrawn" and row["deployed"] and row["version"] == f"{c.name}-v2"
    assert row["detail"]["to"] == f"{c.name}-v0" and row["detail"]["withdrawn"] == f"{c.name}-v1"
    assert same(c.policy.predictor.net, net) and same(_net_from_bytes(row["blob"]), net)
    assert c.shipped_runs and c.previous is None and c.deployed_at == 12
    assert c.adapt(_Stalls(range(12, 40)), "x", 40) == []  # (the shipped model is on no probation)
    # exploring strokes do not count; stalls after the probation's 10 regular strokes neither
    c = on_probation(probation=10)
    assert c.adapt(_Stalls({3, 5, 7}, explore={3, 5, 7}), "x", 12) == []
    c = on_probation(probation=10)
    assert c.adapt(_Stalls({20, 21, 22}), "x", 25) == [] and c.previous is None
    assert on_probation(probation=0).adapt(_Stalls({3, 5, 7}), "x", 12) == []
    # a checkpoint on probation: the model to go back to comes back with it
    c = on_probation(probation=10)
    c2 = AdaptiveESAC(f"esac-adaptive={model}", env, probation=10)

    class _Models(_Stalls):
        class con:
            @staticmethod
            def execute(sql, params):
                from agents.adaptive import _net_bytes

                class _Row:
                    def fetchone(self):
                        return (_net_bytes(fresh, c.policy),)
                return _Row()

    c2.restore(c.state(), _Models(()), "x")
    assert c2.previous[0] == f"{c.name}-v0" and c2.previous[2]
    assert same(c2.previous[1], net) and same(c2.policy.predictor.net, fresh)
    (row,) = c2.adapt(_Stalls({3, 5, 7}), "x", 12)
    assert row["kind"] == "withdrawn" and same(c2.policy.predictor.net, net)
    with pytest.raises(ValueError, match="probation"):
        AdaptiveESAC(f"esac-adaptive={model}", env, probation=10, probation_stalls=0)
    assert make_controller(f"esac-adaptive={model}", env).config()["probation"] == 50


def test_reference_strokes_every_n_and_at_each_change_of_the_told_operating_point(tiny_esac):
    """Without ``on_change`` every n-th stroke (as before); with it, also the first stroke told
    another supply set-point (> 0.1 bar) or payload (> 5 %), n then counting from it; the
    schedule survives a checkpoint, and bad settings are refused by name."""
    from agents.adaptive import AdaptiveESAC, ReferenceSchedule

    ks = np.arange(0, 1200)
    np.testing.assert_array_equal(np.flatnonzero(ReferenceSchedule(100).flags(ks)),
                                  np.arange(0, 1200, 100))
    assert not ReferenceSchedule(0).flags(ks).any()

    def told(k):
        load = 10.0 if k < 300 else (10.4 if k < 600 else 25.0)  # +4 %: no reference; then +150 %
        supply = 250_000.0 if k < 900 else 250_000.0 - 2e4  # -0.2 bar
        return Conditions(supply_pressure_gauge_pa=supply, load_mass_kg=load)

    sched = ReferenceSchedule(500, on_change=True)
    got = np.concatenate([sched.flags(ks[i:i + 25], [told(k) for k in ks[i:i + 25]])
                          for i in range(0, 1200, 25)])
    assert np.flatnonzero(got).tolist() == [0, 500, 600, 900]
    again = ReferenceSchedule(500, on_change=True)
    again.restore(json.loads(json.dumps(sched.state())))
    assert again.flags(np.arange(1200, 1500), [told(1000)] * 300).tolist() == (
        sched.flags(np.arange(1200, 1500), [told(1000)] * 300).tolist())
    with pytest.raises(ValueError, match="told conditions"):
        ReferenceSchedule(500, on_change=True).flags(ks)
    with pytest.raises(ValueError, match="reference_every"):
        ReferenceSchedule(-1)
    with pytest.raises(ValueError, match="reference_every"):
        ReferenceSchedule(0, on_change=True)
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    c = AdaptiveESAC(f"esac-adaptive={tiny_esac[0]}", env, reference_every=500,
                     reference_on_change=True)
    _, flags = c.plan(np.arange(0, 25), [told(0)] * 25)
    assert flags["reference"].tolist() == [True] + [False] * 24
    assert c.config()["reference_every"] == 500 and c.config()["reference_on_change"]
    shipped = make_controller(f"esac-adaptive={tiny_esac[0]}", env).references
    assert (shipped.every, shipped.on_change) == (100, False)  # the default: every 100th
    assert make_controller("gaslaw-adaptive", env).references.every == 100
    c2 = AdaptiveESAC(f"esac-adaptive={tiny_esac[0]}", env, reference_every=500,
                      reference_on_change=True)
    c2.restore(c.state(), None, "x")
    assert c2.references.last == 0 and c2.references.point == (250_000.0, 10.0)


def test_a_life_takes_a_reference_stroke_where_the_told_payload_steps(tiny_esac, tmp_path):
    """The operating loop tells the controller each stroke's payload: with
    ``reference_on_change`` the first stroke at the new load is a reference stroke (cut off on
    arrival), and the record says so."""
    sc = Scenario("step", drift={"load_mass_kg": [(0, 10.0), (29, 10.0), (30, 20.0)]})
    rid = operate(sc, f"esac-adaptive={tiny_esac[0]}", strokes=60, db=tmp_path / "s.duckdb",
                  block=20, progress=False,
                  options={"reference_every": 500, "reference_on_change": True})
    with Record(tmp_path / "s.duckdb", read_only=True) as rec:
        s = rec.strokes(rid)
    assert np.flatnonzero(s["reference"]).tolist() == [0, 30]
    assert (s["cutoff_time_s"][[0, 30]].astype(float) > 0.9).all()  # cut off on arrival


def test_a_reference_stroke_cut_off_on_arrival_measures_the_conventional_figures(tmp_path):
    """With ``reference_cut="arrival"`` (the default) a reference stroke is cut off on arrival:
    the same stroke time as the uncut one (``"never"``, the earlier default), less air wasted,
    and the controller counts its measured objective against the conventional energy the record
    keeps (``energy_conventional_j``, what the uncut stroke wastes). Bad values are refused by
    name; ``"never"`` leaves the run's configuration as it was before the option (an earlier
    record resumes with it)."""
    from agents.adaptive import AdaptiveGasLaw, ReferenceSchedule, latest_reference

    sc = Scenario("flat", drift={"load_mass_kg": [(0, 10.0)]})
    s = {}
    for cut in ("never", "arrival"):
        rid = operate(sc, "gaslaw-adaptive", strokes=2, db=tmp_path / f"{cut}.duckdb", seed=1,
                      block=2, progress=False, options={"reference_cut": cut})
        with Record(tmp_path / f"{cut}.duckdb", read_only=True) as rec:
            s[cut] = rec.strokes(rid)
            cfg = rec.run(rid)["config"]["controller"]
        assert cfg.get("reference_cut") == (None if cut == "never" else cut)
    uncut, cut = s["never"], s["arrival"]
    assert uncut["reference"][0] and cut["reference"][0]
    assert np.isnan(float(uncut["cutoff_time_s"][0])) and cut["cutoff_time_s"][0] > 0.9
    assert cut["stroke_time_s"][0] == pytest.approx(uncut["stroke_time_s"][0], abs=1e-9)
    assert uncut["energy_wasted_j"][0] == pytest.approx(uncut["energy_conventional_j"][0])
    assert cut["energy_conventional_j"][0] == pytest.approx(uncut["energy_wasted_j"][0])
    assert cut["energy_wasted_j"][0] < 0.7 * uncut["energy_wasted_j"][0]  # the saved air
    assert cut["objective"][0] > uncut["objective"][0]
    assert latest_reference(cut, (np.nan, np.nan)) == pytest.approx(
        latest_reference(uncut, (np.nan, np.nan)))
    with pytest.raises(ValueError, match="reference_cut"):
        ReferenceSchedule(100, cut="sometimes")
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    with pytest.raises(ValueError, match="not gaslaw-adaptive's"):
        make_controller("gaslaw-adaptive", env, explore=0.2)
    assert AdaptiveGasLaw(env).references.cut == "arrival"  # the default


def test_the_explored_demands_grow_when_the_tuned_one_reaches_their_top(tiny_esac):
    """With ``explore_max``, the tuned demand at the range's top step widens the range by its
    first width (the tuner's grid keeping its 0.05 step) up to ``explore_max``; below it, or by
    default, nothing grows; a checkpoint carries the grown range."""
    from agents.adaptive import AdaptiveESAC

    model = tiny_esac[0]
    env = CutOffVectorEnv(num_envs=1, **ENV_CONFIG)
    c = AdaptiveESAC(f"esac-adaptive={model}", env, explore_max=1.2)
    c.demand = 0.2
    c._grow()
    assert c.explore_range == (0.0, 0.3) and c.tuner.grid.size == 7
    c.demand = 0.25
    c._grow()
    assert c.explore_range == (0.0, 0.6)
    np.testing.assert_allclose(c.tuner.grid, np.arange(13) * 0.05, atol=1e-12)
    _, flags = c.plan(np.arange(1, 2001), [Conditions(load_mass_kg=10.0)] * 2000)
    drawn = c._planned[flags["explore"]]
    assert drawn.max() > 0.5 and drawn.min() >= 0.0 and (c._planned[~flags["explore"]] == 0.25).all()
    for _ in range(5):
        c.demand = c.explore_range[1]
        c._grow()
    assert c.explore_range == (0.0, 1.2) and c.tuner.grid.size == 25  # capped at explore_max
    c2 = AdaptiveESAC(f"esac-adaptive={model}", env, explore_max=1.2)
    c2.restore(c.state(), None, "x")
    assert c2.explore_range == (0.0, 1.2) and c2.tuner.grid.size == 25
    fixed = AdaptiveESAC(f"esac-adaptive={model}", env)
    assert fixed.config()["explore_max"] == 0.3
    fixed.demand = 0.3
    fixed._grow()
    assert fixed.explore_range == (0.0, 0.3)
    with pytest.raises(ValueError, match="explore_max"):
        AdaptiveESAC(f"esac-adaptive={model}", env, explore_max=0.2)

# -- the user's rig ----------------------------------------------------------------------------
def _my_rig(tmp_path: Path) -> Path:
    """A rig file of another cylinder set-up: a smaller dead volume, 4 bar and 15 kg."""
    from pneugym.params import RigParams

    rig = RigParams().with_(supply_pressure_gauge_pa=4e5, load_mass_kg=15.0,
                            cylinder={"dead_volume_m3": 1.2e-4})
    return rig.save(tmp_path / "my_rig.yaml")


def test_a_scenario_on_a_rig_moves_supply_and_payload_with_the_rig():
    from pneugym.params import RigParams

    rig = RigParams(supply_pressure_gauge_pa=4e5, load_mass_kg=15.0)
    s = SCENARIOS["shift"].on_rig(rig, "my_rig")
    assert s.name == "shift@my_rig" and "supply x1.6, payload x1.5" in s.description
    assert s.value("supply_pressure_gauge_pa", 0) == pytest.approx(4.8e5)  # 3 bar x 1.6
    assert s.value("supply_pressure_gauge_pa", 2500) == pytest.approx(3.2e5)  # 2 bar x 1.6
    assert s.value("friction_scale", 0) == SCENARIOS["shift"].value("friction_scale", 0)
    lc = SCENARIOS["load-change"].on_rig(rig, "my_rig")
    assert [lc.value("load_mass_kg", k) for k in (0, 1500, 3500)] == pytest.approx([15, 37.5, 7.5])
    assert SCENARIOS["wear"].on_rig(RigParams(), "thesis").drift == SCENARIOS["wear"].drift
    with pytest.raises(ValueError, match="letters, digits"):
        SCENARIOS["wear"].on_rig(rig, "my rig/2")
    with pytest.raises(ValueError, match=r"'shift' on rig 'big' \(supply 9 bar.*outside"):
        SCENARIOS["shift"].on_rig(RigParams(supply_pressure_gauge_pa=9e5), "big")


def test_a_life_on_the_users_rig_runs_that_rig_and_records_it(tmp_path):
    """``operate(rig=FILE)``: the plant is the file's rig at its supply and payload, the run is
    named after it, the record keeps it (exported runs state it) and another rig under the same
    name is refused."""
    from pneugym.data import read_run
    from pneugym.envs import conventional_figures
    from pneugym.rigfile import load

    path = _my_rig(tmp_path)
    rig = load(path)
    db = tmp_path / "r.duckdb"
    sc = Scenario("flat", friction_jitter=0.0)
    rid = operate(sc, "gaslaw", strokes=4, db=db, block=4, progress=False, rig=path)
    assert rid == "flat@my_rig/seed0/gaslaw"
    with Record(db, read_only=True) as rec:
        run = rec.run(rid)
        truth = rec.truth("flat@my_rig", 0, 0, 3)
        exported = read_run(export_runs(rec, rid, tmp_path / "runs", 0, 0)[0])
    assert run["config"]["env"]["rig"] == json.loads(json.dumps(rig.to_dict()))
    assert truth["supply_pressure_gauge_pa"].tolist() == [4e5] * 4
    assert truth["load_mass_kg"].tolist() == [15.0] * 4
    clean = sc.on_rig(rig, "my_rig").conditions(0, 0)
    t_conv, _ = conventional_figures(
        type(clean)(supply_pressure_gauge_pa=4e5, load_mass_kg=15.0).rig(rig), clean.dip)
    t_thesis, _ = conventional_figures(
        type(clean)(supply_pressure_gauge_pa=4e5, load_mass_kg=15.0).rig(
            rig.with_(cylinder={"dead_volume_m3": 2.44e-4})), clean.dip)
    # the environment's stroke and the plant's alone agree to 1e-5; the thesis's dead volume
    # would move it by far more: the file's rig ran
    assert truth["conventional_time_s"][0] == pytest.approx(t_conv, rel=1e-4)
    assert abs(t_conv - t_thesis) > 100 * 1e-4 * t_conv, (t_conv, t_thesis)
    assert exported.meta["rig"]["dead_volume_m3"] == pytest.approx(1.2e-4)
    assert exported.meta["supply_pressure_gauge_pa"] == 4e5
    other = rig.with_(cylinder={"dead_volume_m3": 2e-4})
    with pytest.raises(ValueError, match="other knots, rest or environment"):
        operate(sc, "endstroke", strokes=4, db=db, block=4, progress=False, rig=other,
                rig_name="my_rig")
    with pytest.raises(ValueError, match="names no rig"):
        operate(sc, "gaslaw", strokes=4, db=db, progress=False, rig_name="my_rig")


def test_the_monitor_reads_a_run_over_its_own_rig(tmp_path, monkeypatch):
    """On a run of the user's rig the workflow is handed that rig as the commissioned one, and
    a named change's air cost is the plant's on that rig."""
    from pneugym.operation import monitor as M
    from pneugym.rigfile import load

    path = _my_rig(tmp_path)
    db = tmp_path / "m.duckdb"
    rid = operate(Scenario("flat"), "gaslaw", strokes=12, db=db, block=12, progress=False,
                  rig=path)
    seen = {}

    def fake(runs, candidates, passes, stroke_friction, rig, **workflow):
        seen["rig"] = rig
        return {"named": "leakage", "decision": "leakage", "effect":
                {"leak_drive_area_m2": 3e-7}}

    monkeypatch.setattr(M, "examine", fake)
    pts = M.monitor(str(db), rid, every=12, window=4, progress=False)
    assert seen["rig"] == load(path)
    cost = pts[0]["air_cost"]
    mine = M.air_cost({"leak_drive_area_m2": 3e-7}, cost["cut_s"], 4e5, 15.0, rig=load(path))
    thesis = M.air_cost({"leak_drive_area_m2": 3e-7}, cost["cut_s"], 4e5, 15.0)
    assert cost["conventional_nl"] == pytest.approx(mine["conventional_nl"], rel=1e-9)
    assert abs(cost["conventional_nl"] - thesis["conventional_nl"]) > 1e-3


def test_cli_operates_the_users_rig(tmp_path, capsys):
    from pneugym.cli import main

    path = _my_rig(tmp_path)
    db = tmp_path / "c.duckdb"
    assert main(["operate", "--rig", str(path), "--rig-name", "cell-7", "--scenario", "healthy",
                 "--policy", "endstroke", "--strokes", "3", "--block", "3", "--db", str(db),
                 "--no-progress"]) == 0
    assert "recorded healthy@cell-7/seed0/endstroke" in capsys.readouterr().out
    for argv, msg in ((["--rig", str(path)], "go with --scenario"),
                      (["--scenario", "healthy", "--policy", "gaslaw", "--rig-name", "x"],
                       "give --rig FILE"),
                      (["--scenario", "healthy", "--policy", "gaslaw", "--rig",
                        str(tmp_path / "none.yaml")], "file not found")):
        with pytest.raises(SystemExit):
            main(["operate", *argv, "--db", str(db)])
        assert msg in capsys.readouterr().err


def test_adaptive_esac_fine_tunes_an_ensemble_member_by_member(tiny_esac, tmp_path, monkeypatch):
    """An ensemble model (``fit.ensemble``) adapts as a single one does: each candidate is an
    ensemble of as many members, recorded whole, and the running model stays one."""
    from agents import esac
    import agents.adaptive as A
    from agents.adaptive import _net_from_bytes

    _, _, (x, y, mask, ep) = tiny_esac
    ens, _ = esac.fit(x, y, mask, hidden=(8,), epochs=2, groups=ep, progress=False, members=2)
    model = tmp_path / "ens.pt"
    esac.save(model, ens, {"layout": CutOffVectorEnv(num_envs=1, history=2).observation_layout(),
                           "n_in": x.shape[1], "hidden": [8], "delay_input": False,
                           "lookahead_s": [], "rule": {"margin": 0.6, "max_time_increase": 1.0}})
    orig = A.AdaptiveESAC.__init__

    def small(self, spec, env, seed=0, **kw):
        orig(self, spec, env, seed, adapt_every=20, window=40, epochs=2, explore=0.3,
             explore_range=(0.6, 1.4))

    monkeypatch.setattr(A.AdaptiveESAC, "__init__", small)
    db = tmp_path / "e.duckdb"
    rid = operate(Scenario("steady"), f"esac-adaptive={model}", strokes=60, db=db, block=20,
                  progress=False)
    with Record(db, read_only=True) as rec:
        rows = rec.con.execute("SELECT blob FROM models WHERE run_id = ? AND kind = 'esac'",
                               [rid]).fetchall()
    assert rows  # (the first tuning with enough strokes)
    for (blob,) in rows:
        net = _net_from_bytes(blob)
        assert esac.is_ensemble(net) and len(net.members) == 2
