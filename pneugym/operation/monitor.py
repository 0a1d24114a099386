"""Condition monitoring: the discrepancy workflow (:class:`pneugym.discrepancy.Discrepancy`) run on
the recent record of an operating run, at checkpoints (:func:`monitor`).

At every ``every``-th stroke it takes ``window`` strokes since the last checkpoint, their cut-off
times spread as widely as the record allows (reference strokes and a controller's exploration
give it different ones) (their sensor traces at the control rate, exported as ``pneugym-measurement/1`` runs
with the rig as commissioned), lets the workflow calibrate the nominal model (Cd and friction: wear
and temperature move them) and test every candidate (the five effects and a slower valve), and
records its answer: the effect
named (or ``none``), the fitted values and, for a named effect, what it costs in air (the free air
of a conventional stroke and of the window's median cut, with and without the effect, on the
plant). The exported runs state each stroke's payload, as an operator who knows the product's mass
would. The first checkpoint that names an effect is the alarm ("leakage: drive leak area
2.1e-7 m^2, first significant after stroke 2000"). Answers are written to the record's ``monitor``
table.
"""
from __future__ import annotations

import json
import math
import tempfile
from typing import Any

import numpy as np

from .record import Record, export_runs

#: What the monitor tests by default: the workflow's five effects and a valve slower than
#: commissioned (:data:`~pneugym.discrepancy.candidates.VALVE_DELAY`), which wear and age bring
#: and which the five alone read as an extra dead volume (docs/operation.md).
MONITORED: tuple[str, ...] = ("leakage", "heat_transfer", "stribeck_friction", "sensor_lag",
                              "dead_volume", "valve_delay")

MONITOR_SCHEMA = """
CREATE TABLE IF NOT EXISTS monitor (
    run_id VARCHAR, stroke BIGINT, first_stroke BIGINT, named VARCHAR, decision VARCHAR,
    effect JSON, air_cost JSON, wall_s DOUBLE, PRIMARY KEY (run_id, stroke));
"""


def _pick(strokes: np.ndarray, cut_s: np.ndarray, window: int) -> np.ndarray:
    """``window`` strokes whose cut-off times spread as widely as the record allows (an uncut
    reference stroke counts as the latest cut): evenly spaced quantiles of the cut times, the
    most recent stroke of each; different cuts are what tell a leak from friction."""
    t = np.where(np.isnan(cut_s), np.inf, cut_s)
    order = np.lexsort((-strokes, t))  # by cut time, the most recent first among equal ones
    picked: list[int] = []
    for q in np.linspace(0, strokes.size - 1, window):
        j = order[int(round(q))]
        same = order[t[order] == t[j]]  # the most recent stroke of this cut time not yet taken
        free = [i for i in same if strokes[i] not in picked]
        i = free[0] if free else next(i for i in order if strokes[i] not in picked)
        picked.append(int(strokes[i]))
    return np.array(sorted(picked))


def air_cost(effect: dict[str, float], cut_s: float, supply_gauge_pa: float,
             load_kg: float, dwell_s: float | None = None) -> dict[str, float]:
    """Free air [NL] per stroke with and without the fitted ``effect`` (``{EffectParams field:
    value}``, or ``{"group.field": value}`` for another rig field, e.g. ``valve.delay_scale``): a
    conventional stroke and a stroke cut at ``cut_s``, on the commissioned rig, each with the
    rest at the stroke end (``dwell_s``, default the operating
    :data:`~pneugym.operation.run.DWELL_S`)."""
    from agents.oracle import TimedCutPolicy
    from pneugym.envs import Conditions
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.params import RigParams

    from .run import DWELL_S, run_block

    cond = Conditions(supply_pressure_gauge_pa=supply_gauge_pa, load_mass_kg=load_kg)
    t = np.array([math.inf, cut_s])
    nl = []
    groups: dict[str, dict[str, float]] = {}
    for k, v in effect.items():
        g, name = k.split(".", 1) if "." in k else ("effects", k)
        groups.setdefault(g, {})[name] = float(v)
    for rig in (RigParams(), RigParams().with_(**groups)):
        env = CutOffVectorEnv(num_envs=2, autoreset=False, rig=rig)
        f, _, _ = run_block(env, TimedCutPolicy(env.observation_layout(), t), [cond, cond],
                            np.zeros(2, dtype=bool), 0, False,
                            dwell_s=DWELL_S if dwell_s is None else dwell_s)
        nl += [float(v) for v in f["free_air_nl"]]
    return {"conventional_nl": nl[0], "conventional_with_effect_nl": nl[2],
            "cut_nl": nl[1], "cut_with_effect_nl": nl[3], "cut_s": float(cut_s),
            "extra_per_stroke_conventional_nl": nl[2] - nl[0],
            "extra_per_stroke_cut_nl": nl[3] - nl[1]}


