"""Whether the AIS given covers a scene, the scene's footprint, and the ``dark`` rule
(docs/ais.md, "Matching").

**Coverage rule.** The AIS given covers a scene imaged from ``t_start`` to ``t_stop`` when it
holds position reports inside the footprint (or anywhere, without one) both at most
``max_report_gap_s`` before ``t_start`` (``t_start - gap <= t <= t_start``) and at most that long
after ``t_stop``: the feed was live around the acquisition there. It cannot tell how far a feed
reaches (a coastal receiver's ~40 nautical miles, a satellite feed's revisit): a detection is
called dark on the strength of the file the user gave.

**Dark.** A detection is dark when no vessel matched it and the AIS covers the scene; ``dark``
is unknown (``None``) when it does not, and when no AIS was given at all.
"""

from __future__ import annotations

import numpy as np

from sarship.pipeline.ais.displacement import PixelToLonLat
from sarship.pipeline.ais.reports import Reports
from sarship.pipeline.errors import InputError


def footprint_ring(georef: PixelToLonLat, shape: tuple[int, int], *, points_per_side: int = 16) -> np.ndarray:
    """The scene's outline in lon/lat: its border (continuous pixel coordinates ``[0, H] x [0,
    W]``) sampled at ``points_per_side`` points per side, closed, counter-clockwise in pixels.

    Parameters
    ----------
    georef : object with ``lonlat(rows, cols)``
        The scene's pixel -> lon/lat mapping.
    shape : tuple of int
        ``(H, W)``.
    points_per_side : int, default 16
        Samples per side (a GRD's border is nearly straight; 16 follows its curvature to metres).

    Returns
    -------
    np.ndarray
        ``(4 points_per_side + 1, 2)`` lon/lat, the first point repeated last.
    """
    H, W = (float(v) for v in shape)
    if not (H > 0 and W > 0) or points_per_side < 1:
        raise InputError(f"a footprint needs a positive shape and points_per_side >= 1, got {shape}, {points_per_side}")
    s = np.linspace(0.0, 1.0, points_per_side, endpoint=False)
    rows = np.concatenate([s * H, np.full_like(s, H), (1 - s) * H, np.zeros_like(s), [0.0]])
    cols = np.concatenate([np.zeros_like(s), s * W, np.full_like(s, W), (1 - s) * W, [0.0]])
    lon, lat = georef.lonlat(rows, cols)
    return np.stack([np.asarray(lon, np.float64), np.asarray(lat, np.float64)], -1)


def inside(lon: np.ndarray, lat: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Which points lie inside the closed lon/lat polygon ``ring`` (even-odd ray casting,
    vectorised over points; longitudes unwrapped about the ring's first point, so a footprint
    across the antimeridian works).

    Parameters
    ----------
    lon, lat : np.ndarray
        Points, WGS84 degrees.
    ring : np.ndarray
        ``(k, 2)`` polygon vertices (lon, lat); closed or not.

    Returns
    -------
    np.ndarray
        Boolean mask, the shape of ``lon``.
    """
    ring = np.asarray(ring, np.float64)
    ref = ring[0, 0]
    rx = ref + (ring[:, 0] - ref + 180.0) % 360.0 - 180.0
    ry = ring[:, 1]
    x = ref + (np.asarray(lon, np.float64) - ref + 180.0) % 360.0 - 180.0
    y = np.asarray(lat, np.float64)
    out = np.zeros(x.shape, bool)
    x0s, y0s = rx, ry
    x1s, y1s = np.roll(rx, -1), np.roll(ry, -1)
    for x0, y0, x1, y1 in zip(x0s, y0s, x1s, y1s):  # over the ring's few edges; vectorised over points
        if y0 == y1:
            continue
        crosses = (y0 > y) != (y1 > y)
        xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        out ^= crosses & (x < xc)
    return out


def covers_scene(
    reports: Reports,
    t_start: float,
    t_stop: float,
    *,
    ring: np.ndarray | None = None,
    max_report_gap_s: float = 600.0,
) -> bool:
    """The coverage rule of the module doc: reports (inside ``ring`` when given) both within
    ``max_report_gap_s`` before ``t_start`` and within it after ``t_stop``.

    Parameters
    ----------
    reports : Reports
        The AIS reports read for the scene.
    t_start, t_stop : float
        The scene's first and last line times (the same time twice for a scene with one).
    ring : np.ndarray, optional
        The footprint (:func:`footprint_ring`); reports anywhere count without it.
    max_report_gap_s : float, default 600
        How long before and after the scene a report must exist. 600 s: a live feed carries a
        class A vessel under way every 2-10 s and at anchor every 3 minutes [itu-m1371]; ten
        minutes without any report in the footprint is a gap in the feed, not quiet sea traffic.

    Returns
    -------
    bool

    References
    ----------
    [itu-m1371].
    """
    if not (np.isfinite(max_report_gap_s) and max_report_gap_s >= 0):
        raise InputError(f"max_report_gap_s must be a finite number >= 0, got {max_report_gap_s!r}")
    t = np.asarray(reports.t, np.float64)
    sel = (t >= t_start - max_report_gap_s) & (t <= t_stop + max_report_gap_s)
    if ring is not None and sel.any():
        sel[sel] = inside(reports.lon[sel], reports.lat[sel], ring)
    ts = t[sel]
    return bool(np.any(ts <= t_start) and np.any(ts >= t_stop))


def dark_flags(vessel_of_detection: np.ndarray, covered: bool) -> np.ndarray | None:
    """Per detection ``dark`` (True: no vessel matched it) when the AIS covers the scene, else
    None (unknown for every detection).

    Parameters
    ----------
    vessel_of_detection : np.ndarray
        :attr:`sarship.pipeline.ais.match.Assignment.vessel` (-1: unmatched).
    covered : bool
        :func:`covers_scene`.

    Returns
    -------
    np.ndarray or None
        Boolean per detection, or None.
    """
    return (np.asarray(vessel_of_detection) < 0) if covered else None


__all__ = ["covers_scene", "dark_flags", "footprint_ring", "inside"]
