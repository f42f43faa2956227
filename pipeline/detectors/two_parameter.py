"""Two-parameter (Gaussian) CFAR (``two_parameter``), with the exact small-sample threshold.

The classical detector (Novak & Hesse 1991; ESA SNAP's "Adaptive Thresholding"): estimate
the clutter mean mu and standard deviation sigma from the N cells of the background ring
and declare a target where the tested value exceeds ``mu + t sigma``, with t from the PFA
under a Gaussian model, t = Phi^{-1}(1 - PFA).

Target-window version. When the tested value is the mean of the n = target^2 cells of the
target window, its standard deviation is sigma / sqrt(n): the rule must be
``x_t > mu + t sigma / sqrt(n)`` (the t/sqrt(n) correction SNAP never applied, so its
target-window PFA is far below the one asked for).

Exact threshold (``threshold="student"``, default). mu and sigma are estimates from N
samples: for Gaussian clutter, (x_t - mu_hat) / (sigma_hat * sqrt(1/n + 1/N)) follows
Student's t with N - 1 degrees of freedom, exactly (independent CUT and ring). So the
detection rule (x_t - mu_hat)/sigma_hat > t_N with t_N = sqrt(1/n + 1/N) * t_{N-1}^{-1}(1 -
PFA) has exactly the PFA asked for. ``threshold="gaussian"`` gives the classical
t = Phi^{-1}(1 - PFA) / sqrt(n), exact only as N -> infinity.

``domain`` picks the quantity the Gaussian model is applied to: ``intensity`` (as SNAP),
``amplitude`` (sqrt) or ``db`` (10 log10, where speckle is closest to Gaussian). In ``db``
non-positive values are floored at 1e-30 (-300 dB), a fixed floor so that tiles agree;
data with exact zeros (8-bit quantised JPEG chips, no-data borders) then carry -300 dB
outliers into the ring statistics: use ``intensity`` or ``amplitude`` for such data.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit, objmode, uint64
from pydantic import Field

from sarship.pipeline.detectors import simd
from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, check_windows, with_defaults
from sarship.pipeline.detectors.simd import (
    prefetch,
    vadd,
    vcol,
    vcols,
    vdiv,
    vdivn,
    vload,
    vmul,
    vscatter,
    vscatter4,
    vsel_gt,
    vsplat,
    vsqrt,
    vstep,
    vstore,
    vstore_stat,
    vsub,
)
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.stats.tails import norm_isf, t_isf
from sarship.pipeline.tiling import boxsum, intensity_absent
from sarship.pipeline.tiling.boxsum import hsum_row, ring_slot, stream_state, vertical_row, vertical_steady


class TwoParameterParams(
    with_defaults(
        DetectorParams,
        "TwoParameterDefaults",
        pfa=1e-6,
        guard=41,
        background=81,
        merge_px=2,
        land_mask="texture",
        auto_min_area_px=10,
        auto_min_length_m=25.0,
        auto_min_area_m2=200.0,
    )
):
    """Parameters of ``two_parameter``.

    Defaults chosen on real data by cross-validation (tuned on half A of SAR-Ship-Dataset,
    HRSID and OpenSARShip, reported on half B; bench/REALDATA.md). Size rule (unset
    ``min_area_px`` / ``min_length_m``): ships of at least 25 m and 200 m^2 when the scene's
    pixel spacing is known, of at least 10 px otherwise.
    """

    threshold: Literal["student", "gaussian"] = Field(
        "student", description="exact Student-t threshold for N ring samples, or the classical Gaussian one"
    )
    domain: Literal["intensity", "amplitude", "db"] = Field("intensity", description="quantity modelled as Gaussian")
    nodata: float | None = Field(
        None,
        description="value marking absent pixels besides NaN (e.g. 0 for a zero-filled border); "
        "None: NaN only (exact zeros are data: 8-bit chips have them in dark sea)",
    )


def threshold(pfa: float, n_ring: int, n_target: int, kind: str = "student") -> float:
    """Threshold on (x_t - mu_hat) / sigma_hat for the given PFA."""
    if kind == "student":
        return float(np.sqrt(1.0 / n_target + 1.0 / n_ring) * t_isf(pfa, n_ring - 1))
    return float(norm_isf(pfa) / np.sqrt(n_target))


def prepare(p: TwoParameterParams) -> dict:
    n_t = p.target**2
    return {
        "n_ring": p.n_ring,
        "n_target": n_t,
        "threshold": threshold(p.pfa, p.n_ring, n_t, p.threshold),
        "statistic": "(target mean - ring mean) / ring std",
        "domain": p.domain,
    }


# ---------------------------------------------------------------------------------------
# Fused streaming kernel.
# ---------------------------------------------------------------------------------------
#
# Bit for bit the former implementation (transform to float64 y, y * y, four or five calls
# of ``boxsum.centered_box_sum``, then the decision; ``tests/pipeline/test_two_parameter_kernel.py``
# states it in numpy): the same float64 values enter the same additions in the same order
# (``boxsum`` docstring), streamed like ``ca_cfar``: output rows are produced one at a time
# and the horizontal sums of the input rows just ahead, into small rings that stay in L2,
# so no full-size float64 intermediate is written. Per column strip:
#
# * Each input row is transformed once (``_transform_row``), into a ring of rows ``Y``.
#   The logarithm of ``db`` is numpy's (numba's differs in the last bit): it is taken by
#   ``np.log10`` on bands of DB_BAND rows (``_db_band``), in cache.
# * Horizontal pass (``_hscan4``): four rows at a time, one row per SIMD lane (the scans
#   along a row are chains of dependent additions; rows are the parallel dimension), y and
#   y * y together; 4 x 4 transposes move data between rows and lanes. Each lane performs
#   exactly the additions of ``boxsum.hsum_row``.
# * Vertical pass and decision fused (``_decide_row``), four columns per vector: in a steady
#   row the running prefix of the next row block is updated and added to the suffix row,
#   for the four sums, and the statistic is formed at once; rows that open a row block or
#   start a prefix (a few per block) are formed first by ``boxsum.vertical_row``. The
#   divisions by the integers N, N - 1 and target**2 use ``vdivn`` (exact, without the
#   divider).
#
# The vector operations are LLVM IR vectors (:mod:`sarship.pipeline.detectors.simd`): IEEE fadd, fmul,
# fdiv and sqrt, no fast-math flags, no contraction, so each lane rounds as scalar code
# would. The hot functions take whole arrays and flat indices and are compiled without the
# NRT (``_nrt=False``): array views and reference counting (atomic operations) in the
# inner loops cost more than the arithmetic. The functions that compile in code of
# ``simd`` or ``boxsum`` are not cached on their own: they are cached as part of
# ``_detect_strip``, whose cache key follows those files (``_make_detect_strip``).

#: Most output columns per strip: the rings (background and guard, y and y*y) stay in L2.
STRIP = 768

_MODE = {"intensity": 0, "amplitude": 1, "db": 2}

#: Rows of the ``db`` domain's logarithm computed at a time (in cache, by numpy).
DB_BAND = 64


@njit(cache=True)
def _log10_inplace(L, n):
    """L[:n] = np.log10(L[:n]), by numpy itself.

    numba's ``log10`` (libm) and numpy's (SIMD) differ in the last bit for ~10 % of values:
    the ``db`` transform must be numpy's. An object-mode block (the GIL is taken for it)
    in a function of its own, without ``nogil``, which numba would warn about."""
    with objmode():
        np.log10(L[:n], out=L[:n])


@njit(nogil=True, cache=True)
def _db_band(src, r0, n, c0, L):
    """L[:n] = log10(max(src[r0: r0+n, c0: c0 + L.shape[1]] as float64, 1e-30)), as the
    former ``np.log10(np.maximum(x.astype(np.float64), 1e-30))`` (NaN propagated)."""
    w = L.shape[1]
    for r in range(n):
        for c in range(w):
            v = np.float64(src[uint64(r0 + r), uint64(c0 + c)])
            L[uint64(r), uint64(c)] = v if not (v <= 1e-30) else 1e-30
    _log10_inplace(L, n)


@njit(nogil=True, cache=True, _nrt=False)
def _transform_row(src, r, c0, n, mode, Y, slot):
    """Y[slot, :n] = y of src[r, c0: c0 + n]: as float64 (mode 0), sqrt(max(x, 0)) (1), or
    10 * src, src being the logarithm from ``_db_band`` (2) -- bit for bit the numpy
    transform."""
    if mode == 0:
        for c in range(n):
            Y[uint64(slot), uint64(c)] = np.float64(src[uint64(r), uint64(c0 + c)])
    elif mode == 1:
        for c in range(n):
            v = np.float64(src[uint64(r), uint64(c0 + c)])
            # np.maximum(x, 0.0): NaN kept, -0.0 -> +0.0
            Y[uint64(slot), uint64(c)] = np.sqrt(v if not (v <= 0.0) else 0.0)
    else:
        for c in range(n):
            Y[uint64(slot), uint64(c)] = 10.0 * src[uint64(r), uint64(c0 + c)]


@njit(nogil=True, _nrt=False)
def _acc(a, b, v, H2):
    """(a + v, b + v * v); b unchanged when H2 is None (y alone, resolved at compile time)."""
    if H2 is not None:
        return vadd(a, v), vadd(b, vmul(v, v))
    return vadd(a, v), b


@njit(nogil=True, _nrt=False)
def _suffix_step(a, b, v, su, sw, k, H2):
    """One step of the suffix scans of :func:`_hscan4`: a += v, b += v * v, stored at
    su.flat[k: k+4] and sw.flat[k: k+4]."""
    a, b = _acc(a, b, v, H2)
    vstore(su, k, a)
    if H2 is not None:
        vstore(sw, k, b)
    return a, b


@njit(nogil=True, _nrt=False)
def _window_sums(su, sw, k, p, q, H2):
    """(su.flat[k: k+4] + p, sw.flat[k: k+4] + q): a window's suffix plus the prefix."""
    h = vadd(vload(su, k), p)
    if H2 is not None:
        return h, vadd(vload(sw, k), q)
    return h, h


