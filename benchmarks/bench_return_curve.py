"""How far a cut-off learned across the rig family can get from what a policy may observe: the
return of every cut-off time, learned from the oracle's search, told the observation or the
hidden truth, and how it grows with the number of family draws.

A diagnosis for issue 12's learned-policy targets, not a policy the package ships. For each
family draw (``agents.evaluation.suites.family_draws``) it runs the oracle's scoring
(``OraclePolicy.score_cuts``: the noise-free episode on the jitted plant) at cut-off times on a
grid of 45 fractions (``GRID``) of the commissioning stroke's time (what the observation
states) and never cutting. A network (an MLP, mean squared error) learns the return of each grid cut as
a fraction of the draw's best gain over the conventional stroke, from

- **observed**: what a family policy may read before the stroke: the supply set-point, the rig
  file's datasheet values and the six features of the commissioning stroke
  (``observe_rig``, ``observe_commissioning``; the stroke's own events are left out: they hold
  the time until they happen);
- **truth**: the draw's hidden rig (every field the family draws), supply, load and supply dip
  (privileged: no policy may read it).

The cut is the grid time of the highest predicted return (open loop: a full-information
contextual bandit, every draw labelling every cut; the learning problem a model-free agent
meets with one cut per episode). Figures: the pooled oracle fraction (mean return over the
draws, against the grid's best and never cutting) on ``--val-seed`` draws (the choices of this
script, the network and its loss, were made on them) and on ``--held-out-seed`` draws (those of
``bench_mpc.py``'s first held-out set, where ``mpc-rig`` keeps 0.845 of the first 40), for nested
training sets of ``--sizes`` draws and ``--fit-seeds`` network seeds; then the observed network
on the whole training set on the transfer suite's episodes (against the suite oracle's
search; returns noise-free, so within a few thousandths of ``pneugym evaluate``'s).
Writes ``return_curve.json`` (configuration, provenance, every figure), ``return_curve.csv``
(the learning curves) and ``return_curve.png``, and keeps the scored draws (``scores-*.npz``,
reused by a later run into the same ``--out`` for the same draws and sources).

    python benchmarks/bench_return_curve.py --workers 2    # about 25 minutes on 2 cores
    python benchmarks/bench_return_curve.py --draws 3072 --sizes 768 1536 3072 --workers 2
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import operator
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from common import ROOT, json_default  # noqa: F401

from pneugym.parallel import add_arguments as add_parallel_arguments  # noqa: E402

#: cut-off times tried, as fractions of the commissioning stroke's time
GRID = tuple(float(f) for f in np.round(np.linspace(0.15, 1.25, 45), 6))
#: the rig features a policy can only know once the stroke has shown them (left out)
EVENT_FEATURES = ("t_pressure_rise", "t_breakaway", "dp_breakaway")
#: where a grid cut's fraction of the best gain is clipped (a stall costs several gains)
CLIP = (-3.0, 1.0)
#: least gain [return] a draw's fractions are divided by (a draw where cutting gains nothing)
MIN_GAIN = 0.05
HIDDEN = (128, 128)
EPOCHS = 60


def env_config() -> dict[str, Any]:
    from agents.evaluation.specs import evaluation_env_config

    return evaluation_env_config({"history": 8})


def static_columns(layout: dict[str, Any]) -> list[int]:
    """Observation columns a policy may read before the stroke: the newest sample's supply
    set-point, then the rig features but the stroke's events."""
    feats = layout["features"]
    newest = (int(layout["history"]) - 1) * len(feats)
    cols = [newest + [f["name"] for f in feats].index("supply_setpoint")]
    start = int(layout["history"]) * len(feats)
    cols += [start + k for k, f in enumerate(layout["rig_features"])
             if f["name"] not in EVENT_FEATURES]
    return cols


