"""Commissioning: a model of one rig fitted to a few of its measured strokes, for planning.

A rig file states what a datasheet gives: bore, rod, stroke, supply line, dead volume, load. What
it cannot give (the valve's delay and flow areas, the friction, the cushions' settings, seal
leaks, the chambers' heat exchange, a transducer lag, friction at low speed) shows in two recorded strokes
(:func:`commissioning_protocol`): a *conventional* stroke (the valve delay, the pressure rise,
breakaway, motion, the cushion) and a stroke *cut off on arrival and held* (the trapped air:
leaks, heat). :func:`commission` fits them through the plant with the discrepancy workflow's
machinery (:class:`~pneugym.discrepancy.fit.Problem`, :class:`~pneugym.discrepancy.candidates.
FitParam`, multi-start ``least_squares``, more starts where the fit stays far from the strokes)
and returns a :class:`Commissioned` model: the fitted rig and the fit's uncertainty (Laplace
approximation, inflated for autocorrelated residuals), from which a planner draws plausible rigs
(:meth:`Commissioned.members`).

The discrepancy workflow names an effect only when the evidence demands it (diagnosis); this fit
keeps whatever predicts the strokes better (prediction). Units are SI, pressures absolute inside
the plant, gauge in the measured-run files.

    pneugym commission runs/*.json --out commissioned/     # rig.json, commissioning.json, report
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .data import MeasuredRun, read_runs, simulate_run
from .discrepancy.candidates import CANDIDATES, FitParam, apply, read
from .discrepancy.fit import Executor, Job, Problem, fixed_step, solve
from .discrepancy.prepare import prepare
from .discrepancy.residuals import estimate_noise, nrmse
from .discrepancy.stats import FORM_DELTA, f_test, form_delta, inflation
from .params import LINE_MODELS, ORIFICE_MODELS, RigParams, forms_tried
from .plant import _real

FORMAT = "pneugym-commissioning/1"
#: samples per run the fit uses (longer runs are block-averaged, as in the discrepancy workflow)
MAX_SAMPLES = 1500
#: the flow areas' factor (on the stated ones) the first fits may reach: their substep (the
#: line's CFL bound shrinks as the valve widens) is then 2.5 times the one of the full bounds
#: (5x). A first fit that ends on this cap goes on with the full bounds and their smaller
#: substep, from where it ended and from its own start, the better kept (the cap may have led
#: it into another basin: a rig whose exhaust is 2.6x the stated one ended at misfit 1,069
#: where the full bounds from the stated values reach 1.3)
FAST_AREA_FACTOR = 2.0
#: the fit's procedure, for caches of kept fits: 2 since a first fit on the area cap goes on
#: from its start as well (fits of version 1 differ where a first fit ended on the cap)
FIT_VERSION = 2
AREAS = ("valve.area_m2", "valve.exhaust_area_m2", "cylinder.port_area_m2")
#: the rise of the driving-port pressure [Pa] that marks the valve's opening (the delay's guess)
RISE_PA = 5e3


def fitted_params(known: RigParams) -> tuple[FitParam, ...]:
    """What the fit estimates around the rig file ``known``: the valve delay [s] (absolute), the
    valve, exhaust and port areas and the cushion length (factors on the stated values), the
    static, Coulomb and viscous friction, the two cushion factors, the drive and piston seal
    leaks and the pressure transducers' lag. Bounds are physical, wide enough for rigs far from the thesis's."""
    fr = known.friction
    cy = known.cylinder
    out = [FitParam("valve.delay_s", 0.005, 0.8, 0.1, unit="s"),
           *(FitParam(p, 0.2, 5.0, 1.0, log=True, log_step=0.3, relative=True, unit="x stated")
             for p in ("valve.area_m2", "valve.exhaust_area_m2", "cylinder.port_area_m2"))]
    for name, val, default, lo_f, hi_f in (("static_n", fr.static_n, 359.0, 0.2, 5.0),
                                           ("coulomb_n", fr.coulomb_n, 126.0, 0.05, 5.0),
                                           ("viscous_n_s_per_m", fr.viscous_n_s_per_m, 1557.0,
                                            0.03, 8.0)):
        ref = val if val > 0 else default
        # breakaway is resolved to a substep: the SSR is a staircase in static_n (see
        # pneugym.discrepancy.candidates.nominal_params)
        out.append(FitParam(f"friction.{name}", lo_f * ref, hi_f * ref, ref, log=True,
                            log_step=0.1, diff_step=0.3 if name == "static_n" else None,
                            unit="N s/m" if name.startswith("viscous") else "N"))
    if cy.cushion_length_m > 0:
        out += [FitParam("cylinder.cushion_length_m", 0.25,
                         min(2.5, 0.45 * cy.stroke_m / cy.cushion_length_m), 1.0, log=True,
                         log_step=0.3, relative=True, unit="x stated"),
                FitParam("cylinder.cushion_factor_drive", 0.01, 1.0, 1.0, log=True,
                         log_step=0.3, unit="-"),
                FitParam("cylinder.cushion_factor_exhaust", 0.001, 1.0, 1.0, log=True,
                         log_step=0.3, unit="-")]
    # a transducer lag delays every measured pressure: left out, friction and areas bend to it
    lag = FitParam("effects.sensor_lag_s", 0.0, 0.05, 0.01, unit="s")
    return (*out, *CANDIDATES["leakage"].params, lag)


#: tried after the others, from their fit (starts: :data:`EXTRA_STARTS`): the chambers' heat
#: exchange and Stribeck friction (extra friction at low speed). Kept only if
#: the F-test on the effective sample size (autocorrelated residuals) gives p below
#: :data:`EXTRA_P`: with a model whose form differs from the rig's, free parameters soak up
#: the structural error and then predict worse
EXTRA_PARAMS = (
    FitParam("effects.heat_transfer_time_constant_s", 1e-3, 1e3, 1.0, log=True, log_step=1.0,
             unit="s"),
    *CANDIDATES["stribeck_friction"].params,
)
#: the extras' starts, each fitted (in parallel) from the others' fit, the best kept: heat
#: exchange from all but isothermal (1 ms) and from 1 s (slow exchange, nearly adiabatic strokes:
#: from 1 ms the fit sees no slope towards it)
EXTRA_STARTS = ({"effects.heat_transfer_time_constant_s": 1e-3, "effects.stribeck_force_n": 0.0,
                 "effects.stribeck_velocity_m_s": 0.02},
                {"effects.heat_transfer_time_constant_s": 1.0, "effects.stribeck_force_n": 0.0,
                 "effects.stribeck_velocity_m_s": 0.02})
EXTRA_P = 1e-3

#: a misfit (SSR/N) the report flags: residuals over three times the noise's, issue 17's bound
#: for a model that reproduces its data
MISFIT_FLAG = 9.0


def commissioning_protocol(truth: RigParams, known: RigParams | None = None, *,
                           t_end: float = 3.0, sample_rate_hz: float = 1000.0,
                           noise: Any = "default", seed: int = 0) -> list[MeasuredRun]:
    """The two strokes to record on a rig before planning on it, here simulated on ``truth``
    (the JSON states ``known``, the rig file): ``conventional`` (never cut) and
    ``end_stroke_cutoff`` (cut on arrival, then held to ``t_end`` [s]: the trapped air shows
    leaks and heat exchange). Noise as :func:`pneugym.data.simulate_run` (400 Pa, 0.03 mm)."""
    kw = {"t_end": t_end, "sample_rate_hz": sample_rate_hz, "noise": noise, "known": known}
    return [simulate_run(truth, [(0.0, 1)], seed=seed, name="conventional",
                         description="commissioning: conventional stroke", **kw),
            simulate_run(truth, [(0.0, 1)], cut_on_arrival=True, seed=seed + 1,
                         name="end_stroke_cutoff",
                         description="commissioning: cut off on arrival and held", **kw)]


def delay_guess(run: MeasuredRun) -> float:
    """The valve delay [s] a run shows: when its driving-port pressure first rose
    :data:`RISE_PA` above its start (less 10 ms of rise), or 0.2 s if it never did."""
    p = run.p_drive
    k = np.flatnonzero(p - np.median(p[: max(5, len(p) // 100)]) > RISE_PA)
    return max(float(run.t[k[0]]) - 0.01, 0.01) if k.size else 0.2


@dataclass
class Commissioned:
    """A rig model fitted to measured strokes: ``rig`` (the fitted rig; its substep fixed, see
    :func:`~pneugym.discrepancy.fit.fixed_step`), ``stated`` (the rig file it started from),
    the fitted ``params`` with their ``values`` (natural units) and transformed ``u``, the
    transformed covariance ``cov_u`` (Laplace: ``kappa s^2 (J^T J)^-1``), the fit's ``ssr``
    over ``n`` weighted samples, the inflation ``kappa``, and per run and channel ``nrmse``."""

    rig: RigParams
    stated: RigParams
    params: tuple[FitParam, ...]
    values: np.ndarray
    u: np.ndarray
    cov_u: np.ndarray
    ssr: float
    n: int
    kappa: float
    runs: list[str] = field(default_factory=list)
    nrmse: dict[str, dict[str, float]] = field(default_factory=dict)
    extras: list[str] = field(default_factory=list)
    #: the best fits of the other forms the strokes cannot tell from this one (:data:`FORM_DELTA`)
    alternatives: list[RigParams] = field(default_factory=list)
    alternative_misfits: list[float] = field(default_factory=list)
    #: each alternative's ``N_eff ln(SSR_form / SSR_best)`` (twice its log-likelihood deficit)
    alternative_deltas: list[float] = field(default_factory=list)
    #: whether this fit came from the further starts of a refit (``commission(refit_starts=)``)
    refitted: bool = False

    @property
    def misfit(self) -> float:
        """``SSR / N``: about 1 when the model reproduces the strokes to the noise."""
        return self.ssr / max(self.n, 1)

    def std(self) -> dict[str, float]:
        """Standard error of each fitted value (natural units, linearised)."""
        su = np.sqrt(np.clip(np.diag(self.cov_u), 0.0, None))
        return {p.path: p.dvalue_du(u) * s for p, u, s in zip(self.params, self.u, su)}

    def rig_at(self, values: Sequence[float]) -> RigParams:
        """The stated rig (fixed substep) with ``values`` of the fitted parameters."""
        return apply(self.rig_base(), self.params, values)

    def rig_base(self) -> RigParams:
        return self.stated.with_(solver={"dt_s": self.rig.solver.dt_s})

    def members(self, n: int, seed: int = 0, spread: float = 1.0,
                forms: bool = False) -> list[RigParams]:
        """``n`` plausible rigs: the fitted one, with ``forms`` the :attr:`alternatives` (other
        model forms the strokes cannot rule out), then draws from the fit's Laplace
        approximation with its standard deviations times ``spread`` (within the parameters'
        bounds; a draw the rig refuses is redrawn)."""
        if n < 1:
            raise ValueError(f"members n = {n!r} must be >= 1")
        if not (isinstance(spread, (int, float)) and 0 <= spread < math.inf):
            raise ValueError(f"members spread = {spread!r} must be a finite number >= 0")
        out = [self.rig, *(self.alternatives if forms else [])][:n]
        rng = np.random.default_rng([seed, 29])
        w, V = np.linalg.eigh(0.5 * (self.cov_u + self.cov_u.T))
        L = V * np.sqrt(np.clip(w, 0.0, None)) * spread
        lo = np.array([p.u_bounds[0] for p in self.params])
        hi = np.array([p.u_bounds[1] for p in self.params])
        tries = 0
        while len(out) < n and tries < 50 * n:
            tries += 1
            u = np.clip(self.u + L @ rng.standard_normal(len(self.params)), lo, hi)
            try:
                out.append(self.rig_at([p.from_u(x) for p, x in zip(self.params, u)]))
            except ValueError:
                continue
        return out

    # -- files -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        from .provenance import provenance

        return {"format": FORMAT, "rig": self.rig.to_dict(), "stated": self.stated.to_dict(),
                "params": [asdict(p) for p in self.params],
                "values": [float(v) for v in self.values], "u": [float(v) for v in self.u],
                "cov_u": [[float(v) for v in row] for row in self.cov_u],
                "ssr": float(self.ssr), "n": int(self.n), "kappa": float(self.kappa),
                "misfit": self.misfit, "runs": list(self.runs), "nrmse": self.nrmse,
                "extras": list(self.extras), "std": self.std(),
                "alternatives": [r.to_dict() for r in self.alternatives],
                "alternative_misfits": [float(v) for v in self.alternative_misfits],
                "alternative_deltas": [float(v) for v in self.alternative_deltas],
                "refitted": bool(self.refitted), "provenance": provenance()}

    @classmethod
    def from_dict(cls, d: Any, where: str = "commissioning") -> "Commissioned":
        """The model of :meth:`to_dict`; a malformed one is refused naming ``where``."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"{where}: not a {FORMAT} file")
        try:
            params = tuple(FitParam(**{**p, "start": tuple(p["start"]) if p.get("start")
                                       else None}) for p in d["params"])
            k = len(params)
            values, u = np.array(d["values"], float), np.array(d["u"], float)
            cov = np.array(d["cov_u"], float)
            if not (len(d.get("alternatives", [])) == len(d.get("alternative_misfits", []))
                    == len(d.get("alternative_deltas", []))):
                raise ValueError("alternatives, alternative_misfits and alternative_deltas "
                                 "must pair up")
            if values.shape != (k,) or u.shape != (k,) or cov.shape != (k, k) or not (
                    np.isfinite(values).all() and np.isfinite(u).all()
                    and np.isfinite(cov).all()):
                raise ValueError("values, u and cov_u must be finite, one per parameter")
            m = cls(rig=RigParams.from_dict(d["rig"]),
                       stated=RigParams.from_dict(d["stated"]), params=params, values=values,
                       u=u, cov_u=cov, ssr=_number(d, "ssr"), n=_count(d, "n"),
                       kappa=_number(d, "kappa"), runs=_names(d, "runs"),
                       nrmse=dict(d.get("nrmse", {})), extras=_names(d, "extras"),
                       alternatives=[RigParams.from_dict(r) for r in d.get("alternatives", [])],
                       alternative_misfits=[_number(d, "alternative_misfits", v)
                                            for v in d.get("alternative_misfits", [])],
                       alternative_deltas=[_number(d, "alternative_deltas", v, -math.inf)
                                           for v in d.get("alternative_deltas", [])],
                       refitted=_flag(d, "refitted"))
            m.rig_at(m.values)  # every parameter's path names a field of the stated rig
            return m
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None

    def save(self, out: str | Path) -> Path:
        """Write ``commissioning.json`` (the model) and ``rig.json`` (the fitted rig, a rig file
        :meth:`RigParams.load` reads) into folder ``out``; returns the folder."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "commissioning.json").write_text(json.dumps(self.to_dict(), indent=1))
        self.rig.save(out / "rig.json")
        return out

    @classmethod
    def load(cls, path: str | Path) -> "Commissioned":
        """A saved model: its folder or its ``commissioning.json``."""
        p = Path(path)
        f = p / "commissioning.json" if p.is_dir() else p
        if not f.is_file():
            raise FileNotFoundError(f"no commissioning.json at {path} (pneugym commission "
                                    f"writes one)")
        if f.stat().st_size > 10_000_000:
            raise ValueError(f"{f}: larger than 10 MB, not a commissioning file")
        try:
            d = json.loads(f.read_text(), parse_constant=_refuse_constant)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{f}: not JSON ({exc})") from None
        return cls.from_dict(d, str(f))


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number a commissioning file may hold")


def _stated_rig(runs: Sequence[MeasuredRun], base: RigParams | None) -> RigParams:
    """The rig the runs state (every run the same up to its operating point)."""
    rigs = [r.rig(base) for r in runs]
    point = ("supply_pressure_gauge_pa", "load_mass_kg")
    ref = {k: v for k, v in rigs[0].to_dict().items() if k not in point}
    for r, g in zip(runs[1:], rigs[1:]):
        if {k: v for k, v in g.to_dict().items() if k not in point} != ref:
            raise ValueError(f"run {r.name!r} states another rig than run {runs[0].name!r}: "
                             f"commission one rig at a time")
    return rigs[0]


def commission(runs: Sequence[MeasuredRun] | Sequence[str | Path], base: RigParams | None = None,
               *, starts: int = 2, max_nfev: int = 40, extras: bool = True,
               line_models: Sequence[str] | None = LINE_MODELS,
               orifice_models: Sequence[str] | None = None, seed: int = 0,
               n_jobs: int = 1, max_samples: int = MAX_SAMPLES,
               refit_starts: int = 0) -> Commissioned:
    """Fit the rig model to measured ``runs`` (objects, or files / folders of the measured-run
    format; ``base`` fills what their ``rig`` sections leave out). ``starts``: least-squares
    starts (the first at the rig file's values and the delay the runs show, the others drawn
    within the bounds) for each supply-line model of ``line_models`` (a rig file rarely says
    how its line behaves; ``None``: the stated one only), all in ``n_jobs`` processes; each line
    model's best fit is then fitted again with every other orifice law of ``orifice_models``
    (default ``None``: the stated one only; docs/policies.md says why). The best fit wins; the
    other forms the strokes cannot rule out (:data:`FORM_DELTA`) stay as
    :attr:`Commissioned.alternatives`. ``extras``: then try :data:`EXTRA_PARAMS` (kept if
    significant, :data:`EXTRA_P`). ``refit_starts``: if the finished fit's misfit exceeds
    :data:`MISFIT_FLAG` (a wrong basin, as a fit far from the rig often is), this many more
    starts per line model are drawn and fitted; if one of them ends below the best first
    start, the whole fit is finished again from all the starts, and the finished fit of lower
    SSR is kept (:attr:`Commissioned.refitted` says which).
    Raises ``ValueError`` on no runs, runs of different rigs or bad options."""
    for name, v, lo in (("starts", starts, 1), ("max_nfev", max_nfev, 1),
                        ("n_jobs", n_jobs, 1), ("max_samples", max_samples, 100),
                        ("refit_starts", refit_starts, 0)):
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
            raise ValueError(f"commission {name} = {v!r} must be an integer >= {lo}")
    runs = list(runs)
    if runs and not isinstance(runs[0], MeasuredRun):
        runs = read_runs(runs, base)
    if not runs:
        raise ValueError("commission: no runs given (record a conventional stroke and one cut "
                         "off on arrival: pneugym.commission.commissioning_protocol)")
    stated = _stated_rig(runs, base)
    lines = forms_tried(stated.line.model, line_models, LINE_MODELS, "commission line model")
    laws = forms_tried(stated.valve.flow_model, orifice_models, ORIFICE_MODELS,
                       "commission orifice law")
    prepared, _ = prepare(runs, [r.rig(base) for r in runs], max_samples)
    sigma = estimate_noise(prepared)
    params = fitted_params(stated)
    fast = tuple(replace(p, hi=FAST_AREA_FACTOR) if p.path in AREAS else p for p in params)
    rng = np.random.default_rng([seed, 31])
    first = np.array([delay_guess(runs[0]) if p.path == "valve.delay_s" else
                      p.stated(stated) if not p.path.startswith("effects") else
                      (p.start or (p.lo, p.hi))[0] for p in params])

    def drawn(k: int) -> list[np.ndarray]:  # starts within the bounds, the delay at its guess
        return [np.array([v if p.path == "valve.delay_s" else p.draw(rng)
                          for p, v in zip(params, first)]) for _ in range(k)]

    starts_u = [first] + drawn(starts - 1)
    form_rigs = {(m, o): [r.rig(base).with_(line={"model": m}, valve={"flow_model": o})
                          for r in runs] for m in lines for o in laws}
    form_bases = {f: [fixed_step(g, fast) for g in rigs] for f, rigs in form_rigs.items()}

    def first_fits(starts_u: list[np.ndarray]) -> tuple[list, list, list]:
        jobs = [Job(prepared, form_bases[m, laws[0]], sigma, fast, _inside(s, fast), max_nfev)
                for m in lines for s in starts_u]
        which = [(m, laws[0]) for m in lines for _ in starts_u]
        return past_cap(jobs, which, executor.map(solve, jobs))

    def past_cap(jobs: list, which: list, results: list) -> tuple[list, list, list]:
        # a fit on the cap goes on with the full bounds from where it ended and from its start
        capped = [i for i, r in enumerate(results) if _on_cap(jobs[i], r[0])]
        full = {i: [fixed_step(g, params) for g in form_rigs[which[i]]] for i in capped}
        again = [Job(prepared, full[i], sigma, params, _inside(x, params), max_nfev)
                 for i in capped for x in (Problem(prepared, [], sigma, fast).values(
                     results[i][0]), jobs[i].start)]
        done = executor.map(solve, again)
        for k, i in enumerate(capped):
            j = min((2 * k, 2 * k + 1), key=lambda j: done[j][1])
            jobs[i], results[i] = again[j], done[j]
        return jobs, which, results

    def finished(jobs: list, which: list, results: list) -> Commissioned:
        # each line model's best fit, again with every other orifice law (from its values)
        prob = Problem(prepared, [], sigma, fast)
        again = []
        for m in lines:
            k = min((i for i, f in enumerate(which) if f[0] == m), key=lambda i: results[i][1])
            for o in laws[1:]:
                again.append(Job(prepared, form_bases[m, o], sigma, fast,
                                 _inside(prob.values(results[k][0]), fast), max_nfev))
        # (the other laws' fits past the cap as the first ones: every form compared alike)
        jobs2, which2, results2 = past_cap(again, [(m, o) for m in lines for o in laws[1:]],
                                           executor.map(solve, again))
        return _finish(results + results2, jobs + jobs2, which + which2, stated, prepared,
                       sigma, runs, max_nfev, extras, executor)

    executor = Executor(n_jobs)
    try:
        jobs, which, results = first_fits(starts_u)
        model = finished(jobs, which, results)
        if refit_starts and model.misfit > MISFIT_FLAG:  # a wrong basin: look further
            jobs2, which2, results2 = first_fits(drawn(refit_starts))
            if min(r[1] for r in results2) < min(r[1] for r in results):
                again = finished(jobs + jobs2, which + which2, results + results2)
                if again.ssr < model.ssr:
                    model = replace(again, refitted=True)
        return model
    finally:
        executor.close()


def _number(d: dict, key: str, v: Any = None, lo: float = 0.0) -> float:
    """``d[key]`` (or ``v``, one of its items): a finite number >= ``lo``, else
    ``ValueError``."""
    v = d[key] if v is None else v
    if not (_real(v) and v >= lo):  # (the plant's test: a finite real, not a bool)
        raise ValueError(f"{key} = {v!r} must be a finite number >= {lo:g}")
    return float(v)


def _count(d: dict, key: str) -> int:
    """``d[key]``: an integer >= 1, else ``ValueError``."""
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{key} = {v!r} must be an integer >= 1")
    return v


def _names(d: dict, key: str) -> list[str]:
    """``d[key]`` (default empty): a list of strings, else ``ValueError``."""
    v = d.get(key, [])
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ValueError(f"{key} = {v!r:.80} must be a list of names")
    return list(v)


def _flag(d: dict, key: str) -> bool:
    """``d[key]`` (default false): true or false, else ``ValueError``."""
    v = d.get(key, False)
    if not isinstance(v, bool):
        raise ValueError(f"{key} = {v!r} must be true or false")
    return v


def _alternatives(results, jobs, which, best, prepared, sigma) -> tuple[list, list, list]:
    """The best fit of every form other than ``which[best]`` that the strokes cannot rule out
    (:data:`FORM_DELTA`): rigs, misfits and deltas."""
    if len(set(which)) == 1:  # one form tried: nothing to compare (and no extra simulation)
        return [], [], []
    prob = Problem(prepared, jobs[best].bases, sigma, jobs[best].params)
    _, n_eff = inflation([x for _, _, x in prob.segments(prob.values(results[best][0]))])
    ssr_best = results[best][1]
    rigs, misfits, deltas = [], [], []
    for form in dict.fromkeys(which):
        if form == which[best]:
            continue
        k = min((i for i, f in enumerate(which) if f == form), key=lambda i: results[i][1])
        ssr = results[k][1]
        delta = form_delta(ssr, ssr_best, n_eff)
        if delta < FORM_DELTA:  # (a failed fit's inf / nan is not)
            p = Problem(prepared, jobs[k].bases, sigma, jobs[k].params)
            rigs.append(apply(jobs[k].bases[0], p.params, p.values(results[k][0])))
            misfits.append(float(ssr) / max(prob.n, 1))
            deltas.append(float(delta))
    return rigs, misfits, deltas


def _finish(results, jobs, which, stated, prepared, sigma, runs, max_nfev, extras,
            executor) -> Commissioned:
    """The best of the first fits (none on the area cap), then with :data:`EXTRA_PARAMS` if
    they are significant; the forms it cannot rule out beside it."""
    best = int(np.argmin([r[1] for r in results]))
    form, bases, first = which[best], jobs[best].bases, jobs[best].params
    alternatives, alt_misfits, alt_deltas = _alternatives(results, jobs, which, best,
                                                          prepared, sigma)
    stated = stated.with_(line={"model": form[0]}, valve={"flow_model": form[1]})
    u, ssr, jac, _ = results[best]  # (no fit ends on the area cap: past_cap went on with it)
    prob = Problem(prepared, bases, sigma, first)
    used: list[str] = []
    if extras:
        big = prob.params + EXTRA_PARAMS
        tries = executor.map(solve, [Job(prepared, bases, sigma, big, _inside(np.concatenate(
            [prob.values(u), [st[p.path] for p in EXTRA_PARAMS]]), big), max_nfev)
            for st in EXTRA_STARTS])
        u2, ssr2, jac2, _ = min(tries, key=lambda r: r[1])
        _, n_eff = inflation([x for _, _, x in prob.segments(prob.values(u))])
        _, p_value = f_test(ssr, ssr2, len(EXTRA_PARAMS), len(big), n_eff)
        if p_value < EXTRA_P:
            u, ssr, jac = u2, ssr2, jac2
            prob = Problem(prepared, bases, sigma, big)
            used = [p.path for p in EXTRA_PARAMS]
    params = prob.params
    values = prob.values(u)
    segments = [s for _, _, s in prob.segments(values)]
    kappa, _ = inflation(segments)
    cov = _covariance(jac, ssr, prob.n, kappa)
    sims = prob.simulate(values)
    return Commissioned(
        rig=apply(bases[0], params, values), stated=stated, params=params, values=values, u=u,
        cov_u=cov, ssr=float(ssr), n=prob.n, kappa=float(kappa), runs=[r.name for r in runs],
        nrmse={r.name: nrmse([r], [s]) for r, s in zip(prepared, sims)}, extras=used,
        alternatives=alternatives, alternative_misfits=alt_misfits,
        alternative_deltas=alt_deltas)


def _on_cap(job: Job, u: np.ndarray) -> bool:
    """Whether a fit with the first fits' area cap (:data:`FAST_AREA_FACTOR`) ended on it."""
    return any(p.path in AREAS and p.hi == FAST_AREA_FACTOR and p.from_u(x) >= 0.99 * p.hi
               for p, x in zip(job.params, u))