def monitor(db: str, run_id: str, every: int = 250, window: int = 6, first: int | None = None,
            last: int | None = None, progress: bool = True, **workflow: Any
            ) -> list[dict[str, Any]]:
    """Run the workflow on ``run_id``'s record at strokes ``every``, ``2 every``, ... (from
    ``first`` to ``last`` if given; checkpoints already in the record are kept). ``workflow``:
    options of :class:`~pneugym.discrepancy.Discrepancy` (default ``seed=0``,
    ``calibrate="basic"``, ``discrepancy_term=None`` and ``candidates=MONITORED``, the five
    effects and a slower valve: the settings the monitor's published figures were measured with;
    with the AR term it misattributed drift sooner, docs/operation.md; ``calibrate="extended"``
    frees the valve delay in the calibration instead, and then tests the five effects). A
    named change is recorded with its fitted values
    (``{field: value}`` for an effect, ``{"valve.delay_scale": x}`` for the valve) and its air
    cost. Returns every checkpoint's answer, in order."""
    from tqdm import tqdm

    from pneugym.data import read_runs
    from pneugym.discrepancy import CANDIDATES, Discrepancy

    # the extended calibration frees the valve delay itself: the five effects are left to test
    default = MONITORED if workflow.get("calibrate", "basic") == "basic" else tuple(CANDIDATES)
    if not (isinstance(every, int) and every >= 10 and isinstance(window, int) and window >= 3):
        raise ValueError(f"every = {every!r} (>= 10 strokes) and window = {window!r} (>= 3 runs)")
    with Record(db) as rec:
        rec.con.execute(MONITOR_SCHEMA)
        run = rec.run(run_id)
        if run is None:
            raise ValueError(f"no run {run_id!r} in {db}")
        n = int(rec.con.execute("SELECT max(stroke) + 1 FROM strokes WHERE run_id = ?",
                                [run_id]).fetchone()[0] or 0)
        cps = [c for c in range(every, n + 1, every)
               if (first is None or c >= first) and (last is None or c <= last)]
        done = set(rec.frame("SELECT stroke FROM monitor WHERE run_id = ?", [run_id])["stroke"]
                   .tolist())
        for c in tqdm([c for c in cps if c not in done], desc=f"monitor {run_id}",
                      unit="checkpoint", disable=not progress):
            s = rec.strokes(run_id, c - every, c - 1)
            if s["stroke"].size < window:
                continue
            picked = _pick(s["stroke"], s["cutoff_time_s"], window)
            with tempfile.TemporaryDirectory() as d:
                files = []
                for k in picked:
                    files += export_runs(rec, run_id, d, int(k), int(k))
                runs = read_runs(files)
                import time

                t0 = time.perf_counter()
                wf = Discrepancy(**{"seed": 0, "calibrate": "basic", "discrepancy_term": None,
                                    "candidates": default, **workflow}).fit(runs)
                wall = time.perf_counter() - t0
            effect: dict[str, float] = {}
            cost: dict[str, float] = {}
            if wf.named_effect_ not in ("none", "ambiguous"):
                named = next(c for c in wf.candidates if c.name == wf.named_effect_)
                effect = {(q.name if q.path.startswith("effects.") else q.path):
                          wf.fitted_params_[q.path] for q in named.params}
                t = rec.frame("SELECT supply_setpoint_pa, cutoff_time_s FROM strokes WHERE "
                              "run_id = ? AND stroke BETWEEN ? AND ?", [run_id, c - every, c - 1])
                load = float(runs[-1].meta["load_mass_kg"])
                cost = air_cost(effect, float(np.nanmedian(t["cutoff_time_s"])),
                                float(np.median(t["supply_setpoint_pa"])), load,
                                float(run["config"].get("dwell_s", 0.0)))
            rec.con.execute("INSERT OR REPLACE INTO monitor VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                            [run_id, c, int(c - every), wf.named_effect_, wf.decision_,
                             json.dumps(effect), json.dumps(cost), wall])
        return checkpoints(rec, run_id)


def checkpoints(rec: Record, run_id: str) -> list[dict[str, Any]]:
    """The monitor's answers recorded for a run, in order (empty if never monitored)."""
    has = rec.con.execute("SELECT count(*) FROM information_schema.tables WHERE table_name = "
                          "'monitor'").fetchone()[0]
    if not has:
        return []
    cur = rec.con.execute("SELECT stroke, first_stroke, named, decision, effect, air_cost, "
                          "wall_s FROM monitor WHERE run_id = ? ORDER BY stroke", [run_id])
    cols = [d[0] for d in cur.description]
    out = []
    for r in cur.fetchall():
        row = dict(zip(cols, r))
        row["effect"], row["air_cost"] = json.loads(row["effect"]), json.loads(row["air_cost"])
        out.append(row)
    return out


def alarm(points: list[dict[str, Any]]) -> str:
    """The monitor's verdict in one line: the first checkpoint at which something changed (an
    effect named, or two the workflow cannot tell apart), or "no change"."""
    hit = next((p for p in points if p["named"] != "none"), None)
    if hit is None:
        return (f"no change: {len(points)} checkpoints up to stroke "
                f"{points[-1]['stroke'] if points else 0}, no effect named")
    where = f"first significant in strokes {hit['first_stroke']}-{hit['stroke'] - 1}"
    if hit["named"] == "ambiguous":
        return f"a change it cannot name ({hit['decision']}), {where}"
    vals = ", ".join(f"{k} {v:.2g}" for k, v in hit["effect"].items() if v > 0)
    cost = hit["air_cost"].get("extra_per_stroke_conventional_nl")
    extra = f"; costs {cost:.3f} NL per conventional stroke" if cost is not None else ""
    return f"{hit['named']}: {vals}, {where}{extra}"
