"""Episode bookkeeping of the cut-off task, jitted so that one environment step, or a batch of
them, is a single compiled call: apply the action, advance the plant one control period, decide
whether the episode ends, and pay the reward. No physics here: the plant kernels of
:mod:`pneugym.physics.system` do all of it.

Per-episode array ``e`` (float64, length ``NE``), indexed by the ``E_*`` constants:
"""
from numba import njit, prange

from ..physics.layout import (
    D_MODE, D_STICKS, D_T, D_T_ARRIVE, MODE_START, MODE_STUCK, P_FS, P_NCELLS, P_PA, P_PS,
    STATUS_OK, Y_SD, Y_SE, Y_X,
)
from ..physics.advance import command_advance
from ..physics.cylinder import chamber_pressures
from ..physics.energy import energy_wasted, max_drive_force
from ..physics.valve import valve_closed

E_CUT = 0        # 1 while the supply is cut (latched unless reversible)
E_REV = 1        # 1 = the agent may re-open the supply
E_T_CONV = 2     # conventional stroke time at these conditions [s]
E_E_CONV = 3     # conventional wasted energy at these conditions [J]
E_PHI = 4        # potential at the last step (= return so far for dense rewards)
E_T_LIMIT = 5    # time limit [s]
E_WINDOW = 6     # decision window after arrival without a cut-off [s]
E_W_TIME = 7     # weight of the stroke-time increase
E_W_STALL = 8    # penalty for a stroke not completed (stall or time-out)
E_W_STICK = 9    # penalty per stick-slip event
E_DONE = 10      # 0 running, 1 terminated, 2 truncated
E_STALLED = 11   # 1 if it ended stuck short of the stroke with the supply cut
E_COMPLETED = 12  # 1 if the piston reached the end of stroke
E_E_WASTED = 13  # wasted energy when the episode ended [J]
E_T_CUT = 14     # time of the first cut-off command [s] (-1 = never)
E_DENSE = 15     # 1 = dense (telescoping) reward, 0 = sparse (objective at the end)
E_PERIOD = 16    # control period [s]
E_OBJ = 17       # objective so far (the potential, updated every step)
NE = 18


@njit(cache=True)
def stick_slips(d):
    """Stick-slip events: mid-stroke sticks that slipped again (a piston stuck now, e.g. a stall,
    is not counted until it moves)."""
    n = d[D_STICKS]
    if d[D_MODE] == MODE_STUCK:
        n -= 1.0
    return n


@njit(cache=True)
def objective(y, P, d, e, done, completed):
    """The episode objective if the episode ended now (while running: the shaping potential).

    ``- E_wasted / E_conv - w_time * max(0, T / T_conv - 1) - w_stick * sticks
    - w_stall * (not completed at the end)``, with the sticks of :func:`stick_slips`; where ``T`` is the arrival time, the current time
    while the piston is on its way, or the time limit for a stroke that never completed."""
    t = d[D_T]
    if d[D_T_ARRIVE] >= 0.0:
        t = d[D_T_ARRIVE]
    elif done:
        t = e[E_T_LIMIT]
    j = -energy_wasted(y, P, d) / e[E_E_CONV]
    j -= e[E_W_TIME] * max(0.0, t / e[E_T_CONV] - 1.0)
    j -= e[E_W_STICK] * stick_slips(d)
    if done and not completed:
        j -= e[E_W_STALL]
    return j


@njit(cache=True)
def step_one(y, P, d, e, action, w):
    """One control period of one episode. Returns ``(reward, plant status)``; ``e[E_DONE]``
    tells whether (and how) it ended. A finished episode is left untouched (reward 0).
    ``w``: the plant's work array (:func:`pneugym.physics.advance.work_size`), so that a step
    allocates nothing."""
    if e[E_DONE] != 0.0:
        return 0.0, STATUS_OK
    t0 = d[D_T]
    cut = action == 1 if e[E_REV] > 0.0 else (e[E_CUT] > 0.0 or action == 1)
    if cut and e[E_T_CUT] < 0.0:
        e[E_T_CUT] = t0
    e[E_CUT] = 1.0 if cut else 0.0
    st = command_advance(y, P, d, w, 0.0 if cut else 1.0, e[E_PERIOD], False)
    if st != STATUS_OK:
        return 0.0, st

    t = d[D_T]
    arrived = d[D_T_ARRIVE] >= 0.0
    closed = valve_closed(d, P)
    done = 0.0
    if arrived:
        if cut and closed:
            done = 1.0
        elif not cut and t - d[D_T_ARRIVE] >= e[E_WINDOW] - 1e-9:
            done = 1.0
    elif cut and closed and e[E_REV] < 0.5 and (d[D_MODE] == MODE_STUCK or d[D_MODE] == MODE_START) \
            and max_drive_force(y, P) <= P[P_FS]:  # (a reversible cut may be undone: no stall)
        done = 1.0
        e[E_STALLED] = 1.0
    if done == 0.0 and t >= e[E_T_LIMIT] - 1e-9:
        done = 2.0
    return _settle(y, P, d, e, done), STATUS_OK


