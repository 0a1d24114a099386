"""The operating loop: consecutive strokes of one drifting rig under one controller, each stroke
recorded (:func:`operate`).

Strokes run in blocks of ``block`` through the batched environment (the drift is a function of
the stroke number, so a block's strokes are independent of each other; a controller learns
between blocks). Before a block the controller may adapt from the record; after it the block's
measured outcome updates it, and the block, its sensor traces and the controller's checkpoint
are written in one transaction. Beside the controller's strokes the loop records the truth of
each stroke with what a conventional controller and the drift-aware oracle (the best single cut
under the true conditions, :class:`agents.oracle.OraclePolicy`) do under it, once per distinct
condition of a block (a drift step holds one).
"""
from __future__ import annotations

import datetime
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .record import Record
from .scenarios import Scenario, scenario as get_scenario

#: the operating environment's options (as every evaluation: the rig's datasheet values and
#: its commissioning stroke observed, single samples; learned policies stack their own history
#: and drop the features they do not read)
ENV_CONFIG: dict[str, Any] = {"observe_rig": True, "observe_commissioning": True}


def run_id_of(scenario: str, seed: int, controller: str) -> str:
    """The id of a run in the record."""
    return f"{scenario}/seed{seed}/{controller}"


class _Stepper:
    """Runs one block of strokes under a policy and records what the controller saw: the sensor
    samples of every step and, for controllers that learn from them, the observations at the
    cut and :data:`agents.esac.LAGS` control periods before it (in the model's layout). Rows
    ``keep`` (reference strokes) run ``keep_policy`` instead (``None``: never cut)."""

    def __init__(self, policy: Any, keep: np.ndarray, inputs: bool, lags: tuple[int, ...],
                 keep_policy: Any = None):
        self.policy, self.keep, self.inputs = policy, keep, inputs
        self.keep_policy = keep_policy
        self.lags = np.asarray(lags, dtype=np.int64)
        self.k = 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        if self.inputs:
            m = self.policy.model_obs(obs)
            a = np.asarray(self.policy.act_model(m), dtype=np.int64)
            depth = int(self.lags[-1]) + 1
            if self.k == 0:
                self.ring = np.full((depth,) + m.shape, np.nan, dtype=np.float32)
                self.at_cut = np.full((m.shape[0], self.lags.size, m.shape[1]), np.nan,
                                      dtype=np.float32)
                self.cut_seen = np.zeros(m.shape[0], dtype=bool)
            self.ring[self.k % depth] = m
        else:
            a = np.asarray(self.policy.act(obs), dtype=np.int64)
        ref = 0 if self.keep_policy is None else np.asarray(self.keep_policy.act(obs), np.int64)
        a = np.where(self.keep, ref, a)
        if self.inputs:
            new = np.flatnonzero((a == 1) & ~self.cut_seen & ~self.keep)
            for j, lag in enumerate(self.lags):
                if self.k - lag >= 0:
                    self.at_cut[new, j] = self.ring[(self.k - lag) % depth, new]
            self.cut_seen[new] = True
        self.k += 1
        return a


