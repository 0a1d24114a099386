"""A controller run offline over measured runs (``pneugym-measurement/1``): when it would have cut,
and what the model predicts that cut saves, beside the cut the run itself made.

    pneugym replay measured/ --policy gaslaw --rig my_rig.yaml --out replay/

The run's samples are resampled at the controller's period (linear interpolation) and fed to the
controller from the extend command until it cuts. Its decision is exact up to the run's own cut:
after that the recording shows a stroke the controller's command would not have produced, so a
controller that had not cut by then is flagged (``after_recorded_cut``) and its outcome is
unknown (``predicted`` None). The prediction runs the environment's plant on the rig the run's
JSON states (over the controller's), or on ``--model-rig``, at the run's supply and load.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..params import RigParams
from .controller import Controller

OUTCOME_KEYS = ("saving_ratio", "time_increase", "stroke_time_s", "stalled", "stick_slip_events",
                "objective")


def recorded_cut_s(run: Any) -> float | None:
    """Time [s] of the run's own cut-off: the first command 0 after the supply was commanded
    (None: never cut while recorded)."""
    opened = False
    for t, v in run.schedule():
        if v == 1:
            opened = True
        elif opened:
            return float(t)
    return None


def predict_cuts(rig: RigParams, cuts_s: Sequence[float | None], period_s: float,
                 time_limit_s: float = 4.0) -> list[dict[str, Any]]:
    """The environment's outcome (saving ratio, time increase, stroke time [s], stall,
    stick-slips, objective) of cutting at each time of ``cuts_s`` [s] (None: never) on ``rig``
    at its supply and load, noise-free, all in one batch."""
    from ..envs import Conditions
    from ..envs.cutoff import CutOffVectorEnv

    cond = Conditions(supply_pressure_gauge_pa=rig.supply_pressure_gauge_pa,
                      load_mass_kg=rig.load_mass_kg)
    n = len(cuts_s)
    env = CutOffVectorEnv(num_envs=n, autoreset=False, rig=rig, control_period_s=period_s,
                          time_limit_s=time_limit_s)
    env.reset(seed=0, options={"conditions": [cond] * n})
    first = np.array([math.inf if c is None else round(c / period_s) for c in cuts_s])
    out: list[dict[str, Any] | None] = [None] * n
    k = 0
    while any(o is None for o in out):
        _, _, term, trunc, info = env.step((k >= first).astype(np.int64))
        k += 1
        for i in np.flatnonzero(info.get("_final_info", np.zeros(n, bool))):
            if out[i] is None:
                fi = info["final_info"]
                out[i] = {key: _py(fi[key][i]) for key in OUTCOME_KEYS}
    return out  # type: ignore[return-value]


def replay_run(controller: Controller, run: Any, rig: RigParams | None = None,
               commissioning: Sequence[Any] = ()) -> dict[str, Any]:
    """Feed ``run`` (a :class:`pneugym.data.MeasuredRun`) to ``controller``; returns its cut
    time [s] (None: it never cut while recorded), the run's own, and the outcome the model
    predicts for each and for a conventional stroke (:func:`predict_cuts` on ``rig``, default
    the rig the run's JSON states over the controller's, at the run's supply, load and external
    force, within the controller's time limit). A controller that had not cut by the run's own
    cut is flagged (``after_recorded_cut``) and its outcome is unknown (``predicted`` None).
    ``commissioning``: measured commissioning strokes (extend, cut off on arrival, held); a
    policy that reads one gets the stroke at the run's operating point
    (:func:`commissioning_for`), or, if none are given, the one the controller holds
    (:meth:`Controller.set_commissioning`)."""
    p = controller.period_s
    if run.sample_dt_s > p * (1 + 1e-6):
        raise ValueError(f"{run.name}: sampled every {run.sample_dt_s * 1e3:.3g} ms, coarser than "
                         f"the controller's period ({p * 1e3:g} ms): it cannot be replayed")
    stated = run.rig(controller.rig)  # the run's own rig section over the controller's rig
    mine, theirs = _geometry(controller.rig), _geometry(stated)
    if mine != theirs:  # (an end-stroke rule would cut mid-stroke on a longer cylinder)
        raise ValueError(f"{run.name}: the run states a cylinder of bore, rod, stroke "
                         f"{theirs} m, the controller's rig {mine} m: load the controller for "
                         f"the rig the runs were measured on (--rig FILE)")
    if stated.stroke_direction != "extend":
        raise ValueError(f"{run.name}: a {stated.stroke_direction} stroke; the controller runs "
                         f"extension strokes")
    supply = float(run.meta["supply_pressure_gauge_pa"])
    load = float(run.meta.get("load_mass_kg", controller.rig.load_mass_kg))
    grid = np.arange(math.ceil(max(run.t[0], 0.0) / p - 1e-9), math.floor(run.t[-1] / p + 1e-9)
                     + 1) * p
    if not grid.size or grid[0] > p * (1 + controller.period_tolerance):
        raise ValueError(f"{run.name}: its first sample is {run.t[0]:.4g} s after the extend "
                         f"command; the controller decides from the first control period "
                         f"({p * 1e3:g} ms) on, so a run recorded from later cannot be replayed")
    cols = [np.interp(grid, run.t, getattr(run, c)) for c in ("x", "p_drive", "p_exhaust")]
    # (the set-point is gauge in the run; the controller takes it absolute over its ambient)
    # (no strokes given: the one the controller holds, set_commissioning, if any)
    controller.reset(supply + controller.rig.gas.ambient_pressure_pa, load,
                     commissioning_for(run, commissioning, supply, load)
                     if controller.reads_commissioning and commissioning else None)
    for k in range(grid.size):
        if controller.step(grid[k], cols[0][k], cols[1][k], cols[2][k]):
            break
    cut, own = controller.cut_time_s, recorded_cut_s(run)
    late = own is not None and (cut is None or cut > own)
    model_rig = (rig or stated).with_(supply_pressure_gauge_pa=supply, load_mass_kg=load,
                                      external_force_n=stated.external_force_n)
    ctl, rec, conv = predict_cuts(model_rig, [cut, own, None], p, controller.time_limit_s)
    return {"run": run.name, "description": run.description, "supply_bar_gauge": supply / 1e5,
            "load_kg": load, "cut_time_s": cut, "recorded_cut_time_s": own,
            "after_recorded_cut": late, "predicted": None if late else ctl,
            "predicted_recorded": rec, "predicted_conventional": conv}


def commissioning_for(run: Any, strokes: Sequence[Any], supply_gauge_pa: float,
                      load_kg: float) -> Any:
    """The commissioning stroke of ``strokes`` recorded at ``run``'s operating point (supply
    within 5 kPa, payload within 0.5 kg); ``ValueError`` if none is."""
    for s in strokes:
        if (abs(float(s.meta["supply_pressure_gauge_pa"]) - supply_gauge_pa) <= 5e3
                and abs(float(s.meta.get("load_mass_kg", load_kg)) - load_kg) <= 0.5):
            return s
    have = ", ".join(f"{float(s.meta['supply_pressure_gauge_pa']) / 1e5:g} bar g / "
                     f"{float(s.meta.get('load_mass_kg', load_kg)):g} kg" for s in strokes)
    raise ValueError(f"{run.name}: the policy reads a commissioning stroke (extend, cut off on "
                     f"arrival, held 1.5 s) at the run's operating point, "
                     f"{supply_gauge_pa / 1e5:g} bar g / {load_kg:g} kg; give one "
                     f"(--commissioning RUN)"
                     + (f": those given are at {have}" if have else ""))


def _measured(items: Any, base: RigParams) -> list[Any]:
    """Measured runs from objects, paths and folders."""
    from ..data import MeasuredRun, read_runs

    items = items if isinstance(items, (list, tuple)) else [items]
    loaded = [r for r in items if isinstance(r, MeasuredRun)]
    paths = [r for r in items if not isinstance(r, MeasuredRun)]
    return loaded + (read_runs(paths, base=base) if paths else [])


def _geometry(rig: RigParams) -> tuple[float, float, float]:
    c = rig.cylinder
    return (c.bore_m, c.rod_m, c.stroke_m)


def replay(controller: Controller, runs: Any, rig: Any = None,
           commissioning: Any = ()) -> list[dict[str, Any]]:
    """:func:`replay_run` for each measured run of ``runs`` (paths, folders, or
    :class:`~pneugym.data.MeasuredRun` objects); ``rig``: the rig the predictions run on
    (a rig file, a dict, a RigParams; default the controller's); ``commissioning``: the
    commissioning strokes (the same kinds) for a policy that reads one."""
    from ..rigfile import as_rig

    model = as_rig(rig, "rig") if rig is not None else None
    strokes = _measured(commissioning, controller.rig) if commissioning else []
    if controller.reads_commissioning and not strokes and controller.commissioning is None:
        raise ValueError(f"{controller.source} reads a commissioning stroke of the rig (extend, "
                         f"cut off on arrival, held 1.5 s) at each run's operating point: give "
                         f"them (--commissioning RUN ...)")
    return [replay_run(controller, r, model, strokes)
            for r in _measured(runs, controller.rig)]


def _py(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return v


def write_outputs(results: list[dict[str, Any]], out: Path, source: str) -> None:
    """``replay.json`` (everything), ``replay.csv`` (one row per run) and ``replay.png``."""
    from ..provenance import provenance

    out.mkdir(parents=True, exist_ok=True)
    (out / "replay.json").write_text(json.dumps(
        {"policy": source, "runs": results, "provenance": provenance()}, indent=2))
    fields = ["run", "description", "supply_bar_gauge", "load_kg", "cut_time_s",
              "recorded_cut_time_s", "after_recorded_cut"]
    with open(out / "replay.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(fields + [f"{who}_{k}" for who in ("predicted", "recorded", "conventional")
                             for k in OUTCOME_KEYS])
        for r in results:
            w.writerow([r[f] for f in fields] + [
                (r[key] or {}).get(k) for key in ("predicted", "predicted_recorded",
                                                  "predicted_conventional")
                for k in OUTCOME_KEYS])
    plot(results, out / "replay.png", source)


def plot(results: list[dict[str, Any]], path: Path, source: str) -> None:
    """Predicted saving vs stroke-time increase of the controller's cut and of each run's own."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for key, label, marker in (("predicted", source, "o"),
                               ("predicted_recorded", "the run's own cut", "s")):
        pts = [(r[key]["time_increase"], r[key]["saving_ratio"]) for r in results
               if r[key] is not None and r[key]["time_increase"] is not None]
        if pts:
            x, y = np.array(pts).T
            ax.scatter(100 * x, 100 * y, marker=marker, label=label)
    ax.set_xlabel("predicted stroke-time increase [%]")
    ax.set_ylabel("predicted saving of wasted energy [%]")
    ax.set_title(f"Replay of {len(results)} measured run(s)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pneugym replay", description=__doc__.split("\n\n")[0],
        epilog="examples:\n"
               "  pneugym replay measured/ --policy gaslaw --rig rig.yaml --out replay/\n"
               "  pneugym replay measured/run3.csv --policy runs/esac --rig rig.yaml\n"
               "  pneugym replay measured/ --policy esac-family --rig rig.yaml "
               "--commissioning commissioning/ --model-rig report/updated_model.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="measured runs: folders or NAME.csv/NAME.json files")
    p.add_argument("--policy", action="append", default=None,
                   help="a baseline, a learned policy's name under --runs, a run directory "
                        "or a model file (default gaslaw; one per replay)")
    p.add_argument("--rig", default=None, help="rig file of the rig the runs were measured on")
    p.add_argument("--model-rig", default=None,
                   help="rig file the predictions run on (default --rig), e.g. the discrepancy "
                        "workflow's updated_model.json")
    p.add_argument("--commissioning", nargs="+", default=[], metavar="RUN",
                   help="commissioning strokes (extend, cut off on arrival, held 1.5 s), one "
                        "per operating point of the runs, for a policy that reads one "
                        "(esac-family, ppo-family)")
    p.add_argument("--runs", "--runs-dir", dest="runs_dir", default="runs",
                   help="where learned policies' runs are (as evaluate's and export's --runs)")
    p.add_argument("--out", default=None, help="folder for replay.json/.csv/.png")
    return p


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]] | int:
    ap = parser()
    args = ap.parse_args(argv)
    if args.policy and len(args.policy) > 1:
        ap.error(f"--policy given {len(args.policy)} times ({', '.join(args.policy)}): one "
                 f"controller per replay")
    args.policy = (args.policy or ["gaslaw"])[0]
    try:
        ctl = Controller.load(args.policy, rig=args.rig, runs=args.runs_dir)
        results = replay(ctl, list(args.runs), rig=args.model_rig,
                         commissioning=list(args.commissioning))
    except (ValueError, OSError) as exc:  # a refused model, rig or run: named, exit status 2
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for r in results:
        def fmt(o):
            if o is None:
                return "unknown (the run cut first)"
            ti = "stall" if o["time_increase"] is None else f"{100 * o['time_increase']:+.1f} %"
            return f"saving {100 * o['saving_ratio']:5.1f} %, time {ti}"
        cut = "never" if r["cut_time_s"] is None else f"{r['cut_time_s']:.3f} s"
        own = "never" if r["recorded_cut_time_s"] is None else f"{r['recorded_cut_time_s']:.3f} s"
        flag = "  (after the run's own cut)" if r["after_recorded_cut"] else ""
        print(f"{r['run']}: cuts at {cut}{flag}: {fmt(r['predicted'])} | run's own cut {own}: "
              f"{fmt(r['predicted_recorded'])}")
    if args.out:
        out = Path(args.out)
        write_outputs(results, out, ctl.source)
        print(f"wrote {out / 'replay.json'}, replay.csv, replay.png")
    return results


if __name__ == "__main__":
    main()
