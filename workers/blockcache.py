"""The memory budget for the scene reads a job keeps between its texture land pass and its
detection pass (issue 17: the land pass read every tile, then the detection pass decoded the
same Zarr chunks again).

The land pass reads each tile once with the detection's context (tile + merge margin + the
detector's halo + the land mask's halo: :func:`sarship.workers.tasks.read_land_block`); the
job keeps that read as Dask data on the worker that made it and passes it to the tile's
texture sample and to its detection, so Dask runs both where the read is, within the job's
placement (GPU / CPU workers), and moves it only when another worker must run them (a worker
busy or gone); the read is released once the tile's detection is done (workers/jobs.py). A job
keeps at most as many reads as fit in this budget per worker of the cluster; the other tiles'
detections read the scene again.

Budget per worker: ``SARSHIP_BLOCK_CACHE_MB`` (0: keep none), default the machine's memory /
(4 x cores), at most 2048 MiB (so one worker process per core keeps at most a quarter of the
memory).
"""

from __future__ import annotations

import os

from sarship.pipeline import settings


def limit_bytes() -> int:
    """The byte budget per worker: ``SARSHIP_BLOCK_CACHE_MB`` (MiB, a number >= 0), else
    min(memory / (4 x cores), 2 GiB); a value that is not such a number is an
    :class:`InputError` naming the setting."""
    mib = settings.read("block_cache_mb")
    if mib is not None:
        return int(mib * 2**20)
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8 * 2**30
    return int(min(total // (4 * (os.cpu_count() or 1)), 2 * 2**30))
