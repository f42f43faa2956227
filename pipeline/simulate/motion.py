"""Moving ships: speed and course over ground, zero-Doppler times and the azimuth displacement.

Motion (``moving``)
    Each ship gets a speed over ground (SOG, knots) and a course over ground (COG, degrees
    clockwise from north in the scene's north-up frame: rows south, columns east;
    :mod:`~sarship.pipeline.simulate.geometry`) from its own random stream (``_S_MOTION``; no
    other stream changes, so a scene without ``moving`` is the scene it always was). A fraction
    ``anchored_fraction`` is at anchor or drifting: SOG U(0, :data:`ANCHORED_MAX_KN`) kn, COG
    uniform (a drift, unrelated to the bow). The others are under way: SOG U(``speed_kn``), COG =
    bow + N(0, :data:`COG_NOISE_DEG`) (the hull points along the track up to a leeway or drift
    angle). Without ``moving`` (with ``ais``) every ship is at anchor with SOG 0.

Zero-Doppler time
    Row ``y`` (continuous) is imaged at ``first_line_time + y * azimuth_time_interval_s``. A
    ship's *true position* is where it is at its own zero-Doppler time: the time of its true row.

Azimuth displacement
    A target with velocity ``v_toward`` towards the radar has a Doppler offset ``2 v_toward /
    lambda``: its Doppler history crosses zero ``R v_toward / V_r**2`` later, so it is imaged
    ``dx = V_g R v_toward / V_r**2 = R v_toward / V`` metres further along the flight direction
    (increasing rows; ``V_r**2 = V V_g``, ``V`` the platform velocity), whatever the look side
    (Raney 1971, docs/references.md#raney1971). ``v_toward = -(v . u_range)`` with ``u_range`` the
    ground unit vector of increasing columns (away from the radar). A moving ship is rendered at
    its true position moved ``dx / d_az`` rows (``R`` at its column from the geometry's range
    model). Not modelled: the defocus by the along-track velocity and the ship's own motion over
    the aperture (the hull is rendered sharp).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.ais.reports import KNOT_M_S
from sarship.pipeline.simulate.config import SimConfig, parse_time, scene_time
from sarship.pipeline.simulate.fields import _S_MOTION, _rng
from sarship.pipeline.simulate.geometry import (
    INCIDENCE_DEG,
    PLATFORM_VELOCITY_M_S,
    RANGE_DIRECTION_DEG,
    sar_geometry,
    slant_range_m,
)

#: SOG (kn) of the ships at anchor or drifting: U(0, ANCHORED_MAX_KN).
ANCHORED_MAX_KN = 1.0
#: Standard deviation (deg) of COG - bow of the ships under way.
COG_NOISE_DEG = 2.0


@dataclass(frozen=True)
class Motion:
    """Per ship (index = ship id): ``sog_kn``, ``anchored``, and the COG draws (``cog_offset_deg``:
    COG - bow under way; ``drift_cog_deg``: COG at anchor)."""

    sog_kn: np.ndarray
    anchored: np.ndarray
    cog_offset_deg: np.ndarray
    drift_cog_deg: np.ndarray

    def cog_deg(self, i: int, bow_deg: float) -> float:
        """COG of ship ``i`` whose bow points at ``bow_deg``."""
        c = self.drift_cog_deg[i] if self.anchored[i] else bow_deg + self.cog_offset_deg[i]
        return float(c % 360.0)


def draw_motion(cfg: SimConfig) -> Motion | None:
    """The ships' motion (None unless ``cfg.moving`` or ``cfg.ais``); ``cfg`` validated.

    All draws are made whatever their values (one stream, fixed order), so a ship's motion depends
    only on the seed, its index and the motion fields.
    """
    if not (cfg.moving or cfg.ais):
        return None
    n = cfg.ships
    rng = _rng(cfg.seed, _S_MOTION)
    anchored = rng.random(n) < cfg.anchored_fraction
    under_way = rng.uniform(cfg.speed_kn[0], cfg.speed_kn[1], n)
    drifting = rng.uniform(0.0, ANCHORED_MAX_KN, n)
    offset = rng.normal(0.0, COG_NOISE_DEG, n)
    drift_cog = rng.uniform(0.0, 360.0, n)
    if not cfg.moving:
        return Motion(np.zeros(n), np.ones(n, dtype=bool), offset, drift_cog)
    return Motion(np.where(anchored, drifting, under_way), anchored, offset, drift_cog)


def ground_velocity(sog_kn: Any, cog_deg: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(v_east, v_north)`` in m/s of a SOG (knots) and COG (degrees from true north).

    Parameters
    ----------
    sog_kn, cog_deg
        Arrays (or numbers) of the same shape.

    Returns
    -------
    tuple of numpy.ndarray
        East and north components, m/s.
    """
    v = np.asarray(sog_kn, dtype=np.float64) * KNOT_M_S
    c = np.radians(np.asarray(cog_deg, dtype=np.float64))
    return v * np.sin(c), v * np.cos(c)


