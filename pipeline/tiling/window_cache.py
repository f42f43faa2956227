"""Many small windows of one scene array, each chunk read once.

The steps that look at every detection after the tiles have run (the sidelobe refinement,
pipeline/targets/sidelobes.py; the local contrast, pipeline/targets/local_contrast.py) read a small window
around each detection from the scene, the detection mask and the land mask. Read one by one
from Zarr, every window decodes the 512 x 512 chunks it touches (about 3 ms a window for the
three arrays on the development machine), and neighbouring detections decode the same chunks
again. :class:`CachedWindows` reads block-aligned rectangles instead and keeps the most
recently used ones within a byte budget, so a scene's chunks are decoded about once however
many detections lie in them.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import numpy as np

#: block side: the scene stores' inner chunk (pipeline/scene.py ``INNER_CHUNK``)
BLOCK = 512
#: default cache budget per array
MAX_BYTES = 256 * 2**20


class CachedWindows:
    """``read(ra, rb, ca, cb)`` through a block cache.

    ``read``: the underlying rectangle reader of an array of ``shape`` (rows, cols; trailing
    axes, e.g. stacked channels, are kept); blocks of ``block`` x ``block`` pixels aligned at
    multiples of ``block`` (clipped to the array) are read whole and kept, least recently used
    first out, while their bytes stay within ``max_bytes`` (at least one block is always kept).
    Returns what ``read`` would return for the window (a copy, never a view of the cache).
    """

    def __init__(
        self,
        read: Callable[[int, int, int, int], np.ndarray],
        shape: tuple[int, int],
        block: int = BLOCK,
        max_bytes: int = MAX_BYTES,
    ):
        self._read = read
        self.H, self.W = int(shape[0]), int(shape[1])
        self.block = int(block)
        self.max_bytes = int(max_bytes)
        self._blocks: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._bytes = 0
        self.reads = 0  # blocks read from the underlying array (for tests and profiles)

    def _get(self, bi: int, bj: int) -> np.ndarray:
        key = (bi, bj)
        a = self._blocks.get(key)
        if a is not None:
            self._blocks.move_to_end(key)
            return a
        b = self.block
        a = np.asarray(self._read(bi * b, min((bi + 1) * b, self.H), bj * b, min((bj + 1) * b, self.W)))
        self.reads += 1
        self._blocks[key] = a
        self._bytes += a.nbytes
        while self._bytes > self.max_bytes and len(self._blocks) > 1:
            _, old = self._blocks.popitem(last=False)
            self._bytes -= old.nbytes
        return a

    def __call__(self, ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
        ra, rb = max(int(ra), 0), min(int(rb), self.H)
        ca, cb = max(int(ca), 0), min(int(cb), self.W)
        if rb <= ra or cb <= ca:  # an empty window: what the array itself returns for one
            return np.asarray(self._read(ra, max(ra, rb), ca, max(ca, cb)))
        b = self.block
        out = None
        for bi in range(ra // b, (rb - 1) // b + 1):
            for bj in range(ca // b, (cb - 1) // b + 1):
                blk = self._get(bi, bj)
                r0, r1 = max(ra, bi * b), min(rb, (bi + 1) * b)
                c0, c1 = max(ca, bj * b), min(cb, (bj + 1) * b)
                if out is None:
                    out = np.empty((rb - ra, cb - ca) + blk.shape[2:], blk.dtype)
                out[r0 - ra : r1 - ra, c0 - ca : c1 - ca] = blk[r0 - bi * b : r1 - bi * b, c0 - bj * b : c1 - bj * b]
        return out