def dwell(env: Any, i: int, dwell_s: float, noise: tuple[float, float],
          rng: np.random.Generator) -> dict[str, np.ndarray]:
    """After stroke ``i`` of ``env`` ended (at its arrival, or stalled), hold its valve command
    for ``dwell_s`` [s] at the control rate, as the cylinder rests at the end before its return,
    and return the sensor samples (``noise``: position [m] and pressure [Pa] standard
    deviations) and ``air_mass_kg``, the air drawn from the supply from the extend command to
    the end of the rest (a supply never cut keeps filling the driving chamber). The trapped
    air's decay is where a leak shows most clearly."""
    from pneugym.envs import episode as EP
    from pneugym.physics import layout as L
    from pneugym.physics import system as K

    y, P, d, b = env.Y[i], env.P[i], env.D[i], env._b
    period = float(env.control_period_s)
    valve = 0 if env.E[i, EP.E_CUT] > 0.0 else 1
    out: dict[str, list] = {k: [] for k in ("t", "x", "p_drive", "p_exhaust", "valve")}
    t_end = float(d[L.D_T]) + dwell_s
    while True:  # the sample at the stroke's end (the last step's state), then one per period
        z = rng.standard_normal(3) * (noise[0], noise[1], noise[1])
        out["t"].append(float(d[L.D_T]))
        out["x"].append(float(y[b + L.Y_X]) + z[0])
        out["p_drive"].append(float(y[b + L.Y_SD]) + z[1])
        out["p_exhaust"].append(float(y[b + L.Y_SE]) + z[2])
        out["valve"].append(valve)
        if float(d[L.D_T]) >= t_end - 1e-9:
            break
        if K.command_advance(y, P, d, env._W[i], -1.0, period, False) != L.STATUS_OK:
            break  # a rest that cannot be stepped ends the record (never seen on the rigs here)
    rest = {k: np.asarray(v) for k, v in out.items()}
    rest["air_mass_kg"] = np.asarray(float(y[b + L.Y_MIN]))
    return rest


def known(c: Any) -> Any:
    """What a controller is told of a stroke's conditions: the supply set-point and the payload
    (an operator knows the product's mass), never friction, valve delay, leaks or dips."""
    from pneugym.envs import Conditions

    return Conditions(supply_pressure_gauge_pa=c.supply_pressure_gauge_pa,
                      load_mass_kg=c.load_mass_kg)


def commissioned(sc: Scenario, seed: int, cond: Any, base: Any) -> np.ndarray:
    """The commissioning stroke a controller is told under ``cond``: the one the life's rig made
    at its start (stroke 0's leaks; nominal friction and valve delay) at ``cond``'s operating
    point (supply set-point, payload), recorded once per operating point and then kept while
    the rig drifts (:func:`pneugym.envs.commissioning.condition_features`)."""
    from pneugym.envs import Conditions
    from pneugym.envs.commissioning import condition_features

    start = sc.conditions(0, seed)
    return condition_features(Conditions(supply_pressure_gauge_pa=cond.supply_pressure_gauge_pa,
                                         load_mass_kg=cond.load_mass_kg,
                                         rig_changes=start.rig_changes), base)


