"""Decision latency of the neural policies on one core, their network on torch, onnxruntime and
numpy, against the budget of a control period; and whether the three decide alike.

For every model (default: the run directories ``esac``, ``ppo`` and ``esac-family`` under
``--runs``; others as ``NAME=PATH``), loaded with :func:`agents.registry.load_policy` for a
one-cylinder environment observing the rig (as a controller runs it):

- **latency**: the network alone on one input row (the backend's share), then
  ``policy.predict(obs)`` on single observations, replayed from nominal episodes
  (the policy stacks the history and keeps its state as on a rig), ``--calls`` calls per
  backend, the backends interleaved call by call; median, p99 and max [us], and as a fraction
  of the budget. With :class:`pneugym.deploy.Controller`, its ``step`` (raw samples in, valve
  command out) is timed the same way on the sensor readings of those episodes;
- **decisions**: the nominal suite (``--episodes`` per cell, two cells) on every backend: the
  fraction of episodes whose cut-off time equals torch's;
- **outputs**: the largest difference of the network's outputs from torch's on the inputs it
  saw in those episodes before the cut (after it the decision is latched), against
  ``pneugym.deploy.export``'s tolerance.

Budget: the control period (5 ms) minus ``--reserve-ms`` for the sample and command I/O. The
valve's response is not subtracted: its switching delay (``ValveParams.delay_s``, 185-215 ms
by the thesis) and opening/closing ramp (``ramp_s``, 10 ms) both exceed the period and follow
the command; the plant simulates them, so the policies were trained with them. What the
environment does not model is the decision's own latency, which delays the command; it must
end before the next sample. The JSON records the valve's figures next to the latencies.

One core: the process is pinned to ``--core``; torch, onnxruntime, numba and BLAS use one
thread each. Writes ``deploy.json`` and ``deploy.png`` to ``--out``.

    python benchmarks/bench_deploy.py --runs runs                 # 2000 calls, 24 x 2 episodes
    python benchmarks/bench_deploy.py --runs /tmp/mj3/runs --calls 2000 --episodes 4
    python benchmarks/bench_deploy.py --models ppo=runs/ppo --out bench/deploy
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy, numba and torch start their pools

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable, Sequence  # noqa: E402

from common import fmt_table, g, machine_info  # noqa: E402  (the checkout on sys.path)

DEFAULT_MODELS = ("esac", "ppo", "esac-family")
BACKENDS = ("torch", "onnx", "numpy")
#: rows of network inputs kept per model to compare the backends' outputs on
MAX_ROWS = 20_000


def main(argv: Sequence[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--models", nargs="+", default=None,
                    help="NAME=PATH of trained models (run directories or model files); default "
                         "the runs esac, ppo, esac-family under --runs that exist")
    ap.add_argument("--runs", default="runs", help="folder of the default models' runs")
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS)
    ap.add_argument("--calls", type=int, default=2000, help="timed decisions per backend (>= 2000 "
                                                            "for a meaningful p99)")
    ap.add_argument("--episodes", type=int, default=24,
                    help="nominal-suite episodes per cell (two cells) for the decision check")
    ap.add_argument("--seed", type=int, default=5_000_000, help="seed of the suite's episodes")
    ap.add_argument("--reserve-ms", type=float, default=0.0,
                    help="time of the control period kept for sampling and the valve command "
                         "[ms], taken off the budget")
    ap.add_argument("--core", type=int, default=0, help="the CPU core to pin the process to")
    ap.add_argument("--no-controller", action="store_true",
                    help="skip timing pneugym.deploy.Controller.step")
    ap.add_argument("--baselines", nargs="*", default=["gaslaw", "mpc"],
                    help="baselines whose Controller.step is timed too (no network, no backend)")
    ap.add_argument("--out", default="bench/deploy", help="folder for the results")
    args = ap.parse_args(argv)
    if args.calls < 1 or args.episodes < 1:
        ap.error("--calls and --episodes must be >= 1")
    models = _models(args, ap)
    threads = one_core(args.core)

    from agents.evaluation.specs import evaluation_env_config
    from agents.evaluation.suites import suite_episodes
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    cfg = evaluation_env_config({})
    probe = CutOffVectorEnv(num_envs=1, **cfg)
    rig = probe.rig
    budget = budget_s(float(probe.control_period_s), args.reserve_ms * 1e-3)
    conds = [c for _, c in suite_episodes("nominal", args.episodes, args.seed)]
    result: dict[str, Any] = {
        "budget": {"control_period_s": float(probe.control_period_s),
                   "reserve_s": args.reserve_ms * 1e-3, "budget_s": budget,
                   "valve_delay_s": {f"{p / 1e5:g}bar": rig.valve.delay_for(p)
                                     for p in (1.5e5, 2.5e5)},
                   "valve_ramp_s": rig.valve.ramp_s,
                   "why": "control period minus I/O reserve; the valve's delay and ramp follow "
                          "the command and are simulated (see the module docstring)"},
        "models": {}, "config": vars(args), "threads": threads, "machine": machine_info(),
        "provenance": provenance()}
    for name, path in models.items():
        print(f"== {name}: {path}", flush=True)
        result["models"][name] = bench_model(name, path, probe, conds, cfg, args, budget)
    result["baselines"] = {}
    for name in args.baselines:
        print(f"== {name} (baseline)", flush=True)
        result["baselines"][name] = time_baseline(name, conds, args.seed, budget)
    _report(result)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "deploy.json").write_text(json.dumps(result, indent=2, default=str))
    _plot(result, out / "deploy.png")
    print(f"wrote {out / 'deploy.json'} and .png")
    return result


def _models(args: argparse.Namespace, ap: argparse.ArgumentParser) -> dict[str, Path]:
    if args.models:
        out = {}
        for spec in args.models:
            name, sep, path = spec.partition("=")
            if not sep:
                ap.error(f"--models {spec!r}: give NAME=PATH")
            out[name] = Path(path)
        return out
    out = {n: Path(args.runs) / n for n in DEFAULT_MODELS if (Path(args.runs) / n).exists()}
    if not out:
        ap.error(f"no runs {list(DEFAULT_MODELS)} under {args.runs}: give --runs or --models")
    return out


def one_core(core: int) -> dict[str, Any]:
    """Pin the process to ``core`` and every runtime to one thread; what was set."""
    import numba
    import torch

    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})
    torch.set_num_threads(1)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already started: it runs no work here anyway
        pass
    numba.set_num_threads(1)
    return {"affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
            else None, "torch": torch.get_num_threads(), "numba": numba.get_num_threads(),
            "onnxruntime": "intra_op 1, inter_op 1 (pneugym.deploy.export.OnnxNetwork)"}


def budget_s(control_period_s: float, reserve_s: float = 0.0) -> float:
    """A decision's time budget [s]: the control period less the I/O reserve."""
    return control_period_s - reserve_s


