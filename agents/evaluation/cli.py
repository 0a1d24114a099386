"""Benchmark cut-off policies on the pneugym suites and write results.json, results.csv and plots.

examples:
  pneugym evaluate       # baselines + ESAC, PPO, family ESAC (trained on demand), three suites
  pneugym evaluate --policies conventional gaslaw oracle ppo=runs/ppo/model.zip \\
      --suite robustness --episodes 3 --seed 1000000 --out results
  pneugym evaluate --policies gaslaw esac=runs/esac esac10=runs/esac:max_time_increase=0.1
  pneugym evaluate --rig my_rig.yaml --runs runs/my_rig   # on your rig (policies trained for it)
  pneugym evaluate --rig my_rig.yaml --suite points --points 4:20 6:40   # at your operating points
  python evaluate.py --policies gaslaw --no-progress   # the same command, from a checkout

Suites (sensor noise 0.03 mm / 400 Pa in every episode):
- ``nominal``: the thesis conditions, 1.5 and 2.5 bar gauge with 10 kg;
- ``robustness``: load {5, 10, 15, 20, 30} kg x supply {1.5, 2, 2.5, 3, 4, 5} bar, plus
  disturbance sets at 1.5 and 2.5 bar with 10 kg: random supply dips (10-30 %, 50-300 ms),
  friction -30 % / +30 %, valve delay -20 % / +20 %;
- ``transfer``: rigs no policy was trained on: the thesis rig, 6 held-out draws of the rig family
  (preset ``family``), 5 rigs beyond its edges and 3 model forms it does not draw, each at 1.5 bar
  5 kg, 2.5 bar 10 kg, 4 bar 20 kg and 5.5 bar 35 kg; each episode has its own oracle, and the
  figures come per rig too.

Every policy meets the same episodes (conditions and sensor noise from ``--seed``; keep evaluation
seeds >= 1,000,000, the range this project never uses for training or calibration). Every saved
model is loaded and checked (file, observation layout, decision overrides) before any episode
runs or any policy is trained on demand; a problem is a usage error (exit 2) naming it.
``oracle_fraction = (return - conventional return) / (oracle return - conventional return)``
on the suite's (or condition's) mean returns.
"""
from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence

from pneugym.outputs import check_output_dir
from pneugym.parallel import add_arguments as add_parallel_arguments
from pneugym.rigfile import as_rig

from .outputs import print_table, write_outputs
from .run import evaluate
from .specs import DEFAULT_POLICIES, check_policy_specs, load_models, resolve_learned
from .suites import EVAL_SEED, EXTRA_SUITES, SUITES


