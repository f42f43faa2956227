"""Adaptive polarimetric whitening filter + CFAR (``apwf``), exact threshold.

Source: chapter 2 of Sun Tianyu's Tsinghua thesis (2020); docs/algorithms/apwf.md, bibliography
in docs/references.md.

Model. The scattering vector of a pixel, X = [S_hh, S_hv, S_vv]^T (quad-pol, p = 3) or
two channels (dual-pol, p = 2, e.g. [S_vh, S_vv]; order: :func:`sarship.pipeline.tiling.inputs.polarimetric_source`),
is zero-mean circular complex Gaussian over sea clutter with covariance Sigma = E[X X^H]
(eq 2-1 to 2-3). The polarimetric whitening filter (PWF) is the quadratic form

    y = X^H Sigma^-1 X                                                     (eq 2-6, A* = Sigma^-1)

whose closed form under reflection symmetry is eq 2-8 (used as a test oracle; here the
general Hermitian inverse is used, any Sigma). With the true Sigma, y is Gamma(p, 1).

Adaptive estimate (the choice made here). Sigma is estimated per pixel as the sample mean
of X X^H over N clutter cells of a sliding window centred on the cell under test (CUT):

* ``estimator="ring"`` (default): the ring between the ``guard`` and ``background`` windows,
  N = background^2 - guard^2; the CUT and the ship around it are not in the estimate
  (the better default).
* ``estimator="window"``: the thesis' reading, the whole ``background`` window including
  the CUT, N = background^2 (``guard`` is not used).

Window sums of the p^2 real numbers of X X^H (the p powers |X_i|^2 and the real and
imaginary parts of the p(p-1)/2 upper-triangle products X_i X_j^*) are box sums
(:func:`sarship.pipeline.tiling.boxsum.centered_box_sum`: O(1) per pixel whatever the window, and
bit-identical for any tiling), the speed-up the thesis missed (it forms the 3 x N by N x 3
product per pixel). Then, per pixel in Numba, y = N X^H S^-1 X with S the window sum
(S / N the covariance estimate), from the closed-form adjugate of the Hermitian 2x2 / 3x3
S (:func:`herm_inv`): y = N (X^H adj(S) X) / det(S). A degenerate estimate (det(S) <= 0,
e.g. an all-zero region) gives y = 0 when X = 0, else +inf.

Threshold (exact for N independent clutter samples; mask = y > T, stat = y):

* ``ring``: S ~ complex Wishart(N, Sigma) independent of X, so y/N = X^H S^-1 X is
  beta-prime(p, N - p + 1): the density of eq 2-9. PFA(T) = 1 - I_{T/(T+N)}(p, N - p + 1)
  (regularised incomplete beta); by I_x(a, b) = 1 - I_{1-x}(b, a),
  z = betaincinv(N - p + 1, p, PFA), T = N (1 - z) / z (``scipy.special.betaincinv``).
* ``window``: S = X X^H + S0, S0 the sum over the other N - 1 cells. Sherman-Morrison gives
  X^H S^-1 X = q / (1 + q), q = X^H S0^-1 X ~ beta-prime(p, N - p), so y/N is exactly
  Beta(p, N - p) (bounded: y < N). PFA(T) = 1 - I_{T/N}(p, N - p),
  T = N (1 - betaincinv(N - p, p, PFA)). Eq 2-9 does not apply to this estimator.
* Large N, both: eq 2-10, PFA = exp(-T) sum_{k<p} T^k / k! (the Gamma(p, 1) tail of the
  known-Sigma PWF), T = gammainccinv(p, PFA) (no Newton iteration needed). It is only the
  N -> infinity limit: with small windows (N ~ 100) it overshoots the PFA several-fold
  (recorded in ``prepare`` as ``threshold_large_n``, not used).

Absent pixels (no data; not in the thesis, which assumes complete data). A pixel whose
data is not finite (NaN) or has no signal (all channels, or the covariance diagonal, exactly
0: a zero-filled border or a declared no-data value of 0) is absent
(:mod:`sarship.pipeline.tiling.polsar_absent`): its products are zeroed before the window sums and
it is not counted, so each pixel's estimate uses its K <= N valid cells (K from the same
tiling-invariant box sums, of the validity plane): y = K X^H S^-1 X with S the sum over the
K valid cells, compared with the exact threshold T(K) of the formulas below (N replaced by
K; the thresholds of the counts present in a tile are computed there). A pixel is not
tested (decision 0, stat 0) when it is absent itself or when K < ``min_valid(N, p)`` =
max(ceil(N / 2), p + 1): the threshold is exact for any K > p, so the minimum is about the
estimate's representativeness, not calibration; half the cells keeps every pixel along a
straight edge testable (a straight edge through or next to the CUT removes less than half of
a centred ring or window), while pixels in a corner or a narrow strip of data, whose Sigma
would come from one side only, are not tested. Where K < N the statistic reported (``stat``)
is y T(N) / T(K), the same ratio to its threshold, so stat > T(N) wherever mask is set.
Without absent pixels K = N everywhere and nothing changes, bit for bit.

Neighbouring pixels' speckle is assumed independent (as in the simulator); mirror-extended
borders (the thesis' choice) repeat samples, so the threshold is approximate within
background // 2 of the scene edge. Halo: background // 2. Only ``target = 1`` (the CUT is
one pixel).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator
from scipy import special

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.gpu import is_device_array, to_host
from sarship.pipeline.tiling.boxsum import centered_box_sum
from sarship.pipeline.tiling.polsar_absent import present, zero_absent

#: Fewest valid cells in a pixel's estimate, as a fraction of N (see the module docstring).
MIN_VALID_FRACTION = 0.5

#: Core rows / columns processed at once (bounds the float64 intermediates of a tile).
STRIP_ROWS = 256
STRIP_COLS = 1024


class APWFParams(
    with_defaults(DetectorParams, "APWFDefaults", pfa=1e-6, guard=41, background=61, min_area_px=2, merge_px=5)
):
    """Parameters of ``apwf`` (the shared parameters plus ``estimator``)."""

    estimator: Literal["ring", "window"] = Field(
        "ring",
        description="clutter cells estimating Sigma: 'ring' (between guard and background "
        "windows) or 'window' (the thesis: the whole background window, CUT included)",
    )

    @model_validator(mode="after")
    def _target_one(self):
        if self.target != 1:
            raise ValueError(f"apwf tests single pixels: target must be 1, got {self.target}")
        return self

    def n_samples(self) -> int:
        """N, the number of cells in the covariance estimate."""
        if self.estimator == "window":
            return self.background**2
        return self.n_ring


# ------------------------------------------------------------------------------ thresholds


def threshold(pfa: float, p: int, n: int, estimator: str = "ring") -> float:
    """Exact T with P(y > T) = pfa for the adaptive PWF with an N-sample estimate."""
    if n <= p:
        raise ValueError(f"need more than p = {p} samples in the covariance estimate, got N = {n}")
    if estimator == "ring":
        z = float(special.betaincinv(n - p + 1, p, pfa))  # = N / (T + N)
        return n * (1.0 - z) / z
    if estimator == "window":
        return n * (1.0 - float(special.betaincinv(n - p, p, pfa)))
    raise ValueError(f"estimator must be 'ring' or 'window', got '{estimator}'")


def pfa_exact(t: float, p: int, n: int, estimator: str = "ring") -> float:
    """P(y > t) for the adaptive PWF (inverse of :func:`threshold`)."""
    if estimator == "ring":
        return float(special.betainc(n - p + 1, p, n / (t + n)))
    return float(special.betainc(n - p, p, 1.0 - t / n)) if t < n else 0.0


def min_valid(n: int, p: int) -> int:
    """Fewest valid cells K for which a pixel is tested: max(ceil(N / 2), p + 1)."""
    return max(int(math.ceil(MIN_VALID_FRACTION * n)), p + 1)


def count_thresholds(counts, pfa: float, p: int, estimator: str = "ring") -> np.ndarray:
    """:func:`threshold` for an array of valid-cell counts K (float64, vectorised; K > p)."""
    k = np.asarray(counts, np.float64)
    if estimator == "ring":
        z = special.betaincinv(k - p + 1, p, pfa)
        return k * (1.0 - z) / z
    return k * (1.0 - special.betaincinv(k - p, p, pfa))


def threshold_map(K, tested, pfa: float, p: int, estimator: str, n_full: float, thr_full: float):
    """Per-pixel threshold T(K) (NumPy or CuPy like ``K``): ``thr_full`` where K = N,
    :func:`count_thresholds` of the tile's distinct partial counts elsewhere, +inf where
    the pixel is not tested."""
    xp = np
    if is_device_array(K):
        import cupy as xp
    T = xp.full(K.shape, np.inf, np.float64)
    T[tested & (K == n_full)] = thr_full
    part = tested & (K != n_full)
    if bool(part.any()):
        kp = K[part]
        u = xp.unique(kp)
        tu = xp.asarray(count_thresholds(to_host(u), pfa, p, estimator))
        T[part] = tu[xp.searchsorted(u, kp)]
    return T


def threshold_large_n(pfa: float, p: int) -> float:
    """Eq 2-10: T with exp(-T) sum_{k<p} T^k/k! = pfa (the N -> infinity limit)."""
    return float(special.gammainccinv(p, pfa))


def prepare(prm: APWFParams) -> dict:
    n = prm.n_samples()
    dist = (
        "y/N ~ beta-prime(p, N-p+1) (eq 2-9)"
        if prm.estimator == "ring"
        else "y/N ~ Beta(p, N-p) (CUT in its own estimate; Sherman-Morrison)"
    )
    return {
        "n_samples": n,
        "min_valid": {str(p): min_valid(n, p) for p in (2, 3)},
        "estimator": prm.estimator,
        "thresholds": {str(p): threshold(prm.pfa, p, n, prm.estimator) for p in (2, 3)},
        "threshold_large_n": {str(p): threshold_large_n(prm.pfa, p) for p in (2, 3)},
        "statistic": "y = X^H Sigma_hat^-1 X (eq 2-6)",
        "distribution": dist,
    }


# ------------------------------------------------------------------------------ Hermitian maths


@njit(nogil=True, cache=True, inline="always")
def _adj3(a, d, f, b, c, e):
    """Adjugate of the Hermitian [[a, b, c], [b*, d, e], [c*, e*, f]] (a, d, f real).

    Returns the diagonal (A11, A22, A33), the upper triangle (A12, A13, A23) and det.
    """
    A11 = d * f - (e.real * e.real + e.imag * e.imag)
    A22 = a * f - (c.real * c.real + c.imag * c.imag)
    A33 = a * d - (b.real * b.real + b.imag * b.imag)
    A12 = c * e.conjugate() - b * f
    A13 = b * e - c * d
    A23 = b.conjugate() * c - a * e
    det = a * A11 + (b * A12.conjugate()).real + (c * A13.conjugate()).real
    return A11, A22, A33, A12, A13, A23, det


@njit(nogil=True, cache=True)
def herm_inv(A):
    """Inverse of a Hermitian positive-definite 2x2 or 3x3 matrix by its closed-form adjugate."""
    p = A.shape[0]
    out = np.empty((p, p), np.complex128)
    if p == 2:
        a = A[0, 0].real
        d = A[1, 1].real
        b = A[0, 1]
        det = a * d - (b.real * b.real + b.imag * b.imag)
        out[0, 0] = d / det
        out[1, 1] = a / det
        out[0, 1] = -b / det
        out[1, 0] = -b.conjugate() / det
        return out
    A11, A22, A33, A12, A13, A23, det = _adj3(A[0, 0].real, A[1, 1].real, A[2, 2].real, A[0, 1], A[0, 2], A[1, 2])
    out[0, 0] = A11 / det
    out[1, 1] = A22 / det
    out[2, 2] = A33 / det
    out[0, 1] = A12 / det
    out[0, 2] = A13 / det
    out[1, 2] = A23 / det
    out[1, 0] = A12.conjugate() / det
    out[2, 0] = A13.conjugate() / det
    out[2, 1] = A23.conjugate() / det
    return out


# ------------------------------------------------------------------------------ kernels


@njit(nogil=True, cache=True)
def _products(x, out):
    """out[q] = the p^2 real numbers of X X^H per pixel (float64), X = x[i, j, :].

    p = 3: |x0|^2, |x1|^2, |x2|^2, Re/Im x0 x1*, Re/Im x0 x2*, Re/Im x1 x2*.
    p = 2: |x0|^2, |x1|^2, Re/Im x0 x1*.
    """
    R, C, p = x.shape
    for i in range(R):
        for j in range(C):
            if p == 3:
                ar = np.float64(x[i, j, 0].real)
                ai = np.float64(x[i, j, 0].imag)
                br = np.float64(x[i, j, 1].real)
                bi = np.float64(x[i, j, 1].imag)
                cr = np.float64(x[i, j, 2].real)
                ci = np.float64(x[i, j, 2].imag)
                out[0, i, j] = ar * ar + ai * ai
                out[1, i, j] = br * br + bi * bi
                out[2, i, j] = cr * cr + ci * ci
                out[3, i, j] = ar * br + ai * bi
                out[4, i, j] = ai * br - ar * bi
                out[5, i, j] = ar * cr + ai * ci
                out[6, i, j] = ai * cr - ar * ci
                out[7, i, j] = br * cr + bi * ci
                out[8, i, j] = bi * cr - br * ci
            else:
                ar = np.float64(x[i, j, 0].real)
                ai = np.float64(x[i, j, 0].imag)
                br = np.float64(x[i, j, 1].real)
                bi = np.float64(x[i, j, 1].imag)
                out[0, i, j] = ar * ar + ai * ai
                out[1, i, j] = br * br + bi * bi
                out[2, i, j] = ar * br + ai * bi
                out[3, i, j] = ai * br - ar * bi


@njit(nogil=True, cache=True)
def _products_cov(C, out):
    """The p^2 real numbers of a covariance matrix per pixel, in :func:`_products`' layout."""
    R, W, p, _ = C.shape
    for i in range(R):
        for j in range(W):
            for d in range(p):
                out[d, i, j] = np.float64(C[i, j, d, d].real)
            q = p
            for a in range(p):
                for b in range(a + 1, p):
                    z = C[i, j, a, b]
                    out[q, i, j] = np.float64(z.real)
                    out[q + 1, i, j] = np.float64(z.imag)
                    q += 2


