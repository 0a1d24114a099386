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
    """Predictions from a script over time: the objective rises, peaks at step 5, falls."""

    def __init__(self, layout):
        self.layout, self.stroke_m, self.k = layout, 0.18, 0

    def __call__(self, obs):
        j = -abs(self.k - 5) * 0.01
        self.k += 1
        return _pred(wasted_fraction=-j)


def test_lookback_rule_cuts_once_the_predicted_objective_stops_rising():
    lay = _layout()
    pol = esac.ESACPolicy(lay, _Scripted(lay), lookback=1, max_time_increase=1.0, max_stick=1.0)
    obs = np.zeros((1, 14), dtype=np.float32)
    obs[0, 12] = 0.01  # not a fresh episode's first sample
    acts = [int(pol.act(obs)[0]) for _ in range(9)]
    assert acts.index(1) == 6  # the first step after the peak at step 5


def test_save_load_roundtrip_and_refusal(tmp_path):
    pred = _predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout, "rule": {"margin": 0.07}}
    esac.save(tmp_path / "m.pt", pred.net, meta)
    pred2, meta2 = esac.load(tmp_path / "m.pt")
    x = np.random.default_rng(1).random((5, 14)).astype(np.float32)
    np.testing.assert_array_equal(pred.raw(x), pred2.raw(x))
    pol = esac.load_policy(tmp_path / "m.pt", _layout(1))  # stacks its history of 2 itself
    assert pol.rule()["margin"] == 0.07
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
