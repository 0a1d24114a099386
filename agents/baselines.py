"""The two fixed schemes of the thesis: conventional actuation and end-stroke cut-off."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from .base import Policy


class ConventionalPolicy(Policy):
    """Never cuts the supply: the driving side ends filled to supply pressure."""

    name = "conventional"

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.zeros(obs.shape[0], dtype=np.int64)


class EndStrokePolicy(Policy):
    """Cuts the supply once the measured position is within ``tolerance_m`` of the stroke end
    (thesis 5.7: the valve then closes one switching delay later)."""

    name = "endstroke"

    def __init__(self, layout: Mapping[str, Any], tolerance_m: float = 2e-4):
        super().__init__(layout)
        if not tolerance_m >= 0:
            raise ValueError(f"tolerance_m = {tolerance_m!r} must be >= 0")
        self.tolerance_m = float(tolerance_m)
        feats = {f["name"]: f for f in layout["features"]}
        self.stroke_m = float(feats["position"]["scale"])

    def act(self, obs: np.ndarray) -> np.ndarray:
        return (self.read(obs, "position") >= self.stroke_m - self.tolerance_m).astype(np.int64)
