"""The rig family (pneugym.envs.family): draws inside the stated ranges, reproducible, each rig
in the episode's conditions (and so in every cache key); the transfer suite built on it; the
Gas-Law rule per rig; the environment's retry of a step that went non-physical."""
import math
import warnings

import numpy as np
import pytest

from agents import BASELINES, make_policy
from agents.base import run_first_episodes
from agents.evaluation.suites import (TRANSFER_EDGES, TRANSFER_FORMS, TRANSFER_HELD_OUT,
                                      TRANSFER_POINTS, suite_cells, suite_episodes, transfer_rigs)
from agents.gaslaw import GasLawPerRigPolicy, GasLawPolicy
from pneugym.envs import Conditions
from pneugym.envs.conditions import PRESETS, as_conditions
from pneugym.envs.cutoff import CutOffVectorEnv, conventional_figures
from pneugym.envs.family import CHANGEABLE, RigFamily, apply_changes, check_changes
from pneugym.params import RigParams
from pneugym.physics import layout as L
from pneugym.plant import RigWarning

FAMILY = PRESETS["family"]


@pytest.fixture(scope="module")
def draws():
    return [FAMILY.sample(np.random.default_rng([3, i])) for i in range(40)]


def test_draws_stay_in_the_family_ranges(draws):
    fam, base = FAMILY.family, RigParams()
    forms = set()
    for c in draws:
        rig = c.rig()
        assert fam.dead_volume_m3[0] <= rig.cylinder.dead_volume_m3 <= fam.dead_volume_m3[1]
        assert fam.line_length_m[0] <= rig.line.length_m <= fam.line_length_m[1]
        assert fam.line_diameter_m[0] <= rig.line.diameter_m <= fam.line_diameter_m[1]
        for got, ref, name in ((rig.valve.area_m2, base.valve.area_m2, "valve_area_scale"),
                               (rig.cylinder.port_area_m2, base.cylinder.port_area_m2,
                                "port_area_scale")):
            lo, hi = getattr(fam, name)
            assert lo * ref * (1 - 1e-12) <= got <= hi * ref * (1 + 1e-12)
        assert 0.02 <= rig.valve.delay_s <= 0.3
        assert 150.0 <= rig.friction.static_n <= 600.0
        assert rig.friction.coulomb_n <= 0.9 * rig.friction.static_n
        assert 1.5e5 <= c.supply_pressure_gauge_pa <= 6e5 and 2.0 <= c.load_mass_kg <= 40.0
        assert rig.cylinder.bore_m == base.cylinder.bore_m  # the datasheet geometry stays
        forms.add((rig.line.model, rig.valve.flow_model))
        # every draw can complete: its conventional stroke within the family's bound
        t, _ = conventional_figures(rig, c.dip)
        assert t <= fam.max_conventional_time_s
    assert len(forms) == 4  # both line models and both orifice laws occur


def test_draws_are_reproducible_and_differ(draws):
    again = FAMILY.sample(np.random.default_rng([3, 0]))
    assert again == draws[0] and again.physics_key() == draws[0].physics_key()
    assert len({c.rig_changes for c in draws}) == len(draws)


def test_rig_changes_round_trip_and_are_checked():
    c = Conditions(rig_changes={"line.length_m": 2.0, "valve.flow_model": "iso6358"})
    assert c.rig_changes == (("line.length_m", 2.0), ("valve.flow_model", "iso6358"))
    assert as_conditions(c.to_dict()) == c  # JSON-ready and back
    assert c.rig().line.length_m == 2.0 and c.rig().valve.flow_model == "iso6358"
    assert c.physics_key() != Conditions().physics_key()
    with pytest.raises(ValueError, match="did you mean 'line.length_m'"):
        Conditions(rig_changes={"line.lenght_m": 2.0})
    with pytest.raises(ValueError, match="cylinder.bore_m"):
        check_changes({"cylinder.bore_m": 0.1})  # not something a family changes
    with pytest.raises(ValueError, match="number or"):
        check_changes({"line.length_m": True})
    with pytest.raises(ValueError, match="mm given as m"):
        apply_changes(RigParams(), check_changes({"line.diameter_m": 5.0}))
    assert set(CHANGEABLE) >= {k for rig in TRANSFER_EDGES.values() for k in rig}