@njit(nogil=True, _nrt=False)
def _hscan4(Y, y0, y1, y2, y3, m, g0, n_out, H1, H2, o0, o1, o2, o3, su, sw):
    """Horizontal window sums of four rows of y (Y.flat[y_r + i], i = 0, 1, ..; the first
    is global column g0) and of y * y: H1.flat[o_r + i] = sum(y_r[i: i+m]) and H2.flat[o_r
    + i] = sum(y_r[i: i+m] ** 2), i < n_out. The additions of ``boxsum.hsum_row`` in each SIMD
    lane (one lane per row). ``su``, ``sw``: scratch of at least 4 * m float64 (suffix sums).

    ``H2`` None (the target window: y alone) is a compile-time case: numba prunes the
    ``H2 is not None`` branches, so that version does no work on y * y."""
    s = -(g0 % m)  # column of the first block start (<= 0)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1  # block end: suffix sums from e down to i_lo
            a = vsplat(0.0)
            b = vsplat(0.0)
            c = e
            while c - 3 >= i_lo:
                v0, v1, v2, v3 = vcols(Y, y0, y1, y2, y3, uint64(c - 3))
                ju = uint64(4 * (c - s))
                a, b = _suffix_step(a, b, v3, su, sw, ju, H2)
                a, b = _suffix_step(a, b, v2, su, sw, ju - 4, H2)
                a, b = _suffix_step(a, b, v1, su, sw, ju - 8, H2)
                a, b = _suffix_step(a, b, v0, su, sw, ju - 12, H2)
                c -= 4
            while c >= i_lo:
                a, b = _suffix_step(a, b, vcol(Y, y0, y1, y2, y3, uint64(c)), su, sw, uint64(4 * (c - s)), H2)
                c -= 1
            i0 = i_lo
            if i0 == s:  # the window starting the block is the whole block: suffix alone
                vscatter(H1, o0, o1, o2, o3, uint64(i0), a)
                if H2 is not None:
                    vscatter(H2, o0, o1, o2, o3, uint64(i0), b)
                i0 += 1
            # prefix of the next block, up to column i0 + m - 2
            p = vsplat(0.0)
            q = vsplat(0.0)
            for c in range(s + m, i0 + m - 1):
                p, q = _acc(p, q, vcol(Y, y0, y1, y2, y3, uint64(c)), H2)
            i = i0
            while i + 4 <= i_hi:
                v0, v1, v2, v3 = vcols(Y, y0, y1, y2, y3, uint64(i + m - 1))
                ju = uint64(4 * (i - s))
                p, q = _acc(p, q, v0, H2)
                ha, ka = _window_sums(su, sw, ju, p, q, H2)
                p, q = _acc(p, q, v1, H2)
                hb, kb = _window_sums(su, sw, ju + 4, p, q, H2)
                p, q = _acc(p, q, v2, H2)
                hc, kc = _window_sums(su, sw, ju + 8, p, q, H2)
                p, q = _acc(p, q, v3, H2)
                hd, kd = _window_sums(su, sw, ju + 12, p, q, H2)
                vscatter4(H1, o0, o1, o2, o3, uint64(i), ha, hb, hc, hd)
                if H2 is not None:
                    vscatter4(H2, o0, o1, o2, o3, uint64(i), ka, kb, kc, kd)
                i += 4
            while i < i_hi:
                p, q = _acc(p, q, vcol(Y, y0, y1, y2, y3, uint64(i + m - 1)), H2)
                h, k = _window_sums(su, sw, uint64(4 * (i - s)), p, q, H2)
                vscatter(H1, o0, o1, o2, o3, uint64(i), h)
                if H2 is not None:
                    vscatter(H2, o0, o1, o2, o3, uint64(i), k)
                i += 1
        s += m


