"""The plots of an evaluation: energy saved against stroke-time increase per suite, the
robustness heatmaps (saving and oracle fraction per load and supply) and one nominal episode's
trajectories under each baseline."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents import BASELINES, make_policy
from pneugym.envs import Conditions

from .suites import EVAL_SEED, LOADS_KG, SUPPLIES_BAR


def plot_results(results: dict[str, Any], out: Path) -> None:
    """Every plot of ``results`` into the folder ``out``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for suite, s in results["suites"].items():
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for name in s["policies"]:
            rec = [r for r in s["episodes"] if r["policy"] == name and r["completed"]]
            x = [100 * r["time_increase"] for r in rec]
            y = [100 * r["saving_ratio"] for r in rec]
            pts = ax.scatter(x, y, s=10, alpha=0.35)
            p = s["policies"][name]
            if p["time_increase_mean"] is not None:
                ax.scatter(100 * p["time_increase_mean"], 100 * p["saving_mean"], s=90,
                           marker="*", color=pts.get_facecolor()[0], edgecolor="k",
                           label=name)
        ax.set_xlabel("stroke-time increase [%]")
        ax.set_ylabel("energy saved (eq. 5.10) [%]")
        ax.set_title(f"{suite} suite: episodes and means (stars)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.savefig(out / f"{suite}_saving_vs_time.png", dpi=120, bbox_inches="tight")
        plt.close(fig)
    for suite, s in results["suites"].items():
        if any("per_rig" in p for p in s["policies"].values()):
            plot_per_rig(suite, s, out)
    rob = results["suites"].get("robustness")
    if rob:
        names = list(rob["policies"])
        fig, axes = plt.subplots(2, len(names), figsize=(3.2 * len(names), 5.6), squeeze=False)
        for j, name in enumerate(names):
            pc = rob["policies"][name]["per_condition"]
            for row, (key, title, vmin, vmax) in enumerate(
                    (("saving_mean", "saving", 0.0, 1.0), ("oracle_fraction", "oracle fr.", -1, 1))):
                grid = np.full((len(LOADS_KG), len(SUPPLIES_BAR)), np.nan)
                for a, m in enumerate(LOADS_KG):
                    for b, bar in enumerate(SUPPLIES_BAR):
                        v = pc.get(f"{bar:g}bar-{m:g}kg", {}).get(key)
                        grid[a, b] = np.nan if v is None else v
                ax = axes[row, j]
                im = ax.imshow(grid, origin="lower", vmin=vmin, vmax=vmax, cmap="viridis",
                               aspect="auto")
                ax.set_xticks(range(len(SUPPLIES_BAR)), [f"{b:g}" for b in SUPPLIES_BAR])
                ax.set_yticks(range(len(LOADS_KG)), [f"{m:g}" for m in LOADS_KG])
                ax.set_title(f"{name}: {title}", fontsize=9)
                if j == 0:
                    ax.set_ylabel("load [kg]")
                if row == 1:
                    ax.set_xlabel("supply [bar g]")
                fig.colorbar(im, ax=ax, fraction=0.046)
        fig.tight_layout()
        fig.savefig(out / "robustness_heatmaps.png", dpi=110)
        plt.close(fig)
    plot_examples(results, out)


def plot_per_rig(suite: str, s: dict[str, Any], out: Path) -> None:
    """Oracle fraction per rig and policy (a suite of several rigs: ``per_rig``), clipped to
    [-1, 1.05] so that one rig's failure does not flatten the others' bars."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in s["policies"] if n not in ("conventional", "oracle")]
    rigs = list(s["policies"]["oracle"]["per_rig"])
    fig, ax = plt.subplots(figsize=(2.0 + 0.75 * len(rigs), 4.5))
    w = 0.8 / max(1, len(names))
    for j, name in enumerate(names):
        vals = [s["policies"][name]["per_rig"][r]["oracle_fraction"] for r in rigs]
        vals = [np.nan if v is None else min(max(v, -1.0), 1.05) for v in vals]
        ax.bar(np.arange(len(rigs)) + j * w, vals, w, label=name)
    ax.set_xticks(np.arange(len(rigs)) + 0.4 - w / 2, rigs, rotation=35, ha="right", fontsize=8)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_ylim(-1.0, 1.1)
    ax.set_ylabel("oracle fraction (clipped to [-1, 1.05])")
    ax.set_title(f"{suite} suite: oracle fraction per rig", fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / f"{suite}_oracle_fraction_per_rig.png", dpi=110)
    plt.close(fig)


def plot_examples(results: dict[str, Any], out: Path) -> None:
    """Position and driving pressure of one nominal 2.5 bar episode under each baseline."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pneugym.envs.cutoff import CutOffEnv
    from pneugym.physics import layout as L

    names = [n for n in results["config"]["policies"] if n in BASELINES]
    fig, ax = plt.subplots(2, 1, figsize=(6.5, 5), sharex=True)
    cond = Conditions(supply_pressure_gauge_pa=2.5e5)
    for name in names:
        env = CutOffEnv(render_mode="rgb_array", observe_rig=True)  # as evaluations run
        pol = make_policy(name, env)
        if getattr(pol, "commissioned_per_rig", False):
            continue  # it needs its rig's commissioning strokes first (not one example)
        obs, info = env.reset(seed=EVAL_SEED, options={"conditions": cond})
        pol.begin_episodes([cond])
        done = False
        while not done:
            a, _ = pol.predict(obs)
            obs, _, te, tr, info = env.step(a)
            done = te or tr
        tr_ = np.array(env._trace)
        ax[0].plot(tr_[:, L.R_T], tr_[:, L.R_X] * 1e3, label=f"{name} ({100 * info['saving_ratio']:.0f} %)")
        ax[1].plot(tr_[:, L.R_T], (tr_[:, L.R_PD] - 101325.0) / 1e5, label=name)
    ax[0].set_ylabel("position [mm]")
    ax[1].set_ylabel("driving pressure [bar g]")
    ax[1].set_xlabel("time since the extend command [s]")
    ax[0].set_title("one nominal episode (2.5 bar, 10 kg) per policy; energy saved in brackets",
                    fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "example_trajectories.png", dpi=120)
    plt.close(fig)
