"""Benchmark cut-off policies on the pneugym suites and write results.json, results.csv and plots.

    python evaluate.py       # baselines + trained ESAC, PPO, DQN (trained on demand), both suites
    python evaluate.py --policies conventional gaslaw oracle ppo=runs/ppo/model.zip \\
        --suite robustness --episodes 3 --seed 1000000 --out results
    python evaluate.py --policies gaslaw esac=runs/esac esac10=runs/esac:max_time_increase=0.1

Suites (sensor noise 0.03 mm / 400 Pa in every episode):
- ``nominal``: the thesis conditions, 1.5 and 2.5 bar gauge with 10 kg;
- ``robustness``: load {5, 10, 15, 20, 30} kg x supply {1.5, 2, 2.5, 3, 4, 5} bar, plus
  disturbance sets at 1.5 and 2.5 bar with 10 kg: random supply dips (10-30 %, 50-300 ms),
  friction -30 % / +30 %, valve delay -20 % / +20 %.

Every policy meets the same episodes (conditions and sensor noise from ``--seed``; keep evaluation
seeds >= 1,000,000, the range this project never uses for training or calibration). Every saved
model is loaded and checked (file, observation layout, decision overrides) before any episode
runs or any policy is trained on demand; a problem is a usage error (exit 2) naming it.
``oracle_fraction = (return - conventional return) / (oracle return - conventional return)``
on the suite's (or condition's) mean returns.
"""
from __future__ import annotations

import argparse
import csv
import math
import re
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from tqdm import tqdm

import pneugym  # noqa: F401  (registers the environment)
from agents import BASELINES, make_policy
from agents.base import Policy, run_first_episodes
from agents.registry import load_policy
from pneugym.envs import Conditions, ConditionSpace
from pneugym.envs.cutoff import CutOffVectorEnv
from pneugym.outputs import atomic_write_json, check_output_dir, staged_files
from pneugym.provenance import provenance

DEFAULT_POLICIES = ["conventional", "endstroke", "gaslaw", "esac", "ppo", "dqn", "oracle"]
LEARNED = ("esac", "ppo", "dqn")  # a bare name: the model under --runs, trained if missing
NOISE = {"position_noise_m": 3e-5, "pressure_noise_pa": 400.0}
LOADS_KG = (5.0, 10.0, 15.0, 20.0, 30.0)
SUPPLIES_BAR = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0)
EVAL_SEED = 1_000_000


def _fixed(bar: float, kg: float, **kw: Any) -> ConditionSpace:
    return ConditionSpace(supply_pressure_gauge_pa=bar * 1e5, load_mass_kg=kg, **NOISE, **kw)


def suite_cells(suite: str) -> list[tuple[str, ConditionSpace]]:
    """The condition cells of a suite: ``(label, space to draw each episode's conditions from)``."""
    if suite == "nominal":
        return [(f"{b:g}bar-10kg", _fixed(b, 10.0)) for b in (1.5, 2.5)]
    if suite == "robustness":
        cells = [(f"{b:g}bar-{m:g}kg", _fixed(b, m)) for m in LOADS_KG for b in SUPPLIES_BAR]
        for b in (1.5, 2.5):
            cells += [
                (f"{b:g}bar-dip", _fixed(b, 10.0, dip_probability=1.0, dip_depth=(0.1, 0.3),
                                         dip_duration_s=(0.05, 0.3), dip_start_s=(0.0, 1.0))),
                (f"{b:g}bar-friction-30%", _fixed(b, 10.0, friction_scale=0.7)),
                (f"{b:g}bar-friction+30%", _fixed(b, 10.0, friction_scale=1.3)),
                (f"{b:g}bar-valve-delay-20%", _fixed(b, 10.0, valve_delay_scale=0.8)),
                (f"{b:g}bar-valve-delay+20%", _fixed(b, 10.0, valve_delay_scale=1.2)),
            ]
        return cells
    raise ValueError(f"unknown suite {suite!r}; choose nominal, robustness or all")


def suite_episodes(suite: str, episodes: int, seed: int) -> list[tuple[str, Conditions]]:
    """``episodes`` draws per cell, each from its own seeded generator."""
    out = []
    for c, (label, space) in enumerate(suite_cells(suite)):
        for k in range(episodes):
            rng = np.random.default_rng([seed, c, k])
            out.append((label, space.sample(rng)))
    return out


