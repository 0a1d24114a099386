"""The evaluation suites (sensor noise 0.03 mm / 400 Pa in every episode):

- ``nominal``: the thesis conditions, 1.5 and 2.5 bar gauge with 10 kg (on another rig, its own
  operating point too: the supply and load its rig file states);
- ``robustness``: load {5, 10, 15, 20, 30} kg x supply {1.5, 2, 2.5, 3, 4, 5} bar, plus
  disturbance sets at 1.5 and 2.5 bar with 10 kg: random supply dips (10-30 %, 50-300 ms),
  friction -30 % / +30 %, valve delay -20 % / +20 %;
- ``transfer``: rigs no policy was trained on (:func:`transfer_rigs`): the thesis rig, held-out
  draws of the rig family, rigs beyond its edges and model forms it does not draw, each at four
  operating points (:data:`TRANSFER_POINTS`), each episode with its own oracle;
- ``points`` (only when named): those operating points on the environment's own rig, or the
  points given (``points=``, ``pneugym evaluate --points BAR:KG ...``; :func:`check_points`);
- ``cylinders`` (only when named): :data:`CYLINDER_HELD_OUT` held-out draws of the
  ``family-cylinders`` preset (single-rod and inclined cylinders among them) at those operating
  points (:func:`cylinder_rigs`).

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


#: operating points (supply bar gauge, load kg) of every rig of the transfer suite
TRANSFER_POINTS = ((1.5, 5.0), (2.5, 10.0), (4.0, 20.0), (5.5, 35.0))
#: held-out draws of the rig family in the transfer suite
TRANSFER_HELD_OUT = 6
#: rigs beyond the family's edges (``pneugym.envs.family.RigFamily``): each one quantity out of range
TRANSFER_EDGES: dict[str, dict[str, float]] = {
    "edge-dead-volume": {"cylinder.dead_volume_m3": 8e-4},
    "edge-long-line": {"line.length_m": 6.5},
    "edge-slow-small-valve": {"valve.delay_s": 0.4, "valve.area_m2": 0.25 * 1.56e-5},
    "edge-high-friction": {"friction.static_n": 750.0, "friction.coulomb_n": 320.0,
                           "friction.viscous_n_s_per_m": 4000.0},
    "edge-soft-cushion": {"cylinder.cushion_length_m": 0.03, "cylinder.cushion_factor_exhaust": 0.5},
}
#: the thesis rig under model forms and effects the family does not draw
TRANSFER_FORMS: dict[str, dict[str, Any]] = {
    "form-lumped-iso6358": {"line.model": "lumped", "valve.flow_model": "iso6358",
                            "cylinder.cushion_ramp_m": 0.004},
    "form-leaks-heat": {"effects.leak_drive_area_m2": 2e-7, "effects.leak_piston_area_m2": 5e-8,
                        "effects.heat_transfer_time_constant_s": 1.0},
    "form-stribeck-sensor-lag": {"effects.stribeck_force_n": 50.0, "effects.sensor_lag_s": 0.01},
}
SUITES = ("nominal", "robustness", "transfer")
#: suites that only run when named: ``points``, the transfer suite's operating points on the
#: environment's own rig (``--rig``), for a policy retrained for that rig
EXTRA_SUITES = ("points", "cylinders")
#: held-out draws of the ``family-cylinders`` preset in the ``cylinders`` suite
CYLINDER_HELD_OUT = 6
#: the slowest conventional stroke [s] of an edge or model-form rig (the episodes' limit is 4 s)
EDGE_MAX_CONVENTIONAL_TIME_S = 3.2


def transfer_rigs(base: RigParams | None = None) -> dict[str, tuple]:
    """The rigs of the transfer suite, by name, as ``rig_changes`` to ``base`` (default the
    thesis rig): the thesis rig itself, :data:`TRANSFER_HELD_OUT` draws of the ``family`` preset's
    rig family from :data:`EVAL_SEED` (seeds no training uses; redrawn until every
    :data:`TRANSFER_POINTS` completes within the family's time bound), the edges
    (:data:`TRANSFER_EDGES`) and the model forms (:data:`TRANSFER_FORMS`)."""
    from pneugym.envs.conditions import PRESETS
    from pneugym.envs.family import check_changes, checked_substep

    base = base or RigParams()
    family = PRESETS["family"].family
    rigs: dict[str, tuple] = {"thesis": ()}
    for k, changes in enumerate(held_out_draws("family", TRANSFER_HELD_OUT, 12, base)):
        rigs[f"heldout-{k + 1}"] = changes
    for name, ch in {**TRANSFER_EDGES, **TRANSFER_FORMS}.items():
        changes = check_changes(ch, name)
        dts = []
        for b, m in TRANSFER_POINTS:  # every point must complete in time; a design error else
            c = Conditions(supply_pressure_gauge_pa=b * 1e5, load_mass_kg=m, rig_changes=changes)
            try:
                dts.append(checked_substep(c.rig(base), c.dip, EDGE_MAX_CONVENTIONAL_TIME_S,
                                           family.max_conventional_sticks))
            except ValueError as exc:
                raise ValueError(f"transfer rig {name!r} at {b:g} bar, {m:g} kg on this base "
                                 f"rig: {exc}") from None
        if any(dts):
            changes = check_changes(changes + (("solver.dt_s", min(d for d in dts if d)),), name)
        rigs[name] = changes
    return rigs


def held_out_draws(preset: str, n: int, stream: int, base: RigParams) -> list[tuple]:
    """``n`` draws of the rig family of conditions preset ``preset`` from seed
    ``[EVAL_SEED, stream]`` (seeds no training uses), as ``rig_changes`` to ``base``; a draw is
    redrawn until every :data:`TRANSFER_POINTS` completes within the family's time bound."""
    from pneugym.envs.conditions import PRESETS
    from pneugym.envs.family import StrokeRefused, draw_substep

    family = PRESETS[preset].family
    rng = np.random.default_rng([EVAL_SEED, stream])
    out: list[tuple] = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 100 * n:
            raise ValueError(f"the {preset} family draws no {n} rigs on this base whose "
                             f"conventional strokes complete at every operating point of the "
                             f"suite in {100 * n} tries")
        changes = family.sample(rng, base)
        dts = []
        try:
            for b, m in TRANSFER_POINTS:
                c = Conditions(supply_pressure_gauge_pa=b * 1e5, load_mass_kg=m,
                               rig_changes=changes)
                dts.append(draw_substep(c, base, family))
        except StrokeRefused:
            continue
        if any(dts):
            changes += (("solver.dt_s", min(d for d in dts if d)),)
        out.append(changes)
    return out


def family_draws(seed: int, n: int) -> list[Conditions]:
    """The first ``n`` episodes' conditions of the ``family`` preset, with the suites'
    :data:`NOISE`, drawn from ``numpy.random.default_rng(seed)``: the fresh family draws of the
    model-predictive benchmarks (``bench_mpc*.py``; seed 3,000,000 validates, 4,000,000 and
    5,000,000 are held out). The first ``n`` of a larger ``n`` are the same draws."""
    from pneugym.envs.conditions import PRESETS

    space = PRESETS["family"].with_(**NOISE)
    rng = np.random.default_rng(seed)
    return [space.sample(rng) for _ in range(n)]


def cylinder_rigs(base: RigParams | None = None) -> dict[str, tuple]:
    """The rigs of the ``cylinders`` suite, by name (``cyl-1`` ...), as ``rig_changes`` to
    ``base`` (default the thesis rig): held-out draws of the ``family-cylinders`` preset, whose
    cylinders are single-rod or double-rod, horizontal or inclined (-90 to +90 degrees)."""
    draws = held_out_draws("family-cylinders", CYLINDER_HELD_OUT, 13, base or RigParams())
    return {f"cyl-{k + 1}": changes for k, changes in enumerate(draws)}


def check_points(points: Any) -> tuple[tuple[float, float], ...]:
    """Operating points ``((supply bar gauge, load kg), ...)`` of the ``points`` suite, checked:
    at least one, none twice, each a supply and load a rig takes (:class:`RigParams`' own
    checks). Raises ValueError naming the point."""
    try:
        pts = tuple((float(b), float(m)) for b, m in points)
    except (TypeError, ValueError):
        raise ValueError(f"points = {points!r}: expected (supply bar gauge, load kg) pairs, "
                         f"e.g. ((4.0, 20.0), (6.0, 40.0))") from None
    if not pts:
        raise ValueError("points: give at least one operating point (supply bar g, load kg)")
    for b, m in pts:
        try:
            RigParams().with_(supply_pressure_gauge_pa=b * 1e5, load_mass_kg=m)
        except ValueError as exc:
            raise ValueError(f"operating point {b:g} bar g / {m:g} kg: {exc}") from None
    if len(set(pts)) < len(pts):
        raise ValueError(f"points = {pts}: an operating point is given twice")
    return pts


def suite_cells(suite: str, rig: RigParams | None = None, points: Any = None
                ) -> list[tuple[str, ConditionSpace]]:
    """The condition cells of a suite: ``(label, space to draw each episode's conditions from)``;
    ``rig``'s own operating point is a cell of the nominal suite when it is none of the thesis's;
    ``points`` (supply bar g, load kg): the ``points`` suite's operating points instead of
    :data:`TRANSFER_POINTS` (the other suites refuse them)."""
    if points is not None and suite != "points":
        raise ValueError(f"operating points are given for the {suite} suite: only the points "
                         f"suite takes them")
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
    if suite == "points":
        pts = TRANSFER_POINTS if points is None else check_points(points)
        return [(f"{b:g}bar-{m:g}kg", _fixed(b, m)) for b, m in pts]
    if suite in ("transfer", "cylinders"):
        rigs = transfer_rigs(rig) if suite == "transfer" else cylinder_rigs(rig)
        return [(f"{name}/{b:g}bar-{m:g}kg", _fixed(b, m, rig_changes=changes))
                for name, changes in rigs.items() for b, m in TRANSFER_POINTS]
    raise ValueError(f"unknown suite {suite!r}; choose one of {SUITES} or all")


def suite_episodes(suite: str, episodes: int, seed: int, rig: RigParams | None = None,
                   points: Any = None) -> list[tuple[str, Conditions]]:
    """``episodes`` draws per cell, each from its own seeded generator (``points``: see
    :func:`suite_cells`)."""
    out = []
    for c, (label, space) in enumerate(suite_cells(suite, rig, points)):
        for k in range(episodes):
            rng = np.random.default_rng([seed, c, k])
            out.append((label, space.sample(rng)))
    return out
