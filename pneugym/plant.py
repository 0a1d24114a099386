"""The plant: packs :class:`~pneugym.params.RigParams` into arrays once, picks a stable substep,
owns the state and advances it through the jitted kernels of :mod:`pneugym.physics`.

>>> from pneugym import Plant, thesis_rig
>>> plant = Plant(thesis_rig(2.5))
>>> traj = plant.run(t_end=2.0, schedule=[(0.0, 1)])      # conventional extension
>>> round(plant.arrival_time_s, 2) > 0
True
"""
from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence, TypeVar

import numpy as np

from .params import RigParams
from .physics import layout as L
from .physics import system as K
from .physics.energy import flow_exergy, saving_ratio
from .physics.orifice import NOC, OC_CM_STAR, linear_conductance, orifice_constants

RK3_REAL_LIMIT = 2.51  # SSP-RK3 stability bound on the negative real axis (h |λ|)
RK3_IMAG_LIMIT = math.sqrt(3.0)  # ... and on the imaginary axis (h |ω|)
#: largest h lambda of the lumped line's implicit orifice chain (see stability_limits)
CHAIN_H_LAMBDA = 40.0
#: factor on the FD line's acoustic bound with two cells (see stability_limits)
TWO_CELL_CFL_FACTOR = 0.5
#: ... with the valve and port conductances in the bound too (see stability_limits)
CHAIN_H_LAMBDA_ENDS = 60.0
#: Longest automatic substep [s] with the implicit FD line (``SolverParams(line_scheme=
#: "implicit")``), whose own stability sets none: on the thesis rig at 1.5 and 2.5 bar, stroke
#: time and wasted energies (conventional, cut on arrival, mid- and late cut-off) lie within
#: 0.28 % of the converged reference at 5 ms, 0.5 % at 6.5 ms, and the state goes non-physical
#: from 6.5-7 ms (``benchmarks/bench_accuracy.py``; the scan that chose it, before the piston's
#: events were taken in parts: with them 0.16 % at 5 ms). Off the thesis rig: ``benchmarks/
#: bench_line_scheme.py``, docs/plant.md
IMPLICIT_LINE_MAX_DT_S = 5e-3

#: The implicit FD line takes over only where its substep is at least this many times the
#: explicit line's: on the thesis rig an implicit substep with its piston events costs about
#: 3.4 explicit ones (7.7x fewer substeps for a 2.2-2.3x faster plant); where another process
#: (an exhaust orifice, the piston's air spring) keeps the implicit substep short, the explicit
#: line is as fast or faster (a rig whose exhaust orifice held it to 1.9 ms against the explicit
#: line's 1.24 ms ran 0.5x as fast)
IMPLICIT_LINE_MIN_GAIN = 4.0

#: the explicit substep's limits that the implicit FD line removes (:func:`stability_limits`)
LINE_LIMITS = ("line CFL", "line friction")


#: Longest simulated span [s] of one call (a stroke lasts seconds; longer is a unit slip).
MAX_SPAN_S = 3600.0
#: Most samples one :meth:`Plant.run` records (8 bytes x channels each).
MAX_RECORD_ROWS = 20_000_000
#: Times a call retries with half the automatic substep after a non-physical state.
MAX_STEP_RETRIES = 4
_T = TypeVar("_T")


class SimulationError(RuntimeError):
    """The state went non-physical; the message names the time and the state."""


class RigWarning(UserWarning):
    """A rig that can be simulated but is almost surely not what was meant."""


