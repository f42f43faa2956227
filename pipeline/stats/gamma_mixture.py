"""Finite gamma mixture of SAR intensities with L looks, fitted by EM (seed 003, eqs (1)-(2)).

Model (docs/references.md, Liu et al. 2017, section 3.1):

- eq (1): the mixture density ``p(y) = sum_i pi_i f(y | theta_i)``, ``sum_i pi_i = 1``, K classes;
- eq (2): each class is the fully developed speckle intensity of L looks,
  ``f(y | mu) = L^L y^(L-1) exp(-L y / mu) / (Gamma(L) mu^L)``: a gamma law of shape L (the
  number of looks, fixed: the paper names it the image's looks and never estimates it) and
  mean ``mu``; the class parameters are ``theta_i = mu_i``.

The paper fits (1) with the EM algorithm of Dempster, Laird and Rubin (its ref. [22]) without
writing the updates; with L fixed they are closed form:

- E step: ``tau_ni = pi_i f(y_n | mu_i) / sum_j pi_j f(y_n | mu_j)`` (responsibilities);
- M step: ``pi_i = mean_n tau_ni``, ``mu_i = sum_n tau_ni y_n / sum_n tau_ni`` (the gamma ML
  mean of the weighted sample, shape fixed).

The iteration stops when the mean log-likelihood changes by less than ``tol`` (or after
``max_iter`` steps). The initialisation is deterministic (:func:`initial_mixture`): nested
upper quantile slices of the sample, so the brightest class starts on the top tail (where
ships are) rather than on a quarter of the sea. Classes are returned sorted by mean: class
K-1 is the brightest (the paper's man-made / ship class).

Only terms that differ between classes matter for classification: the negative log of
``pi_i f(y | mu_i)`` is ``L ln mu_i + L y / mu_i - ln pi_i`` plus a term common to every class
(:func:`class_energy_terms`); it is finite at ``y = 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import special

#: Smallest class mean, relative to the sample mean: a class of exact zeros (8-bit chips) would
#: otherwise collapse on mu = 0, where ln mu is -inf.
MEAN_FLOOR = 1e-6
#: Smallest class weight kept (a class EM empties keeps a finite ln pi).
WEIGHT_FLOOR = 1e-12


@dataclass(frozen=True)
class GammaMixture:
    """A fitted K-class gamma mixture with L looks (classes sorted by mean)."""

    weights: np.ndarray  # (K,) pi_i
    means: np.ndarray  # (K,) mu_i
    looks: float
    loglik: float  # mean log-likelihood of the sample at the returned parameters
    iterations: int
    converged: bool

    def to_dict(self) -> dict:
        return {
            "weights": [float(v) for v in self.weights],
            "means": [float(v) for v in self.means],
            "looks": float(self.looks),
            "loglik": float(self.loglik),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
        }


def initial_mixture(y: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic start: the sorted sample cut at the upper quantiles 1/2, 1/20, 1/200, ...
    (class k >= 1 starts on the slice between the 1 - 0.5 * 10^-(k-1) and 1 - 0.5 * 10^-k
    quantiles, the last on the top 0.5 * 10^-(K-2)); weights and means of the slices.
    Sample quantiles make it invariant to the intensity scale."""
    ys = np.sort(np.asarray(y, np.float64))
    n = ys.size
    cuts = [0] + [int(round(n * (1.0 - 0.5 * 10.0 ** (-(k - 1))))) for k in range(1, K)] + [n]
    for k in range(1, K + 1):  # at least one sample a slice
        cuts[k] = min(max(cuts[k], cuts[k - 1] + 1), n - (K - k))
    w = np.diff(cuts).astype(np.float64) / n
    mu = np.array([ys[cuts[k] : cuts[k + 1]].mean() for k in range(K)])
    return w, mu


