"""Figures of an operating record: per run, per hour and per shift (DuckDB queries), cumulative
air against a conventional controller and the drift-aware oracle, and the report (Markdown, PNG,
JSON) of :func:`write_report`.

``oracle_fraction = (J - J_conventional) / (J_oracle - J_conventional)`` on the summed objective
of the strokes (the same definition as the evaluation's); ``air_fraction`` is the air saved
against the conventional controller over what the oracle saves. Reference strokes and
exploring ones count as the controller's strokes: their air is spent.
``oracle_fraction_regular`` leaves them out: what the controller's own decisions get.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .record import Record
from .scenarios import SCENARIO_NAME

JOINED = """
SELECT s.*, t.* EXCLUDE (scenario, seed, stroke)
FROM strokes s JOIN runs r USING (run_id)
JOIN truth t ON t.scenario = r.scenario AND t.seed = r.seed AND t.stroke = s.stroke
WHERE s.run_id = ?
"""
SUMMARY = f"""
SELECT count(*) AS strokes, sum(stalled::INT) AS stalls,
       sum((stick_slip_events > 0)::INT) AS stick_slip_strokes,
       sum((NOT completed)::INT) AS incomplete, max(stroke_time_s) AS worst_stroke_time_s,
       sum(reference::INT) AS reference_strokes, sum(explore::INT) AS explore_strokes,
       avg(saving_ratio) AS saving_mean,
       sum(free_air_nl) AS air_nl, sum(conventional_free_air_nl) AS air_conventional_nl,
       sum(oracle_free_air_nl) AS air_oracle_nl,
       (sum(conventional_free_air_nl) - sum(free_air_nl))
         / nullif(sum(conventional_free_air_nl) - sum(oracle_free_air_nl), 0) AS air_fraction,
       (sum(objective) - sum(conventional_objective))
         / nullif(sum(oracle_objective) - sum(conventional_objective), 0) AS oracle_fraction,
       (sum(objective) FILTER (WHERE NOT reference AND NOT explore)
          - sum(conventional_objective) FILTER (WHERE NOT reference AND NOT explore))
         / nullif(sum(oracle_objective) FILTER (WHERE NOT reference AND NOT explore)
                  - sum(conventional_objective) FILTER (WHERE NOT reference AND NOT explore), 0)
         AS oracle_fraction_regular
FROM ({JOINED})
"""


def _period(col: str) -> str:
    return f"""
SELECT {col} AS period, count(*) AS strokes, avg(saving_ratio) AS saving_mean,
       avg(stroke_time_s) AS stroke_time_mean_s, max(stroke_time_s) AS stroke_time_max_s,
       sum(stalled::INT) AS stalls, sum((stick_slip_events > 0)::INT) AS stick_slip_strokes,
       sum(conventional_free_air_nl) - sum(free_air_nl) AS air_saved_nl,
       (sum(objective) - sum(conventional_objective))
         / nullif(sum(oracle_objective) - sum(conventional_objective), 0) AS oracle_fraction
FROM (SELECT *, floor(hour)::INT AS hour_index, floor(hour / ?)::INT AS shift_index
      FROM ({JOINED}))
