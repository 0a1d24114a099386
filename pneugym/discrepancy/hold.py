"""Hold tests: a closed chamber's pressure decay, leakage against heat settling.

A *hold test* records the pressure of a chamber that was filled and then closed: no motion, no
valve. It is the experiment the workflow suggests to separate a leak from heat transfer (a leak
keeps the pressure falling towards ambient, warm air settles within a few time constants), and
the kind of record public data sets hold (:mod:`pneugym.discrepancy.datasets`).

The model is the plant itself: the driving chamber of the rig with the piston at the end of
stroke and the valve closed, started at the measured pressure, replayed by
:class:`pneugym.plant.Plant` (its leak orifice, thesis eqs. 4.1-4.3, and its chamber energy
equation). Before the closing time the chamber is held at its starting pressure (the supply
is still connected). The dynamics depend on the leak area only through the ratio area / volume,
so a record of unknown volume is fitted on the rig's chamber and the leak is reported per litre
of chamber (and as an area when the record states its volume).

Parameters: the nominal model has the starting pressure and the closing time; the candidates
add ``leakage`` (the air stays at ambient temperature, as in the plant's default isothermal
chambers) through either leak law, the better fit of the two standing for it: an orifice (the
leak's Cd*A, thesis eqs. 4.1-4.3) or a laminar capillary (its ``K = pi d^4 / (128 l)``,
Hagen-Poiseuille: the flow of pores and printed layers, with a long tail near ambient),
``heat_transfer`` (air warmer than ambient at closing, settling
with a time constant) and, on top of a named one, the other (a leak through which the expanding
air cools and warms back). The decision uses the checks of
:class:`~pneugym.discrepancy.Discrepancy`, with the last third of the hold held out: the fit
must forecast it.
"""
from __future__ import annotations

import csv
import json
import math
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ..outputs import staged_files
from ..params import RigParams, thesis_rig
from ..physics import layout as L
from ..plant import Plant, RigWarning, SimulationError
from ..provenance import provenance

from .candidates import FitParam
from .report import _clean
from .stats import f_test, inflation, lr_test, separation, standard_errors
from .workflow import z_score

#: the held-out share of the hold (its end)
HOLDOUT_SHARE = 1.0 / 3.0
#: a record of fewer samples is refused
MIN_SAMPLES = 30
#: a longer record [s] is refused (time in ms given as s?)
MAX_DURATION_S = 3600.0
#: a record whose uniform grid would hold more than this many times its samples is refused
#: (a long gap between dense samples: the grid would exhaust memory)
MAX_UNIFORM_FACTOR = 10
#: a larger hold CSV [bytes] is refused
MAX_HOLD_BYTES = 100_000_000
#: the leak laws and the model each is fitted as
LEAK_LAWS = {"orifice": "leakage", "laminar": "leakage_laminar"}


