r"""Order-statistic CFAR (OS-CFAR) for L-look gamma intensity (exponential for L = 1).

Window
------
Square windows centred on the cell under test (CUT), sides ``target`` <= ``guard`` <
``background`` (all odd). The clutter samples are the ``N = background**2 - guard**2``
cells of the ring between the guard square (which contains the target area) and the
background square. The tested value ``x_t`` is the mean of the ``n = target**2`` cells of
the target window (``target = 1``: the CUT itself).

Rank convention
---------------
``k`` is the rank of the ring sample used as the clutter level counted in **ascending**
order, as in Rohling (1983): with the ring samples sorted ``X_(1) <= X_(2) <= ... <= X_(N)``
the clutter level is ``X_(k)``. The default is ``k = round(3N/4)`` (the 75th percentile of
the ring; exact, since N = B^2 - G^2 with B, G odd is a multiple of 8), so the estimate is
unaffected by up to ``N - k = N/4`` interfering targets (bright cells) in the ring.
The issue text that requested this detector says "k-th largest ... default 3N/4"; Rohling's
default 3N/4 is the ascending rank (the 75th percentile). Someone thinking in descending
order ("the j-th largest") converts with ``k = N - j + 1`` (the 3N/4-th *largest* would be
the 25th percentile, ``k = N/4 + 1``, which is not robust to N/4 bright interferers).
``1 <= k <= N`` is validated with the parameters.

Decision and statistic
----------------------
A pixel is detected when ``x_t > alpha * X_(k)``; ``stat = x_t / X_(k)`` (float32) is the
statistic compared with ``alpha``. Both sides are evaluated in float64 from the input
values (the float64 product ``alpha * X_(k)`` against the float64 mean ``x_t``); a NaN
ring sample ranks above every number (as in ``np.partition``), a NaN ``x_t`` is never
detected. ``stat`` is ``inf`` where ``X_(k) = 0``; where the float32 rounding of the
ratio (or a negative ``X_(k)``) would not exceed ``alpha`` it is the smallest float32
above ``alpha``, so ``stat > alpha`` wherever ``mask`` is set; it is 0 elsewhere.

Threshold multiplier
--------------------
Clutter intensity of mean ``mu``: ring samples ``mu * G_i / L`` with ``G_i ~ Gamma(L, 1)``
iid, and ``x_t = mu * Gamma(nL, 1) / (nL)`` (mean of n iid cells). The test is scale
invariant (CFAR); with ``G_(k)`` the k-th ordered unit-scale sample,

    P(x_t > alpha X_(k) | G_(k)) = Q(nL, n * alpha * G_(k)),      Q = regularized upper
                                                                     incomplete gamma,

and ``U = F_L(G_(k)) ~ Beta(k, N - k + 1)`` (F_L = P(L, .), the Gamma(L) CDF), hence

    PFA(alpha) = E[Q(nL, n alpha G_(k))]
               = int_0^1 Q(nL, n alpha F_L^{-1}(I^{-1}_{k, N-k+1}(t))) dt .

* Exponential clutter, single-cell target (L = 1, n = 1): Rohling (1983, eq. for the
  OS-CFAR false-alarm probability); Gandhi & Kassam (1988):

      PFA = prod_{i=0}^{k-1} (N - i) / (N - i + alpha)
          = exp(lnG(N+1) - lnG(N-k+1) + lnG(N-k+1+alpha) - lnG(N+1+alpha)),

  evaluated with ``gammaln`` and solved for ``alpha`` by ``brentq`` in ``log alpha``.
  For ``alpha > 1e5`` (tiny k with tiny PFA, e.g. k = 1: alpha ~ N / PFA) the gammaln
  difference cancels catastrophically (absolute error ~ eps * alpha ln alpha in log PFA),
  so the product is summed directly as ``-sum_i log1p(alpha / (N - i))``.
  Check: N = 20, k = 15, PFA = 1e-3 gives alpha = 6.855 (Richards 2005, Fundamentals of
  Radar Signal Processing, sec. 6.5, quotes 6.857).
* General L and n: the integral above, computed by composite Gauss-Legendre quadrature
  after the change of variable ``y = ln G_(k)`` (density of ``G_(k)`` = Beta(k, N-k+1)
  pdf of ``F_L(g)`` times the Gamma(L) pdf ``f_L(g)``):

      PFA = int Q(nL, n alpha e^y) beta_pdf(F_L(e^y)) f_L(e^y) e^y dy ,

  on ``[ln g_lo, ln g_hi]`` with ``g_lo``, ``g_hi`` the ``1e-10*pfa`` lower and ``1e-13``
  upper quantiles of ``G_(k)`` (truncation error below ``1e-10*pfa + 2e-13*PFA``). The
  ``t``-form is not integrated directly: near ``t = 0`` its integrand behaves like
  ``exp(-c t^(1/k))``, which Gauss-Legendre in ``t`` resolves badly when the lower tail of
  ``X_(k)`` dominates (small N, small PFA); in ``y`` the integrand is smooth and bell
  shaped. 128 panels x 16 nodes agree with the closed form (L = 1, n = 1) to 3e-9
  relative at worst over N = 8...1e6, k = 1...N, PFA = 1e-2...1e-12 (tests check 1e-6,
  and scipy's adaptive ``quad`` on the density of X_(k) for L = 2.5, 4 and n = 9).
  ``alpha`` is then found by ``brentq`` in ``log alpha`` on a bracket grown until the
  sign changes (PFA(alpha) decreases from 1 at alpha = 0 to 0). Results are cached on
  ``(N, k, L, n, pfa)``.

References: H. Rohling, "Radar CFAR thresholding in clutter and multiple target
situations", IEEE Trans. AES 19(4):608-621, 1983. P. P. Gandhi, S. A. Kassam, "Analysis
of CFAR processors in nonhomogeneous background", IEEE Trans. AES 24(4):427-445, 1988.

Speed
-----
A full selection over N ~ 2000 ring samples per pixel is the naive cost. The Numba kernel
(single-threaded ``@njit(nogil=True, cache=True)``, no fastmath) decides by *counting*
instead. With ``pred(v) = alpha * float64(v) < x_t`` (monotone in v, since rounding of
the product is monotone for alpha > 0),

    x_t > alpha X_(k)  <=>  pred(X_(k))  <=>  #{i : pred(X_i)} >= k ,

because the samples satisfying ``pred`` are exactly the smallest ones (ties included:
equality is not a detection). ``pred(v)`` equals ``v < c`` with ``c`` the smallest value
of the block's dtype for which ``pred`` fails (from ``x_t / alpha`` and a few
``nextafter`` steps), so the inner loop is a vectorised compare-and-count in the input
dtype, row segment by row segment, stopping as soon as the count reaches k (detected) or
the number of samples ``>= c`` exceeds ``N - k`` (not detected), after about N/4 samples
for clutter.

Most pixels never get there: an exact *screen* rejects them first. Every value has a
bin, the top 12 bits of its float32 pattern (rounded down from float64), monotone in the
value, with lower edge ``e[b] <= v``. A histogram of the two full-width bands of the ring
(rows rg+1...rb above and below the CUT, M = 2 (rb - rg) B samples) slides along the row
(4 (rb - rg) updates per pixel) with a pointer to the bin of its (M - (N - k))-th
smallest sample; at least N - k + 1 ring samples are then ``>= e[ptr]`` (or NaN), so
``alpha * e[ptr] >= x_t`` proves ``#{pred} <= k - 1``: not detected. For the default
windows the band bound sits near the 58th percentile of the clutter and rejects ~99.9 %
of clutter pixels. For the rare detected pixels ``X_(k)`` (for ``stat``) is found by one
radix step on the same bins and a quickselect inside one bin.

Measured (one thread, default windows target 1 / guard 41 / background 61, N = 2040,
k = 1530, PFA 1e-5, 1024 x 1024 float32 block, a shared 2-core Xeon VM): 22-27 Mpx/s on
exponential (L = 1) and L = 4 gamma clutter, also on K-textured clutter and across a
land/sea step (22-25 Mpx/s for float64 blocks); 4-6 Mpx/s with the screen off (count
only); ~7 Mpx/s on a scene with ~2 % ship pixels. The brute-force numpy reference
(``np.partition`` on ``sliding_window_view``) runs at 0.009-0.017 Mpx/s and
``scipy.ndimage.generic_filter`` at ~0.006 Mpx/s: ~2000-4000 x slower.
Everything is per pixel and independent of the tile origin (the target mean is summed
in a fixed row-major order), so masks and statistics are bit-identical however the scene
is tiled.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit
from pydantic import Field, model_validator
from scipy import special

from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.tiling import boxsum, intensity_absent

from .base import DetectorParams, DetectorSpec, float_block, with_defaults

__all__ = [
    "OSParams",
    "SPEC",
    "default_k",
    "detect",
    "os_pfa_exponential",
    "os_pfa_quadrature",
    "os_threshold_multiplier",
    "prepare",
]


# ---------------------------------------------------------------------------------------
# parameters


def default_k(n_ring: int) -> int:
    """Rohling's default rank: round(3N/4) in ascending order (the 75th percentile)."""
    return max(1, (3 * int(n_ring) + 2) // 4)


class OSParams(
    with_defaults(
        DetectorParams,
        "OSDefaults",
        pfa=1e-6,
        guard=21,
        background=41,
        merge_px=4,
        land_mask="texture",
        auto_min_area_px=10,
        auto_min_length_m=25.0,
        auto_min_area_m2=200.0,
    )
):
    """OS-CFAR parameters: the common ones plus the rank ``k``.

    Defaults chosen on real data by cross-validation (tuned on half A of SAR-Ship-Dataset,
    HRSID and OpenSARShip, reported on half B; bench/REALDATA.md). Size rule (unset
    ``min_area_px`` / ``min_length_m``): ships of at least 25 m and 200 m^2 when the scene's
    pixel spacing is known, of at least 10 px otherwise. Among the candidates tuned on half A,
    the best one that keeps the README's simulated K-sea demo at FoM >= 0.8 (the others, with
    41/81 windows, over-alarm on textured sea at 3 m).
    """

    k: int | None = Field(
        None,
        description=(
            "rank of the ring sample used as clutter level, counted in ASCENDING order "
            "(Rohling 1983: X_(1) <= ... <= X_(N), N = background^2 - guard^2); "
            "1 <= k <= N; default round(3N/4), the 75th percentile (robust to N/4 bright "
            "interferers in the ring). The j-th largest is k = N - j + 1."
        ),
    )

    nodata: float | None = Field(
        None,
        description="value marking absent pixels besides NaN (e.g. 0 for a zero-filled border); "
        "None: NaN only (exact zeros are data: 8-bit chips have them in dark sea)",
    )

    @model_validator(mode="after")
    def _rank(self):
        if self.k is not None:
            n = self.background**2 - self.guard**2
            if not 1 <= self.k <= n:
                raise ValueError(
                    f"k ({self.k}) must be in the range 1..N = {n} "
                    f"(N = background^2 - guard^2 = {self.background}^2 - {self.guard}^2 ring cells)"
                )
        return self

    @property
    def k_rank(self) -> int:
        """The rank used: ``k`` or, when unset, ``round(3N/4)``."""
        return int(self.k) if self.k is not None else default_k(self.n_ring)


# ---------------------------------------------------------------------------------------
# false-alarm probability and threshold multiplier


def _check_nk(n_ring: int, k: int) -> None:
    if not (int(n_ring) >= 1 and 1 <= int(k) <= int(n_ring)):
        raise ValueError(f"k ({k}) must be in the range 1..N = {n_ring}")


def os_pfa_exponential(alpha, n_ring: int, k: int):
    """Closed-form PFA of OS-CFAR in exponential clutter (L = 1, single-cell target).

    ``prod_{i=0}^{k-1} (N-i)/(N-i+alpha)``, evaluated in the log domain with gammaln.
    """
    _check_nk(n_ring, k)
    a = np.asarray(alpha, dtype=np.float64)
    n, kk = float(n_ring), float(k)
    lp = (
        special.gammaln(n + 1.0)
        - special.gammaln(n - kk + 1.0)
        + special.gammaln(n - kk + 1.0 + a)
        - special.gammaln(n + 1.0 + a)
    )
    big = a > _GAMMALN_ALPHA_MAX
    if np.any(big):
        # gammaln(N-k+1+alpha) - gammaln(N+1+alpha) cancels catastrophically for huge
        # alpha (absolute error ~ eps * alpha * ln(alpha)): sum the k factors instead.
        m = n - np.arange(int(k), dtype=np.float64)  # N, N-1, ..., N-k+1
        lp = np.array(lp, dtype=np.float64, copy=True)
        lp[big] = [-np.sum(np.log1p(ai / m)) for ai in np.atleast_1d(a[big])]
        lp = lp.reshape(a.shape)
    return np.exp(lp)


_GAMMALN_ALPHA_MAX = 1e5  # above: log PFA = -sum_i log1p(alpha / (N - i)), see below
_GL_NODES = 16
_GL_PANELS = 128


@functools.lru_cache(maxsize=256)
def _quadrature_rule(n_ring: int, k: int, looks: float, pfa_floor: float):
    """Nodes g_j (unit-scale G_(k) values) and weights w_j with E[h(G_(k))] ~ sum w_j h(g_j).

    Composite Gauss-Legendre in y = ln g over [ln g_lo, ln g_hi]; g_lo is the
    ``pfa_floor`` lower quantile of G_(k), g_hi its 1e-13 upper quantile.
    """
    n, kk, L = float(n_ring), float(k), float(looks)
    a_, b_ = kk, n - kk + 1.0  # U = F_L(G_(k)) ~ Beta(a_, b_); 1 - U ~ Beta(b_, a_)
    u_lo = float(special.betaincinv(a_, b_, pfa_floor))
    if not (u_lo > 0.0 and math.isfinite(u_lo)):
        u_lo = 1e-300
    g_lo = float(special.gammaincinv(L, u_lo))
    q_hi = float(special.betaincinv(b_, a_, 1e-13))  # 1 - u_hi, accurately
    if not (q_hi > 0.0 and math.isfinite(q_hi)):
        q_hi = 1e-300
    g_hi = float(special.gammainccinv(L, q_hi))
    if not (g_lo > 0.0 and math.isfinite(g_lo)):
        g_lo = 1e-300
    if not (g_hi > g_lo and math.isfinite(g_hi)):
        raise ValueError(f"cannot bracket the distribution of X_(k) (N={n_ring}, k={k}, L={looks})")
    y_lo, y_hi = math.log(g_lo), math.log(g_hi)
    x, w = np.polynomial.legendre.leggauss(_GL_NODES)
    edges = np.linspace(y_lo, y_hi, _GL_PANELS + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    y = (mid[:, None] + half[:, None] * x[None, :]).ravel()
    wy = (half[:, None] * w[None, :]).ravel()
    g = np.exp(y)
    log_u = np.log(special.gammainc(L, g))
    log_1mu = np.log(special.gammaincc(L, g))
    log_beta_pdf = (a_ - 1.0) * log_u + (b_ - 1.0) * log_1mu - special.betaln(a_, b_)
    log_gamma_pdf = (L - 1.0) * y - g - special.gammaln(L)
    with np.errstate(over="ignore", under="ignore"):
        weights = wy * np.exp(log_beta_pdf + log_gamma_pdf + y)
    weights[~np.isfinite(weights)] = 0.0
    g.setflags(write=False)
    weights.setflags(write=False)
    return g, weights


def os_pfa_quadrature(alpha, n_ring: int, k: int, looks: float = 1.0, n_target: int = 1, pfa_floor: float = 1e-20):
    """PFA of OS-CFAR for L-look gamma clutter and an n-cell mean target window.

    ``E[Q(nL, n alpha G_(k))]`` by Gauss-Legendre quadrature (see the module docstring).
    ``pfa_floor`` bounds the absolute truncation error of the lower tail.
    """
    _check_nk(n_ring, k)
    g, w = _quadrature_rule(int(n_ring), int(k), float(looks), float(pfa_floor))
    nl = float(n_target) * float(looks)
    a = np.asarray(alpha, dtype=np.float64)
    q = special.gammaincc(nl, float(n_target) * a[..., None] * g)
    return np.sum(q * w, axis=-1)


@functools.lru_cache(maxsize=1024)
def _alpha_cached(n_ring: int, k: int, looks: float, n_target: int, pfa: float, quadrature: bool) -> float:
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    if not quadrature:

        def log_pfa(u):
            p = float(os_pfa_exponential(math.exp(u), n_ring, k))
            return math.log(p) if p > 0.0 else -1e300
    else:
        floor = min(1e-20, 1e-10 * pfa)

        def log_pfa(u):
            p = float(os_pfa_quadrature(math.exp(u), n_ring, k, looks, n_target, floor))
            return math.log(p) if p > 0.0 else -1e300

    target = math.log(pfa)

    def f(u):
        return log_pfa(u) - target

    # PFA(alpha) decreases from 1 (alpha -> 0) to 0 (alpha -> inf): grow a bracket in
    # u = ln(alpha) until the sign changes.
    lo, hi = 0.0, 0.0
    f_hi = f(hi)
    if f_hi > 0.0:
        while f_hi > 0.0:
            lo, hi = hi, hi + 2.0
            if hi > 700.0:
                raise ValueError(f"no threshold multiplier reaches pfa={pfa} (N={n_ring}, k={k})")
            f_hi = f(hi)
    else:
        f_lo = f_hi
        while f_lo <= 0.0:
            hi, lo = lo, lo - 2.0
            if lo < -700.0:
                raise ValueError(f"no threshold multiplier reaches pfa={pfa} (N={n_ring}, k={k})")
            f_lo = f(lo)
    u = optimize.brentq(f, lo, hi, xtol=1e-13, rtol=4 * np.finfo(float).eps, maxiter=500)
    return float(math.exp(u))


def os_threshold_multiplier(
    n_ring: int, k: int, pfa: float, looks: float = 1.0, n_target: int = 1, method: str = "auto"
) -> float:
    """alpha such that ``P(x_t > alpha X_(k)) = pfa`` in homogeneous gamma clutter.

    ``method="auto"``: closed form (Rohling 1983) for ``looks == 1`` and ``n_target == 1``,
    Gauss-Legendre quadrature otherwise; ``"quadrature"`` forces the quadrature (checks).
    Cached on ``(N, k, L, n, pfa)``.
    """
    _check_nk(n_ring, k)
    if not (0.0 < pfa < 1.0):
        raise ValueError(f"pfa must be in (0, 1), got {pfa}")
    if not (looks > 0.0 and math.isfinite(looks)):
        raise ValueError(f"looks must be positive, got {looks}")
    if int(n_target) < 1:
        raise ValueError(f"n_target must be >= 1, got {n_target}")
    if method not in ("auto", "quadrature"):
        raise ValueError(f"method must be 'auto' or 'quadrature', got {method!r}")
    quad = method == "quadrature" or not (float(looks) == 1.0 and int(n_target) == 1)
    return _alpha_cached(int(n_ring), int(k), float(looks), int(n_target), float(pfa), quad)


# ---------------------------------------------------------------------------------------
# the detector


def prepare(params: OSParams) -> dict:
    """Scene-independent scalars: ring size, rank and the threshold multiplier."""
    if params.looks is None:
        raise ValueError("looks must be resolved")
    n_ring = int(params.n_ring)
    k = int(params.k_rank)
    if not 1 <= k <= n_ring:
        raise ValueError(f"k ({k}) must be in the range 1..N = {n_ring}")
    n_target = int(params.target) ** 2
    looks = float(params.looks)
    alpha = os_threshold_multiplier(n_ring, k, float(params.pfa), looks, n_target)
    exact = looks == 1.0 and n_target == 1
    return {
        "n_ring": n_ring,
        "k": k,
        "k_order": "ascending",
        "alpha": alpha,
        "looks": looks,
        "n_target": n_target,
        "pfa": float(params.pfa),
        "alpha_method": "closed_form" if exact else "quadrature",
    }


_NBINS = 4096  # float32 bit pattern >> 19: sign-less exponent + 4 mantissa bits
_BIN_SHIFT = 19
_NAN_BIN = _NBINS - 1


def _bin_edges() -> np.ndarray:
    """Lower edge of each screening bin (float64); bin 0 holds <= 0 and tiny subnormals."""
    b = np.arange(_NBINS, dtype=np.uint32)
    with np.errstate(invalid="ignore"):  # the bit patterns above +inf are NaNs
        edges = (b << np.uint32(_BIN_SHIFT)).view(np.float32).astype(np.float64)
    edges[0] = -np.inf
    edges[b > (np.uint32(0x7F800000) >> np.uint32(_BIN_SHIFT))] = np.inf  # NaN bin (and unused)
    return edges


_EDGES = _bin_edges()


@njit(nogil=True, cache=True)
def _bins_from_bits(u, out):
    """Screening bin of each value from its float32 bits (monotone in the value)."""
    for i in range(u.shape[0]):
        for j in range(u.shape[1]):
            v = u[i, j]
            if (v & np.uint32(0x7FFFFFFF)) > np.uint32(0x7F800000):
                out[i, j] = _NAN_BIN
            elif v >= np.uint32(0x80000000):
                out[i, j] = 0
            else:
                out[i, j] = np.uint16(v >> np.uint32(_BIN_SHIFT))


def _screen_bins(block: np.ndarray) -> np.ndarray:
    """uint16 bins such that every value v in bin b satisfies v >= edge[b] (or is NaN)."""
    if block.dtype == np.float32:
        f32 = block
    else:  # round DOWN to float32, so that edge[bin(v)] <= float32(v) <= v still holds
        with np.errstate(over="ignore", invalid="ignore"):
            f32 = block.astype(np.float32)
            up = f32.astype(np.float64) > block
        f32[up] = np.nextafter(f32[up], np.float32(-np.inf))
    out = np.empty(block.shape, dtype=np.uint16)
    _bins_from_bits(np.ascontiguousarray(f32).view(np.uint32), out)
    return out


@njit(nogil=True, cache=True)
def _count_below(row, c0, c1, c):
    # a slice plus non-negative indexing lets LLVM vectorise the compare-and-count
    # (indexing row[q] with a signed q adds wraparound handling and gathers)
    seg = row[c0:c1]
    cnt = np.int32(0)
    for q in range(seg.shape[0]):
        cnt += np.int32(seg[q] < c)
    return cnt


@njit(nogil=True, cache=True)
def _hist_segment(brow, c0, c1, hist):
    seg = brow[c0:c1]
    for q in range(seg.shape[0]):
        hist[seg[q]] += 1


@njit(nogil=True, cache=True)
def _gather_bin(row, brow, c0, c1, tb, buf, m):
    # branch-free compaction of the samples whose bin is tb
    seg = row[c0:c1]
    bseg = brow[c0:c1]
    for q in range(seg.shape[0]):
        buf[m] = np.float64(seg[q])
        m += np.int64(bseg[q] == tb)
    return m


@njit(nogil=True, cache=True)
def _kth_ring(block, bins, ci, cj, rb, rg, k, hist, buf):
    """k-th smallest ring sample of the CUT (ci, cj); requires it to be a number.

    bins are monotone in the value (s < s' => bin(s) <= bin(s')), so the k-th smallest
    is the (k - #below its bin)-th smallest of its bin. A plain quickselect on ~2000
    random values costs ~15 us in branch mispredictions; this costs a few us.
    """
    for a in range(-rb, rb + 1):
        brow = bins[ci + a]
        if a < -rg or a > rg:
            _hist_segment(brow, cj - rb, cj + rb + 1, hist)
        else:
            _hist_segment(brow, cj - rb, cj - rg, hist)
            _hist_segment(brow, cj + rg + 1, cj + rb + 1, hist)
    cum = 0
    tb = 0
    while cum + hist[tb] < k:
        cum += hist[tb]
        tb += 1
    hist[:] = 0
    m = 0
    for a in range(-rb, rb + 1):
        row = block[ci + a]
        brow = bins[ci + a]
        if a < -rg or a > rg:
            m = _gather_bin(row, brow, cj - rb, cj + rb + 1, tb, buf, m)
        else:
            m = _gather_bin(row, brow, cj - rb, cj - rg, tb, buf, m)
            m = _gather_bin(row, brow, cj + rg + 1, cj + rb + 1, tb, buf, m)
    return _select(buf, m, k - cum - 1)


@njit(nogil=True, cache=True)
def _select(a, n, k):
    """k-th smallest (0-based) of a[:n] (no NaN), in place: Hoare quickselect."""
    lo = 0
    hi = n - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        piv = a[mid]
        i = lo
        j = hi
        while i <= j:
            while a[i] < piv:
                i += 1
            while piv < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


@njit(nogil=True, cache=True)
def _hist_column(hist, bins, r0, r1, col, ptr, d):
    """Add (d = 1) or remove (d = -1) bins[r0:r1, col]; return the change of #(bin < ptr)."""
    lt = 0
    for r in range(r0, r1):
        b = bins[r, col]
        hist[b] += d
        if b < ptr:
            lt += d
    return lt


@njit(nogil=True, cache=True)
def _os_kernel(block, bins, edges, halo, h, w, rb, rg, rt, k, alpha, stat_floor, screen, mask, stat):
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    max_above = n_ring - k
    n_cells = float((2 * rt + 1) ** 2)
    wb = 2 * rb + 1
    one = np.empty(1, block.dtype)
    one[0] = np.inf
    pinf = one[0]
    one[0] = -np.inf
    ninf = one[0]
    buf = np.empty(n_ring + 1, np.float64)  # +1: _gather_bin writes one past the last kept
    # screen: the two full-width bands of the ring (rows rg+1..rb above and below the CUT)
    # hold m_band samples; if at least need_above of them are certainly not below c, the
    # pixel is not detected. The band histogram slides along the row (4 * (rb - rg)
    # updates per pixel) and ptr tracks the bin of its r_band-th smallest sample.
    m_band = 2 * (rb - rg) * wb
    need_above = max_above + 1
    r_band = m_band - need_above + 1
    use_screen = screen and r_band >= 1
    hist = np.zeros(edges.shape[0], np.int32)
    sel_hist = np.zeros(edges.shape[0], np.int32)
    for i in range(h):
        ci = i + halo
        ptr = 0
        n_lt = 0
        if use_screen:
            hist[:] = 0
            for col in range(halo - rb, halo + rb + 1):
                _hist_column(hist, bins, ci - rb, ci - rg, col, 0, 1)
                _hist_column(hist, bins, ci + rg + 1, ci + rb + 1, col, 0, 1)
        for j in range(w):
            cj = j + halo
            if use_screen:
                if j > 0:
                    n_lt += _hist_column(hist, bins, ci - rb, ci - rg, cj - 1 - rb, ptr, -1)
                    n_lt += _hist_column(hist, bins, ci + rg + 1, ci + rb + 1, cj - 1 - rb, ptr, -1)
                    n_lt += _hist_column(hist, bins, ci - rb, ci - rg, cj + rb, ptr, 1)
                    n_lt += _hist_column(hist, bins, ci + rg + 1, ci + rb + 1, cj + rb, ptr, 1)
                # invariant: n_lt = #(band bins < ptr) < r_band <= n_lt + hist[ptr]
                while n_lt >= r_band:
                    ptr -= 1
                    n_lt -= hist[ptr]
                while n_lt + hist[ptr] < r_band:
                    n_lt += hist[ptr]
                    ptr += 1
            if rt == 0:
                xt = np.float64(block[ci, cj])
            else:
                s = 0.0
                for a in range(ci - rt, ci + rt + 1):
                    for b in range(cj - rt, cj + rt + 1):
                        s += np.float64(block[a, b])
                xt = s / n_cells
            if not (xt == xt):  # NaN target: never detected
                continue
            # >= need_above band samples are >= edges[ptr] (or NaN): none of them is below
            # when alpha * edges[ptr] >= xt (product rounding is monotone)
            if use_screen and alpha * edges[ptr] >= xt:
                continue
            # c: the smallest value v of the block's dtype with not (alpha * v < xt)
            one[0] = xt / alpha
            c = one[0]
            if c != c:
                continue
            while alpha * np.float64(c) < xt:
                c = np.nextafter(c, pinf)
            while True:
                p = np.nextafter(c, ninf)
                if p == c or alpha * np.float64(p) < xt:
                    break
                c = p
            # count ring samples < c, row segment by row segment, with early exits
            below = 0
            above = 0
            hit = False
            for a in range(-rb, rb + 1):
                row = block[ci + a]
                if a < -rg or a > rg:
                    cnt = _count_below(row, cj - rb, cj + rb + 1, c)
                    below += cnt
                    above += wb - cnt
                else:
                    cnt = _count_below(row, cj - rb, cj - rg, c)
                    cnt2 = _count_below(row, cj + rg + 1, cj + rb + 1, c)
                    below += cnt + cnt2
                    above += 2 * (rb - rg) - cnt - cnt2
                if below >= k:
                    hit = True
                    break
                if above > max_above:
                    break
            if not hit:
                continue
            mask[i, j] = True
            # exact X_(k) by a radix step on the (value-monotone) bins, then a small
            # quickselect inside the one bin that holds it (see _kth_ring)
            xk = _kth_ring(block, bins, ci, cj, rb, rg, k, sel_hist, buf)
            if xk > 0.0:
                r = np.float32(xt / xk)
            elif xk == 0.0:
                r = np.float32(np.inf)
            else:
                r = np.float32(stat_floor)
            if not (np.float64(r) > alpha):
                r = np.float32(stat_floor)
            stat[i, j] = r


def rank_for(k: int, n_ring: int, n_valid: int) -> int:
    """The rank used with ``n_valid`` present ring cells: ``round(n_valid * k / N)`` in 1..n_valid
    (the same quantile of the ring; ``k`` itself when the ring is complete)."""
    return min(max(1, (2 * int(n_valid) * int(k) + int(n_ring)) // (2 * int(n_ring))), int(n_valid))


@njit(nogil=True, cache=True)
def _os_partial(xn, halo, ii, jj, kv, rb, rg, rt, ktab, atab, alpha_n, floor_n, mask, stat):
    """OS-CFAR on the listed core pixels (ii, jj) with kv present ring cells: the rank and
    multiplier of their count (``ktab[kv]``, ``atab[kv]``); absent cells are NaN in ``xn``.
    The statistic is ``(x_t / X_(k)) * alpha_N / alpha_K`` (so ``stat > alpha_N`` exactly where
    detected, as for complete rings; ``floor_n``: the smallest float32 above alpha_N)."""
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    buf = np.empty(n_ring, np.float64)
    n_cells = float((2 * rt + 1) ** 2)
    for q in range(ii.shape[0]):
        i = ii[q]
        j = jj[q]
        ci = i + halo
        cj = j + halo
        kk = kv[q]
        if rt == 0:
            xt = np.float64(xn[ci, cj])
        else:
            sacc = 0.0
            for a in range(ci - rt, ci + rt + 1):
                for b in range(cj - rt, cj + rt + 1):
                    sacc += np.float64(xn[a, b])
            xt = sacc / n_cells
        m = 0
        for a in range(-rb, rb + 1):
            for b in range(-rb, rb + 1):
                if -rg <= a <= rg and -rg <= b <= rg:
                    continue
                v = np.float64(xn[ci + a, cj + b])
                if v == v:
                    buf[m] = v
                    m += 1
        k = ktab[m]
        alpha = atab[m]
        if not (xt == xt) or m != kk:
            continue
        xk = _select(buf, m, k - 1)
        if not (alpha * xk < xt):
            continue
        mask[i, j] = True
        if xk > 0.0:
            r = np.float32((xt / xk) * (alpha_n / alpha))
        elif xk == 0.0:
            r = np.float32(np.inf)
        else:
            r = np.float32(floor_n)
        if not (np.float64(r) > alpha_n):
            r = np.float32(floor_n)
        stat[i, j] = r


def _stat_floor(alpha: float) -> float:
    a32 = np.float32(alpha)
    if not float(a32) > alpha:
        a32 = np.nextafter(a32, np.float32(np.inf))
    return float(a32)


def absent_redo(block, ok, halo, origin, params: OSParams, prep: dict, mask, stat, box=None):
    """OS-CFAR on the pixels whose background window meets an absent cell: K present ring
    cells, rank ``rank_for(k, N, K)``, its exact multiplier; fewer than ``ceil(N/2)`` present
    cells or an absent cell in the target window: not tested. NumPy arrays, in place."""
    rb, rg, rt = int(params.background) // 2, int(params.guard) // 2, int(params.target) // 2
    b, g, t = 2 * rb + 1, 2 * rg + 1, 2 * rt + 1
    n_ring = int(prep["n_ring"])
    K, nb, nt = intensity_absent.counts(ok, halo, origin, b, g, t, box or boxsum.centered_box_sum)
    redo = nb < float(b * b)
    mask[redo] = False
    stat[redo] = 0
    tested = redo & (nt == float(t * t)) & (K >= float(intensity_absent.min_valid(n_ring)))
    ii, jj = np.nonzero(tested)
    if not ii.size:
        return
    kv = K[ii, jj].astype(np.int64)
    k0, looks, pfa = int(prep["k"]), float(prep["looks"]), float(prep["pfa"])
    ktab = np.zeros(n_ring + 1, np.int64)
    atab = np.full(n_ring + 1, np.nan)
    for kk in np.unique(kv):
        kr = rank_for(k0, n_ring, int(kk))
        ktab[kk] = kr
        atab[kk] = os_threshold_multiplier(int(kk), kr, pfa, looks, t * t)
    xn = intensity_absent.fill(block, ok, np.nan)
    _os_partial(
        xn,
        halo,
        ii.astype(np.int64),
        jj.astype(np.int64),
        kv,
        rb,
        rg,
        rt,
        ktab,
        atab,
        float(prep["alpha"]),
        _stat_floor(float(prep["alpha"])),
        mask,
        stat,
    )


def detect(block, halo: int, origin, params: OSParams, prep: dict, *, _screen: bool = True):
    """OS-CFAR on one padded tile: ``(mask, stat)`` of the ``(h, w)`` core.

    ``block`` has shape ``(h + 2*halo, w + 2*halo)``; ``halo >= background // 2``.
    ``stat = x_t / X_(k)`` (float32; > alpha where ``mask``; 0 elsewhere). ``origin`` is
    not needed: every pixel's maths depends only on its own window. ``_screen=False``
    turns off the (exact) histogram screen; for tests and benchmarks. A CuPy ``block`` runs
    on its GPU (:func:`sarship.pipeline.gpu.cfar.os_cfar`: the same exact comparisons, so the same
    mask and statistic) and returns CuPy arrays.
    """
    gpu = is_device_array(block)
    if not gpu:
        block = float_block(block)
    halo = int(halo)
    rb, rg, rt = int(params.background) // 2, int(params.guard) // 2, int(params.target) // 2
    if halo < rb:
        raise ValueError(f"halo ({halo}) must be at least background // 2 = {rb}")
    h, w = block.shape[0] - 2 * halo, block.shape[1] - 2 * halo
    if h < 0 or w < 0:
        raise ValueError(f"block {block.shape} is smaller than twice the halo ({halo})")
    n_ring = (2 * rb + 1) ** 2 - (2 * rg + 1) ** 2
    k = int(prep["k"])
    if int(prep.get("n_ring", n_ring)) != n_ring or not 1 <= k <= n_ring:
        raise ValueError(f"prep (n_ring={prep.get('n_ring')}, k={k}) does not match the windows (N={n_ring})")
    alpha = float(prep["alpha"])
    if not (alpha > 0.0 and math.isfinite(alpha)):
        raise ValueError(f"alpha must be positive and finite, got {alpha}")
    a32 = np.float32(alpha)
    if not float(a32) > alpha:
        a32 = np.nextafter(a32, np.float32(np.inf))
    if gpu:
        return SPEC.twin()(block, halo, rb, rg, rt, k, alpha, float(a32), origin=origin, params=params, prep=prep)
    mask = np.zeros((h, w), dtype=np.bool_)
    stat = np.zeros((h, w), dtype=np.float32)
    ok = intensity_absent.present(block, params.nodata)
    complete = bool(ok.all())
    xb = block if complete else intensity_absent.fill(block, ok, np.nan)
    if h and w:
        bins = _screen_bins(xb)
        _os_kernel(xb, bins, _EDGES, halo, h, w, rb, rg, rt, k, alpha, float(a32), bool(_screen), mask, stat)
        if not complete:  # absent pixels (module docstring of pipeline.intensity_absent)
            absent_redo(xb, ok, halo, origin, params, prep, mask, stat)
    return mask, stat


SPEC = DetectorSpec(
    name="os_cfar",
    summary=(
        "Order-statistic CFAR: x_t > alpha * X_(k), X_(k) the k-th smallest ring sample "
        "(default k = 3N/4); exact alpha for L-look gamma clutter"
    ),
    reference=(
        "Rohling 1983, IEEE Trans. AES 19(4):608-621; Gandhi & Kassam 1988, IEEE Trans. AES "
        "24(4):427-445; docs/algorithms/cfar.md"
    ),
    params=OSParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=True,
    gpu="sarship.pipeline.gpu.cfar:os_cfar",
)