def truth_features(conds: Sequence[Any]) -> np.ndarray:
    """The hidden truth of each draw: every rig field the family draws (the base rig's where a
    draw leaves it, 0 where that is None: an effect off; a model form as 1 where it differs
    from the base's), supply, load and the supply dip (0 without one)."""
    from pneugym.envs.family import FAMILY_FIELDS, apply_changes
    from pneugym.params import RigParams

    base = RigParams()
    rows = []
    for c in conds:
        rig = apply_changes(base, c.rig_changes)
        row = []
        for name in FAMILY_FIELDS:
            value = operator.attrgetter(name)  # (a dotted field)
            v = value(rig)
            row.append(float(v != value(base)) if isinstance(v, str) else
                       0.0 if v is None else float(v))  # (None: the effect is off)
        dip = [0.0 if v is None else float(v) for v in (c.dip_start_s, c.dip_duration_s,
                                                          c.dip_depth)]  # None: no dip
        rows.append(row + [c.supply_pressure_gauge_pa, c.load_mass_kg] + dip)
    return np.array(rows, dtype=float)


def score_chunk(conds: Sequence[Any], seed: int, grid: Sequence[float]) -> dict[str, np.ndarray]:
    """For ``conds``: the observation at the extend command (``X``), the return of a cut at
    every ``grid`` fraction of the commissioning stroke's time (``R``) and never cutting
    (``RC``), that time (``TC``) [s], and the truth (``T``)."""
    from agents.base import ObservationReader
    from agents.oracle import OraclePolicy
    from pneugym.envs.cutoff import CutOffVectorEnv

    env = CutOffVectorEnv(num_envs=len(conds), autoreset=False, **env_config())
    obs, _ = env.reset(seed=seed, options={"conditions": list(conds)})
    layout = env.observation_layout()
    period = float(layout["control_period_s"])
    tc = ObservationReader(layout)(obs, "comm_stroke_time")
    oracle = OraclePolicy(layout, env_config=env.config, seed=seed)
    quiet = {i: c.noise_free() for i, c in enumerate(conds)}
    steps = [[round(f * t / period) * period for f in grid] for t in tc]
    scores = oracle.score_cuts(quiet, {i: sorted(set(s)) + [math.inf]
                                       for i, s in enumerate(steps)})
    R = np.array([[scores[i][t] for t in s] for i, s in enumerate(steps)])
    RC = np.array([scores[i][math.inf] for i in range(len(conds))])
    return {"X": obs.astype(np.float64), "R": R, "RC": RC, "TC": tc,
            "T": truth_features(conds)}


def score_draws(conds: Sequence[Any], seed: int, grid: Sequence[float], workers: int = 1,
                desc: str = "draws", chunk: int = 64, progress: bool = True,
                ray_address: str | None = None) -> dict[str, np.ndarray]:
    """:func:`score_chunk` over ``conds`` in chunks of ``chunk`` draws
    (:func:`pneugym.parallel.run_tasks`: ``workers`` processes or Ray); draw ``j`` with noise
    seed ``seed + j`` (the vector environment seeds its sub-environments in turn from a chunk's
    seed), so the numbers do not depend on where the chunks run. (The sensor noise touches only
    the observation's sensor samples, which the networks do not read; the returns are scored
    without it.)"""
    from pneugym.parallel import run_tasks

    tasks = [{"conds": list(conds[i:i + chunk]), "seed": seed + i, "grid": tuple(grid)}
             for i in range(0, len(conds), chunk)]
    out = run_tasks(score_chunk, tasks, workers, ray_address, progress=progress,
                    desc=f"{desc} ({chunk} draws a task)",
                    pythonpath=[str(Path(__file__).resolve().parent)])
    return {k: np.concatenate([o[k] for o in out]) for k in out[0]}


def fraction_targets(R: np.ndarray, RC: np.ndarray) -> np.ndarray:
    """Each grid cut's return as a fraction of the draw's best gain over never cutting
    (at least :data:`MIN_GAIN`), clipped to :data:`CLIP`."""
    best = np.maximum(R.max(1), RC)
    gain = np.maximum(best - RC, MIN_GAIN)
    return np.clip((R - RC[:, None]) / gain[:, None], *CLIP)


