"""Jitted physics kernels (numba, ``cache=True``): the single source of truth for the equations.

Components (each a short module with its equations and units in its docstrings):

- :mod:`.orifice`   orifice mass flow (thesis eqs. 4.1-4.3, ISO 6358), its implicit stage solve
- :mod:`.line`      1-D compressible supply line (staggered FD) and the lumped alternative
- :mod:`.cylinder`  chamber pressures and volumes, cushions, friction, chamber energy equation
- :mod:`.valve`     supply pressure, main valve (delay, spool ramp, command queue), supply flow
- :mod:`.energy`    air potential energy (eq. 5.9), flow exergy, wasted energy, total air mass

The assembled plant:

- :mod:`.rhs`       the right-hand side of the whole plant; the implicit part of an IMEX stage
- :mod:`.chain`     the lumped line's orifice chain solved implicitly (Newton, tridiagonal)
- :mod:`.stepping`  one IMEX Runge-Kutta substep, then the events
- :mod:`.events`    piston events (Karnopp stick/slip, end stops) and the sensor lag
- :mod:`.advance`   advancing one plant: substep loop, recording, command + advance
- :mod:`.batch`     advancing many plants in one parallel call
- :mod:`.system`    all of the plant's kernels under one name (``system as K``)
- :mod:`.layout`    the packed array layouts
- :mod:`.testbed`   the line alone between simple boundaries (analytic checks)
"""
