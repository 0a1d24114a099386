"""The seed ranges: training, validation and test seeds stay below :data:`MAX_TRAINING_SEED`;
evaluation (``pneugym evaluate``) uses the seeds from there up, so no evaluation episode is ever
one that training or tuning saw."""
from __future__ import annotations

MAX_TRAINING_SEED = 1_000_000  # evaluation seeds start here


def check_seed(name: str, seed: int, span: int = 1) -> None:
    """Raise ValueError unless the ``span`` seeds from ``seed`` (the ``name`` seeds: training,
    validation, test) all lie in ``[0, MAX_TRAINING_SEED)``."""
    if not (0 <= seed and seed + span <= MAX_TRAINING_SEED):
        what = f"seed {seed}" if span == 1 else f"seeds {seed}..{seed + span - 1}"
        raise ValueError(f"{name} {what} must lie in [0, {MAX_TRAINING_SEED}): the seeds from "
                         f"{MAX_TRAINING_SEED} up are reserved for evaluation"
                         + (", and seeds are never negative" if seed < 0 else ""))
