"""Whole extension strokes under the thesis's three actuation schemes (thesis ch. 5-6):
conventional (never cut), end-stroke cut-off and a cut-off commanded at a given time, plus the
search for the cut-off time that gives a wanted stroke-time increase.

Every figure comes from :class:`pneugym.plant.Plant`; nothing here re-implements physics.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from .params import RigParams
from .physics.energy import saving_ratio
from .plant import Plant, Trajectory, check_duration

#: A stroke longer than this [s] counts as stalled.
T_MAX_S = 6.0


@dataclass
class StrokeResult:
    """One extension stroke. Times are from the extend command [s]; energies [J]."""

    scheme: str
    cutoff_command_s: float | None
    stroke_time_s: float | None  # arrival at the end of stroke; None if stalled
    stalled: bool
    stick_events: int
    energy_wasted_j: float
    energy_conventional_j: float
    air_mass_kg: float
    breakaway_time_s: float | None
    p_drive_breakaway_pa: float | None
    trajectory: Trajectory | None = field(default=None, repr=False)

    @property
    def saving_ratio(self) -> float:
        """Thesis eq. 5.10 (fraction)."""
        return saving_ratio(self.energy_conventional_j, self.energy_wasted_j)


def _breakaway(traj: Trajectory) -> tuple[float | None, float | None]:
    moving = np.flatnonzero(traj["x"] > 1e-6)
    if moving.size == 0:
        return None, None
    i = max(int(moving[0]) - 1, 0)
    return float(traj["t"][i]), float(traj["p_drive"][i])


def simulate_stroke(params: RigParams, cutoff_s: float | str | None = None,
                    record_dt: float = 1e-3, t_max: float = T_MAX_S,
                    plant: Plant | None = None) -> StrokeResult:
    """Simulate one extension.

    ``cutoff_s``: ``None`` conventional; ``"endstroke"`` cut when the piston reaches the end;
    a number: cut-off command at that time [s]. The wasted energy is taken when the return
    stroke would begin: the filled driving side if never cut, else the trapped air once the
    valve has closed and the piston has arrived (or stalled).
    """
    if not (cutoff_s is None or cutoff_s == "endstroke"):
        if isinstance(cutoff_s, str):
            raise ValueError(f"cutoff_s = {cutoff_s!r} is invalid: must be None, 'endstroke' or a "
                             f"time [s]")
        cutoff_s = check_duration(cutoff_s, "cutoff_s", allow_zero=True)
    t_max = check_duration(t_max, "t_max")
    pl = plant if plant is not None and plant.params is params else Plant(params)
    pl.reset()
    if cutoff_s is None:
        scheme, sched = "conventional", [(0.0, 1)]
    elif cutoff_s == "endstroke":
        scheme, sched = "endstroke", [(0.0, 1)]
    else:
        scheme, sched = "cutoff", [(0.0, 1), (float(cutoff_s), 0)]
    traj = _run_until_settled(pl, sched, record_dt, t_max, cut_on_arrival=scheme == "endstroke")
    t_arr = pl.arrival_time_s
    cut_cmd = None
    if cutoff_s == "endstroke":
        cut_cmd = t_arr
    elif cutoff_s is not None:
        cut_cmd = float(cutoff_s)
    tb, pb = _breakaway(traj)
    return StrokeResult(
        scheme=scheme, cutoff_command_s=cut_cmd, stroke_time_s=t_arr, stalled=t_arr is None,
        stick_events=pl.stick_events, energy_wasted_j=pl.energy_wasted_j,
        energy_conventional_j=pl.conventional_energy_j, air_mass_kg=pl.air_mass_in_kg,
        breakaway_time_s=tb, p_drive_breakaway_pa=pb, trajectory=traj)


def _run_until_settled(pl: Plant, sched, record_dt, t_max, cut_on_arrival=False) -> Trajectory:
    """Run in chunks until the piston has arrived (or stalled) and, after a cut-off, the valve
    has closed."""
    chunks = []
    t = 0.0
    while t < t_max - 1e-12:
        t_next = min(t_max, t + 0.25)
        todo = [s for s in sched if t - 1e-12 <= s[0] < t_next - 1e-12]
        chunk = pl.run(t_next, todo, record_dt,
                       cut_on_arrival=cut_on_arrival and pl.arrival_time_s is None)
        chunks.append(chunk.data)
        t = pl.time_s
        if any(s[0] >= t - 1e-12 for s in sched):
            continue  # commands still to come
        if not pl.supply_cut:
            if pl.arrival_time_s is not None:
                break
        elif pl.valve_closed and (pl.arrival_time_s is not None or (pl.stuck and _stalled(pl))):
            break
    data = np.concatenate(chunks)
    return Trajectory(data[np.concatenate([[True], np.diff(data[:, 0]) > 1e-12])])


def _stalled(pl: Plant) -> bool:
    """Stuck with the supply cut and the valve closed: with no leak into the driving side the
    net force can only fall, so the piston will not move again. Checked 0.1 s later."""
    snap = pl.snapshot()
    pl.advance(0.1)
    still = pl.stuck and pl.arrival_time_s is None
    pl.restore(snap)
    return still


def cutoff_for_time_increase(params: RigParams, increase: float,
                             conventional: StrokeResult | None = None,
                             tol_s: float = 2e-4) -> StrokeResult:
    """The cut-off whose stroke time is ``(1 + increase)`` x the conventional one (bisection
    on the command time; later cut-offs give shorter strokes)."""
    if isinstance(increase, bool) or not (isinstance(increase, numbers.Real)
                                           and 0.0 <= increase <= 10.0):
        raise ValueError(f"increase = {increase!r} is invalid: must be a stroke-time increase "
                         f"in [0, 10] (a fraction: 0.1 = +10 %)")
    conv = conventional or simulate_stroke(params)
    if conv.stroke_time_s is None:
        raise ValueError("the conventional stroke does not complete; no cut-off can be placed")
    target = conv.stroke_time_s * (1.0 + increase)
    pl = Plant(params)
    lo, hi = 0.0, conv.stroke_time_s  # lo: too early (slow or stalled), hi: late enough

    def stroke(tc: float) -> float:
        r = simulate_stroke(params, tc, record_dt=0.01, plant=pl)
        return math.inf if r.stroke_time_s is None else r.stroke_time_s

    if stroke(hi) > target:
        raise ValueError("even a cut-off at the conventional arrival is slower than the target")
    while hi - lo > tol_s:
        mid = 0.5 * (lo + hi)
        if stroke(mid) > target:
            lo = mid
        else:
            hi = mid
    return simulate_stroke(params, hi, plant=pl)
