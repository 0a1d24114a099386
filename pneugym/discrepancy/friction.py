"""Friction-only path of the workflow: measured friction force against piston velocity.

The real-data case of issue 5 is thesis Table 5.1 (:data:`TABLE_5_1`): 16 friction forces, the
first the breakaway force at rest, the others at steady velocities 0.01-0.25 m/s. The model is
the plant's own friction law, :func:`pneugym.physics.cylinder.friction_force` (sliding:
``C + Kv v`` plus the optional Stribeck term ``F_str exp(-(v/v_str)^2)``) and the static
(breakaway) force ``Fs`` of the Karnopp stick model. Two readings of the thesis's model:

- ``static="breakaway"``: the v = 0 row is the breakaway force ``Fs`` (a free parameter); the
  moving rows follow the sliding law. This is the plant's model.
- ``static="curve"``: the whole table is one friction-velocity curve (as thesis Fig. 5.4 plots
  it): every row, v = 0 included, follows the sliding law.

The nominal model is fitted first (``Fs``, ``C``, ``Kv``), then ``stribeck_friction`` jointly;
the decision uses the checks of :class:`~pneugym.discrepancy.Discrepancy` with leave-one-out
cross-validation in place of a held-out run and the effective sample size of the residuals in
velocity order.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..physics.cylinder import friction_force
from .candidates import CANDIDATES, FitParam
from .stats import effective_sample_size, f_test, standard_errors

#: Thesis Table 5.1: piston velocity [m/s], driving-chamber force [N], exhaust-chamber force [N],
#: piston friction force [N] (averages of two runs; the v = 0 row is the breakaway force).
TABLE_5_1 = np.array([
    [0.000, 359, 359, 359], [0.010, 1249, 1133, 115], [0.014, 1224, 1087, 137],
    [0.019, 1235, 1087, 148], [0.048, 1408, 1145, 263], [0.072, 1146, 844, 302],
    [0.101, 902, 682, 220], [0.130, 879, 636, 243], [0.134, 1249, 879, 370],
    [0.154, 903, 474, 428], [0.173, 868, 497, 370], [0.202, 1064, 636, 428],
    [0.226, 1041, 613, 428], [0.235, 1422, 995, 428], [0.240, 1411, 844, 567],
    [0.250, 1758, 1191, 567]], dtype=float)
#: The thesis's friction parameters (5.6): Fs, C, Kv.
THESIS_FRICTION = {"static_n": 359.0, "coulomb_n": 126.0, "viscous_n_s_per_m": 1557.0}
#: velocity bands for localisation [m/s]: (name, lo, hi), hi exclusive
BANDS = (("at rest (v = 0)", 0.0, 1e-9), ("low, 0 < v < 0.03", 1e-9, 0.03),
         ("mid, 0.03 <= v < 0.15", 0.03, 0.15), ("high, v >= 0.15", 0.15, np.inf))


def friction_model(v: np.ndarray, static_n: float, coulomb_n: float, viscous_n_s_per_m: float,
                   stribeck_force_n: float = 0.0, stribeck_velocity_m_s: float = 0.01,
                   static: str = "breakaway") -> np.ndarray:
    """Friction force [N] at velocities ``v`` [m/s] (>= 0), computed by the plant's kernel.

    With ``static="breakaway"`` the force at ``v == 0`` is the breakaway force ``static_n``."""
    out = np.array([friction_force(float(x), 1.0, coulomb_n, viscous_n_s_per_m, stribeck_force_n,
                                   stribeck_velocity_m_s) for x in np.asarray(v, float)])
    if static == "breakaway":
        out[np.asarray(v) == 0.0] = static_n
    return out


@dataclass
class FrictionFit:
    params: dict[str, float]
    residual_n: np.ndarray
    ssr: float
    jac: np.ndarray
    u: np.ndarray
    n_params: int


@dataclass
class FrictionDiscrepancy:
    """Friction-only discrepancy workflow on force-velocity data (default: thesis Table 5.1).

    ``fit()`` calibrates the nominal model, localises the residuals by velocity band, fits the
    Stribeck candidate (multi-start), applies the checks and names ``stribeck_friction`` or
    ``none``. Results are attributes ending in ``_`` and :meth:`report_dict`."""

    velocity_m_s: np.ndarray = field(default_factory=lambda: TABLE_5_1[:, 0].copy())
    force_n: np.ndarray = field(default_factory=lambda: TABLE_5_1[:, 3].copy())
    static: str = "breakaway"
    alpha: float = 0.01
    min_improvement: float = 0.1
    z_min: float = 3.0
    n_starts: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        self.velocity_m_s = np.asarray(self.velocity_m_s, float)
        self.force_n = np.asarray(self.force_n, float)
        if self.velocity_m_s.shape != self.force_n.shape or self.velocity_m_s.size < 6:
            raise ValueError("velocity_m_s and force_n need the same length (at least 6 points)")
        if not (np.isfinite(self.velocity_m_s).all() and np.isfinite(self.force_n).all()) \
                or (self.velocity_m_s < 0).any():
            raise ValueError("velocities must be finite and >= 0, and forces finite")
        if self.static not in ("breakaway", "curve"):
            raise ValueError("static must be 'breakaway' or 'curve'")
        order = np.argsort(self.velocity_m_s, kind="stable")
        self.velocity_m_s, self.force_n = self.velocity_m_s[order], self.force_n[order]

    # -- parameters ---------------------------------------------------------------------
    def _params(self, stribeck: bool) -> tuple[FitParam, ...]:
        nom = (FitParam("friction.static_n", 1.0, 5000.0, 359.0, log=True, log_step=0.1, unit="N"),
               FitParam("friction.coulomb_n", 0.0, 2000.0, 100.0, unit="N"),
               FitParam("friction.viscous_n_s_per_m", 0.0, 2e4, 1000.0, unit="N s/m"))
        if self.static == "curve":
            nom = nom[1:]  # no breakaway parameter: v = 0 follows the sliding law
        return nom + (CANDIDATES["stribeck_friction"].params if stribeck else ())

    def _predict(self, params, vals, v) -> np.ndarray:
        kw = {p.name: float(x) for p, x in zip(params, vals)}
        kw.setdefault("static_n", 0.0)
        return friction_model(v, static=self.static, **kw)

    def _fit(self, stribeck: bool, mask: np.ndarray | None = None, rng=None) -> FrictionFit:
        params = self._params(stribeck)
        m = np.ones(self.force_n.size, bool) if mask is None else mask
        v, F = self.velocity_m_s[m], self.force_n[m]
        lo = np.array([p.u_bounds[0] for p in params])
        hi = np.array([p.u_bounds[1] for p in params])
        rng = rng or np.random.default_rng(self.seed)
        A = np.c_[np.ones(int((v > 0).sum())), v[v > 0]]
        c0, k0 = np.linalg.lstsq(A, F[v > 0], rcond=None)[0] if A.shape[0] >= 2 else (100.0, 1000.0)
        base = {"static_n": float(F[v == 0].mean()) if (v == 0).any() else 359.0,
                "coulomb_n": max(float(c0), 1.0), "viscous_n_s_per_m": max(float(k0), 1.0)}
        best = None
        for k in range(self.n_starts if stribeck else 1):
            start = dict(base)
            for p in params[len(params) - (2 if stribeck else 0):]:
                start[p.name] = CANDIDATES["stribeck_friction"].typical[p.name] if k == 0 else p.draw(rng)
            u0 = np.clip([p.to_u(start[p.name]) for p in params], lo + 1e-9, hi - 1e-9)
            sol = least_squares(lambda u: F - self._predict(params, [p.from_u(x) for p, x in zip(params, u)], v),
                                u0, bounds=(lo, hi), diff_step=1e-4)
            if best is None or sol.cost < best.cost:
                best = sol
        vals = [p.from_u(x) for p, x in zip(params, best.x)]
        return FrictionFit({p.name: float(x) for p, x in zip(params, vals)},
                           F - self._predict(params, vals, v), float(2 * best.cost), best.jac, best.x,
                           len(params))

    # -- workflow -------------------------------------------------------------------------
    def fit(self) -> FrictionDiscrepancy:
        v, F = self.velocity_m_s, self.force_n
        n = F.size
        thesis = friction_model(v, static=self.static, **THESIS_FRICTION)
        self.thesis_residual_n_ = F - thesis
        self.nominal_ = self._fit(False)
        self.stribeck_ = self._fit(True)
        r0, r1 = self.nominal_.residual_n, self.stribeck_.residual_n
        self.bands_ = []
        for name, lo, hi in BANDS:
            m = (v >= lo) & (v < hi)
            if m.any():
                self.bands_.append({"band": name, "points": int(m.sum()),
                                    "rms_thesis_n": _rms(self.thesis_residual_n_[m]),
                                    "rms_nominal_n": _rms(r0[m]), "rms_stribeck_n": _rms(r1[m])})
        self.worst_band_ = max(self.bands_, key=lambda b: b["rms_nominal_n"])["band"]
        # checks
        p_extra = 2
        self.n_eff_ = effective_sample_size(r1)
        self.F_, self.p_value_ = f_test(self.nominal_.ssr, self.stribeck_.ssr, p_extra,
                                        self.stribeck_.n_params, self.n_eff_)
        self.F_white_, self.p_value_white_ = f_test(self.nominal_.ssr, self.stribeck_.ssr, p_extra,
                                                    self.stribeck_.n_params, float(n))
        params = self._params(True)
        se_u = standard_errors(self.stribeck_.jac, self.stribeck_.ssr, n, n / self.n_eff_)
        self.stderr_, self.z_, self.at_bound_ = {}, {}, []
        for p, u, s in zip(params, self.stribeck_.u, se_u):
            if not p.path.startswith("effects."):
                continue
            se = float(s * p.dvalue_du(u))
            self.stderr_[p.name] = se
            lo, hi = p.u_bounds
            on_lo, on_hi = u - lo <= 1e-3 * (hi - lo), hi - u <= 1e-3 * (hi - lo)
            if p.null is not None:
                self.z_[p.name] = abs(p.from_u(u) - p.null) / se if se > 0 else float("inf")
                if on_hi:
                    self.at_bound_.append(p.name)
            elif on_lo or on_hi:
                self.at_bound_.append(p.name)
        # leave-one-out cross-validation (the held-out check of a table)
        rng = np.random.default_rng(self.seed)
        loo0, loo1 = np.empty(n), np.empty(n)
        for i in range(n):
            m = np.arange(n) != i
            for fit_s, out in ((False, loo0), (True, loo1)):
                f = self._fit(fit_s, m, rng)
                out[i] = F[i] - self._predict(self._params(fit_s), list(f.params.values()), v[i:i + 1])[0]
        self.loo_residual_n_ = {"nominal": loo0, "stribeck": loo1}
        self.improvement_ = 1.0 - self.stribeck_.ssr / self.nominal_.ssr
        self.loo_improvement_ = 1.0 - float(loo1 @ loo1) / float(loo0 @ loo0)
        self.checks_ = {
            "significant": bool(self.p_value_ < self.alpha),
            "material": bool(self.improvement_ >= self.min_improvement),
            "away_from_null": bool(self.z_.get("stribeck_force_n", 0.0) >= self.z_min),
            "not_on_bound": not self.at_bound_,
            "resolved": bool(np.isfinite(list(self.stderr_.values())).all()),
            "improves_holdout": bool(self.loo_improvement_ >= 0.5 * self.min_improvement),
        }
        self.named_effect_ = "stribeck_friction" if all(self.checks_.values()) else "none"
        return self

    def report_dict(self) -> dict:
        """The result as JSON-able data."""
        return {
            "static": self.static, "named_effect": self.named_effect_, "checks": self.checks_,
            "thesis_params": THESIS_FRICTION, "nominal_params": self.nominal_.params,
            "stribeck_params": self.stribeck_.params, "stribeck_stderr": self.stderr_,
            "z": self.z_, "at_bound": self.at_bound_,
            "rms_n": {"thesis": _rms(self.thesis_residual_n_), "nominal": _rms(self.nominal_.residual_n),
                      "stribeck": _rms(self.stribeck_.residual_n)},
            "ssr_improvement": self.improvement_, "F": self.F_, "p_value": self.p_value_,
            "n_eff": self.n_eff_, "p_value_white": self.p_value_white_,
            "loo_rms_n": {k: _rms(r) for k, r in self.loo_residual_n_.items()},
            "loo_improvement": self.loo_improvement_, "bands": self.bands_,
            "worst_band": self.worst_band_,
            "points": [{"v_m_s": float(a), "force_n": float(b), "residual_nominal_n": float(c),
                        "residual_stribeck_n": float(d)}
                       for a, b, c, d in zip(self.velocity_m_s, self.force_n, self.nominal_.residual_n,
                                             self.stribeck_.residual_n)],
        }


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(r) ** 2)))