def velocity_towards_radar(
    v_east: Any,
    v_north: Any,
    range_direction_deg: float = RANGE_DIRECTION_DEG,
    sin_incidence: float = math.sin(math.radians(INCIDENCE_DEG)),
) -> np.ndarray:
    """``v_toward = -(v . u_range) sin(theta)`` (m/s): the line-of-sight velocity towards the radar
    of a ship moving on the sea surface (its ground-range velocity seen at incidence ``theta``).

    Parameters
    ----------
    v_east, v_north
        Ground velocity (m/s).
    range_direction_deg
        Ground direction (degrees from north) of increasing range (columns), away from the radar.
    sin_incidence
        ``sin`` of the incidence angle (the simulated sensor's 35 degrees by default).
    """
    a = math.radians(range_direction_deg)
    v_ground = np.asarray(v_east, dtype=np.float64) * math.sin(a) + np.asarray(v_north, dtype=np.float64) * math.cos(a)
    return -v_ground * sin_incidence


def azimuth_displacement_m(
    slant_range: Any, v_toward_m_s: Any, platform_velocity_m_s: float = PLATFORM_VELOCITY_M_S
) -> np.ndarray:
    """``dx = R v_toward / V``: how far (m) along the flight direction a moving target is imaged.

    Parameters
    ----------
    slant_range
        Slant range R (m).
    v_toward_m_s
        Velocity component towards the radar (m/s; positive: approaching).
    platform_velocity_m_s
        Platform velocity V (m/s).

    Returns
    -------
    numpy.ndarray
        The displacement (m); positive along increasing rows (later azimuth time).

    References
    ----------
    R. K. Raney, "Synthetic aperture imaging radar and moving targets", IEEE Trans. Aerospace
    and Electronic Systems 7(3), 1971 (docs/references.md#raney1971).
    """
    return (
        np.asarray(slant_range, dtype=np.float64) * np.asarray(v_toward_m_s, dtype=np.float64) / platform_velocity_m_s
    )


def displacement_rows(cfg: SimConfig, col: Any, sog_kn: Any, cog_deg: Any) -> np.ndarray:
    """The azimuth displacement (rows) of ships at column ``col`` moving at SOG/COG."""
    ve, vn = ground_velocity(sog_kn, cog_deg)
    r = slant_range_m(cfg.shape, cfg.pixel_spacing_m, col)
    return azimuth_displacement_m(r, velocity_towards_radar(ve, vn)) / cfg.pixel_spacing_m[0]


def first_line_posix(cfg: SimConfig) -> float:
    """POSIX seconds of the scene's first line time."""
    return parse_time(scene_time(cfg)).timestamp()


def zero_doppler_time_s(cfg: SimConfig, row: Any) -> np.ndarray:
    """POSIX seconds at which rows ``row`` (continuous) are imaged: ``t0 + row * dt``."""
    dt = sar_geometry(cfg.shape, cfg.pixel_spacing_m)["azimuth_time_interval_s"]
    return first_line_posix(cfg) + np.asarray(row, dtype=np.float64) * dt


def iso_time(t_s: float) -> str:
    """ISO 8601 UTC (microseconds) of POSIX seconds ``t_s``."""
    return _dt.datetime.fromtimestamp(t_s, _dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def motion_properties(cfg: SimConfig, s: Any) -> dict[str, Any]:
    """A truth Feature's motion properties of ship ``s`` (a placed ``_Ship`` with motion).

    ``sog_kn``, ``cog_deg``, ``bow_deg`` (the hull's heading), ``v_toward_m_s``,
    ``true_position_px`` (the hull centre at its zero-Doppler time), ``displaced_position_px``
    (where it is imaged), ``displacement_px`` (rows, positive along increasing rows) and
    ``displacement_m``, ``zero_doppler_time`` (of the true row) and, for a ``geo`` scene, the true
    ``lon`` and ``lat``.
    """
    ve, vn = ground_velocity(s.sog_kn, s.cog_deg)
    d = float(s.rc - s.rc_true)
    out = {
        "sog_kn": float(s.sog_kn),
        "cog_deg": float(s.cog_deg),
        "bow_deg": float(s.bow_deg),
        "v_toward_m_s": float(velocity_towards_radar(ve, vn)),
        "true_position_px": [float(s.rc_true), float(s.cc)],
        "displaced_position_px": [float(s.rc), float(s.cc)],
        "displacement_px": d,
        "displacement_m": d * cfg.pixel_spacing_m[0],
        "zero_doppler_time": iso_time(float(zero_doppler_time_s(cfg, s.rc_true))),
    }
    if cfg.geo is not None:
        from sarship.pipeline.simulate.land import geo_lonlat

        lon, lat = geo_lonlat(cfg, s.rc_true, s.cc)
        out["lon"], out["lat"] = float(lon), float(lat)
    return out


__all__ = [
    "ANCHORED_MAX_KN",
    "COG_NOISE_DEG",
    "Motion",
    "azimuth_displacement_m",
    "displacement_rows",
    "draw_motion",
    "first_line_posix",
    "ground_velocity",
    "iso_time",
    "motion_properties",
    "velocity_towards_radar",
    "zero_doppler_time_s",
]
