"""agents/esac.py: the ESAC predictor (learns a known relation, saves and loads), its rollout
data, and the cut-off rule of thesis 6.8."""
import numpy as np
import pytest
import torch

from agents import esac
from agents.base import run_first_episodes
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv


def _layout(history=2):
    return CutOffVectorEnv(num_envs=1, history=history).observation_layout()


def test_predictor_learns_a_synthetic_relation():
    """Targets that are known functions of the inputs: the fitted network reproduces them on
    fresh inputs (classification > 95 % right, regression R^2 > 0.9)."""
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)

    def make(n):
        x = rng.uniform(-1, 1, (n, 6)).astype(np.float32)
        y = np.stack([x[:, 0] > 0.2 * x[:, 1], x[:, 2] > 0.5,       # two classes
                      0.5 + 0.4 * np.tanh(2 * x[:, 0]),              # final position / stroke
                      0.3 * x[:, 1] ** 2 + 0.1 * x[:, 3],            # log time ratio
                      1.2 + 0.1 * x[:, 4],                           # conventional time
                      0.5 * (x[:, 0] + 1) * (x[:, 5] + 1) / 4,       # wasted fraction
                      300 + 50 * x[:, 4]], axis=1).astype(np.float32)  # E_conv [J]
        return x, y

    x, y = make(4000)
    net, hist = esac.fit(x, y, np.ones_like(y), hidden=(64, 64), epochs=40, batch_size=128,
                         lr=3e-3, progress=False)
    assert hist["val"][-1] < hist["val"][0]
    xt, yt = make(1000)
    with torch.no_grad():
        out = net(torch.as_tensor(xt)).numpy()
    reg = out[:, 2:] * net.out_std.numpy() + net.out_mean.numpy()
    for k in range(2):
        assert np.mean((out[:, k] > 0) == (yt[:, k] > 0.5)) > 0.95
    for k in range(5):
        r2 = 1 - np.var(reg[:, k] - yt[:, 2 + k]) / np.var(yt[:, 2 + k])
        assert r2 > 0.9, (k, r2)


def test_rollouts_record_the_observation_at_the_cut(tmp_path):
    data = esac.rollouts(tmp_path, 12, 3, history=2, progress=False)
    n = data["obs"].shape[0]
    assert 0 < n <= 12 and data["obs"].shape[1] == 14
    # the newest sample's time feature is the cut time / time limit (4 s)
    np.testing.assert_allclose(data["obs"][:, 12] * 4.0, data["t_cut"], atol=1e-6)
    comp = data["completed"]
    assert np.all(np.isfinite(data["stroke_time_s"][comp]))
    assert np.all(np.isnan(data["stroke_time_s"][~comp]))
    assert np.all(data["final_position_m"][comp] > 0.17)
    # cached: the same arrays come back from disk
    again = esac.rollouts(tmp_path, 12, 3, history=2, progress=False)
    np.testing.assert_array_equal(again["obs"], data["obs"])
    assert len(list(tmp_path.glob("esac-rollouts-*.npz"))) == 1
    y, mask = esac.targets(data, 0.18)
    assert y.shape == (n, 7) and np.all(mask[:, 3] == comp)
    # the lagged observations: the same episode seen lag periods before the cut
    lags = np.asarray(esac.LAGS)
    assert data["obs_lag"].shape == (n, lags.size, 14)
    np.testing.assert_array_equal(data["obs_lag"][:, 0], data["obs"])
    np.testing.assert_allclose(data["lag_s"], lags * 0.005)
    t_lag = data["obs_lag"][:, :, 12] * 4.0
    seen = ~np.isnan(t_lag)
    expect = data["t_cut"][:, None] - data["lag_s"][None, :]
    np.testing.assert_allclose(t_lag[seen], expect[seen], atol=1e-6)
    assert np.all(expect[~seen] < -1e-9)   # missing only where the episode had not begun


def _predictor(history=2):
    net = esac.make_net(7 * history, (8,))
    return esac.ESACPredictor(net, _layout(history))


