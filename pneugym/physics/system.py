"""The assembled plant's kernels under one name, ``from pneugym.physics import system as K``.

Each kernel lives in the module of its job; this module only re-exports them, so that
``K.<name>`` works for the plant, the environments, the tests and the benchmarks:

- :mod:`.valve`     supply pressure, spool ramp and opening, command queue, supply flow
- :mod:`.cylinder`  chamber pressures and volumes (and cushions, friction, energy equation)
- :mod:`.rhs`       the right-hand side: every equation assembled; the implicit part of a stage
- :mod:`.chain`     the lumped line's implicit orifice chain (Newton, tridiagonal)
- :mod:`.stepping`  one IMEX substep (tableau ``IMEX_A*``), then the events
- :mod:`.events`    piston events (Karnopp stick/slip, end stops) and the sensor lag
- :mod:`.advance`   substep loop with recording, control-level ``command_advance``
- :mod:`.batch`     many plants in one parallel call
- :mod:`.energy`    wasted energy, driving-side energy and force, total air mass

Array layouts: :mod:`pneugym.physics.layout`. Everything is SI with absolute pressures.
"""
from .advance import advance, advance_ws, command_advance, record_row, work_size
from .batch import advance_batch
from .chain import CHAIN_MAX_IT, CHAIN_TOL, implicit_chain, signed_flow_deriv
from .cylinder import chamber_pressures, piston_force
from .energy import driving_side_energy, energy_wasted, filled_energy, max_drive_force, total_air_mass
from .events import V_STICK, piston_events
from .rhs import rhs, rhs_valve, stage_rhs
from .stepping import IMEX_A21, IMEX_A22, IMEX_A31, IMEX_A32, IMEX_A33, substep
from .valve import (
    command, pop_due_commands, spool_position, supply_flow, supply_pressure, valve_closed,
    valve_opening,
)

# the names these kernels had when they were private to this module
_ramp = spool_position
_pop_due_commands = pop_due_commands
_piston_events = piston_events
_flow_deriv = signed_flow_deriv

__all__ = [
    "CHAIN_MAX_IT", "CHAIN_TOL", "IMEX_A21", "IMEX_A22", "IMEX_A31", "IMEX_A32", "IMEX_A33",
    "V_STICK", "advance", "advance_batch", "advance_ws", "chamber_pressures", "command",
    "command_advance", "driving_side_energy", "energy_wasted", "filled_energy", "implicit_chain",
    "max_drive_force", "piston_events", "piston_force", "pop_due_commands", "record_row", "rhs", "rhs_valve",
    "signed_flow_deriv", "spool_position", "stage_rhs", "substep", "supply_flow",
    "supply_pressure", "total_air_mass", "valve_closed", "valve_opening", "work_size",
]
