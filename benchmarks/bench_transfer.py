"""Policies retrained for a rig, against the same rig's zero-shot figures (issue 12's "policies
retrained for a rig" figure).

For each named rig of the transfer suite (:func:`agents.evaluation.suites.transfer_rigs`) it writes
the rig file, trains ESAC for that rig (``pneugym train --rig``, the chosen budget) and evaluates
on the transfer suite's operating points of that rig (``pneugym evaluate --rig FILE --suite
points``): the baselines, Gas-Law as shipped and re-calibrated for the rig, the main job's ESAC and
the family ESAC zero-shot (from ``--runs``, trained there on demand), the retrained ESAC and the
oracle. Writes ``transfer_retrained.json`` and ``transfer_retrained.png`` (oracle fraction per rig
and policy).

The retrained ESAC learns over the range its rig runs at (``--train-range points``, the default:
``env.conditions`` = the family's supply and load ranges, which hold every operating point of
the suite, :func:`points_range`), or on its config's preset alone (``--train-range preset``:
``randomized``, 1.5-5 bar g and 5-30 kg, the earlier figures).

    python benchmarks/bench_transfer.py                         # 4 rigs, quick budget, ~15 min
    python benchmarks/bench_transfer.py --rigs all              # the suite's 15 rigs, ~50 min
    python benchmarks/bench_transfer.py --rigs heldout-1 --episodes 1 --out bench/
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from common import ROOT  # noqa: F401  (the checkout on sys.path)

DEFAULT_RIGS = ("heldout-1", "heldout-4", "edge-dead-volume", "form-leaks-heat")


def points_range() -> dict[str, list[float]]:
    """``env.conditions`` of a retrained ESAC under ``--train-range points``: the family preset's
    supply and load ranges, checked to hold every operating point of the transfer suite."""
    from agents.evaluation.suites import TRANSFER_POINTS
    from pneugym.envs.conditions import PRESETS

    fam = PRESETS["family"]
    rng = {"supply_pressure_gauge_pa": list(fam.supply_pressure_gauge_pa),
           "load_mass_kg": list(fam.load_mass_kg)}
    (plo, phi), (mlo, mhi) = rng["supply_pressure_gauge_pa"], rng["load_mass_kg"]
    outside = [(b, m) for b, m in TRANSFER_POINTS if not (plo <= b * 1e5 <= phi and mlo <= m <= mhi)]
    if outside:  # a design error: the suite's points and the family's ranges drifted apart
        raise ValueError(f"the family's supply and load ranges leave out the transfer points "
                         f"{outside}")
    return rng


def retrain(name: str, rig, out: Path, budget: str, train_range: str, progress: bool,
            overrides: tuple[str, ...] = ()) -> str:
    """``esac_retrained=PATH`` of the ESAC trained for ``rig`` into ``out / name / esac``
    (reused when finished there with the same budget, range and overrides, as its
    ``bench_key.json`` records; trained again otherwise); ``overrides``: more ``--set`` entries
    of its training."""
    import json

    from agents import training

    run = out / name / "esac"
    key = {"budget": budget, "train_range": train_range, "overrides": list(overrides)}
    kept = run / "bench_key.json"
    model = training.model_path(run) if run.is_dir() else None
    if model is not None and (not kept.is_file() or json.loads(kept.read_text()) != key):
        model = None  # trained with other options (or unknown ones): not this request's
    if model is None:
        over = [] if train_range == "preset" else [
            f"env.conditions.{k}=[{lo!r}, {hi!r}]" for k, (lo, hi) in points_range().items()]
        training.train("esac", run, budget=budget, rig=rig, overrides=[*over, *overrides],
                       progress=progress, force=(run / training.RUN_FILE).is_file())
        model = training.model_path(run)
        kept.write_text(json.dumps(key))
    return f"esac_retrained={model}"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--rigs", nargs="+", default=list(DEFAULT_RIGS),
                    help="transfer-suite rig names (agents.evaluation.suites.transfer_rigs), or "
                         "all")
    ap.add_argument("--budget", default="quick", help="train.py budget of the retrained ESAC")
    ap.add_argument("--train-range", choices=("points", "preset"), default="points",
                    help="the retrained ESAC's training conditions: the range of the suite's "
                         "operating points (default) or its config's preset alone")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration entry of the retrained ESAC (as pneugym train --set; "
                         "repeatable)")
    ap.add_argument("--runs", default="runs", help="where the main job's policies are")
    ap.add_argument("--episodes", type=int, default=2, help="episodes per operating point")
    ap.add_argument("--seed", type=int, default=1_000_000, help="evaluation seed")
    ap.add_argument("--out", default="bench/transfer", help="folder for the results and runs")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from agents.evaluation import evaluate
    from agents.evaluation.specs import resolve_learned
    from agents.evaluation.suites import transfer_rigs
    from pneugym.envs.family import apply_changes
    from pneugym.params import RigParams
    from pneugym.provenance import provenance

    rigs = transfer_rigs()
    if args.rigs == ["all"]:
        args.rigs = list(rigs)
    unknown = [r for r in args.rigs if r not in rigs]
    if unknown:
        ap.error(f"unknown transfer rig(s) {unknown}; known: {list(rigs)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    zero_shot = resolve_learned(["esac", "esac-family"], args.runs, "quick", progress)
    table: dict[str, dict] = {}
    for name in args.rigs:
        rig = apply_changes(RigParams(), rigs[name])
        rig_file = rig.save(out / name / "rig.json")
        t0 = time.perf_counter()
        mine = retrain(name, rig, out, args.budget, args.train_range, progress, tuple(args.set))
        train_s = time.perf_counter() - t0
        pols = ["conventional", "gaslaw", "gaslaw-rig", zero_shot[0].replace("esac=", "esac_main="),
                zero_shot[1].replace("esac-family=", "esac_family="),
                mine, "oracle"]
        res = evaluate(pols, ["points"], args.episodes, args.seed, env_config={"rig": rig},
                       progress=progress)
        p = res["suites"]["points"]["policies"]
        table[name] = {"rig_file": str(rig_file), "retrain_wall_s": train_s,
                       **{k: {m: v[m] for m in ("oracle_fraction", "saving_mean",
                                                "time_increase_mean", "stall_rate",
                                                "stick_slip_rate")} for k, v in p.items()}}
        print(f"{name}: " + ", ".join(f"{k} {v['oracle_fraction']:.3f}" for k, v in p.items()
                                       if v["oracle_fraction"] is not None), flush=True)
    result = {"rigs": table, "config": {**vars(args), "points_range": points_range()},
              "provenance": provenance()}
    (out / "transfer_retrained.json").write_text(json.dumps(result, indent=2))
    _plot(table, out / "transfer_retrained.png")
    print(f"wrote {out / 'transfer_retrained.json'} and .png")
    return result


def _plot(table: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = list(table)
    pols = [k for k in next(iter(table.values())) if isinstance(table[names[0]][k], dict)
            and k not in ("conventional", "oracle")]
    fig, ax = plt.subplots(figsize=(min(14.0, 1.6 + 1.4 * len(names)), 4))
    w = 0.8 / len(pols)
    for j, pol in enumerate(pols):
        vals = [table[n][pol]["oracle_fraction"] or 0.0 for n in names]
        ax.bar(np.arange(len(names)) + j * w, np.clip(vals, -0.5, 1.05), w, label=pol)
    ax.set_xticks(np.arange(len(names)) + 0.4 - w / 2, names, rotation=30 if len(names) > 6
                  else 20, ha="right" if len(names) > 6 else "center", fontsize=8)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_ylabel("oracle fraction (clipped at -0.5)")
    ax.set_title("per rig: zero-shot, re-calibrated and retrained", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