def _pred(**kw):
    base = {"p_complete": np.array([0.99]), "p_stick": np.array([0.0]),
            "final_position_m": np.array([0.18]), "stroke_time_s": np.array([1.2]),
            "conventional_time_s": np.array([1.2]), "time_increase": np.array([0.0]),
            "wasted_fraction": np.array([0.3]), "wasted_energy_j": np.array([90.0]),
            "energy_conventional_j": np.array([300.0])}
    return {**base, **{k: np.array([v]) for k, v in kw.items()}}


def test_rule_needs_completion_with_margin_time_demand_and_stick_risk():
    pol = esac.ESACPolicy(_layout(), _predictor(), margin=0.05, max_time_increase=0.2,
                          max_stick=0.5)
    assert pol.decide(_pred())[0]
    assert not pol.decide(_pred(p_complete=0.9))[0]          # inside the safety margin
    assert not pol.decide(_pred(final_position_m=0.17))[0]   # short of the stroke end
    assert not pol.decide(_pred(time_increase=0.3))[0]       # beyond the time demand
    assert not pol.decide(_pred(p_stick=0.6))[0]
    wide = esac.ESACPolicy(_layout(), _predictor(), margin=0.2)
    assert wide.decide(_pred(p_complete=0.9))[0]
    absolute = esac.ESACPolicy(_layout(), _predictor(), time_demand_s=1.3)
    assert absolute.decide(_pred(stroke_time_s=1.25, time_increase=5.0))[0]
    assert not absolute.decide(_pred(stroke_time_s=1.35))[0]
    assert pol.rule()["margin"] == 0.05
    with pytest.raises(ValueError, match="margin"):
        esac.ESACPolicy(_layout(), _predictor(), margin=1.5)


class _Scripted(esac.ESACPredictor):
    """Predictions from a script over control steps: the objective of a cut at step ``k`` is
    ``-|k - 5| / 100`` (it peaks at step 5); a cut ``Δ`` later is a cut at ``k + Δ / 5 ms``."""

    def __init__(self, layout):
        self.layout, self.stroke_m, self.k = layout, 0.18, 0
        self.delay_input, self.lookahead_s = True, np.array([0.005, 0.01])

    def __call__(self, obs, delay_s=None):
        if delay_s is None:
            k = self.k
            self.k += 1
            return _pred(wasted_fraction=abs(k - 5) * 0.01)
        ks = self.k - 1 + np.asarray(delay_s) / 0.005
        return {key: np.full((1, ks.size), v[0]) for key, v in _pred().items()} | {
            "wasted_fraction": np.abs(ks - 5)[None, :] * 0.01}


def test_lookahead_rule_cuts_once_no_later_cut_predicts_better():
    lay = _layout()
    obs = np.zeros((1, 14), dtype=np.float32)
    pol = esac.ESACPolicy(lay, _Scripted(lay), lookahead=1, max_time_increase=1.0, max_stick=1.0)
    assert [int(pol.act(obs)[0]) for _ in range(9)].index(1) == 5   # at the peak
    eager = esac.ESACPolicy(lay, _Scripted(lay), lookahead=0, max_time_increase=1.0,
                            max_stick=1.0)
    assert int(eager.act(obs)[0]) == 1   # the thesis's rule: as soon as 1-3 hold
    loose = esac.ESACPolicy(lay, _Scripted(lay), lookahead=1, hysteresis=0.015,
                            max_time_increase=1.0, max_stick=1.0)
    assert [int(loose.act(obs)[0]) for _ in range(9)].index(1) == 4   # within the hysteresis
    with pytest.raises(ValueError, match="delay_input"):
        esac.ESACPolicy(lay, _predictor(), lookahead=1)