def class_energy_terms(weights, means, looks: float) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)`` with ``-ln(pi_i f(y | mu_i)) = a_i + b_i y + c(y)``, ``c`` common to all classes:
    ``a_i = L ln mu_i - ln pi_i``, ``b_i = L / mu_i`` (eq (2))."""
    mu = np.asarray(means, np.float64)
    w = np.asarray(weights, np.float64)
    L = float(looks)
    return L * np.log(mu) - np.log(w), L / mu


def _log_joint(y: np.ndarray, w: np.ndarray, mu: np.ndarray, L: float) -> np.ndarray:
    """``ln(pi_i f(y_n | mu_i))``, shape (n, K) (eq (2), full density)."""
    ly = np.log(np.maximum(y, np.finfo(np.float64).tiny))
    base = L * math.log(L) - special.gammaln(L) + (L - 1.0) * ly  # common to all classes
    return base[:, None] + np.log(w)[None, :] - L * np.log(mu)[None, :] - L * y[:, None] / mu[None, :]


def fit_gamma_mixture(y: np.ndarray, looks: float, K: int = 4, max_iter: int = 500, tol: float = 1e-9) -> GammaMixture:
    """EM for the K-class gamma mixture of eq (1)-(2) with L = ``looks`` fixed (module docstring).

    ``y``: a 1-D sample of non-negative finite intensities (absent pixels already left out).
    Deterministic: the same sample in the same order gives the same floats.
    """
    y = np.ascontiguousarray(np.asarray(y, np.float64).ravel())
    if y.size < K:
        raise ValueError(f"gamma mixture: {y.size} samples are too few for {K} classes")
    if not np.all(np.isfinite(y)) or np.any(y < 0):
        raise ValueError("gamma mixture: the sample must be finite and non-negative")
    L = float(looks)
    if not L > 0:
        raise ValueError(f"looks must be positive, got {looks}")
    floor = MEAN_FLOOR * max(float(y.mean()), np.finfo(np.float64).tiny)
    w, mu = initial_mixture(y, K)
    mu = np.maximum(mu, floor)
    base = float(
        np.mean(L * math.log(L) - special.gammaln(L) + (L - 1.0) * np.log(np.maximum(y, np.finfo(np.float64).tiny)))
    )
    prev = -np.inf
    converged = False
    it = 0
    nk = np.empty(K)
    sy = np.empty(K)
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        ll = _em_step(y, np.log(w) - L * np.log(mu), L / mu, nk, sy) / y.size + base
        w = np.maximum(nk / y.size, WEIGHT_FLOOR)  # M step
        w = w / w.sum()
        mu = np.where(nk > 0, sy / np.where(nk > 0, nk, 1.0), mu)
        mu = np.maximum(mu, floor)
        if abs(ll - prev) < tol * max(1.0, abs(ll)):
            converged = True
            break
        prev = ll
    order = np.argsort(mu, kind="stable")
    w, mu = w[order], mu[order]
    lj = _log_joint(y, w, mu, L)
    m = lj.max(1)
    ll = float((m + np.log(np.exp(lj - m[:, None]).sum(1))).mean())
    return GammaMixture(weights=w, means=mu, looks=L, loglik=ll, iterations=it, converged=converged)


@njit(nogil=True, cache=True)
def _em_step(y, c, b, nk, sy):
    """One E step over the sample (responsibilities from ``ln pi_i f_i = c_i - b_i y`` + common
    term) accumulated into the M step's sums ``nk = sum tau``, ``sy = sum tau y``; returns
    ``sum_n ln sum_i exp(c_i - b_i y_n)`` (the log-likelihood without the common term)."""
    K = c.shape[0]
    nk[:] = 0.0
    sy[:] = 0.0
    e = np.empty(K)
    ll = 0.0
    for n in range(y.shape[0]):
        v = y[n]
        m = -np.inf
        for k in range(K):
            e[k] = c[k] - b[k] * v
            if e[k] > m:
                m = e[k]
        s = 0.0
        for k in range(K):
            e[k] = math.exp(e[k] - m)
            s += e[k]
        ll += m + math.log(s)
        for k in range(K):
            t = e[k] / s
            nk[k] += t
            sy[k] += t * v
    return ll


def mixture_sf(q: float, weights, means, looks: float) -> float:
    """``P(y > q)`` under the mixture (eq (1)-(2)): ``sum_i pi_i Q(L, L q / mu_i)``."""
    w = np.asarray(weights, np.float64)
    mu = np.asarray(means, np.float64)
    return float(np.sum(w * special.gammaincc(looks, looks * q / mu)))


def mixture_isf(p: float, weights, means, looks: float) -> float:
    """The intensity ``q`` with ``P(y > q) = p`` under the mixture (weights renormalised to 1):
    root of the monotone tail between the classes' own quantiles (scipy brentq)."""
    from scipy import optimize, stats  # lazy: importing scipy.optimize/stats costs every command start-up time

    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    mu = np.asarray(means, np.float64)
    L = float(looks)
    qs = stats.gamma.isf(p, L, scale=mu / L)
    lo, hi = float(qs.min()), float(qs.max())
    if lo == hi:
        return lo
    return float(
        optimize.brentq(lambda q: mixture_sf(q, w, mu, L) - p, lo, hi, xtol=1e-14 * hi, rtol=1e-15, maxiter=500)
    )
