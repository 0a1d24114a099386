"""Training ESAC (thesis 6.8): rollouts (cached), the predictor, its accuracy on held-out
conditions, and its decision rule tuned on the validation conditions (:func:`train_esac`).
The predictor and the controller themselves are :mod:`agents.esac`."""
from __future__ import annotations

import itertools
import time
from pathlib import Path
from typing import Any

from .config import DEFAULT_CACHE_DIR
from .rundir import atomic_write_json
from .seeds import check_seed
from .validation import (choose_decision, oracle_fraction, validation_conditions,
                         validation_references)


def train_esac(cfg: dict[str, Any], out: Path, seed: int, progress: bool, record
               ) -> dict[str, Any]:
    """Rollouts (cached), the predictor, its accuracy on held-out conditions, the rule tuned on the
    validation conditions; writes ``model.pt``, ``accuracy.json``, ``accuracy.png``,
    ``rule_sweep.json``."""
    from agents import esac
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    history = int(cfg["env"]["history"])
    cache = Path(cfg.get("cache_dir", DEFAULT_CACHE_DIR))
    n_train = int(cfg["timesteps"])
    test = cfg["test"]
    val = cfg["validation"]
    check_seed("training", seed, n_train)
    check_seed("test", int(test["seed"]), int(test["episodes"]))
    check_seed("validation", int(val["seed"]), int(val["episodes"]))
    if seed < int(test["seed"]) + int(test["episodes"]) and int(test["seed"]) < seed + n_train:
        raise ValueError(f"training seeds {seed}..{seed + n_train - 1} overlap the held-out test "
                         f"seeds from {test['seed']}: choose another --seed")
    env_cfg: dict[str, Any] = {"history": history}
    for flag in ("observe_rig", "observe_commissioning"):
        if cfg["env"].get(flag):
            env_cfg[flag] = True
    conditions = cfg["env"].get("conditions")
    if conditions:  # the preset's ranges overridden (rollouts, held-out test, validation)
        env_cfg["conditions"] = dict(conditions)
    if cfg.get("rig") is not None:
        env_cfg["rig"] = cfg["rig"]
    rig_cfg = {k: v for k, v in env_cfg.items() if k != "history"}
    layout = CutOffVectorEnv(num_envs=1, **env_cfg).observation_layout()
    t0 = time.perf_counter()
    print(f"rollouts: {n_train} for training, {test['episodes']} held out (cached in {cache})",
          flush=True)
    lags = tuple(int(k) for k in cfg.get("lags", esac.LAGS))
    data = esac.rollouts(cache, n_train, seed, history, cfg["preset"], env_config=rig_cfg,
                         lags=lags, progress=progress)
    held = esac.rollouts(cache, int(test["episodes"]), int(test["seed"]), history, cfg["preset"],
                         env_config=rig_cfg, lags=lags, progress=progress)
    t_data = time.perf_counter() - t0
    stroke = float(layout["features"][0]["scale"])
    fit = cfg["fit"]
    delay_input = bool(fit.get("delay_input", False))
    x, y, mask, episode = esac.samples(data, stroke, delay_input)
    lookahead_s = [float(d) for d in data["lag_s"] if d > 0] if delay_input else []
    net, hist = esac.fit(x, y, mask, hidden=tuple(fit["hidden"]),
                         epochs=int(fit["epochs"]), batch_size=int(fit["batch_size"]),
                         lr=float(fit["lr"]), weight_decay=float(fit.get("weight_decay", 0.0)),
                         seed=seed, patience=int(fit.get("patience", 15)),
                         time_loss=fit.get("time_loss", "mse"), groups=episode,
                         progress=progress, members=int(fit.get("ensemble", 1)))
    pred = esac.ESACPredictor(net, layout, delay_input, lookahead_s)
    acc = esac.accuracy(pred, held)
    atomic_write_json(out / "accuracy.json", acc)
    esac.plot_accuracy(pred, held, out / "accuracy.png",
                       title=f"ESAC on {acc['samples']} held-out rollouts (history {history})")
    print("held-out accuracy: " + ", ".join(
        f"{k} {v:.4g}" for k, v in acc.items() if isinstance(v, float)), flush=True)
    # the rule: tuned on the validation conditions
    conds = validation_conditions(cfg["preset"], int(val["episodes"]), int(val["seed"]),
                                  cfg.get("rig"), conditions)
    grid_cfg = cfg["rule_grid"]
    keys = list(grid_cfg)
    grid = [dict(zip(keys, vals)) for vals in itertools.product(*(grid_cfg[k] for k in keys))]
    t1 = time.perf_counter()
    sweep = esac.sweep_rule(pred, conds, grid, env_config=rig_cfg, seed=int(val["seed"]))
    refs = validation_references(conds, {**env_cfg, "preset": cfg["preset"]}, int(val["seed"]),
                                 cache)
    best = choose_decision(sweep, float(cfg.get("prefer_saving_within", 0.0)),
                           float(cfg.get("max_stall_rate", 0.0)))
    rule = {**esac.RULE_DEFAULTS, **{k: best[k] for k in keys}}
    for r in sweep:
        r["oracle_fraction"] = oracle_fraction(r["return"], refs)
    atomic_write_json(out / "rule_sweep.json", {"grid": sweep, "chosen": best,
                                                "references": refs})
    t_sweep = time.perf_counter() - t1
    meta = {"n_in": int(x.shape[1]), "hidden": list(fit["hidden"]), "layout": layout,
            "delay_input": delay_input, "lookahead_s": lookahead_s,
            "rule": rule, "rig": cfg.get("rig"), "accuracy": acc, "fit": {k: v for k, v in hist.items()
                                                    if k not in ("train", "val")},
            "data": {"train_rollouts": int(data["obs"].shape[0]), "samples": int(x.shape[0]),
                     "seed": seed,
                     "test_rollouts": int(held["obs"].shape[0]), "test_seed": int(test["seed"]),
                     "preset": cfg["preset"], "conditions": conditions or None,
                     "pneugym_sources": esac.source_hash()},
            "provenance": provenance()}
    esac.save(out / "model.pt", net, meta)
    best_frac = oracle_fraction(best["return"], refs)
    print(f"rule tuned on {len(conds)} validation conditions: {rule} -> return "
          f"{best['return']:.4f} (oracle fraction "
          f"{best_frac if best_frac is None else round(best_frac, 3)}), stall "
          f"{best['stall_rate']:.3f}", flush=True)
    return {"model": "model.pt", "train_wall_s": time.perf_counter() - t0,
            "data_wall_s": t_data, "fit_wall_s": hist["fit_wall_s"], "sweep_wall_s": t_sweep,
            "accuracy": acc, "rule": rule, "validation_references": refs,
            "best": {"return": best["return"], "oracle_fraction": best_frac,
                     "stall_rate": best["stall_rate"]},
            "fit": {k: v for k, v in hist.items() if k not in ("train", "val")},
            "loss_history": {"train": hist["train"], "val": hist["val"]},
            "observation_layout": layout, "env_config": env_cfg}