def cached(out: Path, name: str, conds: Sequence[Any], seed: int, workers: int,
           progress: bool, ray_address: str | None) -> dict[str, np.ndarray]:
    """:func:`score_draws` of ``conds``, kept in ``out`` (``scores-*.npz``) under a key of the
    conditions, the noise seed, the grid, the environment's options and the sources of
    ``pneugym``, ``agents``, ``configs`` and this script, and reused from there."""
    import hashlib

    from common import versions

    key = hashlib.sha256(json.dumps([
        repr(list(conds)), seed, GRID, repr(sorted(env_config().items())),
        versions()["pneugym_source_sha256"],
        hashlib.sha256(Path(__file__).read_bytes()).hexdigest()]).encode())
    path = out / f"scores-{name}-{key.hexdigest()[:12]}.npz"
    if path.is_file():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    d = score_draws(conds, seed, GRID, workers, name, progress=progress,
                    ray_address=ray_address)
    np.savez_compressed(path, **d)
    return d


def log_columns(T: np.ndarray) -> np.ndarray:
    """The truth's columns (of the training draws ``T``) that are positive and span more than
    5x: the network reads their logarithm as well."""
    lo = np.where(T.min(0) > 0, T.min(0), np.inf)
    return (T > 0).all(0) & (T.max(0) > 5 * lo)


def inputs(kind: str, d: dict[str, np.ndarray], cols: Sequence[int],
           logs: np.ndarray | None = None) -> np.ndarray:
    """The network's inputs: ``observed`` (``cols`` of the observation) or ``truth`` (and the
    logarithm of its columns ``logs``, :func:`log_columns` of the training draws)."""
    if kind == "observed":
        return d["X"][:, list(cols)]
    T = d["T"]
    return np.column_stack([T, np.log(np.maximum(T[:, logs], 1e-300))])


def epochs_for(n: int, epochs: int, batch: int = 256) -> int:
    """Passes over ``n`` draws that make as many minibatch steps as ``epochs`` passes over
    12,288 (and at least ``epochs``)."""
    return max(epochs, math.ceil(epochs * math.ceil(12288 / batch) / math.ceil(n / batch)))


def fit(X: np.ndarray, Y: np.ndarray, seed: int, hidden: Sequence[int] = HIDDEN,
        epochs: int = EPOCHS):
    """An MLP from standardised ``X`` to ``Y`` (mean squared error, AdamW, cosine learning
    rate), trained on one thread (the same numbers on any machine's thread count); returns its
    prediction function."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit(torch, X, Y, seed, hidden, epochs)
    finally:
        torch.set_num_threads(threads)


def _fit(torch, X: np.ndarray, Y: np.ndarray, seed: int, hidden: Sequence[int], epochs: int):
    torch.manual_seed(seed)
    mu, sd = X.mean(0), X.std(0) + 1e-6
    layers: list[Any] = []
    n = X.shape[1]
    for h in hidden:
        layers += [torch.nn.Linear(n, h), torch.nn.SiLU()]
        n = h
    net = torch.nn.Sequential(*layers, torch.nn.Linear(n, Y.shape[1]))
    opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-5)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    x = torch.tensor((X - mu) / sd, dtype=torch.float32)
    y = torch.tensor(Y, dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        perm = torch.randperm(len(x), generator=gen)
        for i in range(0, len(x), 256):
            j = perm[i:i + 256]
            loss = torch.nn.functional.mse_loss(net(x[j]), y[j])
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    net.eval()

    def predict(Z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return net(torch.tensor((Z - mu) / sd, dtype=torch.float32)).numpy()
    return predict


def pooled_fraction(R: np.ndarray, RC: np.ndarray, k: np.ndarray, best: np.ndarray) -> float:
    """``(mean return of cut k - mean never) / (mean best - mean never)``."""
    r = R[np.arange(len(k)), k]
    return float((r.mean() - RC.mean()) / (best.mean() - RC.mean()))


def early_share(R: np.ndarray, k: np.ndarray, best: np.ndarray) -> float:
    """The share of the loss against ``best`` that comes from cuts before the grid's best."""
    loss = best - R[np.arange(len(k)), k]
    early = k < R.argmax(1)
    return float(loss[early].sum() / max(loss.sum(), 1e-12))