@njit(nogil=True, _nrt=False)
def _hscan1(Y, yr, yc, m, g0, H1, H2, d, su):
    """One row of :func:`_hscan4`, in scalar code (tile edges): y = Y[yr, yc:], into H1[d]
    and, unless H2 is None, H2[d] (``su``: scratch of at least m float64 in its first row)."""
    x = Y[:, yc:]
    hsum_row(x, yr, m, g0, H1, d, su)
    if H2 is not None:
        hsum_row(x, yr, m, g0, H2, d, su, True)


@njit(nogil=True, _nrt=False)
def _fill(Y, ys, k, r0, col, m, g0, nrows, H1, H2, st, su, sw):
    """Horizontal sums of the stream rows r0 .. r0 + k - 1 that lie in [0, nrows), whose
    values y are Y[ys[q], col:], q < k; into the rings H1 (y) and, unless None, H2 (y * y):
    stream row r in slot ``ring_slot(st, r, len(H1))``."""
    Rz, n_out = H1.shape
    ny = Y.shape[1]
    if k == 4 and r0 >= 0 and r0 + 4 <= nrows:
        o0 = ring_slot(st, r0, Rz) * n_out
        o1 = ring_slot(st, r0 + 1, Rz) * n_out
        o2 = ring_slot(st, r0 + 2, Rz) * n_out
        o3 = ring_slot(st, r0 + 3, Rz) * n_out
        _hscan4(
            Y,
            ys[0] * ny + col,
            ys[1] * ny + col,
            ys[2] * ny + col,
            ys[3] * ny + col,
            m,
            g0,
            n_out,
            H1,
            H2,
            o0,
            o1,
            o2,
            o3,
            su,
            sw,
        )
    else:
        for q in range(k):
            r = r0 + q
            if 0 <= r < nrows:
                _hscan1(Y, ys[q], col, m, g0, H1, H2, ring_slot(st, r, Rz), su)


