"""Halo geometry: cutting a tile plus its mirror-extended context out of a scene.

The thesis (Sun 2020, docs/references.md#sun2020; Algorithm 1, step 1) mirror-extends the image at its
borders by the sliding-window size. We use the mirror *without* repeating the edge pixel
(numpy ``pad(mode="reflect")``, scipy.ndimage ``mode="mirror"``): scene pixel ``-k`` is
pixel ``k``. For halos wider than the scene the reflection repeats (a triangle wave of
period ``2 (n - 1)``), exactly as ``numpy.pad`` does, so a tile's padded block is always a
slice of the one mirror-extended scene, whatever the tile size.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def reflect_index(start: int, stop: int, n: int) -> np.ndarray:
    """Scene indices of the mirror-extended positions ``start .. stop-1`` (``reflect`` mode)."""
    idx = np.arange(start, stop, dtype=np.int64)
    if n == 1:
        return np.zeros_like(idx)
    period = 2 * (n - 1)
    idx = np.mod(idx, period)
    return np.where(idx >= n, period - idx, idx)


def padded_block(
    read: Callable[[int, int, int, int], np.ndarray],
    shape: tuple[int, int],
    r0: int,
    r1: int,
    c0: int,
    c1: int,
    halo: int,
) -> np.ndarray:
    """Tile ``[r0:r1, c0:c1]`` with ``halo`` pixels of mirror-extended context on each side.

    ``read(ra, rb, ca, cb)`` returns the scene rectangle ``[ra:rb, ca:cb]``, a 2-D array or
    an array with trailing axes (e.g. ``(rows, cols, p)`` stacked polarimetric channels).
    Only the bounding rectangle of the needed scene pixels is read (at most the tile plus
    its halo). The mirror extension acts on the two image axes only; trailing axes are
    kept whole. The result is ``padded[halo + i, halo + j, ...] == scene[r0 + i, c0 + j, ...]``.
    """
    H, W = shape
    ri = reflect_index(r0 - halo, r1 + halo, H)
    ci = reflect_index(c0 - halo, c1 + halo, W)
    ra, rb = int(ri.min()), int(ri.max()) + 1
    ca, cb = int(ci.min()), int(ci.max()) + 1
    raw = np.asarray(read(ra, rb, ca, cb))
    pads = ((ra - (r0 - halo), (r1 + halo) - rb), (ca - (c0 - halo), (c1 + halo) - cb))
    if pads == ((0, 0), (0, 0)):
        return raw
    if raw.shape[0] > 1 and raw.shape[1] > 1:
        # numpy's reflect padding is the same mirror (repeated for pads wider than a scene
        # that the read covers whole), built from slice copies rather than a gather
        if raw.ndim > 2:
            pads = pads + ((0, 0),) * (raw.ndim - 2)
        return np.pad(raw, pads, mode="reflect")
    return raw[np.ix_(ri - ra, ci - ca)]  # trailing axes, if any, are kept whole


def mirror_pad(x: np.ndarray, halo: int) -> np.ndarray:
    """The whole array mirror-extended by ``halo`` along its first two axes (reference for
    tests and small scenes); trailing axes are kept whole."""
    H, W = x.shape[:2]
    return x[np.ix_(reflect_index(-halo, H + halo, H), reflect_index(-halo, W + halo, W))]
