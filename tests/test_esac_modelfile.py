"""agents/esac/modelfile.py: a saved model loads back, and a damaged or foreign file, bad
metadata or damaged weights are refused with the file and key named."""
import json

import numpy as np
import pytest
import torch

from agents import esac
from agents.base import run_first_episodes
from esac_helpers import meta_file, obs_layout, small_predictor
from pneugym.envs import Conditions
from pneugym.envs.cutoff import CutOffVectorEnv


def test_save_load_roundtrip_and_refusal(tmp_path):
    pred = small_predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout, "rule": {"margin": 0.07}}
    esac.save(tmp_path / "m.pt", pred.net, meta)
    pred2, meta2 = esac.load(tmp_path / "m.pt")
    x = np.random.default_rng(1).random((5, 14)).astype(np.float32)
    np.testing.assert_array_equal(pred.raw(x), pred2.raw(x))
    pol = esac.load_policy(tmp_path / "m.pt", obs_layout(1))  # stacks its history of 2 itself
    assert pol.rule()["margin"] == 0.07
    over = esac.load_policy(tmp_path / "m.pt", obs_layout(1), max_time_increase=0.1)
    assert over.rule()["max_time_increase"] == 0.1 and over.rule()["margin"] == 0.07
    with pytest.raises(ValueError, match="unknown ESAC rule parameter.*'marjin'"):
        esac.load_policy(tmp_path / "m.pt", obs_layout(1), marjin=0.1)
    # the reloaded controller decides as one built on the predictor it was saved from
    from agents.esac.policy import RULE_DEFAULTS, ESACPolicy

    direct = ESACPolicy(obs_layout(1), pred, **{**RULE_DEFAULTS, "margin": 0.07})
    conds = [Conditions(), Conditions(load_mass_kg=25.0, supply_pressure_gauge_pa=1.5e5)]
    runs = [run_first_episodes(CutOffVectorEnv(num_envs=2, autoreset=False), p, conds, 1_000_000)
            for p in (pol, direct)]
    for key in ("objective", "cutoff_time_s"):
        assert list(runs[0][key]) == list(runs[1][key]), key
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
    pred = small_predictor()
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
# metadata: checked, each problem named with the file and key
# ------------------------------------------------------------------------------------------------
def _without_position():
    lay = dict(obs_layout())
    lay["features"] = [f for f in lay["features"] if f["name"] != "position"]
    lay["size"] = 12
    return lay


@pytest.mark.parametrize("changes, match", [
    ({"layout": {}}, r"its metadata's layout has no 'features'"),
    ({"layout": "x"}, r"its metadata's layout is 'x'; expected an object"),
    ({"layout": ...}, r"its metadata's layout is None"),
    ({"layout": _without_position()}, r"features \[.*\] lack \['position'\]"),
    ({"layout": {**obs_layout(), "features": "abc"}}, r"features is 'abc'"),
    ({"layout": {**obs_layout(), "history": 0}}, r"history is 0"),
    ({"n_in": 15}, r"its metadata's n_in is 15; expected 14: the layout's size 14"),
    ({"n_in": True}, r"n_in is True"),
    ({"hidden": [10 ** 5] * 3}, r"hidden is \[100000, 100000, 100000\]; expected a list of at "
                                r"most 16 layer widths from 1 to 4096"),
    ({"hidden": [4096] * 16}, r"describes a network .* of [\d,]+ bytes of weights, but the file "
                              r"holds"),
    ({"members": 0}, r"members is 0; expected the ensemble's number of networks, an integer "
                     r"from 1 to 32"),
    ({"members": 33}, r"members is 33"),
    ({"members": 2}, r"do not fit the network its metadata describes \(n_in 14, hidden \[8\], "
                     r"2 members\)"),
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
    f = meta_file(tmp_path, **changes)
    with pytest.raises(ValueError, match=f"m.pt: .*{match}"):
        esac.load_policy(f, obs_layout(1))


def test_damaged_weights_are_named(tmp_path):
    pred = small_predictor()
    state = pred.net.state_dict()
    for key, value in (("in_std", torch.zeros_like(state["in_std"])),
                       ("body.0.weight", torch.full_like(state["body.0.weight"], float("nan")))):
        bad = dict(state, **{key: value})
        torch.save({"format": esac.FORMAT, "state_dict": bad, "meta": __import__("json").dumps(
            {"n_in": 14, "hidden": [8], "layout": pred.layout})}, tmp_path / "w.pt")
        with pytest.raises(ValueError, match=f"w.pt: its weights \\['{key}'\\] hold NaN"):
            esac.load(tmp_path / "w.pt")


def test_saved_rule_values_are_normalised_and_applied(tmp_path):
    f = meta_file(tmp_path, rule={"lookahead": 0.0, "time_demand_s": 1.5})
    pol = esac.load_policy(f, obs_layout(1))
    assert pol.rule()["lookahead"] == 0 and pol.rule()["time_demand_s"] == 1.5