def _inside(values: np.ndarray, params: Sequence[FitParam]) -> np.ndarray:
    return np.array([min(max(float(v), p.lo), p.hi) for v, p in zip(values, params)])


def _covariance(jac: np.ndarray, ssr: float, n: int, kappa: float) -> np.ndarray:
    """``kappa s^2 (J^T J)^-1`` in the transformed variables (pseudo-inverse: directions the
    strokes do not show get the floor of a millionth of the best-shown one's information)."""
    p = jac.shape[1]
    s2 = ssr / max(n - p, 1)
    w, V = np.linalg.eigh(jac.T @ jac)
    w = np.maximum(w, max(float(w.max()), 1e-300) * 1e-6)
    return kappa * s2 * (V / w) @ V.T


# -- the command --------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="pneugym commission",
        description="Fit a model of one rig to a few of its measured strokes (a conventional "
                    "one and one cut off on arrival and held), for the model-predictive cut-off "
                    "mpc-rig.",
        epilog="examples:\n  pneugym commission measured/ --out commissioned/\n"
               "  pneugym evaluate --rig commissioned/rig.json --policies mpc_mine=commissioned/"
               " --suite points",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="measured runs (pneugym-measurement/1 JSON files or "
                                            "folders of them)")
    ap.add_argument("--rig", default=None, help="rig file filling what the runs' rig sections "
                                                "leave out")
    ap.add_argument("--out", required=True, help="output folder (commissioning.json, rig.json, "
                                                 "report.md, fit.png)")
    ap.add_argument("--starts", type=int, default=2, help="least-squares starts (default 2)")
    ap.add_argument("--max-nfev", type=int, default=40,
                    help="least-squares iterations per start and restart (default 40)")
    ap.add_argument("--refit-starts", type=int, default=4, metavar="N",
                    help="if the fit's misfit exceeds 9, N more starts per line model, the "
                         "better fit kept (default 4, as mpc-rig's; 0: none)")
    ap.add_argument("--jobs", type=int, default=1, help="processes for the starts (default 1)")
    ap.add_argument("--line-models", nargs="+", default=list(LINE_MODELS), choices=LINE_MODELS,
                    help="supply-line models to try; the best fit wins (default: both)")
    ap.add_argument("--orifice-models", nargs="+", default=None, choices=ORIFICE_MODELS,
                    help="orifice laws to try, each from each line model's best fit; the best "
                         "fit wins (default: the stated one, the rig file's or 'thesis')")
    ap.add_argument("--no-extras", action="store_true",
                    help="do not try heat exchange and Stribeck friction")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the starts drawn within the bounds (default 0)")
    ap.add_argument("--no-plots", action="store_true", help="no fit.png")
    return ap