def test_bad_families_are_refused():
    with pytest.raises(ValueError, match="probability"):
        RigFamily(p_leak=1.5)
    with pytest.raises(ValueError, match="low <= high"):
        RigFamily(line_length_m=(5.0, 0.3))
    with pytest.raises(ValueError, match="did you mean 'line_length_m'"):
        RigFamily().with_(line_lenght_m=(1.0, 2.0))
    with pytest.raises(ValueError, match="mm given as m"):  # extremes must make valid rigs
        RigFamily(line_diameter_m=(0.004, 8.0))
    impossible = FAMILY.with_(family=RigFamily(max_conventional_time_s=0.05))
    with pytest.raises(ValueError, match="no rig whose conventional stroke completes"):
        impossible.sample(np.random.default_rng(0))


def test_the_environment_draws_a_rig_per_episode():
    env = CutOffVectorEnv(num_envs=3, preset="family")
    _, info = env.reset(seed=4)
    rigs = [c.rig(env.rig) for c in env.conditions]
    assert len({r.line.length_m for r in rigs}) == 3
    assert [dict(c.rig_changes) for c in env.conditions] == list(info["conditions"]["rig_changes"])
    for i, r in enumerate(rigs):  # each row's plant is its own rig
        assert env.P[i, L.P_V0D] == pytest.approx(r.cylinder.dead_volume_m3)
        assert env.P[i, L.P_LINE_MODEL] == (r.line.model == "lumped")


def test_transfer_suite_rigs_and_cells():
    rigs = transfer_rigs()
    assert list(rigs)[0] == "thesis" and rigs["thesis"] == ()
    held = [k for k in rigs if k.startswith("heldout-")]
    assert len(held) == TRANSFER_HELD_OUT and set(TRANSFER_EDGES) | set(TRANSFER_FORMS) < set(rigs)
    assert transfer_rigs() == rigs  # fixed: the same rigs every time
    # held-out draws: from evaluation seeds, none of them a training draw's rig
    train = {FAMILY.sample(np.random.default_rng(s)).rig_changes for s in range(200)}
    assert not train & {rigs[k] for k in held}
    cells = suite_cells("transfer")
    assert len(cells) == len(rigs) * len(TRANSFER_POINTS)
    eps = suite_episodes("transfer", 1, 1_000_000)
    assert {lab.split("/")[0] for lab, _ in eps} == set(rigs)
    assert all(c.rig_changes == rigs[lab.split("/")[0]] for lab, c in eps)
    edge = dict(rigs["edge-dead-volume"])
    assert edge["cylinder.dead_volume_m3"] > FAMILY.family.dead_volume_m3[1]


def test_gaslaw_takes_each_episodes_rig_and_the_per_rig_k():
    rigs = transfer_rigs()
    conds = [Conditions(supply_pressure_gauge_pa=2.5e5, rig_changes=rigs[k])
             for k in ("thesis", "edge-dead-volume")]
    env = CutOffVectorEnv(num_envs=2, autoreset=False)
    pol = GasLawPolicy.for_env(env)
    pol.begin_episodes(conds)
    assert list(pol._v0) == [RigParams().cylinder.dead_volume_m3, 8e-4]
    pol.begin_episodes([Conditions()] * 2)  # back to one rig
    assert pol._v0 == RigParams().cylinder.dead_volume_m3
    assert "gaslaw-rig" in BASELINES
    per = make_policy("gaslaw-rig", env)
    assert isinstance(per, GasLawPerRigPolicy)
    per.begin_episodes(conds)
    assert per.table(()) == pytest.approx({r: k for r, k in GasLawPolicy(
        env.observation_layout()).k.items()}, rel=1e-12)  # the thesis rig: the shipped table
    assert per.k[1] != per.k[0] and len(per._tables) == 2
    out = run_first_episodes(env, per, conds, 0)
    assert all(math.isfinite(v) for v in out["objective"])


