"""Train learned cut-off policies: stable-baselines3 PPO and DQN on the batched environment, and
the ESAC neural predictor (thesis 6.8).

examples:
  pneugym train --algo ppo  --preset randomized --timesteps 1500000 --seed 0 --out runs/ppo
  pneugym train --algo dqn  --out runs/dqn
  pneugym train --algo esac --out runs/esac          # --timesteps = rollouts of training data
  pneugym train --algo ppo --out runs/ppo --resume   # continue from the last checkpoint
  pneugym train --algo ppo --budget quick            # the quick budget of configs/ppo.yaml
  pneugym train --algo ppo --set algo.learning_rate=1e-4 --set env.history=8
  pneugym train --algo esac --rig my_rig.yaml --out runs/my_rig/esac   # for your rig
  pneugym train --algo esac --seeds 0-4 --workers 2 --out runs/esac-seeds   # 5 seeds, 2 processes
  pneugym train --algo esac --seeds 0-4 --ray-address auto --out /shared/runs  # on a Ray cluster
  pneugym train --algo ppo --tune space.yaml --trials 20 --workers 2 --out runs/ppo-tune
  python train.py --algo ppo                         # the same command, from a checkout

Hyperparameters live in ``configs/<algo>.yaml`` (a ``default`` budget and a ``quick`` one that
overrides it); ``--set key.sub=value`` overrides single entries. Every run directory holds
``run.json`` (configuration, seed, package versions, observation layout, status, validation
history), the model (``model.zip`` / ``best_model.zip`` for SB3, ``model.pt`` for ESAC), the last
checkpoints and the logs (``progress.csv``; TensorBoard event files under ``tb/`` when
``tensorboard`` is installed). Files are written to a temporary name and renamed, so an
interrupted run leaves its last good checkpoint usable. Training seeds stay below 1,000,000;
evaluation uses the seeds above.

Runs are never lost: a run folder that holds anything is refused unless ``--resume`` (continue its
last checkpoint; an error if there is none) or ``--force`` (start over a folder that holds a
train.py ``run.json``: lists the files train.py wrote there, then removes exactly those; other
files stay, and a non-empty folder without ``run.json`` is refused even with ``--force``). The
whole configuration (YAML file, budget, ``--set``) is checked before anything is written: unknown
keys (with the nearest known name), SB3 keywords against the algorithm's constructor, types and
ranges. SIGINT or SIGTERM stop training at the next step with a checkpoint and
``status: "interrupted"`` in ``run.json``; ``--resume`` continues from it (a second signal stops
at once; a run whose seed is not a training seed is not resumed). Checkpoints are loaded without
unpickling anything (``agents/safe_load.py``); DQN replay buffers are saved as plain arrays
(``replay_*.npz``), and the pickled ``replay_*.pkl`` of older runs are loaded only with
``--trust-pickled-replay-buffer`` (only for your own runs).
"""
from __future__ import annotations

import argparse
import signal
import sys
from typing import Any, Sequence

from pneugym.parallel import add_arguments as add_parallel_arguments

from .config import ALGOS
from .rundir import RUN_FILE
from .signals import TrainingInterrupted
from .trainer import train