def report_markdown(m: Commissioned) -> str:
    """A human summary of a commissioned model."""
    std = m.std()
    lines = ["# Commissioned rig model", "",
             f"Runs: {', '.join(m.runs)}. Misfit SSR/N = {m.misfit:.2f} (about 1 when the model "
             f"reproduces the strokes to the noise; inflation kappa {m.kappa:.1f}); supply line "
             f"modelled as {m.stated.line.model!r}, orifices by the "
             f"{m.stated.valve.flow_model!r} law.", "",
             "| parameter | stated | fitted | ± (1 s.e.) |", "|---|---|---|---|"]
    for p, v in zip(m.params, m.values):  # a relative parameter: its factor times the stated
        stated = (m.stated.valve_delay_s if p.path == "valve.delay_s"
                  else read(m.stated, p.path))
        scale = stated if p.relative else 1.0
        lines.append(f"| {p.path} | {stated:.4g} | {v * scale:.4g} | {std[p.path] * scale:.2g} |")
    lines += ["", "NRMSE per run and channel:", ""]
    for run, ch in m.nrmse.items():
        lines.append(f"- {run}: " + ", ".join(f"{k} {v:.4f}" for k, v in ch.items()))
    if m.extras:
        lines += ["", f"Kept beyond the base set: {', '.join(m.extras)}."]
    if m.refitted:
        lines += ["", f"Fitted again from further starts (the first ones ended above a misfit "
                  f"of {MISFIT_FLAG:g}); this fit is the better one."]
    if m.alternatives:
        forms = ", ".join(f"{r.line.model!r} line with the {r.valve.flow_model!r} law (misfit "
                          f"{v:.2f})" for r, v in zip(m.alternatives, m.alternative_misfits))
        lines += ["", f"The strokes cannot rule out: {forms}. Strokes at other operating "
                  f"points (a low supply pressure, where the orifice laws part most) may tell "
                  f"them apart."]
    if not m.misfit <= MISFIT_FLAG:
        lines += ["", f"**The misfit exceeds {MISFIT_FLAG:g}**: the residuals are over three "
                  f"times the noise's. Check the runs and the rig file, and fit again with more "
                  f"`--starts` (or `--refit-starts`). `mpc-rig` still plans on it "
                  f"(docs/policies.md)."]
    return "\n".join(lines) + "\n"


