r"""Lognormal-mixture CFAR (``lmm``): per-cell fit of a mixture of ln x, calibrated tail.

Per cell: EM fits of 1..K components to ln x over the background ring, the number K'
chosen by BIC, the chosen fit polished to the maximum likelihood, and the threshold where
the mixture's tail equals PFA, raised by the first-order predictive correction for the
fit's finite-sample error (section "Calibration"; ``select="fixed", tail="plugin"`` is the
thesis' plug-in EM threshold, bit for bit the earlier behaviour).

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

Calibration: choice of K' and the predictive tail
-------------------------------------------------
The problem (measured). The plug-in threshold of a mixture fitted to the N ring samples
exceeds the PFA on the mixture's own clutter. Exact measure used throughout (no counting
noise): for iid clutter and a CUT independent of its ring, P(FA) = E[S_true(t)] over
rings, averaged over M = 20000 independent default rings (N = 1240, histogram h = 1/8);
ratio to PFA at PFA 1e-3 / 1e-5 (standard errors ~0.5 % / 1-3 %; "C2": the tests'
2-component clutter a = (.7, .3), mu = (0, 1), s = (.5, .8); "C3": (.5, .3, .2),
(-1, .5, 2), (.5, .4, .6); "C1": one lognormal (0, .6); "C4": (.9, .1), (0, 1.5),
(.5, .7); "C5": (.6, .4), (0, 2), (.4, .5)):

====================================  ===========  ===========  ===========  ===========  ===========
fit / threshold                       C1           C2           C3           C4           C5
====================================  ===========  ===========  ===========  ===========  ===========
K = 3 fixed, plug-in (old default)    1.51 / 4.82  1.26 / 2.28  1.13 / 1.81  0.88 / 0.94  1.19 / 1.66
K = 2 fixed, plug-in                  1.40 / 2.84  1.09 / 1.21  0.08 / 0.00  0.89 / 1.27  1.06 / 1.24
K = 3 fixed, predictive               1.33 / 2.98  1.23 / 1.98  1.03 / 1.08  0.98 / 1.14  1.10 / 1.28
K' <= 3 by BIC, plug-in               1.03 / 1.09  1.09 / 1.21  1.13 / 1.81  0.89 / 1.27  1.06 / 1.24
K' <= 3 by BIC, predictive (default)  1.01 / 1.01  1.12 / 1.32  1.03 / 1.08  1.00 / 1.11  1.01 / 1.02
====================================  ===========  ===========  ===========  ===========  ===========

(BIC chose K' = 1 on C1, 2 on C2 / C4 / C5 (> 99.9 %), 3 on C3 (99.3 %).) Neither fix alone
suffices: the predictive correction cannot rescue an over-fitted K (C1, C2 with K = 3),
and the right K with a plug-in threshold stays biased at low PFA (C3).

Causes (each measured):

1. Too many components for N samples: K = 3 on 2-component (or lognormal) clutter uses
   the extra component to follow the sampling noise of the upper tail; its tail is too
   light on average (C2: mean ln T 0.07 neper low at PFA 1e-5, with 1.6x the variance of
   a 2-component fit). Neither variance collapse (smallest fitted s: 1 % quantile 0.32 at
   tol 1e-5) nor thin components (top weight 0.26..0.35 in 90 % of rings) are the issue:
   the over-fit is spread over the whole top of the mixture. Remedy: choose K' <= K per
   cell by BIC (C2: K' = 2 in > 99.9 % of rings, C3: K' = 3 in 99.3 %, C1: K' = 1).
2. Estimation noise of the threshold (also for the right K): a threshold estimate with
   variance v gives E[S_true] ~ PFA exp(h^2 v / 2), h = f/S the log-tail slope, which
   grows as the PFA falls (C3 with K = 3 fixed: 1.13 at 1e-3, 1.81 at 1e-5). Remedy: the
   predictive correction below.
3. The EM stopping rule was an implicit regulariser: EM stopped at tol 1e-5 stays near its
   quantile initialisation; converged to the ML the plug-in is worse (C2, K = 2 fixed:
   1.09 / 1.21 at tol 1e-5, 1.25 / 2.64 converged; K = 3: 4.4 at 1e-5), so the old
   threshold depended on ``tol``. The predictive path uses the ML itself (Newton-polished),
   so its threshold no longer depends on the stopping rule (only the BIC choice does,
   through the likelihood at the EM's stop).
4. Not a cause: binning and the grid. EM on the raw samples (exact form), on bins of 1/8
   or 1/32 neper give the same ratios (C2: 1.125 / 1.126 / 1.125 at 1e-3); the grid form
   decides with the fast form's fit wherever a pixel is near its threshold.

The fit (``fit_threshold``): EM for K' = 1..K (``select="bic"``; components frozen at
weight 0 dropped), candidates ordered by ``BIC = -2 ln L + (3K' - 1) ln n``. With
``tail="predictive"`` the best candidate whose components are resolved (variance above the
EM's floor and, for a histogram, above h^2/9) is polished to the ML by damped Newton
(Levenberg-Marquardt) in theta = (logits of a, mu, ln s) with the analytic gradient and
Hessian (``mixture_grad_hess``; converged when the Newton decrement is < 1e-12, <= 30
steps; 5.9 steps on average on C2); if that fails the next candidate is tried (a
non-converging polish means the candidate is not identified), and a ring where none
qualifies (constant or quantised data) gets the plug-in threshold of the best EM fit.

The predictive correction (``predictive_shift``). With A the observed information at the
ML, ``dS`` the gradient of ``S(t)`` in theta and ``f`` the log-domain density, the
delta-method variance of the fitted ln T is ``v = dS^T A^-1 dS / f^2``. The Bayesian
posterior-predictive exceedance (flat prior, Laplace approximation, ln S linear in theta)
is ``S(t) exp(dS^T A^-1 dS / (2 S^2))``; solving it = PFA to first order about the plug-in
root t_p gives ``t = t_p + dS^T A^-1 dS / (2 f S) = t_p + h v / 2``, which is exactly the
shift that cancels the Jensen term of cause 2. For K' = 1 it is
``phi(z) s (1 + z^2/2) / (2 n PFA)`` and calibrated within 1 % at n = 1240, PFA 1e-5
(plug-in: +9 %; tests: test_predictive_shift_one_component). Sheppard-corrected scales
enter dS through d ln s / d ln s_fitted = s_fitted^2 / s^2. The shift is per cell and data
driven: on C2 0.03 neper on average at PFA 1e-3, 0.13 at PFA 1e-5.

Residual (not corrected): the ML tail of overlapping components is biased low by O(1/N)
(C2: mean ML ln T 0.035 neper below the truth at PFA 1e-3; oracle fits with known
allocation are unbiased), which the first-order correction does not address: +12 % at
PFA 1e-3 and +32 % at PFA 1e-5 on C2 (from +26 % / +128 %); removing it would need the
third-order (Cox-Snell) bias of the mixture ML. On clutter outside the model (gamma
intensity: ln x has a doubly exponential upper tail, lighter than any Gaussian) the
mixture over-estimates the tail and the FAR is below the PFA whatever the fit, more so
with fewer components: exponential clutter, PFA 1e-3: old default 0.19, new 0.15 of
nominal; 4-look gamma: 0.83 / 0.31 at PFA 1e-3 and 0.23 / 0.004 at PFA 1e-5 (BIC picks
K' = 2 there), i.e. the default threshold is ~0.9 dB higher than the old one (1.3 dB above
the ideal) at PFA 1e-5 on 4-look gamma sea. ``select="fixed"`` keeps K components.

Cost: EM for every K' <= K plus ~6 Newton steps: 1.9x the old per-fit time (below).
Tests: test_default_fit_is_calibrated_ring_level (the table's measure, C2 / C3, old path
rejected), test_default_false_alarm_count (end to end, every default but the PFA),
test_default_fit_matches_independent_reference (scipy ML / numpy information / brentq).

Decision and statistic
----------------------
Detected when ``ln x_t > t`` (float64). ``stat = float32(exp(ln x_t - t)) = x_t / T``; where
the float32 rounding would not exceed 1 it is the smallest float32 above 1, so
``mask == (stat > 1)`` (threshold of the statistic: 1). 0 where not detected.

Exact, fast and grid forms
--------------------------
``method="exact"``: the fit on the n raw ring samples of every pixel (ln of the block is
taken once). Cost ~ n K iterations exp() per pixel and K'.

``method="fast"``: the fit on the ring's *histogram* of y on a fixed global grid of bin width
``bin_width`` (default 1/8 neper; bin b covers ``[b h, (b + 1) h)``, the same for every
tile), each bin represented by its centre with weight = count. The histogram is integer,
slid along each row (about 4 x background updates per pixel), so it is exactly the same
for any tiling; EM then costs (number of non-empty bins) K exp() per iteration instead of
n K. Binning inflates each component variance by ~h^2/12 (Sheppard); it is subtracted
after the fit (floored at s^2/4). EM, Newton polish, BIC and threshold are the same code
as the exact form (``fit_threshold``, with the bin centres weighted by their counts).

Measured, thesis path (K = 3 fixed, plug-in; 2-core shared Xeon VM, one thread, float32,
defaults guard 21 / background 41 (N = 1240), PFA 1e-5, tol 1e-5, exponential clutter): exact 0.00032 Mpx/s
(~3100 s for 1000 x 1000, extrapolated from 100 x 100; mean 69 EM iterations), fast
0.0059 Mpx/s (168 s for 1000 x 1000, mean 75 iterations, 2.5 % of pixels hit max_iter):
~19x. The thesis (window not stated) reports MATLAB 37.5 s / Titan V 1.73 s: its window or
iteration count must be far smaller. The default path (BIC + predictive), same quiet VM,
CPU time of one thread, exponential clutter, PFA 1e-5: exact 5340 s/Mpx (60 x 60; thesis
path on the same run 2820), fast 204 s/Mpx (200 x 200; thesis path 109), mean work 125
(EM iterations over K' = 1..3 plus Newton steps; thesis path 70): 1.9x.
Agreement (tests/test_lmm.py, 96 x 96 lognormal-mixture scene with 8 ships, guard 7 /
background 17, PFA 1e-3; stated tolerance <= 0.1 % differing pixels and detections within
1): default path 3 of 9216 pixels differ (88 exact vs 91 fast), 33 vs 33 connected
detections; thesis path 2 (89 vs 91), 28 vs 29. On 96 x 96 mixture clutter (guard 11 /
background 41, K = 2 and 3, thesis path) no pixel differed. Hence the fast form replaces
the exact one (the grid form below is the default).
Calibration of the thesis path (fast, K = 2 fixed on a 2-component lognormal mixture,
N = 1560, 1024^2 px, PFA 1e-3): 1118 false alarms for 1049 expected (+6.6 %, bound 198;
512^2 px at PFA 4e-3, the same expected count, as in tests/test_lmm.py: 1101, +5.0 %); with
K = 3 on the same clutter 1274 (+21 %, section "Calibration"). The default path, grid form,
every default but the PFA (N = 1240, 512^2 px, PFA 4e-3, tests/test_lmm.py): 1121 (C2,
+6.9 %) and 1057 (C3, +0.8 %) for 1049 expected, the thesis path with K = 3 1182 / 1097;
at PFA 1e-3 on 1024^2 px: 1186 / 1059, thesis path K = 3 1324 (+26 %, outside) / 1189.
EM on a K = 3 mixture of non-mixture data (exponential clutter) converges slowly and the
plug-in tail threshold depends on the stopping rule (tol 1e-4 / 1e-5 / 1e-6: mean 24 / 71 /
223 iterations, threshold changes up to 0.9 / 0.6 / 0.3 nepers vs converged); the
predictive path thresholds the Newton-converged ML instead.

Grid form
---------
``method="grid"``: the fast form's fit (histogram of the ring, built directly at each
node: the same integer counts as the sliding one, hence the same ln T bit for bit) only at
nodes on a *global* grid, rows and columns at multiples of ``grid_step`` (default
``max(1, guard // 4)``, below) in
scene coordinates, so every tile computes the same nodes. A tile fits the nodes around its
core, which may lie in the halo: the halo is ``background // 2 + grid_step`` for this
form (``SPEC.halo_fn``). The node thresholds are bilinearly interpolated in ln T to each
pixel with fractions ``(r - r0) / grid_step`` of its global coordinates (nodes whose ring
holds fewer than ``max(8, 3K)`` usable samples are left out and the weights of the others
renormalised, in a fixed order): ``t_int``. Approximation: ln T is taken to vary linearly
between nodes; it fails next to bright targets, whose pixels lie in the *rings* of the
nearby nodes (raising their T) while lying in the guard of their own window.
Refinement (``grid_refine`` = r nepers, default 2, below): a pixel whose ``ln x_t`` exceeds
``min(t_int, surrounding valid node thresholds) - r`` is a candidate and its own fast fit
decides (and gives stat); every other pixel is not detected. With r > 0 the grid mask is
therefore exactly the fast mask restricted to the candidates (stat identical there);
``grid_refine = 0`` is pure interpolation (decide ``ln x_t > t_int``). ``grid_step = 1``
is the fast form bit for bit (slower).

Measured, thesis path (same VM, one thread, 1000 x 1000 exponential clutter, defaults, PFA 1e-5):
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
The default path (BIC + predictive): agreement scene, step 4 / refine 2: no pixel differs
from the fast form (refine 1: 8, pure interpolation: 55 of 9216); default windows with
ships (120 x 120): none. Default settings, 1000 x 1000 exponential clutter, PFA 1e-5, CPU
time of one thread on the quiet VM: 11.3 s (0.089 Mpx/s; thesis path on the same run
5.9 s), 51201 fits (nodes and candidates) at 220 us each.

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

from sarship.pipeline.gpu import is_device_array

from .base import DetectorParams, DetectorSpec, float_block, with_defaults

__all__ = ["LMMParams", "SPEC", "prepare", "detect", "em_fit_points", "mixture_threshold_log",
           "mixture_sf_log", "mixture_loglik", "mixture_grad_hess", "ml_newton", "predictive_shift",
           "fit_threshold", "init_z_table", "LMM_NOTES"]

#: Measured agreement / speed of the two forms: see the module docstring.
LMM_NOTES = "see module docstring"

DEFAULT_METHOD = "grid"


class LMMParams(with_defaults(DetectorParams, "LMMDefaults", pfa=1e-5, guard=21, background=41,
                              min_area_px=3, merge_px=2)):
    """LMM-CFAR parameters: the common ones plus the mixture / EM settings."""

    components: int = Field(3, ge=1, le=6, description="K, number of lognormal components (eq 3-1); with "
                                                       "select='bic' the most, K' <= K chosen per cell")
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
    select: str = Field("bic", pattern="^(bic|fixed)$",
                        description="'bic': per cell, K' <= components chosen by the BIC of the EM fits; "
                                    "'fixed': K' = components (the thesis)")
    tail: str = Field("predictive", pattern="^(predictive|plugin)$",
                      description="'predictive': ML fit (Newton-polished EM) and its threshold raised by the "
                                  "delta-method predictive correction (calibrated PFA); 'plugin': 1 - F(T) = PFA "
                                  "for the EM fit (thesis eq 3-5)")


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
        "select": p.select,
        "tail": p.tail,
        "max_iter": int(p.max_iter),
        "tol": float(p.tol),
        "bin_width": float(p.bin_width),
        "grid_step": grid_step(p),
        "grid_refine": float(p.grid_refine),
        "statistic": "x_t / T (T: 1 - F(T) = PFA for the fitted ring mixture); detected when > 1",
    }


def init_z_table(K: int) -> np.ndarray:
    """Row K' - 1 holds the EM's initial normal quantiles ``Phi^-1((k + 1/2)/K')``, k < K'."""
    t = np.zeros((K, K))
    for k1 in range(1, K + 1):
        t[k1 - 1, :k1] = special.ndtri((np.arange(k1) + 0.5) / k1)
    return t


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
# ML polish, choice of K and the predictive tail (module docstring, "Calibration")


@njit(nogil=True, cache=True)
def mixture_loglik(y, wt, n_pts, K, a, mu, s):
    """sum_j wt_j ln f(y_j) for the Gaussian mixture (a, mu, s) of K components, a_k > 0."""
    ca = np.empty(K)
    inv = np.empty(K)
    lt = np.empty(K)
    for k in range(K):
        ca[k] = math.log(a[k]) - math.log(s[k])
        inv[k] = 1.0 / s[k]
    ll = 0.0
    W = 0.0
    for j in range(n_pts):
        mx = -np.inf
        for k in range(K):
            u = (y[j] - mu[k]) * inv[k]
            t = ca[k] - 0.5 * u * u
            lt[k] = t
            if t > mx:
                mx = t
        tot = 0.0
        for k in range(K):
            tot += math.exp(lt[k] - mx)
        ll += wt[j] * (mx + math.log(tot))
        W += wt[j]
    return ll - W * _LOG_SQRT_2PI


@njit(nogil=True, cache=True)
def mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H):
    """Log-likelihood with its gradient ``G`` and Hessian ``H`` (filled in) in the
    unconstrained parameters theta = (eta_0..eta_{K-2}, mu_0..mu_{K-1}, lambda_0..lambda_{K-1}),
    ``a = softmax(eta_0, .., eta_{K-2}, 0)``, ``s = exp(lambda)``: p = 3K - 1 of them.

    Per point, ``ln f = logsumexp_k l_k`` with ``l_k = ln a_k - lambda_k - u_k^2/2 - ln sqrt(2 pi)``,
    ``u_k = (y - mu_k)/s_k``. With the responsibilities ``g_k`` and the scores ``d_k = grad l_k``
    (``d eta_m = [k == m] - a_m``, ``d mu_k = u_k/s_k``, ``d lambda_k = u_k^2 - 1``):
    ``grad ln f = sum_k g_k d_k`` and
    ``Hess ln f = sum_k g_k (Hess l_k + d_k d_k^T) - grad grad^T``, where ``Hess l_k`` is
    ``-(diag a - a a^T)`` on the etas and ``[[-1/s_k^2, -2 u_k/s_k], [., -2 u_k^2]]`` on
    ``(mu_k, lambda_k)``.
    """
    p = 3 * K - 1
    for q in range(p):
        G[q] = 0.0
        for r in range(p):
            H[q, r] = 0.0
    ca = np.empty(K)
    inv = np.empty(K)
    lt = np.empty(K)
    Gj = np.empty(p)
    for k in range(K):
        ca[k] = math.log(a[k]) - math.log(s[k])
        inv[k] = 1.0 / s[k]
    ll = 0.0
    W = 0.0
    for j in range(n_pts):
        w = wt[j]
        W += w
        yj = y[j]
        mx = -np.inf
        for k in range(K):
            u = (yj - mu[k]) * inv[k]
            t = ca[k] - 0.5 * u * u
            lt[k] = t
            if t > mx:
                mx = t
        tot = 0.0
        for k in range(K):
            e = math.exp(lt[k] - mx)
            lt[k] = e
            tot += e
        ll += w * (mx + math.log(tot))
        rt = 1.0 / tot
        for q in range(p):
            Gj[q] = 0.0
        # upper triangle (q <= r) of sum_k g_k (Hess l_k + d_k d_k^T), then grad
        for k in range(K):
            g = lt[k] * rt
            wg = w * g
            u = (yj - mu[k]) * inv[k]
            dmu = u * inv[k]
            dla = u * u - 1.0
            im = K - 1 + k
            il = 2 * K - 1 + k
            for m in range(K - 1):
                dm = (1.0 if m == k else 0.0) - a[m]
                Gj[m] += g * dm
                c = wg * dm
                for m2 in range(m, K - 1):
                    H[m, m2] += c * ((1.0 if m2 == k else 0.0) - a[m2])
                H[m, im] += c * dmu
                H[m, il] += c * dla
            Gj[im] += g * dmu
            Gj[il] += g * dla
            H[im, im] += wg * (dmu * dmu - inv[k] * inv[k])
            H[im, il] += wg * (dmu * dla - 2.0 * dmu)
            H[il, il] += wg * (dla * dla - 2.0 * u * u)
        for q in range(p):
            c = w * Gj[q]
            G[q] += c
            for r in range(q, p):
                H[q, r] -= c * Gj[r]
    for m in range(K - 1):
        for m2 in range(m, K - 1):
            H[m, m2] -= W * ((a[m] if m == m2 else 0.0) - a[m] * a[m2])
    for q in range(p):
        for r in range(q):
            H[q, r] = H[r, q]
    return ll - W * _LOG_SQRT_2PI


@njit(nogil=True, cache=True)
def _chol_solve(A, b, p, x, L):
    """x = A^-1 b for symmetric positive definite A (p x p) by Cholesky (L: work).
    Returns False, leaving x undefined, if A is not numerically positive definite."""
    for i in range(p):
        for j in range(i + 1):
            acc = A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not (acc > 1e-14 * abs(A[i, i])):
                    return False
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    for i in range(p):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    for i in range(p - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, p):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return True


@njit(nogil=True, cache=True)
def _from_theta(K, th, a, mu, s):
    """(a, mu, s) from theta; False if a weight or scale under/overflows."""
    mx = 0.0
    for k in range(K - 1):
        if th[k] > mx:
            mx = th[k]
    tot = math.exp(-mx)
    for k in range(K - 1):
        tot += math.exp(th[k] - mx)
    for k in range(K - 1):
        a[k] = math.exp(th[k] - mx) / tot
    a[K - 1] = math.exp(-mx) / tot
    ok = True
    for k in range(K):
        mu[k] = th[K - 1 + k]
        lam = th[2 * K - 1 + k]
        if not (-300.0 < lam < 300.0) or not (a[k] > 1e-300) or mu[k] != mu[k]:
            ok = False
        else:
            s[k] = math.exp(lam)
    return ok


@njit(nogil=True, cache=True)
def ml_newton(y, wt, n_pts, K, a, mu, s, A, max_steps):
    """Maximum likelihood from the start (a, mu, s) (all a_k > 0): damped Newton
    (Levenberg-Marquardt) on theta (see :func:`mixture_grad_hess`). A step is the Newton
    step when the observed information ``A = -Hess`` is positive definite, else (or if it
    does not increase the likelihood) a damped one, ``(A + lam diag|A|) d = grad``, lam
    x10 until it does. Converged when the Newton decrement ``grad^T A^-1 grad`` (~ twice
    the log-likelihood still to gain) is below 1e-12. (a, mu, s) are updated in place and
    ``A`` (p x p) holds the observed information at them. Returns (steps, converged,
    log-likelihood)."""
    p = 3 * K - 1
    th = np.empty(p)
    for k in range(K - 1):
        th[k] = math.log(a[k]) - math.log(a[K - 1])
    for k in range(K):
        th[K - 1 + k] = mu[k]
        th[2 * K - 1 + k] = math.log(s[k])
    G = np.empty(p)
    H = np.empty((p, p))
    M = np.empty((p, p))
    L = np.empty((p, p))
    d = np.empty(p)
    tn = np.empty(p)
    at = np.empty(K)
    mt = np.empty(K)
    st = np.empty(K)
    lam = 0.0
    steps = 0
    ok = False
    ll = mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H)
    while True:
        for q in range(p):
            for r in range(p):
                A[q, r] = -H[q, r]
        pd = _chol_solve(A, G, p, d, L)
        if pd:
            dec = 0.0
            for q in range(p):
                dec += G[q] * d[q]
            if dec < 1e-12:
                ok = True
                break
        if steps >= max_steps:
            break
        steps += 1
        accepted = False
        for _ in range(12):
            if lam > 0.0 or not pd:
                if lam == 0.0:
                    lam = 1e-4
                for q in range(p):
                    for r in range(p):
                        M[q, r] = A[q, r]
                    M[q, q] = A[q, q] + lam * (abs(A[q, q]) + 1e-300)
                if not _chol_solve(M, G, p, d, L):
                    lam *= 10.0
                    continue
            for q in range(p):
                tn[q] = th[q] + d[q]
            lln = -np.inf
            if _from_theta(K, tn, at, mt, st):
                lln = mixture_loglik(y, wt, n_pts, K, at, mt, st)
            if lln >= ll - 1e-13 * abs(ll):
                accepted = True
                break
            lam = 1e-4 if lam == 0.0 else lam * 10.0
        if not accepted:
            break
        for q in range(p):
            th[q] = tn[q]
        _from_theta(K, th, a, mu, s)
        lam = lam * 0.01 if lam > 1e-8 else 0.0
        ll = mixture_grad_hess(y, wt, n_pts, K, a, mu, s, G, H)
    return steps, ok, ll


@njit(nogil=True, cache=True)
def predictive_shift(t, K, a, mu, s, jac, A):
    """The predictive correction ``0.5 q / (f S)`` of the plug-in threshold ``t`` (nepers),
    ``q = dS^T A^-1 dS``: ``dS`` the gradient of ``S(t) = sum a_k Q((t - mu_k)/s_k)`` in theta
    (``dS/d eta_m = a_m (Q_m - S)``, ``dS/d mu_k = a_k phi(u_k)/s_k``,
    ``dS/d lambda_k = a_k phi(u_k) u_k jac_k``, jac: d lambda / d lambda_fitted, the Sheppard
    correction's), ``A`` the observed information, ``f`` the log-domain density at t.
    ``q / f^2`` is the delta-method variance of the fitted threshold. NaN when A is not
    positive definite or the tail is degenerate."""
    p = 3 * K - 1
    S, f = _sf_and_pdf(t, a, mu, s, K)
    if not (S > 0.0 and f > 0.0):
        return np.nan
    dS = np.empty(p)
    for k in range(K):
        u = (t - mu[k]) / s[k]
        ph = math.exp(-0.5 * u * u) / 2.5066282746310002
        if k < K - 1:
            dS[k] = a[k] * (0.5 * math.erfc(u * 0.7071067811865476) - S)
        dS[K - 1 + k] = a[k] * ph / s[k]
        dS[2 * K - 1 + k] = a[k] * ph * u * jac[k]
    x = np.empty(p)
    L = np.empty((p, p))
    if not _chol_solve(A, dS, p, x, L):
        return np.nan
    q = 0.0
    for r in range(p):
        q += dS[r] * x[r]
    sh = 0.5 * q / (f * S)
    if not (sh >= 0.0 and sh < np.inf):
        return np.nan
    return sh


@njit(nogil=True, cache=True)
def _resolved(K, s, res):
    for k in range(K):
        if not (s[k] * s[k] > res):
            return False
    return True


@njit(nogil=True, cache=True)
def fit_threshold(y, wt, n_pts, K, init_zs, max_iter, tol, shep, select, predictive, z, log_pfa,
                  a, mu, s):
    """The threshold t = ln T for one ring (weighted points y, wt); returns (t, work, K').

    1. EM (:func:`em_fit_points`) for K' = 1..K (``select``), or K' = K only; components
       frozen at weight 0 are dropped; the candidates are ordered by their BIC
       ``-2 ln L + (3K' - 1) ln n`` (n = sum wt, L at the EM's stopping point).
    2. ``predictive``: in BIC order, a candidate whose components are all resolved
       (variance above the EM's floor, 1e-4 of the sample variance, and for a histogram
       above h^2/9 = 4/3 shep) is polished to the ML by :func:`ml_newton` (<= 30 steps);
       the first that converges, stays resolved and has a finite predictive shift is used:
       ``t = t_plug + shift`` (``t_plug``: 1 - F = PFA for the ML mixture after the
       Sheppard correction ``s^2 - shep``, floored at s^2/4; shift:
       :func:`predictive_shift`). If none qualifies (degenerate rings: constant or
       quantised data), the plug-in threshold of the best-BIC EM fit.
       Not ``predictive``: the plug-in threshold of the best-BIC EM fit (``select=False``
       too: the thesis' EM + eq 3-5, the earlier behaviour bit for bit).
    ``init_zs[K' - 1, :K']``: the initial normal quantiles per K'. (a, mu, s) receive the
    chosen fit (first K' entries). ``work``: EM iterations (all K') + Newton steps.
    """
    Ka = np.zeros(K, np.int64)
    ca = np.zeros((K, K))
    cm = np.zeros((K, K))
    cs = np.ones((K, K))
    bic = np.full(K, np.inf)
    ta = np.empty(K)
    tm = np.empty(K)
    ts = np.empty(K)
    W = 0.0
    ym = 0.0
    for j in range(n_pts):
        W += wt[j]
        ym += wt[j] * y[j]
    ym /= W
    vy = 0.0
    for j in range(n_pts):
        vy += wt[j] * (y[j] - ym) * (y[j] - ym)
    vy /= W
    # smallest resolvable component variance: the EM's floor (1e-4 of the sample variance),
    # and for a histogram (shep = h^2/12 > 0) h^2/9, below which the Sheppard correction
    # is floored too (a component narrower than about a bin is not resolved by the counts)
    res = 1.0001e-4 * vy + 1e-12
    if 4.0 / 3.0 * shep > res:
        res = 4.0 / 3.0 * shep
    lnW = math.log(W)
    work = 0
    k0 = 1 if select else K
    for Kc in range(k0, K + 1):
        work += em_fit_points(y, wt, n_pts, Kc, init_zs[Kc - 1, :Kc], max_iter, tol, ta, tm, ts)
        m = 0
        for k in range(Kc):
            if ta[k] > 0.0:
                ca[Kc - 1, m] = ta[k]
                cm[Kc - 1, m] = tm[k]
                cs[Kc - 1, m] = ts[k]
                m += 1
        Ka[Kc - 1] = m
        bic[Kc - 1] = -2.0 * mixture_loglik(y, wt, n_pts, m, ca[Kc - 1], cm[Kc - 1], cs[Kc - 1]) \
            + (3 * m - 1) * lnW
    order = np.argsort(bic, kind="mergesort")  # stable: on a tie the smaller K' first
    jac = np.empty(K)
    if predictive:
        for oi in range(K - k0 + 1):
            c = order[oi]
            m = Ka[c]
            for k in range(m):
                a[k] = ca[c, k]
                mu[k] = cm[c, k]
                s[k] = cs[c, k]
            if not _resolved(m, s, res):
                continue
            A = np.empty((3 * m - 1, 3 * m - 1))
            st, ok, _ = ml_newton(y, wt, n_pts, m, a, mu, s, A, 30)
            work += st
            if not (ok and _resolved(m, s, res)):
                continue
            for k in range(m):
                v = s[k] * s[k]
                q = v - shep
                q = q if q > 0.25 * v else 0.25 * v
                jac[k] = v / q
                s[k] = math.sqrt(q)
            t = mixture_threshold_log(a, mu, s, m, z, log_pfa)
            sh = predictive_shift(t, m, a, mu, s, jac, A)
            if sh == sh:
                return t + sh, work, m
    c = order[0]
    m = Ka[c]
    for k in range(m):
        a[k] = ca[c, k]
        mu[k] = cm[c, k]
        v = cs[c, k] * cs[c, k]
        q = v - shep
        s[k] = math.sqrt(q if q > 0.25 * v else 0.25 * v)
    return mixture_threshold_log(a, mu, s, m, z, log_pfa), work, m


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
def _exact_kernel(block, halo, h, w, rb, rg, rt, K, init_zs, max_iter, tol, select, predictive, z,
                  log_pfa, nmin, mask, stat, iters):
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
            t, iters[i, j], _ = fit_threshold(buf, ones, n, K, init_zs, max_iter, tol, 0.0, select,
                                              predictive, z, log_pfa, a, mu, s)
            _decide(lx, t, i, j, mask, stat)


@njit(nogil=True, cache=True)
def _bin_index(block, inv_h):
    """Global ln-x bin of every value (floor(ln x / h)), offset to >= 0; -1 if unusable;
    with the offset and the smallest and largest bin used (bmax = -1: none)."""
    H, Wd = block.shape
    off = 1 + int(math.ceil(800.0 * inv_h))  # ln of positive float64 > -745
    B = np.empty((H, Wd), np.int32)
    bmin = 1 << 30
    bmax = -1
    for r in range(H):
        for c in range(Wd):
            x = np.float64(block[r, c])
            if x > 0.0 and x < np.inf:
                b = int(math.floor(math.log(x) * inv_h)) + off
                B[r, c] = b
                if b < bmin:
                    bmin = b
                if b > bmax:
                    bmax = b
            else:
                B[r, c] = -1
    return B, off, bmin, bmax


@njit(nogil=True, cache=True)
def _col(hist, B, r0, r1, c, d):
    for r in range(r0, r1):
        b = B[r, c]
        if b >= 0:
            hist[b] += d


@njit(nogil=True, cache=True)
def _fast_kernel(block, halo, h, w, rb, rg, rt, K, init_zs, max_iter, tol, select, predictive, z,
                 log_pfa, nmin, bw, mask, stat, iters):
    inv_h = 1.0 / bw
    B, off, bmin, bmax = _bin_index(block, inv_h)
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
            t, iters[i, j], _ = fit_threshold(yv, wv, n, K, init_zs, max_iter, tol, shep, select,
                                              predictive, z, log_pfa, a, mu, s)
            _decide(lx, t, i, j, mask, stat)


@njit(nogil=True, cache=True)
def _ring_hist_fit(B, hist, ci, cj, rb, rg, bmin, bmax, off, bw, yv, wv, K, init_zs, max_iter, tol,
                   select, predictive, z, log_pfa, nmin, a, mu, s):
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
    t, it, _ = fit_threshold(yv, wv, n, K, init_zs, max_iter, tol, bw * bw / 12.0, select, predictive,
                             z, log_pfa, a, mu, s)
    return t, it


@njit(nogil=True, cache=True)
def _grid_kernel(block, halo, h, w, rb, rg, rt, K, init_zs, max_iter, tol, select, predictive, z,
                 log_pfa, nmin, bw, step, refine, g0r, g0c, mask, stat, iters):
    """Grid form: fast (histogram) fit at global nodes (multiples of ``step``), ln T
    bilinearly interpolated. ``(g0r, g0c)``: global coordinates of the core's [0, 0];
    ``halo >= rb + step - 1`` so the ring of every needed node lies in the block."""
    inv_h = 1.0 / bw
    B, off, bmin, bmax = _bin_index(block, inv_h)
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
                                                init_zs, max_iter, tol, select, predictive, z, log_pfa,
                                                nmin, a, mu, s)
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
                                           init_zs, max_iter, tol, select, predictive, z, log_pfa, nmin,
                                           a, mu, s)
                    iters[i, j] = it
                    if t != t:
                        continue
                _decide(lx, t, i, j, mask, stat)


def detect(block, halo: int, origin, params: LMMParams, prep: dict, *, _iters: bool = False):
    """LMM-CFAR on one padded tile: ``(mask, stat)`` of the ``(h, w)`` core.

    ``stat = x_t / T`` (float32, > 1 where ``mask``; 0 elsewhere). ``origin`` (scene
    coordinates of ``block[0, 0]``) is used by the grid form only (global node positions). ``_iters=True`` also returns the
    per-pixel EM iteration counts (for tests / benchmarks). A CuPy ``block`` runs on its
    GPU (:mod:`sarship.pipeline.gpu.lmm`: the same fits, one CUDA thread per ring) and returns CuPy
    arrays (``_iters`` is not available there).
    """
    gpu = is_device_array(block)
    if not gpu:
        block = float_block(block)
    elif block.ndim != 2:
        raise ValueError(f"block must be 2-D, got shape {block.shape}")
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
    if gpu:  # CuPy block: the GPU twin (pipeline.gpu.lmm), one thread per ring fit
        from sarship.pipeline.gpu.lmm import detect as detect_gpu

        if halo > need:
            d = halo - need
            block = block[d: block.shape[0] - d, d: block.shape[1] - d]
            origin = (int(origin[0]) + d, int(origin[1]) + d)
            halo = need
        return detect_gpu(block, halo, origin, rb, rg, rt, K, prep, prep["method"], step,
                          float(prep.get("grid_refine", params.grid_refine)))
    mask = np.zeros((h, w), dtype=np.bool_)
    stat = np.zeros((h, w), dtype=np.float32)
    iters = np.zeros((h, w), dtype=np.int32)
    if h and w:
        if halo > need:  # trim the extra halo (kernels assume halo == need is enough)
            d = halo - need
            block = np.ascontiguousarray(block[d: block.shape[0] - d, d: block.shape[1] - d])
            origin = (int(origin[0]) + d, int(origin[1]) + d)
            halo = need
        init_zs = init_z_table(K)
        args = (block, halo, h, w, rb, rg, rt, K, init_zs, int(prep["max_iter"]), float(prep["tol"]),
                prep.get("select", params.select) == "bic", prep.get("tail", params.tail) == "predictive",
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
        "Lognormal-mixture CFAR: per-cell fit of a Gaussian mixture of ln x over the background "
        "ring (EM, K' <= K components by BIC, ML by Newton); threshold 1 - F(T) = PFA plus the "
        "predictive correction for the fit's finite-sample error"
    ),
    reference="Tsinghua thesis 2020 (seeds/000), chapter 3, eq 3-1, 3-4..3-7",
    params=LMMParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    halo_fn=_halo,
    halo_rule="background // 2 (+ grid_step for method='grid')",
    gpu=True,
)
