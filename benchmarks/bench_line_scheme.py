"""The implicit FD line (``SolverParams(line_scheme="implicit")``) against the explicit one on
rigs its 5 ms substep was not chosen on: the transfer suite's rigs with an FD line (the thesis
rig, the held-out family draws, the edges, the model forms), each at its four operating points.

For every rig-point: stroke time and the wasted energies of a cut on arrival and of a cut at
60 % of the stroke time, with either scheme, against the rig-point's own converged reference
(4x the line cells, a quarter of the explicit substep); and the CPU time of a conventional
stroke with either scheme (its ratio is the speed-up). Writes ``line_scheme.json`` (with the
configuration and versions) and ``line_scheme.png``.

    python benchmarks/bench_line_scheme.py [--quick] [--dt-s 0.005] [--draws N] [--out DIR]

``--draws N``: N new draws of the rig family instead (seed stream ``--stream``, default 58:
no training and no suite uses it), ``line_scheme_draws.json`` / ``.png``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from common import ROOT, json_default, machine_info, versions
from pneugym import Plant, RigParams
from pneugym.envs.family import apply_changes
from pneugym.plant import choose_dt

from agents.evaluation.suites import TRANSFER_POINTS, held_out_draws, transfer_rigs

QUANTITIES = ("stroke", "endcut", "cut60")
T_MAX = 8.0  # [s] simulated at most per run
CUT_AT = 0.6  # the cut-off at this fraction of the conventional stroke time
GOAL_PCT = 0.5
#: the seed stream of ``--draws`` (the transfer suite draws from stream 12, the cylinders' 13)
DRAW_STREAM = 58


def metrics(rig: RigParams, t_cut: float) -> dict[str, float]:
    """Stroke time [s], energy [J] of a cut on arrival and of a cut at ``t_cut`` [s] (recorded
    every 50 ms: a finer grid would shorten the implicit line's substeps)."""
    pl = Plant(rig)
    pl.advance(T_MAX, 1, stop_on_arrival=True)
    out = {"stroke": pl.arrival_time_s}
    pl.reset()
    pl.run(T_MAX, cut_on_arrival=True, record_dt=0.05)
    out["endcut"] = pl.energy_wasted_j
    pl.reset()
    pl.run(T_MAX, schedule=[(0.0, 1), (t_cut, 0)], record_dt=0.05)
    out["cut60"] = pl.energy_wasted_j
    return out


def cpu_stroke(rig: RigParams, reps: int) -> float:
    """Median CPU time [s] of a conventional stroke to arrival."""
    pl = Plant(rig)
    pl.advance(T_MAX, 1, stop_on_arrival=True)
    times = []
    for _ in range(reps):
        pl.reset()
        t = time.thread_time()
        pl.advance(T_MAX, 1, stop_on_arrival=True)
        times.append(time.thread_time() - t)
    return sorted(times)[len(times) // 2]


def rig_points(quick: bool, draws: int = 0, stream: int = DRAW_STREAM):
    """``(name, rig)`` of every transfer rig with an FD line of several cells at each point,
    its ``solver.dt_s`` (a substep the suite fixes for a few rigs) left out; with ``draws``,
    of that many draws of the ``family`` preset's rigs from seed stream ``stream`` instead."""
    rigs = transfer_rigs() if not draws else {
        f"draw-{k + 1}": ch for k, ch in enumerate(held_out_draws("family", draws, stream, RigParams()))}
    for name, changes in rigs.items():
        ch = tuple(c for c in changes if c[0] != "solver.dt_s")
        for bar, kg in TRANSFER_POINTS[1:3] if quick else TRANSFER_POINTS:
            rig = apply_changes(RigParams(supply_pressure_gauge_pa=bar * 1e5, load_mass_kg=kg), ch)
            if rig.line.model == "fd" and rig.line.n_cells > 1:
                yield f"{name}@{bar:g}bar/{kg:g}kg", rig
        if quick and name in ("heldout-2", "draw-2"):
            break


def run(dt_s: float | None, quick: bool, reps: int, draws: int = 0, stream: int = DRAW_STREAM) -> dict:
    out = {}
    for key, rig in rig_points(quick, draws, stream):
        dt, _ = choose_dt(rig)
        ref = rig.with_(line={"n_cells": 4 * rig.line.n_cells}, solver={"dt_s": dt / 4})
        imp = rig.with_(solver={"line_scheme": "implicit"})
        if dt_s is not None:  # (never above the automatic substep: the one used is recorded)
            imp = imp.with_(solver={"dt_s": min(dt_s, choose_dt(imp)[0])})
        pl = Plant(rig)
        pl.advance(T_MAX, 1, stop_on_arrival=True)
        t_cut = CUT_AT * pl.arrival_time_s
        m_ref, m_exp, m_imp = metrics(ref, t_cut), metrics(rig, t_cut), metrics(imp, t_cut)
        err = {s: {q: 100.0 * (m[q] - m_ref[q]) / m_ref[q] for q in QUANTITIES}
               for s, m in (("explicit", m_exp), ("implicit", m_imp))}
        c_exp, c_imp = cpu_stroke(rig, reps), cpu_stroke(imp, reps)
        out[key] = {"dt_explicit_s": dt, "dt_implicit_s": Plant(imp).dt_s, "cut_at_s": t_cut,
                    "reference": m_ref, "errors_pct": err,
                    "max_abs_pct": {s: max(abs(v) for v in e.values()) for s, e in err.items()},
                    "cpu_stroke_s": {"explicit": c_exp, "implicit": c_imp},
                    "speedup": c_exp / c_imp}
        print(f"{key:44s} max|err| explicit {out[key]['max_abs_pct']['explicit']:7.3f} %  "
              f"implicit {out[key]['max_abs_pct']['implicit']:7.3f} %  speed-up "
              f"{out[key]['speedup']:.2f}x", flush=True)
    return out


def summary(res: dict) -> dict:
    def med(xs):  # (the upper middle value until 2026-12-06: docs/plant.md's figures say so)
        return float(np.median(xs))
    s = {"rig_points": len(res)}
    for scheme in ("explicit", "implicit"):
        e = [r["max_abs_pct"][scheme] for r in res.values()]
        s[scheme] = {"within_goal": sum(x <= GOAL_PCT for x in e), "median_max_abs_pct": med(e),
                     "worst_max_abs_pct": max(e)}
    sp = [r["speedup"] for r in res.values()]
    s["speedup"] = {"median": med(sp), "min": min(sp), "max": max(sp)}
    # where the implicit line is used (elsewhere both runs are the explicit line)
    used = [r for r in res.values() if r["dt_implicit_s"] != r["dt_explicit_s"]]
    s["where_used"] = {"rig_points": len(used)}
    if used:
        for scheme in ("explicit", "implicit"):
            e = [r["max_abs_pct"][scheme] for r in used]
            s["where_used"][scheme] = {"within_goal": sum(x <= GOAL_PCT for x in e),
                                       "median_max_abs_pct": med(e)}
        sp = [r["speedup"] for r in used]
        s["where_used"]["speedup"] = {"median": med(sp), "min": min(sp), "max": max(sp)}
    return s


def plot(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    ex = [max(r["max_abs_pct"]["explicit"], 1e-3) for r in res.values()]
    im = [max(r["max_abs_pct"]["implicit"], 1e-3) for r in res.values()]
    a.loglog(ex, im, "o", ms=4)
    lim = [1e-3, max(ex + im) * 1.5]
    a.plot(lim, lim, "k:", lw=1)
    a.axhline(GOAL_PCT, color="r", lw=0.8)
    a.axvline(GOAL_PCT, color="r", lw=0.8)
    a.set_xlabel("explicit line: max |error| [%]")
    a.set_ylabel("implicit line: max |error| [%]")
    a.set_title("against each rig-point's converged reference")
    b.hist([r["speedup"] for r in res.values()], bins=15)
    b.set_xlabel("speed-up of a conventional stroke (CPU time)")
    b.set_ylabel("rig-points")
    b.set_title("implicit over explicit line")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--quick", action="store_true", help="two rigs at two points (about 1 min)")
    ap.add_argument("--dt-s", type=float, default=None,
                    help="the implicit line's substep [s] (default: automatic, 5 ms)")
    ap.add_argument("--repeats", type=int, default=None, help="timed strokes per rig-point")
    ap.add_argument("--draws", type=int, default=0,
                    help="instead of the transfer suite's rigs, this many new draws of the rig family "
                         "(held out: seeds no training and no suite uses; writes line_scheme_draws.*)")
    ap.add_argument("--stream", type=int, default=DRAW_STREAM, help="the draws' seed stream")
    a = ap.parse_args(argv)
    reps = a.repeats or (3 if a.quick else 7)
    warnings.simplefilter("ignore")  # rigs that stick by friction at some points warn
    res = run(a.dt_s, a.quick, reps, a.draws, a.stream)
    s = summary(res)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"config": {"quick": a.quick, "dt_s": a.dt_s, "repeats": reps, "cut_at": CUT_AT,
                      "draws": a.draws, "stream": a.stream if a.draws else None,
                      "goal_pct": GOAL_PCT, "points": TRANSFER_POINTS},
           "summary": s, "rig_points": res, "machine": machine_info(), "versions": versions()}
    stem = "line_scheme_draws" if a.draws else "line_scheme"
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=json_default))
    plot(res, out / f"{stem}.png")
    print(f"{s['rig_points']} rig-points; within {GOAL_PCT} %: explicit {s['explicit']['within_goal']}, "
          f"implicit {s['implicit']['within_goal']}; median max|err| explicit "
          f"{s['explicit']['median_max_abs_pct']:.3f} %, implicit {s['implicit']['median_max_abs_pct']:.3f} %; "
          f"speed-up median {s['speedup']['median']:.2f}x ({s['speedup']['min']:.2f}-"
          f"{s['speedup']['max']:.2f}x)")
    u = s["where_used"]
    if u["rig_points"]:
        print(f"where the implicit line is used ({u['rig_points']} rig-points): within {GOAL_PCT} %: "
              f"explicit {u['explicit']['within_goal']}, implicit {u['implicit']['within_goal']}; median "
              f"max|err| explicit {u['explicit']['median_max_abs_pct']:.3f} %, implicit "
              f"{u['implicit']['median_max_abs_pct']:.3f} %; speed-up median {u['speedup']['median']:.2f}x "
              f"({u['speedup']['min']:.2f}-{u['speedup']['max']:.2f}x)")
    print(f"wrote {out / stem}.json and {stem}.png")
    return doc


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
