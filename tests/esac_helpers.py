"""Shared by the tests of agents/esac/: a small observation layout, an untrained predictor,
scripted predictions and model files with chosen metadata."""
from __future__ import annotations

import json

import numpy as np
import torch

from agents import esac
from pneugym.envs.cutoff import CutOffVectorEnv


def obs_layout(history=2):
    return CutOffVectorEnv(num_envs=1, history=history).observation_layout()


def small_predictor(history=2):
    net = esac.make_net(7 * history, (8,))
    return esac.ESACPredictor(net, obs_layout(history))


def prediction(**kw):
    base = {"p_complete": np.array([0.99]), "p_stick": np.array([0.0]),
            "final_position_m": np.array([0.18]), "stroke_time_s": np.array([1.2]),
            "conventional_time_s": np.array([1.2]), "time_increase": np.array([0.0]),
            "wasted_fraction": np.array([0.3]), "wasted_energy_j": np.array([90.0]),
            "energy_conventional_j": np.array([300.0])}
    return {**base, **{k: np.array([v]) for k, v in kw.items()}}


def meta_file(tmp_path, name="m.pt", **changes):
    pred = small_predictor()
    meta = {"n_in": 14, "hidden": [8], "layout": pred.layout, "delay_input": False,
            "lookahead_s": [], "rule": {"margin": 0.05, "lookahead": 0.0}}
    for key, value in changes.items():
        if value is ...:
            meta.pop(key)
        elif key == "rule":
            meta["rule"] = value if not isinstance(value, dict) else {**meta["rule"], **value}
        else:
            meta[key] = value
    torch.save({"format": esac.FORMAT, "state_dict": pred.net.state_dict(),
                "meta": json.dumps(meta)}, tmp_path / name)
    return tmp_path / name
