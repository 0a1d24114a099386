"""Outputs of the workflow: ``report.json``, ``report.md``, ``updated_model.json`` and PNG plots,
written as a set (:func:`pneugym.outputs.staged_files`): a failure leaves the old set untouched."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..data import MeasuredRun
from ..outputs import check_output_dir, staged_files
from ..params import RigParams
from ..provenance import provenance
from .candidates import FitParam
from .fit import FitResult
from .followup import RunPlan
from .prepare import Preparation
from .residuals import (
    CHANNELS,
    PHASE_TEXT,
    PHASES,
    UNITS,
    Finding,
    RunPhases,
    channels_of,
    phase_shares,
    reduction,
)

REPORT_FORMAT = "pneugym-discrepancy-report/1"
NRMSE_DEFINITION = (
    "per channel c: NRMSE_c = sqrt(mean over the samples of all runs in the set of "
    "(measured_c - simulated_c)^2) / (max - min of measured_c over the set); overall NRMSE = "
    "mean of NRMSE_c over the compared channels (x, p_drive, p_exhaust, plus mdot_supply and "
    "T_drive where measured)")
#: findings worse than this (RMS residual in noise sigmas) are listed as failures
FAIL_Z = 3.0
#: the PNG plots :func:`write_plots` writes
PLOTS = ("overlays.png", "residuals.png", "candidates.png")
PHASE_COLOURS = {"before_motion": "#dddddd", "stroke": "#d6e9f8", "trapped": "#fde3c8",
                 "end_supply": "#dcf2d5"}


class FittedDiscrepancy(Protocol):
    """What the report reads of a fitted :class:`~pneugym.discrepancy.Discrepancy`: its results
    after ``fit`` (defined here so that the report needs nothing of the workflow module, which
    imports this one). ``candidates_`` holds :class:`~pneugym.discrepancy.CandidateResult`
    entries, best first; the optional ``no_gap_``, ``noise_at_floor_`` and ``separation_`` are
    read with ``getattr``."""

    runs_: list[MeasuredRun]
    fit_runs_: list[MeasuredRun]
    holdout_runs_: list[MeasuredRun]
    rigs_: list[RigParams]
    phases_: list[RunPhases]
    preparation_: list[Preparation]
    sigma_: dict[str, float]
    sims_: dict[str, list[dict[str, np.ndarray]]]
    findings_: dict[str, list[Finding]]
    candidates_: list[Any]
    nominal_params_: tuple[FitParam, ...]
    calibrated_: FitResult
    fitted_params_: dict[str, float]
    gaps_: dict[str, dict[str, dict[str, float]]]
    named_effect_: str
    decision_: str
    ambiguous_: list[str]
    suggestion_: str | None
    warnings_: list[str]
    wall_time_s_: float
    min_improvement: float
    discrepancy_term: str | None

    def suggested_runs(self) -> list[Any]: ...

    @property
    def held_out_tested(self) -> bool: ...

    @property
    def gap_before(self) -> float: ...

    @property
    def gap_after(self) -> float: ...

    @property
    def gap_reduction(self) -> float | None: ...

    @property
    def updated_model(self) -> RigParams: ...

    def config(self) -> dict[str, Any]: ...


def _clean(o: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.bool_, bool)):
        return bool(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, Path):
        return str(o)
    return o


def report_dict(d: FittedDiscrepancy, updated_model_path: str | None = None) -> dict[str, Any]:
    """Everything the report says, as plain JSON-able data."""
    hold = {r.name for r in d.holdout_runs_}
    cal = d.gaps_["calibrated"]["all"]["overall"]
    runs = []
    for r, ph, rig, prep in zip(d.runs_, d.phases_, d.rigs_, d.preparation_):
        runs.append({
            "name": r.name, "source": str(r.source) if r.source else None,
            "description": r.description, "role": "holdout" if r.name in hold else "fit",
            "samples": len(r), "duration_s": float(r.t[-1] - r.t[0]),
            "sample_rate_hz": 1.0 / r.sample_dt_s, "channels": list(channels_of(r)),
            "supply_pressure_gauge_pa": rig.supply_pressure_gauge_pa, "load_mass_kg": rig.load_mass_kg,
            "valve_commands": r.schedule(), "t_motion_s": ph.t_motion_s, "t_arrival_s": ph.t_arrival_s,
            "t_cut_effective_s": ph.t_cut_effective_s,
            "phases": [{"phase": p, "t_start_s": a, "t_end_s": b} for p, a, b in ph.spans(r.t)],
            "preparation": prep.to_json(),
        })
    failures = [f.sentence() for f in d.findings_["calibrated"] if f.rms_z > FAIL_Z]
    return _clean({
        "format": REPORT_FORMAT,
        "named_effect": d.named_effect_,
        "decision": d.decision_,
        "held_out_tested": d.held_out_tested,
        "warnings": d.warnings_,
        "ambiguous_between": d.ambiguous_,
        "suggested_experiment": d.suggestion_,
        # the same as strokes to measure (followup.RunPlan): run them, then the workflow again
        "suggested_runs": [p.to_dict() for p in d.suggested_runs()],
        "candidates": [c.to_json() for c in d.candidates_],
        "fitted_params": d.fitted_params_,
        "calibrated_params": d.calibrated_.as_dict(),
        # the model form kept, and each form's answer and fit (line_models, orifice_models)
        "line_model": getattr(d, "line_model_", None),
        "orifice_model": getattr(d, "orifice_model_", None),
        "form_fits": getattr(d, "form_fits_", {}),
        # these are factors on the value each run's JSON states, not values in the field's unit
        "relative_params": [p.path for p in d.nominal_params_ if p.relative],
        "nominal_params": {p.path: float(v) for p, v in zip(
            d.nominal_params_, [p.stated(d.rigs_[d.runs_.index(d.fit_runs_[0])]) for p in d.nominal_params_])},
        "gap_before": d.gap_before,
        "gap_after": d.gap_after,
        "gap_reduction": d.gap_reduction,
        "gap_calibrated": cal,
        "gap_reduction_vs_calibrated": reduction(cal, d.gap_after),
        "no_gap": bool(getattr(d, "no_gap_", False)),
        "gaps": d.gaps_,
        "nrmse_definition": NRMSE_DEFINITION,
        "updated_model": updated_model_path,
        "holdout": sorted(hold),
        "runs": runs,
        "noise_sigma": d.sigma_,
        "noise_at_floor": getattr(d, "noise_at_floor_", []),
        "failures": failures,
        "localisation": {m: [f.__dict__ for f in fs] for m, fs in d.findings_.items()},
        "separation": getattr(d, "separation_", None),
        "config": d.config(),
        "wall_time_s": d.wall_time_s_,
        "provenance": provenance(),
    })


def write_report(d: FittedDiscrepancy, out: str | Path, plots: bool = True) -> Path:
    """Write the report files into ``out`` (created) as a whole: they are written to a staging
    folder and renamed into ``out`` only once all are written, so a failure leaves the old
    report, model and plots as they were. Plots of an earlier report that this one does not
    write are then removed. Returns the path of ``report.json``."""
    out = check_output_dir(out, "report folder")
    with staged_files(out) as stage:
        (stage / "updated_model.json").write_text(
            json.dumps(_clean(d.updated_model.to_dict()), indent=2, allow_nan=False) + "\n",
            encoding="utf-8")
        rep = report_dict(d, str(out / "updated_model.json"))
        if plots:
            rep["plots"] = [str(out / p.name) for p in write_plots(d, stage)]
        (stage / "report.json").write_text(json.dumps(rep, indent=2, allow_nan=False) + "\n",
                                           encoding="utf-8")
        (stage / "report.md").write_text(markdown(rep), encoding="utf-8")
    for name in PLOTS if not plots else ():
        (out / name).unlink(missing_ok=True)  # stale: not part of this report
    return out / "report.json"


# ------------------------------------------------------------------------------------------
def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def markdown(rep: dict[str, Any]) -> str:
    """A readable report from :func:`report_dict`."""
    L: list[str] = ["# Discrepancy report", ""]
    L += [f"> **Warning: {w}**" for w in rep.get("warnings", [])]
    L += [""] if rep.get("warnings") else []
    L += [f"**Named effect: `{rep['named_effect']}`**", "", rep["decision"], ""]
    if rep.get("suggested_experiment") and rep.get("ambiguous_between"):
        L += [(f"Suggested experiment to separate {' and '.join(rep['ambiguous_between'])}: "
               f"{rep['suggested_experiment']}"), ""]
    elif rep.get("suggested_experiment"):
        L += [f"Suggested experiment (the evidence is short): {rep['suggested_experiment']}", ""]
    if rep.get("suggested_runs"):
        L += ["As strokes to measure (`suggested_runs` in report.json; record them in the "
              "measurement format and run the workflow again on every run):", ""]
        L += [f"- {RunPlan(**p).sentence()}" for p in rep["suggested_runs"]] + [""]
    fits = rep.get("form_fits") or {}
    if len(fits) > 1:
        stated = next(iter(fits))
        kept = next(m for m, v in fits.items() if v["kept"])
        tried = "; ".join(f"`{m}`: named `{v['named']}`, NRMSE {v['gap_after']:.4g}, Akaike "
                          f"{v['aic_above_best']:+.1f} over the best" for m, v in fits.items())
        verdict = (f"the stated `{stated}` kept (no other fits clearly better)" if kept == stated
                   else f"**`{kept}` fits clearly better than the stated `{stated}`** and is the "
                        f"updated model's form ({rep['line_model']} line, {rep['orifice_model']} law)")
        L += [f"Model form: the workflow ran on each form ({tried}); {verdict}.", ""]
    g = rep["gaps"]
    L += ["## Gap (NRMSE)", "",
          (f"Overall NRMSE over all runs: **{rep['gap_before']:.4g} before** (nominal model from the "
           f"runs' JSON) -> {rep['gap_calibrated']:.4g} (calibrated nominal) -> **{rep['gap_after']:.4g} "
           f"after** (updated model): " + (
               "**no gap to reduce** (the nominal model reproduces the runs to round-off)."
               if rep["gap_reduction"] is None else
               f"reduction **{rep['gap_reduction']:.1%}** "
               f"({_pct(rep['gap_reduction_vs_calibrated'])} against the calibrated nominal model).")),
          "",
          f"NRMSE: {rep['nrmse_definition']}.", ""]
    chans = [c for c in CHANNELS if c in g["nominal"]["all"]]
    L += ["| model | runs | overall | " + " | ".join(chans) + " |",
          "|---|---|---|" + "---|" * len(chans)]
    for m in ("nominal", "calibrated", "updated"):
        for s in ("fit", "holdout", "all"):
            if s in g[m]:
                L.append(f"| {m} | {s} | {g[m][s]['overall']:.4g} | "
                         + " | ".join(f"{g[m][s].get(c, float('nan')):.4g}" for c in chans) + " |")
    L += ["", "## Runs", "", "| run | role | description | samples | supply (bar g) | motion at | arrival at | cut-off reaches valve at |",
          "|---|---|---|---|---|---|---|---|"]
    for r in rep["runs"]:
        L.append(f"| {r['name']} | {r['role']} | {r['description'] or '-'} | {r['samples']} | "
                 f"{r['supply_pressure_gauge_pa'] / 1e5:.3g} | {_sec(r['t_motion_s'])} | "
                 f"{_sec(r['t_arrival_s'])} | {_sec(r['t_cut_effective_s'])} |")
    changed = [r["preparation"]["sentence"] for r in rep["runs"]
               if r["preparation"]["windowed"] or r["preparation"]["block"] > 1]
    if changed:
        L += ["", ("Long runs were cut to the part that carries information before the fit "
                   "(everything in this report refers to the runs as cut):"), ""]
        L += [f"- {s}" for s in changed]
    floor = set(rep.get("noise_at_floor", []))
    L += ["", "Noise levels estimated from quiet segments: "
          + ", ".join(f"{c} {v:.3g} {UNITS[c]}" + (" (floor: no noise found)" if c in floor else "")
                      for c, v in rep["noise_sigma"].items()), ""]
    L += ["## Where the calibrated nominal model fails", ""]
    if rep["failures"]:
        L += [f"- {s}" for s in rep["failures"][:12]]
        if len(rep["failures"]) > 12:
            L.append(f"- ... {len(rep['failures']) - 12} more in report.json (localisation)")
    else:
        L.append(f"Nowhere: every run, phase and channel is within {FAIL_Z:g} sigma RMS.")
    L += ["", "Residual RMS in noise sigmas, per phase (calibrated nominal -> updated model):", "",
          "| run | channel | " + " | ".join(PHASE_TEXT[p] for p in PHASES) + " |",
          "|---|---|" + "---|" * len(PHASES)]
    loc = {m: {(f["run"], f["channel"], f["phase"]): f["rms_z"] for f in rep["localisation"][m]}
           for m in ("calibrated", "updated")}
    for r in rep["runs"]:
        for c in chans:
            cells = []
            for p in PHASES:
                a, b = loc["calibrated"].get((r["name"], c, p)), loc["updated"].get((r["name"], c, p))
                cells.append("-" if a is None else f"{a:.1f} -> {b:.1f}")
            L.append(f"| {r['name']} | {c} | " + " | ".join(cells) + " |")
    if rep["candidates"]:
        L += ["", "## Candidates (best first)", "",
              "| candidate | passed | score | where (share removed per phase) | fit improvement | held-out improvement | F (p) | N_eff | parameters | why not |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    else:
        L += ["", "## Candidates", "", "None fitted: there is no gap to reduce."]
    for c in rep["candidates"]:
        pars = ", ".join(f"{k} = {_fmt(v)} ± {_fmt(c['stderr'].get(k))}" for k, v in c["parameters"].items())
        where = phase_shares(c.get("by_phase", {}))
        L.append(f"| {c['name']} | {_fmt(c['passed'])} | {c['score']:+.3f} | {where or '-'} | {c['improvement_fit']:+.1%} | "
                 f"{_pct(c['improvement_holdout'])} | {_fmt(c['F'], 3)} ({_fmt(c['p_value'], 2)}) | "
                 f"{_fmt(c['n_eff'], 3)} | {pars} | {'; '.join(c['reasons']) or '-'} |")
    L += ["", "## Fitted parameters", "",
          "Factors (`x stated`) multiply the value each run's JSON states.", "",
          "| parameter | as given | calibrated | updated model |", "|---|---|---|---|"]
    factors = set(rep.get("relative_params", []))
    for k, v in rep["fitted_params"].items():
        name = f"{k} (x stated)" if k in factors else k
        L.append(f"| {name} | {_fmt(rep['nominal_params'].get(k))} | {_fmt(rep['calibrated_params'].get(k))} | {_fmt(v)} |")
    L += ["", (f"Updated model (load with `RigParams.from_dict(json.load(open(path)))`): "
               f"`{rep['updated_model']}`"), ""]
    if rep.get("plots"):
        L += ["## Plots", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in rep["plots"]] + [""]
    cfg = rep["config"]
    L += ["## How this was made", "",
          (f"Workflow settings: {json.dumps(cfg)}. Wall time {rep['wall_time_s']:.1f} s. "
           f"Versions: {json.dumps(rep['provenance']['versions'])}; commit "
           f"{rep['provenance']['git_commit']}."), ""]
    return "\n".join(L)


def _sec(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g} s"


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:+.1%}"


# ------------------------------------------------------------------------------------------
def write_plots(d: FittedDiscrepancy, out: Path) -> list[Path]:
    """``overlays.png``, ``residuals.png``, ``candidates.png``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hold = {r.name for r in d.holdout_runs_}
    chans = [c for c in CHANNELS if c in d.sims_["nominal"][0]]
    scale = {"x": (1e3, "x [mm]"), "p_drive": (1e-5, "p_drive [bar abs]"),
             "p_exhaust": (1e-5, "p_exhaust [bar abs]"), "mdot_supply": (1e3, "mdot_supply [g/s]"),
             "T_drive": (1.0, "T_drive [K]")}
    paths = []
    nr, nc = len(d.runs_), len(chans)

    fig, axes = plt.subplots(nr, nc, figsize=(4.2 * nc, 2.6 * nr), squeeze=False, sharex=True)
    for i, r in enumerate(d.runs_):
        for j, c in enumerate(chans):
            ax = axes[i, j]
            k, label = scale[c]
            _shade(ax, d.phases_[i], r.t)
            ax.plot(r.t, getattr(r, c) * k, color="0.35", lw=0.8, label="measured")
            ax.plot(r.t, d.sims_["nominal"][i][c] * k, "--", color="tab:blue", lw=1.0, label="nominal")
            ax.plot(r.t, d.sims_["updated"][i][c] * k, color="tab:red", lw=1.0,
                    label=f"updated ({d.named_effect_})")
            ax.set_ylabel(label)
            if j == 0:
                ax.set_title(f"{r.name} ({'held out' if r.name in hold else 'fitted'})", loc="left", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    paths.append(_save(fig, out / "overlays.png"))

    fig, axes = plt.subplots(nr, nc, figsize=(4.2 * nc, 2.6 * nr), squeeze=False, sharex=True)
    for i, r in enumerate(d.runs_):
        for j, c in enumerate(chans):
            ax = axes[i, j]
            _shade(ax, d.phases_[i], r.t)
            for m, col in (("calibrated", "tab:blue"), ("updated", "tab:red")):
                z = (getattr(r, c) - d.sims_[m][i][c]) / d.sigma_[c]
                ax.plot(r.t, z, color=col, lw=0.6, label=f"{m}")
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_ylabel(f"{c} residual [sigma]")
            if j == 0:
                ax.set_title(f"{r.name} ({'held out' if r.name in hold else 'fitted'})", loc="left", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    from matplotlib.patches import Patch
    handles, labels = axes[0, 0].get_legend_handles_labels()
    handles += [Patch(color=PHASE_COLOURS[p]) for p in PHASES]
    labels += [PHASE_TEXT[p] for p in PHASES]
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    paths.append(_save(fig, out / "residuals.png"))

    cs = d.candidates_
    fig, ax = plt.subplots(figsize=(7, 0.6 * len(cs) + 1.5))
    y = np.arange(len(cs))[::-1]
    ax.barh(y + 0.18, [max(c.material_fit, -0.2) for c in cs], 0.36, color=["tab:green" if c.passed else "0.6" for c in cs],
            label="fitted runs")
    if d.holdout_runs_:
        ax.barh(y - 0.18, [max(c.material_holdout or 0.0, -0.2) for c in cs], 0.36,
                color=["tab:olive" if c.passed else "0.8" for c in cs], label="held-out run")
    ax.set_yticks(y, [f"{c.name} ({'pass' if c.passed else 'fail'})" for c in cs])
    ax.axvline(0.0, color="k", lw=0.6)
    ax.axvline(d.min_improvement, color="tab:red", lw=0.6, ls="--", label="required (fitted runs)")
    ax.set_xlabel("fraction of the calibrated model's SSR removed"
                  + ("" if d.discrepancy_term is None else " above the noise"))
    ax.set_xlim(-0.25, 1.02)  # bars below -20 % are clipped there
    ax.set_title(f"candidates, ranked (named: {d.named_effect_})", fontsize=10)
    if not cs:
        ax.text(0.5, 0.5, "none fitted: no gap to reduce", ha="center", va="center",
                transform=ax.transAxes)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    paths.append(_save(fig, out / "candidates.png"))
    return paths


def _shade(ax, phases, t) -> None:
    for p, a, b in phases.spans(t):
        ax.axvspan(a, b, color=PHASE_COLOURS[p], lw=0, zorder=0)


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