def figures(R, RC, k, best) -> dict[str, Any]:
    r = R[np.arange(len(k)), k]
    return {"oracle_fraction": pooled_fraction(R, RC, k, best),
            "stall_like": int((r < RC - 1.0).sum()), "episodes": int(len(k))}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--draws", type=int, default=12288, help="training family draws")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1536, 3072, 6144, 12288],
                    help="nested training sets (the first N draws)")
    ap.add_argument("--seed", type=int, default=300_000, help="seed of the training draws")
    ap.add_argument("--val", type=int, default=1536, help="validation draws")
    ap.add_argument("--val-seed", type=int, default=310_000, help="seed of the validation draws")
    ap.add_argument("--held-out", type=int, default=1536, help="held-out draws")
    ap.add_argument("--held-out-seed", type=int, default=4_000_000,
                    help="seed of the held-out draws (bench_mpc.py's first held-out set)")
    ap.add_argument("--fit-seeds", type=int, default=2, help="network seeds per size and input")
    ap.add_argument("--epochs", type=int, default=EPOCHS, help="passes over 12,288 draws "
                    "(a smaller set gets as many minibatch steps)")
    ap.add_argument("--transfer-episodes", type=int, default=2,
                    help="episodes per cell of the transfer suite (0: skip it)")
    add_parallel_arguments(ap, "scoring the draws")
    ap.add_argument("--out", default="bench/return-curve", help="folder for the results")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if min(args.draws, args.val, args.held_out, args.fit_seeds, args.epochs, args.workers) < 1 \
            or args.transfer_episodes < 0:
        ap.error("--draws, --val, --held-out, --fit-seeds, --epochs and --workers must be >= 1, "
                 "--transfer-episodes >= 0")
    if min(args.sizes) < 2 or max(args.sizes) > args.draws:
        ap.error(f"--sizes must lie in [2, --draws = {args.draws}]")
    return run(args)


