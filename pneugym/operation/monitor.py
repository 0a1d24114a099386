"""Condition monitoring: the discrepancy workflow (:class:`pneugym.discrepancy.Discrepancy`) run on
the recent record of an operating run, at checkpoints (:func:`monitor`).

At every ``every``-th stroke it takes ``window`` strokes since the last checkpoint, their cut-off
times spread as widely as the record allows (reference strokes and a controller's exploration
give it different ones) (their sensor traces at the control rate, exported as ``pneugym-measurement/1`` runs
with the rig as commissioned), fits each stroke's own friction, lets the workflow calibrate the
nominal model (Cd and a factor on each stroke's friction: wear and temperature move them) and
test every candidate (the five effects and a slower valve), then, in a second pass with the
named change written in, the candidates left (:func:`examine`), and records its answer: the effect
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

from .record import Record, export_runs, run_rig

#: What the monitor tests by default: the workflow's five effects and a valve slower than
#: commissioned (:data:`~pneugym.discrepancy.candidates.VALVE_DELAY`), which wear and age bring
#: and which the five alone read as an extra dead volume (docs/operation.md). Written out:
#: importing the workflow takes seconds, and a checkpoint does it only when it runs.
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


def air_cost(effect: dict[str, float], cut_s: float | None, supply_gauge_pa: float,
             load_kg: float, dwell_s: float | None = None, rig: Any = None
             ) -> dict[str, float | None]:
    """Free air [NL] per stroke with and without the fitted ``effect`` (``{EffectParams field:
    value}``, or ``{"group.field": value}`` for another rig field, e.g. ``valve.delay_scale``): a
    conventional stroke and a stroke cut at ``cut_s`` [s] (None: the window's strokes were
    never cut; the cut stroke is then the conventional one), on the commissioned rig (``rig``,
    default
    the thesis rig), each with the rest at the stroke end (``dwell_s``, default the operating
    :data:`~pneugym.operation.run.DWELL_S`)."""
    from agents.oracle import TimedCutPolicy
    from pneugym.envs import Conditions
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.params import RigParams

    from .run import DWELL_S, run_block

    cond = Conditions(supply_pressure_gauge_pa=supply_gauge_pa, load_mass_kg=load_kg)
    t = np.array([math.inf, math.inf if cut_s is None else float(cut_s)])
    nl = []
    root = RigParams() if rig is None else rig
    groups: dict[str, dict[str, float]] = {}
    for k, v in effect.items():
        g, name = k.split(".", 1) if "." in k else ("effects", k)
        # a slower valve is a factor on the rig's stated delay (as apply_named writes it)
        groups.setdefault(g, {})[name] = float(v) * (root.valve.delay_scale
                                                     if k == "valve.delay_scale" else 1.0)
    for r in (root, root.with_(**groups)):
        env = CutOffVectorEnv(num_envs=2, autoreset=False, rig=r)
        f, _, _ = run_block(env, TimedCutPolicy(env.observation_layout(), t), [cond, cond],
                            np.zeros(2, dtype=bool), 0, False,
                            dwell_s=DWELL_S if dwell_s is None else dwell_s)
        nl += [float(v) for v in f["free_air_nl"]]
    return {"conventional_nl": nl[0], "conventional_with_effect_nl": nl[2],
            "cut_nl": nl[1], "cut_with_effect_nl": nl[3],
            "cut_s": None if cut_s is None else float(cut_s),
            "extra_per_stroke_conventional_nl": nl[2] - nl[0],
            "extra_per_stroke_cut_nl": nl[3] - nl[1]}


def _key(q: Any) -> str:
    """How a named change records a fitted parameter: an effect by its field, else
    ``"group.field"``."""
    return q.name if q.path.startswith("effects.") else q.path


def apply_named(runs: list[Any], effect: dict[str, float], rig: Any = None
                ) -> tuple[list[Any], Any]:
    """``runs`` and a base rig with a named change written in, for a further pass: a slower
    valve as a factor on each run's stated delay (``valve.delay_scale``), an effect
    (``{EffectParams field: value}``) into the base rig the runs' JSON is read over (``rig``,
    default the thesis rig; returned as it is when no effect is written)."""
    import copy
    import dataclasses

    from pneugym.params import RigParams

    effects: dict[str, float] = {}
    out = list(runs)
    for k, v in effect.items():
        if k == "valve.delay_scale":
            metas = [copy.deepcopy(r.meta) for r in out]
            for m in metas:
                m["rig"]["valve_delay_s"] = float(m["rig"]["valve_delay_s"]) * float(v)
            out = [dataclasses.replace(r, meta=m) for r, m in zip(out, metas)]
        elif "." not in k:
            effects[k] = float(v)
        else:
            raise ValueError(f"cannot write the named change {k!r} into the runs")
    root = RigParams() if rig is None else rig
    return out, (root.with_(effects=effects) if effects else rig)


def examine(runs: list[Any], candidates: Any, passes: int = 2, stroke_friction: bool = True,
            rig: Any = None, **workflow: Any) -> dict[str, Any]:
    """The workflow on one window's runs, in up to ``passes`` passes: each pass after the first
    writes the changes named so far into the model and tests the candidates left, so that a
    second change behind the first (a leak behind a slower valve) is named too; the changes
    named so far are calibrated again beside every candidate (``calibrate_also``), so a
    candidate gets no credit for what they explain. With
    ``stroke_friction`` each stroke's own friction is fitted first and the calibration fits
    one factor on it (:func:`~pneugym.discrepancy.fit.own_friction`). ``rig``: the commissioned
    rig the runs' JSON is read over (default the thesis rig). Returns ``named`` (the
    changes joined by ``+``, ``none`` or ``ambiguous``), ``decision`` (every pass's), ``effect``
    (their fitted values) and the last pass's workflow (``workflow``)."""
    from pneugym.discrepancy import Discrepancy
    from pneugym.discrepancy.fit import own_friction

    if not (isinstance(passes, int) and passes >= 1):
        raise ValueError(f"passes = {passes!r}: an integer >= 1")
    left = list(candidates)
    named: list[str] = []
    decisions: list[str] = []
    effect: dict[str, float] = {}
    found: tuple = ()  # the named changes' parameters, calibrated again in every later pass
    cur, base = list(runs), rig
    for k in range(passes):
        if k:
            cur, base = apply_named(runs, effect, rig)
        if stroke_friction:
            cur = own_friction(cur, base=base)
        wf = Discrepancy(**{"seed": 0, "calibrate": "basic", "discrepancy_term": None,
                            **workflow, "candidates": left, "calibrate_also": found}
                         ).fit(cur, base=base)
        decisions.append(wf.decision_)
        if wf.named_effect_ in ("none", "ambiguous"):
            if not named:
                named.append(wf.named_effect_)
            break
        cand = next(c for c in wf.candidates if c.name == wf.named_effect_)
        named.append(cand.name)
        for q in found:  # the earlier changes as fitted beside this one
            v = wf.fitted_params_[q.path]
            effect[_key(q)] = effect[_key(q)] * v if q.relative else v
        effect.update({_key(q): wf.fitted_params_[q.path] for q in cand.params})
        found += cand.params
        left = [c for c in left if getattr(c, "name", c) != cand.name]
        if not left:
            break
    return {"named": "+".join(named), "decision": " | then: ".join(decisions),
            "effect": effect if named[0] not in ("none", "ambiguous") else {}, "workflow": wf}


def monitor(db: str, run_id: str, every: int = 250, window: int = 6, first: int | None = None,
            last: int | None = None, progress: bool = True, passes: int = 2,
            stroke_friction: bool = True, **workflow: Any) -> list[dict[str, Any]]:
    """Run the workflow on ``run_id``'s record at strokes ``every``, ``2 every``, ... (from
    ``first`` to ``last`` if given; checkpoints already in the record are kept), in up to
    ``passes`` passes with each stroke's own friction (``stroke_friction``; see
    :func:`examine`). ``workflow``:
    options of :class:`~pneugym.discrepancy.Discrepancy` (default ``seed=0``,
    ``calibrate="basic"``, ``discrepancy_term=None`` and ``candidates=MONITORED``, the five
    effects and a slower valve: the settings the monitor's published figures were measured with;
    with the AR term it misattributed drift sooner, docs/operation.md; ``calibrate="extended"``
    frees the valve delay in the calibration instead, and then tests the five effects). A
    named change is recorded with its fitted values
    (``{field: value}`` for an effect, ``{"valve.delay_scale": x}`` for the valve; two changes
    as ``"valve_delay+leakage"`` with both's values) and its air
    cost. Returns every checkpoint's answer, in order."""
    from tqdm import tqdm

    from pneugym.data import read_runs
    from pneugym.discrepancy import CANDIDATES

    # the extended calibration frees the valve delay itself: the five effects are left to test
    default = MONITORED if workflow.get("calibrate", "basic") == "basic" else tuple(CANDIDATES)
    candidates = workflow.pop("candidates", default)
    if not (isinstance(every, int) and every >= 10 and isinstance(window, int) and window >= 3):
        raise ValueError(f"every = {every!r} (>= 10 strokes) and window = {window!r} (>= 3 runs)")
    if not (isinstance(passes, int) and passes >= 1):
        raise ValueError(f"passes = {passes!r}: an integer >= 1")
    with Record(db) as rec:
        rec.con.execute(MONITOR_SCHEMA)
        run = rec.run(run_id)
        if run is None:
            raise ValueError(f"no run {run_id!r} in {db}")
        rig = run_rig(run["config"])  # None: the thesis rig
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
                got = examine(runs, candidates, passes, stroke_friction, rig, **workflow)
                wall = time.perf_counter() - t0
            effect, cost = got["effect"], {}
            if effect:
                t = rec.frame("SELECT supply_setpoint_pa, cutoff_time_s FROM strokes WHERE "
                              "run_id = ? AND stroke BETWEEN ? AND ?", [run_id, c - every, c - 1])
                load = float(runs[-1].meta["load_mass_kg"])
                cuts = np.asarray(t["cutoff_time_s"], dtype=float)  # (never cut: NULL)
                cuts = cuts[np.isfinite(cuts)]
                cost = air_cost(effect, float(np.median(cuts)) if cuts.size else None,
                                float(np.median(t["supply_setpoint_pa"])), load,
                                float(run["config"].get("dwell_s", 0.0)), rig)
            rec.con.execute("INSERT OR REPLACE INTO monitor VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                            [run_id, c, int(c - every), got["named"], got["decision"],
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
    vals = ", ".join(f"{k} {v:.3g}" for k, v in hit["effect"].items() if v > 0)
    cost = hit["air_cost"].get("extra_per_stroke_conventional_nl")
    extra = f"; costs {cost:.3f} NL per conventional stroke" if cost is not None else ""
    return f"{hit['named']}: {vals}, {where}{extra}"