def test_delay_input_predictor_shapes_and_samples():
    lay = _layout()
    net = esac.make_net(15, (8,))
    pred = esac.ESACPredictor(net, lay, delay_input=True, lookahead_s=[0.0, 0.01, 0.04])
    np.testing.assert_array_equal(pred.lookahead_s, [0.01, 0.04])
    obs = np.random.default_rng(0).random((3, 14)).astype(np.float32)
    now, later = pred(obs), pred(obs, [0.0, 0.01, 0.04])
    assert now["p_complete"].shape == (3,) and later["p_complete"].shape == (3, 3)
    np.testing.assert_allclose(later["wasted_fraction"][:, 0], now["wasted_fraction"], rtol=1e-6)
    with pytest.raises(ValueError, match="inputs"):
        esac.ESACPredictor(net, lay)   # 15 inputs are not an observation of 14
    with pytest.raises(ValueError, match="no delay input"):
        _predictor()(obs, [0.01])
    # samples: one per recorded lag, the delay last, the episode's targets repeated
    data = {"obs": obs, "obs_lag": np.stack([obs, obs * 0.5], axis=1),
            "lag_s": np.array([0.0, 0.01]), "completed": np.array([True, True, False]),
            "stick_slip_events": np.zeros(3, int), "final_position_m": np.full(3, 0.18),
            "stroke_time_s": np.array([1.0, 1.2, np.nan]),
            "conventional_time_s": np.ones(3), "energy_wasted_j": np.ones(3),
            "energy_conventional_j": np.full(3, 2.0)}
    data["obs_lag"][2, 1] = np.nan   # cut before the lag's observation existed
    x, y, m, ep = esac.samples(data, 0.18)
    assert x.shape == (5, 15) and list(ep) == [0, 0, 1, 1, 2]
    np.testing.assert_allclose(x[:, -1], [0.0, 0.01, 0.0, 0.01, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(x[1, :14], obs[0] * 0.5)
    np.testing.assert_array_equal(y[3], y[2])
    x0, _, _, ep0 = esac.samples(data, 0.18, delay_input=False)
    assert x0.shape == (3, 14) and list(ep0) == [0, 1, 2]


def test_save_load_roundtrip_and_refusal(tmp_path):
    pred = _predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout, "rule": {"margin": 0.07}}
    esac.save(tmp_path / "m.pt", pred.net, meta)
    pred2, meta2 = esac.load(tmp_path / "m.pt")
    x = np.random.default_rng(1).random((5, 14)).astype(np.float32)
    np.testing.assert_array_equal(pred.raw(x), pred2.raw(x))
    pol = esac.load_policy(tmp_path / "m.pt", _layout(1))  # stacks its history of 2 itself
    assert pol.rule()["margin"] == 0.07
    over = esac.load_policy(tmp_path / "m.pt", _layout(1), max_time_increase=0.1)
    assert over.rule()["max_time_increase"] == 0.1 and over.rule()["margin"] == 0.07
    with pytest.raises(ValueError, match="unknown ESAC rule parameter.*'marjin'"):
        esac.load_policy(tmp_path / "m.pt", _layout(1), marjin=0.1)
    env = CutOffVectorEnv(num_envs=1, autoreset=False)
    out = run_first_episodes(env, pol, [Conditions()], 1_000_000)
    assert out["completed"][0] or out["stalled"][0] or out["objective"][0] < 0
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an ESAC model"):
        esac.load(tmp_path / "other.pt")
    from agents.learned import LayoutMismatchError
    with pytest.raises(LayoutMismatchError, match="observe_params"):
        esac.load_policy(tmp_path / "m.pt", CutOffVectorEnv(
            num_envs=1, history=2, observe_params=True).observation_layout())


class _Marker:
    """Unpickling this creates ``path``."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_damaged_or_foreign_files_are_named(tmp_path):
    """A truncated model, another file renamed .pt, a torch file of something else, a pickled
    object (never unpickled), bad metadata, weights of another network: a ValueError naming
    the file, never torch's own traceback."""
    import json

    pred = _predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout}
    esac.save(tmp_path / "m.pt", pred.net, meta)
    raw = (tmp_path / "m.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(raw[: len(raw) // 2])
    (tmp_path / "text.pt").write_text("hello")
    torch.save({"format": esac.FORMAT, "x": _Marker(tmp_path / "ran")}, tmp_path / "evil.pt")
    for name in ("cut.pt", "text.pt", "evil.pt"):
        with pytest.raises(ValueError, match=f"{name} is not a readable ESAC model"):
            esac.load(tmp_path / name)
    assert not (tmp_path / "ran").exists()
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="list.pt is not an ESAC model"):
        esac.load(tmp_path / "list.pt")
    torch.save({"format": esac.FORMAT, "state_dict": {}, "meta": "{"}, tmp_path / "meta.pt")
    with pytest.raises(ValueError, match="meta.pt: its metadata is missing or not JSON"):
        esac.load(tmp_path / "meta.pt")
    torch.save({"format": esac.FORMAT, "state_dict": {}, "meta": json.dumps({"n_in": "x"})},
               tmp_path / "meta2.pt")
    with pytest.raises(ValueError, match="meta2.pt: its metadata.s n_in is .x.; expected the "
                                         "network.s input size"):
        esac.load(tmp_path / "meta2.pt")
    esac.save(tmp_path / "other.pt", pred.net, {**meta, "hidden": [16]})
    with pytest.raises(ValueError, match="other.pt: its weights do not fit the network"):
        esac.load(tmp_path / "other.pt")
    with pytest.raises(FileNotFoundError, match="no ESAC model at"):
        esac.load(tmp_path / "missing.pt")


