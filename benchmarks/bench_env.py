"""Speed of the cut-off environment against Gymnasium's ``CartPole-v1``, measured in one run.

Run from the repository root::

    python benchmarks/bench_env.py            # full run (1-2 minutes on 2 cores)
    python benchmarks/bench_env.py --quick    # ~30 s: fewer repeats and steps
    python benchmarks/bench_env.py --out DIR  # where env.json goes (default benchmarks/results)

Cases (see ``benchmarks/README.md``), all timed round-robin in one process after a warm-up:

- ``cartpole``: ``gymnasium.make("CartPole-v1")``, one environment;
- ``cutoff``: ``gymnasium.make("pneugym/CutOff-v0")``, one environment;
- ``cartpole_vec64``: ``gymnasium.make_vec("CartPole-v1", 64, vectorization_mode="vector_entry_point")``
  (Gymnasium's numpy ``CartPoleVectorEnv``), for context;
- ``cutoff_vec64``: ``gymnasium.make_vec("pneugym/CutOff-v0", 64,
  vectorization_mode="vector_entry_point")`` with numba's default thread count, and
  ``cutoff_vec64_1thread`` with ``numba.set_num_threads(1)``;
- ``cutoff_sb3_vec64``: the same batch behind the SB3 adapter (``CutOffVecEnv``).

Each environment gets the same pre-drawn actions (a cut-off with probability 1 % per step, so
episodes end by arrival, stall and cut-off, and resets are part of the cost). The figures are env
steps per second (a vector step of 64 environments counts 64). The issue's goals: one
environment >= 0.3x CartPole's rate, the batch of 64 >= 2x. Then, not round-robin: where a
vector step's time goes, at 64 and 256 envs, on one and on all numba threads (its compiled call
against the Python around it, and the step's speed-up on all threads; ``step_split``: each thread
count in a block of its own, as a user runs it); the oracle's
plan (its search episodes per second) and a Gas-Law K sweep (episodes per second).
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

import gymnasium as gym  # noqa: E402
import numba  # noqa: E402

import pneugym  # noqa: E402,F401  (registers pneugym/CutOff-v0)
from pneugym.provenance import provenance  # noqa: E402

GOAL_SINGLE = 0.3
GOAL_VEC64 = 2.0
N_VEC = 64
P_CUT = 0.01


def stats(values):
    a = np.asarray(values, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max()),
            "n": int(a.size)}


# ------------------------------------------------------------------------------------------
# cases: each is a callable that runs a fixed number of env steps and returns it
# ------------------------------------------------------------------------------------------
class SingleCase:
    """``steps`` steps of one environment, resetting when an episode ends."""

    def __init__(self, env_id: str, steps: int, seed: int, **kwargs):
        self.env = gym.make(env_id, **kwargs)
        self.steps = steps
        self.actions = (np.random.default_rng(seed).random(steps) < P_CUT).astype(np.int64)
        self.env.reset(seed=seed)
        self.episodes = 0

    def __call__(self) -> int:
        env, acts = self.env, self.actions
        for k in range(self.steps):
            _, _, term, trunc, _ = env.step(int(acts[k]))
            if term or trunc:
                env.reset()
                self.episodes += 1
        return self.steps


class VectorCase:
    """``calls`` steps of a vector env (gymnasium API; autoreset inside)."""

    def __init__(self, env_id: str, calls: int, seed: int, threads: int | None = None,
                 num_envs: int = N_VEC, **kwargs):
        self.env = gym.make_vec(env_id, num_envs=num_envs,
                                vectorization_mode="vector_entry_point", **kwargs)
        self.calls = calls
        self.threads = threads
        self.num_envs = num_envs
        self.actions = (np.random.default_rng(seed).random((calls, num_envs)) < P_CUT
                        ).astype(np.int64)
        self.env.reset(seed=seed)

    def __call__(self) -> int:
        prev = numba.get_num_threads()
        if self.threads:
            numba.set_num_threads(self.threads)
        try:
            for k in range(self.calls):
                self.env.step(self.actions[k])
        finally:
            numba.set_num_threads(prev)
        return self.calls * self.num_envs


class SB3Case:
    """``calls`` steps of the SB3 adapter (``step_async`` + ``step_wait``)."""

    def __init__(self, calls: int, seed: int):
        from pneugym.envs.sb3 import CutOffVecEnv

        self.env = CutOffVecEnv(num_envs=N_VEC)
        self.env.seed(seed)
        self.env.reset()
        self.calls = calls
        self.actions = (np.random.default_rng(seed).random((calls, N_VEC)) < P_CUT).astype(np.int64)

    def __call__(self) -> int:
        for k in range(self.calls):
            self.env.step(self.actions[k])
        return self.calls * N_VEC


def step_split(calls: int, reps: int, seed: int, threads: int, num_envs: int = N_VEC) -> dict:
    """Where a vector step's time goes on ``threads`` numba threads: the whole step, its
    one compiled call (``pneugym.envs.episode.step_observe``, the plants and the sensing) and
    the Python around it (the actions' check, the infos, the resets of finished episodes), in
    microseconds per step (median and range over ``reps`` runs of ``calls`` steps)."""
    from pneugym.envs import episode as EP

    inner, spent = EP.step_observe, [0.0]

    def timed(*args):
        t0 = time.perf_counter()
        out = inner(*args)
        spent[0] += time.perf_counter() - t0
        return out

    prev = numba.get_num_threads()
    numba.set_num_threads(threads)
    case = VectorCase("pneugym/CutOff-v0", calls, seed, num_envs=num_envs)
    EP.step_observe = timed
    try:
        case()  # warm-up
        total, kernel = [], []
        for _ in range(reps):
            spent[0] = 0.0
            t0 = time.perf_counter()
            case()
            total.append((time.perf_counter() - t0) / calls * 1e6)
            kernel.append(spent[0] / calls * 1e6)
    finally:
        EP.step_observe = inner
        numba.set_num_threads(prev)
    python = [t - k for t, k in zip(total, kernel)]
    return {"num_envs": num_envs, "threads": threads, "calls": calls, "step_us": stats(total),
            "compiled_call_us": stats(kernel), "python_us": stats(python)}


def round_robin(cases: dict, reps: int) -> dict[str, list[float]]:
    """Steps per second of every case, one call of each per round, after a warm-up round."""
    for fn in cases.values():
        fn()
    rates: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(reps):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            n = fn()
            rates[name].append(n / (time.perf_counter() - t0))
    return rates


# ------------------------------------------------------------------------------------------
# episodes per second of the oracle's search and the Gas-Law sweep
# ------------------------------------------------------------------------------------------
def bench_oracle(n_conditions: int, seed: int) -> dict:
    from agents import OraclePolicy
    from pneugym.envs import PRESETS, CutOffEnv

    pol = OraclePolicy.for_env(CutOffEnv())
    counted = {"episodes": 0}
    inner = pol._figures

    def counting(*args, **kwargs):
        fig = inner(*args, **kwargs)
        counted["episodes"] += len(fig["objective"])
        return fig

    pol._figures = counting
    rng = np.random.default_rng(seed)
    conds = [PRESETS["randomized"].sample(rng) for _ in range(n_conditions)]
    pol.plan(PRESETS["thesis-2.5bar"].sample(rng))  # warm-up (compilation, caches)
    counted["episodes"] = 0
    t0 = time.perf_counter()
    for c in conds:
        pol.plan(c)
    wall = time.perf_counter() - t0
    return {"plans": n_conditions, "wall_s": wall, "s_per_plan": wall / n_conditions,
            "search_episodes": counted["episodes"],
            "episodes_per_plan": counted["episodes"] / n_conditions,
            "episodes_per_s": counted["episodes"] / wall,
            "numba_threads": numba.get_num_threads()}


def bench_gaslaw(n_k: int, reps: int) -> dict:
    from agents.gaslaw import sweep

    ks = np.geomspace(0.02, 20.0, n_k)
    sweep(2.5, ks[:2])  # warm-up
    walls = []
    for _ in range(reps):
        t0 = time.perf_counter()
        sweep(2.5, ks)
        walls.append(time.perf_counter() - t0)
    w = float(np.median(walls))
    return {"episodes_per_sweep": n_k, "sweep_wall": stats(walls), "episodes_per_s": n_k / w,
            "calibrate_estimate_s": 6 * w, "numba_threads": numba.get_num_threads()}


# ------------------------------------------------------------------------------------------
def table(headers, rows) -> str:
    cells = [list(map(str, headers))] + [[str(c) for c in r] for r in rows]
    w = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    line = lambda r: "  ".join(c.rjust(w[i]) if i else c.ljust(w[i])  # noqa: E731
                               for i, c in enumerate(r))
    return "\n".join([line(cells[0]), "  ".join("-" * x for x in w)] + [line(r) for r in cells[1:]])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"), help="output directory")
    ap.add_argument("--quick", action="store_true", help="~30 s: fewer repeats and steps")
    ap.add_argument("--repeats", type=int, default=None, help="rounds (default 15, quick 5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-extras", action="store_true", help="skip the oracle and Gas-Law figures")
    args = ap.parse_args(argv)
    reps = args.repeats or (5 if args.quick else 15)
    steps = 1000 if args.quick else 3000      # single-env steps per call
    calls = 30 if args.quick else 100         # vector steps per call (x64 env steps)

    load0 = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    s = args.seed
    cases = {
        "cartpole": SingleCase("CartPole-v1", steps, s),
        "cutoff": SingleCase("pneugym/CutOff-v0", steps, s),
        "cartpole_vec64": VectorCase("CartPole-v1", calls, s),
        "cutoff_vec64": VectorCase("pneugym/CutOff-v0", calls, s),
        "cutoff_vec64_1thread": VectorCase("pneugym/CutOff-v0", calls, s, threads=1),
        "cutoff_sb3_vec64": SB3Case(calls, s),
    }
    rates = round_robin(cases, reps)
    med = {k: float(np.median(v)) for k, v in rates.items()}
    cp = med["cartpole"]
    ratios = {k: v / cp for k, v in med.items()}
    result = {
        "config": {"repeats": reps, "single_steps_per_call": steps, "vector_calls": calls,
                   "num_envs": N_VEC, "p_cut_per_step": P_CUT, "seed": s, "quick": args.quick,
                   "numba_threads_default": numba.get_num_threads(),
                   "numba_threading_layer": numba.config.THREADING_LAYER,
                   "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                   "cpu_count": os.cpu_count(), "loadavg_start": load0},
        "steps_per_s": {k: stats(v) for k, v in rates.items()},
        "ratio_vs_cartpole": ratios,
        "goals": {"single": GOAL_SINGLE, "vec64": GOAL_VEC64,
                  "single_met": ratios["cutoff"] >= GOAL_SINGLE,
                  "vec64_met": ratios["cutoff_vec64"] >= GOAL_VEC64,
                  "vec64_1thread_met": ratios["cutoff_vec64_1thread"] >= GOAL_VEC64},
        "cutoff_episodes_single": cases["cutoff"].episodes,
    }
    labels = {"cartpole": "CartPole-v1 (gym.make)", "cutoff": "pneugym/CutOff-v0 (gym.make)",
              "cartpole_vec64": "CartPole-v1 make_vec 64 (numpy)",
              "cutoff_vec64": f"CutOff-v0 make_vec 64 ({numba.get_num_threads()} numba threads)",
              "cutoff_vec64_1thread": "CutOff-v0 make_vec 64 (1 numba thread)",
              "cutoff_sb3_vec64": "CutOff-v0 SB3 CutOffVecEnv 64"}
    goal = {"cutoff": f">= {GOAL_SINGLE}x", "cutoff_vec64": f">= {GOAL_VEC64}x",
            "cutoff_vec64_1thread": f">= {GOAL_VEC64}x"}
    rows = [[labels[k], f"{med[k]:,.0f}", f"{stats(rates[k])['min']:,.0f}",
             f"{stats(rates[k])['max']:,.0f}", f"{ratios[k]:.3g}x", goal.get(k, "")]
            for k in cases]
    print(table(["case", "env steps/s (median)", "min", "max", "vs CartPole", "goal"], rows))

    threads = sorted({1, numba.get_num_threads()})
    split = [step_split(calls if n == N_VEC else calls // 4, reps, s, t, n)
             for n in (N_VEC, 4 * N_VEC) for t in threads]
    result["step_split"] = split
    print()
    print(table(["vector step", "step [us]", "compiled call [us]", "Python [us]",
                 "vs 1 thread"],
                [[f"{d['num_envs']} envs, {d['threads']} numba thread(s)",
                  f"{d['step_us']['median']:.0f}", f"{d['compiled_call_us']['median']:.0f}",
                  f"{d['python_us']['median']:.0f}",
                  f"{split[i - i % len(threads)]['step_us']['median'] / d['step_us']['median']:.2f}x"]
                 for i, d in enumerate(split)]))

    if not args.no_extras:
        prev = numba.get_num_threads()
        result["oracle"] = bench_oracle(2 if args.quick else 3, s)
        numba.set_num_threads(1)
        result["oracle_1thread"] = bench_oracle(2 if args.quick else 3, s + 1)
        numba.set_num_threads(prev)
        result["gaslaw_sweep"] = bench_gaslaw(64, 3 if args.quick else 5)
        numba.set_num_threads(1)
        result["gaslaw_sweep_1thread"] = bench_gaslaw(64, 3 if args.quick else 5)
        numba.set_num_threads(prev)
        rows = []
        for k in ("oracle", "oracle_1thread"):
            o = result[k]
            rows.append([f"oracle plan ({o['numba_threads']} thr)", f"{o['episodes_per_s']:,.0f}",
                         f"{o['episodes_per_plan']:.0f} episodes, {o['s_per_plan']:.2f} s/plan"])
        for k in ("gaslaw_sweep", "gaslaw_sweep_1thread"):
            gl = result[k]
            rows.append([f"Gas-Law K sweep ({gl['numba_threads']} thr)", f"{gl['episodes_per_s']:,.0f}",
                         f"64 K in {gl['sweep_wall']['median']:.2f} s; calibrate (6 supplies) "
                         f"~{gl['calibrate_estimate_s']:.1f} s"])
        print()
        print(table(["search", "episodes/s", "note"], rows))

    try:
        result["config"]["numba_threading_layer_used"] = numba.threading_layer()
    except ValueError:  # no parallel region ran
        pass
    result["config"]["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    result["provenance"] = provenance()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "env.json", "w") as fh:
        json.dump(result, fh, indent=1)
    print(f"\nload average {load0} -> {result['config']['loadavg_end']}; wrote {out / 'env.json'}")
    return result


if __name__ == "__main__":
    main()
