"""The operating record: every stroke in an embedded DuckDB database.

Tables (one database may hold many runs: a run is one scenario, seed and controller):

- ``runs``: ``run_id``, scenario, seed, controller, strokes asked, the configuration and the
  versions (JSON), status.
- ``strokes``: one row per stroke: the supply set-point it ran at (``supply_setpoint_pa``,
  gauge [Pa]: the operator's set-point, as the rig file's supply), what the controller
  decided (``cutoff_time_s``, its
  ``controller_version``, whether it was a ``reference`` stroke or an ``explore`` one) and
  the measured outcome (completion, stall, stick-slips, stroke time, final position, wasted
  energy, free air; ``energy_conventional_j``, the driving side's energy filled to supply at
  full stroke, the closed form of a conventional stroke's), plus the objective;
  ``decision_inputs`` (the observations the controller saw at the cut and before it, float32)
  for controllers that learn from them.
- ``traces``: the sensor samples at the control rate: ``t`` [s], ``x`` [m], ``p_drive``,
  ``p_exhaust`` [Pa absolute], ``valve`` (1 supply, 0 cut off).
- ``truth``: the hidden truth per scenario, seed and stroke (the drifting quantities), with what
  a conventional controller and the drift-aware oracle do under it. Controllers never read it.
- ``models``: every model a controller built, deployed or not, with the scores that decided.
- ``checkpoints``: each run's next stroke and the controller's state.
- ``scenarios``: the knots, rest and environment each scenario name's truth was made with.

A block of strokes, its traces and the checkpoint are written in one transaction: an
interrupted run leaves no half-written stroke, and resumes from its checkpoint.
DuckDB is an optional dependency (``pip install -e ".[operation]"``).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id VARCHAR PRIMARY KEY, scenario VARCHAR, seed BIGINT, controller VARCHAR,
    strokes BIGINT, config JSON, provenance JSON, started_utc VARCHAR, status VARCHAR);
CREATE TABLE IF NOT EXISTS strokes (
    run_id VARCHAR, stroke BIGINT, hour DOUBLE, controller_version VARCHAR,
    reference BOOLEAN, explore BOOLEAN, supply_setpoint_pa DOUBLE, cutoff_time_s DOUBLE,
    completed BOOLEAN, stalled BOOLEAN, stick_slip_events INTEGER, stroke_time_s DOUBLE,
    final_position_m DOUBLE, energy_wasted_j DOUBLE, free_air_nl DOUBLE, objective DOUBLE,
    saving_ratio DOUBLE, decision_inputs BLOB, energy_conventional_j DOUBLE,
    PRIMARY KEY (run_id, stroke));
ALTER TABLE strokes ADD COLUMN IF NOT EXISTS energy_conventional_j DOUBLE;
CREATE TABLE IF NOT EXISTS traces (
    run_id VARCHAR, stroke BIGINT, t DOUBLE, x DOUBLE, p_drive DOUBLE, p_exhaust DOUBLE,
    valve TINYINT);
CREATE TABLE IF NOT EXISTS truth (
    scenario VARCHAR, seed BIGINT, stroke BIGINT, supply_pressure_gauge_pa DOUBLE,
    load_mass_kg DOUBLE, friction_scale DOUBLE, valve_delay_scale DOUBLE,
    leak_drive_area_m2 DOUBLE, conventional_time_s DOUBLE, conventional_energy_j DOUBLE,
    conventional_free_air_nl DOUBLE, conventional_objective DOUBLE, oracle_cutoff_time_s DOUBLE,
    oracle_objective DOUBLE, oracle_free_air_nl DOUBLE, oracle_saving_ratio DOUBLE,
    oracle_stroke_time_s DOUBLE, PRIMARY KEY (scenario, seed, stroke));
CREATE TABLE IF NOT EXISTS models (
    run_id VARCHAR, version VARCHAR, stroke BIGINT, kind VARCHAR, deployed BOOLEAN,
    score_new DOUBLE, score_running DOUBLE, detail JSON, blob BLOB);
CREATE TABLE IF NOT EXISTS scenarios (
    scenario VARCHAR, seed BIGINT, spec JSON, PRIMARY KEY (scenario, seed));
CREATE TABLE IF NOT EXISTS checkpoints (
    run_id VARCHAR PRIMARY KEY, next_stroke BIGINT, state BLOB);
"""
#: the tables :meth:`Record.export_parquet` writes (all but the controllers' checkpoints;
#: ``monitor`` is the condition monitor's, :mod:`pneugym.operation.monitor`)
EXPORTED = ("models", "monitor", "runs", "scenarios", "strokes", "traces", "truth")
STROKE_COLUMNS = ("stroke", "hour", "controller_version", "reference", "explore",
                  "supply_setpoint_pa", "cutoff_time_s", "completed", "stalled",
                  "stick_slip_events", "stroke_time_s", "final_position_m", "energy_wasted_j",
                  "energy_conventional_j", "free_air_nl", "objective", "saving_ratio",
                  "decision_inputs")
