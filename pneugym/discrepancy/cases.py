"""Benchmark cases of the discrepancy workflow: one hidden effect, offsets, and a model form.

A case is three runs of the thesis protocol made on a *true* rig, with JSON files that state the
default rig (what an experimenter who knows nothing of the truth would write). The truth has

- one hidden effect drawn from its plausible range (:data:`RANGES`), or none (a control);
- nominal parameters off by up to ±5 % (discharge coefficient, the three friction forces);
- with ``form="mismatched"``, also a different *model form*: the plant options the workflow
  never fits (:func:`form_mismatch`): another line model or resolution, ISO 6358 orifices,
  another cushion length and transition, a transducer tee volume, another spool ramp, and a
  valve delay off by up to ±8 %. The workflow fits the default form, as on a real rig, whose
  form differs from every model.

The mismatched cases are a test bench, never a tuning set: the workflow's thresholds were set
on the matched-form cases and are not changed to suit these.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..data import MeasuredRun, thesis_protocol
from ..params import RigParams, thesis_rig
from .candidates import CANDIDATES

EFFECTS = tuple(CANDIDATES)
FORMS = ("matched", "mismatched")
#: plausible ranges of the hidden effects (log-uniform unless said)
RANGES = {
    "leakage": "drive, piston or both seal leaks, Cd*A 1e-7 ... 6e-7 m² each",
    "heat_transfer": "thermal time constant 0.1 ... 1.5 s",
    "stribeck_friction": "extra force 100 ... 230 N (uniform), Stribeck velocity 0.015 ... 0.05 m/s",
    "sensor_lag": "pressure-transducer time constant 5 ... 30 ms (the thesis's transducers: 15 ms)",
    "dead_volume": "extra volume at the driving port 4e-5 ... 2e-4 m³ (the rig's: 2.3e-4 m³)",
}
#: the model-form differences of ``form="mismatched"`` (every case draws all of them)
FORM_RANGES = {
    "line": "1-D finite differences with 12 ... 40 cells, or the lumped-volume line (3 ... 6 volumes); "
            "the model: finite differences, 3 cells",
    "orifices": "ISO 6358 flow with critical ratio b 0.2 ... 0.45 (half the cases) or the thesis's "
                "eqs. 4.1-4.3 with laminar band 0.02 ... 0.1; the model: eqs. 4.1-4.3, band 0.05",
    "cushion": "cushion length 0.85 ... 1.15 x and transition 1 ... 5 mm; the model: 13.6 mm, 2 mm",
    "tee": "a transducer tee of 0.5 ... 3 cm³ at 30 ... 90 % of the line; the model: none",
    "spool": "opening ramp 5 ... 20 ms, delay 0.92 ... 1.08 x; the model: 10 ms, the thesis's delay",
}
PERTURB = 0.05


def _logu(rng: np.random.Generator, a: float, b: float) -> float:
    return float(np.exp(rng.uniform(np.log(a), np.log(b))))


def hidden_effect(name: str, rng: np.random.Generator) -> dict[str, float]:
    """Random parameters of one effect in its plausible range (:data:`RANGES`); ``{}`` for none."""
    if name == "leakage":
        kind = rng.integers(3)
        out = {"leak_drive_area_m2": 0.0, "leak_piston_area_m2": 0.0}
        if kind in (0, 2):
            out["leak_drive_area_m2"] = _logu(rng, 1e-7, 6e-7)
        if kind in (1, 2):
            out["leak_piston_area_m2"] = _logu(rng, 1e-7, 6e-7)
        return out
    if name == "heat_transfer":
        return {"heat_transfer_time_constant_s": _logu(rng, 0.1, 1.5)}
    if name == "stribeck_friction":
        return {"stribeck_force_n": float(rng.uniform(100.0, 230.0)),
                "stribeck_velocity_m_s": _logu(rng, 0.015, 0.05)}
    if name == "sensor_lag":
        return {"sensor_lag_s": _logu(rng, 0.005, 0.03)}
    if name == "dead_volume":
        return {"dead_volume_m3": _logu(rng, 4e-5, 2e-4)}
    if name == "none":
        return {}
    raise ValueError(f"unknown effect {name!r}; choose from {list(EFFECTS) + ['none']}")


def form_mismatch(known: RigParams, rng: np.random.Generator) -> dict[str, dict[str, Any]]:
    """Changes of model form (:data:`FORM_RANGES`) as ``RigParams.with_`` groups."""
    ln, cy = known.line, known.cylinder
    if rng.random() < 0.5:
        line = {"model": "fd", "n_cells": int(rng.integers(12, 41))}
    else:
        line = {"model": "lumped", "n_cells": int(rng.integers(3, 7))}
    line["tee_volumes"] = ((float(rng.uniform(0.3, 0.9)) * ln.length_m, _logu(rng, 0.5e-6, 3e-6)),)
    if rng.random() < 0.5:
        valve = {"flow_model": "iso6358", "iso_b": float(rng.uniform(0.2, 0.45))}
    else:
        valve = {"flow_model": "thesis", "linear_ratio": float(rng.uniform(0.02, 0.1))}
    valve["ramp_s"] = _logu(rng, 0.005, 0.02)
    valve["delay_s"] = known.valve_delay_s * float(rng.uniform(0.92, 1.08))
    cyl = {"cushion_length_m": cy.cushion_length_m * float(rng.uniform(0.85, 1.15)),
           "cushion_ramp_m": _logu(rng, 0.001, 0.005)}
    return {"line": line, "valve": valve, "cylinder": cyl}


def make_case(effect: str, seed: int, form: str = "matched"
              ) -> tuple[RigParams, RigParams, list[MeasuredRun]]:
    """``(known rig, true rig, runs)`` of one case: the thesis protocol at 1 kHz with 400 Pa and
    0.03 mm of noise, at 1.5 or 2.5 bar, on the true rig; every run's JSON states ``known``."""
    if form not in FORMS:
        raise ValueError(f"form {form!r} must be one of {FORMS}")
    rng = np.random.default_rng(seed)
    known = thesis_rig(float(rng.choice([1.5, 2.5])))

    def f() -> float:
        return 1.0 + rng.uniform(-PERTURB, PERTURB)

    fr = known.friction
    changes: dict[str, dict[str, Any]] = {
        "valve": {"discharge_coefficient": known.valve.discharge_coefficient * f()},
        "friction": {"static_n": fr.static_n * f(), "coulomb_n": fr.coulomb_n * f(),
                     "viscous_n_s_per_m": fr.viscous_n_s_per_m * f()},
        "effects": hidden_effect(effect, rng)}
    if form == "mismatched":
        # drawn from a stream of its own, so a matched and a mismatched case of one seed share
        # their effect and offsets
        for group, vals in form_mismatch(known, np.random.default_rng([seed, 17])).items():
            changes.setdefault(group, {}).update(vals)
    truth = known.with_(**changes)
    return known, truth, thesis_protocol(truth, known, seed=seed)
