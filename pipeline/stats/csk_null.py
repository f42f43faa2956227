"""The distribution of the windowed CSK estimate on circular complex Gaussian sea (the ``csk`` null).

The ``csk`` detector (docs/algorithms/complex_stats.md) thresholds the sample complex signal
kurtosis of eq 37 of Leng et al. 2020 (docs/references.md#leng2020) over the n = w^2 cells of
a window, zero mean assumed (the paper's assumption for SLC data):

    CSK_n = n sum|z|^4 / (sum|z|^2)^2 - 2 - |sum z^2|^2 / (sum|z|^2)^2.

Under the null, z_1..z_n i.i.d. circular complex Gaussian CN(0, s2) (fully developed speckle,
eq 39 with beta = 1), CSK_n is free of s2 (scale invariant) and of the phase origin, so its law
depends on n alone; a threshold from it is CFAR.

What is exact. With I_k = |z_k|^2 ~ Exp(s2) and D = I / sum I ~ Dirichlet(1, ..., 1)
(independent of sum I), E[sum D_k^2] = 2 / (n + 1) and, the phases being independent and
uniform, E|sum D_k exp(2j phi_k)|^2 = E[sum D_k^2]; hence

    E[CSK_n] = n 2/(n + 1) - 2 - 2/(n + 1) = -4 / (n + 1)          (exact, every n)

(the estimate is biased low by 4/(n+1); the tests check the simulation below against it).
The delta method gives Var[CSK_n] = 4/n + O(n^-2) (Var I = s2^2, Var I^2 = 20 s2^4,
Cov(I, I^2) = 4 s2^3; the |m20|^2 term is O_p(1/n)), i.e. CSK_n ~ N(-4/(n+1), 4/n)
asymptotically. That normal law is far too light in the upper tail for small n (n = 49:
P(CSK > 1.922) is 1e-4 by simulation and 1e-12 under the normal law; the normal 1e-6
threshold, 1.28, is the exact law's 1e-3 point, ~1000 false alarms for one): one bright speckle
sample dominates the tail. So the
thresholds come from the exact law, tabulated by simulation.

Simulation (importance sampling, reproducible). ``samples`` windows of n i.i.d. CN(0, 1)
cells are drawn with a fixed seed; in each, cell 0 (the cell under test) is, with probability
1 - ALPHA, scaled in power by theta (drawn from THETAS, equal weights), i.e. its power is
Exp(theta) instead of Exp(1) (a defensive mixture proposal, Hesterberg 1995,
docs/references.md#hesterberg1995). The likelihood ratio of a window is
1 / (ALPHA + (1 - ALPHA) mean_theta r_theta(I_0)), r_theta(x) = exp(x (1 - 1/theta)) / theta,
bounded by 1 / ALPHA, so every estimate below is unbiased with finite variance. Two events:

* ``window`` (every pixel of a window whose CSK exceeds T): P(CSK > T). CSK is symmetric in the
  cells, so P(CSK > T) = n P(CSK > T and I_0 is the largest power of the window); the right side
  is what the tilted cell 0 samples well (the tail is made by one bright cell).
* ``bright`` (the default: the cell under test must also exceed the window's mean power,
  I_0 > sum I / n, so that a ship's detection covers its bright pixels and not the whole
  window around them): P(CSK > T and I_0 > sum I / n). By the same symmetry (swap the labels of
  cell 0 and of the window's brightest cell j), for every k != 0,
  P(CSK > T, I_0 > mean, argmax = j) = P(CSK > T, I_k > mean, argmax = 0), and the brightest
  cell is above the mean, so P(CSK > T, I_0 > mean) = E[1(CSK > T, argmax = 0) N_above],
  N_above the number of cells above the window's mean power; again an event of the tilted
  cell (estimating the bright event directly needs a second bright cell the proposal does
  not make, and its error was 40-90 % at 1e-5..1e-6).

The threshold for ``pfa`` is the smallest simulated CSK value T whose estimated exceedance
probability is at most ``pfa``; its relative standard error (of the IS estimate at T) is
returned with it. With the default 2^20 windows the error is ~2 % at 1e-4, ~5 % at 1e-6 and
grows in the deep tail (~20-50 % near 1e-12 for n = 49-81): reported in ``run.json``.
Deeper than the simulated CSK values reach (not even at the PFA floor 1e-15 for n = 49 with
the default samples: tests/pipeline/test_csk.py) the threshold is the largest possible value n - 2 (one
cell carrying all the power), which no window exceeds.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

#: Defensive weight of the untilted proposal and the power tilts of the cell under test.
ALPHA = 0.25
THETAS = np.array([2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0])
SEED = 20200615
SAMPLES = 1 << 20


def samples_for(n: int) -> int:
    """Simulated windows for n cells: 2^20 up to n = 81 (window 9), 2^19 above (the cost is
    ~0.1 s per 10^6 cells on one core, so a window-15 table takes as long as a window-11 one)."""
    return SAMPLES if int(n) <= 81 else SAMPLES // 2


@njit(cache=True)
def _simulate(
    n: int,
    m: int,
    seed: int,
    thetas: np.ndarray,
    alpha: float,
    csk: np.ndarray,
    w: np.ndarray,
    is_max: np.ndarray,
    above: np.ndarray,
) -> None:
    """``m`` windows of ``n`` cells: CSK, likelihood ratio, whether cell 0 is the brightest and
    how many cells exceed the window's mean power."""
    np.random.seed(seed)
    nt = thetas.size
    pw = np.empty(n)
    for i in range(m):
        theta = 1.0
        if np.random.random() >= alpha:
            theta = thetas[min(int(np.random.random() * nt), nt - 1)]
        s1 = 0.0
        s2 = 0.0
        cr = 0.0
        ci = 0.0
        st = math.sqrt(theta)
        for k in range(n):
            x = np.random.standard_normal() * 0.7071067811865476
            y = np.random.standard_normal() * 0.7071067811865476
            if k == 0:
                x *= st
                y *= st
            p = x * x + y * y
            pw[k] = p
            s1 += p
            s2 += p * p
            cr += x * x - y * y
            ci += 2.0 * x * y
        inv = 1.0 / (s1 * s1)
        csk[i] = n * s2 * inv - 2.0 - (cr * cr + ci * ci) * inv
        i0 = pw[0]
        top = True
        cnt = 0
        for k in range(n):
            if k > 0 and pw[k] > i0:
                top = False
            if pw[k] * n > s1:
                cnt += 1
        is_max[i] = top
        above[i] = cnt
        q = 0.0
        for t in range(nt):
            q += math.exp(i0 * (1.0 - 1.0 / thetas[t])) / thetas[t]
        q = alpha + (1.0 - alpha) * q / nt
        w[i] = 1.0 / q if math.isfinite(q) else 0.0


