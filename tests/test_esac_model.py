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
