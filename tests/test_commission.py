"""Commissioning (pneugym.commission) and the model-predictive cut-off on it (agents.mpc_rig):
the fit recovers a rig the rig file misstates, the model's files and uncertainty, the plan
against the oracle, the evaluation's per-rig commissioning, refusals."""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agents.base import run_first_episodes
from agents.evaluation.commissioning import DATASHEET_FIELDS, rig_file, rig_groups
from agents.evaluation.specs import evaluation_env_config
from agents.mpc_rig import RigModelPolicy, completing
from agents.oracle import OraclePolicy
from pneugym.commission import (ORIFICE_MODELS, Commissioned, commission,
                                commissioning_protocol, delay_guess, fitted_params, main,
                                report_markdown)
from pneugym.data import write_run
from pneugym.discrepancy.fit import Problem
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv
from pneugym.params import RigParams

KNOWN = RigParams()
#: the truth: what the rig file (the thesis rig) misstates
TRUTH = KNOWN.with_(friction={"static_n": 430.0, "coulomb_n": 100.0},
                    valve={"exhaust_area_m2": 6e-5, "delay_s": 0.25},
                    effects={"leak_drive_area_m2": 2e-7})


@pytest.fixture(scope="module")
def runs():
    return commissioning_protocol(TRUTH, KNOWN, seed=3)


@pytest.fixture(scope="module")
def model(runs, tmp_path_factory) -> Commissioned:
    """The model ``pneugym commission`` fits and writes (one start, no extras: about 20 s)."""
    folder = tmp_path_factory.mktemp("measured")
    for r in runs:
        write_run(r, folder / r.name)
    out = tmp_path_factory.mktemp("commissioned")
    assert main([str(folder), "--out", str(out), "--starts", "1", "--no-extras",
                 "--max-nfev", "25", "--line-models", "fd"]) == 0
    for f in ("commissioning.json", "rig.json", "report.md", "fit.png"):
        assert (out / f).is_file()
    m = Commissioned.load(out)
    m.folder = out
    return m


def test_the_protocol_and_the_delay_guess(runs):
    assert [r.name for r in runs] == ["conventional", "end_stroke_cutoff"]
    assert runs[0].valve.min() == 1.0 and runs[1].valve[-1] == 0.0  # never cut / cut and held
    stated = runs[1].rig()  # what the JSON states: the rig file, not the truth
    assert stated.friction == KNOWN.friction and stated.valve_delay_s == KNOWN.valve_delay_s
    assert 0.22 <= delay_guess(runs[0]) <= 0.25  # the pressure rise, 10 ms before it shows


def test_the_fit_recovers_what_the_rig_file_misstates(model):
    v = dict(zip([p.path for p in model.params], model.values))
    assert v["valve.delay_s"] == pytest.approx(0.25, abs=0.005)
    assert v["valve.exhaust_area_m2"] * KNOWN.valve.exhaust_area_m2 == pytest.approx(6e-5, rel=0.05)
    assert v["friction.static_n"] == pytest.approx(430.0, rel=0.05)
    assert v["friction.coulomb_n"] == pytest.approx(100.0, rel=0.1)
    assert v["effects.leak_drive_area_m2"] == pytest.approx(2e-7, rel=0.1)
    assert model.misfit < 1.5  # the strokes reproduced to about the noise
    assert model.rig.valve.delay_s == pytest.approx(v["valve.delay_s"])
    assert RigParams.load(model.folder / "rig.json") == model.rig  # a rig file
    assert "valve.delay_s" in (model.folder / "report.md").read_text()