def run_policy(policy: Policy, conds: Sequence[Conditions], env_config: dict, seed: int
               ) -> dict[str, np.ndarray]:
    """Final figures of one episode per condition, all stepped as one batch."""
    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **env_config)
    return run_first_episodes(env, policy, list(conds), seed)


def _mean(v: Sequence[Any]) -> float | None:
    vals = [float(x) for x in v if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(vals)) if vals else None


def summarize(rec: list[dict[str, Any]], conv: float, oracle: float) -> dict[str, Any]:
    """Suite (or condition) metrics of one policy's episode records."""
    ret = _mean([r["objective"] for r in rec])
    gap = oracle - conv
    return {
        "episodes": len(rec),
        "saving_mean": _mean([r["saving_ratio"] for r in rec]),
        "time_increase_mean": _mean([r["time_increase"] for r in rec]),
        "stall_rate": _mean([r["stalled"] for r in rec]),
        "stick_slip_rate": _mean([r["stick_slip_events"] > 0 for r in rec]),
        "completion_rate": _mean([r["completed"] for r in rec]),
        "return_mean": ret,
        "oracle_fraction": (ret - conv) / gap if abs(gap) > 1e-12 else None,
    }


def evaluate(policies: Sequence[str], suites: Sequence[str], episodes: int, seed: int,
             env_config: dict | None = None,
             preloaded: Mapping[str, Policy] | None = None) -> dict[str, Any]:
    """Run every policy on every suite; returns the results.json structure. ``preloaded``:
    policies already loaded (:func:`load_models`), by name."""
    env_config = dict(env_config or {})
    check_policy_specs(policies)
    names = list(dict.fromkeys(["conventional", *policies, "oracle"]))  # references always run
    probe = CutOffVectorEnv(num_envs=1, **env_config)
    preloaded = dict(preloaded or {})
    results: dict[str, Any] = {"suites": {}}
    for suite in suites:
        eps = suite_episodes(suite, episodes, seed)
        conds = [c for _, c in eps]
        records: dict[str, list[dict[str, Any]]] = {}
        wall: dict[str, float] = {}
        for spec in tqdm(names, desc=f"{suite} suite", unit="policy"):
            name = parse_spec(spec)[0]
            name, pol = (name, preloaded[name]) if name in preloaded else _policy(
                spec, probe, env_config)
            t0 = time.perf_counter()
            out = run_policy(pol, conds, env_config, seed)
            wall[name] = time.perf_counter() - t0
            records[name] = [
                {"suite": suite, "policy": name, "condition": label, "episode": i,
                 **{k: _py(v[i]) for k, v in out.items()}, **c.to_dict()}
                for i, (label, c) in enumerate(eps)]
        conv_ret = _mean([r["objective"] for r in records["conventional"]])
        orc_ret = _mean([r["objective"] for r in records["oracle"]])
        labels = list(dict.fromkeys(label for label, _ in eps))
        pols = {}
        for name, rec in records.items():
            s = summarize(rec, conv_ret, orc_ret)
            s["wall_time_s"] = wall[name]
            s["per_condition"] = {}
            for lab in labels:
                sub = [r for r in rec if r["condition"] == lab]
                cr = _mean([r["objective"] for r in records["conventional"] if r["condition"] == lab])
                orr = _mean([r["objective"] for r in records["oracle"] if r["condition"] == lab])
                s["per_condition"][lab] = summarize(sub, cr, orr)
            pols[name] = s
        results["suites"][suite] = {"policies": pols, "conditions": labels,
                                    "episodes": [r for rec in records.values() for r in rec]}
    results["config"] = {"policies": names, "suites": list(suites), "episodes": episodes,
                         "seed": seed, "env_config": {k: repr(v) if not isinstance(
                             v, (int, float, str, bool, type(None))) else v
                             for k, v in env_config.items()},
                         "sensor_noise": NOISE}
    results["seed"] = seed
    prov = provenance()
    results["versions"] = prov.pop("versions")
    results["provenance"] = prov
    return results


def resolve_learned(policies: Sequence[str], runs: str, budget: str) -> list[str]:
    """Bare names of learned policies become ``NAME=PATH`` of their model under ``runs``,
    trained first (train.py's ``budget``) where none is there yet."""
    names = [p for p in policies if p in LEARNED]
    if not names:
        return list(policies)
    import train

    paths = train.ensure_trained(names, runs, budget)
    return [f"{p}={paths[p]}" if p in paths else p for p in policies]