@functools.lru_cache(maxsize=16)
def null_tail(n: int, samples: int = SAMPLES, seed: int = SEED) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Simulated upper tail of CSK_n for both events: ``{"window" | "bright": (T, P, SE)}``,
    T decreasing simulated CSK values, P the estimated P(event, CSK >= T) and SE its standard
    error (read-only float64 arrays). Cached per (n, samples, seed)."""
    n = int(n)
    if n < 2:
        raise ValueError(f"a CSK window needs at least 2 cells, got {n}")
    csk = np.empty(samples)
    w = np.empty(samples)
    is_max = np.empty(samples, np.bool_)
    above = np.empty(samples, np.int64)
    _simulate(n, samples, seed, THETAS, ALPHA, csk, w, is_max, above)
    order = np.argsort(-csk, kind="stable")
    t = csk[order]
    out = {}
    top = np.where(is_max[order], w[order], 0.0)
    for name, v in (("window", top * float(n)), ("bright", top * above[order])):
        p = np.cumsum(v) / samples
        p2 = np.cumsum(v * v) / samples
        se = np.sqrt(np.maximum(p2 - p * p, 0.0) / samples)
        for a in (t, p, se):
            a.setflags(write=False)
        out[name] = (t, p, se)
    return out


def mean_csk(n: int, samples: int = SAMPLES, seed: int = SEED) -> tuple[float, float]:
    """Importance-sampled E[CSK_n] and its standard error (check against -4/(n+1))."""
    csk = np.empty(samples)
    w = np.empty(samples)
    f1 = np.empty(samples, np.bool_)
    f2 = np.empty(samples, np.int64)
    _simulate(int(n), samples, seed, THETAS, ALPHA, csk, w, f1, f2)
    v = w * csk
    return float(v.mean()), float(v.std() / math.sqrt(samples))


def threshold(
    n: int, pfa: float, event: str = "bright", samples: int = SAMPLES, seed: int = SEED
) -> tuple[float, float]:
    """``(T, rel_se)``: the threshold with estimated P(event, CSK_n > T) <= pfa, and the
    relative standard error of that estimate at T (0 where the table ends: see the module)."""
    if event not in ("window", "bright"):
        raise ValueError(f"event must be 'window' or 'bright', got {event!r}")
    if not 0.0 < pfa < 1.0:
        raise ValueError(f"pfa must be in (0, 1), got {pfa}")
    t, p, se = null_tail(n, samples, seed)[event]
    # p[i] = P(CSK >= t[i]); the threshold t[i] excludes sample i itself: P(CSK > t[i]) = p[i-1]
    i = int(np.searchsorted(p, pfa, side="right"))  # first index with p > pfa
    if i == 0:  # even the largest simulated value is too frequent
        raise ValueError(f"pfa {pfa:g} is above the simulated tail (n = {n})")
    if i >= t.size:
        return float(t[-1]), float(se[-1] / p[-1]) if p[-1] > 0 else 0.0
    if p[i - 1] <= 0.0:  # deeper than any simulated value reaches
        return float(n - 2), 0.0
    return float(t[i - 1]), float(se[i - 1] / p[i - 1])
