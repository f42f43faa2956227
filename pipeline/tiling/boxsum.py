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

Implementation (single-threaded, ``nogil``). The horizontal pass (along rows, blocks of
columns) comes first, on the input; the vertical pass (along columns, blocks of rows) runs
on its float64 results. Both are *streamed*: output rows are produced one at a time, and
the horizontal sums of an input row are computed just before the vertical pass needs them,
into a ring of ``m + 4`` rows, so no full-size float64 intermediate is ever written and the
working set stays in L2 (wide tiles are cut into column strips, which changes nothing in
the sums: column blocks are aligned on global coordinates). Detectors that need several
windows run one stream per window in lockstep and decide row by row
(:mod:`sarship.pipeline.detectors.ca_cfar`).

Exact order of the additions (what the tests pin down, for every input):

* horizontal, along a row, block ``[s, s + m)``: suffix ``S[e] = 0.0 + x[e]``,
  ``S[c] = S[c + 1] + x[c]``; prefix of the next block ``P[s + m] = 0.0 + x[s + m]``,
  ``P[c] = P[c - 1] + x[c]``; ``h[i] = S[i]`` if ``i == s`` else ``S[i] + P[i + m - 1]``;
* vertical, on ``h``, block ``[s, s + m)`` of rows: ``S[e] = h[e]``,
  ``S[r] = S[r + 1] + h[r]``; ``P[s + m] = h[s + m]``, ``P[r] = P[r - 1] + h[r]``;
  ``out[i] = S[i]`` if ``i == s`` else ``S[i] + P[i + m - 1]``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

#: Output columns per strip: a stream's ring, ``(m + 4) x STRIP`` float64, stays in L2.
STRIP = 1024

# ---------------------------------------------------------------------------------------
# Horizontal pass: window sums along rows of the input.
# ---------------------------------------------------------------------------------------


@njit(nogil=True, cache=True)
def _hsum4(x, r, m, g0, H, d0, d1, d2, d3, suf):
    """H[dk, i] = sum(x[r + k, i:i+m]) for k < 4, i < H.shape[1]; x[:, 0] is global column g0.

    Four rows are scanned together with independent accumulators: a prefix/suffix scan is
    a chain of dependent additions, and four interleaved chains keep the floating-point
    units busy. Each row's additions happen in exactly the order of the one-row scan
    :func:`hsum_row`. ``suf`` is a (4, m) float64 scratch buffer.

    Inner loops index with unsigned integers (every index there is >= 0): numba then skips
    its negative-index wraparound, which otherwise costs more than the additions.
    """
    n_out = H.shape[1]
    x0 = x[r]
    x1 = x[r + 1]
    x2 = x[r + 2]
    x3 = x[r + 3]
    h0 = H[d0]
    h1 = H[d1]
    h2 = H[d2]
    h3 = H[d3]
    u0 = suf[0]
    u1 = suf[1]
    u2 = suf[2]
    u3 = suf[3]
    s = -(g0 % m)  # array column of the first block start (<= 0)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1  # block end, inside the row whenever an output needs it
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            for c in range(e, i_lo - 1, -1):
                cu = uint64(c)
                ju = uint64(c - s)
                a0 = a0 + x0[cu]
                a1 = a1 + x1[cu]
                a2 = a2 + x2[cu]
                a3 = a3 + x3[cu]
                u0[ju] = a0
                u1[ju] = a1
                u2[ju] = a2
                u3[ju] = a3
            i0 = i_lo
            if i0 == s:  # the window starting the block is the whole block: suffix alone
                h0[i0] = a0
                h1[i0] = a1
                h2[i0] = a2
                h3[i0] = a3
                i0 += 1
            # prefix of the next block, up to column i0 + m - 2
            p0 = 0.0
            p1 = 0.0
            p2 = 0.0
            p3 = 0.0
            for c in range(s + m, i0 + m - 1):
                cu = uint64(c)
                p0 = p0 + x0[cu]
                p1 = p1 + x1[cu]
                p2 = p2 + x2[cu]
                p3 = p3 + x3[cu]
            for i in range(i0, i_hi):
                iu = uint64(i)
                cu = uint64(i + m - 1)
                ju = uint64(i - s)
                p0 = p0 + x0[cu]
                p1 = p1 + x1[cu]
                p2 = p2 + x2[cu]
                p3 = p3 + x3[cu]
                h0[iu] = u0[ju] + p0
                h1[iu] = u1[ju] + p1
                h2[iu] = u2[ju] + p2
                h3[iu] = u3[ju] + p3
        s += m


@njit(nogil=True, cache=True)
def _term(v, square):
    """v, or (``square``) v * v in float64."""
    if square:
        v = np.float64(v)
        return v * v
    return v


