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
    """out[r, i] = sum(x[r, i:i+m]) for i in range(C - m + 1); x[:, 0] is global column g0."""
    R, C = x.shape
    n_out = C - m + 1
    pre = np.empty(C, np.float64)
    suf = np.empty(C, np.float64)
    for r in range(R):
        acc = 0.0
        for c in range(C):
            if (g0 + c) % m == 0:
                acc = 0.0
            acc += x[r, c]
            pre[c] = acc
        acc = 0.0
        for c in range(C - 1, -1, -1):
            if (g0 + c + 1) % m == 0:
                acc = 0.0
            acc += x[r, c]
            suf[c] = acc
        for i in range(n_out):
            if (g0 + i) % m == 0:
                out[r, i] = suf[i]
            else:
                out[r, i] = suf[i] + pre[i + m - 1]


@njit(nogil=True, cache=True)
def _box_along_rows(x, m, g0, out):
    """out[i, c] = sum(x[i:i+m, c]) for i in range(R - m + 1); x[0, :] is global row g0."""
    R, C = x.shape
    n_out = R - m + 1
    pre = np.empty((R, C), np.float64)
    suf = np.empty((R, C), np.float64)
    for r in range(R):
        if (g0 + r) % m == 0 or r == 0:
            for c in range(C):
                pre[r, c] = x[r, c]
        else:
            for c in range(C):
                pre[r, c] = pre[r - 1, c] + x[r, c]
    for r in range(R - 1, -1, -1):
        if (g0 + r + 1) % m == 0 or r == R - 1:
            for c in range(C):
                suf[r, c] = x[r, c]
        else:
            for c in range(C):
                suf[r, c] = suf[r + 1, c] + x[r, c]
    for i in range(n_out):
        if (g0 + i) % m == 0:
            for c in range(C):
                out[i, c] = suf[i, c]
        else:
            for c in range(C):
                out[i, c] = suf[i, c] + pre[i + m - 1, c]


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
    if sub.dtype != np.float64:
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