def bench_model(name: str, path: Path, probe, conds, cfg, args, budget: float) -> dict[str, Any]:
    """Latency, decisions and outputs of one model on every backend."""
    import numpy as np

    from agents.evaluation.run import run_policy
    from agents.registry import RigMismatchWarning, load_policy
    from pneugym.deploy.export import max_difference, with_backend

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RigMismatchWarning)
        base = load_policy(path, probe)
    pols = {b: with_backend(base, b) for b in args.backends}
    rec: dict[str, Any] = {"path": str(path), "policy": type(base).__name__}
    # decisions over the suite, and the network's inputs before the cut
    ref_b = args.backends[0]
    recorder, previous = _record_inputs(pols[ref_b])
    cuts = {}
    for b, p in pols.items():
        cuts[b] = run_policy(p, conds, cfg, args.seed)["cutoff_time_s"].astype(float)
    _unrecord(pols[ref_b], previous)
    rec["decisions"] = {
        "episodes": len(conds), "reference": ref_b,
        "identical_cut_time_fraction": {b: float(np.mean(_same(c, cuts[ref_b])))
                                        for b, c in cuts.items()},
        "cut_fraction": float(np.mean(np.isfinite(cuts[ref_b])))}
    x = np.concatenate(recorder.rows) if recorder.rows else np.zeros((0, 1), np.float32)
    ref = _network(pols[ref_b])(x)
    rec["outputs"] = {"rows": int(x.shape[0]), "reference": ref_b,
                      "max_abs_output": float(np.abs(ref).max(initial=0.0)),
                      **{b: max_difference(_network(p)(x), ref) for b, p in pols.items()
                         if b != ref_b}}
    # latency: the network alone (one input row), then whole decisions
    rec["network"] = {b: _summary(t, budget) for b, t in time_network(
        {b: _network(p) for b, p in pols.items()}, x, args.calls).items()}
    trace = _episode_observations(probe, conds[:: max(1, len(conds) // 4)], args.seed)
    rec["latency"] = {b: _summary(t, budget) for b, t in
                      time_policy(pols, trace, args.calls).items()}
    if not args.no_controller:
        rec["controller_step"] = time_controller(path, args.backends, pols[ref_b], conds,
                                                 args.seed, args.calls, budget)
    return rec


class _Recorder:
    """Wraps a network evaluation; keeps (a sample of) its input rows before the cut."""

    def __init__(self, fn: Callable, cut_col: int):
        self.fn, self.cut_col, self.rows, self.n, self.calls = fn, cut_col, [], 0, 0

    def __call__(self, x):
        self.calls += 1
        if self.n < MAX_ROWS:
            keep = x[x[:, self.cut_col] < 0.5]
            self.rows.append(keep.copy())
            self.n += keep.shape[0]
        return self.fn(x)


def _record_inputs(policy) -> tuple[_Recorder, Any]:
    """Put a :class:`_Recorder` in ``policy``'s network seam; returns it and what it replaced."""
    holder = policy.predictor if hasattr(policy, "predictor") else policy
    cut_col = policy._cut_index if hasattr(policy, "predictor") else policy._cut_idx
    previous = holder._backend
    holder.backend = r = _Recorder(holder.backend, cut_col)
    return r, previous


def _unrecord(policy, previous: Any) -> None:
    (policy.predictor if hasattr(policy, "predictor") else policy).backend = previous


def _network(policy) -> Callable:
    return policy.predictor.backend if hasattr(policy, "predictor") else policy.backend


def _same(a, b):
    import numpy as np

    return (a == b) | (np.isnan(a) & np.isnan(b))


def _episode_observations(probe, conds, seed: int) -> list:
    """Single-cylinder observation sequences of nominal episodes (cut as endstroke would not:
    the stroke runs uncut, so every step asks the policy)."""
    import numpy as np

    from pneugym.envs.cutoff import CutOffVectorEnv

    out = []
    for k, c in enumerate(conds):
        env = CutOffVectorEnv(num_envs=1, autoreset=False, **probe.config)
        obs, _ = env.reset(seed=seed + k, options={"conditions": [c]})
        seq = []
        while True:
            seq.append(obs[0].copy())
            obs, _, term, trunc, _ = env.step(np.zeros(1, dtype=np.int64))
            if term[0] or trunc[0]:
                break
        out.append(np.asarray(seq))
    return out


def time_network(nets: dict[str, Callable], x, calls: int) -> dict[str, Any]:
    """Wall time [s] of each backend's network evaluation on one input row (rows of ``x`` in
    turn), interleaved call by call, after one warm-up call each."""
    import numpy as np

    rows = [x[i:i + 1] for i in range(min(len(x), calls))] or [np.zeros((1, 1), np.float32)]
    times: dict[str, list] = {b: [] for b in nets}
    for f in nets.values():
        f(rows[0])
    for k in range(calls):
        r = rows[k % len(rows)]
        for b, f in nets.items():
            t0 = time.perf_counter()
            f(r)
            times[b].append(time.perf_counter() - t0)
    return {b: np.asarray(t) for b, t in times.items()}


def time_policy(policies: dict[str, Any], episodes: Sequence, calls: int) -> dict[str, list]:
    """Wall time [s] of ``policy.predict(obs)`` per call, per backend: single observations
    (``episodes``: observation sequences, replayed in turn, each starting a new episode), the
    backends interleaved call by call so that load hits them alike. One warm-up episode first."""
    import numpy as np

    times: dict[str, list] = {b: [] for b in policies}
    clock = time.perf_counter
    first = True
    while first or len(next(iter(times.values()))) < calls:
        for seq in episodes:
            for p in policies.values():
                p.begin_episodes([None])
            for o in seq:
                for b, p in policies.items():
                    t0 = clock()
                    p.predict(o)
                    dt = clock() - t0
                    if not first:
                        times[b].append(dt)
            first = False
            if len(next(iter(times.values()))) >= calls:
                break
    return {b: np.asarray(t[:max(calls, 1)]) for b, t in times.items()}


def time_controller(path: Path, backends: Sequence[str], policy, conds, seed: int, calls: int,
                    budget: float) -> dict[str, Any]:
    """Wall time of :meth:`pneugym.deploy.Controller.step` per backend, on the sensor readings
    of nominal episodes (``pneugym.deploy.check.environment_trace``), interleaved call by call;
    and whether the backends' controllers gave the same commands."""
    import numpy as np

    try:
        from agents.evaluation.specs import evaluation_env_config
        from pneugym.deploy import Controller
        from pneugym.deploy.check import environment_trace
        from pneugym.envs.commissioning import condition_features
    except ImportError as exc:
        return {"error": f"pneugym.deploy.Controller unavailable: {exc}"}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # a rig other than the trained one
            ctls = {b: Controller.load(path, backend=b) for b in backends}
        some = conds[:: max(1, len(conds) // 4)]
        traces = environment_trace(policy, some, seed, evaluation_env_config({}))
        pa = ctls[backends[0]].rig.gas.ambient_pressure_pa
        times: dict[str, list] = {b: [] for b in backends}
        commands: dict[str, list] = {b: [] for b in backends}
        rounds = 0
        while rounds == 0 or len(times[backends[0]]) < calls:
            for c, tr in zip(some, traces):
                for ctl in ctls.values():  # (told the stroke the environment observed)
                    ctl.reset(c.supply_pressure_gauge_pa + pa, c.load_mass_kg,
                              commissioning=condition_features(c, ctl.rig))
                for j in range(tr["t"].size):
                    for b, ctl in ctls.items():
                        t0 = time.perf_counter()
                        cmd = ctl.step(tr["t"][j], tr["x"][j], tr["p_drive"][j],
                                       tr["p_exhaust"][j])
                        dt = time.perf_counter() - t0
                        if rounds:  # the first round warms up
                            times[b].append(dt)
                            commands[b].append(cmd)
            rounds += 1
        ref = np.asarray(commands[backends[0]])
        return {**{b: _summary(np.asarray(t[:calls]), budget) for b, t in times.items()},
                "same_commands_fraction": {b: float(np.mean(np.asarray(c) == ref))
                                           for b, c in commands.items()}}
    except Exception as exc:  # noqa: BLE001 - the controller is optional here; say why
        return {"error": f"{type(exc).__name__}: {exc}"}


def time_baseline(name: str, conds, seed: int, budget: float) -> dict[str, Any]:
    """Wall time of :meth:`pneugym.deploy.Controller.step` of the baseline ``name`` on the
    sensor readings of a quarter of the nominal episodes (every decision timed, none warmed:
    a baseline compiles nothing per call), and the fraction of decisions over the budget."""
    import numpy as np

    from agents import make_policy
    from pneugym.deploy import Controller
    from pneugym.deploy.check import environment_trace
    from pneugym.envs.cutoff import CutOffVectorEnv

    some = conds[:: max(1, len(conds) // 4)]
    env = CutOffVectorEnv(num_envs=len(some), observe_rig=True)
    traces = environment_trace(make_policy(name, env), some, seed, {"observe_rig": True})
    ctl = Controller.load(name)
    pa = ctl.rig.gas.ambient_pressure_pa
    times = []
    for c, tr in zip(some, traces):
        ctl.reset(c.supply_pressure_gauge_pa + pa, c.load_mass_kg)
        for j in range(tr["t"].size):
            t0 = time.perf_counter()
            ctl.step(tr["t"][j], tr["x"][j], tr["p_drive"][j], tr["p_exhaust"][j])
            times.append(time.perf_counter() - t0)
    t = np.asarray(times)
    return {**_summary(t, budget), "over_budget_fraction": float(np.mean(t > budget)),
            "episodes": len(some)}


def _summary(t, budget: float) -> dict[str, float]:
    import numpy as np

    t = np.asarray(t, float)
    med, p99, mx = (float(np.median(t)), float(np.percentile(t, 99)), float(t.max()))
    return {"calls": int(t.size), "median_us": med * 1e6, "p99_us": p99 * 1e6,
            "max_us": mx * 1e6, "mean_us": float(t.mean()) * 1e6,
            "median_of_budget": med / budget, "p99_of_budget": p99 / budget,
            "max_of_budget": mx / budget}


def _report(result: dict) -> None:
    b = result["budget"]
    print(f"\nbudget {b['budget_s'] * 1e3:g} ms per decision (control period "
          f"{b['control_period_s'] * 1e3:g} ms - reserve {b['reserve_s'] * 1e3:g} ms; valve delay "
          f"{min(b['valve_delay_s'].values()) * 1e3:g}-{max(b['valve_delay_s'].values()) * 1e3:g} "
          f"ms and ramp {b['valve_ramp_s'] * 1e3:g} ms follow the command, simulated)")
    rows = []
    for name, m in result["models"].items():
        for what in ("network", "latency", "controller_step"):
            for be, s in (m.get(what) or {}).items():
                if isinstance(s, dict) and "median_us" in s:
                    call = {"network": "network", "latency": "predict"}.get(what, "Controller.step")
                    rows.append([name, call, be,
                                 g(s["median_us"]), g(s["p99_us"]), g(s["max_us"]),
                                 f"{100 * s['p99_of_budget']:.2f}%",
                                 f"{100 * s['max_of_budget']:.2f}%"])
            if isinstance(m.get(what), dict) and "error" in m[what]:
                rows.append([name, what, "-", m[what]["error"][:60], "", "", "", ""])
    for name, s in result.get("baselines", {}).items():
        rows.append([name, "Controller.step", "-", g(s["median_us"]), g(s["p99_us"]),
                     g(s["max_us"]), f"{100 * s['p99_of_budget']:.2f}%",
                     f"{100 * s['max_of_budget']:.2f}%"])
    print(fmt_table(["model", "call", "backend", "median us", "p99 us", "max us", "p99/budget",
                     "max/budget"], rows, title="\ndecision latency, one core"))
    rows = []
    for name, m in result["models"].items():
        d, o = m["decisions"], m["outputs"]
        for be, frac in d["identical_cut_time_fraction"].items():
            diff = o.get(be, {})
            rows.append([name, be, f"{frac:.3f}", d["episodes"], g(diff.get("max_abs"), 3),
                         g(diff.get("max_ratio"), 3), g(o["max_abs_output"], 4), o["rows"]])
    print(fmt_table(["model", "backend", "same cut time", "episodes", "max |out diff|",
                     "diff/tolerance", "max |out|", "rows"], rows,
                    title="\ndecisions (nominal suite) and outputs against torch"))


def _plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    models = list(result["models"])
    backends = result["config"]["backends"]
    panels = [("network", "network (one row)"), ("latency", "policy.predict"),
              ("controller_step", "Controller.step")]
    panels = [p for p in panels if any("median_us" in (result["models"][m].get(p[0]) or {}).get(
        backends[0], {}) for m in models)]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 4), squeeze=False,
                             sharey=True)
    budget_us = result["budget"]["budget_s"] * 1e6
    w = 0.8 / len(backends)
    for ax, (key, title) in zip(axes[0], panels):
        for k, be in enumerate(backends):
            med = [(result["models"][m].get(key) or {}).get(be, {}).get("median_us", np.nan)
                   for m in models]
            p99 = [(result["models"][m].get(key) or {}).get(be, {}).get("p99_us", np.nan)
                   for m in models]
            xs = np.arange(len(models)) + (k - (len(backends) - 1) / 2) * w
            ax.bar(xs, med, w, label=f"{be} median")
            ax.scatter(xs, p99, color="k", marker="_", s=120, zorder=3,
                       label="p99" if k == 0 else None)
        ax.axhline(budget_us, color="r", lw=1, label=f"budget {budget_us / 1e3:g} ms")
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(models)), models)
        ax.set_ylabel("latency per decision [us], one core")
        ax.set_title(title, fontsize=9)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