def run(args) -> dict:
    from agents.evaluation.suites import EVAL_SEED, family_draws, suite_episodes
    from pneugym.envs.cutoff import CutOffVectorEnv
    from pneugym.provenance import provenance

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    cols = static_columns(CutOffVectorEnv(num_envs=1, **env_config()).observation_layout())
    sets = {"train": (args.seed, args.draws), "validation": (args.val_seed, args.val),
            "held-out": (args.held_out_seed, args.held_out)}
    data = {name: cached(out, name, family_draws(seed, n), seed, args.workers, progress,
                         args.ray_address) for name, (seed, n) in sets.items()}
    eps = suite_episodes("transfer", args.transfer_episodes, EVAL_SEED)
    suite = transfer_scores(eps, args, EVAL_SEED, out) if eps else None
    curve = []
    full_nets = {}  # the observed networks on every training draw, for the transfer suite
    logs = log_columns(data["train"]["T"])
    for kind in ("observed", "truth"):
        for n in sorted(set(args.sizes)):
            sub = {k: v[:n] for k, v in data["train"].items()}
            epochs = epochs_for(n, args.epochs)
            for s in range(args.fit_seeds):
                net = fit(inputs(kind, sub, cols, logs), fraction_targets(sub["R"], sub["RC"]),
                          seed=s, epochs=epochs)
                if kind == "observed" and n == args.draws:
                    full_nets[s] = net
                row = {"input": kind, "draws": n, "fit_seed": s}
                for name in ("validation", "held-out"):
                    d = data[name]
                    k = net(inputs(kind, d, cols, logs)).argmax(1)
                    best = np.maximum(d["R"].max(1), d["RC"])
                    row[name] = pooled_fraction(d["R"], d["RC"], k, best)
                    row[f"{name} early share"] = early_share(d["R"], k, best)
                curve.append(row)
                print(f"{kind:8s} {n:6d} draws, seed {s}: validation "
                      f"{row['validation']:.3f}, held-out {row['held-out']:.3f}", flush=True)
    res: dict[str, Any] = {"learning_curve": curve}
    if suite is not None:
        res["transfer"] = transfer(data["train"], cols, args, *suite, nets=full_nets)
    for name, d in data.items():
        best = np.maximum(d["R"].max(1), d["RC"])
        res.setdefault("grid_best_never", {})[name] = {
            "draws": int(len(d["RC"])), "mean_best": float(best.mean()),
            "mean_never": float(d["RC"].mean())}
    res.update(config=vars(args), grid=list(GRID), provenance=provenance(),
               wall_s=time.perf_counter() - t0)
    (out / "return_curve.json").write_text(json.dumps(res, indent=1, default=json_default))
    with open(out / "return_curve.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(curve[0]))
        w.writeheader()
        w.writerows(curve)
    plot(curve, res.get("transfer"), out / "return_curve.png")
    print(f"wrote {out}/return_curve.json, .csv, .png ({res['wall_s']:.0f} s)")
    return res


def transfer_scores(eps: Sequence[tuple], args, seed: int, out: Path
                    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The transfer suite's episodes ``eps`` scored (:func:`score_draws`), each one's rig, and
    its best return: the oracle's search (``OraclePolicy.plan_many``) or the grid's best."""
    from agents.oracle import OraclePolicy
    from pneugym.envs.cutoff import CutOffVectorEnv

    labels = np.array([label.split("/")[0] for label, _ in eps])
    conds = [c for _, c in eps]
    d = cached(out, "transfer", conds, seed, args.workers, not args.no_progress,
               args.ray_address)
    env = CutOffVectorEnv(num_envs=1, **env_config())
    oracle = OraclePolicy(env.observation_layout(), env_config=env.config, seed=seed)
    # (the oracle searches each episode without its sensor noise, as score_chunk scores it)
    best = np.maximum(np.array([r for _, r in oracle.plan_many(conds)]), d["R"].max(1))
    return d, labels, best


def transfer(train: dict[str, np.ndarray], cols: Sequence[int], args, d: dict[str, np.ndarray],
             labels: np.ndarray, best: np.ndarray, nets: dict | None = None) -> dict[str, Any]:
    """The observed network on all training draws (``nets`` by seed where the learning curve
    trained it already), on the transfer suite's scored episodes (:func:`transfer_scores`):
    pooled oracle fraction per network seed, per rig of the first seed, and the grid's own best
    (how much the grid leaves)."""
    res: dict[str, Any] = {"episodes": len(labels),
                           "grid_best": figures(d["R"], d["RC"], d["R"].argmax(1), best)}
    epochs = epochs_for(len(train["RC"]), args.epochs)
    for s in range(args.fit_seeds):
        net = (nets or {}).get(s) or fit(inputs("observed", train, cols),
                                         fraction_targets(train["R"], train["RC"]), seed=s,
                                         epochs=epochs)
        k = net(inputs("observed", d, cols)).argmax(1)
        res.setdefault("observed", []).append(figures(d["R"], d["RC"], k, best))
        if s == 0:
            res["per_rig"] = {rig: pooled_fraction(d["R"][labels == rig], d["RC"][labels == rig],
                                                   k[labels == rig], best[labels == rig])
                              for rig in dict.fromkeys(labels)}
        print(f"transfer suite, observed, seed {s}: {res['observed'][-1]['oracle_fraction']:.3f}"
              f" ({res['observed'][-1]['stall_like']} of {len(labels)} episodes lose more than "
              f"the conventional stroke's return by 1)", flush=True)
    return res


def plot(curve: list[dict[str, Any]], tr: dict[str, Any] | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for kind, color in (("observed", "C0"), ("truth", "C3")):
        for name, style in (("validation", "o-"), ("held-out", "s--")):
            rows = [r for r in curve if r["input"] == kind]
            ns = sorted({r["draws"] for r in rows})
            ys = [np.mean([r[name] for r in rows if r["draws"] == n]) for n in ns]
            ax.plot(ns, ys, style, color=color, label=f"{kind}, {name} draws")
    if tr:
        y = np.mean([f["oracle_fraction"] for f in tr["observed"]])
        ax.axhline(y, color="C0", lw=0.8, ls=":", label="observed, transfer suite")
    ax.axhline(0.9, color="k", lw=0.8, label="issue 12's goal (transfer suite)")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("training draws of the rig family")
    ax.set_ylabel("oracle fraction (pooled)")
    ax.set_title("A return curve learned from the oracle's search")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