@njit(nogil=True, cache=True)
def hsum_row(x, r, m, g0, H, d, suf, square=False):
    """H[d, i] = sum(x[r, i:i+m]) for i < H.shape[1], or (``square``) of the squares; x[:, 0]
    is global column g0.

    Along the row, blocks ``[s, s + m)`` start where the global column is a multiple of m:
    suffix ``S[e] = 0.0 + x[e]``, ``S[c] = S[c + 1] + x[c]`` from the block end down; prefix
    ``P[s + m] = 0.0 + x[s + m]``, ``P[c] = P[c - 1] + x[c]`` over the next block; window
    ``S[i]`` when ``i`` starts a block, else ``S[i] + P[i + m - 1]``.
    """
    n_out = H.shape[1]
    x0 = x[r]
    h0 = H[d]
    u0 = suf[0]
    s = -(g0 % m)
    while s < n_out:
        i_lo = max(s, 0)
        i_hi = min(s + m, n_out)
        if i_lo < i_hi:
            e = s + m - 1
            a0 = 0.0
            for c in range(e, i_lo - 1, -1):
                a0 = a0 + _term(x0[uint64(c)], square)
                u0[uint64(c - s)] = a0
            i0 = i_lo
            if i0 == s:
                h0[i0] = a0
                i0 += 1
            p0 = 0.0
            for c in range(s + m, i0 + m - 1):
                p0 = p0 + _term(x0[uint64(c)], square)
            for i in range(i0, i_hi):
                p0 = p0 + _term(x0[uint64(i + m - 1)], square)
                h0[uint64(i)] = u0[uint64(i - s)] + p0
        s += m


# ---------------------------------------------------------------------------------------
# Vertical pass, streamed: output rows in order, horizontal sums computed just ahead.
# ---------------------------------------------------------------------------------------
#
# A stream for window m over an input x (R = n_out_rows + m - 1 rows, x[0, 0] at global
# (g0r, g0c)) is the tuple (H, pre, suf, st) made by box_stream:
#   H    ring of m + 4 rows of horizontal sums; input row r lives in slot (r - s0) % (m + 4),
#        s0 <= 0 being the array row of the first row block;
#   pre  running vertical prefix over the next row block;
#   suf  scratch of the horizontal scans;
#   st   state: current block start, rows whose horizontal sums are done, s0, and whether
#        pre has been started for the current block.
# When output row i opens a block [s, s + m), the block's horizontal sums are turned into
# vertical suffix sums in place; each later output row i of the block adds the horizontal
# sums of row i + m - 1 (next block) to pre and is suffix[i] + pre (vertical_row and
# vertical_steady: the vertical pass on a filled ring, shared with the fused kernel of
# ``two_parameter``, which fills its rings itself). Horizontal sums are computed four rows
# at a time, at most three rows ahead of need (row i + m - 1): the rows alive at once
# (suffix rows not yet emitted, next-block rows) span at most m + 3 rows, so the ring never
# overwrites a row still needed.

_ST_BLOCK = 0
_ST_DONE = 1
_ST_BASE = 2
_ST_PRE = 3


@njit(nogil=True, cache=True)
def stream_state(m, g0r):
    """The state of a vertical stream of window ``m`` whose input row 0 is global row ``g0r``
    (see :func:`vertical_row`)."""
    st = np.empty(4, np.int64)
    s0 = -(g0r % m)
    st[_ST_BLOCK] = s0
    st[_ST_DONE] = 0
    st[_ST_BASE] = s0
    st[_ST_PRE] = 0
    return st


@njit(nogil=True, cache=True)
def ring_slot(st, r, Rz):
    """The slot of input row ``r`` in a ring of ``Rz`` rows of horizontal sums."""
    return (r - st[_ST_BASE]) % Rz


@njit(nogil=True, cache=True)
def box_stream(m, w, g0r):
    """A stream of ``m x m`` window sums over ``w`` output columns; x row 0 is global row ``g0r``.

    Feed it to :func:`box_stream_row` for output rows 0, 1, 2, ... in order. Detectors that
    need several windows run one stream per window in lockstep (see ``ca_cfar``).
    """
    return (
        np.empty((m + 4, w), np.float64),
        np.empty(w, np.float64),
        np.empty((4, m), np.float64),
        stream_state(m, g0r),
    )


@njit(nogil=True, cache=True)
def _stream_fill(x, m, g0c, H, suf, st, r):
    """Make sure the horizontal sums of x rows up to ``r`` are in the ring."""
    R = x.shape[0]
    Rz = H.shape[0]
    done = st[_ST_DONE]
    while done <= r:
        if done + 4 <= R:
            _hsum4(
                x,
                done,
                m,
                g0c,
                H,
                ring_slot(st, done, Rz),
                ring_slot(st, done + 1, Rz),
                ring_slot(st, done + 2, Rz),
                ring_slot(st, done + 3, Rz),
                suf,
            )
            done += 4
        else:
            hsum_row(x, done, m, g0c, H, ring_slot(st, done, Rz), suf)
            done += 1
    st[_ST_DONE] = done