def test_a_step_that_goes_non_physical_is_retried_with_half_the_substep(monkeypatch):
    env = CutOffVectorEnv(num_envs=2, autoreset=False)
    env.reset(seed=0)
    from pneugym.envs import episode as EP

    real, calls = EP.step_observe, []

    def failing(*args):  # row 1 fails once (args[6]: the status of each row)
        n = real(*args)
        if not calls:
            calls.append(1)
            args[6][1] = L.STATUS_NONPOSITIVE
        return n
    monkeypatch.setattr(EP, "step_observe", failing)
    dt = env.P[1, L.P_DT]
    with pytest.warns(RigWarning, match="retried with half the substep"):
        env.step(np.zeros(2, dtype=np.int64))
    assert env.P[1, L.P_DT] == dt / 2 and env.P[0, L.P_DT] == dt
    assert env.D[1, L.D_T] == pytest.approx(env.D[0, L.D_T])  # the step was taken once
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigWarning)
        env.step(np.zeros(2, dtype=np.int64))


def test_observe_rig_gives_the_datasheet_and_the_strokes_events():
    from pneugym.envs.cutoff import RIG_OBSERVATION

    env = CutOffVectorEnv(num_envs=2, preset="family", observe_rig=True, autoreset=False)
    obs, _ = env.reset(seed=1)
    lay = env.observation_layout()
    assert [f["name"] for f in lay["rig_features"]] == [f.name for f in RIG_OBSERVATION]
    assert lay["size"] == 7 + len(RIG_OBSERVATION) and obs.shape == (2, lay["size"])
    rigs = [c.rig(env.rig) for c in env.conditions]
    assert obs[:, 7] == pytest.approx([r.line.length_m / 5.0 for r in rigs], rel=1e-6)
    assert obs[:, 10] == pytest.approx([c.load_mass_kg / 40.0 for c in env.conditions], rel=1e-6)
    t_rise = None
    for _ in range(200):
        obs, *_ = env.step(np.zeros(2, dtype=np.int64))
        t = obs[:, 5] * env.time_limit_s
        if t_rise is None and (obs[:, 11] < t - 1e-6).all():
            t_rise = obs[:, 11].copy()  # fixed once the pressure rose
    assert t_rise is not None and (obs[:, 11] == t_rise).all()
    delays = [r.valve.delay_s for r in rigs]
    assert all(d <= tr < d + 0.1 for d, tr in zip(delays, t_rise))  # it reads the valve delay
    assert (obs[:, 12] > obs[:, 11]).all() and (obs[:, 13] > 0).all()  # breakaway after the rise


def test_models_without_rig_features_run_where_the_rig_is_observed(tmp_path):
    from agents.learned import LayoutMismatchError, LearnedPolicy

    plain = CutOffVectorEnv(num_envs=1, history=2).observation_layout()
    rich = CutOffVectorEnv(num_envs=1, observe_rig=True).observation_layout()

    class Echo(LearnedPolicy):
        def act_model(self, obs):
            self.seen = obs
            return np.zeros(obs.shape[0], dtype=np.int64)

    pol = Echo(rich, plain)
    obs = np.arange(2 * rich["size"], dtype=np.float32).reshape(2, -1)
    pol.act(obs)
    assert pol.seen.shape == (2, plain["size"])  # rig columns dropped, then stacked
    assert (pol.seen[:, -7:] == obs[:, :7]).all()
    with pytest.raises(LayoutMismatchError, match="observe_rig or observe_commissioning differs"):
        Echo(plain, rich)  # a family model cannot run without what it reads
    # a model of the datasheet and the stroke's events, where a commissioning stroke is observed
    # as well: only the commissioning columns are dropped
    told = CutOffVectorEnv(num_envs=1, observe_rig=True,
                           observe_commissioning=True).observation_layout()
    assert told["size"] == rich["size"] + 6
    assert [f["name"] for f in told["rig_features"][:7]] == [
        f["name"] for f in rich["rig_features"]]
    pol = Echo(told, rich)
    obs = np.arange(2 * told["size"], dtype=np.float32).reshape(2, -1)
    pol.act(obs)
    assert (pol.seen == obs[:, :rich["size"]]).all()
    with pytest.raises(LayoutMismatchError, match="observe_commissioning differs"):
        Echo(rich, told)


@pytest.mark.parametrize("name", ["esac-family", "ppo-family"])
def test_family_runs_have_valid_configurations(name):
    from agents.training import CONFIG_DIR, NAMED_RUNS, load_config

    algo, cfg_file = NAMED_RUNS[name]
    for budget in ("default", "quick"):
        cfg = load_config(algo, budget, CONFIG_DIR / cfg_file, seed=0)
        assert cfg["preset"] == "family" and cfg["env"]["observe_rig"] is True


