"""Training the learned cut-off policies: stable-baselines3 PPO and DQN on the batched
environment, and the ESAC neural predictor (thesis 6.8). ``pneugym train`` (or ``python
train.py``) is the command line (:mod:`agents.training.cli`); :func:`train` is the same in Python.

One job per module, in the order a run meets them:

- :mod:`~agents.training.config`: ``configs/<algo>.yaml``, budgets and ``--set`` overrides, checked
  whole before anything is written (which key takes which value: :mod:`~agents.training.schema`,
  built from the value checks of :mod:`~agents.training.checks`); :mod:`~agents.training.seeds`:
  the training seeds stay below 1,000,000;
- :mod:`~agents.training.rundir`: the run folder, ``run.json`` and atomic writes;
  :mod:`~agents.training.resume`: ``--resume``, ``--force`` or a refusal for a folder that holds
  something;
- :mod:`~agents.training.trainer`: :func:`train`, one run from configuration to a finished
  ``run.json``; :mod:`~agents.training.signals`: SIGINT and SIGTERM as a clean stop;
- :mod:`~agents.training.sb3`: PPO and DQN (with :mod:`~agents.training.callbacks` and
  :mod:`~agents.training.checkpoints`); :mod:`~agents.training.esac`: ESAC;
- :mod:`~agents.training.validation`: the validation conditions, their references, the oracle
  fraction and the tuning of a model's decision rule;
- :mod:`~agents.training.ondemand`: evaluation's train-on-demand (:func:`ensure_trained`).

Importing this package loads neither torch nor stable-baselines3 (training does).
"""
from .config import ALGOS, CONFIG_DIR, ConfigError, check_config, load_config
from .ondemand import DEFAULT_POLICIES, NAMED_RUNS, ensure_trained, model_path, training_plan
from .rundir import RUN_FILE, atomic_write_json, read_run, replay_file, run_files
from .seeds import MAX_TRAINING_SEED, check_seed
from .signals import StopRequest, TrainingInterrupted, stop_on_signals
from .trainer import train
from .validation import (TrainingRangeWarning, choose_decision, decision_grids,
                         operating_point_outside, oracle_fraction, sweep_decisions,
                         validation_conditions, validation_references)

__all__ = ["ALGOS", "CONFIG_DIR", "ConfigError", "check_config", "load_config", "DEFAULT_POLICIES",
           "NAMED_RUNS",
           "ensure_trained", "model_path", "training_plan", "RUN_FILE", "atomic_write_json",
           "read_run", "replay_file", "run_files", "MAX_TRAINING_SEED", "check_seed",
           "StopRequest", "TrainingInterrupted", "stop_on_signals", "train", "choose_decision",
           "decision_grids", "oracle_fraction", "sweep_decisions", "validation_conditions",
           "validation_references", "TrainingRangeWarning", "operating_point_outside"]
