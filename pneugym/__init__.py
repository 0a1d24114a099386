"""pneugym: learn when to cut off the air supply of a pneumatic cylinder.

The plant is a numba-jitted simulation of the rig of the 2006 thesis "Energy Saving for Pneumatic
Actuation using Dynamic Model Prediction"; see ``README.md``.
"""

# OpenMP's wait policy is left at its default (a waiting thread spins briefly, then sleeps): with
# OMP_WAIT_POLICY=PASSIVE, which pneugym used to set, two threads ran a 64-plant batch only 1.15x
# faster than one on a quiet 2-core machine (1.75x with the default); see docs/scale.md.

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