@njit(nogil=True, error_model="numpy", _nrt=False)
def _decide_row(
    w,
    steady_b,
    steady_g,
    Hb1,
    Hb2,
    ab,
    bb,
    Hg1,
    Hg2,
    ag,
    bg,
    P,
    D,
    X,
    xo,
    tt,
    n_ring,
    thr,
    mask,
    stat,
    i,
    c0,
    tmp_s,
    tmp_m,
    src,
    pf,
    pfc,
    pfn,
):
    """Window sums of output row i, columns c0 .. c0 + w - 1 (steady streams: from their
    rings, suffix row a and next-block row b, and running prefix P[0..3]; the others from
    D[0..3]), x_t = X.flat[xo + j] (divided by tt unless 1), and the decision, four columns
    at a time; columns past w (padding of the last vector) are not stored.

    Also prefetches src[pf, pfc: pfc + pfn] (an input row needed soon; pf < 0: none), a
    cache line every other vector: spread over this loop, the misses cost little."""
    n = Hb1.shape[1]
    nr = vsplat(n_ring)
    nm1 = vsplat(n_ring - 1.0)
    inr = vsplat(1.0 / n_ring)
    inm1 = vsplat(1.0 / (n_ring - 1.0))
    ttv = vsplat(tt)
    itt = vsplat(1.0 / tt)
    th = vsplat(thr)
    zero = vsplat(0.0)
    inf = vsplat(np.inf)
    mo = i * mask.shape[1] + c0
    for j in range(0, w, 4):
        ju = uint64(j)
        if steady_b:
            s1b = vstep(Hb1, ab * n + ju, bb * n + ju, P, ju)
            s2b = vstep(Hb2, ab * n + ju, bb * n + ju, P, n + ju)
        else:
            s1b = vload(D, ju)
            s2b = vload(D, n + ju)
        if steady_g:
            s1g = vstep(Hg1, ag * n + ju, bg * n + ju, P, 2 * n + ju)
            s2g = vstep(Hg2, ag * n + ju, bg * n + ju, P, 3 * n + ju)
        else:
            s1g = vload(D, 2 * n + ju)
            s2g = vload(D, 3 * n + ju)
        if pf >= 0 and 2 * j < pfn:
            prefetch(src, pf, pfc + 2 * j)
        x = vload(X, xo + ju)
        if tt != 1.0:
            x = vdivn(x, ttv, itt)
        s1 = vsub(s1b, s1g)
        s2 = vsub(s2b, s2g)
        mu = vdivn(s1, nr, inr)
        var = vdivn(vsub(s2, vmul(s1, mu)), nm1, inm1)
        d = vsub(x, mu)
        q = vdiv(d, vsqrt(var))
        s = vsel_gt(var, zero, q, vsel_gt(d, zero, inf, zero))
        if j + 4 <= w:
            vstore_stat(stat, mask, mo + ju, s, th)
        else:
            vstore_stat(tmp_s, tmp_m, 0, s, th)
            for c in range(w - j):
                stat[i, c0 + j + c] = tmp_s[c]
                mask[i, c0 + j + c] = tmp_m[c]