def _cov_to_x_free_stat(C, S, n, tested=None):
    """y = N tr(S^-1 C) per pixel (numpy; C (h, w, p, p), S in the products layout; N a
    number or the per-pixel counts). ``tested``: pixels whose statistic is used; the others
    (too few valid ring cells: their S may be singular, even all zero) get y = 0. A singular S
    of a tested pixel (degenerate data, e.g. a channel that is zero throughout the ring) gets
    the pseudo-inverse: ``np.linalg.solve`` refuses a batch holding one singular matrix."""
    h, w, p, _ = C.shape
    M = np.empty((h, w, p, p), np.complex128)
    for d in range(p):
        M[..., d, d] = S[d]
    q = p
    for a in range(p):
        for b in range(a + 1, p):
            M[..., a, b] = S[q] + 1j * S[q + 1]
            M[..., b, a] = S[q] - 1j * S[q + 1]
            q += 2
    if tested is not None:
        M[~tested] = np.eye(p)
    with np.errstate(all="ignore"):
        try:
            sol = np.linalg.solve(M, C.astype(np.complex128))
        except np.linalg.LinAlgError:
            sol = np.linalg.pinv(M, hermitian=True) @ C.astype(np.complex128)
        y = n * np.real(np.trace(sol, axis1=2, axis2=3))
    if tested is not None:
        y = np.where(tested, y, 0.0)
    bad = ~np.isfinite(y)
    if bad.any():
        nz = np.abs(C).sum(axis=(2, 3)) > 0
        y[bad] = np.where(nz[bad], np.inf, 0.0)
    return y