# ------------------------------------------------------------------------------------------------
# metadata and rule parameters: checked, each problem named with the file and key
# ------------------------------------------------------------------------------------------------
def _meta_file(tmp_path, name="m.pt", **changes):
    import json

    pred = _predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout, "delay_input": False,
            "lookahead_s": [], "rule": {"margin": 0.05, "lookahead": 0.0}}
    for key, value in changes.items():
        if value is ...:
            meta.pop(key)
        elif key == "rule":
            meta["rule"] = value if not isinstance(value, dict) else {**meta["rule"], **value}
        else:
            meta[key] = value
    torch.save({"format": esac.FORMAT, "state_dict": pred.net.state_dict(),
                "meta": json.dumps(meta)}, tmp_path / name)
    return tmp_path / name


def _without_position():
    lay = dict(_layout())
    lay["features"] = [f for f in lay["features"] if f["name"] != "position"]
    lay["size"] = 12
    return lay


@pytest.mark.parametrize("changes, match", [
    ({"layout": {}}, r"its metadata's layout has no 'features'"),
    ({"layout": "x"}, r"its metadata's layout is 'x'; expected an object"),
    ({"layout": ...}, r"its metadata's layout is None"),
    ({"layout": _without_position()}, r"features \[.*\] lack \['position'\]"),
    ({"layout": {**_layout(), "features": "abc"}}, r"features is 'abc'"),
    ({"layout": {**_layout(), "history": 0}}, r"history is 0"),
    ({"n_in": 15}, r"its metadata's n_in is 15; expected 14: the layout's size 14"),
    ({"n_in": True}, r"n_in is True"),
    ({"hidden": [10 ** 5] * 3}, r"hidden is \[100000, 100000, 100000\]; expected a list of at "
                                r"most 16 layer widths from 1 to 4096"),
    ({"hidden": [4096] * 16}, r"describes a network .* of [\d,]+ bytes of weights, but the file "
                              r"holds"),
    ({"delay_input": "false"}, r"delay_input is 'false'; expected true or false"),
    ({"lookahead_s": "abc"}, r"lookahead_s is 'abc'"),
    ({"lookahead_s": [None]}, r"lookahead_s is \[None\]"),
    ({"lookahead_s": [1e308]}, r"lookahead_s is \[1e\+308\]"),
    ({"rule": []}, r"its metadata's rule is \[\]; expected an object of rule parameters"),
    ({"rule": "x"}, r"its metadata's rule is 'x'"),
    ({"rule": {"margin": "abc"}}, r"its metadata's rule: margin = 'abc': expected the accepted "
                                  r"predicted risk of an incomplete stroke, a probability in "
                                  r"\[0, 1\]"),
    ({"rule": {"margin": None}}, r"rule: margin = None"),
    ({"rule": {"margin": float("nan")}}, r"rule: margin = nan"),
    ({"rule": {"max_stick": float("nan")}}, r"rule: max_stick = nan"),
    ({"rule": {"max_time_increase": -1}}, r"rule: max_time_increase = -1: expected the time "
                                          r"demand"),
    ({"rule": {"lookahead": 0.5}}, r"rule: lookahead = 0.5: expected 0 .* or 1"),
    ({"rule": {"lookahead": 1e30}}, r"rule: lookahead = 1e\+30"),
    ({"rule": {"margin": [0.1, 0.2]}}, r"rule: margin = \[0.1, 0.2\]"),
    ({"rule": {"bogus": 1}}, r"rule: 'bogus' is not an ESAC rule parameter"),
    ({"rule": {"time_demand_s": 0}}, r"rule: time_demand_s = 0: expected an absolute time "
                                     r"demand, seconds > 0"),
])
def test_malformed_metadata_is_named(tmp_path, changes, match):
    f = _meta_file(tmp_path, **changes)
    with pytest.raises(ValueError, match=f"m.pt: .*{match}"):
        esac.load_policy(f, _layout(1))


