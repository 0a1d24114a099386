"""agents/esac/data.py: the rollouts (the observations at the cut and before it, the final
figures, the cache) and the network's samples and targets."""
import numpy as np

from agents import esac


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
    # condition overrides (a training config's env.conditions): drawn within them, cached apart
    hi = esac.rollouts(tmp_path, 12, 3, history=2, progress=False, env_config={
        "conditions": {"supply_pressure_gauge_pa": (5e5, 6e5), "load_mass_kg": 35.0}})
    assert np.all((hi["supply_pressure_gauge_pa"] >= 5e5) & (hi["supply_pressure_gauge_pa"] <= 6e5))
    assert np.all(hi["load_mass_kg"] == 35.0)
    assert len(list(tmp_path.glob("esac-rollouts-*.npz"))) == 2


def test_samples_are_one_per_recorded_lag():
    """One sample per recorded lag, the delay last, the episode's targets repeated; without
    the delay input the observations at the cut only."""
    obs = np.random.default_rng(0).random((3, 14)).astype(np.float32)
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
