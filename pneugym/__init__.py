"""pneugym: learn when to cut off the air supply of a pneumatic cylinder.

The plant is a numba-jitted simulation of the rig of the 2006 thesis "Energy Saving for Pneumatic
Actuation using Dynamic Model Prediction"; see ``README.md``.
"""
import os

# numba's OpenMP threads spin while idle by default; between batched steps that steals the cores
# the caller (a policy, SB3) needs: measured 10x slower vector steps on a loaded 2-core machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ._jitcache import configure as _configure_jit_cache  # noqa: E402

_configure_jit_cache()  # compiled kernels keyed on all jitted sources together

from .params import (  # noqa: E402
    CylinderParams, EffectParams, FrictionParams, GasParams, LineParams, RigParams, SolverParams,
    ValveParams, thesis_rig,
)
from .plant import Plant, PlantBatch, SimulationError, Trajectory  # noqa: E402
from .envs import register as _register_envs  # noqa: E402

_register_envs()

__version__ = "0.1.0"

__all__ = [
    "CylinderParams", "EffectParams", "FrictionParams", "GasParams", "LineParams", "RigParams",
    "SolverParams", "ValveParams", "thesis_rig", "Plant", "PlantBatch", "SimulationError",
    "Trajectory", "__version__",
]
