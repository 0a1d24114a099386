"""agents/esac/model.py: the ESAC predictor learns a known relation; predictions with and
without the delay input."""
import numpy as np
import pytest
import torch

from agents import esac
from esac_helpers import obs_layout, small_predictor


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


def test_delay_input_predictor_shapes():
    lay = obs_layout()
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
        small_predictor()(obs, [0.01])


def _data(n=400, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 14)).astype(np.float32)
    y = np.zeros((n, 7), np.float32)
    y[:, 0], y[:, 1] = rng.random(n) > 0.5, rng.random(n) > 0.8
    y[:, 2:] = rng.normal(size=(n, 5)) + x[:, :5]
    return x, y, np.ones_like(y)


def test_ensemble_member_zero_is_the_single_fit_and_heads_combine_as_stated():
    """fit(members=3): member 0 is the single network of the same seed, to the last bit; the
    members share the normalisation; each output is the worst member's where the rule reads
    it for safety or objective (ENSEMBLE_COMBINE) and the mean elsewhere."""
    torch.set_num_threads(1)
    x, y, m = _data()
    single, _ = esac.fit(x, y, m, hidden=(8,), epochs=3, seed=3, progress=False)
    ens, hist = esac.fit(x, y, m, hidden=(8,), epochs=3, seed=3, progress=False, members=3)
    assert esac.is_ensemble(ens) and not esac.is_ensemble(single)
    assert len(hist["members"]) == 3 and hist["best_val"] == pytest.approx(
        np.mean([h["best_val"] for h in hist["members"]]))
    for a, b in zip(ens.members[0].state_dict().values(), single.body.state_dict().values()):
        assert torch.equal(a, b)
    assert torch.equal(ens.in_mean, single.in_mean) and torch.equal(ens.out_std, single.out_std)
    assert not torch.equal(ens.members[1][0].weight, ens.members[2][0].weight)
    xt = torch.as_tensor(x[:50])
    with torch.no_grad():
        every, out = ens.all_outputs(xt), ens(xt)
        np.testing.assert_array_equal(every[0].numpy(), single(xt).numpy())
    heads = (*esac.CLASS_HEADS, *esac.REG_HEADS)
    reduce = {"min": lambda t: t.min(0).values, "max": lambda t: t.max(0).values,
              "mean": lambda t: t.mean(0)}
    for k, head in enumerate(heads):
        torch.testing.assert_close(out[:, k], reduce[esac.ENSEMBLE_COMBINE[head]](every[:, :, k]))
    assert esac.ENSEMBLE_COMBINE["complete"] == "min"           # the least sure to complete
    assert esac.ENSEMBLE_COMBINE["log_time_ratio"] == "max"     # the slowest stroke


def test_ensemble_predicts_the_worst_member_where_members_disagree():
    """Two members that agree but for the time ratio: the predictor takes the longer stroke and
    the same completion probability."""
    lay = obs_layout()
    ens = esac.make_net(14, (8,), members=2)
    with torch.no_grad():
        ens.members[1].load_state_dict(ens.members[0].state_dict())
        ens.members[1][-1].bias[2 + esac.REG_HEADS.index("log_time_ratio")] += 0.5
    obs = np.random.default_rng(1).random((4, 14)).astype(np.float32)
    p = esac.ESACPredictor(ens, lay)(obs)
    one = esac.make_net(14, (8,))
    one.body.load_state_dict(ens.members[0].state_dict())
    q = esac.ESACPredictor(one, lay)(obs)
    np.testing.assert_allclose(p["p_complete"], q["p_complete"], rtol=1e-6)
    assert np.all(p["time_increase"] > q["time_increase"] + 0.3)


def test_ensemble_saves_loads_and_fine_tunes_member_by_member(tmp_path):
    torch.set_num_threads(1)
    x, y, m = _data()
    lay = obs_layout()
    ens, _ = esac.fit(x, y, m, hidden=(8,), epochs=2, seed=1, progress=False, members=2)
    meta = {"n_in": 14, "hidden": [8], "layout": lay, "delay_input": False, "lookahead_s": []}
    esac.save(tmp_path / "m.pt", ens, meta)
    pred, saved = esac.load(tmp_path / "m.pt")
    assert saved["members"] == 2 and esac.is_ensemble(pred.net)
    a, b = esac.ESACPredictor(ens, lay)(x[:20]), pred(x[:20])
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    tuned, hist = esac.fit(x, y, m, hidden=(8,), epochs=1, seed=5, progress=False, init=ens)
    assert esac.is_ensemble(tuned) and len(tuned.members) == 2 and len(hist["members"]) == 2
    assert torch.equal(tuned.in_mean, ens.in_mean)  # the units it was trained in
    assert not torch.equal(tuned.members[1][0].weight, ens.members[1][0].weight)
    with pytest.raises(ValueError, match="1 to 32"):
        esac.fit(x, y, m, hidden=(8,), epochs=1, progress=False, members=0)
    with pytest.raises(ValueError, match="pass it as init"):
        esac.fit(x, y, m, hidden=(8,), epochs=1, progress=False, members=2, init=ens.member(0))