@dataclass(frozen=True)
class HoldRecord:
    """A closed chamber's measured pressure: times [s], absolute pressures [Pa]."""

    name: str
    t: np.ndarray
    p: np.ndarray
    ambient_pressure_pa: float = 101_325.0
    ambient_temperature_k: float = 293.15
    volume_m3: float | None = None  # the chamber's volume, if known
    source: str = ""

    def __post_init__(self) -> None:
        t = np.asarray(self.t, float)
        p = np.asarray(self.p, float)
        if t.ndim != 1 or t.shape != p.shape or t.size < MIN_SAMPLES:
            raise ValueError(f"hold record {self.name!r}: t and p must be 1-D of one length >= "
                             f"{MIN_SAMPLES} (got {t.shape} and {p.shape})")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise ValueError(f"hold record {self.name!r}: t and p must be finite")
        if not (np.diff(t) > 0).all():
            raise ValueError(f"hold record {self.name!r}: times must increase strictly")
        if t[-1] - t[0] > MAX_DURATION_S:
            raise ValueError(f"hold record {self.name!r}: it lasts {t[-1] - t[0]:.4g} s, more than "
                             f"{MAX_DURATION_S:g} s (time in ms given as s?)")
        if not ((p >= 1e4).all() and p.max() <= 1e8):
            raise ValueError(f"hold record {self.name!r}: pressures must be absolute, in Pa "
                             f"(1e4 <= p <= 1e8; bar given as Pa, or gauge?)")
        if not p[0] > self.ambient_pressure_pa:
            raise ValueError(f"hold record {self.name!r}: it starts at {p[0]:.6g} Pa, not above the "
                             f"ambient {self.ambient_pressure_pa:.6g} Pa (a hold test starts pressurised; "
                             f"gauge given as absolute?)")
        if not (5e4 <= self.ambient_pressure_pa <= 1.2e5):
            raise ValueError(f"hold record {self.name!r}: ambient_pressure_pa "
                             f"{self.ambient_pressure_pa!r} must be in [5e4, 1.2e5] Pa")
        if not (200.0 <= self.ambient_temperature_k <= 350.0):
            raise ValueError(f"hold record {self.name!r}: ambient_temperature_k "
                             f"{self.ambient_temperature_k!r} must be in [200, 350] K")
        if self.volume_m3 is not None and not (0 < self.volume_m3 < 1.0):
            raise ValueError(f"hold record {self.name!r}: volume_m3 {self.volume_m3!r} must be in "
                             f"(0, 1) m³ (litres given as m³? 1 l = 1e-3 m³)")
        object.__setattr__(self, "t", t - t[0])
        object.__setattr__(self, "p", p)

    def uniform(self) -> HoldRecord:
        """The record on a uniform grid of its median sample interval (linear interpolation):
        the statistics assume evenly spaced samples."""
        dt = float(np.median(np.diff(self.t)))
        n = int(self.t[-1] / dt) + 1
        if n > MAX_UNIFORM_FACTOR * self.t.size + 100:
            gap = float(np.max(np.diff(self.t)))
            raise ValueError(f"hold record {self.name!r}: its samples are far from even (a gap "
                             f"of {gap:.3g} s against a median interval of {dt:.3g} s): on a "
                             f"uniform grid it would hold {n:,} samples, more than "
                             f"{MAX_UNIFORM_FACTOR} times its {self.t.size:,}; record it at an "
                             f"even rate or resample it first")
        t = np.arange(0.0, self.t[-1] + 0.5 * dt, dt)
        return HoldRecord(self.name, t, np.interp(t, self.t, self.p), self.ambient_pressure_pa,
                          self.ambient_temperature_k, self.volume_m3, self.source)


def _start_pressure(rec: HoldRecord, t_close: float) -> float:
    """The mean pressure [Pa] up to the closing time (the first sample if none)."""
    before = rec.t <= t_close
    return float(rec.p[before].mean()) if before.any() else float(rec.p[0])


def _params(name: str, rec: HoldRecord, t_close: float) -> tuple[FitParam, ...]:
    """The fitted parameters of the nominal model or of one candidate."""
    if name == "nominal":
        p0 = _start_pressure(rec, t_close)
        return (FitParam("hold.p_start_pa", 0.5 * p0, 1.5 * p0, 0.01 * p0, unit="Pa"),
                FitParam("hold.t_close_s", 0.0, 0.8 * float(rec.t[-1]), 1.0, unit="s", diff_step=0.1))
    if name == "leakage":
        return (FitParam("effects.leak_drive_area_m2", 0.0, 1e-5, 1e-9, null=0.0, unit="m²",
                         start=(1e-11, 1e-7)),)
    if name == "leakage_laminar":
        return (FitParam("effects.leak_drive_laminar_m3", 0.0, 1e-10, 1e-15, null=0.0, unit="m³",
                         start=(1e-19, 1e-14)),)
    return (FitParam("effects.heat_transfer_time_constant_s", 0.05, 200.0, 1.0, log=True,
                     null=0.0, unit="s", start=(0.5, 30.0)),
            FitParam("hold.warm_k", 0.0, 60.0, 1.0, null=0.0, unit="K", start=(0.5, 10.0)))


@dataclass
class HoldFit:
    """One fitted model of a hold record."""

    name: str
    values: dict[str, float]
    ssr_fit: float
    ssr_holdout: float
    n_fit: int
    kappa: float
    n_eff: float
    n_eff_holdout: float
    stderr: dict[str, float] = field(default_factory=dict)
    z: dict[str, float] = field(default_factory=dict)
    at_bound: list[str] = field(default_factory=list)


