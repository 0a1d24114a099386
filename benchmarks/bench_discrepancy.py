"""Benchmark of the discrepancy workflow (issue 5): confusion matrix, gap reduction, real data.

Run from the repository root::

    python benchmarks/bench_discrepancy.py                  # full: 3 cases per effect + 6 controls
    python benchmarks/bench_discrepancy.py --cases 5 --controls 10
    python benchmarks/bench_discrepancy.py --quick          # 1 case per effect + 2 controls
    python benchmarks/bench_discrepancy.py --only real,runtime

Sections:

matrix   plant-generated cases: one effect hidden with random parameters in plausible ranges
         (below), nominal parameters (discharge coefficient, static, Coulomb and viscous
         friction) off by up to +-5 %, supply 1.5 or 2.5 bar, 1 kHz, noise 400 Pa / 0.03 mm,
         the thesis protocol (conventional, end-stroke cut-off, early cut-off at 60 % of the
         stroke); controls: no effect, nominal parameters off by up to +-5 %. The JSON of every
         run states the default rig. Prints the confusion matrix, the right-name rate, the
         control rate and the gap reductions when named; goals: >= 90 %, >= 90 %, >= 50 %.
real     thesis Table 5.1 (friction-only path, both readings of the thesis's model) and the
         expansion-index puzzle (hidden leak, late cut-off at 1.5 bar: apparent index, then the
         index with the named leak in the model).
runtime  the whole workflow as the command line runs it (report and plots included) on three
         3 s runs at 1 kHz, default settings, all cores; goal: < 3 minutes on 2 cores.

Everything is seeded; ``benchmarks/results/discrepancy.json`` gets every number and the
configuration and versions.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

from pneugym import EffectParams, thesis_rig  # noqa: E402
from pneugym.data import thesis_protocol  # noqa: E402
from pneugym.discrepancy import CANDIDATES, Discrepancy  # noqa: E402
from pneugym.discrepancy.cases import FORM_RANGES, FORMS, PERTURB, RANGES, make_case  # noqa: E402
from pneugym.discrepancy.expansion import expansion_index  # noqa: E402
from pneugym.discrepancy.followup import simulate_plans  # noqa: E402
from pneugym.discrepancy.friction import FrictionDiscrepancy  # noqa: E402
from pneugym.parallel import add_arguments as add_parallel_arguments, run_tasks  # noqa: E402
from pneugym.params import LINE_MODELS, ORIFICE_MODELS  # noqa: E402
from pneugym.provenance import provenance  # noqa: E402

EFFECTS = tuple(CANDIDATES)
SECTIONS = {"matrix", "real", "runtime"}
LABELS = EFFECTS + ("none", "ambiguous")
#: what a row keeps of another round of the same case
ROUND_KEYS = ("named", "ambiguous", "gap_after", "gap_reduction", "gap_reduction_vs_calibrated",
              "noise_floor", "candidates", "wall_s", "holdout", "form_fits", "line_model",
              "orifice_model")


def run_case(args) -> dict:
    """One case through the workflow (a process of its own with ``--workers``). With a fifth
    item ``True`` (``--follow-up``), where the answer suggests an experiment (``none`` with the
    evidence short, or ``ambiguous``) its planned runs are made on the same true rig and the
    workflow runs again on all the runs: the row is the second answer, ``first_round`` the first.
    A sixth item (``--follow-up-holdout``) picks the second round's held-out run: ``"auto"`` (the
    workflow's rule on all the runs), ``"first"`` (the first round's), ``"both"`` (auto, then
    the first round's in ``kept_holdout``, fitted again only where the two differ)."""
    effect, seed, form, kw, *rest = args
    follow_up = bool(rest[0]) if rest else False
    holdout = rest[1] if len(rest) > 1 else "auto"
    known, truth, runs = make_case(effect, seed, form)
    t0 = time.perf_counter()
    d = Discrepancy(**kw).fit(runs)
    row = case_row(d, effect, seed, form, truth, time.perf_counter() - t0)
    plans = d.suggested_runs() if follow_up else []
    if plans:
        extra = simulate_plans(plans, truth, known, seed=seed + 100)
        first_holdout = d.holdout_runs_[0].name if d.holdout_runs_ else None
        t0 = time.perf_counter()
        d2 = Discrepancy(**{**kw, "holdout": first_holdout if holdout == "first" else "auto"}).fit(
            runs + extra)
        first = {k: row[k] for k in ROUND_KEYS}
        row = case_row(d2, effect, seed, form, truth, time.perf_counter() - t0)
        row["first_round"] = first
        row["follow_up"] = [p.to_dict() for p in plans]
        if holdout == "both":  # the same runs again, the first round's held-out run kept
            moved = [r.name for r in d2.holdout_runs_] != [first_holdout]
            t0 = time.perf_counter()
            d3 = Discrepancy(**{**kw, "holdout": first_holdout}).fit(runs + extra) if moved else d2
            kept = case_row(d3, effect, seed, form, truth, time.perf_counter() - t0)
            row["kept_holdout"] = {**{k: kept[k] for k in ROUND_KEYS}, "moved": moved}
    return row


def case_row(d: Discrepancy, effect: str, seed: int, form: str, truth, wall: float) -> dict:
    """What the matrix keeps of one fitted case."""
    cal = d.gaps_["calibrated"]["all"]["overall"]
    return {"truth": effect, "seed": seed, "form": form, "named": d.named_effect_, "ambiguous": d.ambiguous_,
            "supply_bar": truth.supply_pressure_gauge_pa / 1e5,
            "hidden": {k: v for k, v in asdict(truth.effects).items() if v != getattr(EffectParams(), k)},
            "true_form": {"line": [truth.line.model, truth.line.n_cells, truth.line.tee_volumes],
                          "valve": [truth.valve.flow_model, truth.valve.iso_b, truth.valve.linear_ratio,
                                    truth.valve.ramp_s, truth.valve_delay_s],
                          "cushion": [truth.cylinder.cushion_length_m, truth.cylinder.cushion_ramp_m]},
            "line_model": d.line_model_, "orifice_model": d.orifice_model_, "form_fits": d.form_fits_,
            "fitted": d.fitted_params_, "gap_before": d.gap_before, "gap_calibrated": cal,
            "gap_after": d.gap_after, "gap_reduction": d.gap_reduction,
            "gap_reduction_vs_calibrated": 1 - d.gap_after / cal,
            "holdout_gap_calibrated": d.gaps_["calibrated"]["holdout"]["overall"],
            "holdout_gap_after": d.gaps_["updated"]["holdout"]["overall"],
            "noise_floor": noise_floor_nrmse(d), "runs": [r.name for r in d.runs_],
            "holdout": d.holdout_runs_[0].name if d.holdout_runs_ else None,
            "candidates": [{"name": c.name, "passed": c.passed, "score": c.score,
                            "reasons": c.reasons, "effect": c.effect} for c in d.candidates_],
            "wall_s": wall}


def noise_floor_nrmse(d: Discrepancy) -> float:
    """The overall NRMSE a perfect model would have on the case's runs (its noise alone)."""
    per = []
    for c in ("x", "p_drive", "p_exhaust"):
        span = max(float(np.ptp(np.concatenate([getattr(r, c) for r in d.runs_]))), 1e-12)
        per.append(d.sigma_[c] / span)
    return float(np.mean(per))


def run_matrix(n_cases: int, n_controls: int, kw: dict, form: str = "matched", workers: int = 1,
               seed_offset: int = 0, ray_address: str | None = None, follow_up: bool = False,
               follow_up_holdout: str = "auto") -> dict:
    cases = [(e, seed_offset + 1000 * (i + 1) + k) for k, e in enumerate(EFFECTS) for i in range(n_cases)]
    cases += [("none", seed_offset + 7000 + i) for i in range(n_controls)]
    args = [(e, s, form, kw, follow_up, follow_up_holdout) for e, s in cases]
    rows = run_tasks(run_case, [{"args": a} for a in args], workers, ray_address, desc="cases",
                     pythonpath=[str(Path(__file__).resolve().parent)])
    for n, row in enumerate(rows, 1):
        print(f"[{n:2d}/{len(cases)}] {row['truth']:18s} seed {row['seed']:5d} {row['supply_bar']:.1f} bar -> "
              f"{row['named']:18s} gap {row['gap_before']:.4f} -> {row['gap_after']:.4f} "
              f"({row['gap_reduction']:+.0%}; vs calibrated {row['gap_reduction_vs_calibrated']:+.0%}; "
              f"noise floor {row['noise_floor']:.4f}) {row['wall_s']:5.1f} s"
              + (f"; first {row['first_round']['named']}, then {', '.join(p['name'] for p in row['follow_up'])}"
                 if "first_round" in row else ""), flush=True)
    out = summarise(rows)
    if follow_up:
        print("\nthe same cases before the suggested experiments (the first round):")
        out["first_round"] = summarise([{**r, **r.get("first_round", {})} for r in rows])
        out["followed_up"] = sum("first_round" in r for r in rows)
        if follow_up_holdout == "both":
            print("\nthe second round with the first round's held-out run kept "
                  f"(moved in {sum(r.get('kept_holdout', {}).get('moved', False) for r in rows)} cases):")
            out["kept_holdout"] = summarise([{**r, **r.get("kept_holdout", {})} for r in rows])
    return out


def summarise(rows: list[dict]) -> dict:
    mat = {t: {lab: 0 for lab in LABELS} for t in EFFECTS + ("none",)}
    for r in rows:
        mat[r["truth"]][r["named"]] += 1
    eff = [r for r in rows if r["truth"] != "none"]
    ctl = [r for r in rows if r["truth"] == "none"]
    right = [r for r in eff if r["named"] == r["truth"]]
    out = {
        "rows": rows, "confusion": mat,
        "name_accuracy": len(right) / len(eff) if eff else None,
        "control_accuracy": sum(r["named"] == "none" for r in ctl) / len(ctl) if ctl else None,
        "gap_reduction_when_named": {
            "min": min((r["gap_reduction"] for r in right), default=None),
            "median": float(np.median([r["gap_reduction"] for r in right])) if right else None,
            "min_vs_calibrated": min((r["gap_reduction_vs_calibrated"] for r in right), default=None),
            "median_vs_calibrated": float(np.median([r["gap_reduction_vs_calibrated"] for r in right])) if right else None,
            "share_at_least_50pct": sum(r["gap_reduction"] >= 0.5 for r in right) / len(right) if right else None,
            "share_at_least_50pct_vs_calibrated":
                sum(r["gap_reduction_vs_calibrated"] >= 0.5 for r in right) / len(right) if right else None,
        },
        "residual_over_noise_floor_when_named": {
            "max": max((r["gap_after"] / r["noise_floor"] for r in right), default=None),
            "median": float(np.median([r["gap_after"] / r["noise_floor"] for r in right])) if right else None,
            "share_within_3x": sum(r["gap_after"] <= 3 * r["noise_floor"] for r in right) / len(right)
            if right else None},
        "wall_s": {"median": float(np.median([r["wall_s"] for r in rows])), "max": max(r["wall_s"] for r in rows)},
    }
    print("\nconfusion matrix (rows: hidden effect, columns: named)")
    w = max(len(x) for x in LABELS) + 1
    print(" " * 19 + "".join(f"{lab[:w - 1]:>{w}}" for lab in LABELS))
    for t, row in mat.items():
        print(f"{t:19s}" + "".join(f"{row[lab]:>{w}}" for lab in LABELS))
    g = out["gap_reduction_when_named"]
    fmt = lambda v: "-" if v is None else f"{v:.0%}"  # noqa: E731
    print(f"\nright name in effect cases: {fmt(out['name_accuracy'])} ({len(right)}/{len(eff)}); goal >= 90 %")
    print(f"'none' in controls:         {fmt(out['control_accuracy'])} "
          f"({sum(r['named'] == 'none' for r in ctl)}/{len(ctl)}); goal >= 90 %")
    print(f"gap reduction when named:   min {fmt(g['min'])}, median {fmt(g['median'])} (vs the nominal "
          f"model of the JSON); against the calibrated nominal model min {fmt(g['min_vs_calibrated'])}, "
          f"median {fmt(g['median_vs_calibrated'])}; goal >= 50 %")
    q = out["residual_over_noise_floor_when_named"]
    if q["max"] is not None:
        print(f"updated model's overall NRMSE over the noise floor when named right: median {q['median']:.1f}x, "
              f"max {q['max']:.1f}x; within 3x in {q['share_within_3x']:.0%}")
    print(f"workflow wall time per case: median {out['wall_s']['median']:.1f} s, max {out['wall_s']['max']:.1f} s")
    if any(len(_fits(r)) > 1 for r in rows):
        # --line-models / --orifice-models: each case ran on every model form; the stated
        # form's run is the default workflow's, so the same cases give its matrix too
        print("\nthe same cases on the stated form only (the default workflow):")
        out["stated_form_only"] = summarise([stated_form(r) for r in rows])
        kept = [next((m for m, v in _fits(r).items() if v.get("kept")), r.get("line_model"))
                for r in rows]
        out["form_chosen"] = {m: kept.count(m) for m in dict.fromkeys(kept)}
    return out


def _fits(row: dict) -> dict:
    """Every model form's answer of a case (``line_fits`` in results written before the
    orifice laws were tried)."""
    return row.get("form_fits") or row.get("line_fits") or {}


def stated_form(row: dict) -> dict:
    """A case's row as the workflow on the stated model form alone gave it."""
    fits = _fits(row)
    first = fits[next(iter(fits))]
    cal = first["gap_calibrated"]
    return {**row, "named": first["named"], "gap_after": first["gap_after"], "gap_calibrated": cal,
            "gap_reduction": 1 - first["gap_after"] / row["gap_before"],
            "gap_reduction_vs_calibrated": 1 - first["gap_after"] / cal,
            "form_fits": {}, "line_fits": {}}


def run_real(kw: dict) -> dict:
    out = {}
    for static in ("breakaway", "curve"):
        f = FrictionDiscrepancy(static=static).fit()
        rep = f.report_dict()
        out[f"table_5_1_{static}"] = rep
        print(f"\nTable 5.1, static = {static!r}: named {rep['named_effect']}; RMS residual thesis "
              f"{rep['rms_n']['thesis']:.1f} N, recalibrated {rep['rms_n']['nominal']:.1f} N, with "
              f"Stribeck {rep['rms_n']['stribeck']:.1f} N (SSR -{rep['ssr_improvement']:.0%}); "
              f"F p = {rep['p_value']:.3g} (N_eff {rep['n_eff']:.1f}; white {rep['p_value_white']:.3g}); "
              f"LOO RMS {rep['loo_rms_n']['nominal']:.1f} -> {rep['loo_rms_n']['stribeck']:.1f} N")
        print(f"  worst band: {rep['worst_band']}; checks {rep['checks']}")
        for b in rep["bands"]:
            print(f"  {b['band']:24s} {b['points']:2d} points: RMS thesis {b['rms_thesis_n']:6.1f}, "
                  f"nominal {b['rms_nominal_n']:6.1f}, Stribeck {b['rms_stribeck_n']:6.1f} N")
        print(f"  Stribeck fit: {rep['stribeck_params']} +- {rep['stribeck_stderr']}")
    # the expansion-index puzzle
    known = thesis_rig(1.5)
    rng = np.random.default_rng(11)
    f = lambda: 1.0 + rng.uniform(-PERTURB, PERTURB)  # noqa: E731
    fr = known.friction
    truth = known.with_(valve={"discharge_coefficient": known.valve.discharge_coefficient * f()},
                        friction={"static_n": fr.static_n * f(), "coulomb_n": fr.coulomb_n * f(),
                                  "viscous_n_s_per_m": fr.viscous_n_s_per_m * f()},
                        effects={"leak_drive_area_m2": 3e-7})
    runs = thesis_protocol(truth, known, early_cutoff_s=0.95, seed=21)
    d = Discrepancy(**kw).fit(runs)
    early = runs[2]
    a = expansion_index(early, known)
    b = expansion_index(early, known, model=d.updated_rig(early))
    c = expansion_index(early, known, model=truth)
    out["expansion_puzzle"] = {
        "hidden": {"leak_drive_area_m2": 3e-7}, "named_effect": d.named_effect_,
        "fitted": d.fitted_params_, "apparent_index": a.__dict__, "index_with_named_effect": b.__dict__,
        "index_with_true_model": c.__dict__, "gap_before": d.gap_before, "gap_after": d.gap_after,
        "gap_reduction": d.gap_reduction}
    print(f"\nexpansion-index puzzle (1.5 bar, cut-off command 0.95 s, hidden leak 3e-7 m²): apparent index "
          f"{a.n:.2f} (eq. 5.2 end points {a.n_endpoints:.2f}; window {a.t_start_s:.2f}-{a.t_end_s:.2f} s, "
          f"V ratio {a.volume_ratio:.3f}); named {d.named_effect_} "
          f"({', '.join(f'{k} = {v:.3g}' for k, v in d.fitted_params_.items() if k.startswith('effects'))}); "
          f"index with it in the model {b.n:.2f} (end points {b.n_endpoints:.2f}; true model {c.n:.2f})")
    return out


def run_runtime(n_jobs) -> dict:
    known = thesis_rig(2.5)
    truth = known.with_(effects={"leak_piston_area_m2": 2e-7})
    runs = thesis_protocol(truth, known, seed=99)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cpu0 = os.times()
        d = Discrepancy(n_jobs=n_jobs, progress=True).fit(runs)
        d.report(tmp)
        wall = time.perf_counter() - t0
        cpu1 = os.times()
    load = os.getloadavg()
    res = {"wall_s": wall, "cpu_s_parent": cpu1.user - cpu0.user, "cpu_s_children": cpu1.children_user - cpu0.children_user,
           "n_jobs": d.config()["n_jobs"], "cpus": os.cpu_count(), "load_avg_after": load,
           "named_effect": d.named_effect_, "runs": [f"{r.name}: {len(r)} samples, {r.t[-1]:.1f} s" for r in runs]}
    print(f"\nruntime: whole workflow + report on three 3 s runs at 1 kHz: {wall:.1f} s wall "
          f"(goal < 180 s on 2 cores; {os.cpu_count()} CPUs, load average after {load[0]:.1f}); named {d.named_effect_}")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=3, help="cases per effect (default 3)")
    ap.add_argument("--controls", type=int, default=6, help="control cases (default 6)")
    ap.add_argument("--quick", action="store_true", help="1 case per effect, 2 controls")
    ap.add_argument("--only", default="matrix,real,runtime", help="sections: matrix,real,runtime")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: all cores)")
    ap.add_argument("--form", choices=FORMS, default="matched",
                    help="matched: the data have the model's form; mismatched: the data come from other "
                         "plant options (line, orifices, cushions, tee, spool) than the fitted model")
    add_parallel_arguments(ap, "the cases (then use --jobs 1)")
    ap.add_argument("--seed-offset", type=int, default=0,
                    help="added to every case's seed: 0 for the cases the workflow was developed on, "
                         "50000 for the reported mismatched-form bench (held out from development)")
    ap.add_argument("--discrepancy-term", choices=("none", "ar"), default="none",
                    help="the workflow's model of the structural error (default none; ar writes "
                         "*_ar.json)")
    ap.add_argument("--line-models", nargs="+", default=None, choices=LINE_MODELS,
                    help="supply-line models the workflow runs on (default: the stated one; "
                         "writes *_lines.json and also prints the stated line's matrix)")
    ap.add_argument("--orifice-models", nargs="+", default=None, choices=ORIFICE_MODELS,
                    help="orifice laws the workflow runs on, with each line model (default: the "
                         "stated one; writes *_forms.json and also prints the stated form's matrix)")
    ap.add_argument("--follow-up", action="store_true",
                    help="where the answer suggests an experiment (none with the evidence short, or "
                         "ambiguous), make its planned runs on the case's true rig and run the workflow "
                         "again on all the runs (writes *_followup.json; prints both rounds)")
    ap.add_argument("--follow-up-holdout", choices=("auto", "first", "both"), default="auto",
                    help="the follow-up round's held-out run: auto (the workflow's rule on all the "
                         "runs), first (the first round's), both (auto, and first where it differs)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    a = ap.parse_args(argv)
    if a.quick:
        a.cases, a.controls = 1, 2
    if a.cases > 6:  # the effects' seeds (offset + 1000 (i + 1) + k) would reach the controls'
        ap.error(f"--cases {a.cases}: at most 6 per effect (the controls' seeds start at "
                 f"offset + 7000)")
    kw = dict(seed=0, n_jobs=a.jobs,
              discrepancy_term=None if a.discrepancy_term == "none" else a.discrepancy_term,
              line_models=a.line_models, orifice_models=a.orifice_models)
    only = set(a.only.split(","))
    if not only <= SECTIONS:
        ap.error(f"--only {a.only}: unknown section(s) {sorted(only - SECTIONS)}; choose from "
                 f"{sorted(SECTIONS)}")
    res: dict = {"config": {"cases_per_effect": a.cases, "controls": a.controls, "ranges": RANGES,
                            "form": a.form, "seed_offset": a.seed_offset, "follow_up": a.follow_up,
                            "follow_up_holdout": a.follow_up_holdout,
                            "workers": a.workers, "ray_address": a.ray_address, "form_ranges": FORM_RANGES if a.form == "mismatched" else None,
                            "nominal_perturbation": PERTURB, "workflow": Discrepancy(**kw).config()},
                 "provenance": provenance()}
    t0 = time.perf_counter()
    if "matrix" in only:
        res["matrix"] = run_matrix(a.cases, a.controls, kw, a.form, a.workers, a.seed_offset,
                                   a.ray_address, a.follow_up, a.follow_up_holdout)
    if "real" in only:
        res["real"] = run_real(kw)
    if "runtime" in only:
        res["runtime"] = run_runtime(a.jobs)
    res["total_wall_s"] = time.perf_counter() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "discrepancy.json" if a.form == "matched" else "discrepancy_mismatched.json"
    if a.discrepancy_term != "none":
        name = name.replace(".json", f"_{a.discrepancy_term}.json")
    if a.orifice_models:
        name = name.replace(".json", "_forms.json")
    elif a.line_models:
        name = name.replace(".json", "_lines.json")
    if a.follow_up:
        name = name.replace(".json", "_followup.json")
    # a run of other cases or sections does not overwrite another's results
    if a.seed_offset:
        name = name.replace(".json", f"_offset{a.seed_offset}.json")
    if a.quick:
        name = name.replace(".json", "_quick.json")
    if only != SECTIONS:
        name = name.replace(".json", f"_{'-'.join(sorted(only))}.json")
    (out / name).write_text(json.dumps(res, indent=2, default=float))
    print(f"\nwritten {out / name} ({res['total_wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