@njit(nogil=True, cache=True)
def _pwf(x, S, K, T, thr, mask, stat):
    """y = K X^H S^-1 X per pixel from the window sums S[q] (layout of :func:`_products`)
    over K[i, j] valid cells, mask = y > T[i, j]; T = +inf: not tested (mask 0, stat 0);
    where T != thr (K < N) stat = y thr / T."""
    h, w, p = x.shape
    thr32 = np.float32(thr)
    above = np.nextafter(thr32, np.float32(np.inf))
    for i in range(h):
        for j in range(w):
            t = T[i, j]
            if not t < np.inf:
                mask[i, j] = False
                stat[i, j] = np.float32(0.0)
                continue
            n = K[i, j]
            if p == 3:
                x0 = np.complex128(x[i, j, 0])
                x1 = np.complex128(x[i, j, 1])
                x2 = np.complex128(x[i, j, 2])
                A11, A22, A33, A12, A13, A23, det = _adj3(
                    S[0, i, j],
                    S[1, i, j],
                    S[2, i, j],
                    complex(S[3, i, j], S[4, i, j]),
                    complex(S[5, i, j], S[6, i, j]),
                    complex(S[7, i, j], S[8, i, j]),
                )
                q = (
                    A11 * (x0.real * x0.real + x0.imag * x0.imag)
                    + A22 * (x1.real * x1.real + x1.imag * x1.imag)
                    + A33 * (x2.real * x2.real + x2.imag * x2.imag)
                    + 2.0
                    * (
                        (x0.conjugate() * A12 * x1).real
                        + (x0.conjugate() * A13 * x2).real
                        + (x1.conjugate() * A23 * x2).real
                    )
                )
                nz = (x0 != 0) or (x1 != 0) or (x2 != 0)
            else:
                x0 = np.complex128(x[i, j, 0])
                x1 = np.complex128(x[i, j, 1])
                a = S[0, i, j]
                d = S[1, i, j]
                b = complex(S[2, i, j], S[3, i, j])
                det = a * d - (b.real * b.real + b.imag * b.imag)
                q = (
                    d * (x0.real * x0.real + x0.imag * x0.imag)
                    + a * (x1.real * x1.real + x1.imag * x1.imag)
                    - 2.0 * (x0.conjugate() * b * x1).real
                )
                nz = (x0 != 0) or (x1 != 0)
            if det > 0.0:
                y = n * q / det
            elif nz:
                y = np.inf
            else:
                y = 0.0
            m = y > t
            if t != thr:
                y = y * (thr / t)
            s = np.float32(y)
            if m and s <= thr32:
                s = above  # keep stat > threshold wherever mask is set
            mask[i, j] = m
            stat[i, j] = s


