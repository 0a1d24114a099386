"""Statistics for the decision: effective sample size of autocorrelated residuals, the nested
F-test and likelihood-ratio test corrected with it, parameter standard errors."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats


def effective_sample_size(r: np.ndarray) -> float:
    """Effective number of independent samples of a residual series ``r``.

    ``N_eff = N / (1 + 2 sum_k rho_k)``, the autocorrelations ``rho_k`` summed over the initial
    positive sequence (Geyer 1992: up to the first lag where the sum of a pair of consecutive
    autocorrelations turns negative). White noise gives ``N_eff ~ N``, an AR(1) series with
    coefficient ``phi`` gives ``N (1 - phi) / (1 + phi)``; clipped to ``[1, N]``."""
    r = np.asarray(r, float)
    n = r.size
    if n < 4:
        return float(max(n, 1))
    r = r - r.mean()
    v = float(r @ r)
    if v <= 0.0:
        return float(n)
    m = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(r, m)
    acf = np.fft.irfft(f * np.conj(f), m)[:n] / v
    tau = -1.0  # 1 + 2 sum_{k>=1} rho_k  =  -rho_0 + 2 sum_{k>=0} rho_k
    for k in range(0, n - 1, 2):
        pair = acf[k] + acf[k + 1]
        if pair <= 0.0:
            break
        tau += 2.0 * pair
    tau = max(tau, 1.0 / n)
    return float(min(max(n / tau, 1.0), n))


def inflation(segments: Sequence[np.ndarray]) -> tuple[float, float]:
    """Variance inflation ``kappa`` and effective size of a set of residual segments (one per
    run and channel). ``kappa`` is the SSR-weighted mean of the segments' ``N / N_eff``, so the
    segments that carry the misfit set it; returns ``(kappa, N / kappa)``."""
    ssr = np.array([float(s @ s) for s in segments])
    ns = np.array([s.size for s in segments], float)
    k = np.array([n / effective_sample_size(s) for s, n in zip(segments, ns)])
    kappa = float((ssr * k).sum() / ssr.sum()) if ssr.sum() > 0 else 1.0
    return kappa, float(ns.sum() / kappa)


#: Akaike margin between two model forms with the same parameters: a form fits clearly better
#: than another when ``N_eff ln(SSR_other / SSR_form) >= FORM_DELTA`` (the other's Akaike
#: weight is then under 5 % of its own); closer, the runs cannot tell the two apart
FORM_DELTA = 6.0


def form_delta(ssr: float, ssr_best: float, n_eff: float) -> float:
    """``N_eff ln(SSR / SSR_best)``: how much worse a form's fit is than the best's (Akaike
    difference at equal parameter counts; a failed fit's inf / nan compares as inf)."""
    d = n_eff * np.log(max(ssr, 1e-300) / max(ssr_best, 1e-300))
    return float(d) if np.isfinite(d) else float("inf")


def f_test(ssr0: float, ssr1: float, p_extra: int, p_total: int, n_eff: float) -> tuple[float, float]:
    """Nested-model F-test with an effective sample size: ``F = (SSR0 - SSR1)/p / (SSR1/(N_eff - P))``.

    Returns ``(F, p_value)``; a worse or equal fit gives ``(0, 1)``, an exact fit of a misfit
    (``SSR1 = 0 < SSR0``: noise-free data) ``(inf, 0)``."""
    dof = max(n_eff - p_total, 1.0)
    if ssr0 <= ssr1:
        return 0.0, 1.0
    if ssr1 <= 0:
        return float("inf"), 0.0
    F = (ssr0 - ssr1) / p_extra / (ssr1 / dof)
    return float(F), float(stats.f.sf(F, p_extra, dof))


def lr_test(ssr0: float, ssr1: float, n_eff: float, dof: int = 1) -> tuple[float, float]:
    """Likelihood-ratio statistic ``N_eff ln(SSR0 / SSR1)`` for two fixed predictions of the same
    data (e.g. a held-out run) and its chi-square p-value with ``dof`` degrees of freedom; an
    exact prediction of a misfit (``SSR1 = 0 < SSR0``) gives ``(inf, 0)``."""
    if ssr0 <= ssr1:
        return 0.0, 1.0
    if ssr1 <= 0:
        return float("inf"), 0.0
    s = n_eff * float(np.log(ssr0 / ssr1))
    return s, float(stats.chi2.sf(s, dof))


def separation(ssr_a: float, ssr_b: float, n_eff: float) -> tuple[float, float]:
    """How clearly the better of two fits (``ssr_a`` <= ``ssr_b``) beats the other:
    ``N_eff ln(SSR_b / SSR_a)`` and its chi-square p-value (1 dof); an exact fit is separated
    from the other unless that fits exactly too."""
    if ssr_a > 0:
        stat = n_eff * float(np.log(ssr_b / ssr_a))
    else:
        stat = float("inf") if ssr_b > 0 else 0.0
    return stat, float(stats.chi2.sf(stat, 1))


def standard_errors(jac: np.ndarray, ssr: float, n: int, kappa: float) -> np.ndarray:
    """Standard errors of the fitted (transformed) variables from the weighted residuals'
    Jacobian: ``sqrt(diag(kappa s^2 (J^T J)^-1))``, ``s^2 = SSR / (N - P)``; the inflation
    ``kappa`` accounts for autocorrelated residuals. Unidentified directions get ``inf``."""
    p = jac.shape[1]
    s2 = ssr / max(n - p, 1)
    jtj = jac.T @ jac
    try:
        w, V = np.linalg.eigh(jtj)
    except np.linalg.LinAlgError:
        return np.full(p, np.inf)
    tol = max(float(w.max()), 0.0) * 1e-12
    good = w > tol
    var = (V[:, good] ** 2) @ (1.0 / w[good])
    var[(V[:, ~good] ** 2).sum(axis=1) > 1e-6] = np.inf
    return np.sqrt(kappa * s2 * var)


def ar_whitener(r: np.ndarray, max_order: int = 5) -> np.ndarray:
    """Whitening filter of an autoregressive model of the residual series ``r``.

    Fits ``r_t = a_1 r_{t-1} + ... + a_p r_{t-p} + e_t`` by least squares for every order
    ``p <= max_order`` (on the same samples) and keeps the order with the lowest BIC; returns
    ``[1, -a_1, ..., -a_p]``, the FIR filter whose output is ``e`` (:func:`whiten`). Series
    shorter than ``8 * (max_order + 1)`` samples get the orders they can carry."""
    r = np.asarray(r, float)
    pmax = int(min(max_order, max(r.size // 8 - 1, 0)))
    if pmax == 0:
        return np.ones(1)
    y = r[pmax:]
    n = y.size
    lags = np.column_stack([r[pmax - k:r.size - k] for k in range(1, pmax + 1)])
    best, coef = n * np.log(max(float(y @ y) / n, 1e-300)), np.zeros(0)
    for p in range(1, pmax + 1):
        a, *_ = np.linalg.lstsq(lags[:, :p], y, rcond=None)
        e = y - lags[:, :p] @ a
        bic = n * np.log(max(float(e @ e) / n, 1e-300)) + p * np.log(n)
        if bic < best:
            best, coef = bic, a
    return np.concatenate([[1.0], -coef])


def whiten(x: np.ndarray, filt: np.ndarray) -> np.ndarray:
    """``x`` (a series, or the rows of a matrix) through the FIR whitening filter ``filt`` of
    :func:`ar_whitener`, its first ``len(filt) - 1`` samples (the filter's start-up) dropped."""
    x = np.asarray(x, float)
    p = len(filt) - 1
    out = filt[0] * x[p:]
    for k in range(1, p + 1):
        out = out + filt[k] * x[p - k:x.shape[0] - k]
    return out
