"""Evaluating cut-off policies on the pneugym suites: ``pneugym evaluate`` (or ``python
evaluate.py``) is the command line (:mod:`agents.evaluation.cli`); :func:`evaluate` is the same
in Python, returning the ``results.json`` structure.

- :mod:`~agents.evaluation.suites`: the ``nominal`` and ``robustness`` suites and their seeded
  episodes;
- :mod:`~agents.evaluation.specs`: the policies to run (``NAME``, ``NAME=PATH[:key=value,...]``),
  checked and loaded before any work, learned ones trained on demand;
- :mod:`~agents.evaluation.run`: every policy on the same episodes, and the metrics;
- :mod:`~agents.evaluation.outputs`: the printed table, ``results.json``, ``results.csv``;
  :mod:`~agents.evaluation.plots`: the plots.
"""
from .outputs import print_table, write_outputs
from .plots import plot_examples, plot_results
from .run import evaluate, run_policy, summarize
from .specs import (DEFAULT_POLICIES, LEARNED, RESERVED, check_policy_specs, load_models,
                    make_named_policy, parse_spec, resolve_learned)
from .suites import EVAL_SEED, LOADS_KG, NOISE, SUPPLIES_BAR, suite_cells, suite_episodes

__all__ = ["evaluate", "run_policy", "summarize", "print_table", "write_outputs",
           "plot_results", "plot_examples", "DEFAULT_POLICIES", "LEARNED", "RESERVED",
           "check_policy_specs", "load_models", "make_named_policy", "parse_spec",
           "resolve_learned", "EVAL_SEED", "LOADS_KG", "NOISE", "SUPPLIES_BAR", "suite_cells",
           "suite_episodes"]
