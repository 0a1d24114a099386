"""agents.training.validation: the decision row a run acts by."""
import pytest

from agents import training


def test_choose_decision_prefers_saving_within_tolerance():
    rows = [{"rule": "quantile", "value": 0.2, "return": -0.650, "stall_rate": 0.0, "saving": 0.60},
            {"rule": "quantile", "value": 0.1, "return": -0.653, "stall_rate": 0.0, "saving": 0.63},
            {"rule": "hazard", "value": 0.02, "return": -0.652, "stall_rate": 0.1, "saving": 0.70},
            {"rule": "hazard", "value": 0.05, "return": -0.700, "stall_rate": 0.0, "saving": 0.75}]
    assert training.choose_decision(rows)["value"] == 0.2
    assert training.choose_decision(rows, 0.005)["value"] == 0.1  # the stalling one is not chosen
    assert training.choose_decision(rows, 0.1)["value"] == 0.05
    # ESAC's use: rules that stall on validation are excluded first
    assert training.choose_decision(rows, 0.0, max_stall_rate=0.0)["value"] == 0.2
    assert training.choose_decision(rows[2:3] + rows[3:], 0.0, 0.0)["value"] == 0.05
    assert training.choose_decision(rows[2:3], 0.0, 0.0)["value"] == 0.02  # none without: all
    with pytest.raises(ValueError, match="prefer_saving_within"):
        training.choose_decision(rows, -1.0)
    assert training.decision_grids({"rule": "quantile", "grid": [0.5]}) == {"quantile": [0.5]}
