"""Cut-off policies with one SB3-like interface,
``predict(obs, state=None, episode_start=None, deterministic=True) -> (action, state)``:

- :class:`~agents.baselines.ConventionalPolicy` (never cuts),
  :class:`~agents.baselines.EndStrokePolicy` (cuts at the end of stroke);
- :class:`~agents.gaslaw.GasLawPolicy`: the thesis's predictor (eq. 5.1) with K calibrated per
  supply pressure;
- :class:`~agents.oracle.OraclePolicy`: the best single cut-off time, found with privileged access
  to the episode's conditions (an upper bound for latched policies);
- :class:`~agents.mpc.ModelPredictivePolicy`: fits the rig to the stroke so far and runs the
  plant ahead to cut at the best time (not privileged, not trained);
- :class:`~agents.mpc_rig.RigModelPolicy` (``mpc-rig``): plans its cut on a model of the rig
  fitted to two commissioning strokes (:mod:`pneugym.commission`);
- learned (train.py): :class:`~agents.esac.ESACPolicy`, the thesis's proposed neural predictor
  (6.8), and :class:`~agents.learned.SB3Policy` for stable-baselines3 models.

:func:`make_policy` builds a baseline by name for an environment; :func:`load_policy` loads a
trained model (checking its observation layout against the environment's).
"""
from .base import ObservationReader, Policy
from .baselines import ConventionalPolicy, EndStrokePolicy
from .esac import ESACPolicy, ESACPredictor
from .gaslaw import GasLawPolicy
from .learned import LayoutMismatchError, LearnedPolicy, SB3Policy
from .mpc import ModelPredictivePolicy
from .mpc_rig import RigModelPolicy
from .oracle import OraclePolicy
from .registry import BASELINES, load_policy, make_policy

__all__ = ["Policy", "ObservationReader", "ConventionalPolicy", "EndStrokePolicy",
           "GasLawPolicy", "OraclePolicy", "ModelPredictivePolicy", "RigModelPolicy",
           "BASELINES", "make_policy", "load_policy",
           "LearnedPolicy", "SB3Policy", "ESACPolicy", "ESACPredictor", "LayoutMismatchError"]