def test_the_model_round_trips_and_draws_plausible_rigs(model, tmp_path):
    again = Commissioned.load(model.save(tmp_path))
    assert np.array_equal(again.values, model.values) and again.rig == model.rig
    assert np.array_equal(again.cov_u, model.cov_u)
    rigs = model.members(5, seed=1)
    assert rigs[0] == model.rig and len({r.friction.static_n for r in rigs}) == 5
    se = model.std()["friction.static_n"]
    assert all(abs(r.friction.static_n - model.rig.friction.static_n) < 6 * se + 1e-9
               for r in rigs)
    assert model.members(5, seed=1) == rigs  # seeded

    def dev(rs):
        return np.mean([abs(r.friction.static_n - model.rig.friction.static_n) for r in rs[1:]])

    assert dev(model.members(5, seed=1, spread=2.0)) > 1.5 * dev(rigs)  # twice the deviations
    with pytest.raises(ValueError, match="spread"):
        model.members(5, spread=-1.0)


def test_the_report_gives_values_not_factors(model):
    """A parameter fitted as a factor on the stated value is reported in its unit."""
    row = next(ln for ln in report_markdown(model).splitlines()
               if ln.startswith("| valve.exhaust_area_m2 |"))
    stated, fitted = (float(x) for x in row.split("|")[2:4])
    assert stated == pytest.approx(KNOWN.valve.exhaust_area_m2, rel=1e-3)
    assert fitted == pytest.approx(6e-5, rel=0.05)


def test_the_report_flags_a_fit_far_above_the_noise(model):
    assert "exceeds" not in report_markdown(model)
    bad = replace(model, ssr=50.0 * model.n)  # a misfit of 50
    assert "Misfit SSR/N = 50.00" in report_markdown(bad)
    assert "**The misfit exceeds 9**" in report_markdown(bad)