def parse_spec(spec: str) -> tuple[str, str | None, dict[str, Any]]:
    """``NAME``, or ``NAME=PATH[:key=value,...]`` of a saved model with its decision overridden:
    ESAC rule parameters (``esac10=runs/esac:max_time_increase=0.1``), or an SB3 model's
    ``rule`` and ``value`` (``ppo3=runs/ppo:rule=quantile,value=0.3``). Numbers are read as
    numbers, anything else as text; the values are checked when the model is loaded
    (:func:`agents.registry.load_policy`)."""
    if "=" not in spec:
        return spec, None, {}
    name, path = spec.split("=", 1)
    over: dict[str, Any] = {}
    head, sep, tail = path.rpartition(":")
    if sep and "=" in tail:
        path = head
        for item in tail.split(","):
            key, eq, val = (x.strip() for x in item.partition("="))
            if not eq or not key:
                raise ValueError(f"{spec!r}: overrides are key=value pairs separated by commas "
                                 f"(e.g. {name}={path}:margin=0.05,max_time_increase=0.1)")
            if not val:
                raise ValueError(f"{spec!r}: {key}= has no value; give one, e.g. {key}=0.1")
            if key in over:
                raise ValueError(f"{spec!r}: {key} is given twice")
            try:
                over[key] = float(val)
            except ValueError:
                over[key] = val
    if {"rule", "value"} & set(over):
        if set(over) - {"rule", "value"}:
            raise ValueError(f"{spec!r}: an SB3 decision override takes rule and value only; "
                             f"{sorted(set(over) - {'rule', 'value'})} are ESAC rule parameters")
        over = {"decision": over}
    return name, path, over


#: Names a saved model may not take: the references every suite runs, and the baselines.
RESERVED = ("conventional", "oracle")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


def check_policy_specs(specs: Sequence[str]) -> list[str]:
    """Refuse what would give a wrong table: a saved model under a baseline's or a reference's
    name (``conventional=runs/ppo`` would replace the reference of every oracle fraction), a
    name given twice (rows would overwrite each other), an empty or odd name. Returns the
    names in order."""
    names = []
    for spec in specs:
        name, path, _ = parse_spec(spec)
        if path is not None:
            if name in BASELINES:
                role = "a reference of every suite" if name in RESERVED else "a baseline"
                raise ValueError(f"{spec!r}: {name!r} is {role}; give the saved model another "
                                 f"name (e.g. {name}_model={path})")
            if not path:
                raise ValueError(f"{spec!r}: no model path after '='")
            if not Path(path).exists():
                hint = (" (overrides follow the path as :key=value, e.g. "
                        f"{path.rpartition(':')[0]}:margin=0.05)"
                        if ":" in path and "=" not in path.rpartition(":")[2] else "")
                raise FileNotFoundError(f"{spec!r}: no saved model at {path}{hint}")
        elif name not in BASELINES and name not in LEARNED:
            raise ValueError(f"unknown policy {spec!r}: baselines are {sorted(BASELINES)}, "
                             f"learned ones {list(LEARNED)} (trained on demand under --runs), "
                             f"saved models are given as NAME=PATH")
        if not _NAME.match(name):
            raise ValueError(f"{spec!r}: policy name {name!r} must start with a letter or digit "
                             f"and hold only letters, digits and _ . + -")
        if name in names:
            raise ValueError(f"policy name {name!r} is given twice: its rows would overwrite "
                             f"each other; give each policy its own name")
        names.append(name)
    return names


def load_models(specs: Sequence[str], runs: str | Path = "runs", budget: str = "quick",
                env_config: dict | None = None) -> dict[str, Policy]:
    """Load, and so check, every saved model the run needs before any episode or training:
    each ``NAME=PATH`` (file, layout, decision override) and each bare learned name whose run
    under ``runs`` is finished; for the others, check that train.py can train or resume them
    (:func:`train.training_plan`). Returns the loaded policies by name; raises ValueError
    naming the spec and what is wrong."""
    probe = CutOffVectorEnv(num_envs=1, **dict(env_config or {}))
    out: dict[str, Policy] = {}
    bare = [s for s in specs if s in LEARNED]
    todo: list[tuple[str, str, Path | str, dict[str, Any]]] = []
    if bare:
        import train

        for name, (what, p) in train.training_plan(bare, runs, budget).items():
            if what == "ready":
                todo.append((name, name, p, {}))
    for spec in specs:
        name, path, over = parse_spec(spec)
        if path is not None:
            todo.append((spec, name, path, over))
    for spec, name, path, over in todo:
        try:
            out[name] = load_policy(path, probe, **over)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{spec!r}: {exc}") from None
    return out


