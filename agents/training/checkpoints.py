"""Continuing from a checkpoint: the model loaded without unpickling anything, with the
schedules of its run's configuration (:func:`load_checkpoint`), and DQN's replay buffer refilled
(:func:`restore_replay_buffer`)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from .rundir import replay_file


def _resume_schedules(kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """The schedules a resumed model takes from its run's config (``kwargs``: the algorithm's
    keywords, ``learning_rate`` already a schedule, :func:`agents.training.sb3._schedule`); the
    others get SB3's defaults (:func:`agents.safe_load.replacements`)."""
    out = {k: kwargs[k] for k in ("learning_rate", "clip_range", "clip_range_vf") if k in kwargs}
    if "train_freq" in kwargs:
        tf = kwargs["train_freq"]
        out["train_freq"] = tuple(tf) if isinstance(tf, list) else tf
    return out


def load_checkpoint(cls, algo: str, path: Path, venv, kwargs: Mapping[str, Any],
                    layout: Mapping[str, Any]):
    """The checkpoint at ``path`` on ``venv``, loaded without unpickling anything
    (:func:`agents.safe_load.load_sb3`), its schedules from the run's config; refused with a
    :class:`~agents.learned.LayoutMismatchError` if it was trained on another layout."""
    from agents.learned import check_layout
    from agents.safe_load import load_sb3

    model = load_sb3(path, algo, cls=cls, env=venv, schedules=_resume_schedules(kwargs))
    old = model.__dict__.get("pneugym_layout")
    if old is not None and old != layout:
        check_layout(old, layout, f"checkpoint {path}")
    return model


def restore_replay_buffer(model, ckpt: Path, trust_pickle: bool = False) -> None:
    """Refill a resumed DQN's replay buffer from the arrays saved with checkpoint ``ckpt``. A
    pickled buffer (``.pkl``, older runs) is loaded only with ``trust_pickle`` (a pickle can run
    code); otherwise the run continues with an empty buffer, and says so."""
    from agents.safe_load import load_replay_buffer

    npz, pkl = replay_file(ckpt), replay_file(ckpt, ".pkl")
    if npz.is_file():
        n = load_replay_buffer(model.replay_buffer, npz)
        print(f"replay buffer restored from {npz} ({n} transitions)", flush=True)
    elif pkl.is_file() and trust_pickle:
        print(f"loading the pickled replay buffer {pkl} (--trust-pickled-replay-buffer)",
              flush=True)
        model.load_replay_buffer(pkl)
    elif pkl.is_file():
        print(f"{pkl} is a pickled replay buffer (older pneugym), which can run code when "
              f"loaded: not loaded; continuing with an empty replay buffer. If the run is your "
              f"own, pass --trust-pickled-replay-buffer to load it.", flush=True)
