"""The time at which each row of a scene was imaged (docs/ais.md, "Physics").

A SAR image line is focused at its zero-Doppler azimuth time: ``first_line_time + line *
azimuth_time_interval_s`` (Sentinel-1: ``imageInformation/productFirstLineUtcTime`` and
``azimuthTimeInterval`` of the annotation, [s1-products]). Rows here are continuous pixel-is-area
coordinates (pixel ``i`` covers ``[i, i + 1)``, its centre ``i + 0.5``, as ``centroid_px``), so a
row ``r`` was imaged at ``first_line_time + (r - 0.5) * azimuth_time_interval_s``.

A scene without line times (no ``sar_geometry.first_line_time``) gives one time for all rows:
the middle of ``acquisition_start`` / ``acquisition_stop`` when it has both, else ``acquired``,
else ``acquisition_start``; a scene without any gives None (AIS matching then refuses in one
line). ISO 8601 times without a zone are UTC (as Sentinel-1 annotations write them).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Mapping
from typing import Any

import numpy as np


def iso_seconds(text: Any) -> float | None:
    """POSIX seconds of an ISO 8601 time (``2021-04-01T05:26:23.794457``, ``...Z``,
    ``...+02:00``; no zone: UTC); None when ``text`` is not one.

    Parameters
    ----------
    text : Any
        The attribute's value.

    Returns
    -------
    float or None
        Seconds since 1970-01-01T00:00:00 UTC.
    """
    if not isinstance(text, str) or not text.strip():
        return None
    s = text.strip()
    if s.endswith(("Z", "z")):
        s = s[:-1] + "+00:00"
    try:
        t = _dt.datetime.fromisoformat(s)
    except ValueError:
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.UTC)
    return t.timestamp()


def scene_time(attrs: Mapping[str, Any]) -> float | None:
    """The scene's one time (module doc: middle of the acquisition, else ``acquired``, else
    ``acquisition_start``), POSIX seconds; None when it has none."""
    t0, t1 = iso_seconds(attrs.get("acquisition_start")), iso_seconds(attrs.get("acquisition_stop"))
    if t0 is not None and t1 is not None and t1 >= t0:
        return 0.5 * (t0 + t1)
    for key in ("acquired", "acquisition_start"):
        t = iso_seconds(attrs.get(key))
        if t is not None:
            return t
    return None


def line_times(attrs: Mapping[str, Any], rows: np.ndarray) -> np.ndarray | None:
    """The zero-Doppler time (POSIX seconds) of continuous ``rows`` of a scene (module doc).

    Parameters
    ----------
    attrs : Mapping
        The scene's attributes: ``sar_geometry.first_line_time`` (ISO 8601 UTC) and
        ``sar_geometry.azimuth_time_interval_s``; else ``acquisition_start`` /
        ``acquisition_stop`` / ``acquired``.
    rows : np.ndarray
        Continuous row coordinates (pixel-is-area).

    Returns
    -------
    np.ndarray or None
        One time per row (float64), or None when the scene carries no time at all.

    References
    ----------
    [s1-products] (``productFirstLineUtcTime``, ``azimuthTimeInterval``).
    """
    rows = np.asarray(rows, np.float64)
    sg = attrs.get("sar_geometry")
    if isinstance(sg, Mapping):
        t0 = iso_seconds(sg.get("first_line_time"))
        ati = sg.get("azimuth_time_interval_s")
        if t0 is not None and isinstance(ati, (int, float)) and np.isfinite(ati) and ati != 0:
            return t0 + (rows - 0.5) * float(ati)
    t = scene_time(attrs)
    return None if t is None else np.full(rows.shape, t)


__all__ = ["iso_seconds", "line_times", "scene_time"]
