"""agents/esac/policy.py: the cut-off rule of thesis 6.8 (margin, time demand, stick-slip risk)
and its lookahead."""
import numpy as np
import pytest

from agents import esac
from esac_helpers import obs_layout, prediction, small_predictor


def test_rule_needs_completion_with_margin_time_demand_and_stick_risk():
    pol = esac.ESACPolicy(obs_layout(), small_predictor(), margin=0.05, max_time_increase=0.2,
                          max_stick=0.5)
    assert pol.decide(prediction())[0]
    assert not pol.decide(prediction(p_complete=0.9))[0]          # inside the safety margin
    assert not pol.decide(prediction(final_position_m=0.17))[0]   # short of the stroke end
    assert not pol.decide(prediction(time_increase=0.3))[0]       # beyond the time demand
    assert not pol.decide(prediction(p_stick=0.6))[0]
    wide = esac.ESACPolicy(obs_layout(), small_predictor(), margin=0.2)
    assert wide.decide(prediction(p_complete=0.9))[0]
    absolute = esac.ESACPolicy(obs_layout(), small_predictor(), time_demand_s=1.3)
    assert absolute.decide(prediction(stroke_time_s=1.25, time_increase=5.0))[0]
    assert not absolute.decide(prediction(stroke_time_s=1.35))[0]
    assert pol.rule()["margin"] == 0.05
    with pytest.raises(ValueError, match="margin"):
        esac.ESACPolicy(obs_layout(), small_predictor(), margin=1.5)


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
            return prediction(wasted_fraction=abs(k - 5) * 0.01)
        ks = self.k - 1 + np.asarray(delay_s) / 0.005
        return {key: np.full((1, ks.size), v[0]) for key, v in prediction().items()} | {
            "wasted_fraction": np.abs(ks - 5)[None, :] * 0.01}


def test_lookahead_rule_cuts_once_no_later_cut_predicts_better():
    lay = obs_layout()
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
        esac.ESACPolicy(lay, small_predictor(), lookahead=1)