def write_plot(m: Commissioned, runs: Sequence[MeasuredRun], path: Path) -> Path:
    """Measured against modelled position and port pressures of every run (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .discrepancy.residuals import replay

    fig, axes = plt.subplots(len(runs), 2, figsize=(10, 3.2 * len(runs)), squeeze=False)
    for (ax_x, ax_p), run in zip(axes, runs):
        sim = replay(run, m.rig.with_(supply_pressure_gauge_pa=run.rig().supply_pressure_gauge_pa,
                                      load_mass_kg=run.rig().load_mass_kg))
        ax_x.plot(run.t, run.x * 1e3, ".", ms=1, color="0.6", label="measured")
        ax_x.plot(run.t, sim["x"] * 1e3, color="C0", label="model")
        ax_x.set(title=f"{run.name}: position", xlabel="t [s]", ylabel="x [mm]")
        for c, col in (("p_drive", "C1"), ("p_exhaust", "C2")):
            ax_p.plot(run.t, getattr(run, c) / 1e5, ".", ms=1, color="0.6")
            ax_p.plot(run.t, sim[c] / 1e5, color=col, label=c)
        ax_p.set(title=f"{run.name}: port pressures (gauge)", xlabel="t [s]", ylabel="p [bar]")
        ax_x.legend(loc="lower right")
        ax_p.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    from .outputs import check_output_dir
    from .rigfile import as_rig

    try:
        check_output_dir(a.out, "--out")  # before the fit, not after it
        base = as_rig(a.rig) if a.rig else None
        runs = read_runs(a.runs, base)
        m = commission(runs, base, starts=a.starts, max_nfev=a.max_nfev,
                       extras=not a.no_extras, line_models=a.line_models,
                       orifice_models=a.orifice_models, seed=a.seed,
                       n_jobs=a.jobs, refit_starts=a.refit_starts)
    except (ValueError, OSError) as exc:
        print(f"pneugym commission: {exc}", file=sys.stderr)
        return 2
    out = m.save(a.out)
    (out / "report.md").write_text(report_markdown(m))
    if not a.no_plots:
        write_plot(m, runs, out / "fit.png")
    print(report_markdown(m))
    print(f"wrote {out}/commissioning.json, rig.json, report.md"
          + ("" if a.no_plots else ", fit.png"))
    return 0 if math.isfinite(m.ssr) else 1


if __name__ == "__main__":
    sys.exit(main())
