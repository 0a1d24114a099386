"""Cost of the learned cut-off policies: the time one decision takes (next to the environment step
it has to fit into, 5 ms of simulated time) and training throughput, measured in one run.

Run from the repository root::

    python benchmarks/bench_policies.py              # full run (~15-30 s on 2 cores)
    python benchmarks/bench_policies.py --quick      # ~10 s: fewer repeats, shorter training
    python benchmarks/bench_policies.py --runs runs  # where the trained models are (runs/<name>)
    python benchmarks/bench_policies.py --out DIR    # where policies.json goes

Sections:

- ``decide``: ``policy.predict(obs)`` for one observation and for a batch of 64, for the baselines
  (conventional, Gas-Law) and every trained model found under ``--runs`` (esac, ppo, dqn), timed
  round-robin in one process after a warm-up, next to one ``CutOffEnv.step`` (the reference: the
  ratios hold on a busy machine, the absolute times do not). A learned policy in a ``history=1``
  environment also stacks its history (included).
- ``train``: throughput of each training stage with the default configs: PPO and DQN
  environment steps per second (``model.learn``), ESAC rollouts per second and fit seconds per
  epoch per 10,000 samples.

Medians of the repeats; ``policies.json`` also has min and max, the configuration, versions and
the load average.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

import numba  # noqa: E402
import torch  # noqa: E402

import pneugym  # noqa: E402,F401
from agents import make_policy  # noqa: E402
from agents.registry import load_policy  # noqa: E402
from pneugym.envs import Conditions  # noqa: E402
from pneugym.envs.cutoff import CutOffEnv, CutOffVectorEnv  # noqa: E402
from pneugym.provenance import provenance  # noqa: E402


def stats(values) -> dict:
    a = np.asarray(values, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max()),
            "n": int(a.size)}


def observations(n: int, seed: int) -> np.ndarray:
    """Realistic observations (history=1): samples along a few nominal episodes."""
    env = CutOffVectorEnv(num_envs=4, autoreset=True, preset="randomized")
    obs, _ = env.reset(seed=seed)
    out = []
    while sum(len(o) for o in out) < n:
        obs, *_ = env.step(np.zeros(4, dtype=np.int64))
        out.append(obs.copy())
    return np.concatenate(out)[:n]


def bench_decide(runs: Path, repeats: int, calls: int, seed: int) -> dict:
    env1 = CutOffVectorEnv(num_envs=1)
    pols = {"conventional": make_policy("conventional", env1),
            "gaslaw": make_policy("gaslaw", env1)}
    missing = []
    for name in ("esac", "ppo", "dqn"):
        try:
            pols[name] = load_policy(runs / name, env1)
        except (FileNotFoundError, ValueError) as exc:
            missing.append(f"{name}: {exc}")
    obs = observations(64 * calls, seed)
    step_env = CutOffEnv()
    step_env.reset(seed=seed, options={"conditions": Conditions()})

    def env_step():
        for _ in range(calls):
            _, _, te, tr, _ = step_env.step(0)
            if te or tr:
                step_env.reset(seed=seed, options={"conditions": Conditions()})

    def decide(pol, b):
        def run():
            for k in range(calls):
                pol.predict(obs[k * b:(k + 1) * b] if b > 1 else obs[k])
        return run

    cases = {"env_step": env_step}
    for name, pol in pols.items():
        cases[f"{name}/1"] = decide(pol, 1)
        cases[f"{name}/64"] = decide(pol, 64)
    for fn in cases.values():  # warm-up (compilation, first torch calls)
        fn()
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(repeats):
        for k, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            times[k].append((time.perf_counter() - t0) / calls * 1e6)
    res = {k: stats(v) for k, v in times.items()}
    ref = res["env_step"]["median"]
    return {"us_per_call": res, "ratio_to_env_step": {k: v["median"] / ref
                                                      for k, v in res.items()},
            "missing": missing}


def bench_train(quick: bool, seed: int) -> dict:
    import tempfile

    from stable_baselines3 import PPO

    from agents import esac
    from agents.training import load_config
    from agents.training.sb3 import LatchedDQN, TrainingVecEnv

    out: dict = {}
    steps = 8_192 if quick else 32_768
    for algo in ("ppo", "dqn"):
        cfg = load_config(algo)
        env_cfg = dict(cfg["env"])
        n = int(env_cfg.pop("num_envs"))
        venv = TrainingVecEnv(num_envs=n, preset=cfg["preset"], **env_cfg)
        kwargs = dict(cfg["algo"])
        if algo == "dqn":
            kwargs["learning_starts"] = min(int(kwargs["learning_starts"]), steps // 4)
        cls = PPO if algo == "ppo" else LatchedDQN
        model = cls("MlpPolicy", venv, seed=seed, device="cpu",
                    policy_kwargs=cfg.get("policy_kwargs"), **kwargs)
        t0 = time.perf_counter()
        model.learn(steps)
        wall = time.perf_counter() - t0
        out[algo] = {"steps": int(model.num_timesteps), "wall_s": wall,
                     "steps_per_s": model.num_timesteps / wall}
    cfg = load_config("esac")
    n = 256 if quick else 1024
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        data = esac.rollouts(tmp, n, seed, int(cfg["env"]["history"]), cfg["preset"],
                             progress=False)
        wall = time.perf_counter() - t0
    fit = cfg["fit"]
    x, y, m, _ = esac.samples(data, 0.18, bool(fit.get("delay_input", False)))
    epochs = 3
    t0 = time.perf_counter()
    esac.fit(x, y, m, hidden=tuple(fit["hidden"]), epochs=epochs,
             batch_size=int(fit["batch_size"]), lr=float(fit["lr"]), patience=epochs,
             progress=False)
    fwall = time.perf_counter() - t0
    out["esac"] = {"rollouts": n, "rollout_wall_s": wall, "rollouts_per_s": n / wall,
                   "samples_per_rollout": x.shape[0] / data["obs"].shape[0],
                   "fit_s_per_epoch_per_10k": fwall / epochs / x.shape[0] * 1e4}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--runs", default="runs", help="directory with esac/, ppo/, dqn/ runs")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=None, help="rounds (default 15, quick 5)")
    ap.add_argument("--no-train", action="store_true", help="skip the training throughput")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    repeats = args.repeats or (5 if args.quick else 15)
    load0 = os.getloadavg()
    res = {"config": {"repeats": repeats, "quick": args.quick, "runs": args.runs,
                      "seed": args.seed, "numba_threads": 1, "torch_threads": 1,
                      "cpu_count": os.cpu_count(), "loadavg_start": load0}}
    res["decide"] = bench_decide(Path(args.runs), repeats, 20 if args.quick else 50, args.seed)
    d = res["decide"]
    print(f"\n{'decision':<18}{'µs / call':>11}{'x env step':>12}")
    for k, v in d["us_per_call"].items():
        print(f"{k:<18}{v['median']:>11.1f}{d['ratio_to_env_step'][k]:>12.2f}")
    for m in d["missing"]:
        print(f"(not measured: {m})")
    if not args.no_train:
        res["train"] = bench_train(args.quick, args.seed)
        t = res["train"]
        print(f"\ntraining throughput: PPO {t['ppo']['steps_per_s']:.0f} steps/s, DQN "
              f"{t['dqn']['steps_per_s']:.0f} steps/s, ESAC {t['esac']['rollouts_per_s']:.1f} "
              f"rollouts/s and {t['esac']['fit_s_per_epoch_per_10k']:.2f} s per epoch per 10k "
              f"samples")
    res["config"]["loadavg_end"] = os.getloadavg()
    res["provenance"] = provenance()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".policies.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(res, indent=1))
    tmp.replace(out / "policies.json")
    print(f"\nwrote {out / 'policies.json'}")
    return res


if __name__ == "__main__":
    main()
