"""The azimuth displacement of a moving ship in a SAR image, and the look geometry it needs
(docs/ais.md, "Physics").

A target with velocity ``v_los`` along the line of sight towards the radar adds a Doppler
shift ``2 v_los / lambda`` to its azimuth history; zero-Doppler processing then images it at
the azimuth time where the stationary target's Doppler ``-2 V^2 (t - t0) / (lambda R)``
cancels that shift, ``dt = R v_los / V^2``, i.e. displaced along the flight direction by
([raney1971], eq. (1) of docs/ais.md)::

    dx = R v_los / V                                        (1)

(``R`` the slant range, ``V`` the platform velocity; ``V_ground dt`` with ``V_eff^2 = V
V_ground``). A ship moving towards the radar appears ahead of itself, along the flight. The
line-of-sight velocity of a ship moving horizontally at ``v`` is its ground-range component
projected on the slant direction::

    v_los = -(v . u_range) sin(theta_i)                     (2)

with ``u_range`` the unit ground vector of increasing range (away from the radar) and
``theta_i`` the incidence angle; ``sin(theta_i) = dR / dg``, the slant range's rate of change
with ground distance across track (flat Earth locally), which :func:`look_geometry` reads from
the scene itself: ``dR/dcol`` of the ``range_table`` over the ground metres per column of the
georeference.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from sarship.pipeline.ais.tracks import M_PER_DEG


class PixelToLonLat(Protocol):
    def lonlat(self, rows: Any, cols: Any) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class LookGeometry:
    """Per detection: the unit ground vectors (east, north components) of the flight direction
    (increasing azimuth time) and of increasing range (away from the radar), the slant range
    (m), the platform velocity (m/s) and ``sin`` of the incidence angle; NaN where unknown."""

    flight_east: np.ndarray
    flight_north: np.ndarray
    range_east: np.ndarray
    range_north: np.ndarray
    slant_range_m: np.ndarray
    platform_velocity_m_s: np.ndarray
    sin_incidence: np.ndarray

    def __len__(self) -> int:
        return int(np.asarray(self.slant_range_m).size)

    def valid(self) -> np.ndarray:
        """Where every field is finite (a displacement can be computed)."""
        ok = np.ones(len(self), bool)
        for v in (self.flight_east, self.flight_north, self.range_east, self.range_north):
            ok &= np.isfinite(v)
        for v in (self.slant_range_m, self.platform_velocity_m_s, self.sin_incidence):
            ok &= np.isfinite(v) & (np.asarray(v) > 0)
        return ok

    def take(self, idx: np.ndarray) -> LookGeometry:
        """The rows ``idx``."""
        return LookGeometry(*(np.asarray(getattr(self, f))[idx] for f in self.__dataclass_fields__))


def azimuth_shift_m(
    v_east: np.ndarray,
    v_north: np.ndarray,
    range_east: np.ndarray,
    range_north: np.ndarray,
    slant_range_m: np.ndarray,
    platform_velocity_m_s: np.ndarray,
    sin_incidence: np.ndarray | float = 1.0,
) -> np.ndarray:
    """The azimuth displacement of a moving ship, metres along the flight direction (eqs. 1-2
    of the module doc): positive (ahead, towards increasing azimuth time) for a ship moving
    towards the radar.

    Parameters
    ----------
    v_east, v_north : np.ndarray
        The ship's velocity over ground, m/s.
    range_east, range_north : np.ndarray
        The unit ground vector of increasing range (away from the radar).
    slant_range_m : np.ndarray
        Slant range ``R`` at the ship, m.
    platform_velocity_m_s : np.ndarray
        The platform velocity ``V``, m/s.
    sin_incidence : np.ndarray or float, default 1.0
        ``sin(theta_i)``, the slant-range share of a ground-range velocity (eq. 2). The default
        1 gives the ground-range form ``R v_toward / V`` with ``v_toward = -(v . u_range)``;
        :func:`look_geometry` gives the scene's value (about 0.5-0.7 for Sentinel-1 IW).

    Returns
    -------
    np.ndarray
        ``dx = R v_los / V``, m (broadcast shape of the inputs).

    References
    ----------
    [raney1971].
    """
    v_toward = -(np.asarray(v_east) * range_east + np.asarray(v_north) * range_north)
    return np.asarray(slant_range_m) * v_toward * np.asarray(sin_incidence) / np.asarray(platform_velocity_m_s)


def _unit_en(geo: PixelToLonLat, r: np.ndarray, c: np.ndarray, dr: float, dc: float, h: float):
    """East/north metres per unit step (dr, dc) at (r, c) by central differences of ``h`` px,
    and their length (ground metres per unit step)."""
    x1, y1 = geo.lonlat(r + h * dr, c + h * dc)
    x0, y0 = geo.lonlat(r - h * dr, c - h * dc)
    x1, y1, x0, y0 = (np.asarray(a, np.float64) for a in (x1, y1, x0, y0))
    coslat = np.cos(np.radians(0.5 * (y0 + y1)))
    e = ((x1 - x0 + 180.0) % 360.0 - 180.0) * coslat * M_PER_DEG / (2 * h)
    n = (y1 - y0) * M_PER_DEG / (2 * h)
    length = np.hypot(e, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        return e / length, n / length, length


def look_vectors(
    georef: PixelToLonLat, rows: np.ndarray, cols: np.ndarray, *, step_px: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per detection the unit ground vectors (east, north) of increasing rows and of increasing
    columns, from central differences of the scene's pixel -> lon/lat mapping.

    Parameters
    ----------
    georef : object with ``lonlat(rows, cols)``
        The scene's georeference (:class:`sarship.pipeline.targets.ship_features.Georeference`,
        or a mapping of :mod:`sarship.pipeline.targets.georef`).
    rows, cols : np.ndarray
        Continuous pixel coordinates (pixel-is-area, as ``centroid_px``).
    step_px : float, default 0.5
        Half the finite-difference step, pixels (exact for the bilinear grid within a cell).

    Returns
    -------
    tuple of np.ndarray
        ``(row_east, row_north, col_east, col_north)``: increasing rows (the flight direction
        where azimuth time grows with the row) and increasing columns (away from the radar where
        slant range grows with the column). :func:`look_geometry` orients both from the scene's
        ``sar_geometry``.
    """
    r, c = np.broadcast_arrays(np.asarray(rows, np.float64), np.asarray(cols, np.float64))
    fe, fn, _ = _unit_en(georef, r, c, 1.0, 0.0, step_px)
    re_, rn, _ = _unit_en(georef, r, c, 0.0, 1.0, step_px)
    return fe, fn, re_, rn


