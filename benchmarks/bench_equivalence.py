"""The deployable controller against its policy inside the environment, on whole suites: every
episode is run in the environment, then a :class:`pneugym.deploy.Controller` is fed what the
environment's sensors read (noise included) and its observations (bit for bit) and valve commands
are compared with the environment's (:func:`pneugym.deploy.check.check_equivalence`).

Writes ``equivalence.json`` (per policy and suite: episodes, decisions, observations and commands
that differ, the first difference, wall time; configuration and versions) and
``equivalence.png`` (decisions compared, differences marked). Saved models join as
``NAME=PATH``.

    python benchmarks/bench_equivalence.py        # baselines, robustness + transfer, ~10 min
    python benchmarks/bench_equivalence.py --policies gaslaw esac=runs/esac ppo=runs/ppo \\
        esac_family=runs/esac-family --episodes 2
"""
from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

from common import ROOT  # noqa: F401  (the checkout on sys.path)

DEFAULT_POLICIES = ("conventional", "endstroke", "gaslaw")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--policies", nargs="+", default=list(DEFAULT_POLICIES),
                    help="baselines by name, saved models as NAME=PATH")
    ap.add_argument("--suites", nargs="+", default=["robustness", "transfer"])
    ap.add_argument("--episodes", type=int, default=12, help="episodes per suite cell")
    ap.add_argument("--seed", type=int, default=5, help="seed of the episodes and the noise")
    ap.add_argument("--out", default="bench/equivalence", help="folder for the results")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error("--episodes must be >= 1")
    from agents.evaluation.specs import make_named_policy
    from agents.evaluation.suites import suite_episodes
    from pneugym.deploy.check import check_equivalence
    from pneugym.provenance import provenance

    rows = []
    for suite in args.suites:
        conds = [c for _, c in suite_episodes(suite, args.episodes, args.seed)]
        for spec in args.policies:
            name = spec.split("=", 1)[0]
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # (models run on rigs they were not trained on)
                res = check_equivalence(lambda env: make_named_policy(spec, env)[1], conds,
                                        seed=args.seed)
            res.update(policy=name, suite=suite, wall_s=time.perf_counter() - t0)
            rows.append(res)
            print(f"{suite:11s} {name:14s} {res['episodes']:5d} episodes "
                  f"{res['decisions']:8d} decisions: {res['observations_differing']} "
                  f"observations, {res['commands_differing']} commands differ "
                  f"({res['wall_s']:.0f} s)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"config": vars(args), "results": rows, "provenance": provenance()}
    (out / "equivalence.json").write_text(json.dumps(result, indent=2))
    plot(rows, out / "equivalence.png")
    print(f"wrote {out}/equivalence.json, equivalence.png")
    return result


def plot(rows: list[dict], path: Path) -> None:
    """Decisions compared per policy and suite; bars with any difference in red, annotated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 3.8))
    labels = [f"{r['policy']}\n{r['suite']}" for r in rows]
    bad = [r["observations_differing"] + r["commands_differing"] for r in rows]
    ax.bar(range(len(rows)), [r["decisions"] for r in rows],
           color=["tab:red" if b else "tab:green" for b in bad])
    for k, (r, b) in enumerate(zip(rows, bad)):
        ax.annotate(f"{b} differ", (k, r["decisions"]), ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(rows)), labels, fontsize=7)
    ax.set_ylabel("decisions compared")
    ax.set_title("Controller vs the policy in the environment (bit for bit)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