def _policy(spec: str, env, env_config: dict) -> tuple[str, Policy]:
    name, path, over = parse_spec(spec)
    if path is not None:
        return name, load_policy(path, env, **over)
    if spec not in BASELINES:
        raise SystemExit(f"unknown policy {spec!r}: baselines are {sorted(BASELINES)}, learned "
                         f"ones {list(LEARNED)}, saved models are given as NAME=PATH")
    return spec, make_policy(spec, env)


def _py(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return v


# --------------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------------
def print_table(results: dict[str, Any]) -> None:
    for suite, s in results["suites"].items():
        n = next(iter(s["policies"].values()))["episodes"]
        print(f"\n== {suite} suite ({n} episodes per policy)")
        print(f"{'policy':<14}{'saving %':>9}{'time +%':>9}{'stall %':>8}{'stick %':>8}"
              f"{'done %':>8}{'return':>9}{'oracle fr.':>11}")
        for name, p in s["policies"].items():
            def pct(v):
                return f"{100 * v:.1f}" if v is not None else "-"
            of = p["oracle_fraction"]
            print(f"{name:<14}{pct(p['saving_mean']):>9}{pct(p['time_increase_mean']):>9}"
                  f"{pct(p['stall_rate']):>8}{pct(p['stick_slip_rate']):>8}"
                  f"{pct(p['completion_rate']):>8}{p['return_mean']:>9.3f}"
                  f"{(f'{of:.3f}' if of is not None else '-'):>11}")
    print("(oracle: privileged, knows each episode's conditions; oracle fraction = share of the "
          "oracle's gain over conventional)")


def write_outputs(results: dict[str, Any], out: str | Path) -> None:
    """results.json, results.csv and the plots, replacing those in ``out`` only once all are
    written (an error leaves the previous set untouched)."""
    with staged_files(out) as stage:
        atomic_write_json(stage / "results.json", results)
        rows = [r for s in results["suites"].values() for r in s["episodes"]]
        if rows:
            keys = list(dict.fromkeys(k for r in rows for k in r))
            with open(stage / "results.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=keys)
                w.writeheader()
                w.writerows(rows)
        plot_results(results, stage)


def plot_results(results: dict[str, Any], out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for suite, s in results["suites"].items():
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for name in s["policies"]:
            rec = [r for r in s["episodes"] if r["policy"] == name and r["completed"]]
            x = [100 * r["time_increase"] for r in rec]
            y = [100 * r["saving_ratio"] for r in rec]
            pts = ax.scatter(x, y, s=10, alpha=0.35)
            p = s["policies"][name]
            if p["time_increase_mean"] is not None:
                ax.scatter(100 * p["time_increase_mean"], 100 * p["saving_mean"], s=90,
                           marker="*", color=pts.get_facecolor()[0], edgecolor="k",
                           label=name)
        ax.set_xlabel("stroke-time increase [%]")
        ax.set_ylabel("energy saved (eq. 5.10) [%]")
        ax.set_title(f"{suite} suite: episodes and means (stars)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.savefig(out / f"{suite}_saving_vs_time.png", dpi=120, bbox_inches="tight")
        plt.close(fig)
    rob = results["suites"].get("robustness")
    if rob:
        names = list(rob["policies"])
        fig, axes = plt.subplots(2, len(names), figsize=(3.2 * len(names), 5.6), squeeze=False)
        for j, name in enumerate(names):
            pc = rob["policies"][name]["per_condition"]
            for row, (key, title, vmin, vmax) in enumerate(
                    (("saving_mean", "saving", 0.0, 1.0), ("oracle_fraction", "oracle fr.", -1, 1))):
                grid = np.full((len(LOADS_KG), len(SUPPLIES_BAR)), np.nan)
                for a, m in enumerate(LOADS_KG):
                    for b, bar in enumerate(SUPPLIES_BAR):
                        v = pc.get(f"{bar:g}bar-{m:g}kg", {}).get(key)
                        grid[a, b] = np.nan if v is None else v
                ax = axes[row, j]
                im = ax.imshow(grid, origin="lower", vmin=vmin, vmax=vmax, cmap="viridis",
                               aspect="auto")
                ax.set_xticks(range(len(SUPPLIES_BAR)), [f"{b:g}" for b in SUPPLIES_BAR])
                ax.set_yticks(range(len(LOADS_KG)), [f"{m:g}" for m in LOADS_KG])
                ax.set_title(f"{name}: {title}", fontsize=9)
                if j == 0:
                    ax.set_ylabel("load [kg]")
                if row == 1:
                    ax.set_xlabel("supply [bar g]")
                fig.colorbar(im, ax=ax, fraction=0.046)
        fig.tight_layout()
        fig.savefig(out / "robustness_heatmaps.png", dpi=110)
        plt.close(fig)
    plot_examples(results, out)


def plot_examples(results: dict[str, Any], out: Path) -> None:
    """Position and driving pressure of one nominal 2.5 bar episode under each baseline."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pneugym.envs.cutoff import CutOffEnv
    from pneugym.physics import layout as L

    names = [n for n in results["config"]["policies"] if n in BASELINES]
    fig, ax = plt.subplots(2, 1, figsize=(6.5, 5), sharex=True)
    cond = Conditions(supply_pressure_gauge_pa=2.5e5)
    for name in names:
        env = CutOffEnv(render_mode="rgb_array")
        pol = make_policy(name, env)
        obs, info = env.reset(seed=EVAL_SEED, options={"conditions": cond})
        pol.begin_episodes([cond])
        done = False
        while not done:
            a, _ = pol.predict(obs)
            obs, _, te, tr, info = env.step(a)
            done = te or tr
        tr_ = np.array(env._trace)
        ax[0].plot(tr_[:, L.R_T], tr_[:, L.R_X] * 1e3, label=f"{name} ({100 * info['saving_ratio']:.0f} %)")
        ax[1].plot(tr_[:, L.R_T], (tr_[:, L.R_PD] - 101325.0) / 1e5, label=name)
    ax[0].set_ylabel("position [mm]")
    ax[1].set_ylabel("driving pressure [bar g]")
    ax[1].set_xlabel("time since the extend command [s]")
    ax[0].set_title("one nominal episode (2.5 bar, 10 kg) per policy; energy saved in brackets",
                    fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "example_trajectories.png", dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policies", nargs="+", default=DEFAULT_POLICIES,
                    help="baseline names, learned ones (esac, ppo, dqn: runs/<name>, trained "
                         "on demand) and/or NAME=PATH of saved models")
    ap.add_argument("--runs", default="runs", help="where learned policies are (and are trained)")
    ap.add_argument("--budget", default="quick",
                    help="train.py budget for learned policies trained on demand")
    ap.add_argument("--suite", default="all", choices=["nominal", "robustness", "all"])
    ap.add_argument("--episodes", type=int, default=2, help="episodes per condition cell")
    ap.add_argument("--seed", type=int, default=EVAL_SEED)
    ap.add_argument("--out", default="results")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes {args.episodes}: must be >= 1 (episodes per condition cell)")
    if not 0 <= args.seed < 2 ** 63:
        ap.error(f"--seed {args.seed}: episode seeds must be integers from 0 to 2**63 - 1; "
                 f"held-out results use {EVAL_SEED:,} and up")
    try:  # before any work: a wrong name, an unusable model or --out must not cost a training
        check_policy_specs(args.policies)
        preloaded = load_models(args.policies, args.runs, args.budget)
        check_output_dir(args.out, "--out")  # the string as given: "" is not the current folder
    except (ValueError, OSError) as exc:
        ap.error(str(exc))
    if args.seed < EVAL_SEED:
        print(f"warning: --seed {args.seed} lies in the range used for training and tuning "
              f"(below {EVAL_SEED:,}); figures on it are not held-out results", file=sys.stderr)
    suites = ["nominal", "robustness"] if args.suite == "all" else [args.suite]
    policies = resolve_learned(args.policies, args.runs, args.budget)
    results = evaluate(policies, suites, args.episodes, args.seed, preloaded=preloaded)
    print_table(results)
    write_outputs(results, args.out)
    print(f"\nwrote {args.out}/results.json, results.csv and plots")
    return results


if __name__ == "__main__":
    main()
