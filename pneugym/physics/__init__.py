"""Jitted physics kernels (numba, ``cache=True``): the single source of truth for the equations.

- :mod:`.orifice`  orifice mass flow (thesis eqs. 4.1-4.3, ISO 6358)
- :mod:`.line`     1-D compressible supply line (staggered FD) and the lumped alternative
- :mod:`.cylinder` cushions, friction, chamber energy equation
- :mod:`.energy`   air potential energy (eq. 5.9) and flow exergy
- :mod:`.system`   the assembled plant: right-hand side, SSP-RK3 substep, events, drivers
- :mod:`.layout`   the packed array layouts
"""
