"""Rayleigh mixture of clutter amplitudes: EM fit and the CFAR threshold (seed 002, eq 3-6, 14).

Zhang, Lu, Xiang, Yuan 2023 (docs/references.md, ``zhang2023``) model the clutter amplitude
``A`` of high-resolution SAR by a mixture of ``M_a`` Rayleigh laws (eq 3-4)::

    f(A) = sum_k w_k A / lambda_k^2 exp(-A^2 / (2 lambda_k^2)),
    F(A) = 1 - sum_k w_k exp(-A^2 / (2 lambda_k^2)).

With the intensity ``I = A^2`` and ``s_k = 2 lambda_k^2`` (the k-th component's mean intensity)
this is a mixture of exponential laws of ``I``: ``P(I > t) = sum_k w_k exp(-t / s_k)``. Every
function here works on intensities and scales ``s_k``; amplitudes are ``sqrt`` of them.

Fit (eq 5-6). The paper estimates the weights as the histogram mass of each component's
interval (eq 5) and the scales by maximum likelihood inside it (eq 6: lambda_k^2 = sum H_j j^2 /
(2 sum H_j)). We start from exactly that hard partition (the sorted sample cut into ``M_a``
intervals of equal counts) and refine it by EM, whose M-step is eq 5-6 with soft memberships:
``w_k = mean_i r_ik``, ``s_k = sum_i r_ik I_i / sum_i r_ik``. As in eq 5, the E-step runs on a
histogram: the sample is binned on ``ln I`` (``BIN_WIDTH`` wide bins, relative to the sample
mean), each bin keeps its count and the exact sum of its intensities, so the M-step uses
exact sufficient statistics and only the responsibilities are taken at the bin mean (this is
what makes one fit per target superpixel cheap). ``bin_width=0`` runs the plain per-sample EM.

Threshold (eq 14). ``1 - F(T) = PFA`` is solved for ``t = T^2`` on a proven bracket by a
safeguarded Newton iteration on ``ln G(t) - ln PFA`` (``G(t) = sum_k w_k exp(-t/s_k)`` is
decreasing and log-convex): ``G(t) <= exp(-t / s_max)`` gives ``t_hi = s_max ln(1/PFA)``, and
``G(t) >= w_k exp(-t / s_k)`` gives ``t_lo = max(0, max_k s_k ln(w_k / PFA))``.
:func:`mixture_threshold_brentq` is the same root by :func:`scipy.optimize.brentq` (reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

#: Width of the ln-intensity bins of the histogram EM (eq 5's histogram).
BIN_WIDTH = 0.1
#: Bins span ln(I / mean) in [BIN_LO, BIN_LO + N_BINS * BIN_WIDTH); values outside go to the end bins.
BIN_LO = -16.0
N_BINS = 400
#: Relative change of the log-likelihood below which EM stops.
EM_TOL = 1e-9
#: Smallest component scale relative to the sample mean (a component on exact zeros).
SCALE_FLOOR = 1e-12


@dataclass(frozen=True)
class RayleighMixture:
    """Weights ``w`` and intensity scales ``s = 2 lambda^2`` (eq 3-4), components by increasing scale."""

    weights: np.ndarray
    scales: np.ndarray
    iterations: int

    @property
    def lambdas(self) -> np.ndarray:
        """The Rayleigh scale parameters lambda_k of eq 3 (amplitude units)."""
        return np.sqrt(self.scales / 2.0)

    def sf(self, amplitude) -> np.ndarray:
        """``1 - F(A)`` (eq 4)."""
        t = np.asarray(amplitude, np.float64) ** 2
        return np.sum(self.weights * np.exp(-t[..., None] / self.scales), axis=-1)


@njit(cache=True, nogil=True)
def _log_tail(t, w, s):
    """ln G(t) and d ln G / dt for G(t) = sum w_k exp(-t / s_k) (log-sum-exp)."""
    m = -np.inf
    for k in range(w.size):
        if w[k] > 0.0:
            v = math.log(w[k]) - t / s[k]
            if v > m:
                m = v
    acc = 0.0
    dacc = 0.0
    for k in range(w.size):
        if w[k] > 0.0:
            e = math.exp(math.log(w[k]) - t / s[k] - m)
            acc += e
            dacc -= e / s[k]
    return m + math.log(acc), dacc / acc


@njit(cache=True, nogil=True)
def threshold_intensity(w, s, pfa):
    """``t`` with ``sum_k w_k exp(-t / s_k) = pfa`` (eq 14 in intensity, ``T_cfar = sqrt(t)``):
    safeguarded Newton on ln G(t) - ln pfa inside the proven bracket (module docstring)."""
    smax = 0.0
    lo = 0.0
    for k in range(w.size):
        if w[k] > 0.0:
            if s[k] > smax:
                smax = s[k]
            if w[k] > pfa:
                v = s[k] * math.log(w[k] / pfa)
                if v > lo:
                    lo = v
    hi = smax * math.log(1.0 / pfa)
    if hi <= lo:
        return hi
    lp = math.log(pfa)
    t = 0.5 * (lo + hi)
    for _ in range(200):
        g, dg = _log_tail(t, w, s)
        f = g - lp
        if f > 0.0:
            lo = t
        else:
            hi = t
        if f == 0.0 or hi - lo <= 4e-16 * hi:
            return t
        tn = t - f / dg if dg < 0.0 else 0.5 * (lo + hi)
        if not (lo < tn < hi):
            tn = 0.5 * (lo + hi)
        if abs(tn - t) <= 1e-15 * t:
            return tn
        t = tn
    return t


def mixture_threshold(weights, scales, pfa: float) -> float:
    """The amplitude threshold ``T_cfar`` with ``1 - F(T_cfar) = pfa`` (eq 14)."""
    w = np.ascontiguousarray(weights, np.float64)
    s = np.ascontiguousarray(scales, np.float64)
    return math.sqrt(threshold_intensity(w, s, float(pfa)))


def mixture_threshold_brentq(weights, scales, pfa: float) -> float:
    """Reference for :func:`mixture_threshold`: the same root by ``scipy.optimize.brentq``."""
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    w = np.asarray(weights, np.float64)
    s = np.asarray(scales, np.float64)
    keep = w > 0
    w, s = w[keep], s[keep]
    lo = max(0.0, float(np.max(s * np.log(np.maximum(w, 1e-300) / pfa))))
    hi = float(s.max() * np.log(1.0 / pfa))

    def f(t):
        a = np.log(w) - t / s
        m = a.max()
        return m + np.log(np.exp(a - m).sum()) - np.log(pfa)

    if hi <= lo:
        return math.sqrt(hi)
    if f(lo) <= 0.0:  # the bound is the root to rounding (one component dominates the tail)
        return math.sqrt(lo)
    if f(hi) >= 0.0:
        return math.sqrt(hi)
    return math.sqrt(optimize.brentq(f, lo, hi, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500))


@njit(cache=True, nogil=True)
def _bin(vals, mean, width, counts, sums):
    nb = counts.size
    for i in range(vals.size):
        v = vals[i]
        if v > 0.0:
            b = int(math.floor((math.log(v / mean) - BIN_LO) / width))
            if b < 0:
                b = 0
            elif b >= nb:
                b = nb - 1
        else:
            b = 0
        counts[b] += 1.0
        sums[b] += v


@njit(cache=True, nogil=True)
def em_binned(counts, sums, K, max_iter, w, s):
    """EM for a K-component exponential (Rayleigh-amplitude) mixture on binned data: ``counts[b]``
    samples whose intensities sum to ``sums[b]``. Writes ``w`` and ``s`` (by increasing scale);
    returns the iterations run. Start: the sorted sample cut into K equal-count intervals, each
    with its weight (eq 5) and ML scale (eq 6)."""
    nb = counts.size
    n = 0.0
    tot = 0.0
    for b in range(nb):
        n += counts[b]
        tot += sums[b]
    mean = tot / n if n > 0 else 1.0
    floor = SCALE_FLOOR * mean if mean > 0 else SCALE_FLOOR
    # initial hard partition (eq 5-6)
    cw = np.zeros(K)
    cs = np.zeros(K)
    acc = 0.0
    for b in range(nb):
        if counts[b] == 0.0:
            continue
        k = int((acc + 0.5 * counts[b]) * K / n)
        if k >= K:
            k = K - 1
        cw[k] += counts[b]
        cs[k] += sums[b]
        acc += counts[b]
    for k in range(K):
        if cw[k] > 0.0:
            s[k] = max(cs[k] / cw[k], floor)
            w[k] = cw[k] / n
        else:
            s[k] = mean if mean > 0 else 1.0
            w[k] = 0.0
    tb = np.empty(nb)
    for b in range(nb):
        tb[b] = sums[b] / counts[b] if counts[b] > 0 else 0.0
    logw = np.empty(K)
    r = np.empty(K)
    prev = -np.inf
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        for k in range(K):
            cw[k] = 0.0
            cs[k] = 0.0
            logw[k] = math.log(w[k]) - math.log(s[k]) if w[k] > 0.0 else -np.inf
        ll = 0.0
        for b in range(nb):
            c = counts[b]
            if c == 0.0:
                continue
            m = -np.inf
            for k in range(K):
                r[k] = logw[k] - tb[b] / s[k]
                if r[k] > m:
                    m = r[k]
            z = 0.0
            for k in range(K):
                r[k] = math.exp(r[k] - m)
                z += r[k]
            ll += c * (m + math.log(z))
            for k in range(K):
                q = r[k] / z
                cw[k] += c * q
                cs[k] += q * sums[b]
        for k in range(K):
            if cw[k] > 0.0:
                w[k] = cw[k] / n
                s[k] = max(cs[k] / cw[k], floor)
            else:
                w[k] = 0.0
        if abs(ll - prev) <= EM_TOL * abs(ll):
            break
        prev = ll
    # order by scale
    for i in range(1, K):
        j = i
        while j > 0 and s[j - 1] > s[j]:
            s[j - 1], s[j] = s[j], s[j - 1]
            w[j - 1], w[j] = w[j], w[j - 1]
            j -= 1
    return it


@njit(cache=True, nogil=True)
def fit_binned(vals, K, max_iter, width, w, s):
    """Histogram EM (:func:`em_binned`) on the intensities ``vals`` (bins of ``width`` on
    ln(I / mean); ``width <= 0``: one bin per sample, the plain EM)."""
    n = vals.size
    tot = 0.0
    for i in range(n):
        tot += vals[i]
    mean = tot / n if n > 0 and tot > 0 else 1.0
    if width <= 0.0:
        return em_binned(np.ones(n), np.sort(vals.astype(np.float64)), K, max_iter, w, s)
    counts = np.zeros(N_BINS)
    sums = np.zeros(N_BINS)
    _bin(vals, mean, width, counts, sums)
    return em_binned(counts, sums, K, max_iter, w, s)


def fit_rayleigh_mixture(
    amplitudes, components: int = 3, max_iter: int = 200, bin_width: float = BIN_WIDTH
) -> RayleighMixture:
    """Fit eq 3-4 to clutter amplitudes by EM (eq 5-6 as its M-step; module docstring)."""
    a = np.asarray(amplitudes, np.float64).ravel()
    a = a[np.isfinite(a)]
    if a.size < components:
        raise ValueError(f"need at least {components} finite amplitudes, got {a.size}")
    w = np.zeros(int(components))
    s = np.zeros(int(components))
    it = fit_binned(np.ascontiguousarray(a * a), int(components), int(max_iter), float(bin_width), w, s)
    return RayleighMixture(weights=w, scales=s, iterations=int(it))