def run_block(env: Any, policy: Any, conds: list, keep: np.ndarray, seed: int, inputs: bool,
              lags: tuple[int, ...] = (0,), dwell_s: float = 0.0, privileged: bool = False,
              commissioning: list | None = None, keep_cut: str = "never"
              ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list]:
    """One block: every stroke of ``conds`` under ``policy`` (rows ``keep``, the reference
    strokes, never cut, or with ``keep_cut="arrival"`` cut off on arrival), each
    followed by a rest of ``dwell_s`` at the end (:func:`dwell`). Returns the final figures, the
    sensor traces (``row``, ``t``, ``x``, ``p_drive``, ``p_exhaust`` absolute, ``valve``) and
    each row's decision inputs (float32 bytes, or None). The policy is told each stroke's
    :func:`known` conditions, the true ones only if ``privileged`` (the oracle, the
    references), and ``commissioning`` (one stroke's features per row, :func:`commissioned`)
    when the environment observes it (else the stroke of each row's own conditions)."""
    from agents.base import ObservationReader, collect_finals
    from pneugym.units import free_air_nl

    n = env.num_envs
    read = ObservationReader(env.observation_layout())
    pa = float(env.rig.gas.ambient_pressure_pa)
    step = _Stepper(policy, keep, inputs, lags, _keep_policy(env, keep_cut))
    options: dict[str, Any] = {"conditions": list(conds)}
    if commissioning is not None:
        options["commissioning"] = list(commissioning)
    obs, _ = env.reset(seed=seed, options=options)
    policy.begin_episodes(list(conds) if privileged else [known(c) for c in conds])
    done = np.zeros(n, dtype=bool)
    out: dict[str, list] = {}
    tr: dict[str, list] = {k: [] for k in ("row", "t", "x", "p_drive", "p_exhaust", "valve")}
    while not done.all():
        a = step.act(obs)
        live = np.flatnonzero(~done)
        tr["row"].append(live)
        tr["t"].append(read(obs, "time")[live])
        tr["x"].append(read(obs, "position")[live])
        tr["p_drive"].append(read(obs, "p_drive")[live] + pa)
        tr["p_exhaust"].append(read(obs, "p_exhaust")[live] + pa)
        cut = (a[live] == 1) | (read(obs, "supply_cut")[live] > 0.5)  # the env latches the cut
        tr["valve"].append(1 - cut.astype(np.int64))
        obs, _, _, _, info = env.step(a)
        for i in collect_finals(info, done, out):
            if dwell_s > 0:
                c = conds[i]
                rest = dwell(env, int(i), dwell_s, (c.position_noise_m, c.pressure_noise_pa),
                             np.random.default_rng([seed, int(i)]))
                mass = float(rest.pop("air_mass_kg"))
                out["air_mass_kg"][i], out["free_air_nl"][i] = mass, free_air_nl(mass)
                tr["row"].append(np.full(rest["t"].size, i))
                for k, v in rest.items():
                    tr[k].append(v)
    traces = {k: np.concatenate(v) for k, v in tr.items()}
    order = np.lexsort((traces["t"], traces["row"]))
    traces = {k: v[order] for k, v in traces.items()}
    dec = [None] * n
    if inputs:
        dec = [step.at_cut[i].tobytes() if step.cut_seen[i] else None for i in range(n)]
    return {k: np.array(v, dtype=object) for k, v in out.items()}, traces, dec


def _keep_policy(env: Any, keep_cut: str) -> Any:
    """How reference strokes run: ``"never"`` cut (``None``), or ``"arrival"``: cut off on
    arrival (:class:`agents.baselines.EndStrokePolicy`, thesis 5.7)."""
    from agents.adaptive import REFERENCE_CUTS
    from agents.baselines import EndStrokePolicy

    if keep_cut not in REFERENCE_CUTS:
        raise ValueError(f"keep_cut = {keep_cut!r}: choose from {REFERENCE_CUTS}")
    return EndStrokePolicy(env.observation_layout()) if keep_cut == "arrival" else None


def references(oracle: Any, conds: list, dwell_s: float = 0.0) -> dict[str, np.ndarray]:
    """What a conventional controller and the oracle do under each of ``conds`` (noise-free;
    one plan and one batched run per distinct condition), each stroke followed by the same rest
    as the controller's (``dwell_s``), so that the air is counted alike."""
    from agents.oracle import TimedCutPolicy
    from pneugym.envs.cutoff import CutOffVectorEnv

    clean = [c.noise_free() for c in conds]
    keys = list(dict.fromkeys(c.physics_key() for c in clean))
    first = {c.physics_key(): c for c in reversed(clean)}
    uniq = [first[k] for k in keys]
    plans = oracle.plan_many(uniq)
    t_cut = np.array([math.inf] * len(uniq) + [t for t, _ in plans])
    env = CutOffVectorEnv(num_envs=t_cut.size, autoreset=False, **oracle.env_config)
    fig, _, _ = run_block(env, TimedCutPolicy(env.observation_layout(), t_cut), uniq + uniq,
                          np.zeros(t_cut.size, dtype=bool), 0, False, dwell_s=dwell_s,
                          privileged=True)
    m = len(uniq)
    per_key = {}
    for j, k in enumerate(keys):
        per_key[k] = {
            "conventional_time_s": fig["stroke_time_s"][j], "conventional_energy_j":
            fig["energy_wasted_j"][j], "conventional_free_air_nl": fig["free_air_nl"][j],
            "conventional_objective": fig["objective"][j],
            "oracle_cutoff_time_s": plans[j][0], "oracle_objective": fig["objective"][m + j],
            "oracle_free_air_nl": fig["free_air_nl"][m + j],
            "oracle_saving_ratio": fig["saving_ratio"][m + j],
            "oracle_stroke_time_s": fig["stroke_time_s"][m + j]}
    rows = [per_key[c.physics_key()] for c in clean]
    return {k: np.array([np.nan if r[k] is None else float(r[k]) for r in rows])
            for k in rows[0]}