def parser() -> argparse.ArgumentParser:
    """The command line of ``pneugym evaluate`` / ``python evaluate.py``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--policies", nargs="+", default=DEFAULT_POLICIES,
                    help="baseline names, learned ones (esac, ppo, dqn: runs/<name>, trained "
                         "on demand) and/or NAME=PATH of saved models")
    ap.add_argument("--runs", default="runs", help="where learned policies are (and are trained)")
    ap.add_argument("--budget", default="quick",
                    help="train.py budget for learned policies trained on demand")
    ap.add_argument("--suite", default="all", choices=[*SUITES, *EXTRA_SUITES, "all"],
                    help="which suite to run (default all: nominal, robustness and transfer; "
                         "points: the transfer suite's operating points on the --rig rig; "
                         "cylinders: held-out single-rod and inclined cylinders of the "
                         "family-cylinders preset)")
    ap.add_argument("--episodes", type=int, default=2, help="episodes per condition cell")
    ap.add_argument("--seed", type=int, default=EVAL_SEED,
                    help=f"seed of the episodes (default {EVAL_SEED:,}; keep >= {EVAL_SEED:,})")
    ap.add_argument("--out", default="results",
                    help="folder for results.json, results.csv and the plots")
    ap.add_argument("--rig", default=None, metavar="FILE",
                    help="rig file to evaluate on (default the thesis rig); learned policies "
                         "trained on demand are trained on it; a model trained on another rig "
                         "runs as it is, with a warning naming the differences")
    ap.add_argument("--no-progress", action="store_true",
                    help="no progress bars (evaluation, and training on demand)")
    ap.add_argument("--commission-starts", type=int, default=None, metavar="N",
                    help="mpc-rig: least-squares starts of each rig's commissioning fit "
                         "(default 2)")
    ap.add_argument("--commission-nfev", type=int, default=None, metavar="N",
                    help="mpc-rig: iterations per start of each rig's commissioning fit "
                         "(default 40)")
    ap.add_argument("--commission-refit", type=int, default=None, metavar="N",
                    help="mpc-rig: more starts per line model where a rig's fit ends above a "
                         "misfit of 9 (default 4; 0: none)")
    ap.add_argument("--points", nargs="+", default=None, metavar="BAR:KG",
                    help="the points suite's operating points, supply (bar gauge) and load "
                         "(kg), e.g. --points 4:20 6:40 (default the transfer suite's: 1.5:5 "
                         "2.5:10 4:20 5.5:35); with --suite points")
    add_parallel_arguments(ap, "the (suite, policy) pairs")
    return ap


def parse_points(items: Sequence[str]) -> tuple[tuple[float, float], ...]:
    """``--points`` values ``BAR:KG`` as checked ``(supply bar g, load kg)`` pairs."""
    from .suites import check_points

    pts = []
    for item in items:
        parts = item.split(":")
        try:
            if len(parts) != 2:
                raise ValueError
            pts.append((float(parts[0]), float(parts[1])))
        except ValueError:
            raise ValueError(f"--points {item!r}: expected BAR:KG, the supply in bar gauge and "
                             f"the load in kg (e.g. 4:20)") from None
    return check_points(pts)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the ``results.json``
    structure. Every problem found before the work (a policy spec, a saved model, ``--seed``,
    ``--runs``, ``--out``) exits 2 with the message."""
    ap = parser()
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f"--workers {args.workers}: must be >= 1")
    from pneugym.parallel import ray_problem

    if ray_problem(args.ray_address):
        ap.error(ray_problem(args.ray_address))
    for flag, v in (("--commission-starts", args.commission_starts),
                    ("--commission-nfev", args.commission_nfev)):
        if v is not None and v < 1:
            ap.error(f"{flag} {v}: must be >= 1")
    if args.commission_refit is not None and args.commission_refit < 0:
        ap.error(f"--commission-refit {args.commission_refit}: must be >= 0")
    if args.episodes < 1:
        ap.error(f"--episodes {args.episodes}: must be >= 1 (episodes per condition cell)")
    if not 0 <= args.seed < 2 ** 63:
        ap.error(f"--seed {args.seed}: episode seeds must be integers from 0 to 2**63 - 1; "
                 f"held-out results use {EVAL_SEED:,} and up")
    try:  # before any work: a wrong name, an unusable model or --out must not cost a training
        points = None
        if args.points is not None:
            if args.suite != "points":
                raise ValueError(f"--points {' '.join(args.points)} are the points suite's "
                                 f"operating points: give --suite points (not {args.suite})")
            points = parse_points(args.points)
        env_config = {} if args.rig is None else {"rig": as_rig(args.rig, "--rig")}
        check_policy_specs(args.policies)
        preloaded = load_models(args.policies, args.runs, args.budget, env_config)
        check_output_dir(args.out, "--out")  # the string as given: "" is not the current folder
    except (ValueError, OSError) as exc:
        ap.error(str(exc))
    if args.seed < EVAL_SEED:
        print(f"warning: --seed {args.seed} lies in the range used for training and tuning "
              f"(below {EVAL_SEED:,}); figures on it are not held-out results", file=sys.stderr)
    suites = list(SUITES) if args.suite == "all" else [args.suite]
    progress = not args.no_progress
    policies = resolve_learned(args.policies, args.runs, args.budget, progress,
                               env_config.get("rig"))
    results = evaluate(policies, suites, args.episodes, args.seed, env_config=env_config,
                       preloaded=preloaded, progress=progress, workers=args.workers,
                       ray_address=args.ray_address, commission={
                           k: v for k, v in (("starts", args.commission_starts),
                                             ("max_nfev", args.commission_nfev),
                                             ("refit_starts", args.commission_refit))
                           if v is not None}, points=points)
    print_table(results)
    write_outputs(results, args.out)
    print(f"\nwrote {args.out}/results.json, results.csv and plots")
    return results
