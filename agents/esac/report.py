"""How well an ESAC predictor predicts: errors on held-out rollouts (:func:`accuracy`,
``accuracy.json``) and predicted-against-simulated plots (:func:`plot_accuracy`,
``accuracy.png``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .model import ESACPredictor


def accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Prediction errors on a rollout set (held-out conditions): completion accuracy, final
    position, stroke time, time increase and wasted energy."""
    p = pred(data["obs"])
    comp = data["completed"].astype(bool)
    c_hat = p["p_complete"] >= 0.5
    stall = ~comp
    out: dict[str, Any] = {
        "samples": int(comp.size), "completed_share": float(comp.mean()),
        "completion_accuracy": float((c_hat == comp).mean()),
        "false_complete_rate": float((c_hat & stall).sum() / max(1, stall.sum())),
        "final_position_mae_mm": float(np.mean(np.abs(p["final_position_m"]
                                                      - data["final_position_m"])) * 1e3),
        "final_position_mae_mm_incomplete": float(np.mean(np.abs(
            p["final_position_m"][stall] - data["final_position_m"][stall])) * 1e3)
        if stall.any() else None,
        "wasted_fraction_mae": float(np.mean(np.abs(
            p["wasted_fraction"] - data["energy_wasted_j"] / data["energy_conventional_j"]))),
        "wasted_energy_mae_j": float(np.mean(np.abs(p["wasted_energy_j"]
                                                    - data["energy_wasted_j"]))),
        "conventional_time_mae_ms": float(np.mean(np.abs(p["conventional_time_s"]
                                                         - data["conventional_time_s"])) * 1e3),
        "stick_accuracy": float(((p["p_stick"] >= 0.5) == (data["stick_slip_events"] > 0))
                                .mean()),
    }
    if comp.any():
        t_true = data["stroke_time_s"][comp]
        ti_true = t_true / data["conventional_time_s"][comp] - 1.0
        err = p["stroke_time_s"][comp] - t_true
        out.update(
            stroke_time_mae_ms=float(np.mean(np.abs(err)) * 1e3),
            stroke_time_median_ae_ms=float(np.median(np.abs(err)) * 1e3),
            stroke_time_mape=float(np.mean(np.abs(err) / t_true)),
            time_increase_mae=float(np.mean(np.abs(p["time_increase"][comp] - ti_true))))
        # the region the controller decides in: completing cuts with at most +50 % time
        near = ti_true <= 0.5
        if near.any():
            out["stroke_time_mae_ms_within_50pct"] = float(np.mean(np.abs(err[near])) * 1e3)
            out["time_increase_mae_within_50pct"] = float(np.mean(np.abs(
                p["time_increase"][comp][near] - ti_true[near])))
    if pred.delay_input and "obs_lag" in data:
        out["by_delay"] = [_delay_accuracy(pred, data, j) for j in range(len(data["lag_s"]))]
    return out


def _delay_accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray], j: int
                    ) -> dict[str, Any]:
    """Errors of the predictions made ``lag_s[j]`` before the cut (lookahead rule's inputs)."""
    ok = ~np.isnan(data["obs_lag"][:, j, 0])
    delay = float(data["lag_s"][j])
    if not ok.any():  # no cut came this long after the episode began
        return {"delay_s": delay, "samples": 0}
    p = pred(data["obs_lag"][ok, j], delay)
    comp = data["completed"][ok].astype(bool)
    wf = data["energy_wasted_j"][ok] / data["energy_conventional_j"][ok]
    row = {"delay_s": delay, "samples": int(ok.sum()),
           "completion_accuracy": float(((p["p_complete"] >= 0.5) == comp).mean()),
           "wasted_fraction_mae": float(np.mean(np.abs(p["wasted_fraction"] - wf)))}
    ti = data["stroke_time_s"][ok][comp] / data["conventional_time_s"][ok][comp] - 1.0
    near = ti <= 0.5
    if near.any():
        row["time_increase_mae_within_50pct"] = float(np.mean(np.abs(
            p["time_increase"][comp][near] - ti[near])))
    return row


def plot_accuracy(pred: ESACPredictor, data: Mapping[str, np.ndarray], path: str | Path,
                  title: str = "ESAC on held-out conditions") -> None:
    """Predicted vs simulated: completion probability vs cut time, final position, stroke time
    and wasted energy (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = pred(data["obs"])
    comp = data["completed"].astype(bool)
    fig, ax = plt.subplots(2, 2, figsize=(9, 7.5))
    rel_t = data["t_cut"] / data["conventional_time_s"]
    ax[0, 0].scatter(rel_t[comp], p["p_complete"][comp], s=3, alpha=0.3, label="completed")
    ax[0, 0].scatter(rel_t[~comp], p["p_complete"][~comp], s=3, alpha=0.3, label="incomplete")
    ax[0, 0].set_xlabel("cut time / conventional stroke time")
    ax[0, 0].set_ylabel("predicted P(complete)")
    ax[0, 0].legend(fontsize=8, markerscale=3)
    s = pred.stroke_m * 1e3
    ax[0, 1].scatter(data["final_position_m"] * 1e3, p["final_position_m"] * 1e3, s=3, alpha=0.3)
    ax[0, 1].plot([0, s], [0, s], "k--", lw=0.8)
    ax[0, 1].set_xlabel("final position, simulated [mm]")
    ax[0, 1].set_ylabel("predicted [mm]")
    t = data["stroke_time_s"][comp]
    ax[1, 0].scatter(t, p["stroke_time_s"][comp], s=3, alpha=0.3)
    lim = [float(np.nanmin(t)), float(min(np.nanmax(t), 4.0))] if comp.any() else [0, 4]
    ax[1, 0].plot(lim, lim, "k--", lw=0.8)
    ax[1, 0].set_xlabel("stroke time, simulated [s] (completed strokes)")
    ax[1, 0].set_ylabel("predicted [s]")
    wf = data["energy_wasted_j"] / data["energy_conventional_j"]
    ax[1, 1].scatter(wf, p["wasted_fraction"], s=3, alpha=0.3)
    ax[1, 1].plot([0, 1.05], [0, 1.05], "k--", lw=0.8)
    ax[1, 1].set_xlabel("wasted energy / conventional, simulated")
    ax[1, 1].set_ylabel("predicted")
    for a in ax.flat:
        a.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

