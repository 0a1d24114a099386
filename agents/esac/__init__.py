"""ESAC, the Energy Saving Actuation Control the thesis proposes in 6.8 but never builds: a neural
network that, from the current sensor history, predicts what would happen if the supply were cut
**now** (or after a short delay), and a controller that cuts at the first instant the prediction
says the stroke completes with a safety margin and within the time demand, and that waiting
longer no longer pays.

**Predictor** (:class:`ESACNet`, :class:`ESACPredictor`). Input: the observation of
``pneugym/CutOff-v0`` with ``history=k`` (the last ``k`` samples of position, velocity, both port
pressures, supply set-point, time, cut flag) and, for a model with ``delay_input``, the delay
``Δ`` [s] before the cut. Outputs, for a cut at ``now + Δ``:

- ``p_complete``: probability that the piston still reaches the end of stroke;
- ``final_position_m``: where it ends (the stroke length if it completes);
- ``stroke_time_s``: when it arrives (from the extend command), if it completes;
- ``conventional_time_s``: when it would arrive without a cut (so ``time_increase`` =
  ``stroke_time_s / conventional_time_s - 1`` needs nothing the controller cannot see);
- ``wasted_fraction`` and ``wasted_energy_j``: the air energy left in the driving side (eq. 5.9),
  as a fraction of a conventional stroke's and in joules;
- ``p_stick``: probability of a stick-slip event on the way.

**Training data** (:func:`generate_rollouts`): episodes of the batched environment over the
``randomized`` conditions, each cut off at a random time; the episode's final figures label the
observation at the cut (``Δ = 0``) and the observations ``LAGS`` control periods before it (the
same outcome seen ``Δ`` earlier: before the cut an episode is the uncut one). Cached on disk
(:func:`rollouts`), keyed by the generator's settings and a hash of the plant's sources.

**Controller** (:class:`ESACPolicy`): cut when ``p_complete >= 1 - margin``, the predicted final
position is within ``tolerance_m`` of the stroke end, the predicted time increase is at most
``max_time_increase`` (the time demand), ``p_stick <= max_stick`` and, with ``lookahead``, no
predicted later cut (``Δ`` in the training lags) scores a better objective. ``margin`` is the
safety margin: the accepted predicted risk of an incomplete stroke. train.py tunes the rule on
validation conditions (training seeds), ``agents.training.choose_decision``.

Modules, by job (each name below is also importable from ``agents.esac``):

- :mod:`~agents.esac.data`: rollouts and their cache, the network's samples and targets;
- :mod:`~agents.esac.model`: the network, its fit, :class:`ESACPredictor`;
- :mod:`~agents.esac.modelfile`: ``model.pt``: save, load, the checks of its metadata;
- :mod:`~agents.esac.rule`: the rule's parameters, defaults and their check;
- :mod:`~agents.esac.policy`: :class:`ESACPolicy`, :func:`load_policy`, :func:`sweep_rule`;
- :mod:`~agents.esac.report`: prediction accuracy on held-out rollouts and its plots.

Imports flow one way: ``data``, ``model`` and ``rule`` import no other module of the package;
``modelfile`` imports ``model`` and ``rule``; ``report`` imports ``model``; ``policy`` imports
``model``, ``modelfile`` and ``rule``.
"""
from __future__ import annotations

from .data import (
    GENERATOR_VERSION,
    LAGS,
    generate_rollouts,
    rollouts,
    samples,
    source_hash,
    targets,
)
from .model import (
    CLASS_HEADS,
    ENSEMBLE_COMBINE,
    MAX_MEMBERS,
    REG_HEADS,
    ESACPredictor,
    ensemble_of,
    fit,
    is_ensemble,
    make_net,
)
from .modelfile import (
    FORMAT,
    MAX_FILE_BYTES,
    MAX_HIDDEN_LAYERS,
    MAX_HIDDEN_WIDTH,
    MAX_META_BYTES,
    is_esac_file,
    load,
    save,
    torch_isfinite_all,
)
from .policy import ESACPolicy, load_policy, sweep_rule
from .report import accuracy, plot_accuracy
from .rule import RULE_DEFAULTS, RULE_PARAMETERS, check_rule

__all__ = [
    "CLASS_HEADS", "ENSEMBLE_COMBINE", "FORMAT", "GENERATOR_VERSION", "LAGS", "MAX_FILE_BYTES", "MAX_HIDDEN_LAYERS",
    "MAX_HIDDEN_WIDTH", "MAX_MEMBERS", "MAX_META_BYTES", "REG_HEADS", "RULE_DEFAULTS", "RULE_PARAMETERS",
    "ESACPolicy", "ESACPredictor", "accuracy", "check_rule", "ensemble_of", "fit", "generate_rollouts",
    "is_ensemble", "is_esac_file", "load", "load_policy", "make_net", "plot_accuracy", "rollouts", "samples",
    "save", "source_hash", "sweep_rule", "targets", "torch_isfinite_all",
]
