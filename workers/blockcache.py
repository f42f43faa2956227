"""Decoded scene blocks kept between the land pass and the detection pass of one job, in the
process that read them (issue 17: the texture land pass read every tile, then the detection
pass decoded the same Zarr chunks again).

The land pass reads each tile once with the detection's context (tile + merge margin + the
detector's halo + the land mask's halo), takes its texture sample from that block and leaves
it here, in the worker process that read it, under ``(job token, tile index)``, returning that
worker's address; the tile's detection is submitted to that worker first (Dask's ``workers=``
with ``allow_other_workers``: when another worker takes it, that one reads the scene) and takes
the block back (removing it), trimming the land halo when the scene has no land. On
``sarship detect``'s in-process threaded worker both passes always meet. A block that does not
fit under the byte limit is not kept (the detection reads it as before), so memory stays
bounded; the job drops whatever is left under its token on every worker when it ends, failed
or not.

Limit per process: ``SARSHIP_BLOCK_CACHE_MB`` (0 turns the cache off), default the machine's
memory / (4 x cores), at most 2048 MiB (so one worker process per core keeps at most a quarter
of the memory).
"""

from __future__ import annotations

import os
import threading
from typing import Any

import numpy as np

_lock = threading.Lock()
_blocks: dict[tuple[str, Any], np.ndarray] = {}
_bytes = 0


def limit_bytes() -> int:
    """The byte limit: ``SARSHIP_BLOCK_CACHE_MB``, else min(memory / (4 x cores), 2 GiB)."""
    raw = os.environ.get("SARSHIP_BLOCK_CACHE_MB", "").strip()
    if raw:
        try:
            return max(0, int(float(raw) * 2**20))
        except ValueError:
            return 0
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8 * 2**30
    return int(min(total // (4 * (os.cpu_count() or 1)), 2 * 2**30))


def put(token: str, key: Any, block: np.ndarray) -> bool:
    """Keep ``block`` under ``(token, key)`` if it fits under the limit; whether it was kept."""
    global _bytes
    n = int(block.nbytes)
    with _lock:
        if _bytes + n > limit_bytes():
            return False
        old = _blocks.pop((token, key), None)
        if old is not None:
            _bytes -= int(old.nbytes)
        _blocks[(token, key)] = block
        _bytes += n
        return True


def take(token: str, key: Any) -> np.ndarray | None:
    """The block kept under ``(token, key)``, removed from the cache; None if there is none."""
    global _bytes
    with _lock:
        block = _blocks.pop((token, key), None)
        if block is not None:
            _bytes -= int(block.nbytes)
        return block


def drop(token: str) -> int:
    """Remove every block of ``token`` (the job ended); how many there were."""
    global _bytes
    with _lock:
        keys = [k for k in _blocks if k[0] == token]
        for k in keys:
            _bytes -= int(_blocks.pop(k).nbytes)
        return len(keys)


def held_bytes() -> int:
    with _lock:
        return _bytes
