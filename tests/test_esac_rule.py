"""agents/esac/rule.py: rule parameters (overrides, per-row arrays) are checked, each problem
named."""
import numpy as np
import pytest

from agents import esac
from esac_helpers import meta_file, obs_layout, small_predictor


@pytest.mark.parametrize("kw, match", [
    ({"margin": float("nan")}, "margin = nan"), ({"margin": "abc"}, "margin = 'abc'"),
    ({"lookahead": 0.7}, "lookahead = 0.7"), ({"time_demand_s": -1.0}, "time_demand_s = -1.0"),
    ({"max_stick": -5.0}, "max_stick = -5.0"), ({"w_stall": float("inf")}, "w_stall = inf"),
    ({"hysteresis": None}, "hysteresis = None"),
])
def test_rule_overrides_are_checked(tmp_path, kw, match):
    f = meta_file(tmp_path)
    with pytest.raises(ValueError, match=f"m.pt: the rule override: {match}: expected"):
        esac.load_policy(f, obs_layout(1), **kw)
    with pytest.raises(ValueError, match=f"rule: {match}"):  # the controller checks them too
        esac.ESACPolicy(obs_layout(), small_predictor(), **kw)


def test_rule_arrays_are_checked_per_row():
    pol = esac.ESACPolicy(obs_layout(), small_predictor(), margin=np.array([0.0, 0.5, 1.0]),
                          lookahead=np.array([0.0, 0.0, 0.0]))
    assert pol.rule()["margin"] == [0.0, 0.5, 1.0] and pol.lookahead.dtype == np.int64
    with pytest.raises(ValueError, match=r"rule: margin = nan"):
        esac.ESACPolicy(obs_layout(), small_predictor(), margin=np.array([0.1, np.nan]))