#: the rest at the end of each stroke before its return [s]: the record holds it (the monitor
#: reads the trapped air's decay there)
DWELL_S = 0.4


def operate(scenario: str | Scenario, controller: str, strokes: int = 5000,
            db: str | Path = "ops.duckdb", seed: int = 0, block: int = 25,
            progress: bool = True, dwell_s: float = DWELL_S,
            options: dict[str, Any] | None = None, rig: Any = None,
            rig_name: str | None = None) -> str:
    """Run ``strokes`` strokes of ``scenario`` under ``controller`` (a spec of
    :func:`agents.adaptive.make_controller`: ``gaslaw``, ``esac=runs/esac``,
    ``gaslaw-adaptive``, ``esac-adaptive=runs/esac``, ...), recording every stroke in the DuckDB
    file ``db``. A run already in ``db`` with the same configuration resumes from its
    checkpoint (and returns at once if finished). Each stroke's record ends with a rest of
    ``dwell_s`` at the stroke end (the valve held). ``options``: keyword arguments of an
    adaptive ESAC controller (e.g. ``{"rollback_after": 0}``), recorded with its configuration.
    ``rig``: the operated rig (a :class:`~pneugym.params.RigParams`, a mapping or a rig file;
    default the thesis rig): the scenario runs at its stated supply and payload
    (:meth:`Scenario.on_rig`), named ``SCENARIO@NAME`` (``rig_name``, default the file's stem),
    and the record keeps the rig. Returns the run's id."""
    from tqdm import tqdm

    from agents.adaptive import MEASURED, make_controller
    from agents.esac.data import LAGS
    from agents.oracle import OraclePolicy
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    sc, env_config, env_record = on_rig(get_scenario(scenario), rig, rig_name)
    if not (isinstance(strokes, int) and strokes >= 1):
        raise ValueError(f"strokes = {strokes!r} must be an integer >= 1")
    if isinstance(seed, bool) or not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed = {seed!r} must be an integer >= 0")
    if not (isinstance(block, int) and 1 <= block <= 1024):
        raise ValueError(f"block = {block!r} must be an integer in [1, 1024]")
    if not (isinstance(dwell_s, (int, float)) and 0.0 <= dwell_s <= 10.0):
        raise ValueError(f"dwell_s = {dwell_s!r} must be in [0, 10] s")
    probe = CutOffVectorEnv(num_envs=1, **env_config)
    ctrl = make_controller(controller, probe, seed, **dict(options or {}))
    run_id = run_id_of(sc.name, seed, controller)
    config = {"scenario": sc.to_dict(), "seed": seed, "block": block, "env": env_record,
              "dwell_s": float(dwell_s), "controller": ctrl.config()}
    oracle = OraclePolicy.for_env(probe)
    with Record(db) as rec:
        start, state = rec.start_run(run_id, sc.name, seed, controller, strokes, config,
                                     provenance(), _now())
        rec.claim_truth(sc.name, seed, {"scenario": sc.to_dict(), "dwell_s": float(dwell_s),
                                        "env": env_record})
        if state is not None:
            ctrl.restore(state, rec, run_id)
        bar = tqdm(total=strokes, initial=min(start, strokes), desc=f"{sc.name} {controller}",
                   unit="stroke", disable=not progress)
        env = None
        for k0 in range(start, strokes, block):
            ks = np.arange(k0, min(k0 + block, strokes))
            models = ctrl.adapt(rec, run_id, int(k0))
            conds = [sc.conditions(int(k), seed) for k in ks]
            truth = rec.truth(sc.name, seed, int(ks[0]), int(ks[-1]))
            if truth["stroke"].size < ks.size:
                refs = references(oracle, conds, float(dwell_s))
                t = [sc.truth(int(k), seed) for k in ks]
                rec.write_truth(sc.name, seed, {"stroke": ks, **{q: [r[q] for r in t]
                                                                 for q in t[0]}, **refs})
            if env is None or env.num_envs != ks.size:
                env = CutOffVectorEnv(num_envs=ks.size, autoreset=False, **env_config)
            policy, flags = ctrl.plan(ks, [known(c) for c in conds])
            told = [commissioned(sc, seed, c, env.rig) for c in conds]
            fig, traces, dec = run_block(env, policy, conds, flags["reference"],
                                         seed=int(np.random.default_rng([seed, k0]).integers(
                                             2**31)), inputs=ctrl.needs_inputs, lags=LAGS,
                                         dwell_s=float(dwell_s), privileged=ctrl.privileged,
                                         commissioning=told, keep_cut=ctrl.references.cut)
            rows = _stroke_rows(sc, ks, fig, flags, dec, ctrl.version, conds)
            ctrl.update({k: _measured(rows[k]) for k in MEASURED})
            traces["stroke"] = ks[traces.pop("row")]
            rec.write_block(run_id, rows, traces, int(ks[-1]) + 1, ctrl.state(), models)
            bar.update(ks.size)
        bar.close()
        rec.finish_run(run_id)
    return run_id


