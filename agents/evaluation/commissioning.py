"""Commissioning in an evaluation: a policy that plans on a model of its rig
(``commissioned_per_rig``, e.g. :class:`agents.mpc_rig.RigModelPolicy`) gets, for every rig of a
suite, the two strokes a user would record on it (:func:`pneugym.commission.
commissioning_protocol`, simulated on the rig's truth at the rig file's operating point) and the
rig file a user would write (:func:`rig_file`: the datasheet values, never the hidden truth);
then it runs that rig's episodes. The strokes' noise is the measured-run default (400 Pa,
0.03 mm at 1 kHz), seeded from the evaluation's seed."""
from __future__ import annotations

from typing import Any, Collection, Sequence

import numpy as np

from pneugym.envs import Conditions
from pneugym.envs.family import apply_changes
from pneugym.params import RigParams

#: what a user writes in a rig file (the others a rig family varies are hidden truth)
DATASHEET_FIELDS = ("line.length_m", "line.diameter_m", "cylinder.dead_volume_m3",
                    "cylinder.design", "cylinder.mounting_angle_deg")


def rig_file(changes: tuple, base: RigParams) -> RigParams:
    """The rig file of a rig ``base`` under ``rig_changes``: ``base`` with only the
    :data:`DATASHEET_FIELDS` changed."""
    return apply_changes(base, tuple((k, v) for k, v in changes if k in DATASHEET_FIELDS))


def commissioning_runs(changes: tuple, base: RigParams, seed: int, g: int) -> list:
    """The two recorded strokes that commission rig number ``g`` of an evaluation: simulated on
    the rig's truth (``base`` under ``changes``, at ``base``'s operating point) and stated as its
    rig file (:func:`rig_file`), with the noise of seed ``seed + 7919 g``."""
    from pneugym.commission import commissioning_protocol

    truth = Conditions(supply_pressure_gauge_pa=base.supply_pressure_gauge_pa,
                       load_mass_kg=base.load_mass_kg, rig_changes=changes).rig(base)
    return commissioning_protocol(truth, rig_file(changes, base), seed=int(seed) + 7919 * g)


def rig_groups(eps: Sequence[tuple[str, Conditions]]) -> dict[str, list[int]]:
    """Episode indices by rig: the label's part before ``/`` (one group for a suite on the
    environment's own rig)."""
    groups: dict[str, list[int]] = {}
    for i, (label, _) in enumerate(eps):
        groups.setdefault(label.split("/")[0] if "/" in label else "", []).append(i)
    return groups


def run_commissioned(policy: Any, eps: Sequence[tuple[str, Conditions]], env_config: dict,
                     seed: int, base: RigParams, run_policy, progress: bool = False,
                     only: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """Final figures of every episode of ``eps`` (in order), each rig's episodes run after
    ``policy`` was commissioned on that rig; ``run_policy(policy, conds, env_config, seed)``
    runs a batch of episodes. Each episode's figures include its rig's ``commission_misfit``
    (the fit's mean square residual over the noise's, :attr:`pneugym.commission.Commissioned.
    misfit`). ``only``: the rigs (names of :func:`rig_groups`) to run, the others left out of
    the figures; each rig's strokes, fit and episodes are the same as in a run of all of them
    (so rigs can run as tasks of their own)."""
    from tqdm import tqdm

    groups = rig_groups(eps)
    if only is not None and (not only or set(only) - set(groups)):
        raise ValueError(f"run_commissioned: only = {sorted(only)} must name rigs of the "
                         f"episodes: {list(groups)}")
    parts: dict[int, dict[str, Any]] = {}
    for g, (name, idx) in enumerate(tqdm(groups.items(), desc="commissioning", unit="rig",
                                         disable=not progress or len(groups) < 2)):
        if only is not None and name not in only:
            continue  # (g still counts it: a rig's strokes are seeded by its place in eps)
        changes = eps[idx[0]][1].rig_changes
        if any(eps[i][1].rig_changes != changes for i in idx):
            raise ValueError(f"rig {name!r}: its episodes differ in their rig")
        runs = commissioning_runs(changes, base, seed, g)
        policy.commission(runs, **getattr(policy, "commission_options", {}))
        out = run_policy(policy, [eps[i][1] for i in idx], env_config, seed)
        for k, i in enumerate(idx):
            parts[i] = {**{key: v[k] for key, v in out.items()},
                        "commission_misfit": float(policy.model.misfit)}
    order = sorted(parts)
    return {k: np.array([parts[i][k] for i in order]) for k in parts[order[0]]}
