"""Discrepancy workflow (issue 5): find where simulation and measurement disagree, name the
missing effect, add it to the model and show the gap shrink.

Python API: :class:`Discrepancy` (``fit`` / ``report`` / ``predict`` / ``score``); command line:
``python -m pneugym.discrepancy PATH... --out DIR``. The friction-only path for force-velocity
data (thesis Table 5.1) is :class:`FrictionDiscrepancy`; the thesis's expansion-index puzzle is
:func:`expansion_index`.
"""
from .candidates import CANDIDATES, MORE_CANDIDATES, Candidate, FitParam, separating_experiment
from .residuals import CHANNELS, PHASES, estimate_noise, nrmse, run_phases
from .stats import effective_sample_size
from .workflow import CandidateResult, Discrepancy

__all__ = ["CANDIDATES", "MORE_CANDIDATES", "CHANNELS", "PHASES", "Candidate", "CandidateResult", "Discrepancy",
           "FitParam", "effective_sample_size", "estimate_noise", "nrmse", "run_phases",
           "separating_experiment"]