@njit(nogil=True, cache=True)
def vertical_row(H, st, m, i, pre, dst):
    """The vertical pass for output row i, except the steady case; call for i = 0, 1, 2, ...
    in order, the horizontal sums of input rows i .. i + m - 1 being in the ring ``H``
    (:func:`ring_slot`), ``pre`` the running prefix of the stream (``st``).

    Opens a row block when row i starts one (vertical suffix sums in place). Returns True
    when row i is steady (left to the caller: :func:`vertical_steady`, or the same additions
    in vector code); otherwise writes the window sums of row i into ``dst`` and returns False.
    """
    Rz, n = H.shape
    s = st[_ST_BLOCK]
    if i == 0 or i == s + m:  # output row i opens a block
        if i > 0:
            s += m
        st[_ST_BLOCK] = s
        st[_ST_PRE] = 0
        e = s + m - 1
        # vertical suffix sums of the block, in place, down to the first row still needed
        b = ring_slot(st, e, Rz)
        for r in range(e - 1, i - 1, -1):
            a = ring_slot(st, r, Rz)
            for c in range(n):
                H[a, c] = H[b, c] + H[a, c]
            b = a
        # prefix of the next block up to row i + m - 2 (only when a tile starts mid-block)
        for r in range(s + m, i + m - 1):
            a = ring_slot(st, r, Rz)
            if st[_ST_PRE] == 0:
                st[_ST_PRE] = 1
                for c in range(n):
                    pre[c] = H[a, c]
            else:
                for c in range(n):
                    pre[c] = pre[c] + H[a, c]
    a = ring_slot(st, i, Rz)
    if i == s:  # the window starting the block is the whole block: suffix alone
        for c in range(n):
            dst[c] = H[a, c]
        return False
    if st[_ST_PRE] == 1:
        return True
    st[_ST_PRE] = 1  # the prefix starts at row i + m - 1
    b = ring_slot(st, i + m - 1, Rz)
    for c in range(n):
        p = H[b, c]
        pre[c] = p
        dst[c] = H[a, c] + p
    return False


@njit(nogil=True, cache=True)
def vertical_steady(H, st, m, i, pre, dst):
    """A steady row i of :func:`vertical_row`: ``pre += H[i + m - 1]``, ``dst = H[i] + pre``."""
    Rz, n = H.shape
    a = ring_slot(st, i, Rz)
    b = ring_slot(st, i + m - 1, Rz)
    for c in range(n):
        p = pre[c] + H[b, c]
        pre[c] = p
        dst[c] = H[a, c] + p


@njit(nogil=True, cache=True)
def box_stream_row(x, m, g0c, stream, i, dst):
    """dst[c] = sum(x[i:i+m, c:c+m]) for c < dst.size; call for i = 0, 1, 2, ... in order.

    ``x`` is the input seen by this window (``x[0, 0]`` at global ``(g0r, g0c)``, ``g0r``
    given to :func:`box_stream`), with ``dst.size + m - 1`` columns; the sums are those of
    :func:`centered_box_sum`, bit for bit.
    """
    H, pre, suf, st = stream
    _stream_fill(x, m, g0c, H, suf, st, i + m - 1)
    if vertical_row(H, st, m, i, pre, dst):
        vertical_steady(H, st, m, i, pre, dst)


@njit(nogil=True, cache=True)
def _box_sum(x, m, g0r, g0c, strip, out):
    """out[i, c] = sum(x[i:i+m, c:c+m]); x[0, 0] is global pixel (g0r, g0c)."""
    h, w = out.shape
    for c0 in range(0, w, strip):
        c1 = min(c0 + strip, w)
        xs = x[:, c0 : c1 + m - 1]
        stream = box_stream(m, c1 - c0, g0r)
        for i in range(h):
            box_stream_row(xs, m, g0c + c0, stream, i, out[i, c0:c1])


def window_input(block, m: int, halo: int):
    """``(sub, off)``: the part of a padded block that the ``m x m`` windows centred on the
    core read (``block[off:off + h + m - 1, off:off + w + m - 1]``, ``off = halo - m // 2``),
    after checking that ``m`` is odd and fits in the halo. Any array type (NumPy or CuPy)."""
    if m % 2 != 1:
        raise ValueError(f"window side must be odd, got {m}")
    r = m // 2
    if r > halo:
        raise ValueError(f"window {m} needs a halo of {r}, block has {halo}")
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    off = halo - r
    return block[off : off + h + m - 1, off : off + w + m - 1], off


def centered_box_sum(block: np.ndarray, m: int, halo: int, origin: tuple[int, int]) -> np.ndarray:
    """Sum over the ``m x m`` window centred on each core pixel of a padded block.

    Parameters
    ----------
    block : (h + 2*halo, w + 2*halo) array
        Tile with its halo; ``block[0, 0]`` is global pixel ``origin`` (row, col).
    m : int
        Odd window side, ``m // 2 <= halo``.
    halo, origin
        As in :mod:`sarship.pipeline.detectors.base`.

    Returns
    -------
    (h, w) float64 array of window sums, bit-identical for any tiling of the scene.
    """
    sub, off = window_input(block, m, halo)
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    if sub.dtype not in (np.float32, np.float64):
        sub = sub.astype(np.float64)
    out = np.empty((h, w), np.float64)
    _box_sum(sub, m, origin[0] + off, origin[1] + off, STRIP, out)
    return out


def core(block: np.ndarray, halo: int) -> np.ndarray:
    """The core (tile without halo) of a padded block."""
    if halo == 0:
        return block
    return block[halo:-halo, halo:-halo]
