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


def sar_geometry(shape: tuple[int, int], pixel_spacing_m: tuple[float, float]) -> dict[str, Any]:
    """The ``sar_geometry`` attribute of a simulated scene of ``shape`` and spacing [az, rg]."""
    W = int(shape[1])
    d_az, d_rg = float(pixel_spacing_m[0]), float(pixel_spacing_m[1])
    vg = EFFECTIVE_VELOCITY_M_S**2 / PLATFORM_VELOCITY_M_S
    last = float(max(W - 1, 1))
    slant = [NEAR_RANGE_M, NEAR_RANGE_M + last * d_rg * math.sin(math.radians(INCIDENCE_DEG))]
    return {
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


__all__ = ["ghost_offsets", "geometry", "sar_geometry"]