def window_sums(block: np.ndarray, halo: int, origin: tuple[int, int], prm: APWFParams) -> np.ndarray:
    """S[q, i, j]: sums of the p^2 real numbers of X X^H over the valid clutter cells of each
    core pixel (``estimator``: ring or whole window), float64, tiling-invariant."""
    return window_sums_counts(block, halo, origin, prm)[0]


def window_sums_counts(block: np.ndarray, halo: int, origin: tuple[int, int], prm: APWFParams):
    """``(S, K, ok)``: :func:`window_sums` (absent cells left out), the number K of valid
    cells in each core pixel's estimate (float64, exact integers) and the core's
    :func:`~sarship.pipeline.tiling.polsar_absent.present` mask."""
    b, g = int(prm.background), int(prm.guard)
    r = b // 2
    off = halo - r
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    sub = block[off : off + h + 2 * r, off : off + w + 2 * r]
    o = (int(origin[0]) + off, int(origin[1]) + off)
    p = block.shape[2]
    ok = present(sub)
    complete = bool(ok.all())
    sub = zero_absent(sub, ok)
    prods = np.empty((p * p, sub.shape[0], sub.shape[1]), np.float64)
    if block.ndim == 4:
        _products_cov(sub, prods)
    else:
        _products(sub, prods)
    S = np.empty((p * p, h, w), np.float64)
    for q in range(p * p):
        S[q] = centered_box_sum(prods[q], b, r, o)
        if prm.estimator == "ring":
            S[q] -= centered_box_sum(prods[q], g, r, o)
    if complete:  # the box sums of a plane of ones: exactly N everywhere
        K = np.full((h, w), float(prm.n_samples()))
    else:
        v = ok.astype(np.float64)
        K = centered_box_sum(v, b, r, o)
        if prm.estimator == "ring":
            K -= centered_box_sum(v, g, r, o)
    return S, K, ok[r : r + h, r : r + w]


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], prm: APWFParams, prep: dict):
    """Adaptive PWF-CFAR on one padded tile ``(h + 2 halo, w + 2 halo, p)``, p = 2 or 3.

    Returns (mask = y > T, stat = y as float32; absent pixels and pixels with fewer than
    :func:`min_valid` valid cells: mask 0, stat 0; K < N: y against T(K), stat = y T(N) / T(K),
    see the module docstring). The core is processed in strips of
    :data:`STRIP_ROWS` x :data:`STRIP_COLS` pixels (sub-blocks with their own origin:
    the box sums, hence y, are the same bit for bit). A CuPy ``block`` runs on its GPU
    (:func:`sarship.pipeline.gpu.polsar.apwf`: the same window sums bit for bit, the same adjugate
    arithmetic) and returns CuPy arrays.
    """
    cov = block.ndim == 4
    if not (
        (block.ndim == 3 and block.shape[2] in (2, 3))
        or (cov and block.shape[2] == block.shape[3] and block.shape[2] in (2, 3))
    ):
        raise ValueError(
            f"apwf needs (rows, cols, p) channels or (rows, cols, p, p) covariances with p = 2 or 3, "
            f"got shape {block.shape}"
        )
    b = int(prm.background)
    check_windows(halo, b)
    p = block.shape[2]
    if is_device_array(block):  # CuPy block: the GPU twin (pipeline.gpu.polsar)
        return SPEC.twin()(
            block,
            halo,
            origin,
            b,
            int(prm.guard),
            prm.estimator == "ring",
            float(prep["n_samples"]),
            float(prep["thresholds"][str(p)]),
            pfa=float(prm.pfa),
            kmin=min_valid(int(prep["n_samples"]), p),
        )
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    n = float(prep["n_samples"])
    thr = float(prep["thresholds"][str(p)])
    kmin = min_valid(int(n), p)
    mask = np.empty((h, w), np.bool_)
    stat = np.empty((h, w), np.float32)
    for r0 in range(0, h, STRIP_ROWS):
        r1 = min(r0 + STRIP_ROWS, h)
        for c0 in range(0, w, STRIP_COLS):
            c1 = min(c0 + STRIP_COLS, w)
            sub = block[r0 : r1 + 2 * halo, c0 : c1 + 2 * halo]
            S, K, ok = window_sums_counts(sub, halo, (origin[0] + r0, origin[1] + c0), prm)
            T = threshold_map(K, ok & (K >= kmin), float(prm.pfa), p, prm.estimator, n, thr)
            core = zero_absent(sub[halo : halo + r1 - r0, halo : halo + c1 - c0], ok)
            if cov:
                tested = T < np.inf
                y = _cov_to_x_free_stat(core, S, K, tested)
                m = tested & (y > T)
                with np.errstate(invalid="ignore"):
                    y = np.where(T != thr, y * (thr / T), y)
                st = np.where(tested, y, 0.0).astype(np.float32)
                st[m & (st <= np.float32(thr))] = np.nextafter(np.float32(thr), np.float32(np.inf))
                mask[r0:r1, c0:c1] = m
                stat[r0:r1, c0:c1] = st
            else:
                _pwf(core, S, K, T, thr, mask[r0:r1, c0:c1], stat[r0:r1, c0:c1])
    return mask, stat


SPEC = DetectorSpec(
    name="apwf",
    summary="Adaptive polarimetric whitening filter + CFAR (quad- or dual-pol SLC), exact threshold",
    reference="Sun 2020 (Tsinghua thesis) ch. 2, eq 2-6, 2-8, 2-9, 2-10; Novak & Burl 1990 (PWF); "
    "docs/algorithms/apwf.md",
    params=APWFParams,
    prepare=prepare,
    detect=detect,
    input="polarimetric",
    needs_looks=False,
    gpu="sarship.pipeline.gpu.polsar:apwf",
)