def test_damaged_weights_are_named(tmp_path):
    pred = _predictor()
    state = pred.net.state_dict()
    for key, value in (("in_std", torch.zeros_like(state["in_std"])),
                       ("body.0.weight", torch.full_like(state["body.0.weight"], float("nan")))):
        bad = dict(state, **{key: value})
        torch.save({"format": esac.FORMAT, "state_dict": bad, "meta": __import__("json").dumps(
            {"n_in": 14, "hidden": [8], "layout": pred.layout})}, tmp_path / "w.pt")
        with pytest.raises(ValueError, match=f"w.pt: its weights \\['{key}'\\] hold NaN"):
            esac.load(tmp_path / "w.pt")


def test_saved_rule_values_are_normalised_and_applied(tmp_path):
    f = _meta_file(tmp_path, rule={"lookahead": 0.0, "time_demand_s": 1.5})
    pol = esac.load_policy(f, _layout(1))
    assert pol.rule()["lookahead"] == 0 and pol.rule()["time_demand_s"] == 1.5


@pytest.mark.parametrize("kw, match", [
    ({"margin": float("nan")}, "margin = nan"), ({"margin": "abc"}, "margin = 'abc'"),
    ({"lookahead": 0.7}, "lookahead = 0.7"), ({"time_demand_s": -1.0}, "time_demand_s = -1.0"),
    ({"max_stick": -5.0}, "max_stick = -5.0"), ({"w_stall": float("inf")}, "w_stall = inf"),
    ({"hysteresis": None}, "hysteresis = None"),
])
def test_rule_overrides_are_checked(tmp_path, kw, match):
    f = _meta_file(tmp_path)
    with pytest.raises(ValueError, match=f"m.pt: the rule override: {match}: expected"):
        esac.load_policy(f, _layout(1), **kw)
    with pytest.raises(ValueError, match=f"rule: {match}"):  # the controller checks them too
        esac.ESACPolicy(_layout(), _predictor(), **kw)


def test_rule_arrays_are_checked_per_row():
    pol = esac.ESACPolicy(_layout(), _predictor(), margin=np.array([0.0, 0.5, 1.0]),
                          lookahead=np.array([0.0, 0.0, 0.0]))
    assert pol.rule()["margin"] == [0.0, 0.5, 1.0] and pol.lookahead.dtype == np.int64
    with pytest.raises(ValueError, match=r"rule: margin = nan"):
        esac.ESACPolicy(_layout(), _predictor(), margin=np.array([0.1, np.nan]))
