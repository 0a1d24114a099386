"""Sweep throughput on 1 and 2 workers: the same small training sweep (several seeds of one
algorithm) run one seed after the other, in 2 local processes and, with Ray installed, as tasks
of a local Ray runtime with 2 CPUs; runs per minute, the speed-ups as ratios, and the check that
every backend gives every seed the same validation figures. See ``benchmarks/README.md``.

    python benchmarks/bench_scale.py [--quick] [--seeds 0-3] [--out DIR]

Writes ``scale.json`` and ``scale.png``. Every backend shares one rollout / reference cache,
filled by an untimed warm-up run of the same seeds, so the timed runs measure training.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, fmt_table, json_default, machine_info, versions

from agents.training.sweep import parse_seeds, train_seeds

# a small PPO run, long enough (about 20 s) that starting a process (about 5 s) is not the whole story
PPO = ["env.num_envs=8", "env.history=4", "algo.n_steps=128", "algo.batch_size=256",
       "algo.n_epochs=4", "eval_every=4096", "checkpoint_every=8192", "validation.episodes=8"]


def _figures(sw):
    return {k: (r["validation_return"], r["oracle_fraction"]) for k, r in sw["runs"].items()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds of 16384 steps (else 4 of 65536)")
    ap.add_argument("--seeds", default=None, help="training seeds (default 0-3, quick 0-1)")
    ap.add_argument("--timesteps", type=int, default=None)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds or ("0-1" if a.quick else "0-3"))
    steps = a.timesteps or (16384 if a.quick else 65536)
    scratch = Path(tempfile.mkdtemp(prefix="bench-scale-"))
    kw = dict(timesteps=steps, overrides=[*PPO, f"cache_dir={scratch / 'cache'}"])
    backends = [("serial", 1, None), ("processes", 2, None)]
    if importlib.util.find_spec("ray") is not None:
        backends.append(("ray local", 2, "local"))
    try:
        train_seeds("ppo", scratch / "warm-up", seeds, progress=False, **kw)  # fills the caches
        rows, res = [], {"config": {"algo": "ppo", "seeds": seeds, "timesteps": steps,
                                    "overrides": PPO}, "backends": {}}
        ref = None
        for name, workers, addr in backends:
            t0 = time.perf_counter()
            sw = train_seeds("ppo", scratch / name.replace(" ", "-"), seeds, workers, addr,
                             progress=False, **kw)
            wall = time.perf_counter() - t0
            ref = ref or _figures(sw)
            res["backends"][name] = {"workers": workers, "wall_s": wall,
                                     "runs_per_min": 60 * len(seeds) / wall,
                                     "same_figures_as_serial": _figures(sw) == ref,
                                     "figures": _figures(sw)}
        base = res["backends"]["serial"]["wall_s"]
        for name, b in res["backends"].items():
            b["speed_up"] = base / b["wall_s"]
            rows.append([name, b["workers"], f"{b['wall_s']:.1f}", f"{b['runs_per_min']:.2f}",
                         f"{b['speed_up']:.2f}x", b["same_figures_as_serial"]])
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print(fmt_table(["backend", "workers", "wall [s]", "runs / min", "speed-up", "same figures"],
                    rows, title=f"PPO sweep, {len(seeds)} seeds x {steps} steps"))
    from pneugym.provenance import provenance

    # (the training timings follow torch and stable-baselines3, the Ray ones Ray)
    res["machine"], res["versions"] = machine_info(), {**provenance()["versions"], **versions()}
    try:
        import ray

        res["versions"]["ray"] = ray.__version__
    except ImportError:
        res["versions"]["ray"] = "not installed"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scale.json").write_text(json.dumps(res, indent=2, default=json_default))
    _plot(res, out / "scale.png")
    print(f"wrote {out / 'scale.json'} and scale.png")
    return res


def _plot(res, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(res["backends"])
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.bar(names, [res["backends"][n]["runs_per_min"] for n in names], color="tab:blue")
    for i, n in enumerate(names):
        ax.text(i, res["backends"][n]["runs_per_min"], f"{res['backends'][n]['speed_up']:.2f}x",
                ha="center", va="bottom")
    ax.set_ylabel("training runs per minute")
    ax.set_title(f"PPO sweep: {len(res['config']['seeds'])} seeds x {res['config']['timesteps']} steps")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
