"""Benchmark cut-off policies from a checkout: ``python evaluate.py --help``. The same command as
``pneugym evaluate``; the code is the package :mod:`agents.evaluation`."""
from agents.evaluation.cli import main

if __name__ == "__main__":
    main()
