"""Ships: placement (the ship catalogue), footprints, hull patterns and dominant scatterers.

Ships
    Oriented extended targets: a rectangle of length ~ log-uniform in ``length_m``, width
    length/8..length/6 widened to at least one pixel across, random heading. Rendering: 4x4
    sub-samples per pixel give the area fraction ``cov``; a pixel belongs to the ship where
    cov >= 1/4 (plus the centre pixel). Each ship pixel has a mean RCS
    cov * lognormal (sigma = 0.6 nepers, ~2.6 dB, structure fluctuation) with independent
    speckle (the hull is a distributed target: gamma L-look intensity, circular Gaussian for
    complex data), plus 3-5 dominant point scatterers (bow, stern, superstructure, and a
    few random ones; 4-40 x the hull level) added deterministically (fixed amplitude, random
    phase). The pattern is scaled so that the mean ship power over its pixels is
    ``clutter_mean * 10**(scr_db/10)`` (power = intensity; |hh|^2 for slc; span =
    |HH|^2 + 2|HV|^2 + |VV|^2 for quad-pol, relative to the sea span sigma_hh(1+2 eps+gamma)),
    with per-ship scr_db = cfg.scr_db + U(-2, 2) dB (recorded). The ship is added to the sea
    clutter (coherently for complex data). SCR is relative to the mean sea intensity, not
    to the local texture: a ship's RCS does not depend on the waves around it.
    Quad-pol ship classes (:data:`SHIP_CLASSES`): the hull has its own reflection-symmetric
    covariance, and dominant scatterers are trihedrals [1, 0, 1]/sqrt2 (odd bounce) or
    dihedrals rotated by psi, [cos 2psi, sin 2psi, -cos 2psi]/sqrt2 (even bounce) (Lee &
    Pottier, *Polarimetric Radar Imaging*, 2009, ch. 2/6).
    Ships lie on sea only (>= 8 px from the coast), never overlap (bounding boxes 3 px apart)
    and stay >= 5 px from the scene border. With ``moving`` a ship is imaged at its azimuth-
    displaced position (:mod:`~sarship.pipeline.simulate.motion`); both its imaged and its true
    footprint keep these rules.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.config import BORDER_PX, GAP_PX, SimConfig
from sarship.pipeline.simulate.fields import _S_CATALOGUE, _S_SHIPDOM, _S_SHIPHULL, _rng
from sarship.pipeline.simulate.land import _Land, _land_clearance
from sarship.pipeline.simulate.motion import Motion, displacement_rows

#: Quad-pol ship classes: hull (eps, gamma, rho) and probability that a dominant scatterer
#: is a dihedral (else a trihedral), dihedral rotation range (deg).
SHIP_CLASSES: dict[str, dict[str, Any]] = {
    "odd": {"eps": 0.08, "gamma": 1.0, "rho": 0.6, "p_dihedral": 0.2, "psi_deg": 15.0},
    "even": {"eps": 0.10, "gamma": 0.9, "rho": -0.6, "p_dihedral": 0.8, "psi_deg": 15.0},
    "volume": {"eps": 0.35, "gamma": 1.0, "rho": 0.15, "p_dihedral": 0.5, "psi_deg": 90.0},
    "mixed": {"eps": 0.30, "gamma": 1.0, "rho": -0.2, "p_dihedral": 0.5, "psi_deg": 30.0},
}


LAND_MARGIN_PX = 8  # min distance of ship pixels from the coast
COVERAGE_MIN = 0.25  # min area fraction of a ship pixel
HULL_SIGMA = 0.6  # lognormal sigma of hull RCS structure (nepers)


@dataclass
class _Ship:
    idx: int
    rc: float
    cc: float
    length_m: float
    width_m: float
    bow_deg: float
    scr_db: float
    pol_class: str | None
    r0: int
    c0: int
    mask: np.ndarray
    cov: np.ndarray
    scale: float = 0.0
    # dominant scatterers: rows, cols (global), sub-pixel offsets, powers, phases, pol vectors
    dom: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    drawn_m: tuple[float, float] | None = None  # length and width as drawn (before widening to a pixel)
    # motion (moving / ais): true row at its zero-Doppler time (rc is the imaged one), SOG, COG
    rc_true: float | None = None
    sog_kn: float | None = None
    cog_deg: float | None = None

    @property
    def r1(self) -> int:
        return self.r0 + self.mask.shape[0]

    @property
    def c1(self) -> int:
        return self.c0 + self.mask.shape[1]


def _unit_vectors(bow_deg: float) -> tuple[float, float, float, float]:
    """Along (bow) and across unit vectors in metres, as (row, col) components."""
    th = math.radians(bow_deg)
    return -math.cos(th), math.sin(th), math.sin(th), math.cos(th)


def _ship_dims(length: float, ratio: float, bow_deg: float, dy: float, dx: float) -> tuple[float, float]:
    """Rendered length and width (m): at least one pixel along and across."""
    ur, uc, vr, vc = _unit_vectors(bow_deg)
    lpx = math.hypot(ur / dy, uc / dx)
    wpx = math.hypot(vr / dy, vc / dx)
    return max(length, 1.0 / lpx), max(length / ratio, 1.0 / wpx)


def _footprint(
    rc: float, cc: float, length: float, width: float, bow_deg: float, dy: float, dx: float
) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Ship pixels: (r0, c0, mask, coverage) of the rotated rectangle centred at (rc, cc) px."""
    ur, uc, vr, vc = _unit_vectors(bow_deg)
    hr = (abs(ur) * length / 2 + abs(vr) * width / 2) / dy + 1.0
    hc = (abs(uc) * length / 2 + abs(vc) * width / 2) / dx + 1.0
    r0, r1 = math.floor(rc - hr), math.ceil(rc + hr)
    c0, c1 = math.floor(cc - hc), math.ceil(cc + hc)
    sub = (np.arange(4) + 0.5) / 4.0
    ys = ((np.arange(r0, r1)[:, None] + sub[None, :]).ravel() - rc) * dy
    xs = ((np.arange(c0, c1)[:, None] + sub[None, :]).ravel() - cc) * dx
    a = ys[:, None] * ur + xs[None, :] * uc
    b = ys[:, None] * vr + xs[None, :] * vc
    inside = (np.abs(a) <= length / 2) & (np.abs(b) <= width / 2)
    cov = inside.reshape(r1 - r0, 4, c1 - c0, 4).mean(axis=(1, 3))
    mask = cov >= COVERAGE_MIN
    mask[math.floor(rc) - r0, math.floor(cc) - c0] = True
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    return r0 + int(rows[0]), c0 + int(cols[0]), mask[sl].copy(), cov[sl].astype(np.float32)


