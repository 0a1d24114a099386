"""The ``rgb_array`` picture of an episode: position, port pressures and valve over time."""
from __future__ import annotations

import numpy as np

from ..physics import layout as L


def episode_figure(trace: np.ndarray, title: str, stroke_m: float, ambient_pa: float):
    """A matplotlib figure of recorded rows ``trace`` (n, NR) of one episode."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.8), dpi=80)
    ax = fig.subplots(3, 1, sharex=True)
    if trace.size == 0:
        trace = np.zeros((1, L.NR))
    t = trace[:, L.R_T]
    ax[0].plot(t, trace[:, L.R_X] * 1e3, color="k")
    ax[0].axhline(stroke_m * 1e3, color="0.6", lw=0.8, ls="--")
    ax[0].set_ylabel("position [mm]")
    ax[1].plot(t, (trace[:, L.R_PD] - ambient_pa) / 1e5, label="driving")
    ax[1].plot(t, (trace[:, L.R_PE] - ambient_pa) / 1e5, label="exhaust")
    ax[1].set_ylabel("pressure [bar g]")
    ax[1].legend(loc="upper right", fontsize=7)
    ax[2].plot(t, trace[:, L.R_S], label="valve opening")
    ax[2].step(t, trace[:, L.R_CMD], where="post", ls="--", label="command")
    ax[2].set_ylabel("valve [-]")
    ax[2].set_ylim(-0.1, 1.1)
    ax[2].set_xlabel("time since the extend command [s]")
    ax[2].legend(loc="upper right", fontsize=7)
    ax[0].set_title(title, fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def figure_to_rgb(fig) -> np.ndarray:
    """RGB pixels (H, W, 3) uint8 of a matplotlib figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def episode_figure_rgb(trace: np.ndarray, conditions, stroke_m: float, ambient_pa: float
                       ) -> np.ndarray:
    title = (f"{conditions.supply_bar_gauge:.2g} bar g, {conditions.load_mass_kg:.3g} kg"
             if conditions is not None else "")
    return figure_to_rgb(episode_figure(trace, title, stroke_m, ambient_pa))