def test_points_suite_runs_the_transfer_operating_points_on_the_rig():
    cells = suite_cells("points")
    assert [lab for lab, _ in cells] == [f"{b:g}bar-{m:g}kg" for b, m in TRANSFER_POINTS]
    assert all(space.rig_changes == () and space.family is None for _, space in cells)


def test_a_suite_of_several_rigs_plots_the_oracle_fraction_per_rig(tmp_path):
    from agents.evaluation.plots import plot_per_rig

    def pol(*fr):
        return {"per_rig": {r: {"oracle_fraction": f} for r, f in zip(("a", "b"), fr)}}
    suite = {"policies": {"conventional": pol(0.0, 0.0), "esac": pol(0.9, -4.0),
                          "gaslaw": pol(None, 0.5), "oracle": pol(1.0, 1.0)}}
    plot_per_rig("transfer", suite, tmp_path)
    assert (tmp_path / "transfer_oracle_fraction_per_rig.png").stat().st_size > 5000


def test_family_fields_are_what_a_draw_sets_and_outside_names_the_edges():
    from pneugym.envs.family import FAMILY_FIELDS

    fam = FAMILY.family
    draw = FAMILY.sample(np.random.default_rng(5))
    assert {k for k, _ in draw.rig_changes} - {"solver.dt_s"} == set(FAMILY_FIELDS)
    assert fam.outside(draw.rig()) == [] and fam.outside(RigParams()) == []
    rigs = transfer_rigs()
    out = fam.outside(apply_changes(RigParams(), rigs["edge-long-line"]))
    assert out == ["line.length_m 6.5 not in [0.3, 5]"]
    assert fam.outside(apply_changes(RigParams(), rigs["form-leaks-heat"])) == []


def test_a_family_model_warns_only_outside_the_family(tmp_path):
    from agents.registry import RigMismatchWarning, check_rig

    class Pol:
        source, trained_rig, trained_preset = "m", None, "family"

    rigs = transfer_rigs()
    inside = CutOffVectorEnv(num_envs=1, rig=apply_changes(RigParams(), rigs["heldout-1"]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigMismatchWarning)
        check_rig(Pol(), None, inside)
    edge = CutOffVectorEnv(num_envs=1, rig=apply_changes(RigParams(), rigs["edge-long-line"]))
    with pytest.warns(RigMismatchWarning, match=r"rig family.*line.length_m 6.5 not in"):
        check_rig(Pol(), None, edge)
    form = CutOffVectorEnv(num_envs=1, rig=apply_changes(RigParams(), rigs["form-leaks-heat"]))
    with pytest.warns(RigMismatchWarning, match="leak_piston_area_m2"):  # not in the family
        check_rig(Pol(), None, form)


def test_the_cylinders_family_draws_single_rod_and_inclined_cylinders():
    space = PRESETS["family-cylinders"]
    fam = space.family
    draws = [space.sample(np.random.default_rng([4, i])) for i in range(24)]
    designs = {dict(c.rig_changes)["cylinder.design"] for c in draws}
    angles = [dict(c.rig_changes)["cylinder.mounting_angle_deg"] for c in draws]
    assert designs == {"single-rod", "double-rod"}
    assert any(a == 0.0 for a in angles) and any(a > 0 for a in angles) and any(a < 0 for a in angles)
    for c in draws:
        rig = c.rig()
        assert fam.outside(rig) == [] and -90.0 <= rig.cylinder.mounting_angle_deg <= 90.0
        t, _ = conventional_figures(rig, c.dip)  # every draw completes, lifting or lowering
        assert t <= fam.max_conventional_time_s
    # the default family draws neither, and says so of a rig that has them
    assert all("cylinder.design" not in dict(c.rig_changes) for c in
               (FAMILY.sample(np.random.default_rng(i)) for i in range(3)))
    inclined = next(c.rig() for c in draws if dict(c.rig_changes)["cylinder.mounting_angle_deg"])
    assert any(o.startswith("cylinder.mounting_angle_deg") for o in FAMILY.family.outside(inclined))


def test_the_default_family_draws_what_it_always_drew():
    """Cylinder draws are off by default and take no uniforms then: the first draw of a seed is
    the one the main job's policies were trained and evaluated on (recorded values)."""
    changes = dict(FAMILY.family.sample(np.random.default_rng(0)))
    assert len(changes) == 18 and "cylinder.design" not in changes
    assert changes["line.length_m"] == 1.6532495715022089  # (recorded before cylinder draws)
    assert changes["friction.static_n"] == 165.11350888745895


@pytest.mark.parametrize("kw", [dict(mounting_angle_deg=(-100.0, 0.0)),
                                dict(mounting_angle_deg=(10.0, 0.0)), dict(p_single_rod=1.5)])
def test_bad_cylinder_draws_are_refused(kw):
    with pytest.raises(ValueError, match="RigFamily"):
        RigFamily(**kw)


def test_the_cylinders_suite_holds_out_single_rod_and_inclined_rigs():
    from agents.evaluation.suites import CYLINDER_HELD_OUT, cylinder_rigs

    rigs = cylinder_rigs()
    assert len(rigs) == CYLINDER_HELD_OUT and rigs == cylinder_rigs()  # reproducible
    designs = {dict(ch)["cylinder.design"] for ch in rigs.values()}
    assert designs == {"single-rod", "double-rod"}
    assert any(dict(ch)["cylinder.mounting_angle_deg"] != 0.0 for ch in rigs.values())
    cells = suite_cells("cylinders")
    assert len(cells) == CYLINDER_HELD_OUT * len(TRANSFER_POINTS)
    assert cells[0][0] == "cyl-1/1.5bar-5kg"


def test_a_cylinders_family_model_does_not_warn_inside_its_family():
    from agents.registry import RigMismatchWarning, check_rig

    class Pol:
        source, trained_rig, trained_preset = "m", None, "family-cylinders"

    space = PRESETS["family-cylinders"]
    draw = next(c for c in (space.sample(np.random.default_rng([5, i])) for i in range(20))
                if dict(c.rig_changes)["cylinder.mounting_angle_deg"] != 0.0)
    env = CutOffVectorEnv(num_envs=1, rig=draw.rig())
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigMismatchWarning)
        check_rig(Pol(), None, env)