def on_rig(sc: Scenario, rig: Any = None, rig_name: str | None = None
           ) -> tuple[Scenario, dict[str, Any], dict[str, Any]]:
    """``sc`` on ``rig`` (:meth:`Scenario.on_rig`; ``None``: the thesis rig, ``sc`` as it is),
    the operating environment's options and what the record keeps of them (the rig as
    :meth:`~pneugym.params.RigParams.to_dict`)."""
    if rig is None:
        if rig_name is not None:
            raise ValueError(f"rig_name = {rig_name!r} names no rig: give rig too")
        return sc, dict(ENV_CONFIG), dict(ENV_CONFIG)
    from pneugym.rigfile import as_rig

    base = as_rig(rig, "rig")
    if rig_name is None:
        rig_name = Path(rig).stem if isinstance(rig, (str, os.PathLike)) else "custom"
    return (sc.on_rig(base, rig_name), {**ENV_CONFIG, "rig": base},
            {**ENV_CONFIG, "rig": base.to_dict()})


def _stroke_rows(sc: Scenario, ks: np.ndarray, fig: dict, flags: dict, dec: list, version: str,
                 conds: list) -> dict[str, list]:
    def col(name: str) -> list:
        return list(fig[name])

    return {
        "stroke": ks.tolist(), "hour": [sc.hour(int(k)) for k in ks],
        "controller_version": [version] * ks.size,
        "reference": flags["reference"].tolist(), "explore": flags["explore"].tolist(),
        "supply_setpoint_pa": [c.supply_pressure_gauge_pa for c in conds],
        "cutoff_time_s": col("cutoff_time_s"), "completed": col("completed"),
        "stalled": col("stalled"), "stick_slip_events": col("stick_slip_events"),
        "stroke_time_s": col("stroke_time_s"), "final_position_m": col("position_m"),
        "energy_wasted_j": col("energy_wasted_j"),
        "energy_conventional_j": col("energy_conventional_j"), "free_air_nl": col("free_air_nl"),
        "objective": col("objective"), "saving_ratio": col("saving_ratio"),
        "decision_inputs": dec,
    }


def _measured(values: list) -> np.ndarray:
    """A block's column for a controller: numbers as float (None as NaN), flags as bool."""
    if all(isinstance(v, (bool, np.bool_)) for v in values):
        return np.asarray(values, dtype=bool)
    if all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=np.int64)
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat()