TRACE_COLUMNS = ("stroke", "t", "x", "p_drive", "p_exhaust", "valve")
TRUTH_COLUMNS = ("stroke", "supply_pressure_gauge_pa", "load_mass_kg", "friction_scale",
                 "valve_delay_scale", "leak_drive_area_m2", "conventional_time_s",
                 "conventional_energy_j", "conventional_free_air_nl", "conventional_objective",
                 "oracle_cutoff_time_s", "oracle_objective", "oracle_free_air_nl",
                 "oracle_saving_ratio", "oracle_stroke_time_s")


def _duckdb():
    try:
        import duckdb
    except ImportError:  # pragma: no cover - the extra is missing
        raise ImportError("the operating record needs DuckDB: pip install -e \".[operation]\"") \
            from None
    return duckdb


class Record:
    """An operating record in DuckDB at ``path`` (created if absent; ``":memory:"`` for none).
    Use as a context manager, or :meth:`close` it."""

    def __init__(self, path: str | Path = ":memory:", read_only: bool = False):
        self.path = str(path)
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        self.con = _duckdb().connect(self.path, read_only=read_only)
        if not read_only:
            self.con.execute(SCHEMA)

    def __enter__(self) -> "Record":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self.con.close()

    # -- runs ----------------------------------------------------------------------------------
    def run(self, run_id: str) -> dict[str, Any] | None:
        """A run's row (config and provenance parsed), or None."""
        row = self.con.execute("SELECT * FROM runs WHERE run_id = ?", [run_id]).fetchone()
        if row is None:
            return None
        cols = [d[0] for d in self.con.description]
        out = dict(zip(cols, row))
        for k in ("config", "provenance"):
            out[k] = json.loads(out[k]) if out[k] else None
        return out

    def runs(self) -> list[dict[str, Any]]:
        """Every run's id, scenario, seed, controller, strokes asked, recorded and status."""
        q = ("SELECT r.run_id, r.scenario, r.seed, r.controller, r.strokes, r.status, "
             "count(s.stroke) AS recorded FROM runs r LEFT JOIN strokes s USING (run_id) "
             "GROUP BY ALL ORDER BY r.run_id")
        cur = self.con.execute(q)
        cols = [d[0] for d in cur.description]
        return [dict(zip(cols, r)) for r in cur.fetchall()]

    def start_run(self, run_id: str, scenario: str, seed: int, controller: str, strokes: int,
                  config: Mapping[str, Any], provenance: Mapping[str, Any], started: str
                  ) -> tuple[int, bytes | None]:
        """Register a run, or find it to resume: returns ``(next stroke, controller state)``.
        A run of the same id with another configuration is refused (name another database or
        controller)."""
        old = self.run(run_id)
        cfg = json.loads(json.dumps(config))
        if old is not None:
            if old["config"] != cfg:
                diff = sorted(k for k in set(cfg) | set(old["config"])
                              if cfg.get(k) != old["config"].get(k))
                raise ValueError(f"{self.path} already holds run {run_id!r} with another "
                                 f"configuration (differs in {diff}); give another --db or "
                                 f"remove the run (pneugym operate --remove RUN)")
            self.con.execute("UPDATE runs SET strokes = ?, status = 'running' WHERE run_id = ?",
                             [strokes, run_id])
            ck = self.con.execute("SELECT next_stroke, state FROM checkpoints WHERE run_id = ?",
                                  [run_id]).fetchone()
            return (0, None) if ck is None else (int(ck[0]), ck[1])
        self.con.execute("INSERT INTO runs VALUES (?, ?, ?, ?, ?, ?, ?, ?, 'running')",
                         [run_id, scenario, seed, controller, strokes, json.dumps(cfg),
                          json.dumps(provenance), started])
        return 0, None

    def remove_run(self, run_id: str) -> int:
        """Delete a run: its strokes, traces, models, checkpoint and monitoring (the truth of its
        scenario stays for the other runs). Returns the strokes removed."""
        if self.run(run_id) is None:
            raise ValueError(f"no run {run_id!r} in {self.path}")
        n = int(self.con.execute("SELECT count(*) FROM strokes WHERE run_id = ?",
                                 [run_id]).fetchone()[0])
        tables = [r[0] for r in self.con.execute(
            "SELECT table_name FROM information_schema.tables").fetchall()]
        self.con.execute("BEGIN TRANSACTION")
        try:
            for t in ("strokes", "traces", "models", "checkpoints", "monitor", "runs"):
                if t in tables:
                    self.con.execute(f"DELETE FROM {t} WHERE run_id = ?", [run_id])
            self.con.execute("COMMIT")
        except BaseException:
            self.con.execute("ROLLBACK")
            raise
        return n

    def finish_run(self, run_id: str, status: str = "finished") -> None:
        self.con.execute("UPDATE runs SET status = ? WHERE run_id = ?", [status, run_id])

    # -- writing a block -----------------------------------------------------------------------
    def write_block(self, run_id: str, strokes: Mapping[str, Sequence[Any]],
                    traces: Mapping[str, np.ndarray], next_stroke: int, state: bytes,
                    models: Sequence[Mapping[str, Any]] = ()) -> None:
        """One block of strokes, their traces, the models built and the checkpoint, in one
        transaction (all or nothing)."""
        n = len(strokes["stroke"])
        s = {k: list(strokes[k]) for k in STROKE_COLUMNS}
        s["run_id"] = [run_id] * n
        tr = {k: np.asarray(traces[k]) for k in TRACE_COLUMNS}
        tr_run = np.full(tr["t"].size, run_id, dtype=object)
        con = self.con
        con.execute("BEGIN TRANSACTION")
        try:
            cols = ", ".join(STROKE_COLUMNS)
            con.executemany(f"INSERT INTO strokes (run_id, {cols}) VALUES "
                            f"({', '.join('?' * (len(STROKE_COLUMNS) + 1))})",
                            [[s["run_id"][i]] + [_py(s[k][i]) for k in STROKE_COLUMNS]
                             for i in range(n)])
            frame = {"run_id": tr_run, **tr}  # noqa: F841 (read by DuckDB by name)
            con.execute(f"INSERT INTO traces SELECT run_id, {', '.join(TRACE_COLUMNS)} "
                        f"FROM frame")
            for m in models:
                con.execute("INSERT INTO models VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                            [run_id, m["version"], m["stroke"], m["kind"], m["deployed"],
                             _py(m.get("score_new")), _py(m.get("score_running")),
                             json.dumps(m.get("detail", {})), m.get("blob")])
            con.execute("INSERT OR REPLACE INTO checkpoints VALUES (?, ?, ?)",
                        [run_id, next_stroke, state])
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise

    def claim_truth(self, scenario: str, seed: int, spec: Mapping[str, Any]) -> None:
        """Tie ``scenario`` and ``seed``'s truth rows to ``spec`` (the scenario's knots, the rest
        at the stroke end, the environment): another spec under the same name is refused, never
        joined to stale references."""
        text = json.dumps(json.loads(json.dumps(spec)), sort_keys=True)
        row = self.con.execute("SELECT spec FROM scenarios WHERE scenario = ? AND seed = ?",
                               [scenario, seed]).fetchone()
        if row is None:
            self.con.execute("INSERT INTO scenarios VALUES (?, ?, ?)", [scenario, seed, text])
        elif json.loads(row[0]) != json.loads(text):
            raise ValueError(f"{self.path} holds scenario {scenario!r} (seed {seed}) with other "
                             f"knots, rest or environment; name the scenario differently or give "
                             f"another --db")

    def write_truth(self, scenario: str, seed: int, rows: Mapping[str, Sequence[Any]]) -> None:
        """Truth rows of ``scenario`` and ``seed`` (strokes already there are kept)."""
        frame = {"scenario": np.full(len(rows["stroke"]), scenario, dtype=object),  # noqa: F841
                 "seed": np.full(len(rows["stroke"]), seed, dtype=np.int64),
                 **{k: np.asarray(rows[k]) for k in TRUTH_COLUMNS}}
        self.con.execute(f"INSERT OR IGNORE INTO truth SELECT scenario, seed, "
                         f"{', '.join(TRUTH_COLUMNS)} FROM frame")

    def truth(self, scenario: str, seed: int, first: int, last: int) -> dict[str, np.ndarray]:
        """Truth rows of strokes ``first`` to ``last`` (inclusive) already recorded."""
        return self.frame("SELECT * FROM truth WHERE scenario = ? AND seed = ? AND stroke "
                          "BETWEEN ? AND ? ORDER BY stroke", [scenario, seed, first, last])

    # -- reading -------------------------------------------------------------------------------
    def frame(self, query: str, params: Sequence[Any] = ()) -> dict[str, np.ndarray]:
        """A query's result as ``{column: numpy array}``."""
        cur = self.con.execute(query, list(params))
        cols = [d[0] for d in cur.description]
        rows = cur.fetchall()
        return {c: _column([r[i] for r in rows]) for i, c in enumerate(cols)}

    def strokes(self, run_id: str, first: int = 0, last: int | None = None,
                columns: Sequence[str] = STROKE_COLUMNS[:-1]) -> dict[str, np.ndarray]:
        """Recorded strokes of a run (``decision_inputs`` only if asked for), by stroke."""
        last = 2**62 if last is None else last
        have = {r[0] for r in self.con.execute(
            "SELECT column_name FROM information_schema.columns WHERE table_name = 'strokes'"
        ).fetchall()}  # a record written before a column was added reads it as NULL
        cols = ", ".join(c if c in have else f"NULL AS {c}" for c in columns)
        return self.frame(f"SELECT {cols} FROM strokes WHERE run_id = ? AND "
                          f"stroke BETWEEN ? AND ? ORDER BY stroke", [run_id, first, last])

    def trace(self, run_id: str, stroke: int) -> dict[str, np.ndarray]:
        """One stroke's sensor samples."""
        return self.frame("SELECT t, x, p_drive, p_exhaust, valve FROM traces WHERE run_id = ? "
                          "AND stroke = ? ORDER BY t", [run_id, stroke])

    def export_parquet(self, out: str | Path) -> list[Path]:
        """The record's tables (:data:`EXPORTED`, those the file holds) as
        ``OUT/<table>.parquet`` (DuckDB's own writer); other tables in the file are left."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        files = []
        held = {r[0] for r in self.con.execute(
            "SELECT table_name FROM information_schema.tables").fetchall()}
        for table in (t for t in EXPORTED if t in held):
            f = out / f"{table}.parquet"
            self.con.execute(f'COPY "{table}" TO \'{_quote(f)}\' (FORMAT PARQUET)')
            files.append(f)
        return files


def _column(values: list) -> np.ndarray:
    """Query values as an array: numbers with NULL as float (NaN), else as they come."""
    if values and all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
                      for v in values) and any(v is None for v in values):
        return np.array([np.nan if v is None else v for v in values], dtype=float)
    return np.array(values) if not any(isinstance(v, bytes) for v in values) else \
        np.array(values, dtype=object)


def _quote(path: Path) -> str:
    return str(path).replace("'", "''")


def _py(v: Any) -> Any:
    """A numpy scalar as a Python value (NaN as NULL)."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and v != v:
        return None
    return v