@njit(cache=True)
def _settle(y, P, d, e, done):
    """Update the objective, close the episode if ``done`` (1 terminated, 2 truncated) and
    return the step's reward."""
    arrived = d[D_T_ARRIVE] >= 0.0
    j = objective(y, P, d, e, done != 0.0, arrived)
    r = 0.0
    if e[E_DENSE] > 0.0:
        r = j - e[E_PHI]
    elif done != 0.0:
        r = j
    e[E_PHI] = j
    e[E_OBJ] = j
    if done != 0.0:
        e[E_DONE] = done
        e[E_COMPLETED] = 1.0 if arrived else 0.0
        e[E_E_WASTED] = energy_wasted(y, P, d)
    return r


@njit(cache=True)
def truncate(y, P, d, e):
    """End a running episode now as truncated (a step limit outside the plant's time limit);
    returns the extra reward that makes the return equal the final objective."""
    if e[E_DONE] != 0.0:
        return 0.0
    return _settle(y, P, d, e, 2.0)


@njit(cache=True)
def binary(actions):
    """True when every action is 0 (keep) or 1 (cut off): the vector step's check, one
    compiled loop instead of numpy reductions (each costs microseconds on a batch of 64)."""
    for a in actions:
        if a != 0 and a != 1:
            return False
    return True


# --- observation --------------------------------------------------------------------------------
NF = 7  # sensor features per sample (documented in pneugym.envs.cutoff.OBSERVATION)


@njit(cache=True)
def sense(h, x, x_prev, p_drive, p_exhaust, p_supply, pa, t, cut, period, scales):
    """The seven features of one sample into ``h`` (NF,): measured position ``x`` [m] (and the
    previous one, ``x_prev``, for the velocity over one ``period`` [s]), port pressures
    ``p_drive``, ``p_exhaust`` and the supply set-point ``p_supply`` [Pa absolute, ``pa``
    ambient], time ``t`` [s] since the extend command, ``cut`` (1 while the supply is cut),
    each ``(value - offset) / scale`` with ``scales`` of :func:`observe`. The environment and
    :class:`pneugym.deploy.Controller` both sense through this one function."""
    h[0] = x / scales[0]
    h[1] = (x - x_prev) / period / scales[1]
    h[2] = (p_drive - pa) / scales[2]
    h[3] = (p_exhaust - pa) / scales[2]
    h[4] = (p_supply - pa) / scales[2]
    h[5] = t / scales[3]
    h[6] = cut


@njit(cache=True)
def observe_row(i, Y, Ps, Ds, Es, noise, x_prev, scales, fresh, hist, extra, bound, obs):
    """:func:`observe` for episode ``i``."""
    k = hist.shape[1]
    b = 2 * int(Ps[i, P_NCELLS]) - 1
    pa = Ps[i, P_PA]
    x = Y[i, b + Y_X] + noise[i, 0]
    if fresh:
        x_prev[i] = x
    else:
        for s in range(k - 1):
            for f in range(NF):
                hist[i, s, f] = hist[i, s + 1, f]
    sense(hist[i, k - 1], x, x_prev[i], Y[i, b + Y_SD] + noise[i, 1],
          Y[i, b + Y_SE] + noise[i, 2], Ps[i, P_PS], pa, Ds[i, D_T], Es[i, E_CUT],
          Es[i, E_PERIOD], scales)
    h = hist[i, k - 1]
    x_prev[i] = x
    if fresh:
        for s in range(k - 1):
            for f in range(NF):
                hist[i, s, f] = h[f]
    c = 0
    for s in range(k):
        for f in range(NF):
            obs[i, c] = min(max(hist[i, s, f], -bound), bound)
            c += 1
    for f in range(extra.shape[1]):
        obs[i, c] = min(max(extra[i, f], -bound), bound)
        c += 1


