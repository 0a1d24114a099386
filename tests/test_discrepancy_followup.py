"""The suggested experiment as runs to measure (``pneugym.discrepancy.followup``): what each
plan asks of the rig, checked on the plant, and the planned runs made on a simulated rig."""
from __future__ import annotations

import numpy as np
import pytest

from pneugym import thesis_rig
from pneugym.discrepancy import CANDIDATES
from pneugym.discrepancy.followup import (
    EARLY_FRACTION,
    HOLD_S,
    SLOW_LIMIT_S,
    RunPlan,
    simulate_plans,
    suggested_runs,
)
from pneugym.plant import Plant

RIGS = [thesis_rig(1.5), thesis_rig(2.5)]


def test_every_candidate_has_a_plan():
    plans = suggested_runs(list(CANDIDATES), RIGS)
    assert [p.name for p in plans] == ["hold", "slow_stroke", "fast_stroke", "early_cutoff_30"]
    assert all(p.why and p.t_end_s > 0 for p in plans)


def test_leak_and_heat_share_one_hold_at_the_highest_supply():
    plans = suggested_runs(["leakage", "heat_transfer"], RIGS)
    (hold,) = plans
    assert hold.cut == "arrival" and hold.t_end_s == HOLD_S
    assert hold.supply_pressure_gauge_pa == 2.5e5 and hold.load_mass_kg == RIGS[0].load_mass_kg
    assert hold.schedule() == [(0.0, 1)]
    assert hold.sentence().startswith("`hold`: 2.5 bar gauge, 10 kg, cut off on arrival, recorded for 6 s: ")
    # the report's markdown reads the plan back from report.json
    assert RunPlan(**hold.to_dict()) == hold
    import dataclasses

    assert dataclasses.replace(hold, supply_pressure_gauge_pa=2.45e5).sentence().startswith(
        "`hold`: 2.45 bar gauge")  # the plan a user follows: not rounded to 2.5


def _completes(rig, bar):
    x = Plant(rig.with_(supply_pressure_gauge_pa=bar * 1e5)).run(SLOW_LIMIT_S, record_dt=1e-2)["x"]
    return x[-1] >= 0.995 * rig.cylinder.stroke_m


def test_the_slow_stroke_is_the_lowest_supply_that_completes():
    (slow,) = suggested_runs(["stribeck_friction"], RIGS)
    bar = slow.supply_pressure_gauge_pa / 1e5
    assert slow.cut == "never" and 0.4 <= bar < 1.5
    assert _completes(RIGS[0], bar) and not _completes(RIGS[0], bar - 0.1)


def test_the_early_cutoff_is_placed_at_its_share_of_the_stroke():
    (early,) = suggested_runs(["dead_volume"], RIGS)
    rig = RIGS[1]
    assert early.cut == "at" and early.schedule() == [(0.0, 1), (early.cut_s, 0)]
    assert f"cut off at {early.cut_s:g} s" in early.sentence()
    # the command goes out a valve delay and a ramp before the piston passes the share
    tr = Plant(rig).run(3.0, record_dt=1e-3)
    t_pass = early.cut_s + rig.valve_delay_s + rig.valve.ramp_s
    assert np.interp(t_pass, tr["t"], tr["x"]) == pytest.approx(EARLY_FRACTION * rig.cylinder.stroke_m,
                                                              rel=0.02)


def test_unknown_effect_and_no_rigs_are_refused():
    with pytest.raises(ValueError, match="no run plan exposes 'valve_delay'"):
        suggested_runs(["valve_delay"], RIGS)
    with pytest.raises(ValueError, match="needs the rigs"):
        suggested_runs(["leakage"], [])


def test_planned_runs_on_a_simulated_rig_state_their_operating_point():
    truth = thesis_rig(2.5).with_(effects={"leak_drive_area_m2": 4e-7})
    plans = [suggested_runs(["leakage"], RIGS)[0],
             RunPlan("late", 1.5e5, 20.0, "at", 0.6, 1.5, "a test plan")]
    runs = simulate_plans(plans, truth, thesis_rig(2.5), seed=3)
    hold, late = runs
    assert [r.name for r in runs] == ["followup_hold", "followup_late"]
    assert hold.t[-1] == pytest.approx(HOLD_S) and hold.valve[-1] == 0 and hold.valve[0] == 1
    rig = late.rig()
    assert rig.supply_pressure_gauge_pa == 1.5e5 and rig.load_mass_kg == 20.0
    assert rig.effects.leak_drive_area_m2 == 0.0  # the JSON states the known rig, never the truth
    assert late.valve[late.t < 0.6].min() == 1 and late.valve[late.t >= 0.6].max() == 0
    # the leak drains the trapped air of the hold towards ambient
    after = hold.t > hold.t[np.argmax(hold.valve == 0)] + 0.5
    assert hold.p_drive[after][-200:].mean() < hold.p_drive[after][:200].mean() - 2e4
    # each plan its own noise stream, the same seed the same run
    again = simulate_plans(plans[:1], truth, thesis_rig(2.5), seed=3)[0]
    assert np.array_equal(again.p_drive, hold.p_drive)


def test_the_bench_follows_up_with_either_held_out_run(monkeypatch, load_bench):
    """``bench_discrepancy.py --follow-up --follow-up-holdout both``: the second round on all the
    runs by the workflow's rule, and again with the first round's held-out run kept where a
    planned stroke moved it (tiny fits: the plumbing, not the answers)."""
    bench = load_bench("bench_discrepancy")
    # whatever the first round says, follow up with a never-cut stroke (it moves the median)
    monkeypatch.setattr(bench.Discrepancy, "suggested_runs",
                        lambda self: suggested_runs(["sensor_lag"], self.rigs_))
    kw = {"candidates": ["sensor_lag"], "n_starts": 1, "n_probe": 2, "max_nfev": 4, "seed": 0, "n_jobs": 1}
    row = bench.run_case(("none", 7000, "mismatched", kw, True, "both"))
    first, kept = row["first_round"]["holdout"], row["kept_holdout"]
    assert row["runs"][-1] == "followup_fast_stroke" and row["follow_up"][0]["name"] == "fast_stroke"
    assert row["holdout"] != first and kept["moved"] and kept["holdout"] == first
    assert set(bench.ROUND_KEYS) <= set(kept)
    out = bench.summarise([{**row, **kept}])
    assert out["control_accuracy"] == float(kept["named"] == "none")