GROUP BY period ORDER BY period
"""


#: the end of a life the summary also reports on [strokes]
LAST = 1000


def summary(rec: Record, run_id: str) -> dict[str, Any]:
    """A run's figures over its whole life, and its oracle fraction over the last :data:`LAST`
    strokes (``oracle_fraction_last``: where slow drift has gone furthest)."""
    cur = rec.con.execute(SUMMARY, [run_id])
    cols = [d[0] for d in cur.description]
    out = dict(zip(cols, cur.fetchone()))
    out = {k: (float(v) if isinstance(v, float) else v) for k, v in out.items()}
    d = life(rec, run_id)
    m = d["stroke"] > (d["stroke"].max() - LAST if d["stroke"].size else 0)
    gap = d["oracle_objective"][m].sum() - d["conventional_objective"][m].sum()
    out["oracle_fraction_last"] = (float((d["objective"][m].sum()
                                          - d["conventional_objective"][m].sum()) / gap)
                                   if m.any() and abs(gap) > 1e-12 else None)
    return out


def per_period(rec: Record, run_id: str, period: str = "hour") -> list[dict[str, Any]]:
    """Figures per operating hour (``period="hour"``) or per shift (``"shift"``)."""
    if period not in ("hour", "shift"):
        raise ValueError(f"period = {period!r}: choose 'hour' or 'shift'")
    run = rec.run(run_id)
    if run is None:
        raise ValueError(f"no run {run_id!r} in {rec.path}")
    hours = float(run["config"]["scenario"]["shift_hours"])
    cur = rec.con.execute(_period(f"{period}_index"), [hours, run_id])
    cols = [d[0] for d in cur.description]
    return [dict(zip(cols, r)) for r in cur.fetchall()]


def life(rec: Record, run_id: str) -> dict[str, np.ndarray]:
    """Per stroke: the controller's and the references' air, objective and outcome."""
    return rec.frame(f"SELECT stroke, hour, free_air_nl, conventional_free_air_nl, "
                     f"oracle_free_air_nl, objective, conventional_objective, oracle_objective, "
                     f"stroke_time_s, stalled, stick_slip_events, reference, explore "
                     f"FROM ({JOINED}) ORDER BY stroke", [run_id])


def rolling_fraction(d: dict[str, np.ndarray], window: int = 100) -> np.ndarray:
    """The oracle fraction over the last ``window`` strokes, at each stroke."""
    def roll(v):
        c = np.concatenate([[0.0], np.cumsum(np.asarray(v, float))])
        k = np.arange(1, len(v) + 1)
        lo = np.maximum(0, k - window)
        return c[k] - c[lo]

    gap = roll(d["oracle_objective"]) - roll(d["conventional_objective"])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(np.abs(gap) > 1e-9,
                        (roll(d["objective"]) - roll(d["conventional_objective"])) / gap, np.nan)


def recovery(d: dict[str, np.ndarray], steps: list[int], target: float = 0.95,
             window: int = 100) -> dict[int, int | None]:
    """Strokes after each step change until the rolling oracle fraction (over ``window``
    strokes, all after the step) is back to ``target``; None if never. At least ``window``:
    a controller the step did not disturb scores ``window``."""
    out: dict[int, int | None] = {}
    for s in steps:
        after = {k: v[d["stroke"] >= s] for k, v in d.items()}
        if after["stroke"].size < window:
            out[s] = None
            continue
        f = rolling_fraction(after, window)
        ok = np.flatnonzero(f[window - 1:] >= target)
        out[s] = int(ok[0] + window) if ok.size else None
    return out


def step_changes(scenario: dict[str, Any]) -> list[int]:
    """The strokes at which a scenario steps (two knots one stroke apart), at the start of the
    drift step the new value first holds in."""
    res = int(scenario.get("resolution", 1))
    out = set()
    for pts in scenario["drift"].values():
        for (k0, v0), (k1, v1) in zip(pts, pts[1:]):
            if k1 - k0 == 1 and v1 != v0:
                out.add(int(-(-k1 // res) * res))
    return sorted(out)


def plot(rec: Record, run_ids: list[str], path: str | Path) -> Path:
    """Cumulative air saved against the conventional controller (with the oracle's) and the
    rolling oracle fraction, one line per run, and the scenario's drift."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    longest = None
    for rid in run_ids:
        d = life(rec, rid)
        if d["stroke"].size == 0:  # nothing recorded yet
            continue
        saved = np.cumsum(d["conventional_free_air_nl"] - d["free_air_nl"]) / 1000
        ax[0].plot(d["stroke"], saved, label=_label(rec.run(rid)["controller"]))
        ax[1].plot(d["stroke"], rolling_fraction(d), label=_label(rec.run(rid)["controller"]))
        if longest is None or d["stroke"].size > longest["stroke"].size:
            longest = d
    if longest is not None:
        d = longest
        ax[0].plot(d["stroke"], np.cumsum(d["conventional_free_air_nl"]
                                          - d["oracle_free_air_nl"]) / 1000, "k--",
                   label="oracle (knows the drift)")
        run = rec.run(run_ids[0])
        t = rec.frame("SELECT * FROM truth WHERE scenario = ? AND seed = ? ORDER BY stroke",
                      [run["scenario"], run["seed"]])
        t = {k: v[t["stroke"] <= d["stroke"][-1]] for k, v in t.items()}
        for q, lab, scale in (("friction_scale", "friction x", 1), ("valve_delay_scale",
                                                                     "valve delay x", 1),
                              ("load_mass_kg", "load / 10 kg", 0.1),
                              ("supply_pressure_gauge_pa", "supply / 2.5 bar", 1 / 2.5e5),
                              ("leak_drive_area_m2", "leak / 1e-7 m²", 1e7)):
            ax[2].plot(t["stroke"], t[q] * scale, label=lab)
    ax[0].set_ylabel("air saved vs conventional [m³ free air]")
    ax[1].set_ylabel("oracle fraction (last 100 strokes)")
    ax[1].axhline(0.95, color="grey", lw=0.8, ls=":")
    ax[1].set_ylim(0.0, 1.05)
    ax[2].set_ylabel("hidden truth")
    ax[2].set_xlabel("stroke")
    for a in ax:
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
        a.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_hourly(rec: Record, run_ids: list[str], path: str | Path) -> Path:
    """Per operating hour: saving rate, mean and worst stroke time, stalls and stick-slip
    strokes, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(9, 6), sharex=True)
    for rid in run_ids:
        rows = per_period(rec, rid, "hour")
        h = [r["period"] for r in rows]
        lab = _label(rec.run(rid)["controller"])
        ax[0, 0].plot(h, [100 * (r["saving_mean"] or 0) for r in rows], "o-", label=lab)
        line = ax[0, 1].plot(h, [r["stroke_time_mean_s"] for r in rows], "o-", label=lab)
        ax[0, 1].plot(h, [r["stroke_time_max_s"] for r in rows], ":", color=line[0].get_color())
        ax[1, 0].plot(h, [r["stalls"] for r in rows], "o-", label=lab)
        ax[1, 1].plot(h, [r["stick_slip_strokes"] for r in rows], "o-", label=lab)
    for a, y in zip(ax.flat, ("energy saved [%]", "stroke time, mean and worst [s]",
                              "stalls per hour", "stick-slip strokes per hour")):
        a.set_ylabel(y)
        a.grid(alpha=0.3)
    for a in ax[1]:
        a.set_xlabel("operating hour")
    ax[0, 0].legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _shift_table(rec: Record, ids: list[str]) -> list[str]:
    """Markdown rows: each run's figures per shift."""
    lines = ["| controller | shift | strokes | energy saved | mean stroke [s] | worst stroke [s] "
             "| stalls | stick-slip strokes | air saved [m³] | oracle fraction |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for rid in ids:
        for r in per_period(rec, rid, "shift"):
            lines.append(f"| {_label(rec.run(rid)['controller'])} | {r['period'] + 1} | {r['strokes']} | "
                         f"{100 * (r['saving_mean'] or 0):.1f} % | {_f(r['stroke_time_mean_s'])} "
                         f"| {_f(r['stroke_time_max_s'])} | {r['stalls']} | "
                         f"{r['stick_slip_strokes']} | {r['air_saved_nl'] / 1000:.2f} | "
                         f"{_f(r['oracle_fraction'])} |")
    return lines


def write_report(db: str | Path, out: str | Path, run_ids: list[str] | None = None
                 ) -> dict[str, Any]:
    """``OUT/report.md``, ``OUT/report.json``, ``OUT/<scenario>_seed<seed>.png`` (air, oracle
    fraction, drift) and ``..._hourly.png`` (per hour) for the runs (default: every run in
    ``db``). Returns the JSON structure."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with Record(db, read_only=True) as rec:
        runs = rec.runs()
        if run_ids is not None:
            runs = [r for r in runs if r["run_id"] in run_ids]
        if not runs:
            raise ValueError(f"{db}: no runs to report")
        groups: dict[tuple, list[str]] = {}
        for r in runs:
            groups.setdefault((r["scenario"], r["seed"]), []).append(r["run_id"])
        result: dict[str, Any] = {"db": str(db), "runs": {}}
        lines = ["# Operating record", "", f"Database: `{db}`", ""]
        for (sc, seed), ids in groups.items():
            if not (isinstance(sc, str) and SCENARIO_NAME.fullmatch(sc)):
                raise ValueError(f"{db}: scenario name {sc!r} cannot name a report file")
            scen = rec.run(ids[0])["config"]["scenario"]
            png = plot(rec, ids, out / f"{sc}_seed{seed}.png")
            lines += [f"## {sc} (seed {seed})", "", scen["description"], "",
                      "| controller | strokes | oracle fraction | regular strokes | "
                      f"last {LAST} strokes | air saved / oracle's | air saved [m³] | stalls | "
                      "stick-slip strokes | worst stroke [s] | recovery [strokes] |",
                      "|---|---|---|---|---|---|---|---|---|---|---|"]
            steps = step_changes(scen)
            monitored: list[str] = []
            rolled: list[str] = []
            for rid in ids:
                s = summary(rec, rid)
                s["recovery"] = {str(k): v for k, v in recovery(life(rec, rid), steps).items()}
                s["per_hour"] = per_period(rec, rid, "hour")
                s["per_shift"] = per_period(rec, rid, "shift")
                s["models"] = rec.frame("SELECT version, stroke, kind, deployed, score_new, "
                                        "score_running FROM models WHERE run_id = ? ORDER BY "
                                        "stroke", [rid])
                s["models"] = [dict(zip(s["models"], r)) for r in zip(*s["models"].values())] \
                    if s["models"] else []
                from .monitor import alarm, checkpoints

                points = checkpoints(rec, rid)
                if points:
                    s["monitor"] = {"alarm": alarm(points), "checkpoints": points}
                    monitored.append(f"- {_label(rec.run(rid)['controller'])}: {alarm(points)}")
                for kind, what in (("rollback", "rolled back to the shipped model (a "
                                                "fine-tuned one had stopped cutting)"),
                                   ("withdrawn", "withdrew a fine-tuned model that stalled on "
                                                 "probation")):
                    back = [m["stroke"] for m in s["models"] if m["kind"] == kind]
                    if back:
                        rolled.append(f"- {_label(rec.run(rid)['controller'])}: {what}, at "
                                      f"stroke {', '.join(str(k) for k in back)}")
                result["runs"][rid] = s
                saved = (None if s["air_nl"] is None  # a run with no stroke recorded yet
                         else (s["air_conventional_nl"] - s["air_nl"]) / 1000)
                rec_txt = ", ".join(f"{v if v is not None else 'never'}"
                                    for v in s["recovery"].values()) or "-"
                lines.append(f"| {_label(rec.run(rid)['controller'])} | {s['strokes']} | "
                             f"{_f(s['oracle_fraction'])} | {_f(s['oracle_fraction_regular'])} | "
                             f"{_f(s['oracle_fraction_last'])} | "
                             f"{_f(s['air_fraction'])} | "
                             f"{_f(saved, 2)} | {s['stalls']} | {s['stick_slip_strokes']} | "
                             f"{_f(s['worst_stroke_time_s'])} | {rec_txt} |")
            if rolled:
                lines += ["", "Models taken back:", ""] + rolled
            if monitored:
                lines += ["", "Condition monitoring (the discrepancy workflow on the record):",
                          ""] + monitored
            hourly = plot_hourly(rec, ids, out / f"{sc}_seed{seed}_hourly.png")
            lines += ["", f"![{sc}]({png.name})", "", "Per shift:", ""] + _shift_table(rec, ids)
            lines += ["", f"![{sc}, per hour]({hourly.name})", ""]
    (out / "report.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out / "report.json").write_text(json.dumps(_strict(result), indent=2, default=_json,
                                                allow_nan=False) + "\n",
                                     encoding="utf-8")
    return result


def _label(controller: str) -> str:
    """A controller's name for tables and plots: its spec without the model's path."""
    return controller.split("=", 1)[0]


def _f(v: Any, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _strict(v: Any) -> Any:
    """``v`` with every number that is not finite (a score never computed, no cut in a
    window) as None: report.json is strict JSON."""
    if isinstance(v, dict):
        return {k: _strict(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_strict(x) for x in v]
    if isinstance(v, np.ndarray):
        return _strict(v.tolist())
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    return v


def _json(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v))