@njit(cache=True)
def observe(Y, Ps, Ds, Es, rows, noise, x_prev, scales, fresh, hist, extra, bound, obs):
    """Sense episodes ``rows`` and write their observations (float32) into ``obs``.

    ``noise`` (B, 3): additive position [m] and port-pressure [Pa] noise, already drawn;
    ``x_prev`` (B,): the last measured position [m] (updated) for the velocity estimate;
    ``scales``: position [m], velocity [m/s], pressure [Pa] and time [s] scales;
    ``fresh``: a new episode (history filled with this sample, velocity 0);
    ``hist`` (B, k, NF): sample history (updated); ``extra`` (B, m): appended as is;
    every element is clipped to ``[-bound, bound]``."""
    for j in range(rows.shape[0]):
        observe_row(rows[j], Y, Ps, Ds, Es, noise, x_prev, scales, fresh, hist, extra, bound, obs)


@njit(cache=True)
def info_row(i, Y, Ps, Ds, Es, noise, b, out):
    """Episode ``i``'s row of the step info ``out`` (B, 8): time [s], position [m], driving and
    exhaust chamber pressures [Pa absolute]; what its sensors read (position [m], port pressures
    [Pa absolute], the step's ``noise`` added; ``b`` the layout's line offset); its ``E_CUT``."""
    pd, pe, vd, ve = chamber_pressures(Y[i], Ps[i], b)
    out[i, 0] = Ds[i, D_T]
    out[i, 1] = Y[i, b + Y_X]
    out[i, 2] = pd
    out[i, 3] = pe
    out[i, 4] = Y[i, b + Y_X] + noise[i, 0]
    out[i, 5] = Y[i, b + Y_SD] + noise[i, 1]
    out[i, 6] = Y[i, b + Y_SE] + noise[i, 2]
    out[i, 7] = Es[i, E_CUT]


@njit(cache=True)
def info_rows(Y, Ps, Ds, Es, noise, b, out):
    """:func:`info_row` for every episode."""
    for i in range(Y.shape[0]):
        info_row(i, Y, Ps, Ds, Es, noise, b, out)


@njit(cache=True, parallel=True)
def step_observe(Y, Ps, Ds, Es, actions, rewards, status, W, noise, x_prev, scales, hist, extra,
                 bound, obs, b, info, Yb, Db, Eb, steps, max_steps, idle, terminated, truncated):
    """One vector step in one compiled call, each episode's whole step on one thread (numba
    ``prange``): keep its state in ``Yb``, ``Db``, ``Eb`` (for a retry), :func:`step_one`, count
    the step in ``steps``; then, if the step stayed physical (``status`` 0), :func:`observe`
    it (not fresh), end it as truncated at ``max_steps`` steps (0: no limit; the reward gains
    :func:`truncate`'s) and write its :func:`info_row`; an ``idle`` row (ended, not reset) is
    neither observed nor read out again. Fills ``terminated`` and ``truncated``
    from ``E_DONE`` and returns how many episodes not ``idle`` ended (a row that failed is the
    caller's to redo, and its flags with it)."""
    n_ended = 0
    for i in prange(Y.shape[0]):
        Yb[i, :] = Y[i, :]
        Db[i, :] = Ds[i, :]
        Eb[i, :] = Es[i, :]
        rewards[i], status[i] = step_one(Y[i], Ps[i], Ds[i], Es[i], actions[i], W[i])
        steps[i] += 1
        if status[i] == STATUS_OK and not idle[i]:  # (an idle row keeps its last observation)
            observe_row(i, Y, Ps, Ds, Es, noise, x_prev, scales, False, hist, extra, bound, obs)
            if max_steps > 0 and steps[i] >= max_steps and Es[i, E_DONE] == 0.0:
                rewards[i] += truncate(Y[i], Ps[i], Ds[i], Es[i])
            info_row(i, Y, Ps, Ds, Es, noise, b, info)
        done = Es[i, E_DONE]
        terminated[i] = done == 1.0
        truncated[i] = done == 2.0
        if (done == 1.0 or done == 2.0) and not idle[i]:
            n_ended += 1
    return n_ended