# argument lists laid out by hand, kept from the formatter
# fmt: off
def _make_detect_strip(stamp: str):
    """The fused kernel. Its machine code includes code of :mod:`sarship.pipeline.detectors.simd` and
    :mod:`sarship.pipeline.tiling.boxsum`, but numba's on-disk cache only watches this file:
    ``stamp`` (a hash of both files) is a closure variable, part of numba's cache key, so an
    edit there gets a fresh compilation instead of stale cached code. The callees above that
    use either module are not cached themselves (a cached one would be linked in stale):
    they are compiled only when this kernel is.
    """

    @njit(nogil=True, cache=True)
    def detect_strip(src, mode, halo, g0r, g0c, target, guard, background, n_ring, thr, c0, c1,
                     mask, stat):
        """Columns [c0, c1) of the core: all window sums streamed row by row, and the decision."""
        stamp  # noqa: B018 (keeps the stamp in the closure, hence in the cache key)
        h = mask.shape[0]
        w = c1 - c0
        wp = (w + 3) // 4 * 4  # streams run on whole vectors; the padding columns are dropped
        t, g, b = target, guard, background
        ob = halo - b // 2
        og = halo - g // 2
        ot = halo - t // 2
        win = w + b - 1  # columns of the transformed rows: those the background window needs
        xc = ob + c0
        # transformed rows, tile row r in slot (r - ob) % RY; held from their transform (up to
        # 3 rows past the background's need) until the target row halo + i is used
        RY = b // 2 + 8
        Y = np.zeros((RY + 1, wp + b - 1), np.float64)  # and a spare row: target window sums
        ny = Y.shape[1]
        ys = np.empty(4, np.int64)
        su = np.empty((4, b), np.float64)  # scratch of the horizontal scans
        sw = np.empty((4, b), np.float64)
        # rings: filled up to 3 rows past the background's need, each window needs its rows
        # from the output row on: (m // 2 + b // 2 + 4) rows in flight
        Rb = 2 * (b // 2) + 5
        Rg = g // 2 + b // 2 + 5
        Rt = t // 2 + b // 2 + 5 if t > 1 else 1
        Hb1 = np.empty((Rb, wp), np.float64)
        Hb2 = np.empty((Rb, wp), np.float64)
        Hg1 = np.empty((Rg, wp), np.float64)
        Hg2 = np.empty((Rg, wp), np.float64)
        Ht = np.empty((Rt, wp), np.float64)
        P = np.empty((5, wp), np.float64)  # running prefixes: b y, b y*y, g y, g y*y, t y
        D = np.empty((4, wp), np.float64)  # window sums of rows that are not steady
        sb1 = stream_state(b, g0r + ob)
        sb2 = stream_state(b, g0r + ob)
        sg1 = stream_state(g, g0r + og)
        sg2 = stream_state(g, g0r + og)
        stt = stream_state(t, g0r + ot)
        Pb1, Pb2, Pg1, Pg2, Pt = P[0], P[1], P[2], P[3], P[4]
        Db1, Db2, Dg1, Dg2, Yt = D[0], D[1], D[2], D[3], Y[RY]
        tmp_s = np.empty(4, np.float32)
        tmp_m = np.empty(4, np.bool_)
        tt = float(t * t)
        F = ob  # next tile row to transform
        f_end = ob + h + b - 1
        # db: log10 of the tile rows band0 .. band0 + DB_BAND - 1 (strip columns)
        L = np.empty((DB_BAND if mode == 2 else 0, win), np.float64)
        band0 = ob - DB_BAND
        for i in range(h):
            need = ob + i + b - 1
            while F <= need:
                k = min(4, f_end - F)
                for q in range(k):
                    ys[q] = (F + q - ob) % RY
                    if mode == 2:
                        if F + q >= band0 + DB_BAND:
                            band0 = F + q
                            _db_band(src, band0, min(DB_BAND, f_end - band0), xc, L)
                        _transform_row(L, F + q - band0, 0, win, mode, Y, ys[q])
                    else:
                        _transform_row(src, F + q, xc, win, mode, Y, ys[q])
                _fill(Y, ys, k, F - ob, 0, b, g0c + ob + c0, h + b - 1, Hb1, Hb2, sb1, su, sw)
                _fill(Y, ys, k, F - og, og - ob, g, g0c + og + c0, h + g - 1, Hg1, Hg2, sg1, su, sw)
                if t > 1:
                    _fill(Y, ys, k, F - ot, ot - ob, t, g0c + ot + c0, h + t - 1, Ht, None, stt, su,
                          sw)
                F += k
            steady_b = vertical_row(Hb1, sb1, b, i, Pb1, Db1)
            vertical_row(Hb2, sb2, b, i, Pb2, Db2)
            steady_g = vertical_row(Hg1, sg1, g, i, Pg1, Dg1)
            vertical_row(Hg2, sg2, g, i, Pg2, Dg2)
            if t == 1:  # x_t: the transformed row halo + i
                xo = (halo + i - ob) % RY * ny + b // 2
            else:  # x_t: the target window sums, in the spare row RY of Y
                if vertical_row(Ht, stt, t, i, Pt, Yt):
                    vertical_steady(Ht, stt, t, i, Pt, Yt)
                xo = RY * ny
            # prefetch: the next group of rows to transform, or the next band of the db logarithm
            pf = F + 4 + (i & 3) if mode != 2 else band0 + DB_BAND + i % DB_BAND
            if pf >= src.shape[0]:
                pf = -1
            _decide_row(w, steady_b, steady_g, Hb1, Hb2, ring_slot(sb1, i, Rb),
                        ring_slot(sb1, i + b - 1, Rb), Hg1, Hg2, ring_slot(sg1, i, Rg),
                        ring_slot(sg1, i + g - 1, Rg), P, D, Y, xo, tt, n_ring, thr, mask, stat, i,
                        c0, tmp_s, tmp_m, src, pf, xc, win)

    return detect_strip
# fmt: on


_detect_strip = _make_detect_strip(simd.source_stamp(simd, boxsum))


def _transform_reference(block: np.ndarray, domain: str) -> np.ndarray:
    x = block.astype(np.float64)
    if domain == "amplitude":
        return np.sqrt(np.maximum(x, 0.0))
    if domain == "db":
        return 10.0 * np.log10(np.maximum(x, 1e-30))
    return x


@njit(nogil=True, cache=True)
def _decide_reference(xt, s1b, s1g, s2b, s2g, n_ring, thr, mask, stat):
    h, w = xt.shape
    for i in range(h):
        for j in range(w):
            s1 = s1b[i, j] - s1g[i, j]
            s2 = s2b[i, j] - s2g[i, j]
            mu = s1 / n_ring
            var = (s2 - s1 * mu) / (n_ring - 1.0)
            d = xt[i, j] - mu
            if var > 0.0:
                s = d / np.sqrt(var)
            elif d > 0.0:
                s = np.inf
            else:
                s = 0.0
            stat[i, j] = s
            mask[i, j] = s > thr


def detect_reference(block: np.ndarray, halo: int, origin: tuple[int, int], p: TwoParameterParams, prep: dict):
    """The same detector written plainly with :func:`sarship.pipeline.tiling.boxsum.centered_box_sum`
    (bit-identical to :func:`detect`, ~6x slower). :func:`detect` falls back to it when the
    fused kernel cannot be used: window sizes beyond its exact-division range, or a Numba /
    LLVM release on which the kernel's vector intrinsics fail to compile."""
    from sarship.pipeline.tiling.boxsum import centered_box_sum

    x = _transform_reference(block, p.domain)
    x2 = x * x
    s1b = centered_box_sum(x, p.background, halo, origin)
    s1g = centered_box_sum(x, p.guard, halo, origin)
    s2b = centered_box_sum(x2, p.background, halo, origin)
    s2g = centered_box_sum(x2, p.guard, halo, origin)
    if p.target == 1:
        xt = np.ascontiguousarray(x[halo : x.shape[0] - halo, halo : x.shape[1] - halo])
    else:
        xt = centered_box_sum(x, p.target, halo, origin) / float(p.target**2)
    mask = np.empty(xt.shape, np.bool_)
    stat = np.empty(xt.shape, np.float32)
    _decide_reference(xt, s1b, s1g, s2b, s2g, float(prep["n_ring"]), float(prep["threshold"]), mask, stat)
    return mask, stat


_FUSED_BROKEN: list[str] = []


def detect(block: np.ndarray, halo: int, origin: tuple[int, int], p: TwoParameterParams, prep: dict):
    """Two-parameter CFAR on one padded tile; returns (mask, standardised statistic).

    Bit-identical to: y = the tile as float64, transformed (``domain``); the window sums of
    y and y * y over the background and guard windows and of y over the target window by
    ``boxsum.centered_box_sum``; then, per pixel, s1 = s1b - s1g, s2 = s2b - s2g,
    mu = s1 / N, var = (s2 - s1 * mu) / (N - 1), d = x_t - mu, statistic d / sqrt(var)
    (inf if var <= 0 < d, 0 if var <= 0 and d <= 0), mask = statistic > threshold. Fused
    and streamed in column strips of at most ``STRIP`` pixels (which change nothing in the
    sums: their blocks are aligned on global coordinates). A CuPy ``block`` runs on its GPU
    (:func:`sarship.pipeline.gpu.cfar.two_parameter`, same sums and arithmetic; the ``db`` domain's
    logarithm may differ in the last bit) and returns CuPy arrays.
    """
    b, g, t = int(p.background), int(p.guard), int(p.target)
    check_windows(halo, b, g, t)
    if is_device_array(block):  # CuPy block: the GPU twin (pipeline.gpu.cfar), same sums and rule
        return SPEC.twin()(
            block,
            halo,
            origin,
            b,
            g,
            t,
            float(prep["n_ring"]),
            float(prep["threshold"]),
            p.domain,
            pfa=float(p.pfa),
            kind=p.threshold,
            nodata=p.nodata,
        )
    ok = intensity_absent.present(block, p.nodata)
    if not ok.all():  # absent pixels (module docstring of pipeline.intensity_absent)
        src = block if block.dtype in (np.float32, np.float64) else block.astype(np.float64)
        xz = intensity_absent.fill(src, ok, 0.0)
        mask, stat = _detect_complete(xz, halo, origin, p, prep)
        yz = intensity_absent.fill(_transform_reference(xz, p.domain), ok, 0.0)
        intensity_absent.tp_redo(
            yz,
            ok,
            halo,
            origin,
            b,
            g,
            t,
            int(prep["n_ring"]),
            float(p.pfa),
            p.threshold,
            float(prep["threshold"]),
            mask,
            stat,
            boxsum.centered_box_sum,
        )
        return mask, stat
    return _detect_complete(block, halo, origin, p, prep)


def _detect_complete(block, halo, origin, p, prep):
    b, g, t = int(p.background), int(p.guard), int(p.target)
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    mode = _MODE[p.domain]
    src = block if block.dtype in (np.float32, np.float64) else block.astype(np.float64)
    mask = np.empty((h, w), np.bool_)
    stat = np.empty((h, w), np.float32)
    n_ring = float(prep["n_ring"])
    thr = float(prep["threshold"])
    if _FUSED_BROKEN or not (n_ring == int(n_ring) and 8 <= n_ring < 2**21 and t * t < 2**21):
        return detect_reference(block, halo, origin, p, prep)  # outside vdivn's exact range
    n_strips = -(-w // STRIP)
    sw = -(-w // max(n_strips, 1))  # equal strips (a narrow last strip would cost its overlap)
    try:
        for c0 in range(0, w, max(sw, 1)):
            _detect_strip(
                src, mode, halo, int(origin[0]), int(origin[1]), t, g, b, n_ring, thr, c0, min(c0 + sw, w), mask, stat
            )
    except Exception as exc:  # compile failure of the intrinsics on another Numba/LLVM
        from numba.core.errors import NumbaError

        if not isinstance(exc, (NumbaError, RuntimeError, TypeError, NotImplementedError)):
            raise
        import warnings

        _FUSED_BROKEN.append(f"{type(exc).__name__}: {exc}")
        warnings.warn(
            f"two_parameter: fused kernel unavailable ({type(exc).__name__}); using the reference implementation",
            RuntimeWarning,
            stacklevel=2,
        )
        return detect_reference(block, halo, origin, p, prep)
    return mask, stat


SPEC = DetectorSpec(
    name="two_parameter",
    summary="Two-parameter (Gaussian) CFAR with the exact Student-t threshold and target-window correction",
    reference="Novak & Hesse 1991; ESA SNAP Adaptive Thresholding; docs/algorithms/cfar.md",
    params=TwoParameterParams,
    prepare=prepare,
    detect=detect,
    input="intensity",
    needs_looks=False,
    gpu="sarship.pipeline.gpu.cfar:two_parameter",
)