def _real(v: object) -> bool:
    """A finite real number (not a bool, string or array)."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)


def check_command(value: object, what: str = "command") -> float:
    """A valve command as the kernels take it: exactly 0 (cut off) or 1 (supply connected)."""
    if type(value) in (int, float) and value in (0, 1):  # the common case, without ABC checks
        return float(value)  # type: ignore[arg-type]
    ok = isinstance(value, (numbers.Real, np.bool_)) and not (
        isinstance(value, float) and math.isnan(value))
    if not ok or float(value) not in (0.0, 1.0):  # type: ignore[arg-type]
        raise ValueError(f"{what} = {value!r} is invalid: must be 0 (cut off) or 1 (supply "
                         f"connected)")
    return float(value)  # type: ignore[arg-type]


def check_duration(value: object, what: str = "duration_s", allow_zero: bool = False) -> float:
    """A simulated span [s]: finite, > 0 (or >= 0) and at most :data:`MAX_SPAN_S`."""
    if type(value) is float and 0.0 < value <= MAX_SPAN_S:  # the common case (NaN fails it)
        return value
    if not _real(value) or not (value >= 0 if allow_zero else value > 0):  # type: ignore[operator]
        raise ValueError(f"{what} = {value!r} is invalid: must be a finite number "
                         f"{'>= 0' if allow_zero else '> 0'} [s]")
    if value > MAX_SPAN_S:  # type: ignore[operator]
        raise ValueError(f"{what} = {value!r} s is more than {MAX_SPAN_S:g} s in one call (ms "
                         f"given as s?); advance in shorter calls")
    return float(value)  # type: ignore[arg-type]


def check_schedule(schedule: Iterable[tuple[float, int]]) -> list[tuple[float, float]]:
    """Valve commands ``(time_s, value)``: times finite and >= 0, values 0 or 1; sorted by time
    (commands at the same time keep their order: the last one holds)."""
    if isinstance(schedule, (str, bytes)) or not isinstance(schedule, Iterable):
        raise ValueError(f"schedule = {schedule!r} is invalid: must be a list of (time_s, "
                         f"command) pairs, e.g. [(0.0, 1), (0.8, 0)]")
    out = []
    for k, item in enumerate(schedule):
        try:
            t, v = item
        except (TypeError, ValueError):
            raise ValueError(f"schedule[{k}] = {item!r} is invalid: must be a pair "
                             f"(time_s, command)") from None
        t = check_duration(t, f"schedule[{k}] time", allow_zero=True)
        out.append((t, check_command(v, f"schedule[{k}] command")))
    return sorted(out, key=lambda c: c[0])


# ------------------------------------------------------------------------------------------
# packing
# ------------------------------------------------------------------------------------------
def cell_volumes(params: RigParams) -> np.ndarray:
    """Volumes of the line cells [m³]: tube share plus any tee volume located in the cell."""
    ln = params.line
    n = ln.n_cells
    vol = np.full(n, ln.area_m2 * ln.length_m / n)
    for pos, v in ln.tee_volumes:
        i = min(int(pos / ln.length_m * n), n - 1)
        vol[i] += v
    return vol


def pack(params: RigParams, dt_s: float = 0.0) -> np.ndarray:
    """Parameter array ``P`` (layout in :mod:`pneugym.physics.layout`)."""
    g, c, ln, v, f, e = (params.gas, params.cylinder, params.line, params.valve, params.friction,
                         params.effects)
    P = np.zeros(L.NP + ln.n_cells)
    cd = v.discharge_coefficient
    P[L.P_R] = g.gas_constant_j_per_kg_k
    P[L.P_GAMMA] = g.gamma
    P[L.P_T] = g.ambient_temperature_k
    P[L.P_PA] = g.ambient_pressure_pa
    P[L.P_PS] = params.supply_pressure_pa
    P[L.P_MU] = g.viscosity_pa_s
    P[L.P_CDA_VALVE] = cd * v.area_m2
    P[L.P_CDA_PORT] = cd * c.port_area_m2
    P[L.P_CDA_EXH] = cd * v.exhaust_area_m2
    P[L.P_CDA_LINE] = cd * ln.area_m2
    P[L.P_FLOW_MODEL] = 0.0 if v.flow_model == "thesis" else 1.0
    P[L.P_ISO_B] = v.iso_b
    P[L.P_LIN] = v.linear_ratio
    P[L.P_DELAY] = params.valve_delay_s
    P[L.P_RAMP] = v.ramp_s
    P[L.P_AP] = params.drive_piston_area_m2
    P[L.P_AE] = params.exhaust_piston_area_m2
    P[L.P_FLOAD] = params.load_force_n
    P[L.P_STROKE] = c.stroke_m
    P[L.P_V0D] = params.drive_dead_volume_m3 + e.dead_volume_m3
    P[L.P_V0E] = params.exhaust_dead_volume_m3
    P[L.P_CUSH_LEN] = c.cushion_length_m
    P[L.P_CUSH_FD] = c.cushion_factor_drive
    P[L.P_CUSH_FE] = c.cushion_factor_exhaust
    P[L.P_CUSH_RAMP] = c.cushion_ramp_m
    P[L.P_MASS] = params.moving_mass_kg
    P[L.P_FS] = f.static_n
    P[L.P_FC] = f.coulomb_n
    P[L.P_KV] = f.viscous_n_s_per_m
    P[L.P_STRIB_F] = e.stribeck_force_n
    P[L.P_STRIB_V] = e.stribeck_velocity_m_s
    P[L.P_CDA_LEAK_D] = e.leak_drive_area_m2
    P[L.P_CDA_LEAK_P] = e.leak_piston_area_m2
    P[L.P_KLAM_LEAK_D] = e.leak_drive_laminar_m3
    P[L.P_TAU_TH] = e.heat_transfer_time_constant_s
    P[L.P_LAG] = e.sensor_lag_s
    P[L.P_LINE_MODEL] = 0.0 if ln.model == "fd" else 1.0
    if uses_implicit_line(params):
        P[L.P_LINE_MODEL] = 2.0
    P[L.P_NCELLS] = ln.n_cells
    P[L.P_DX] = ln.length_m / ln.n_cells
    P[L.P_LINE_A] = ln.area_m2
    P[L.P_LINE_D] = ln.diameter_m
    P[L.P_DT] = dt_s
    P[L.P_AV] = ln.artificial_viscosity
    P[L.P_SQRT_T] = math.sqrt(g.ambient_temperature_k)
    P[L.P_OC:L.P_OC + NOC] = orifice_constants(g.gamma, g.gas_constant_j_per_kg_k,
                                               P[L.P_FLOW_MODEL], v.iso_b, v.linear_ratio)
    P[L.NP:] = cell_volumes(params)
    return P


def set_supply_dip(P: np.ndarray, start_s: float, duration_s: float, depth: float) -> None:
    """Write a supply-pressure dip into a packed parameter array (see :meth:`Plant.set_supply_dip`)."""
    for name, val in (("start_s", start_s), ("duration_s", duration_s), ("depth", depth)):
        if not _real(val):
            raise ValueError(f"supply dip {name} = {val!r} is invalid: must be a finite number")
    for name, val, ok in (("start_s", start_s, start_s >= 0.0),
                          ("duration_s", duration_s, duration_s >= 0.0),
                          ("depth", depth, 0.0 <= depth < 1.0)):
        if not ok:
            raise ValueError(f"supply dip {name} = {val} is invalid (start and duration >= 0 s, "
                             f"0 <= depth < 1 of the gauge supply pressure)")
    P[L.P_DIP_T0], P[L.P_DIP_DUR], P[L.P_DIP_DEPTH] = start_s, duration_s, depth


#: the laminar leak's stability limit is taken at this many times the supply pressure
LAMINAR_P_FACTOR = 4.0


def stability_limits(params: RigParams) -> dict[str, float]:
    """Largest stable substep [s] for each fast process of the explicit part (before the safety
    factor). The valve and port flows are implicit in the IMEX substep
    (:func:`pneugym.physics.rhs.stage_rhs`) and set no limit.

    - ``line CFL``: the line's acoustic modes (FD line only). On the staggered grid with the
      centred momentum flux the semi-discrete modes of a uniform flow satisfy
      ``|ω| <= 2 c / dx`` for every flow speed ``|u| <= c`` (``c`` isothermal sound speed; tee
      volumes only lower it), so the SSP-RK3 bound on the imaginary axis gives ``√3 dx / (2 c)``;
      ``c`` becomes ``u_max`` where a port or valve wider than the tube can drive the end
      cell's gas faster than sound, and the bound halves with two cells (see the code);
    - ``orifice <name>``: the stiffest explicit orifice-volume pair (linearised orifice
      conductance): exhaust, leaks, and the valve when the line has a single cell (that cell
      takes the implicit port flow, the valve's is explicit);
    - ``implicit orifice chain of the lumped line``: no stability limit (valve, joints and port
      are solved together, :func:`pneugym.physics.chain.implicit_chain`), but a robustness bound
      ``h lambda <= CHAIN_H_LAMBDA`` for the chain's explicit first IMEX stage (see below);
    - ``laminar leak drive``: the laminar leak's linearised rate, taken at
      :data:`LAMINAR_P_FACTOR` times the supply pressure (it grows with the pressure);
    - ``line friction``, ``piston air spring``, ``piston viscous``, ``heat transfer``.
    """
    g, c, ln, v, e = params.gas, params.cylinder, params.line, params.valve, params.effects
    R, gam, T, pa, ps = (g.gas_constant_j_per_kg_k, g.gamma, g.ambient_temperature_k,
                         g.ambient_pressure_pa, params.supply_pressure_pa)
    oc = orifice_constants(gam, R, 0.0 if v.flow_model == "thesis" else 1.0, v.iso_b, v.linear_ratio)
    vol = cell_volumes(params)
    cd = v.discharge_coefficient
    out: dict[str, float] = {}

    def orifice(name: str, cda: float, va: float, vb: float) -> None:
        if cda <= 0:
            return
        G = linear_conductance(ps, cda, T, oc)
        lam = G * R * T * (1.0 / va + 1.0 / vb)
        out[f"orifice {name}"] = RK3_REAL_LIMIT / lam

    v0d = params.drive_dead_volume_m3 + e.dead_volume_m3
    v0e = params.exhaust_dead_volume_m3
    if ln.n_cells == 1:
        # one cell takes both flows: the valve's is explicit then, and next to the implicit port
        # flow on the same cell the IMEX step is stable to 0.72 x the RK3 orifice bound
        # (linearised scan along extensions, FD and lumped, 1.5 and 2.5 bar): 0.7 of it
        orifice("valve -> line cell 0", cd * v.area_m2, vol[0], math.inf)
        out["orifice valve -> line cell 0"] *= 0.7
    orifice("exhaust", cd * v.exhaust_area_m2, v0e, math.inf)
    orifice("leak drive", e.leak_drive_area_m2, v0d, math.inf)
    orifice("leak piston", e.leak_piston_area_m2, v0d, v0e)
    if e.leak_drive_laminar_m3 > 0:
        # q = K (p² - p_a²) / (2 mu R T): dq/dp = K p / (mu R T), lambda = gamma R T dq/dp / V
        # (gamma: adiabatic chambers). Unlike a choked orifice's, it grows with the pressure:
        # taken at 4x the supply's, since a hold test may start its chamber well above it
        lam = gam * e.leak_drive_laminar_m3 * LAMINAR_P_FACTOR * ps / (g.viscosity_pa_s * v0d)
        out["laminar leak drive"] = RK3_REAL_LIMIT / lam
    if ln.model == "lumped" and ln.n_cells > 1:
        # the whole orifice chain (valve, joints, port) is implicit (pneugym.physics.chain.
        # implicit_chain) and has no stability limit, but its first IMEX stage is explicit:
        # where h lambda of the chain is large, a sudden change (the valve opening onto the
        # empty line) overshoots and a cell's mass goes negative. Measured along extensions
        # with and without cut-offs (1.5 and 2.5 bar, 2-12 cells): it held to h lambda ~ 90;
        # the limit keeps h lambda <= CHAIN_H_LAMBDA (lambda: Gershgorin bound per cell of the
        # linearised chain, 2 R T (G_left + G_right) / V_i)
        G = linear_conductance(ps, cd * ln.area_m2, T, oc)
        n = ln.n_cells
        lam = max(2.0 * R * T * G * ((i > 0) + (i < n - 1)) / vol[i] for i in range(n))
        # the end cells also exchange through the valve and the port: with them in the bound,
        # failures came at h lambda ~ 90 both on the thesis rig and on random rigs whose port
        # is several times the tube's area (property test), where the joints-only bound let
        # h lambda reach ~90 at its limit of 40; the tighter of the two bounds holds
        gv = linear_conductance(ps, cd * v.area_m2, T, oc)
        gp = linear_conductance(ps, cd * c.port_area_m2, T, oc)
        lam_ends = max(2.0 * R * T * ((gv if i == 0 else G) + (gp if i == n - 1 else G))
                       / vol[i] for i in range(n))
        out["implicit orifice chain of the lumped line"] = min(CHAIN_H_LAMBDA / lam,
                                                                CHAIN_H_LAMBDA_ENDS / lam_ends)
    if ln.model == "fd" and not uses_implicit_line(params):
        csound = math.sqrt(R * T)
        dx = ln.length_m / ln.n_cells
        # staggered grid, centred flux: |ω| <= 2 c / dx for |u| <= c (see the docstring). The
        # end cells' boundary flows are orifice flows: a port or valve wider than the tube can
        # drive the gas in an end cell faster than sound, at most at the choked flux,
        # u = Cm* R sqrt(T) CdA / A_line (independent of pressure), and the artificial viscosity
        # grows stiff with it: the bound takes 2 u_max for 2 c (found by the property test over
        # random rigs: ports 3.5-4x the tube's area, cushion exits; stable again with margin)
        u_max = max(csound, oc[OC_CM_STAR] * R * math.sqrt(T) * cd
                    * max(c.port_area_m2, v.area_m2) / ln.area_m2)
        out["line CFL"] = RK3_IMAG_LIMIT * dx / (2.0 * u_max)
        if ln.n_cells == 2:
            # the only interior face takes the artificial viscosity of both end cells, whose
            # flows are orifice-driven: random rigs and command sequences (property test) were
            # stable only to 0.62 of the bound (3 cells: 0.92, 4-6 cells: 0.94-1); half of it
            out["line CFL"] *= TWO_CELL_CFL_FACTOR
        lam_f = 32.0 * g.viscosity_pa_s * R * T / (0.5 * pa * ln.diameter_m**2)
        out["line friction"] = RK3_REAL_LIMIT / lam_f
    M = params.moving_mass_kg
    A, Ae = params.drive_piston_area_m2, params.exhaust_piston_area_m2
    if M > 0:
        if A == Ae:  # (this form for a double-rod cylinder: the substeps stay as they were)
            k = A * A * ps * (1.0 / v0d + 1.0 / v0e)
        else:
            k = ps * (A * A / v0d + Ae * Ae / v0e)
        out["piston air spring"] = RK3_IMAG_LIMIT / math.sqrt(k / M)
        if params.friction.viscous_n_s_per_m > 0:
            out["piston viscous"] = RK3_REAL_LIMIT * M / params.friction.viscous_n_s_per_m
    if e.heat_transfer_time_constant_s > 0:
        out["heat transfer"] = RK3_REAL_LIMIT * e.heat_transfer_time_constant_s
    return out


def uses_implicit_line(params: RigParams) -> bool:
    """Whether the substep solves the FD line implicitly: ``SolverParams(line_scheme=
    "implicit")`` on an FD line of more than one cell whose explicit substep the line itself
    limits (its acoustic CFL bound or its wall friction), where the implicit substep (at most
    :data:`IMPLICIT_LINE_MAX_DT_S`, else the next process's bound) is at least
    :data:`IMPLICIT_LINE_MIN_GAIN` times as long. Elsewhere the explicit line is as fast or
    faster (the implicit substep costs about 3.4 explicit ones), and it is kept."""
    ln, sv = params.line, params.solver
    if sv.line_scheme != "implicit" or ln.model != "fd" or ln.n_cells < 2:
        return False
    lim = stability_limits(params.with_(solver={"line_scheme": "explicit"}))
    name = min(lim, key=lim.get)
    if name not in LINE_LIMITS:
        return False
    rest = [v for k, v in lim.items() if k not in LINE_LIMITS]
    dt_implicit = min([IMPLICIT_LINE_MAX_DT_S] + [v * sv.safety for v in rest])
    return dt_implicit >= IMPLICIT_LINE_MIN_GAIN * lim[name] * sv.safety


def choose_dt(params: RigParams) -> tuple[float, str]:
    """The substep [s] and the process that limits it; raises ``ValueError`` if unsteppable."""
    lim = stability_limits(params)
    name = min(lim, key=lim.get)
    stable = lim[name] * params.solver.safety
    s = params.solver
    if s.dt_s is not None:
        if s.dt_s > lim[name]:
            raise ValueError(
                f"SolverParams.dt_s = {s.dt_s:.3g} s is above the stability limit "
                f"{lim[name]:.3g} s set by the {name}; use dt_s=None (automatic) or <= {stable:.3g} s")
        return float(s.dt_s), "user"
    if stable < s.min_dt_s:
        raise ValueError(
            f"this configuration cannot be stepped: the {name} limits the substep to {stable:.3g} s, "
            f"below SolverParams.min_dt_s = {s.min_dt_s:.3g} s (too small a volume or too fine a "
            f"line grid for its orifices); enlarge the volume, coarsen the line or lower min_dt_s")
    if uses_implicit_line(params) and stable > IMPLICIT_LINE_MAX_DT_S:
        return IMPLICIT_LINE_MAX_DT_S, "implicit line (accuracy)"
    return stable, name


def _line_pressures(p: object, n: int) -> np.ndarray:
    """Initial line-cell pressures [Pa absolute]: one number or one per cell, all positive."""
    try:
        arr = np.broadcast_to(np.asarray(p, dtype=float), (n,))
    except (TypeError, ValueError):
        raise ValueError(f"p_line_pa = {p!r} is invalid: must be a pressure [Pa] or one per line "
                         f"cell ({n})") from None
    if isinstance(p, (str, bytes, bool)) or not (np.isfinite(arr).all() and (arr > 0).all()):
        raise ValueError(f"p_line_pa = {p!r} is invalid: must be positive absolute pressures [Pa]")
    return arr


# ------------------------------------------------------------------------------------------
# plant
# ------------------------------------------------------------------------------------------
@dataclass
class Trajectory:
    """Recorded channels (``pneugym.physics.layout.RECORD_NAMES``) at uniform times."""

    data: np.ndarray  # (samples, NR)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.data[:, L.RECORD_NAMES.index(name)]

    @property
    def names(self) -> tuple[str, ...]:
        return L.RECORD_NAMES

    def __len__(self) -> int:
        return self.data.shape[0]


class Plant:
    """One simulated rig. State layout: :mod:`pneugym.physics.layout`.

    The episode starts at the extend command (``t = 0``) from the thesis's initial state (piston
    retracted, driving side at ambient, exhaust chamber at supply pressure). Commands
    (1 = supply connected, 0 = cut off) take effect after the valve delay.
    """

    def __init__(self, params: RigParams | None = None):
        self.params = params or RigParams()
        if not isinstance(self.params, RigParams):
            raise ValueError(f"Plant needs a RigParams, got {type(params).__name__} (a dict: "
                             f"RigParams.from_dict(d))")
        why = self.params.cannot_move()
        if why:
            warnings.warn(f"Plant: {why}", RigWarning, stacklevel=2)
        self.dt_s, self.dt_limited_by = choose_dt(self.params)
        self.dt_retries = 0  # times the substep was halved after a non-physical step
        self.P = pack(self.params, self.dt_s)
        self.n_cells = self.params.line.n_cells
        self._b = 2 * self.n_cells - 1
        self.y = np.zeros(self._b + L.NY)
        self.d = np.zeros(L.ND)
        self._work = np.empty(K.work_size(self.P))  # the kernels' scratch space, reused
        self.reset()

    # -- state ---------------------------------------------------------------------------
    def initial_state(self, p_line_pa: Sequence[float] | float | None = None,
                      p_drive_pa: float | None = None, p_exhaust_pa: float | None = None,
                      position_m: float = 0.0, T_drive_k: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """State arrays ``(y, d)`` at rest; defaults are the thesis's start of an extension.

        ``T_drive_k``: the driving chamber's air temperature [K] (default ambient), e.g. air
        still warm from a fast fill; it relaxes to ambient only with heat transfer
        (``EffectParams.heat_transfer_time_constant_s`` > 0)."""
        prm = self.params
        R, T = prm.gas.gas_constant_j_per_kg_k, prm.gas.ambient_temperature_k
        pa, ps = prm.gas.ambient_pressure_pa, prm.supply_pressure_pa
        n, b = self.n_cells, self._b
        vol = self.P[L.NP:]
        pl = _line_pressures(pa if p_line_pa is None else p_line_pa, n)
        y = np.zeros(b + L.NY)
        y[:n] = pl * vol / (R * T)
        pd = pa if p_drive_pa is None else p_drive_pa
        pe = ps if p_exhaust_pa is None else p_exhaust_pa
        if not (_real(position_m) and 0.0 <= position_m <= prm.cylinder.stroke_m):
            raise ValueError(f"position_m = {position_m!r} is invalid: must be a number in "
                             f"[0, stroke = {prm.cylinder.stroke_m:g}] m")
        vd = self.P[L.P_V0D] + self.P[L.P_AP] * position_m
        ve = self.P[L.P_V0E] + self.P[L.P_AE] * (prm.cylinder.stroke_m - position_m)
        for name, val in (("p_drive_pa", pd), ("p_exhaust_pa", pe)):
            if not (_real(val) and val > 0):
                raise ValueError(f"{name} = {val!r} must be a positive absolute pressure [Pa]")
        td = T if T_drive_k is None else T_drive_k
        if not (_real(td) and 150.0 <= td <= 600.0):
            raise ValueError(f"T_drive_k = {T_drive_k!r} must be an air temperature in [150, 600] K")
        y[b + L.Y_MD] = pd * vd / (R * td)
        y[b + L.Y_ME] = pe * ve / (R * T)
        y[b + L.Y_TD], y[b + L.Y_TE] = td, T
        y[b + L.Y_X] = position_m
        y[b + L.Y_SD], y[b + L.Y_SE] = pd, pe
        d = np.zeros(L.ND)
        d[L.D_T_EXH] = L.NEVER
        d[L.D_T_ARRIVE] = -1.0
        d[L.D_T_CLOSED] = -1.0
        d[L.D_T_S] = 0.0
        d[L.D_MODE] = L.MODE_START if position_m == 0.0 else (
            L.MODE_END if position_m >= prm.cylinder.stroke_m else L.MODE_STUCK)
        return y, d

    def reset(self, **initial) -> "Plant":
        """Back to the start of an extension (keywords as in :meth:`initial_state`)."""
        self.y, self.d = self.initial_state(**initial)
        self._m0 = self.total_air_mass_kg
        return self

    def set_supply_dip(self, start_s: float = 0.0, duration_s: float = 0.0,
                       depth: float = 0.0) -> None:
        """A supply-pressure dip (a disturbance of the run, kept across :meth:`reset`): the
        supply falls by ``depth`` x its gauge pressure along a raised cosine lasting
        ``duration_s`` [s] from ``start_s`` [s]. ``duration_s = 0`` removes it."""
        set_supply_dip(self.P, start_s, duration_s, depth)

    @property
    def supply_dip(self) -> tuple[float, float, float]:
        """``(start_s, duration_s, depth)`` of the supply-pressure dip (duration 0 = none)."""
        return (float(self.P[L.P_DIP_T0]), float(self.P[L.P_DIP_DUR]),
                float(self.P[L.P_DIP_DEPTH]))

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """A copy of the state, for :meth:`restore` (e.g. to search over cut-off times)."""
        return self.y.copy(), self.d.copy()

    def restore(self, snap: tuple[np.ndarray, np.ndarray]) -> None:
        self.y[:], self.d[:] = snap[0], snap[1]

    # -- control -------------------------------------------------------------------------
    def command(self, value: int) -> None:
        """Valve command (1 = supply connected, 0 = cut off), effective after the valve delay."""
        K.command(self.d, self.P, check_command(value))

    def advance(self, duration_s: float, command: int | None = None,
                stop_on_arrival: bool = False) -> None:
        """Give ``command`` (if not None) and advance by ``duration_s`` [s] (control-level API)."""
        cmd = -1.0 if command is None else check_command(command)
        dur = check_duration(duration_s)
        self._retrying(lambda: self._check(K.command_advance(
            self.y, self.P, self.d, self._work, cmd, dur, bool(stop_on_arrival))))

    def run(self, t_end: float, schedule: Iterable[tuple[float, int]] = ((0.0, 1),),
            record_dt: float = 1e-3, cut_on_arrival: bool = False) -> Trajectory:
        """Run to ``t_end`` [s] with commands ``(time_s, value)``, recording every ``record_dt``.

        ``cut_on_arrival`` commands a cut-off the moment the piston reaches the end of stroke
        (the thesis's end-stroke cut-off). Continues from the current state."""
        sched = check_schedule(schedule)
        if not (_real(t_end) and t_end > self.time_s):
            raise ValueError(f"t_end = {t_end!r} is invalid: must be a finite time [s] after the "
                             f"current time {self.time_s:g} s")
        check_duration(t_end - self.time_s, "t_end - current time")
        check_duration(record_dt, "record_dt")
        rows = (t_end - self.time_s) / record_dt
        if rows > MAX_RECORD_ROWS:
            raise ValueError(f"run(t_end={t_end:g}, record_dt={record_dt:g}) would record "
                             f"{rows:.3g} samples, more than {MAX_RECORD_ROWS:g}: raise record_dt")
        return self._retrying(lambda: self._run(t_end, sched, record_dt, cut_on_arrival))

    def _run(self, t_end: float, sched: list[tuple[float, float]], record_dt: float,
             cut_on_arrival: bool) -> Trajectory:
        stops = sorted({t for t, _ in sched if t > self.time_s + 1e-12 and t < t_end} | {t_end})
        nrow = int(math.floor((t_end - self.time_s) / record_dt + 1e-9)) + 3 + 2 * len(stops)
        rec = np.zeros((nrow, L.NR))
        nrec = 0
        for t, v in sched:
            if t <= self.time_s + 1e-12:
                self.command(v)
        for t_stop in stops:
            while True:
                stop = cut_on_arrival and self.arrival_time_s is None
                st, nr = K.advance_ws(self.y, self.P, self.d, t_stop, rec[nrec:], record_dt, stop,
                                      self._work)
                nrec += nr
                self._check(st)
                if stop and self.arrival_time_s is not None:
                    self.command(0)
                    continue
                break
            for t, v in sched:
                if abs(t - t_stop) <= 1e-12:
                    self.command(v)
        data = rec[:nrec]
        if nrec > 1:  # a segment boundary on the recording grid is written twice
            data = data[np.concatenate([[True], np.diff(data[:, 0]) > 1e-12])]
        return Trajectory(data)

    def _retrying(self, call: Callable[[], _T]) -> _T:
        """``call()``; when it meets a non-physical state with the automatic substep, restore the
        state, halve the substep (for the rest of this plant's life), warn and call again (at
        most :data:`MAX_STEP_RETRIES` times): the automatic substep comes from linear stability
        bounds, and sudden changes on some rigs (orifices much wider than the tube) need less."""
        snap = self.snapshot()
        for attempt in range(MAX_STEP_RETRIES + 1):
            try:
                return call()
            except SimulationError as exc:
                # a state broken before the call is not retried (judged only on failure: the
                # check costs more than a 5 ms period's substeps)
                if (self.dt_limited_by == "user" or attempt == MAX_STEP_RETRIES
                        or not self._state_is_physical(*snap)):
                    raise
                self.restore(snap)
                self.dt_s *= 0.5
                self.P[L.P_DT] = self.dt_s
                self.dt_retries += 1
                warnings.warn(f"Plant: {exc}; retrying with half the substep, {self.dt_s:.3g} s, "
                              f"kept for this plant (SolverParams(safety=...) below "
                              f"{self.params.solver.safety:g} avoids the retry)", RigWarning,
                              stacklevel=3)
        raise AssertionError("unreachable")

    def _state_is_physical(self, y: np.ndarray, d: np.ndarray) -> bool:
        """Finite state ``y``, ``d`` with positive masses and temperatures (what the kernels
        check)."""
        b, n = self._b, self.n_cells
        return bool(np.isfinite(y).all() and np.isfinite(d).all() and (y[:n] > 0).all()
                    and min(y[b + L.Y_MD], y[b + L.Y_ME], y[b + L.Y_TD], y[b + L.Y_TE]) > 0)

    def _check(self, status: int) -> None:
        if status == L.STATUS_OK:
            return
        what = {L.STATUS_NONFINITE: "a non-finite value (NaN/inf)",
                L.STATUS_NONPOSITIVE: "a non-positive mass, pressure or temperature"}[status]
        raise SimulationError(
            f"simulation went non-physical at t = {self.time_s:.6f} s: {what}. State: "
            f"x = {self.position_m:.6g} m, v = {self.velocity_m_s:.6g} m/s, "
            f"p_drive = {self.p_drive_pa:.6g} Pa, p_exhaust = {self.p_exhaust_pa:.6g} Pa, "
            f"line p = {np.array2string(self.line_pressures_pa, precision=5)} Pa, "
            f"dt = {self.dt_s:.3g} s (limited by {self.dt_limited_by})")

    # -- observables ---------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return float(self.d[L.D_T])

    @property
    def position_m(self) -> float:
        return float(self.y[self._b + L.Y_X])

    @property
    def velocity_m_s(self) -> float:
        return float(self.y[self._b + L.Y_V])

    @property
    def p_drive_pa(self) -> float:
        return float(K.chamber_pressures(self.y, self.P, self._b)[0])

    @property
    def p_exhaust_pa(self) -> float:
        return float(K.chamber_pressures(self.y, self.P, self._b)[1])

    @property
    def net_force_n(self) -> float:
        """Net force [N] on the piston along the stroke, friction aside (air on both faces,
        ambient on the rod's end, gravity and the external force):
        :func:`pneugym.physics.cylinder.piston_force` on the chamber pressures."""
        pd, pe, _, _ = K.chamber_pressures(self.y, self.P, self._b)
        return float(K.piston_force(pd, pe, self.P))

    @property
    def sensor_pressures_pa(self) -> tuple[float, float]:
        """Driving and exhaust port pressures as the (possibly lagged) transducers read them."""
        return float(self.y[self._b + L.Y_SD]), float(self.y[self._b + L.Y_SE])

    @property
    def line_pressures_pa(self) -> np.ndarray:
        R, T = self.P[L.P_R], self.P[L.P_T]
        return self.y[:self.n_cells] * R * T / self.P[L.NP:]

    @property
    def valve_opening(self) -> tuple[float, float]:
        """(main valve, exhaust path) openings in [0, 1]."""
        s, se = K.valve_opening(self.d, self.P, self.time_s)
        return float(s), float(se)

    @property
    def valve_command(self) -> int:
        return int(self.d[L.D_CMD])

    @property
    def supply_cut(self) -> bool:
        """True once a cut-off has been commanded after the extend command (the valve may still
        be closing)."""
        return self.valve_command == 0 and self._ever_opened

    @property
    def _ever_opened(self) -> bool:
        nq = int(self.d[L.D_NQ])
        return bool(self.d[L.D_T_EXH] < L.NEVER
                    or any(self.d[L.D_Q0 + 2 * k + 1] > 0.5 for k in range(nq)))

    @property
    def valve_closed(self) -> bool:
        """True when the main valve is fully closed and no opening is pending."""
        return bool(K.valve_closed(self.d, self.P))

    @property
    def valve_closed_time_s(self) -> float | None:
        t = float(self.d[L.D_T_CLOSED])
        return None if t < 0 else t

    @property
    def arrival_time_s(self) -> float | None:
        """First time [s] the piston reached the end of stroke (None if not yet)."""
        t = float(self.d[L.D_T_ARRIVE])
        return None if t < 0 else t

    @property
    def mode(self) -> int:
        """0 moving, 1 stuck by friction, 2 held at the extended end, 3 at the retracted end."""
        return int(self.d[L.D_MODE])

    @property
    def stuck(self) -> bool:
        return self.mode == L.MODE_STUCK

    @property
    def stick_events(self) -> int:
        """Times the piston stuck mid-stroke after moving."""
        return int(self.d[L.D_STICKS])

    @property
    def air_mass_in_kg(self) -> float:
        """Air mass drawn from the supply since the extend command [kg]."""
        return float(self.y[self._b + L.Y_MIN])

    @property
    def air_mass_out_kg(self) -> float:
        """Air mass vented to atmosphere (exhaust and leaks) [kg]."""
        return float(self.y[self._b + L.Y_MOUT])

    @property
    def total_air_mass_kg(self) -> float:
        return float(K.total_air_mass(self.y, self.P))

    @property
    def mass_balance_error_kg(self) -> float:
        """Air in the system minus (initial + drawn - vented): zero up to round-off."""
        return self.total_air_mass_kg - (self._m0 + self.air_mass_in_kg - self.air_mass_out_kg)

    # -- energy (thesis 5.5-5.7) -----------------------------------------------------------
    @property
    def driving_volume_m3(self) -> float:
        """Driving-side volume [m³]: line (with tees) plus driving chamber at the current x."""
        return float(self.P[L.NP:].sum() + self.P[L.P_V0D] + self.P[L.P_AP] * self.position_m)

    def filled_energy_j(self, position_m: float | None = None) -> float:
        """Potential energy [J] of the driving side filled to supply pressure (closed form)."""
        x = self.params.cylinder.stroke_m if position_m is None else position_m
        return float(K.filled_energy(self.P, x))

    @property
    def conventional_energy_j(self) -> float:
        """Wasted energy [J] of a conventional extension: driving side at supply, full stroke."""
        return self.filled_energy_j()

    @property
    def driving_side_energy_j(self) -> float:
        """Potential energy [J] of the air now in the line and the driving chamber (eq. 5.9)."""
        return float(K.driving_side_energy(self.y, self.P))

    @property
    def energy_wasted_j(self) -> float:
        """Energy [J] wasted when the return stroke begins now: if the supply is (to be)
        connected, the driving side filled to supply pressure (closed form); after a cut-off,
        the potential energy of the trapped air."""
        return float(K.energy_wasted(self.y, self.P, self.d))

    @property
    def saving_ratio(self) -> float:
        """Thesis eq. 5.10 against conventional actuation at the same conditions (fraction)."""
        return saving_ratio(self.conventional_energy_j, self.energy_wasted_j)

    @property
    def supply_exergy_j(self) -> float:
        """Isothermal flow exergy [J] of the air drawn from the supply."""
        return float(flow_exergy(self.air_mass_in_kg, self.P[L.P_PS], self.P[L.P_PA],
                                 self.P[L.P_R], self.P[L.P_T]))




# ------------------------------------------------------------------------------------------
# batched plants
# ------------------------------------------------------------------------------------------
class PlantBatch:
    """``B`` independent plants with the same line grid, stepped together by
    :func:`pneugym.physics.batch.advance_batch` (parallel over plants with numba ``prange``)."""

    def __init__(self, params: Sequence[RigParams]):
        if isinstance(params, RigParams) or not isinstance(params, Sequence):
            raise ValueError(f"PlantBatch needs a list of RigParams (one per plant), got "
                             f"{type(params).__name__}")
        if not params:
            raise ValueError("PlantBatch needs at least one RigParams")
        plants = [Plant(p) for p in params]
        ns = {pl.n_cells for pl in plants}
        if len(ns) != 1:
            raise ValueError(f"all plants of a batch need the same line.n_cells; got {sorted(ns)}")
        self.plants = plants
        self.P = np.stack([pl.P for pl in plants])
        self.Y = np.stack([pl.y for pl in plants])
        self.D = np.stack([pl.d for pl in plants])
        self.status = np.zeros(len(plants), dtype=np.int64)
        self.W = np.empty((len(plants), K.work_size(self.P[0])))

    def __len__(self) -> int:
        return self.Y.shape[0]

    def reset(self, index: int | None = None) -> None:
        idx = range(len(self)) if index is None else [index]
        for i in idx:
            y, d = self.plants[i].initial_state()
            self.Y[i], self.D[i] = y, d
            self.status[i] = 0

    def set_supply_dip(self, index: int, start_s: float = 0.0, duration_s: float = 0.0,
                       depth: float = 0.0) -> None:
        """Supply-pressure dip of plant ``index`` (see :meth:`Plant.set_supply_dip`)."""
        set_supply_dip(self.P[index], start_s, duration_s, depth)
        self.plants[index].P[:] = self.P[index]

    def advance(self, commands: np.ndarray, duration_s: float) -> None:
        """Command every plant and advance all by ``duration_s`` [s]; raises on any failure."""
        cmds = np.asarray(commands)
        if cmds.shape != (len(self),):
            raise ValueError(f"commands must have shape ({len(self)},), got {cmds.shape}")
        if cmds.dtype.kind not in "biuf" or not ((cmds == 0) | (cmds == 1)).all():
            # (np.isin would cost ~15 us a call: a tenth of a 64-plant step on two threads)
            bad = cmds if cmds.dtype.kind not in "biuf" else cmds[(cmds != 0) & (cmds != 1)]
            raise ValueError(f"commands must be 0 (cut off) or 1 (supply connected); got "
                             f"{bad.ravel()[:5]!r}")
        K.advance_batch(self.Y, self.P, self.D, cmds.astype(np.float64),
                        check_duration(duration_s), self.status, self.W)
        bad = np.flatnonzero(self.status)
        if bad.size:
            i = int(bad[0])
            pl = self.plants[i]
            pl.y[:], pl.d[:] = self.Y[i], self.D[i]
            try:
                pl._check(int(self.status[i]))
            except SimulationError as exc:
                raise SimulationError(f"plant {i} of the batch: {exc}") from None

    def view(self, index: int) -> Plant:
        """Plant ``index`` with its state copied from the batch (for reading observables)."""
        pl = self.plants[index]
        pl.y[:], pl.d[:] = self.Y[index], self.D[index]
        return pl
