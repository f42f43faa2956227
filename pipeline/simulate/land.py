"""Land: coast geometry, land mask and land backscatter parameters.

Land (``land``)
    A coast on one side (drawn from the seed), land depth 15-30 % of the scene plus a fractal
    displacement: a sum of octaves of 1-D cubic-B-spline noise with amplitude ~ scale^H,
    H = 0.7 (fractional-Brownian-like coastline, Mandelbrot 1967; box dimension ~ 1.3).
    Land mean backscatter is +8..12 dB over the sea (a smooth field 10 +- 1 dB clipped to
    [8, 12]), times a strong texture (Gamma(nu = 1), correlation 6 px), with bright urban
    point scatterers (density 1 / 1500 px, +20..35 dB, dihedral/trihedral in quad-pol).
    Quad-pol land covariance: eps = 0.15, gamma = 0.8, rho = 0.35 (vegetation/urban mix).

Georeferenced scenes (``geo``: the scene centre's lon/lat)
    The scene is placed on the Earth north-up (:func:`geo_attrs`: ``crs`` EPSG:4326 and an
    affine ``transform``, or the same mapping as a 6 x 6 grid of ``gcps`` with ``geo_gcps``),
    ``pixel_spacing_m`` metres a pixel (111 320 m a degree of latitude, times cos(lat) of
    longitude). With ``land`` the coast is not drawn from the seed: a pixel is land when its
    centre is inside the GSHHG shoreline (:meth:`sarship.pipeline.land.coastline.Coastline.land`,
    no buffer; extra ``coastline``), so the simulated land is the land ``land_mask=coastline``
    knows. The land's backscatter is the same as above.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.simulate.config import SimConfig
from sarship.pipeline.simulate.fields import _S_COAST, _S_LAND, _axis_weights, _rng

#: Quad-pol land covariance parameters.
LAND_EPS, LAND_GAMMA, LAND_RHO = 0.15, 0.8, complex(0.35, 0.0)
URBAN_PX_PER_POINT = 1500.0
LAND_TEXTURE_NU = 1.0
LAND_TEXTURE_CORR_PX = 6.0
LAND_GAIN_CORR_PX = 64.0
#: Georeferenced scenes: ships keep this many pixels of sea around their box (>= the ships
#: module's LAND_MARGIN_PX).
LAND_CLEARANCE_PX = 8


@dataclass
class _Land:
    side: str  # "top" | "bottom" | "left" | "right"
    depth: float  # mean depth, px
    octaves: list[tuple[float, float, np.ndarray]]


def _land_model(cfg: SimConfig) -> _Land | _GeoLand:
    if cfg.geo is not None:
        return _geo_land_model(cfg)
    H, W = cfg.shape
    rng = _rng(cfg.seed, _S_LAND)
    side = ("top", "bottom", "left", "right")[int(rng.integers(0, 4))]
    along, perp = (W, H) if side in ("top", "bottom") else (H, W)
    depth = float(rng.uniform(0.15, 0.30)) * perp
    a0 = 0.08 * perp
    octaves = []
    s = along / 2.0
    o = 0
    while s >= 3.0 and o < 16:
        n = int(math.ceil(along / s)) + 8
        nodes = _rng(cfg.seed, _S_COAST, o).standard_normal(n)
        octaves.append((s, a0 * 2.0 ** (-0.7 * o), nodes))
        s /= 2.0
        o += 1
    return _Land(side=side, depth=depth, octaves=octaves)


def _coast(land: _Land, along: np.ndarray) -> np.ndarray:
    """Land depth (px from the land side) at pixel-centre coordinates ``along``."""
    d = np.full(along.shape, land.depth)
    for s, amp, nodes in land.octaves:
        k, w = _axis_weights(along, s)
        k = k + 2
        d += amp * (w[0] * nodes[k] + w[1] * nodes[k + 1] + w[2] * nodes[k + 2] + w[3] * nodes[k + 3])
    return d


#: Metres per degree of latitude of the simulator's georeference (the mean).
M_PER_DEG = 111_320.0


def geo_attrs(cfg: SimConfig) -> dict:
    """The georeference attributes of a ``geo`` scene: north-up, centred on ``cfg.geo``, one
    pixel ``pixel_spacing_m`` metres (azimuth = rows southward, range = columns eastward)."""
    lon, lat = cfg.geo
    H, W = cfg.shape
    dlat = cfg.pixel_spacing_m[0] / M_PER_DEG
    dlon = cfg.pixel_spacing_m[1] / (M_PER_DEG * math.cos(math.radians(lat)))
    transform = [lon - W / 2.0 * dlon, dlon, 0.0, lat + H / 2.0 * dlat, 0.0, -dlat]
    if not cfg.geo_gcps:
        return {"crs": "EPSG:4326", "transform": transform}
    c, a, b, f, d, e = transform
    gcps = [
        {"row": float(r), "col": float(q), "x": c + a * q + b * r, "y": f + d * q + e * r}
        for r in np.linspace(0.0, H, 6)
        for q in np.linspace(0.0, W, 6)
    ]
    return {"crs": "EPSG:4326", "gcps": gcps}


def geo_lonlat(cfg: SimConfig, row: Any, col: Any) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 (lon, lat) of continuous pixel coordinates (``row``, ``col``) of a ``geo`` scene
    (the affine mapping of :func:`geo_attrs`, which its GCPs sample too)."""
    c, a, b, f, d, e = geo_attrs(dataclasses.replace(cfg, geo_gcps=False))["transform"]
    row = np.asarray(row, dtype=np.float64)
    col = np.asarray(col, dtype=np.float64)
    return c + a * col + b * row, f + d * col + e * row