def slant_range_m(sar_geometry: Mapping[str, Any], cols: np.ndarray) -> np.ndarray:
    """The slant range (m) at continuous columns ``cols``, interpolated linearly in the
    ``range_table`` (its ``col`` are annotation sample indices, the centre of pixel ``col`` at
    ``col + 0.5`` in continuous coordinates) and extended linearly beyond its ends; NaN without a
    usable table (fewer than 2 points, non-increasing or non-finite columns)."""
    cols = np.asarray(cols, np.float64)
    table = sar_geometry.get("range_table") if isinstance(sar_geometry, Mapping) else None
    try:
        tc = np.asarray(table["col"], np.float64)
        tr = np.asarray(table["slant_range_m"], np.float64)
    except (KeyError, TypeError, ValueError):
        return np.full(cols.shape, np.nan)
    ok = tc.ndim == 1 and tc.shape == tr.shape and tc.size >= 2
    if not ok or not (np.all(np.isfinite(tc)) and np.all(np.isfinite(tr)) and np.all(np.diff(tc) > 0)):
        return np.full(cols.shape, np.nan)
    x = cols - 0.5
    out = np.interp(x, tc, tr)
    lo, hi = x < tc[0], x > tc[-1]
    out[lo] = tr[0] + (x[lo] - tc[0]) * (tr[1] - tr[0]) / (tc[1] - tc[0])
    out[hi] = tr[-1] + (x[hi] - tc[-1]) * (tr[-1] - tr[-2]) / (tc[-1] - tc[-2])
    return out


def look_geometry(
    attrs: Mapping[str, Any], georef: PixelToLonLat, rows: np.ndarray, cols: np.ndarray
) -> LookGeometry | None:
    """The :class:`LookGeometry` of detections at continuous ``(rows, cols)`` of a scene with
    attributes ``attrs`` (its ``sar_geometry``: ``range_table``, ``platform_velocity_m_s``,
    ``azimuth_time_interval_s``) and georeference ``georef``; None when the scene has no usable
    ``sar_geometry``.

    The flight direction is that of increasing rows, reversed when ``azimuth_time_interval_s <
    0``; the range direction that of increasing columns, reversed where the slant range
    decreases with the column; ``sin(theta_i) = |dR/dcol| / (ground metres per column)`` (eq. 2
    of the module doc), NaN outside (0, 1].
    """
    sg = attrs.get("sar_geometry") if isinstance(attrs, Mapping) else None
    if not isinstance(sg, Mapping) or "unavailable" in sg:
        return None
    try:
        V = float(sg["platform_velocity_m_s"])
    except (KeyError, TypeError, ValueError):
        return None
    if not (np.isfinite(V) and V > 0):
        return None
    r, c = np.broadcast_arrays(np.asarray(rows, np.float64), np.asarray(cols, np.float64))
    R = slant_range_m(sg, c)
    if not np.isfinite(R).any():
        return None
    ati = sg.get("azimuth_time_interval_s")
    fsign = -1.0 if isinstance(ati, (int, float)) and ati < 0 else 1.0
    fe, fn, _ = _unit_en(georef, r, c, 1.0, 0.0, 0.5)
    re_, rn, g_per_col = _unit_en(georef, r, c, 0.0, 1.0, 0.5)
    dR = (slant_range_m(sg, c + 0.5) - slant_range_m(sg, c - 0.5)) / 1.0
    rsign = np.where(dR < 0, -1.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_i = np.abs(dR) / g_per_col
    sin_i = np.where((sin_i > 0) & (sin_i <= 1.0 + 1e-6), np.minimum(sin_i, 1.0), np.nan)
    return LookGeometry(
        fsign * fe,
        fsign * fn,
        rsign * re_,
        rsign * rn,
        R,
        np.full(R.shape, V),
        sin_i,
    )


__all__ = ["LookGeometry", "azimuth_shift_m", "look_geometry", "look_vectors", "slant_range_m"]