def test_mpc_rig_plans_near_the_oracle_on_the_true_rig(model):
    env = CutOffVectorEnv(num_envs=2, autoreset=False, rig=TRUTH, observe_rig=True)
    conds = [Conditions(supply_pressure_gauge_pa=b * 1e5, load_mass_kg=10.0) for b in (2.0, 3.0)]
    pol = RigModelPolicy.for_env(env, model=model, members=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = run_first_episodes(env, pol, conds, 1)["objective"]
        orc = OraclePolicy.for_env(env)
        best = np.array([j for _, j in orc.plan_many(conds)])
        run = run_first_episodes(CutOffVectorEnv(num_envs=2, autoreset=False, rig=TRUTH,
                                                 observe_rig=True),
                                 OraclePolicy.for_env(env), conds, 1)  # the oracle, run
    assert np.allclose(run["objective"], best, atol=1e-9)  # its plans are its returns
    assert set(pol._plans) == {(2e5, 10.0), (3e5, 10.0)}  # one plan per operating point
    assert (got >= best - 0.1 * np.abs(best)).all()  # within 10 % of the oracle's return


def test_mpc_rig_prices_stick_slip_and_moves_its_cut_as_told(model):
    """``stick_weight`` (``stall_weight``) prices a plausible rig's stick-slip (a stroke not
    completed) at that many times ``w_stick`` (``w_stall``) in the plan: its returns are the
    environment's less the extra price of each cut's events (what bench_mpc_plan.py's
    ``--stick-weights`` and ``--stall-weights`` score from one run); ``shift_periods`` cuts
    later."""
    env = CutOffVectorEnv(num_envs=1, autoreset=False, rig=TRUTH, observe_rig=True, w_stick=0.4)
    one = RigModelPolicy.for_env(env, model=model, members=1)
    three = RigModelPolicy.for_env(env, model=model, members=1, stick_weight=3.0,
                                   stall_weight=5.0)
    assert three.planner.env_config["w_stick"] == pytest.approx(1.2)
    assert three.planner.env_config["w_stall"] == pytest.approx(10.0)
    c = {0: Conditions(supply_pressure_gauge_pa=2e5, load_mass_kg=25.0)}
    cuts = {0: [k * 0.02 for k in range(5, 40)]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fig = one.planner.score_figures(c, cuts, ("objective", "stick_slip_events", "completed"))[0]
        priced = three.planner.score_cuts(c, cuts)[0]
    assert any(n > 0 for _, n, _ in fig.values())  # some cuts stick: the price shows
    assert not all(done for _, _, done in fig.values())  # and some do not complete
    for t, (j, n, done) in fig.items():
        assert priced[t] == pytest.approx(j - 2.0 * 0.4 * n - 4.0 * 2.0 * (1 - done), abs=1e-9)
    later = RigModelPolicy.for_env(env, model=model, members=1, shift_periods=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0, t2 = (pol.plan([(2e5, 25.0)])[(2e5, 25.0)] for pol in (one, later))
    assert math.isfinite(t0) and t2 == pytest.approx(t0 + 2 * 0.005)  # two periods later
    with pytest.raises(ValueError, match="stick_weight"):
        RigModelPolicy.for_env(env, stick_weight=-1.0)
    with pytest.raises(ValueError, match="stall_weight"):
        RigModelPolicy.for_env(env, stall_weight=math.inf)
    with pytest.raises(ValueError, match="shift_periods"):
        RigModelPolicy.for_env(env, shift_periods=-1)


def test_mpc_rig_takes_only_cuts_its_plausible_rigs_complete(model, monkeypatch):
    """``min_completion``, a chance constraint: the plan takes the best cut (the rule's window
    over every tried cut) among those at least that share of its plausible rigs complete.
    Planner figures stubbed: the return peaks at a 0.3 s cut, plausible rig j completes a
    stroke cut from 0.4 + 0.1 j s on (never cutting, always)."""
    env = CutOffVectorEnv(num_envs=1, autoreset=False, rig=TRUTH, observe_rig=True)

    def figures(conds, cands, names):
        assert tuple(names) == ("objective", "completed")
        return {key: {t: (-abs(t - 0.3) if math.isfinite(t) else -5.0,
                          float(t >= 0.4 + 0.1 * key[1] - 1e-9)) for t in ts}
                for key, ts in cands.items()}

    cuts = {}
    for q in (0.0, 0.5, 1.0):
        pol = RigModelPolicy.for_env(env, model=model, members=2, min_completion=q)
        monkeypatch.setattr(pol.planner, "score_figures", figures)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert len(pol.members_at(2e5, 25.0)[0]) == 2  # both plausible rigs plan
            cuts[q] = pol.plan([(2e5, 25.0)])[(2e5, 25.0)]
    assert cuts == pytest.approx({0.0: 0.3, 0.5: 0.4, 1.0: 0.5})
    assert completing({0.1: 0.0, 0.2: 0.5, math.inf: 1.0}, 0.5) == [0.2, math.inf]
    assert completing({0.1: 0.0, 0.2: 0.25}, 0.5) == [0.2]  # none reaches it: the most
    with pytest.raises(ValueError, match="min_completion"):
        RigModelPolicy.for_env(env, min_completion=1.5)


def test_mpc_rig_decides_as_in_the_environment(model):
    """The deployable controller around mpc-rig, fed what the sensors read under noise, builds
    the same observations and gives the same commands as the policy in the environment."""
    from pneugym.deploy.check import check_equivalence

    conds = [Conditions(supply_pressure_gauge_pa=b * 1e5, load_mass_kg=m, position_noise_m=3e-5,
                        pressure_noise_pa=400.0) for b, m in ((2.0, 10.0), (4.0, 25.0))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = check_equivalence(lambda env: RigModelPolicy.for_env(env, model=model, members=2),
                                conds, seed=4)
    assert res["decisions"] > 100 * res["episodes"]
    assert res["observations_differing"] == 0 and res["commands_differing"] == 0, res["first"]


def test_refusals(runs, model, tmp_path):
    with pytest.raises(ValueError, match="no runs"):
        commission([])
    with pytest.raises(ValueError, match="starts"):
        commission(runs, starts=0)
    other = commissioning_protocol(TRUTH, KNOWN.with_(line={"length_m": 2.0}), seed=1)[:1]
    with pytest.raises(ValueError, match="another rig"):
        commission([runs[0], *other])
    (tmp_path / "commissioning.json").write_text(json.dumps({"format": "nope"}))
    with pytest.raises(ValueError, match="not a pneugym-commissioning/1"):
        Commissioned.load(tmp_path)
    bad = model.to_dict()
    bad["values"] = bad["values"][:-1]
    (tmp_path / "commissioning.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="one per parameter"):
        Commissioned.load(tmp_path)
    for key, v, match in (("ssr", "nan", "ssr"), ("ssr", -1.0, "ssr"), ("n", True, "n = True"),
                          ("kappa", float("inf"), "kappa"), ("runs", "abc", "runs"),
                          ("refitted", "false", "refitted")):
        with pytest.raises(ValueError, match=f"where: {match}"):
            Commissioned.from_dict({**model.to_dict(), key: v}, "where")
    bad = model.to_dict()
    bad["params"][0]["path"] = "valve.nonexistent"  # planned on no member at all: refused
    with pytest.raises(ValueError, match="where: .*nonexistent"):
        Commissioned.from_dict(bad, "where")
    with pytest.raises(FileNotFoundError, match="pneugym commission"):
        Commissioned.load(tmp_path / "missing")
    env = CutOffVectorEnv(num_envs=1, observe_rig=True)
    pol = RigModelPolicy.for_env(env)
    obs, _ = env.reset(seed=0)
    with pytest.raises(RuntimeError, match="no rig model"):
        pol.act(obs)
    with pytest.raises(ValueError, match="observe_rig"):
        RigModelPolicy.for_env(CutOffVectorEnv(num_envs=1))
    with pytest.raises(ValueError, match="members"):
        RigModelPolicy.for_env(env, members=0)
    with pytest.raises(ValueError, match="spread"):
        RigModelPolicy.for_env(env, spread=math.nan)
    with pytest.raises(ValueError, match="rule"):
        RigModelPolicy.for_env(env, rule="best")
    from agents.registry import load_policy

    with pytest.raises(ValueError, match="no overrides"):
        load_policy(model.folder, env, margin=0.1)
    assert isinstance(load_policy(model.folder, env), RigModelPolicy)
    from agents.registry import RigMismatchWarning
    from pneugym.presets import cylinder_rig

    other = CutOffVectorEnv(num_envs=1, observe_rig=True, rig=cylinder_rig(63, 400.0))
    with pytest.warns(RigMismatchWarning, match="commissioned on another rig"):
        load_policy(model.folder, other)
    assert main([str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2


def test_the_fit_chooses_the_supply_line_model_the_strokes_show():
    truth = KNOWN.with_(line={"model": "lumped"})  # the rig file (FD) cannot say
    runs = commissioning_protocol(truth, KNOWN, seed=4)
    m = commission(runs, starts=1, max_nfev=2, extras=False)
    assert m.stated.line.model == "lumped" and m.rig.line.model == "lumped"
    assert commission(runs, starts=1, max_nfev=2, extras=False,
                      line_models=None).rig.line.model == "fd"  # the stated one only
    with pytest.raises(ValueError, match="line model"):
        commission(runs, line_models=("tube",))


def test_the_fit_chooses_the_orifice_law_the_strokes_show():
    """At 1.5 bar the flows are mostly subsonic, where the thesis's law and ISO 6358 part: a
    valve with the critical ratio b = 0.3 of many real ones. (With b = 0.528 the two laws
    differ too little for two strokes: longer fits reach the noise with either, and which law
    the shortest fit picks followed the machine's BLAS kernels.)"""
    known = KNOWN.with_(supply_pressure_gauge_pa=1.5e5)
    runs = commissioning_protocol(known.with_(valve={"flow_model": "iso6358", "iso_b": 0.3}),
                                  known, seed=4)
    fit = {"starts": 1, "max_nfev": 3, "extras": False, "line_models": None}
    m = commission(runs, orifice_models=ORIFICE_MODELS, **fit)
    assert m.stated.valve.flow_model == "iso6358" and m.rig.valve.flow_model == "iso6358"
    assert m.alternatives == [] and m.alternative_deltas == []  # the strokes rule the other out
    assert commission(runs, **fit).rig.valve.flow_model == "thesis"  # the stated law only
    assert "'iso6358' law" in report_markdown(m)
    with pytest.raises(ValueError, match="orifice law"):
        commission(runs, orifice_models=("sharp-edged",))


def test_other_forms_the_strokes_cannot_rule_out_join_the_plausible_rigs(runs, model, tmp_path,
                                                                         monkeypatch):
    import pneugym.commission as C

    monkeypatch.setattr(C, "FORM_DELTA", math.inf)  # every other form: the other line model
    fit = {"starts": 1, "max_nfev": 2, "extras": False, "orifice_models": None}
    m = commission(runs, **fit)
    assert len(m.alternatives) == 1
    assert {m.rig.line.model, m.alternatives[0].line.model} == {"fd", "lumped"}
    assert m.alternative_deltas[0] >= 0 and m.alternative_misfits[0] >= m.misfit * 0.999
    monkeypatch.setattr(C, "FORM_DELTA", -1.0)  # none
    assert commission(runs, **fit).alternatives == []
    alt = model.rig.with_(valve={"flow_model": "iso6358"})
    both = replace(model, alternatives=[alt], alternative_misfits=[1.3], alternative_deltas=[2.5])
    rigs = both.members(4, seed=1, forms=True)
    assert rigs[:2] == [model.rig, alt] and rigs[2:] == model.members(3, seed=1)[1:]
    assert both.members(4, seed=1) == model.members(4, seed=1)  # only when asked
    assert Commissioned.load(both.save(tmp_path)).alternatives == [alt]  # round trip
    assert "cannot rule out: 'fd' line with the 'iso6358' law (misfit 1.30)" in \
        report_markdown(both)
    env = CutOffVectorEnv(num_envs=1, observe_rig=True)
    pol = RigModelPolicy.for_env(env, model=both, members=3, forms=True)
    assert pol.changes[1] == (("valve.flow_model", "iso6358"),)  # planned on with its law
    bad = both.to_dict()
    bad["alternative_deltas"] = []
    (tmp_path / "commissioning.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="pair up"):
        Commissioned.load(tmp_path)


def test_a_fit_far_above_the_noise_is_refitted_from_further_starts(runs, monkeypatch):
    import pneugym.commission as commissioning

    kw = {"max_nfev": 2, "extras": False, "line_models": ["fd"], "seed": 3}
    first = commission(runs, starts=1, **kw)
    assert first.misfit > commissioning.MISFIT_FLAG and not first.refitted  # 2 evaluations
    three = commission(runs, starts=3, **kw)  # the same starts as one and a refit's two
    assert three.ssr < first.ssr  # (seed 3: a drawn start does better)
    again = commission(runs, starts=1, refit_starts=2, **kw)
    assert again.ssr == three.ssr and again.refitted
    assert Commissioned.from_dict(again.to_dict()).refitted == again.refitted
    monkeypatch.setattr(commissioning, "MISFIT_FLAG", math.inf)  # below the flag: no refit
    assert commission(runs, starts=1, refit_starts=2, **kw).ssr == first.ssr
    with pytest.raises(ValueError, match="refit_starts"):
        commission(runs, refit_starts=-1)


def test_a_first_fit_on_the_area_cap_goes_on_from_its_end_and_from_its_start(monkeypatch):
    """The first fits cap the flow areas at FAST_AREA_FACTOR x stated (a coarser substep); on a
    rig whose exhaust is wider, the capped fit bends the other parameters, so it goes on with
    the full bounds from where it ended and from its own start, the better kept."""
    import pneugym.commission as commissioning

    truth = KNOWN.with_(valve={"exhaust_area_m2": 2.6 * KNOWN.valve.exhaust_area_m2})
    runs = commissioning_protocol(truth, KNOWN, seed=3)
    seen, solve = [], commissioning.solve

    def spy(job):
        seen.append((job, solve(job)))
        return seen[-1][1]

    monkeypatch.setattr(commissioning, "solve", spy)
    m = commission(runs, starts=1, max_nfev=6, extras=False, line_models=["fd"])
    exh = [p.path for p in m.params].index("valve.exhaust_area_m2")
    (first, capped), *full = seen
    assert first.params[exh].hi == commissioning.FAST_AREA_FACTOR
    end = Problem(first.runs, [], first.sigma, first.params).values(capped[0])
    assert end[exh] >= 0.99 * commissioning.FAST_AREA_FACTOR  # ended on the cap
    assert [j.params[exh].hi for j, _ in full] == [5.0, 5.0]
    assert full[0][0].start == pytest.approx(end)  # where it ended
    assert np.array_equal(full[1][0].start, first.start)  # its start
    assert m.ssr == min(r[1] for _, r in full) < capped[1]
    assert m.values[exh] > commissioning.FAST_AREA_FACTOR and m.misfit < 3.0


def test_the_fitted_parameters_stay_physical():
    ps = {p.path: p for p in fitted_params(KNOWN)}
    assert ps["cylinder.cushion_length_m"].hi * KNOWN.cylinder.cushion_length_m \
        <= 0.45 * KNOWN.cylinder.stroke_m + 1e-12
    assert ps["valve.delay_s"].lo > 0 and not ps["valve.delay_s"].relative
    no_cushion = KNOWN.with_(cylinder={"cushion_length_m": 0.0})
    assert not any(p.startswith("cylinder.cushion") for p in
                   (q.path for q in fitted_params(no_cushion)))


def test_the_evaluation_commissions_every_rig_from_its_rig_file():
    changes = (("cylinder.dead_volume_m3", 3e-4), ("friction.static_n", 500.0),
               ("line.length_m", 2.0), ("valve.delay_s", 0.1))
    known = rig_file(changes, KNOWN)
    assert known.cylinder.dead_volume_m3 == 3e-4 and known.line.length_m == 2.0
    assert known.friction == KNOWN.friction and known.valve == KNOWN.valve  # hidden truth
    assert "friction.static_n" not in DATASHEET_FIELDS
    eps = [("a/1bar", None), ("b/1bar", None), ("a/2bar", None)]
    assert rig_groups(eps) == {"a": [0, 2], "b": [1]}
    assert rig_groups([("1bar", None)]) == {"": [0]}


def test_evaluate_runs_mpc_rig_with_a_commissioning_per_rig(monkeypatch):
    from agents.evaluation import run as R
    from agents.evaluation.run import evaluate

    seen = []
    real = R.run_policy

    def spy(policy, conds, env_config, seed):
        if isinstance(policy, RigModelPolicy):
            seen.append((policy.model.runs, len(conds)))
        return real(policy, conds, env_config, seed)

    monkeypatch.setattr(R, "run_policy", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = evaluate(["mpc-rig"], ["nominal"], 1, 1_000_000, progress=False,
                       commission={"starts": 1, "max_nfev": 3, "refit_starts": 1})
    s = res["suites"]["nominal"]["policies"]["mpc-rig"]
    assert s["episodes"] == 2 and math.isfinite(s["return_mean"])
    assert ["conventional", "end_stroke_cutoff"] in [r for r, _ in seen]
    ep = res["suites"]["nominal"]["episodes"][-3]  # mpc-rig's (the oracle's come last)
    assert ep["policy"] == "mpc-rig" and ep["commission_misfit"] > 0
    assert res["config"]["commission"] == {"starts": 1, "max_nfev": 3, "refit_starts": 1}


def test_a_rig_of_a_suite_runs_as_a_task_of_its_own_with_the_same_records():
    """mpc-rig on a suite of two rigs, whole and its second rig alone (as evaluate's per-rig
    tasks run it): the same records, each rig's strokes seeded by its place in the suite."""
    from agents.evaluation.run import _per_rig_tasks, gather, policy_records
    from agents.evaluation.suites import transfer_rigs

    rigs = transfer_rigs()
    eps = [(f"{r}/2.5bar-10kg", Conditions(supply_pressure_gauge_pa=2.5e5, load_mass_kg=10.0,
                                           rig_changes=rigs[r], position_noise_m=3e-5,
                                           pressure_noise_pa=400.0)) for r in list(rigs)[:2]]
    fast = {"starts": 1, "max_nfev": 2, "extras": False, "line_models": None, "n_jobs": 1,
            "refit_starts": 1}
    args = dict(suite="transfer", episodes=1, seed=7, env_config=evaluation_env_config({}),
                eps=eps, commission=fast)
    assert _per_rig_tasks("gaslaw", eps) == [None] and _per_rig_tasks("mpc-rig", eps[:1]) == [None]
    split = _per_rig_tasks("mpc-rig", eps)
    assert split == [[eps[0][0].split("/")[0]], [eps[1][0].split("/")[0]]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = policy_records("mpc-rig", **args)
        second = policy_records("mpc-rig", rigs=split[1], **args)
    assert second[1] == whole[1][1:]
    parts = [second, ("mpc-rig", whole[1][:1], 1.5)]  # (tasks end in any order)
    keys = [("transfer", "mpc-rig", r) for r in reversed(split)]
    name, rec, wall = gather(keys, parts)[("transfer", "mpc-rig")]
    assert name == "mpc-rig" and rec == whole[1] and [r["episode"] for r in rec] == [0, 1]
    assert wall == pytest.approx(second[2] + 1.5)
    with pytest.raises(ValueError, match="not commissioned per rig"):
        policy_records("gaslaw", rigs=split[0], **args)
    with pytest.raises(ValueError, match="must name rigs"):
        policy_records("mpc-rig", rigs=["nope"], **args)


def test_the_plan_bench_keeps_fits_per_draw_and_writes_strict_json(model, tmp_path, monkeypatch,
                                                                   load_bench):
    """bench_mpc_plan.py's kept fits carry what they were fitted for: a folder kept for another
    draw, other options or an earlier fitting procedure is refused, not planned on; its
    results hold no infinity."""
    import pneugym.commission as commissioning

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    bench = load_bench("bench_mpc_plan")
    where = tmp_path / "0-stated law"
    model.save(where)
    opts = {"starts": 2, "max_nfev": 40, "refit_starts": 4}
    key = {"seed": 3, "draw": 0}
    version = {"fit_version": commissioning.FIT_VERSION}
    (where / "fit_key.json").write_text(json.dumps(
        {**key, **version, "orifice_models": None, "commission": {**opts, "refit_starts": 0}}))
    assert model.misfit <= 9  # a fit below the flag: the same with any refit_starts
    assert bench._fit(None, None, {**opts, "n_jobs": 2}, where, key).ssr == model.ssr
    with pytest.raises(SystemExit, match="another --fits folder"):
        bench._fit(None, None, {**opts, "starts": 3}, where, key)
    with pytest.raises(SystemExit, match="another --fits folder"):  # another draw's fit
        bench._fit(None, None, {**opts, "refit_starts": 0}, where, {"seed": 4, "draw": 0})
    flagged = replace(model, ssr=50.0 * model.n)
    flagged.save(where)
    with pytest.raises(SystemExit, match="another --fits folder"):  # a refit might change it
        bench._fit(None, None, opts, where, key)
    model.save(where)
    (where / "fit_key.json").write_text(json.dumps(
        {**key, **version, "orifice_models": None, "commission": opts}))
    assert bench._fit(None, None, {**opts, "n_jobs": 1}, where, key).ssr == model.ssr
    (where / "fit_key.json").write_text(json.dumps(  # a fit of the procedure before
        {**key, "orifice_models": None, "commission": opts}))
    with pytest.raises(SystemExit, match="another --fits folder"):
        bench._fit(None, None, opts, where, key)
    assert json.dumps(bench._finite({"cut": math.inf, "x": [1.0, -math.inf]}),
                      allow_nan=False) == '{"cut": null, "x": [1.0, null]}'
