"""pneugym: learn when to cut off the air supply of a pneumatic cylinder.

The plant is a numba-jitted simulation of the rig of the 2006 thesis "Energy Saving for Pneumatic
Actuation using Dynamic Model Prediction"; see ``README.md``.
"""
from .params import (
    CylinderParams, EffectParams, FrictionParams, GasParams, LineParams, RigParams, SolverParams,
    ValveParams, thesis_rig,
)
from .plant import Plant, PlantBatch, SimulationError, Trajectory
from .envs import register as _register_envs

_register_envs()

__version__ = "0.1.0"

__all__ = [
    "CylinderParams", "EffectParams", "FrictionParams", "GasParams", "LineParams", "RigParams",
    "SolverParams", "ValveParams", "thesis_rig", "Plant", "PlantBatch", "SimulationError",
    "Trajectory", "__version__",
]