class HoldDiscrepancy:
    """Name what drains a closed chamber: ``leakage``, ``heat_transfer``, both, or ``none``.

    Parameters: ``alpha`` (0.01, divided by the number of fitted candidates, each leak law
    counting as one), ``min_improvement`` (0.1), ``z_min`` (3), as in
    :class:`~pneugym.discrepancy.Discrepancy`; ``sigma_pa`` the pressure noise (default:
    estimated from the record's second differences, at least the quantisation step /
    sqrt(12)); ``seed`` for the random starts; ``leak_laws`` the laws a leak is fitted with
    (:data:`LEAK_LAWS`; the better fit of the held-in part stands for ``leakage``,
    :attr:`leak_law_`)."""

    def __init__(self, alpha: float = 0.01, min_improvement: float = 0.1, z_min: float = 3.0,
                 sigma_pa: float | None = None, n_starts: int = 2, seed: int = 0,
                 leak_laws: tuple[str, ...] = ("orifice", "laminar")):
        if not (0 < alpha < 1 and 0 <= min_improvement < 1 and z_min >= 0 and n_starts >= 1):
            raise ValueError("HoldDiscrepancy: alpha in (0, 1), min_improvement in [0, 1), "
                             "z_min >= 0 and n_starts >= 1 are required")
        laws = () if isinstance(leak_laws, str) else tuple(dict.fromkeys(leak_laws or ()))
        if not laws or not set(laws) <= set(LEAK_LAWS):
            raise ValueError(f"HoldDiscrepancy leak_laws = {leak_laws!r}: give one or both of "
                             f"{list(LEAK_LAWS)}")
        self.leak_laws = laws
        if sigma_pa is not None and not sigma_pa > 0:
            raise ValueError(f"HoldDiscrepancy sigma_pa = {sigma_pa!r} must be > 0 Pa")
        self.alpha, self.min_improvement, self.z_min = float(alpha), float(min_improvement), float(z_min)
        self.sigma_pa, self.n_starts, self.seed = sigma_pa, int(n_starts), int(seed)

    # -- model ---------------------------------------------------------------------------
    def rig(self, rec: HoldRecord) -> RigParams:
        """The plant's rig for ``rec``: the thesis rig at the record's ambient conditions."""
        return thesis_rig(2.5, gas={"ambient_pressure_pa": rec.ambient_pressure_pa,
                                    "ambient_temperature_k": rec.ambient_temperature_k})

    @staticmethod
    def model_volume_m3(rig: RigParams) -> float:
        """Air volume [m³] the plant closes in: the driving chamber at the end of stroke and
        the line."""
        pl = Plant(rig)
        return float(pl.P[L.P_V0D] + pl.P[L.P_AP] * rig.cylinder.stroke_m + pl.P[L.NP:].sum())

    def simulate(self, rec: HoldRecord, values: dict[str, float]) -> np.ndarray:
        """Modelled pressure [Pa abs] at the record's times for fitted ``values``
        (``hold.*`` and ``effects.*`` keys)."""
        t_close = values["hold.t_close_s"]
        p0 = values["hold.p_start_pa"]
        eff = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("effects.")}
        rig = self.rig(rec).with_(effects=eff)
        warm = values.get("hold.warm_k", 0.0)
        out = np.full(rec.t.size, p0)
        after = rec.t > t_close
        if after.any():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RigWarning)
                pl = Plant(rig)
            pl.reset(p_drive_pa=p0, p_exhaust_pa=rec.ambient_pressure_pa, p_line_pa=p0,
                     position_m=rig.cylinder.stroke_m, T_drive_k=rig.gas.ambient_temperature_k + warm)
            dt = float(np.median(np.diff(rec.t)))
            tr = pl.run(float(rec.t[-1] - t_close) + dt, [(0.0, 0)], record_dt=min(dt, 0.05))
            out[after] = np.interp(rec.t[after] - t_close, tr["t"], tr["p_drive_sensor"])
        return out

    # -- fitting -------------------------------------------------------------------------
    def _fit(self, rec: HoldRecord, names: tuple[str, ...], mask: np.ndarray, t_close: float,
             rng: np.random.Generator, first: dict[str, float] | None = None
             ) -> tuple[tuple[FitParam, ...], np.ndarray, float, np.ndarray]:
        params = _params("nominal", rec, t_close) + sum((_params(n, rec, t_close) for n in names), ())
        lo = np.array([q.u_bounds[0] for q in params])
        hi = np.array([q.u_bounds[1] for q in params])
        p0 = _start_pressure(rec, t_close)

        def resid(u: np.ndarray) -> np.ndarray:
            vals = {q.path: q.from_u(x) for q, x in zip(params, u)}
            try:
                sim = self.simulate(rec, vals)
            except (SimulationError, ValueError):
                return np.full(int(mask.sum()), 1e4)
            return ((rec.p - sim) / self.sigma_)[mask]

        starts = []
        for k in range(self.n_starts):
            v = {"hold.p_start_pa": p0, "hold.t_close_s": t_close}
            for q in params[2:]:
                v[q.path] = (first or {}).get(q.path, q.draw(rng)) if k == 0 else q.draw(rng)
            starts.append(np.clip([q.to_u(v[q.path]) for q in params], lo + 1e-9, hi - 1e-9))
        best = None
        for u0 in starts:
            sol = least_squares(resid, u0, bounds=(lo, hi), diff_step=[q.diff_step or 0.02 for q in params],
                                x_scale=1.0, max_nfev=40)
            if best is None or sol.cost < best.cost:
                best = sol
        vals = np.array([q.from_u(x) for q, x in zip(params, best.x)])
        return params, vals, 2.0 * float(best.cost), best.jac

    def fit(self, rec: HoldRecord) -> HoldDiscrepancy:
        """Fit the nominal model and every candidate to ``rec``; decide."""
        raw = rec
        rec = rec.uniform()
        self.record_ = rec
        t_close = self._closing_guess(raw)
        self.sigma_ = self.sigma_pa or self._noise(raw)
        n_hold = max(int(round(HOLDOUT_SHARE * (rec.t > t_close).sum())), 1)
        fit_mask = np.ones(rec.t.size, bool)
        fit_mask[-n_hold:] = False
        self.holdout_from_s_ = float(rec.t[-n_hold])
        models: dict[tuple[str, ...], HoldFit] = {}
        sims: dict[tuple[str, ...], np.ndarray] = {}

        def run(names: tuple[str, ...], first=None) -> HoldFit:
            # each model its own random starts: a candidate added or left out changes no other
            rng = np.random.default_rng([self.seed, zlib.crc32("+".join(names).encode())])
            params, vals, ssr, jac = self._fit(rec, names, fit_mask, t_close, rng, first)
            values = {q.path: float(v) for q, v in zip(params, vals)}
            sim = self.simulate(rec, values)
            r = (rec.p - sim) / self.sigma_
            kappa, n_eff = inflation([r[fit_mask]])
            _, n_eff_h = inflation([r[~fit_mask]])
            f = HoldFit("+".join(names) or "nominal", values, float(r[fit_mask] @ r[fit_mask]),
                        float(r[~fit_mask] @ r[~fit_mask]), int(fit_mask.sum()), kappa, n_eff, n_eff_h)
            se = standard_errors(jac, ssr, f.n_fit, kappa)
            for k, q in enumerate(params[2:], start=2):
                u = q.to_u(values[q.path])
                f.stderr[q.path] = float(se[k] * q.dvalue_du(u))
                if q.null is not None:
                    f.z[q.path] = z_score(values[q.path], q.null, f.stderr[q.path])
                lo, hi = q.u_bounds
                if hi - u <= 1e-3 * (hi - lo) or (q.null is not None and q.lo != q.null
                                                  and u - lo <= 1e-3 * (hi - lo)):
                    f.at_bound.append(q.path)
            models[names], sims[names] = f, sim
            return f

        base = run(())
        self.checks_: dict[str, dict] = {}
        singles = ("leakage", "heat_transfer")
        n_cands = len(self.leak_laws) + 1
        # the leak: each law fitted and judged (each counts in the level); the better fit of the
        # held-in part stands for it, unless the two are not told apart and only the other passes
        leaks = {law: run((LEAK_LAWS[law],)) for law in self.leak_laws}
        self.leak_law_checks_ = {law: self._judge(m, base, n_cands) for law, m in leaks.items()}
        order = sorted(leaks, key=lambda k: leaks[k].ssr_fit)
        self.leak_law_, self.leak_law_separation_ = order[0], None
        if len(order) == 2:
            stat, p = separation(leaks[order[0]].ssr_fit, leaks[order[1]].ssr_fit,
                                 leaks[order[0]].n_eff)
            resolved = p < self.alpha
            self.leak_law_separation_ = {"law": order[0], "statistic": stat, "p_value": p,
                                         "resolved": resolved}
            passing = [k for k in order if self.leak_law_checks_[k]["passed"]]
            if not resolved and passing:
                self.leak_law_ = passing[0]
        fits = {"leakage": leaks[self.leak_law_], "heat_transfer": run(("heat_transfer",))}
        self.checks_["leakage"] = self.leak_law_checks_[self.leak_law_]
        self.checks_["heat_transfer"] = self._judge(fits["heat_transfer"], base, n_cands)
        passed = sorted((n for n in singles if self.checks_[n]["passed"]),
                        key=lambda n: fits[n].ssr_fit + fits[n].ssr_holdout)
        self.named_effect_ = passed[0] if passed else "none"
        self.extension_: str | None = None
        self.ambiguous_: list[str] = []
        self.suggestion_: str | None = None
        if len(passed) == 2:
            a, b = (fits[n] for n in passed)
            stat, p = separation(a.ssr_fit + a.ssr_holdout, b.ssr_fit + b.ssr_holdout,
                                 a.n_eff + a.n_eff_holdout)
            self.separation_ = {"best": passed[0], "runner_up": passed[1], "statistic": stat,
                                "p_value": p}
            if self.separation_["p_value"] >= self.alpha:
                self.named_effect_ = "ambiguous"
                self.ambiguous_ = list(passed)
                tau = models[("heat_transfer",)].values["effects.heat_transfer_time_constant_s"]
                self.suggestion_ = (
                    f"a hold of at least {max(5 * tau, 2 * float(rec.t[-1])):.0f} s (five fitted time "
                    f"constants), or a second hold started after the chamber has rested at its "
                    f"pressure for {max(5 * tau, 60.0):.0f} s: a leak keeps the pressure falling, air "
                    f"that has reached the wall temperature no longer does")
        if self.named_effect_ in singles:
            first = fits[passed[0]].values
            both = run((LEAK_LAWS[self.leak_law_], "heat_transfer"), first)
            self.checks_["both"] = self._judge(both, fits[passed[0]], 1)
            if self.checks_["both"]["passed"]:
                self.extension_ = "heat_transfer" if passed[0] == "leakage" else "leakage"
        self.models_, self.sims_, self.candidate_fits_ = models, sims, fits
        self.decision_ = self._sentence()
        return self

    def _sentence(self) -> str:
        if self.named_effect_ == "ambiguous":
            s = self.separation_
            return (f"ambiguous: leakage and heat_transfer both pass and fit about equally "
                    f"(N_eff ln(SSR ratio) = {s['statistic']:.3g}, p = {s['p_value']:.2g}); to "
                    f"separate them: {self.suggestion_}")
        if self.named_effect_ == "none":
            short = [n for n in ("leakage", "heat_transfer") if self.checks_[n]["checks"]["material"]
                     and self.checks_[n]["improvement_holdout"] > 0]
            if not short:
                return ("none: neither a leak nor settling air explains the decay better than a "
                        "constant pressure, held-out end included")
            n = max(short, key=lambda k: self.checks_[k]["improvement_fit"])
            c, m = self.checks_[n], self.candidate_fits_[n]
            failed = ", ".join(k for k, v in c["checks"].items() if not v)
            rms = math.sqrt(m.ssr_fit / m.n_fit)
            return (f"none, evidence short: {n} removes {c['improvement_fit']:.0%} of the fitted misfit "
                    f"and {c['improvement_holdout']:.0%} on the held-out end, but fails {failed}; "
                    f"its residuals are {rms:.0f} sigma RMS and structured (N_eff = {m.n_eff:.0f} of "
                    f"{m.n_fit} samples): the form of the model does not fit the decay")
        c = self.checks_[self.named_effect_]
        out = (f"{self.named_effect_}{self._law_text()}: passes every check and forecasts the "
               f"held-out end ({c['improvement_holdout']:.0%} of its misfit removed, "
               f"p = {c['holdout_p']:.2g})")
        if self.extension_:
            out += f"; {self.extension_} on top passes as well"
        elif "both" in self.checks_:
            failed = [k for k, v in self.checks_["both"]["checks"].items() if not v]
            out += f"; the other effect on top does not pass ({', '.join(failed)})"
        return out

    def _law_text(self) -> str:
        """For a named leak: its law, and whether the other law fits clearly worse."""
        if self.named_effect_ != "leakage":
            return ""
        s = self.leak_law_separation_
        if s is None:
            return f" ({self.leak_law_} law)"
        other = next(k for k in self.leak_laws if k != self.leak_law_)
        verdict = (f"the {other} law fits clearly worse" if s["resolved"] else
                   f"not told from the {other} law" + (
                       ", which fits as well but fails a check" if s["law"] == other else ""))
        return f" ({self.leak_law_} law; {verdict}, p = {s['p_value']:.2g})"

    def _judge(self, m: HoldFit, ref: HoldFit, n_cands: int) -> dict:
        """The checks of the workflow for model ``m`` against the nested model ``ref``."""
        level = self.alpha / n_cands
        extra = len(m.values) - len(ref.values)
        F, p = f_test(ref.ssr_fit, m.ssr_fit, extra, len(m.values), m.n_eff)
        imp = 1.0 - m.ssr_fit / ref.ssr_fit if ref.ssr_fit > 0 else 0.0
        stat, ph = lr_test(ref.ssr_holdout, m.ssr_holdout, m.n_eff_holdout)
        imp_h = 1.0 - m.ssr_holdout / ref.ssr_holdout if ref.ssr_holdout > 0 else 0.0
        new = [k for k in m.values if k not in ref.values]
        z = max((m.z.get(k, 0.0) for k in new if k in m.z), default=0.0)
        checks = {"significant": p < level, "material": imp >= self.min_improvement,
                  "away_from_null": z >= self.z_min,
                  "not_on_bound": not [k for k in m.at_bound if k in new],
                  "improves_holdout": ph < level and imp_h >= 0.5 * self.min_improvement}
        return {"model": m.name, "against": ref.name, "F": F, "p_value": p, "improvement_fit": imp,
                "holdout_statistic": stat, "holdout_p": ph, "improvement_holdout": imp_h,
                "z": z, "n_eff": m.n_eff, "checks": checks, "passed": all(checks.values())}

    @staticmethod
    def _closing_guess(rec: HoldRecord) -> float:
        """First guess of the closing time [s] (it is fitted afterwards): the sample before the
        first one more than 3 quantisation steps below the starting level (0 if none)."""
        p = rec.p
        step = HoldDiscrepancy._step(p)
        below = np.flatnonzero(p < p[: max(3, p.size // 100)].mean() - 3 * step)
        return float(rec.t[max(below[0] - 1, 0)]) if below.size else 0.0

    @staticmethod
    def _step(p: np.ndarray) -> float:
        d = np.abs(np.diff(p))
        d = d[d > 0]
        return float(d.min()) if d.size else 1.0

    @staticmethod
    def _noise(rec: HoldRecord) -> float:
        """Pressure noise [Pa]: the robust scatter of second differences, which remove a smooth
        decay (``1.4826 MAD / sqrt(6)``), at least the quantisation step / sqrt(12)."""
        q = HoldDiscrepancy._step(rec.p) / math.sqrt(12.0)
        d2 = np.diff(rec.p, 2)
        mad = float(np.median(np.abs(d2 - np.median(d2))))
        return max(1.4826 * mad / math.sqrt(6.0), q)

    # -- results -------------------------------------------------------------------------
    def leak_per_litre(self, model: tuple[str, ...] | None = None) -> float:
        """Fitted leak per litre of chamber: Cd*A [m²] of the orifice law (``("leakage",)``),
        or ``K`` [m³] of the laminar law (``("leakage_laminar",)``); default: the law that
        stands for ``leakage`` (:attr:`leak_law_`)."""
        vals = self.models_[model or (LEAK_LAWS[self.leak_law_],)].values
        a = vals.get("effects.leak_drive_area_m2", vals.get("effects.leak_drive_laminar_m3"))
        return a / (self.model_volume_m3(self.rig(self.record_)) * 1e3)

    def report_dict(self) -> dict:
        rec = self.record_
        out = {"record": rec.name, "source": rec.source, "samples": int(rec.t.size),
               "duration_s": float(rec.t[-1]), "sigma_pa": self.sigma_,
               "holdout_from_s": self.holdout_from_s_, "named_effect": self.named_effect_,
               "extension": self.extension_, "decision": self.decision_,
               "ambiguous_between": self.ambiguous_, "suggested_experiment": self.suggestion_,
               "checks": self.checks_,
               "models": {m.name: {"values": m.values, "rms_fit_pa": math.sqrt(m.ssr_fit / m.n_fit) * self.sigma_,
                                   "rms_holdout_pa": math.sqrt(m.ssr_holdout / max(rec.t.size - m.n_fit, 1))
                                   * self.sigma_, "n_eff": m.n_eff, "stderr": m.stderr, "z": m.z}
                          for m in self.models_.values()},
               "model_volume_m3": self.model_volume_m3(self.rig(rec))}
        out["leak_law"] = self.leak_law_
        out["leak_law_separation"] = self.leak_law_separation_
        out["leak_law_checks"] = self.leak_law_checks_
        out["leak"] = {"law": self.leak_law_, "per_litre": self.leak_per_litre(),
                       "unit": "m² (Cd*A)" if self.leak_law_ == "orifice" else "m³ (K)"}
        if ("leakage",) in self.models_:
            out["leak_per_litre_m2"] = self.leak_per_litre(("leakage",))
            if rec.volume_m3:
                out["leak_area_m2"] = out["leak_per_litre_m2"] * rec.volume_m3 * 1e3
        if ("leakage_laminar",) in self.models_:
            out["laminar_leak_per_litre_m3"] = self.leak_per_litre(("leakage_laminar",))
            if rec.volume_m3:
                out["laminar_leak_m3"] = out["laminar_leak_per_litre_m3"] * rec.volume_m3 * 1e3
        return out


def read_hold(path: str) -> HoldRecord:
    """A hold record from ``zillen:NAME`` (a shipped public record) or a CSV file with a header
    holding ``t`` [s] and ``p_drive`` [Pa absolute] (as in the measured-run format)."""
    if path.startswith("zillen:"):
        from .datasets import zillen_chamber
        return zillen_chamber(path.split(":", 1)[1])
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"hold record {path}: no such file")
    if p.stat().st_size > MAX_HOLD_BYTES:
        raise ValueError(f"hold record {path}: {p.stat().st_size:,} bytes, more than "
                         f"{MAX_HOLD_BYTES:,} (an hour at 1 kHz takes about 60 MB)")
    with open(p, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if rows:
        rows[0] = [c.strip() for c in rows[0]]
    if not rows or not {"t", "p_drive"} <= set(rows[0]):
        raise ValueError(f"hold record {path}: the header must name the columns t [s] and "
                         f"p_drive [Pa absolute]")
    it, ip = rows[0].index("t"), rows[0].index("p_drive")
    try:
        t = np.array([float(r[it]) for r in rows[1:] if r])
        pr = np.array([float(r[ip]) for r in rows[1:] if r])
    except (ValueError, IndexError):
        raise ValueError(f"hold record {path}: every row needs numbers in t and p_drive") from None
    if p.stem in ("", ".", "..") or p.stem.startswith("."):
        raise ValueError(f"hold record {path}: its file name {p.name!r} gives no record name "
                         f"(its report goes to a folder of that name): rename the file")
    return HoldRecord(p.stem, t, pr, source=str(p))


def write_hold_report(h: HoldDiscrepancy, out: str | Path, plots: bool = True) -> Path:
    """``hold.json``, ``hold.md`` and ``hold.png`` (measured and fitted pressures, residuals)
    of one fitted record into the folder ``out``, written as a set."""
    rep = h.report_dict()
    rep["provenance"] = provenance()
    rec = h.record_
    lines = [f"# Hold test: {rec.name}", "", f"Source: {rec.source or '-'}", "",
             f"**Named: `{rep['named_effect']}`** - {rep['decision']}", "",
             f"{rep['samples']} samples over {rep['duration_s']:.1f} s, pressure noise "
             f"{rep['sigma_pa']:.0f} Pa; the end from {rep['holdout_from_s']:.1f} s is held out.", "",
             "| model | parameters | RMS fit [Pa] | RMS held-out [Pa] | N_eff |", "|---|---|---|---|---|"]
    for name, m in rep["models"].items():
        pars = ", ".join(f"{k.split('.', 1)[1]} = {v:.4g}" for k, v in m["values"].items())
        lines.append(f"| {name} | {pars} | {m['rms_fit_pa']:.0f} | {m['rms_holdout_pa']:.0f} | {m['n_eff']:.0f} |")
    lines += ["", "| test | passed | p | held-out p | failed checks |", "|---|---|---|---|---|"]
    for name, c in rep["checks"].items():
        failed = ", ".join(k for k, v in c["checks"].items() if not v) or "-"
        lines.append(f"| {c['model']} vs {c['against']} | {c['passed']} | {c['p_value']:.2g} | "
                     f"{c['holdout_p']:.2g} | {failed} |")
    lines += ["", f"The leak's law standing for `leakage`: **{rep['leak_law']}**."]
    if "leak_per_litre_m2" in rep:
        lines += ["", f"Leak, orifice law (`leakage`): Cd*A = {rep['leak_per_litre_m2']:.3g} m² per litre of chamber"
                  + (f", {rep['leak_area_m2']:.3g} m² for the stated volume" if "leak_area_m2" in rep else "")]
    if "laminar_leak_per_litre_m3" in rep:
        lines += ["", f"Leak, laminar law (`leakage_laminar`): K = pi d^4 / (128 l) = "
                  f"{rep['laminar_leak_per_litre_m3']:.3g} m³ per litre of chamber"
                  + (f", {rep['laminar_leak_m3']:.3g} m³ for the stated volume" if "laminar_leak_m3" in rep else "")]
    if rep["leak_law_separation"]:
        s = rep["leak_law_separation"]
        lines += ["", f"The leak's law: {s['law']} fits the held-in part better "
                  f"(N_eff ln(SSR ratio) = {s['statistic']:.3g}, p = {s['p_value']:.2g}; "
                  f"{'resolved' if s['resolved'] else 'not resolved'} at alpha)"]
    with staged_files(out) as stage:
        (stage / "hold.json").write_text(json.dumps(_clean(rep), indent=2, allow_nan=False))
        (stage / "hold.md").write_text("\n".join(lines) + "\n")
        if plots:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
            fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True, height_ratios=(2, 1))
            a.plot(rec.t, rec.p / 1e5, "k.", ms=2, label="measured")
            law = {"leakage": "leak (orifice law)", "leakage_laminar": "leak (laminar law)",
                   "heat_transfer": "warm air"}
            for key, sim in h.sims_.items():
                label = " + ".join(law.get(k, k) for k in key) or "nominal"
                a.plot(rec.t, sim / 1e5, lw=1.2, label=label)
                b.plot(rec.t, (rec.p - sim) / 1e3, lw=0.8, label=label)
            for ax in (a, b):
                ax.axvspan(rep["holdout_from_s"], rec.t[-1], color="0.9", zorder=0)
            a.set_ylabel("pressure [bar abs]")
            a.legend(fontsize=8)
            a.set_title(f"{rec.name}: named {rep['named_effect']} (grey: held out)")
            b.set_ylabel("residual [kPa]")
            b.set_xlabel("time [s]")
            fig.tight_layout()
            fig.savefig(stage / "hold.png", dpi=110)
            plt.close(fig)
    return Path(out) / "hold.json"
