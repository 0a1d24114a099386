"""Cut-off policies with one SB3-like interface,
``predict(obs, state=None, episode_start=None, deterministic=True) -> (action, state)``:

- :class:`~agents.baselines.ConventionalPolicy` (never cuts),
  :class:`~agents.baselines.EndStrokePolicy` (cuts at the end of stroke);
- :class:`~agents.gaslaw.GasLawPolicy`: the thesis's predictor (eq. 5.1) with K calibrated per
  supply pressure;
- :class:`~agents.oracle.OraclePolicy`: the best single cut-off time, found with privileged access
  to the episode's conditions (an upper bound for latched policies).

:func:`make_policy` builds one by name for an environment.
"""
from .base import ObservationReader, Policy
from .baselines import ConventionalPolicy, EndStrokePolicy
from .gaslaw import GasLawPolicy
from .oracle import OraclePolicy
from .registry import BASELINES, make_policy

__all__ = ["Policy", "ObservationReader", "ConventionalPolicy", "EndStrokePolicy",
           "GasLawPolicy", "OraclePolicy", "BASELINES", "make_policy"]
