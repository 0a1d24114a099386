"""The ``pneugym`` command: one entry point for every job, each a subcommand.

    pneugym evaluate                          # the main job: benchmark every policy
    pneugym train --algo esac --out runs/esac
    pneugym discrepancy runs/ --out report/
    pneugym validate --out validation/
    pneugym replay measured/ --policy gaslaw --rig rig.yaml
    pneugym <command> --help                  # options and examples of one command

This module is the top of the dependency graph: it imports the command it runs, and only then
(``import pneugym`` stays light and nothing below imports this module).
"""
from __future__ import annotations

import importlib
import sys
from typing import Sequence

#: command -> (module with ``main(argv)``, one-line summary)
COMMANDS: dict[str, tuple[str, str]] = {
    "evaluate": ("agents.evaluation.cli", "benchmark policies on the nominal, robustness and transfer suites"),
    "train": ("agents.training.cli", "train a learned policy (PPO, DQN or ESAC) into a run folder"),
    "discrepancy": ("pneugym.discrepancy.__main__",
                    "find, name and fit the effect that separates measured runs from the model"),
    "validate": ("pneugym.validate", "the plant's validation report against the thesis's figures"),
    "commission": ("pneugym.commission",
                   "fit a model of one rig to two of its measured strokes, for the mpc-rig policy"),
    "calibrate": ("pneugym.calibrate", "fit the rig parameters the thesis does not give"),
    "gaslaw": ("agents.gaslaw", "calibrate the Gas-Law rule's K per supply pressure"),
    "rig": ("pneugym.rigfile", "check a rig file and show how it differs from the thesis rig"),
    "replay": ("pneugym.deploy.replay",
               "run a controller over measured runs: when it would cut, what that saves"),
    "export": ("pneugym.deploy.export", "export a neural policy to ONNX and a numpy runtime"),
    "operate": ("pneugym.operation.__main__",
                "run a rig's operating life (drift, every stroke in DuckDB, adaptation) and report"),
}


def usage() -> str:
    """The top-level help text."""
    from . import __version__

    width = max(map(len, COMMANDS))
    lines = [f"usage: pneugym <command> [options]      (pneugym {__version__})", "",
             "Learn when to cut off the air supply of a pneumatic cylinder.", "", "commands:"]
    lines += [f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items()]
    lines += ["", "pneugym <command> --help shows a command's options and examples."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``pneugym <command> [options]``; returns the exit status."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    if args[0] == "--version":
        from . import __version__

        print(f"pneugym {__version__}")
        return 0
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        from .params import did_you_mean

        print(f"pneugym: unknown command {name!r}{did_you_mean(name, COMMANDS)}\n\n{usage()}",
              file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    saved = sys.argv  # argparse's usage line and a run's recorded command name the subcommand
    sys.argv = [f"pneugym {name}", *rest]
    try:
        result = module.main(rest)
    finally:
        sys.argv = saved
    return result if isinstance(result, int) else 0


if __name__ == "__main__":
    sys.exit(main())
