"""Land: coast geometry, land mask and land backscatter parameters.

Land (``land``)
    A coast on one side (drawn from the seed), land depth 15-30 % of the scene plus a fractal
    displacement: a sum of octaves of 1-D cubic-B-spline noise with amplitude ~ scale^H,
    H = 0.7 (fractional-Brownian-like coastline, Mandelbrot 1967; box dimension ~ 1.3).
    Land mean backscatter is +8..12 dB over the sea (a smooth field 10 +- 1 dB clipped to
    [8, 12]), times a strong texture (Gamma(nu = 1), correlation 6 px), with bright urban
    point scatterers (density 1 / 1500 px, +20..35 dB, dihedral/trihedral in quad-pol).
    Quad-pol land covariance: eps = 0.15, gamma = 0.8, rho = 0.35 (vegetation/urban mix).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sarship.pipeline.simulate.config import SimConfig
from sarship.pipeline.simulate.fields import _S_COAST, _S_LAND, _axis_weights, _rng

#: Quad-pol land covariance parameters.
LAND_EPS, LAND_GAMMA, LAND_RHO = 0.15, 0.8, complex(0.35, 0.0)
URBAN_PX_PER_POINT = 1500.0
LAND_TEXTURE_NU = 1.0
LAND_TEXTURE_CORR_PX = 6.0
LAND_GAIN_CORR_PX = 64.0


@dataclass
class _Land:
    side: str            # "top" | "bottom" | "left" | "right"
    depth: float         # mean depth, px
    octaves: list[tuple[float, float, np.ndarray]]


def _land_model(cfg: SimConfig) -> _Land:
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
        d += amp * (w[0] * nodes[k] + w[1] * nodes[k + 1] + w[2] * nodes[k + 2]
                    + w[3] * nodes[k + 3])
    return d


def _land_mask(cfg: SimConfig, land: _Land, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
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
    """Smallest distance (px, perpendicular to the coast) of box pixels from the land."""
    H, W = cfg.shape
    if land.side in ("top", "bottom"):
        d = _coast(land, np.arange(c0, c1) + 0.5).max()
        p = r0 + 0.5 if land.side == "top" else H - (r1 - 0.5)
    else:
        d = _coast(land, np.arange(r0, r1) + 0.5).max()
        p = c0 + 0.5 if land.side == "left" else W - (c1 - 0.5)
    return float(p - d)