@dataclass
class _GeoLand:
    """Land of a georeferenced scene: the GSHHG shoreline through the scene's georeference."""

    coast: Any  # sarship.pipeline.land.coastline.Coastline (buffer 0)
    side: str = "gshhg"


def _geo_land_model(cfg: SimConfig) -> _GeoLand:
    from sarship.pipeline.land.coastline import open_coastline

    return _GeoLand(
        coast=open_coastline({**geo_attrs(cfg), "pixel_spacing_m": list(cfg.pixel_spacing_m)}, cfg.shape, buffer_m=0.0)
    )


def _land_mask(cfg: SimConfig, land: _Land | _GeoLand, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    if isinstance(land, _GeoLand):
        return land.coast.land(r0, r1, c0, c1)
    H, W = cfg.shape
    rows = np.arange(r0, r1) + 0.5
    cols = np.arange(c0, c1) + 0.5
    if land.side == "top":
        return rows[:, None] < _coast(land, cols)[None, :]
    if land.side == "bottom":
        return (H - rows)[:, None] < _coast(land, cols)[None, :]
    if land.side == "left":
        return cols[None, :] < _coast(land, rows)[:, None]
    return (W - cols)[None, :] < _coast(land, rows)[:, None]


def _land_clearance(cfg: SimConfig, land: _Land, r0: int, r1: int, c0: int, c1: int) -> float:
    """Smallest distance (px, perpendicular to the coast) of box pixels from the land (for a
    georeferenced scene: 0 when land lies within ``LAND_CLEARANCE_PX`` pixels of the box, else
    that margin)."""
    if isinstance(land, _GeoLand):
        m = LAND_CLEARANCE_PX
        return 0.0 if land.coast.land(r0 - m, r1 + m, c0 - m, c1 + m).any() else float(m)
    H, W = cfg.shape
    if land.side in ("top", "bottom"):
        d = _coast(land, np.arange(c0, c1) + 0.5).max()
        p = r0 + 0.5 if land.side == "top" else H - (r1 - 0.5)
    else:
        d = _coast(land, np.arange(r0, r1) + 0.5).max()
        p = c0 + 0.5 if land.side == "left" else W - (c1 - 0.5)
    return float(p - d)
