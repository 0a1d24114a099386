"""Train learned cut-off policies (PPO, DQN, ESAC) from a checkout: ``python train.py --help``.
The same command as ``pneugym train``; the code is the package :mod:`agents.training`."""
from agents.training.cli import main

if __name__ == "__main__":
    main()