_Box = tuple[int, int, int, int]  # r0, r1, c0, c1


class _Boxes:
    """Occupied boxes (grown by GAP_PX), bucketed on a coarse grid for the overlap test."""

    cell = 64

    def __init__(self) -> None:
        self.grid: dict[tuple[int, int], list[_Box]] = {}

    def free(self, r0: int, r1: int, c0: int, c1: int) -> bool:
        b = (r0 - GAP_PX, r1 + GAP_PX, c0 - GAP_PX, c1 + GAP_PX)
        n = self.cell
        return not any(
            o[0] < b[1] and b[0] < o[1] and o[2] < b[3] and b[2] < o[3]
            for p in range(b[0] // n, (b[1] - 1) // n + 1)
            for q in range(b[2] // n, (b[3] - 1) // n + 1)
            for o in self.grid.get((p, q), ())
        )

    def add(self, r0: int, r1: int, c0: int, c1: int) -> None:
        n = self.cell
        for p in range(r0 // n, (r1 - 1) // n + 1):
            for q in range(c0 // n, (c1 - 1) // n + 1):
                self.grid.setdefault((p, q), []).append((r0, r1, c0, c1))


def _place_ships(cfg: SimConfig, land: _Land | None, motion: Motion | None = None) -> list[_Ship]:
    """The ships, placed one after the other on free sea (see the module docstring).

    With ``motion`` the ships that move are imaged ``displacement_rows`` rows from their true
    position (:mod:`~sarship.pipeline.simulate.motion`): the imaged footprint obeys the rules
    above (border, gaps between imaged ships, sea), and so does the true one (border and sea;
    no two true footprints overlap). The random draws are the same with or without ``motion``.
    """
    H, W = cfg.shape
    dy, dx = cfg.pixel_spacing_m
    rng = _rng(cfg.seed, _S_CATALOGUE)
    imaged, true = _Boxes(), _Boxes()
    classes = list(SHIP_CLASSES)
    ships: list[_Ship] = []
    lo, hi = cfg.length_m
    for i in range(cfg.ships):
        length = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else lo
        ratio = float(rng.uniform(6.0, 8.0))
        bow = float(rng.uniform(0.0, 360.0))
        scr = float(cfg.scr_db + rng.uniform(-2.0, 2.0))
        pcls = classes[int(rng.integers(0, len(classes)))]
        drawn = (length, length / ratio)
        length, width = _ship_dims(length, ratio, bow, dy, dx)
        sog = cog = None
        if motion is not None:
            sog, cog = float(motion.sog_kn[i]), motion.cog_deg(i, bow)
        ur, uc, vr, vc = _unit_vectors(bow)
        hr = (abs(ur) * length / 2 + abs(vr) * width / 2) / dy + 1.0
        hc = (abs(uc) * length / 2 + abs(vc) * width / 2) / dx + 1.0
        rlo, rhi = BORDER_PX + hr, H - BORDER_PX - hr
        clo, chi = BORDER_PX + hc, W - BORDER_PX - hc
        placed = None
        if rhi > rlo and chi > clo:
            for _attempt in range(2000):
                rc = float(rng.uniform(rlo, rhi))
                cc = float(rng.uniform(clo, chi))
                shift = float(displacement_rows(cfg, cc, sog, cog)) if sog else 0.0
                r0, c0, mask, cov = _footprint(rc + shift, cc, length, width, bow, dy, dx)
                r1, c1 = r0 + mask.shape[0], c0 + mask.shape[1]
                if r0 < BORDER_PX or c0 < BORDER_PX or r1 > H - BORDER_PX or c1 > W - BORDER_PX:
                    continue
                if not imaged.free(r0, r1, c0, c1):
                    continue
                t0, t1 = math.floor(r0 - shift), math.ceil(r1 - shift)  # the true footprint's rows
                if motion is not None and not true.free(t0, t1, c0, c1):
                    continue
                if land is not None and _land_clearance(cfg, land, r0, r1, c0, c1) < LAND_MARGIN_PX:
                    continue
                if shift and land is not None and _land_clearance(cfg, land, t0, t1, c0, c1) < LAND_MARGIN_PX:
                    continue
                placed = (rc, cc, r0, c0, mask, cov, shift)
                imaged.add(r0, r1, c0, c1)
                true.add(t0, t1, c0, c1)
                break
        if placed is None:
            raise InputError(
                f"simulation ships: could not place ship {i + 1} of {cfg.ships} on free sea "
                f"in the {H}x{W} scene (ships must not overlap each other or land"
                + (
                    "; a moving ship's true and azimuth-displaced positions must both fit"
                    if motion is not None and sog
                    else ""
                )
                + "); use fewer ships, shorter length_m or a larger shape"
            )
        rc, cc, r0, c0, mask, cov, shift = placed
        ships.append(
            _Ship(
                idx=i,
                rc=rc + shift,
                cc=cc,
                length_m=length,
                width_m=width,
                bow_deg=bow,
                scr_db=scr,
                pol_class=pcls if cfg.kind == "quadpol" else None,
                r0=r0,
                c0=c0,
                mask=mask,
                cov=cov,
                drawn_m=drawn,
                rc_true=rc,
                sog_kn=sog,
                cog_deg=cog,
            )
        )
    return ships


def _hull_pattern(cfg: SimConfig, s: _Ship) -> np.ndarray:
    """Relative mean hull RCS per ship pixel (cov x unit-mean lognormal; 0 off the ship)."""
    rng = _rng(cfg.seed, _S_SHIPHULL, s.idx)
    g = rng.standard_normal(s.mask.shape)
    lg = np.exp(HULL_SIGMA * g - 0.5 * HULL_SIGMA**2)
    return np.where(s.mask, s.cov * lg, 0.0)


def _dominants(cfg: SimConfig, s: _Ship) -> dict[str, np.ndarray]:
    """Dominant point scatterers (bow, stern, superstructure, extras) of ship ``s``."""
    dy, dx = cfg.pixel_spacing_m
    rng = _rng(cfg.seed, _S_SHIPDOM, s.idx)
    n_extra = int(rng.integers(0, 3))
    L, Wd = s.length_m, s.width_m
    along = np.concatenate([[0.42 * L, -0.42 * L, rng.uniform(-0.3, 0.15) * L], rng.uniform(-0.4, 0.4, n_extra) * L])
    across = rng.uniform(-0.25, 0.25, along.size) * Wd
    rel = np.concatenate([rng.uniform(4.0, 12.0, 2), rng.uniform(12.0, 40.0, 1), rng.uniform(3.0, 10.0, n_extra)])
    phase = rng.uniform(0.0, 2 * math.pi, along.size)
    ur, uc, vr, vc = _unit_vectors(s.bow_deg)
    rp = s.rc + (along * ur + across * vr) / dy
    cp = s.cc + (along * uc + across * vc) / dx
    rows = np.floor(rp).astype(np.int64)
    cols = np.floor(cp).astype(np.int64)
    dr = rp - rows - 0.5
    dc = cp - cols - 0.5
    mr, mc = np.nonzero(s.mask)
    for j in range(rows.size):  # snap to the nearest ship pixel
        lr, lc = rows[j] - s.r0, cols[j] - s.c0
        if not (0 <= lr < s.mask.shape[0] and 0 <= lc < s.mask.shape[1] and s.mask[lr, lc]):
            k = int(np.argmin((mr - lr) ** 2 + (mc - lc) ** 2))
            rows[j], cols[j] = s.r0 + mr[k], s.c0 + mc[k]
    # polarimetric vectors (unit span) for quad-pol
    info = SHIP_CLASSES[s.pol_class or "mixed"]
    is_di = rng.random(along.size) < info["p_dihedral"]
    psi = np.radians(rng.uniform(-info["psi_deg"], info["psi_deg"], along.size))
    vec = np.where(
        is_di[:, None],
        np.stack([np.cos(2 * psi), np.sin(2 * psi), -np.cos(2 * psi)], axis=1),
        np.array([[1.0, 0.0, 1.0]]),
    ) / math.sqrt(2.0)
    return {"row": rows, "col": cols, "dr": dr, "dc": dc, "rel": rel, "phase": phase, "vec": vec, "dihedral": is_di}


def _ship_geometry(cfg: SimConfig, s: _Ship) -> dict[str, Any]:
    dy, dx = cfg.pixel_spacing_m
    ur, uc, vr, vc = _unit_vectors(s.bow_deg)
    heading = math.degrees(math.atan2(uc / dx, -ur / dy)) % 180.0
    rr, cc = np.nonzero(s.mask)
    return {
        "bbox_px": [s.r0, s.c0, s.r1, s.c1],
        "centroid_px": [float(s.r0 + rr.mean() + 0.5), float(s.c0 + cc.mean() + 0.5)],
        "area_px": int(rr.size),
        "length_px": float(s.length_m * math.hypot(ur / dy, uc / dx)),
        "width_px": float(s.width_m * math.hypot(vr / dy, vc / dx)),
        "heading_deg": float(heading),
        "length_m": float(s.length_m),
        "width_m": float(s.width_m),
    }