def parser() -> argparse.ArgumentParser:
    """The command line of ``pneugym train`` / ``python train.py``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--algo", required=True, choices=ALGOS, help="what to train")
    ap.add_argument("--preset", default=None, help="condition preset (default: the config's)")
    ap.add_argument("--timesteps", type=int, default=None,
                    help="environment steps (ppo, dqn) or training rollouts (esac)")
    ap.add_argument("--seed", type=int, default=0, help="training seed (< 1,000,000)")
    ap.add_argument("--out", default=None, help="run directory (default runs/<algo>)")
    ap.add_argument("--rig", default=None, metavar="FILE",
                    help="rig file (JSON/YAML: RigParams fields, a measured run's rig section, "
                         "or the discrepancy workflow's updated_model.json); default the thesis "
                         "rig")
    ap.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    ap.add_argument("--budget", default="default", help="section of the config (default, quick)")
    ap.add_argument("--config", default=None, help="YAML file (default configs/<algo>.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config entry, e.g. algo.learning_rate=1e-4")
    ap.add_argument("--force", action="store_true",
                    help="start over in a run folder that holds a train.py run.json (lists, then "
                         "removes the files train.py wrote there; keeps anything else)")
    ap.add_argument("--trust-pickled-replay-buffer", action="store_true",
                    help="--resume of a DQN run from an older pneugym: load its pickled replay "
                         "buffer (a pickle can run code: only for your own runs)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    sw = ap.add_argument_group("several runs at once: --seeds (results in <out>/sweep.json) or "
                              "--tune (<out>/tune.json)")
    sw.add_argument("--seeds", default=None, metavar="LIST",
                    help="train one run per seed into <out>/seed_<s>, e.g. 0-4 or 0,3,7")
    add_parallel_arguments(sw, "the runs of --seeds or the trials of --tune")
    sw.add_argument("--tune", default=None, metavar="SPACE",
                    help="search hyperparameters in this YAML space with Ray Tune and Optuna "
                         "(results in <out>/tune.json; see agents/training/tune.py)")
    sw.add_argument("--trials", type=int, default=20, help="training runs of --tune")
    return ap


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the finished run's
    ``run.json`` content. A bad option or configuration exits 2 with the message; a run stopped
    by SIGINT or SIGTERM exits 130 or 143, saying how to continue it."""
    ap = parser()
    args = ap.parse_args(argv)
    many = "-tune" if args.tune is not None else "-seeds" if args.seeds is not None else ""
    out = args.out if args.out is not None else f"runs/{args.algo}{many}"  # "" is refused
    if args.workers < 1:
        ap.error(f"--workers {args.workers}: must be >= 1")
    from pneugym.parallel import ray_problem

    if ray_problem(args.ray_address):
        ap.error(ray_problem(args.ray_address))
    if args.tune is not None:
        return _tune(ap, args, out)
    if args.seeds is not None or args.workers != 1 or args.ray_address is not None:
        return _sweep(ap, args, out)
    try:
        run = train(args.algo, out, args.preset, args.timesteps, args.seed, args.resume,
                    args.budget, args.config, args.set, not args.no_progress, args.force,
                    args.trust_pickled_replay_buffer, rig=args.rig)
    except ValueError as exc:
        ap.error(str(exc))
    except TrainingInterrupted as exc:
        where = f"; last checkpoint {out}/{exc.run['checkpoint']}" if (
            exc.run and exc.run.get("checkpoint")) else ""
        command = ap.prog if ap.prog.startswith("pneugym") else "python train.py"
        again = (f"continue with: {command} --algo {args.algo} --out {out} --resume"
                 if args.algo != "esac" else "ESAC has no checkpoints: rerun with --force")
        print(f"{exc}: {out}/{RUN_FILE} records it{where}; {again}", file=sys.stderr,
              flush=True)
        raise SystemExit(128 + signal.Signals[exc.signal_name].value) from None
    best = run.get("best", {})
    frac = best.get("oracle_fraction")
    print(f"done in {run['total_wall_s']:.0f} s: {out}/{run['model']}"
          f" (validation return {best.get('return', float('nan')):.4f}, oracle fraction "
          f"{'-' if frac is None else f'{frac:.3f}'})")
    return run


def _sweep(ap: argparse.ArgumentParser, args: argparse.Namespace, out: str) -> dict[str, Any]:
    """``--seeds``: one run per seed (:func:`agents.training.sweep.train_seeds`)."""
    from .sweep import train_seeds, parse_seeds

    if args.seeds is None:
        ap.error("--workers and --ray-address run several runs: give --seeds (or --tune)")
    if args.seed != 0:
        ap.error("--seed is one run's seed: with --seeds, list the seeds there")
    if args.resume or args.force:
        ap.error("--seeds starts new runs into <out>/seed_<s>: --resume and --force take one run")
    try:
        sweep = train_seeds(args.algo, out, parse_seeds(args.seeds), args.workers,
                            args.ray_address, not args.no_progress, preset=args.preset,
                            timesteps=args.timesteps, budget=args.budget, config=args.config,
                            overrides=args.set, rig=args.rig)
    except ValueError as exc:
        ap.error(str(exc))
    except KeyboardInterrupt:
        print(f"sweep interrupted: finished runs stay in {out}/seed_*; train the missing seeds "
              f"with --seeds into a new --out", file=sys.stderr, flush=True)
        raise SystemExit(130) from None
    figs = [f"{k} {v['mean']:.4f} +- {v['std']:.4f}" for k, v in sweep["summary"].items()
            if v is not None and k != "wall_s"]
    print(f"done in {sweep['wall_s']:.0f} s ({sweep['backend']}): {len(sweep['seeds'])} runs in "
          f"{out}; {', '.join(figs) or 'no validation figures'}; {out}/sweep.json")
    return sweep


def _tune(ap: argparse.ArgumentParser, args: argparse.Namespace, out: str) -> dict[str, Any]:
    """``--tune``: a Ray Tune + Optuna search (:func:`agents.training.tune.tune_hyperparameters`)."""
    from .tune import tune_hyperparameters

    if args.seeds is not None or args.resume or args.force:
        ap.error("--tune trains new runs with one --seed: --seeds, --resume and --force do not apply")
    try:
        res = tune_hyperparameters(args.algo, out, args.tune, args.trials, args.seed,
                                   args.workers, args.ray_address, preset=args.preset,
                                   timesteps=args.timesteps, budget=args.budget,
                                   config=args.config, overrides=args.set, rig=args.rig)
    except ValueError as exc:
        ap.error(str(exc))
    except RuntimeError as exc:  # failed trials: the others are recorded
        print(f"error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    best = res["best"]
    ret = best["validation_return"]
    print(f"done in {res['wall_s']:.0f} s: {res['trials']} trials; best validation return "
          f"{'-' if ret is None else f'{ret:.4f}'} with {' '.join(best['overrides'])} "
          f"(its run: {out}/trials/{best['trial']}); {out}/tune.json")
    return res