def test_a_real_error_in_a_family_draw_is_named_not_redrawn():
    """Only a stroke that does not complete (or chatters) is redrawn; a rig the plant refuses
    (bar given as Pa, a cushion longer than half a short stroke) is said as it is."""
    from pneugym.presets import cylinder_rig

    space = PRESETS["family"].with_(supply_pressure_gauge_pa=(1.5, 6.0))
    with pytest.raises(ValueError, match="bar given as Pa"):
        space.sample(np.random.default_rng(0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RigWarning)
        with pytest.raises(ValueError, match="half the stroke"):
            PRESETS["family"].sample(np.random.default_rng(0), cylinder_rig(32, 10.0))


@pytest.mark.parametrize("kwargs, msg", [
    ({"heat_transfer_time_constant_s": (0.3, 1e6)}, "heat_transfer_time_constant_s"),
    ({"p_leak": True}, "p_leak"),
    ({"max_conventional_time_s": True}, "max_conventional_time_s"),
    ({"static_friction_n": (True, 600)}, "static_friction_n"),
    ({"line_length_m": ("0.3", "5")}, "line_length_m"),
])
def test_a_family_refuses_bounds_no_rig_can_take_and_non_numbers(kwargs, msg):
    """The extremes are checked with each effect on (a time constant of 1e6 s was accepted,
    its draws silently redrawn); bools and strings are not numbers."""
    with pytest.raises(ValueError, match=msg):
        RigFamily(**kwargs)


def test_the_suites_held_out_draws_name_a_base_the_family_cannot_draw_on():
    """A base no draw can be built on (cushions of 5-25 mm on a 10 mm stroke) is said, not
    redrawn for ever (``pneugym evaluate --rig FILE --suite transfer`` hung)."""
    from agents.evaluation.suites import held_out_draws
    from pneugym.presets import cylinder_rig

    with pytest.raises(ValueError, match="half the stroke"):
        held_out_draws("family", 1, 0, cylinder_rig(32, 10.0))