def run_rig(config: Mapping[str, Any] | None) -> Any:
    """The rig a run operated (from its recorded configuration; ``pneugym operate --rig``), or
    None for the thesis rig."""
    from ..rigfile import as_rig

    rig = ((config or {}).get("env") or {}).get("rig")
    return None if rig is None else as_rig(rig, "the run's recorded rig")


def export_runs(rec: Record, run_id: str, out: str | Path, first: int = 0,
                last: int | None = None) -> list[Path]:
    """Strokes ``first`` to ``last`` of a run as ``pneugym-measurement/1`` runs in ``out`` (one
    CSV + JSON pair per stroke, at the control rate; the rig section is the operated rig as
    commissioned at each stroke's supply, whose valve switches faster at a higher supply
    (thesis Fig. 3.6; the format states the delay itself), the load and supply each stroke's),
    e.g. for the discrepancy workflow; described as ``conventional`` (uncut), ``end_stroke_cutoff``
    (a reference stroke cut off on arrival) or ``early_cutoff``."""
    from ..data import FORMAT, MeasuredRun, write_run
    from ..params import RigParams

    run = rec.run(run_id)
    if run is None:
        raise ValueError(f"no run {run_id!r} in {rec.path}")
    rig = run_rig(run["config"]) or RigParams()
    last = 2**62 if last is None else last
    meta = rec.frame("SELECT s.stroke, s.supply_setpoint_pa, t.load_mass_kg, s.cutoff_time_s, "
                     "s.reference FROM strokes s JOIN truth t ON t.scenario = ? AND t.seed = ? AND "
                     "t.stroke = s.stroke WHERE s.run_id = ? AND s.stroke BETWEEN ? AND ? "
                     "ORDER BY s.stroke", [run["scenario"], run["seed"], run_id, first, last])
    out = Path(out)
    files = []
    for k, ps, load, tc, ref in zip(*(meta[c] for c in ("stroke", "supply_setpoint_pa",
                                                        "load_mass_kg", "cutoff_time_s",
                                                        "reference"))):
        tr = rec.trace(run_id, int(k))
        m = {"format": FORMAT, "supply_pressure_gauge_pa": float(ps),
             "load_mass_kg": float(load),
             "ambient_pressure_pa": rig.gas.ambient_pressure_pa,
             "ambient_temperature_k": rig.gas.ambient_temperature_k,
             "sample_rate_hz": 1.0 / float(np.median(np.diff(tr["t"]))),
             "rig": rig.with_(supply_pressure_gauge_pa=float(ps)).to_measurement_rig(),
             "description": ("conventional" if np.isnan(tc) else
                             "end_stroke_cutoff" if ref else "early_cutoff"),
             "operation": {"run_id": run_id, "stroke": int(k)}}
        files.append(write_run(MeasuredRun(
            name=f"stroke{int(k):07d}", t=tr["t"], valve=tr["valve"].astype(float), x=tr["x"],
            p_drive=tr["p_drive"], p_exhaust=tr["p_exhaust"], meta=m),
            out / f"stroke{int(k):07d}"))
    return files
