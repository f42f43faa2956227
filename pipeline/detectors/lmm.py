r"""Lognormal-mixture CFAR (``lmm``): per-cell EM fit of a K-component mixture of ln x.

Source: chapter 3 of the Tsinghua thesis (seeds/000, ALGORITHMS.md section B).

Model (eq 3-1, 3-3)
-------------------
Sea-clutter intensity ``x > 0`` follows a K-component lognormal mixture
``f(x) = sum_i a_i / (sqrt(2 pi) s_i x) exp(-(ln x - mu_i)^2 / (2 s_i^2))``, i.e.
``y = ln x`` is a K-component Gaussian mixture. ``K = components`` (1..6, default 3;
the thesis does not state K).

Window
------
Square windows centred on the cell under test (CUT), sides ``target <= guard <
background`` (odd). The clutter samples are the ``N = background^2 - guard^2`` cells of
the ring between the guard and background squares (thesis fig 3.1). The tested value
``x_t`` is the mean intensity of the ``target`` window (the CUT itself for target = 1),
summed in a fixed row-major order.

Non-positive samples. ``ln x`` is undefined for ``x <= 0``; ring samples that are
``<= 0``, NaN or infinite are *ignored* (the mixture is fitted to the n <= N positive
finite ring samples: zeros are no-data / masked cells, not clutter). A pixel whose ring
holds fewer than ``max(8, 3K)`` usable samples, or whose target mean is not a positive
finite number, is never detected.

EM (eq 3-4)
-----------
Deterministic initialisation from the sample mean ``m`` and standard deviation ``sd`` of
y: equal weights ``1/K``, means at the normal quantiles ``mu_k = m + sd z_k`` with
``z_k = Phi^{-1}((k + 1/2)/K)``, a common ``s_k = sd sqrt(1 - mean(z_k^2))`` (so the
initial mixture has the sample variance). Updates: responsibilities
``g_jk = a_k phi(y_j|mu_k,s_k) / sum_l a_l phi(y_j|mu_l,s_l)`` (computed relative to the
largest log-term, so no underflow), then ``mu_k``, ``s_k``, ``a_k`` as in eq 3-4.
Stopping rule: the mean log-likelihood per sample (of the parameters entering the
iteration) changes by less than ``tol`` (default 1e-5), or ``max_iter`` iterations
(default 200). Collapse guards: variances are floored at ``1e-4 * sd^2`` (+1e-12); a
component whose total responsibility falls below ``1e-9 n`` is frozen with weight 0.

Threshold (eq 3-5..3-7) with a guaranteed bracket
-------------------------------------------------
In the log domain ``t = ln T``: ``S(t) = 1 - F(t) = sum_i a_i Q((t - mu_i)/s_i)`` with
``Q = 1 - Phi``, and we solve ``S(t) = PFA``. Let ``z = Phi^{-1}(1 - PFA)`` and
``t_lo = min_i(mu_i + s_i z)``, ``t_hi = max_i(mu_i + s_i z)``. Proof of the bracket:
for every i, ``(t_lo - mu_i)/s_i <= z`` so ``Q(.) >= Q(z) = PFA``; with ``sum a_i = 1``,
``S(t_lo) >= PFA``. Likewise ``S(t_hi) <= PFA``. S is continuous and decreasing, so the
root lies in ``[t_lo, t_hi]`` (``t_lo = t_hi`` is then the root). We run Newton on
``g(t) = ln S(t) - ln PFA`` (``g' = -f(t)/S(t)``, well scaled in the tail), safeguarded by
bisection: a Newton step leaving the current bracket is replaced by its midpoint, and the
bracket is shrunk with the sign of g every step; stop when the step or the bracket is
below ``1e-10 (1 + |t|)`` (or 100 steps). Q uses ``0.5 erfc(u / sqrt 2)`` (accurate in the
tail, unlike ``1 - Phi``).

Decision and statistic
----------------------
Detected when ``ln x_t > t`` (float64). ``stat = float32(exp(ln x_t - t)) = x_t / T``; where
the float32 rounding would not exceed 1 it is the smallest float32 above 1, so
``mask == (stat > 1)`` (threshold of the statistic: 1). 0 where not detected.

Exact, fast and grid forms
--------------------------
``method="exact"``: EM on the n raw ring samples of every pixel (ln of the block is taken
once). Cost ~ n K iterations exp() per pixel.

``method="fast"``: EM on the ring's *histogram* of y on a fixed global grid of bin width
``bin_width`` (default 1/8 neper; bin b covers ``[b h, (b + 1) h)``, the same for every
tile), each bin represented by its centre with weight = count. The histogram is integer,
slid along each row (about 4 x background updates per pixel), so it is exactly the same
for any tiling; EM then costs (number of non-empty bins) K exp() per iteration instead of
n K. Binning inflates each component variance by ~h^2/12 (Sheppard); it is subtracted
after convergence (floored). Initialisation, stopping rule and threshold are the same
code as the exact form.

Measured (2-core shared Xeon VM, one thread, float32, K = 3, defaults guard 21 /
background 41 (N = 1240), PFA 1e-5, tol 1e-5, exponential clutter): exact 0.00032 Mpx/s
(~3100 s for 1000 x 1000, extrapolated from 100 x 100; mean 69 EM iterations), fast
0.0059 Mpx/s (168 s for 1000 x 1000, mean 75 iterations, 2.5 % of pixels hit max_iter):
~19x. The thesis (window not stated) reports MATLAB 37.5 s / Titan V 1.73 s: its window or
iteration count must be far smaller. Agreement (tests/test_lmm.py, 96 x 96 lognormal-
mixture scene with 8 ships, guard 7 / background 17, PFA 1e-3): 2 of 9216 pixels differ
(89 vs 91 detected), 28 vs 29 connected detections; stated tolerance <= 0.1 % differing
pixels and detections within 1. On 96 x 96 mixture clutter (guard 11 / background 41,
K = 2 and 3) no pixel differed. Hence ``method="fast"`` is the default.
Calibration (fast, K = 2 on a 2-component lognormal mixture, N = 1560, 1024^2 px, PFA
1e-3): 1118 false alarms for 1049 expected (+6.6 %, bound 198; 512^2 px at PFA 4e-3, the
same expected count, as in tests/test_lmm.py: 1101, +5.0 %); with K = 3 on the same
clutter 1274 (+21 %: the plug-in fit of more parameters on finite N biases the FAR up).
EM on a K = 3 mixture of non-mixture data (exponential clutter) converges slowly and the
tail threshold depends on the stopping rule (tol 1e-4 / 1e-5 / 1e-6: mean 24 / 71 / 223
iterations, threshold changes up to 0.9 / 0.6 / 0.3 nepers vs converged).

Grid form
---------
``method="grid"``: the fast form's fit (histogram of the ring, built directly at each
node: the same integer counts as the sliding one, hence the same ln T bit for bit) only at
nodes on a *global* grid, rows and columns at multiples of ``grid_step`` (default 8) in
scene coordinates, so every tile computes the same nodes. A tile fits the nodes around its
core, which may lie in the halo: the halo is ``background // 2 + grid_step`` for this
form (``SPEC.halo_fn``). The node thresholds are bilinearly interpolated in ln T to each
pixel with fractions ``(r - r0) / grid_step`` of its global coordinates (nodes whose ring
holds fewer than ``max(8, 3K)`` usable samples are left out and the weights of the others
renormalised, in a fixed order): ``t_int``. Approximation: ln T is taken to vary linearly
between nodes; it fails next to bright targets, whose pixels lie in the *rings* of the
nearby nodes (raising their T) while lying in the guard of their own window.
Refinement (``grid_refine`` = r nepers, default 1): a pixel whose ``ln x_t`` exceeds
``min(t_int, surrounding valid node thresholds) - r`` is a candidate and its own fast fit
decides (and gives stat); every other pixel is not detected. With r > 0 the grid mask is
therefore exactly the fast mask restricted to the candidates (stat identical there);
``grid_refine = 0`` is pure interpolation (decide ``ln x_t > t_int``). ``grid_step = 1``
is the fast form bit for bit (slower).

Measured (same VM, one thread, 1000 x 1000 exponential clutter, defaults, PFA 1e-5):
grid_step 8 / refine 1: 5.8 s, 0.17 Mpx/s (fast: 168 s, ~29x); step 16 / refine 1: 2.1 s
(0.48 Mpx/s); step 16 / refine 0: 1.6 s (0.64 Mpx/s). Agreement with fast: default windows
and grid settings on 200 x 200 and 120 x 120 mixture scenes with 10 / 6 ships (x30..300,
3 x 3..13 px): no pixel differs (step 16 / refine 1 on the 200 x 200 scene: 35 of 121
detected pixels missed, since the ship leaves the node guards: keep grid_step <= about
guard / 2). On the agreement scene above (guard 7 / background 17, small windows and dense
ships, the hard case) the defaults (step 8 / refine 1) miss 37 of 91 fast pixels (0.4 %),
step 4 / refine 1: 11 (0.12 %), step 4 / refine 2: 5 (0.05 %, within the tolerance),
pure interpolation step 4: 49. Hence the defaults: ``grid_step = max(1, guard // 4)``
(nodes stay well inside a ship's guard; guard 7 gives step 1, i.e. the fast form itself)
and ``grid_refine = 2``: with them the grid form is within the stated tolerance of the
fast form on both test scenes (tests/test_lmm.py::test_default_grid_meets_the_agreement_rule),
so ``"grid"`` is the default (the issue's rule). Default windows (step 5 / refine 2):
5.9 s for 1000 x 1000 (28x the fast form, 6x the thesis' MATLAB 37.5 s). Calibration (grid_step 8,
the clutter / ring / bound of the fast calibration above): 1079 (refine 1) and 1059
(refine 0) false alarms for 1049 expected, within the bound 198; 1.3 PFA rejected.

Everything is per pixel (grid form: per pixel and per global node) and independent of the
tile origin: bit-identical for any tiling.
All kernels: Numba ``@njit(nogil=True, cache=True)``, no fastmath, single-threaded.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
from numba import njit
from pydantic import Field
from scipy import special

from .base import DetectorParams, DetectorSpec, float_block, with_defaults

__all__ = ["LMMParams", "SPEC", "prepare", "detect", "em_fit_points", "mixture_threshold_log",
           "mixture_sf_log", "LMM_NOTES"]

#: Measured agreement / speed of the two forms: see the module docstring.
LMM_NOTES = "see module docstring"

DEFAULT_METHOD = "grid"


class LMMParams(with_defaults(DetectorParams, "LMMDefaults", pfa=1e-5, guard=21, background=41,
                              min_area_px=3, merge_px=2)):
    """LMM-CFAR parameters: the common ones plus the mixture / EM settings."""

    components: int = Field(3, ge=1, le=6, description="K, number of lognormal components (eq 3-1)")
    method: str = Field(DEFAULT_METHOD, pattern="^(exact|fast|grid)$",
                        description="'exact': EM on the ring samples; 'fast': EM on the ring histogram of ln x; "
                                    "'grid': the fast fit at global grid nodes, ln T bilinearly interpolated")
    max_iter: int = Field(200, ge=1, le=100000, description="EM iteration cap")
    tol: float = Field(1e-5, gt=0.0, lt=1.0,
                       description="EM stops when the mean log-likelihood per sample changes by less than this")
    bin_width: float = Field(0.125, gt=0.0, le=1.0, description="fast / grid forms: histogram bin width in ln x (nepers)")
    grid_step: Optional[int] = Field(None, ge=1, le=256,
                                     description="grid form: node spacing in pixels (nodes at global multiples); "
                                                 "default max(1, guard // 4), so nodes stay inside a ship's guard")
    grid_refine: float = Field(2.0, ge=0.0, le=100.0,
                               description="grid form: pixels with ln x_t > interpolated ln T - grid_refine "
                                           "(nepers) get their own fast fit, which decides")


def grid_step(p: LMMParams) -> int:
    """The node spacing: ``grid_step``, else ``max(1, guard // 4)`` (1 = the fast form)."""
    return int(p.grid_step) if p.grid_step is not None else max(1, int(p.guard) // 4)


def prepare(p: LMMParams) -> dict:
    K = int(p.components)
    return {
        "n_ring": p.n_ring,
        "components": K,
        "method": p.method,
        "z": float(-special.ndtri(p.pfa)),          # Phi^{-1}(1 - PFA)
        "log_pfa": float(math.log(p.pfa)),
        "init_z": [float(special.ndtri((k + 0.5) / K)) for k in range(K)],
        "max_iter": int(p.max_iter),
        "tol": float(p.tol),
        "bin_width": float(p.bin_width),
        "grid_step": grid_step(p),
        "grid_refine": float(p.grid_refine),
        "statistic": "x_t / T (T: 1 - F(T) = PFA for the fitted ring mixture); detected when > 1",
    }


# ---------------------------------------------------------------------------------------
# EM on weighted points (weights = 1: raw samples; weights = counts: histogram bins)

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@njit(nogil=True, cache=True)
def em_fit_points(y, wt, n_pts, K, init_z, max_iter, tol, a, mu, s):
    """EM (eq 3-4) on weighted points; returns the iteration count. See module docstring.

    Each iteration: E-step with the current parameters (responsibilities g_jk, log-sum-exp
    relative to the largest term), accumulating sum g, sum g y, sum g y^2 per component;
    M-step mu = sum g y / sum g, s^2 = sum g y^2 / sum g - mu^2 computed about the
    *previous* mean (shifted sums, no cancellation), a = sum g / W. Stops when the mean
    log-likelihood (of the parameters entering the iteration) changes by < tol.
    """
    W = 0.0
    m = 0.0
    for j in range(n_pts):
        W += wt[j]
        m += wt[j] * y[j]
    m /= W
    v = 0.0
    for j in range(n_pts):
        d = y[j] - m
        v += wt[j] * d * d
    v /= W
    floor = 1e-4 * v + 1e-12
    sd = math.sqrt(v)
    mz2 = 0.0
    for k in range(K):
        mz2 += init_z[k] * init_z[k]
    mz2 /= K
    s0 = sd * math.sqrt(max(1.0 - mz2, 1e-4))
    if s0 * s0 < floor:
        s0 = math.sqrt(floor)
    for k in range(K):
        a[k] = 1.0 / K
        mu[k] = m + sd * init_z[k]
        s[k] = s0
    lt = np.empty(K)
    sg = np.empty(K)
    sgd = np.empty(K)
    sgdd = np.empty(K)
    ca = np.empty(K)
    inv = np.empty(K)
    live = np.ones(K, np.bool_)
    prev = -np.inf
    it = 0
    while it < max_iter:
        it += 1
        for k in range(K):
            sg[k] = 0.0
            sgd[k] = 0.0
            sgdd[k] = 0.0
            if live[k]:
                ca[k] = math.log(a[k]) - math.log(s[k])
                inv[k] = 1.0 / s[k]
        ll = 0.0
        for j in range(n_pts):
            yj = y[j]
            mx = -np.inf
            for k in range(K):
                if live[k]:
                    u = (yj - mu[k]) * inv[k]
                    t = ca[k] - 0.5 * u * u
                    lt[k] = t
                    if t > mx:
                        mx = t
            tot = 0.0
            for k in range(K):
                if live[k]:
                    e = math.exp(lt[k] - mx)
                    lt[k] = e
                    tot += e
            wj = wt[j]
            ll += wj * (mx + math.log(tot))
            r = wj / tot
            for k in range(K):
                if live[k]:
                    g = lt[k] * r
                    d = yj - mu[k]
                    sg[k] += g
                    sgd[k] += g * d
                    sgdd[k] += g * d * d
        ll = ll / W - _LOG_SQRT_2PI
        for k in range(K):
            if live[k]:
                if sg[k] < 1e-9 * W:
                    live[k] = False
                    a[k] = 0.0
                    continue
                dm = sgd[k] / sg[k]
                var = sgdd[k] / sg[k] - dm * dm
                mu[k] = mu[k] + dm
                if var < floor:
                    var = floor
                s[k] = math.sqrt(var)
                a[k] = sg[k] / W
        ch = ll - prev
        prev = ll
        if -tol < ch < tol:
            break
    # normalise the weights (they sum to 1 up to rounding)
    tot = 0.0
    for k in range(K):
        tot += a[k]
    for k in range(K):
        a[k] = a[k] / tot
    return it


# ---------------------------------------------------------------------------------------
# threshold


@njit(nogil=True, cache=True)
def _sf_and_pdf(t, a, mu, s, K):
    """S(t) = sum a Q((t-mu)/s) and its density f(t) = sum a phi((t-mu)/s)/s (log domain)."""
    S = 0.0
    f = 0.0
    for k in range(K):
        if a[k] > 0.0:
            u = (t - mu[k]) / s[k]
            S += a[k] * 0.5 * math.erfc(u * 0.7071067811865476)
            f += a[k] * math.exp(-0.5 * u * u) / (s[k] * 2.5066282746310002)
    return S, f


@njit(nogil=True, cache=True)
def mixture_sf_log(t, a, mu, s):
    """ln S(t) for the mixture (a, mu, s): the log of the exceedance probability of ln x > t."""
    S, f = _sf_and_pdf(t, a, mu, s, a.shape[0])
    return math.log(S) if S > 0.0 else -np.inf


@njit(nogil=True, cache=True)
def mixture_threshold_log(a, mu, s, K, z, log_pfa):
    """t = ln T with S(t) = PFA: Newton on ln S - ln PFA safeguarded by bisection.

    Bracket [min_i(mu_i + s_i z), max_i(mu_i + s_i z)] (see module docstring for the proof).
    """
    lo = np.inf
    hi = -np.inf
    for k in range(K):
        if a[k] > 0.0:
            q = mu[k] + s[k] * z
            if q < lo:
                lo = q
            if q > hi:
                hi = q
    if not (hi > lo):
        return lo
    t = 0.5 * (lo + hi)
    for _ in range(100):
        S, f = _sf_and_pdf(t, a, mu, s, K)
        if S <= 0.0:  # far beyond every component: t is above the root
            hi = t
            t = 0.5 * (lo + hi)
            continue
        g = math.log(S) - log_pfa
        if g > 0.0:
            lo = t
        elif g < 0.0:
            hi = t
        else:
            return t
        if f > 0.0:
            tn = t + g * S / f  # Newton: g' = -f/S
        else:
            tn = 0.5 * (lo + hi)
        if not (lo < tn < hi):
            tn = 0.5 * (lo + hi)
        step = abs(tn - t)
        t = tn
        if step <= 1e-10 * (1.0 + abs(t)) or (hi - lo) <= 1e-10 * (1.0 + abs(t)):
            break
    return t


# ---------------------------------------------------------------------------------------
# kernels


@njit(nogil=True, cache=True)
def _target_log(block, ci, cj, rt):
    """ln of the target-window mean (row-major fixed order); NaN if not positive finite."""
    if rt == 0:
        x = np.float64(block[ci, cj])
    else:
        acc = 0.0
        for a in range(ci - rt, ci + rt + 1):
            for b in range(cj - rt, cj + rt + 1):
                acc += np.float64(block[a, b])
        x = acc / ((2 * rt + 1) * (2 * rt + 1))
    if x > 0.0 and x < np.inf:
        return math.log(x)
    return np.nan


@njit(nogil=True, cache=True)
def _decide(lx, t, i, j, mask, stat):
    if lx > t:
        mask[i, j] = True
        r = np.float32(math.exp(lx - t))
        if not (r > np.float32(1.0)):
            r = np.nextafter(np.float32(1.0), np.float32(np.inf))
        stat[i, j] = r


@njit(nogil=True, cache=True)
def _exact_kernel(block, halo, h, w, rb, rg, rt, K, init_z, max_iter, tol, z, log_pfa,
                  nmin, mask, stat, iters):
    H, Wd = block.shape
    Y = np.empty((H, Wd))
    for r in range(H):
        for c in range(Wd):
            x = np.float64(block[r, c])
            Y[r, c] = math.log(x) if (x > 0.0 and x < np.inf) else np.nan
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    buf = np.empty(n_ring)
    ones = np.ones(n_ring)
    a = np.empty(K)
    mu = np.empty(K)
    s = np.empty(K)
    for i in range(h):
        ci = i + halo
        for j in range(w):
            cj = j + halo
            lx = _target_log(block, ci, cj, rt)
            if lx != lx:
                continue
            n = 0
            for r in range(ci - rb, ci + rb + 1):
                inner = (r >= ci - rg) and (r <= ci + rg)
                for c in range(cj - rb, cj + rb + 1):
                    if inner and c >= cj - rg and c <= cj + rg:
                        continue
                    v = Y[r, c]
                    if v == v:
                        buf[n] = v
                        n += 1
            if n < nmin:
                continue
            iters[i, j] = em_fit_points(buf, ones, n, K, init_z, max_iter, tol, a, mu, s)
            t = mixture_threshold_log(a, mu, s, K, z, log_pfa)
            _decide(lx, t, i, j, mask, stat)


@njit(nogil=True, cache=True)
def _bin_index(block, inv_h):
    """Global ln-x bin of every value (floor(ln x / h)), offset to >= 0; -1 if unusable."""
    H, Wd = block.shape
    off = 1 + int(math.ceil(800.0 * inv_h))  # ln of positive float64 > -745
    B = np.empty((H, Wd), np.int32)
    for r in range(H):
        for c in range(Wd):
            x = np.float64(block[r, c])
            if x > 0.0 and x < np.inf:
                B[r, c] = int(math.floor(math.log(x) * inv_h)) + off
            else:
                B[r, c] = -1
    return B, off


@njit(nogil=True, cache=True)
def _col(hist, B, r0, r1, c, d):
    for r in range(r0, r1):
        b = B[r, c]
        if b >= 0:
            hist[b] += d


@njit(nogil=True, cache=True)
def _fast_kernel(block, halo, h, w, rb, rg, rt, K, init_z, max_iter, tol, z, log_pfa,
                 nmin, bw, mask, stat, iters):
    inv_h = 1.0 / bw
    B, off = _bin_index(block, inv_h)
    H, Wd = block.shape
    bmin = 1 << 30
    bmax = -1
    for r in range(H):
        for c in range(Wd):
            b = B[r, c]
            if b >= 0:
                if b < bmin:
                    bmin = b
                if b > bmax:
                    bmax = b
    if bmax < 0:
        return
    hist = np.zeros(bmax + 1, np.int64)
    nb = bmax - bmin + 1
    yv = np.empty(nb)
    wv = np.empty(nb)
    a = np.empty(K)
    mu = np.empty(K)
    s = np.empty(K)
    shep = bw * bw / 12.0
    for i in range(h):
        ci = i + halo
        hist[:] = 0
        cj = halo
        for c in range(cj - rb, cj + rb + 1):
            if c < cj - rg or c > cj + rg:
                _col(hist, B, ci - rb, ci + rb + 1, c, 1)
            else:
                _col(hist, B, ci - rb, ci - rg, c, 1)
                _col(hist, B, ci + rg + 1, ci + rb + 1, c, 1)
        for j in range(w):
            cj = j + halo
            if j > 0:
                # leaving column cj-1-rb (full), entering cj+rb (full);
                # column cj-1-rg becomes ring in the middle rows, cj+rg leaves it
                _col(hist, B, ci - rb, ci + rb + 1, cj - 1 - rb, -1)
                _col(hist, B, ci - rb, ci + rb + 1, cj + rb, 1)
                _col(hist, B, ci - rg, ci + rg + 1, cj - 1 - rg, 1)
                _col(hist, B, ci - rg, ci + rg + 1, cj + rg, -1)
            lx = _target_log(block, ci, cj, rt)
            if lx != lx:
                continue
            n = 0
            ntot = 0
            for b in range(bmin, bmax + 1):
                cnt = hist[b]
                if cnt > 0:
                    yv[n] = ((b - off) + 0.5) * bw
                    wv[n] = np.float64(cnt)
                    n += 1
                    ntot += cnt
            if ntot < nmin:
                continue
            iters[i, j] = em_fit_points(yv, wv, n, K, init_z, max_iter, tol, a, mu, s)
            for k in range(K):
                v = s[k] * s[k] - shep
                fl = 0.25 * s[k] * s[k]
                s[k] = math.sqrt(v if v > fl else fl)
            t = mixture_threshold_log(a, mu, s, K, z, log_pfa)
            _decide(lx, t, i, j, mask, stat)


@njit(nogil=True, cache=True)
def _ring_hist_fit(B, hist, ci, cj, rb, rg, bmin, bmax, off, bw, yv, wv, K, init_z, max_iter, tol,
                   z, log_pfa, nmin, a, mu, s):
    """The fast form's fit for the ring around block cell (ci, cj), histogram built directly
    (same integer counts as the sliding one, hence the same threshold bit for bit).
    ``hist`` must be zero on entry and is zero on return. Returns (t, iterations); t = NaN
    if the ring holds fewer than nmin usable samples."""
    for c in range(cj - rb, cj + rb + 1):
        if c < cj - rg or c > cj + rg:
            _col(hist, B, ci - rb, ci + rb + 1, c, 1)
        else:
            _col(hist, B, ci - rb, ci - rg, c, 1)
            _col(hist, B, ci + rg + 1, ci + rb + 1, c, 1)
    n = 0
    ntot = 0
    for b in range(bmin, bmax + 1):
        cnt = hist[b]
        if cnt > 0:
            yv[n] = ((b - off) + 0.5) * bw
            wv[n] = np.float64(cnt)
            n += 1
            ntot += cnt
            hist[b] = 0
    if ntot < nmin:
        return np.nan, 0
    it = em_fit_points(yv, wv, n, K, init_z, max_iter, tol, a, mu, s)
    shep = bw * bw / 12.0
    for k in range(K):
        q = s[k] * s[k] - shep
        fl = 0.25 * s[k] * s[k]
        s[k] = math.sqrt(q if q > fl else fl)
    return mixture_threshold_log(a, mu, s, K, z, log_pfa), it


@njit(nogil=True, cache=True)
def _grid_kernel(block, halo, h, w, rb, rg, rt, K, init_z, max_iter, tol, z, log_pfa,
                 nmin, bw, step, refine, g0r, g0c, mask, stat, iters):
    """Grid form: fast (histogram) fit at global nodes (multiples of ``step``), ln T
    bilinearly interpolated. ``(g0r, g0c)``: global coordinates of the core's [0, 0];
    ``halo >= rb + step - 1`` so the ring of every needed node lies in the block."""
    inv_h = 1.0 / bw
    B, off = _bin_index(block, inv_h)
    H, Wd = block.shape
    bmin = 1 << 30
    bmax = -1
    for r in range(H):
        for c in range(Wd):
            b = B[r, c]
            if b >= 0:
                if b < bmin:
                    bmin = b
                if b > bmax:
                    bmax = b
    if bmax < 0:
        return
    hist = np.zeros(bmax + 1, np.int64)
    nb = bmax - bmin + 1
    yv = np.empty(nb)
    wv = np.empty(nb)
    a = np.empty(K)
    mu = np.empty(K)
    s = np.empty(K)
    # nodes kr0..kr1 (rows), kc0..kc1 (cols), global index k -> global coordinate k * step
    kr0 = g0r // step
    kr1 = (g0r + h - 1) // step + 1
    kc0 = g0c // step
    kc1 = (g0c + w - 1) // step + 1
    nr = kr1 - kr0 + 1
    nc = kc1 - kc0 + 1
    T = np.full((nr, nc), np.nan)
    itn = np.zeros((nr, nc), np.int32)
    # block index of global coordinate g: g - g0 + halo
    for u in range(nr):
        ci = (kr0 + u) * step - g0r + halo
        for v in range(nc):
            cj = (kc0 + v) * step - g0c + halo
            T[u, v], itn[u, v] = _ring_hist_fit(B, hist, ci, cj, rb, rg, bmin, bmax, off, bw, yv, wv, K,
                                                init_z, max_iter, tol, z, log_pfa, nmin, a, mu, s)
    inv_step = 1.0 / step
    for i in range(h):
        gr = g0r + i
        kr = gr // step
        u = kr - kr0
        fr = (gr - kr * step) * inv_step
        ci = i + halo
        for j in range(w):
            gc = g0c + j
            kc = gc // step
            v = kc - kc0
            fc = (gc - kc * step) * inv_step
            if fr == 0.0 and fc == 0.0:
                iters[i, j] = itn[u, v]
            lx = _target_log(block, ci, j + halo, rt)
            if lx != lx:
                continue
            # fixed-order weighted mean over the valid surrounding nodes (weights > 0)
            num = 0.0
            den = 0.0
            w00 = (1.0 - fr) * (1.0 - fc)
            w01 = (1.0 - fr) * fc
            w10 = fr * (1.0 - fc)
            w11 = fr * fc
            t00 = T[u, v]
            t01 = T[u, v + 1]
            t10 = T[u + 1, v]
            t11 = T[u + 1, v + 1]
            if w00 > 0.0 and t00 == t00:
                num += w00 * t00
                den += w00
            if w01 > 0.0 and t01 == t01:
                num += w01 * t01
                den += w01
            if w10 > 0.0 and t10 == t10:
                num += w10 * t10
                den += w10
            if w11 > 0.0 and t11 == t11:
                num += w11 * t11
                den += w11
            if den > 0.0:
                t = num if den == 1.0 else num / den
                tmin = t
                for tq in (t00, t01, t10, t11):
                    if tq < tmin:  # NaN compares False
                        tmin = tq
                if refine > 0.0 and lx > tmin - refine:  # candidate: its own fit decides
                    t, it = _ring_hist_fit(B, hist, ci, j + halo, rb, rg, bmin, bmax, off, bw, yv, wv, K,
                                           init_z, max_iter, tol, z, log_pfa, nmin, a, mu, s)
                    iters[i, j] = it
                    if t != t:
                        continue
                _decide(lx, t, i, j, mask, stat)


def detect(block, halo: int, origin, params: LMMParams, prep: dict, *, _iters: bool = False):
    """LMM-CFAR on one padded tile: ``(mask, stat)`` of the ``(h, w)`` core.

    ``stat = x_t / T`` (float32, > 1 where ``mask``; 0 elsewhere). ``origin`` (scene
    coordinates of ``block[0, 0]``) is used by the grid form only (global node positions). ``_iters=True`` also returns the
    per-pixel EM iteration counts (for tests / benchmarks).
    """
    block = float_block(block)
    halo = int(halo)
    rb, rg, rt = int(params.background) // 2, int(params.guard) // 2, int(params.target) // 2
    grid = prep["method"] == "grid"
    step = int(prep.get("grid_step", grid_step(params))) if grid else 0
    need = rb + step if grid else rb
    if halo < need:
        raise ValueError(f"halo ({halo}) must be at least {_halo_rule(prep['method'])} = {need}")
    h, w = block.shape[0] - 2 * halo, block.shape[1] - 2 * halo
    if h < 0 or w < 0:
        raise ValueError(f"block {block.shape} is smaller than twice the halo ({halo})")
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    K = int(prep["components"])
    if int(prep.get("n_ring", n_ring)) != n_ring or K != int(params.components):
        raise ValueError("prep does not match the parameters")
    mask = np.zeros((h, w), dtype=np.bool_)
    stat = np.zeros((h, w), dtype=np.float32)
    iters = np.zeros((h, w), dtype=np.int32)
    if h and w:
        if halo > need:  # trim the extra halo (kernels assume halo == need is enough)
            d = halo - need
            block = np.ascontiguousarray(block[d: block.shape[0] - d, d: block.shape[1] - d])
            origin = (int(origin[0]) + d, int(origin[1]) + d)
            halo = need
        init_z = np.asarray(prep["init_z"], dtype=np.float64)
        args = (block, halo, h, w, rb, rg, rt, K, init_z, int(prep["max_iter"]), float(prep["tol"]),
                float(prep["z"]), float(prep["log_pfa"]), max(8, 3 * K))
        if prep["method"] == "exact":
            _exact_kernel(*args, mask, stat, iters)
        elif grid:
            _grid_kernel(*args, float(prep["bin_width"]), step, float(prep.get("grid_refine", params.grid_refine)),
                         int(origin[0]) + halo, int(origin[1]) + halo,
                         mask, stat, iters)
        else:
            _fast_kernel(*args, float(prep["bin_width"]), mask, stat, iters)
    if _iters:
        return mask, stat, iters
    return mask, stat


def _halo_rule(method) -> str:
    return "background // 2 + grid_step" if method == "grid" else "background // 2"


def _halo(p: LMMParams) -> int:
    """background // 2, plus grid_step for the grid form (the rings of the nodes around the core)."""
    return int(p.background) // 2 + (grid_step(p) if p.method == "grid" else 0)


SPEC = DetectorSpec(
    name="lmm",
    summary=(
        "Lognormal-mixture CFAR: per-cell EM fit of a K-component Gaussian mixture of ln x "
        "over the background ring; threshold 1 - F(T) = PFA by safeguarded Newton"
    ),
    reference="Tsinghua thesis 2020 (seeds/000), chapter 3, eq 3-1, 3-4..3-7",
    params=LMMParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    halo_fn=_halo,
    halo_rule="background // 2 (+ grid_step for method='grid')",
)
