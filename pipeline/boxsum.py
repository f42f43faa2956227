"""Window sums whose value does not depend on how the scene is tiled.

CFAR detectors need, for every pixel, sums over square windows (target, guard, background)
of the intensity and of its square. Summed-area tables and running sums make that O(1) per
pixel, but their floating-point rounding depends on where the running sum started, i.e. on
the tile origin: a tiled run would then differ from a whole-scene run in the last bits, and
a pixel lying on its threshold could flip.

We use instead the van Herk / Gil-Werman decomposition (van Herk 1992, Pattern Recognit.
Lett. 13(7); Gil & Werman 1993, IEEE TPAMI 15(5)), applied to sums: along a line, cut the
*global* pixel grid into blocks of the window length ``m`` (blocks start where the global
coordinate is a multiple of ``m``); inside each block accumulate a prefix sum (left to
right) and a suffix sum (right to left). A window of length ``m`` starting at ``i`` spans
at most two blocks, so its sum is ``suffix[i] + prefix[i + m - 1]`` (or ``suffix[i]`` alone
when ``i`` starts a block). Every sum is formed in an order fixed by global coordinates
alone: bit-identical for any tiling, O(1) per pixel (3 additions), and with no long-range
drift (each partial sum covers fewer than ``m`` samples). Two separable passes (rows, then
columns) give the 2-D box sum. Accumulation is in float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def _box_along_cols(x, m, g0, out):
    """out[r, i] = sum(x[r, i:i+m]) for i in range(C - m + 1); x[:, 0] is global column g0.

    Rows are processed four at a time with independent accumulators: a prefix/suffix scan
    is a chain of dependent additions, and four interleaved chains keep the floating-point
    units busy. Each row's additions happen in exactly the order of the one-row scan.
    """
    R, C = x.shape
    n_out = C - m + 1
    suf = np.empty((4, m), np.float64)
    r = 0
    while r + 4 <= R:
        s = -(g0 % m)
        while s < n_out:
            i_lo = max(s, 0)
            i_hi = min(s + m, n_out)
            if i_lo < i_hi:
                e = s + m - 1
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                a3 = 0.0
                for c in range(e, i_lo - 1, -1):
                    a0 = a0 + x[r, c]
                    a1 = a1 + x[r + 1, c]
                    a2 = a2 + x[r + 2, c]
                    a3 = a3 + x[r + 3, c]
                    suf[0, c - s] = a0
                    suf[1, c - s] = a1
                    suf[2, c - s] = a2
                    suf[3, c - s] = a3
                i0 = i_lo
                if i0 == s:
                    out[r, i0] = suf[0, 0]
                    out[r + 1, i0] = suf[1, 0]
                    out[r + 2, i0] = suf[2, 0]
                    out[r + 3, i0] = suf[3, 0]
                    i0 += 1
                p0 = 0.0
                p1 = 0.0
                p2 = 0.0
                p3 = 0.0
                for c in range(s + m, i0 + m - 1):
                    p0 = p0 + x[r, c]
                    p1 = p1 + x[r + 1, c]
                    p2 = p2 + x[r + 2, c]
                    p3 = p3 + x[r + 3, c]
                for i in range(i0, i_hi):
                    c = i + m - 1
                    p0 = p0 + x[r, c]
                    p1 = p1 + x[r + 1, c]
                    p2 = p2 + x[r + 2, c]
                    p3 = p3 + x[r + 3, c]
                    out[r, i] = suf[0, i - s] + p0
                    out[r + 1, i] = suf[1, i - s] + p1
                    out[r + 2, i] = suf[2, i - s] + p2
                    out[r + 3, i] = suf[3, i - s] + p3
            s += m
        r += 4
    while r < R:
        s = -(g0 % m)
        while s < n_out:
            i_lo = max(s, 0)
            i_hi = min(s + m, n_out)
            if i_lo < i_hi:
                e = s + m - 1
                a0 = 0.0
                for c in range(e, i_lo - 1, -1):
                    a0 = a0 + x[r, c]
                    suf[0, c - s] = a0
                i0 = i_lo
                if i0 == s:
                    out[r, i0] = suf[0, 0]
                    i0 += 1
                p0 = 0.0
                for c in range(s + m, i0 + m - 1):
                    p0 = p0 + x[r, c]
                for i in range(i0, i_hi):
                    p0 = p0 + x[r, i + m - 1]
                    out[r, i] = suf[0, i - s] + p0
            s += m
        r += 1


@njit(nogil=True, cache=True)
def _box_along_rows(x, m, g0, out):
    """out[i, c] = sum(x[i:i+m, c]) for i in range(R - m + 1); x[0, :] is global row g0.

    Processed block by block (blocks of ``m`` rows aligned on global multiples of ``m``):
    the suffix sums of one block live in an ``m x C`` buffer and the prefix sums of the
    next block in one row, so the working set stays small whatever the tile height.
    """
    R, C = x.shape
    n_out = R - m + 1
    suf = np.empty((m, C), np.float64)
    pre = np.empty(C, np.float64)
    s = -(g0 % m)  # array row of the first block start (<= 0)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1  # block end, always inside the array when an output needs it
            for c in range(C):
                suf[e - s, c] = x[e, c]
            for r in range(e - 1, i_lo - 1, -1):
                for c in range(C):
                    suf[r - s, c] = suf[r - s + 1, c] + x[r, c]
            i0 = i_lo
            if i0 == s:
                for c in range(C):
                    out[i0, c] = suf[0, c]
                i0 += 1
            # prefix of the next block up to row i0 + m - 2
            first = True
            for r in range(s + m, i0 + m - 1):
                if first:
                    for c in range(C):
                        pre[c] = x[r, c]
                    first = False
                else:
                    for c in range(C):
                        pre[c] = pre[c] + x[r, c]
            for i in range(i0, i_hi):
                r = i + m - 1
                if first:
                    for c in range(C):
                        pre[c] = x[r, c]
                    first = False
                else:
                    for c in range(C):
                        pre[c] = pre[c] + x[r, c]
                for c in range(C):
                    out[i, c] = suf[i - s, c] + pre[c]
        s += m


def centered_box_sum(block: np.ndarray, m: int, halo: int, origin: tuple[int, int]) -> np.ndarray:
    """Sum over the ``m x m`` window centred on each core pixel of a padded block.

    Parameters
    ----------
    block : (h + 2*halo, w + 2*halo) array
        Tile with its halo; ``block[0, 0]`` is global pixel ``origin`` (row, col).
    m : int
        Odd window side, ``m // 2 <= halo``.
    halo, origin
        As in :mod:`pipeline.detectors.base`.

    Returns
    -------
    (h, w) float64 array of window sums, bit-identical for any tiling of the scene.
    """
    if m % 2 != 1:
        raise ValueError(f"window side must be odd, got {m}")
    r = m // 2
    if r > halo:
        raise ValueError(f"window {m} needs a halo of {r}, block has {halo}")
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    off = halo - r
    sub = block[off: off + h + m - 1, off: off + w + m - 1]
    if sub.dtype not in (np.float32, np.float64):
        sub = sub.astype(np.float64)
    tmp = np.empty((h + m - 1, w), np.float64)
    _box_along_cols(sub, m, origin[1] + off, tmp)
    out = np.empty((h, w), np.float64)
    _box_along_rows(tmp, m, origin[0] + off, out)
    return out


def core(block: np.ndarray, halo: int) -> np.ndarray:
    """The core (tile without halo) of a padded block."""
    if halo == 0:
        return block
    return block[halo:-halo, halo:-halo]
