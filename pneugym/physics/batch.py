"""Many plants advanced together: one control period of every plant of a batch in one
parallel call (numba ``prange`` over the plants). The plants share the line grid
(the same state length); each has its own parameters, state and work array. The physics is that
of :func:`pneugym.physics.advance.command_advance`, so a plant of a batch follows the same
trajectory, bit for bit, as a single plant given the same commands.
"""
from numba import njit, prange

from .advance import command_advance


@njit(cache=True, error_model="numpy", parallel=True)
def advance_batch(Y, Ps, Ds, commands, duration, status, W):
    """Give each plant ``i`` the command ``commands[i]`` and advance it by ``duration`` [s].

    ``Y`` (B, ny), ``Ps`` (B, np), ``Ds`` (B, nd) as in :mod:`layout`, ``W`` (B, work_size) work
    arrays; plants with a non-zero ``status[i]`` are skipped. Plants run in parallel (numba
    ``prange``)."""
    nb = Y.shape[0]
    for i in prange(nb):
        if status[i] == 0:
            status[i] = command_advance(Y[i], Ps[i], Ds[i], W[i], commands[i], duration, False)
