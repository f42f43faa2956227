"""The simulated sensor's acquisition geometry (scene attribute ``sar_geometry``).

A C-band stripmap sensor on a Sentinel-1-like orbit, so that the simulator's azimuth
ambiguities (``--ambiguities``, :mod:`~sarship.pipeline.simulate.artefacts`) fall where
:mod:`sarship.pipeline.targets.ambiguity` (eqs. 1-3) expects them from the same attributes:

* radar frequency 5.405 GHz (lambda = 5.547 cm), PRF 1717 Hz, platform velocity 7590 m/s,
  effective velocity 7180 m/s (the Sentinel-1 IW1 values of the annotation in
  ``tests/pipeline/test_ambiguity.py``, rounded);
* range axis: columns in ground range at the scene's range spacing, slant range
  ``R(col) = 800 km + col * d_rg * sin(35 deg)`` (incidence 35 deg, flat Earth locally);
* azimuth axis: rows at the scene's azimuth spacing, i.e. ``dt_line = d_az / Vg`` with
  ``Vg = Vr^2 / Vs`` (the time route and the metre route of eq. 2 agree exactly);
* Doppler centroid 100 Hz (a small residual squint; it makes the k = +1 and k = -1 ghosts'
  range shifts differ, eq. 3), no TOPS steering (spread 0).

At 10 m spacing the first ghosts are ~5.0 km (~500 rows) away along azimuth and 3-4 columns
away in range.

Time and look directions (issue 33, docs/ais.md): ``first_line_time`` (ISO 8601 UTC, the
scene's ``time``) with ``azimuth_time_interval_s`` gives a row's zero-Doppler time
``first_line_time + row * azimuth_time_interval_s``. The scene's frame is north-up (a
georeferenced scene's, :func:`~sarship.pipeline.simulate.land.geo_attrs`; COG and bow
directions of a scene without ``geo`` are read in the same frame): increasing rows run south
(the flight direction, ``flight_direction_deg`` 180), increasing columns east (away from the
radar, ``range_direction_deg`` 90). Flying south and looking east is a *left*-looking geometry
(``look_side``); the azimuth displacement of a moving ship, ``R v_toward / V`` along
increasing rows, does not depend on the look side (docs/ais.md).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sarship.pipeline.targets.ambiguity import Geometry, geometry_from_attrs

RADAR_FREQUENCY_HZ = 5.405e9
PRF_HZ = 1717.0
PLATFORM_VELOCITY_M_S = 7590.0
EFFECTIVE_VELOCITY_M_S = 7180.0
NEAR_RANGE_M = 800_000.0
INCIDENCE_DEG = 35.0
DOPPLER_CENTROID_HZ = 100.0
#: Ground directions (degrees clockwise from north) of increasing rows and increasing columns.
FLIGHT_DIRECTION_DEG = 180.0
RANGE_DIRECTION_DEG = 90.0
#: Columns (range) increase to the left of the flight direction: a left-looking geometry.
LOOK_SIDE = "left"


def sar_geometry(
    shape: tuple[int, int],
    pixel_spacing_m: tuple[float, float],
    first_line_time: str | None = None,
    georeferenced: bool = False,
) -> dict[str, Any]:
    """The ``sar_geometry`` attribute of a simulated scene of ``shape`` and spacing [az, rg].

    Parameters
    ----------
    shape, pixel_spacing_m
        The scene's (rows, cols) and [azimuth, range] spacing (m).
    first_line_time
        The first line's zero-Doppler time (ISO 8601 UTC), recorded as ``first_line_time``.
    georeferenced
        Record the ground directions of the scene's axes (``flight_direction_deg``,
        ``range_direction_deg``, ``look_side``; see the module docstring).
    """
    W = int(shape[1])
    d_az, d_rg = float(pixel_spacing_m[0]), float(pixel_spacing_m[1])
    vg = EFFECTIVE_VELOCITY_M_S**2 / PLATFORM_VELOCITY_M_S
    last = float(max(W - 1, 1))
    slant = [NEAR_RANGE_M, NEAR_RANGE_M + last * d_rg * math.sin(math.radians(INCIDENCE_DEG))]
    out: dict[str, Any] = {
        "source": "sarship simulator (C-band stripmap, Sentinel-1-like orbit)",
        "radar_frequency_hz": RADAR_FREQUENCY_HZ,
        "prf_hz": PRF_HZ,
        "platform_velocity_m_s": PLATFORM_VELOCITY_M_S,
        "azimuth_time_interval_s": d_az / vg,
        "range_table": {
            "col": [0.0, last],
            "slant_range_m": slant,
            "effective_velocity_m_s": [EFFECTIVE_VELOCITY_M_S] * 2,
            "doppler_centroid_hz": [DOPPLER_CENTROID_HZ] * 2,
        },
        "doppler_centroid_spread_hz": 0.0,
    }
    if first_line_time is not None:
        out["first_line_time"] = first_line_time
    if georeferenced:
        out["flight_direction_deg"] = FLIGHT_DIRECTION_DEG
        out["range_direction_deg"] = RANGE_DIRECTION_DEG
        out["look_side"] = LOOK_SIDE
    return out


def slant_range_m(shape: tuple[int, int], pixel_spacing_m: tuple[float, float], col: np.ndarray) -> np.ndarray:
    """Slant range (m) at columns ``col`` (the :func:`sar_geometry` range table, linear)."""
    t = sar_geometry(shape, pixel_spacing_m)["range_table"]
    lo, hi = t["slant_range_m"]
    return lo + (hi - lo) * np.asarray(col, dtype=np.float64) / t["col"][1]


def geometry(shape: tuple[int, int], pixel_spacing_m: tuple[float, float]) -> Geometry:
    """:class:`~sarship.pipeline.targets.ambiguity.Geometry` of :func:`sar_geometry`."""
    return geometry_from_attrs({"sar_geometry": sar_geometry(shape, pixel_spacing_m)})


def ghost_offsets(
    shape: tuple[int, int],
    pixel_spacing_m: tuple[float, float],
    row: float,
    col: float,
    orders: tuple[int, ...] = (-1, 1),
) -> list[tuple[int, int, int]]:
    """``(k, d_row, d_col)`` of the k-th ghosts of a target at (row, col), rounded to whole
    pixels (the simulator moves the ship's rendered block by whole pixels)."""
    g = geometry(shape, pixel_spacing_m).ghosts([row], [col], orders)
    return [
        (int(k), int(np.rint(g["row"][0, i] - row)), int(np.rint(g["col"][0, i] - col))) for i, k in enumerate(orders)
    ]


__all__ = ["ghost_offsets", "geometry", "sar_geometry", "slant_range_m"]
