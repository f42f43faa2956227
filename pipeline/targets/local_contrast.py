"""Each detection's local contrast: its mean power over the mean power of the clutter around it.

The seed-003 chain discriminates its candidates by geometry and by "scattering characteristics
(amplitude, intensity)" (docs/references.md#liu2017, step 4), and the superpixel CFAR of
seed 002 decides with a local contrast (docs/references.md#zhang2023, eq 11-13). This is the
object-level form of both: for a detection with bounding box ``[r0, r1) x [c0, c1)``, its
clutter ring is every pixel within :data:`RING_PX` pixels (Chebyshev) of the box grown by
:data:`GAP_PX`, less

- the box grown by :data:`GAP_PX` itself (the ship and the skirt of its impulse response),
- pixels of the detection mask (this and every other detection, kept or not),
- land (the run's land mask, when it has one) and absent pixels (not finite, or the
  detector's ``nodata`` value),

and ``contrast_db = 10 log10(mean / ring_mean)``, ``mean`` being the detection's mean pixel
power (its ``mean`` property). A ring of fewer than :data:`MIN_RING_PX` pixels, or with a
mean that is not positive, measures nothing (``None``).

Why local and not the scene's sea level (``tcr_db``): the sea's backscatter changes across a
scene by several dB (incidence angle across a Sentinel-1 swath, wind fronts, slicks); a ship
in the dark far range measured against the scene's mean sea would look dimmer than it is.
The ring reads only the scene, the detection mask and the land mask, so the value does not
depend on the tiling.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

#: the ring starts this many pixels outside the detection's bounding box
GAP_PX = 3
#: and is this many pixels wide
RING_PX = 16
#: a ring with fewer usable pixels measures nothing
MIN_RING_PX = 32

Reader = Callable[[int, int, int, int], np.ndarray]


def ring_mean(
    power: np.ndarray,
    excluded: np.ndarray,
    box: tuple[int, int, int, int],
    window: tuple[int, int, int, int],
    gap: int = GAP_PX,
) -> tuple[float, int]:
    """Mean of ``power`` over the ring pixels of one detection, and their number.

    ``power`` and ``excluded`` (bool: detected, land or absent) cover ``window`` =
    ``(ra, rb, ca, cb)`` in scene pixels; ``box`` = ``(r0, r1, c0, c1)`` is the detection's
    bounding box (end exclusive). The ring is the window less the box grown by ``gap``.
    """
    ra, rb, ca, cb = window
    r0, r1, c0, c1 = box
    use = ~excluded
    ia, ib = max(r0 - gap - ra, 0), min(r1 + gap - ra, rb - ra)
    ja, jb = max(c0 - gap - ca, 0), min(c1 + gap - ca, cb - ca)
    use[ia:ib, ja:jb] = False
    n = int(use.sum())
    if n == 0:
        return float("nan"), 0
    return float(np.mean(power[use], dtype=np.float64)), n


def add_local_contrast(
    feats: list[dict],
    read_power: Reader,
    read_mask: Reader,
    shape: tuple[int, int],
    read_land: Reader | None = None,
    nodata: float | None = None,
    gap: int = GAP_PX,
    ring: int = RING_PX,
    min_ring: int = MIN_RING_PX,
) -> list[dict]:
    """Set ``contrast_db`` (and ``contrast_ring_px``, the ring's pixel count) on every feature.

    ``read_power(ra, rb, ca, cb)``: pixel power of the scene rectangle (what the detector read,
    made power by :func:`sarship.pipeline.tiling.inputs.pixel_power`); ``read_mask``: the detection
    mask; ``read_land``: the run's land mask (non-zero = land) or None.
    """
    H, W = shape
    for f in feats:
        p = f["properties"]
        r0, c0, r1, c1 = p["bbox_px"]  # half-open (docs/interfaces/files.md)
        box = (int(r0), int(r1), int(c0), int(c1))
        m = gap + ring
        win = (max(box[0] - m, 0), min(box[1] + m, H), max(box[2] - m, 0), min(box[3] + m, W))
        power = np.asarray(read_power(*win), np.float64)
        excluded = np.asarray(read_mask(*win)) != 0
        excluded |= ~np.isfinite(power)
        if nodata is not None:
            excluded |= power == nodata
        if read_land is not None:
            excluded |= np.asarray(read_land(*win)) != 0
        ref, n = ring_mean(power, excluded, box, win, gap)
        mean = p.get("mean")
        ok = n >= min_ring and ref > 0 and mean is not None and math.isfinite(mean) and mean > 0
        p["contrast_db"] = round(10.0 * math.log10(mean / ref), 3) if ok else None
        p["contrast_ring_px"] = n
    return feats


def keep_contrast(feats: list[dict], min_contrast_db: float | None) -> list[bool]:
    """Which features pass ``min_contrast_db``: all when it is None; a feature whose contrast
    could not be measured (``contrast_db`` null) is kept (nothing says it is clutter)."""
    if min_contrast_db is None:
        return [True] * len(feats)
    return [
        f["properties"].get("contrast_db") is None or f["properties"]["contrast_db"] >= min_contrast_db for f in feats
    ]
