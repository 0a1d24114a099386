"""The evaluation suites (sensor noise 0.03 mm / 400 Pa in every episode):

- ``nominal``: the thesis conditions, 1.5 and 2.5 bar gauge with 10 kg (on another rig, its own
  operating point too: the supply and load its rig file states);
- ``robustness``: load {5, 10, 15, 20, 30} kg x supply {1.5, 2, 2.5, 3, 4, 5} bar, plus
  disturbance sets at 1.5 and 2.5 bar with 10 kg: random supply dips (10-30 %, 50-300 ms),
  friction -30 % / +30 %, valve delay -20 % / +20 %.

Each cell's episodes are drawn from their own seeded generator (:func:`suite_episodes`), from
:data:`EVAL_SEED` up: seeds no training or calibration uses."""
from __future__ import annotations

from typing import Any

import numpy as np

from pneugym.envs import Conditions, ConditionSpace
from pneugym.params import RigParams

#: sensor noise in every episode of every suite
NOISE = {"position_noise_m": 3e-5, "pressure_noise_pa": 400.0}
#: the robustness grid: loads x supply set-points (gauge)
LOADS_KG = (5.0, 10.0, 15.0, 20.0, 30.0)
SUPPLIES_BAR = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0)
EVAL_SEED = 1_000_000  #: the first evaluation seed: training seeds stay below it


def _fixed(bar: float, kg: float, **kw: Any) -> ConditionSpace:
    return ConditionSpace(supply_pressure_gauge_pa=bar * 1e5, load_mass_kg=kg, **NOISE, **kw)


def suite_cells(suite: str, rig: RigParams | None = None) -> list[tuple[str, ConditionSpace]]:
    """The condition cells of a suite: ``(label, space to draw each episode's conditions from)``;
    ``rig``'s own operating point is a cell of the nominal suite when it is none of the thesis's."""
    if suite == "nominal":
        cells = [(f"{b:g}bar-10kg", _fixed(b, 10.0)) for b in (1.5, 2.5)]
        if rig is not None:
            b, m = rig.supply_pressure_gauge_pa / 1e5, rig.load_mass_kg
            if not (m == 10.0 and b in (1.5, 2.5)):
                cells.append((f"rig-{b:g}bar-{m:g}kg", _fixed(b, m)))
        return cells
    if suite == "robustness":
        cells = [(f"{b:g}bar-{m:g}kg", _fixed(b, m)) for m in LOADS_KG for b in SUPPLIES_BAR]
        for b in (1.5, 2.5):
            cells += [
                (f"{b:g}bar-dip", _fixed(b, 10.0, dip_probability=1.0, dip_depth=(0.1, 0.3),
                                         dip_duration_s=(0.05, 0.3), dip_start_s=(0.0, 1.0))),
                (f"{b:g}bar-friction-30%", _fixed(b, 10.0, friction_scale=0.7)),
                (f"{b:g}bar-friction+30%", _fixed(b, 10.0, friction_scale=1.3)),
                (f"{b:g}bar-valve-delay-20%", _fixed(b, 10.0, valve_delay_scale=0.8)),
                (f"{b:g}bar-valve-delay+20%", _fixed(b, 10.0, valve_delay_scale=1.2)),
            ]
        return cells
    raise ValueError(f"unknown suite {suite!r}; choose nominal, robustness or all")


def suite_episodes(suite: str, episodes: int, seed: int, rig: RigParams | None = None
                   ) -> list[tuple[str, Conditions]]:
    """``episodes`` draws per cell, each from its own seeded generator."""
    out = []
    for c, (label, space) in enumerate(suite_cells(suite, rig)):
        for k in range(episodes):
            rng = np.random.default_rng([seed, c, k])
            out.append((label, space.sample(rng)))
    return out
