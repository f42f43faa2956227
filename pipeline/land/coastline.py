r"""Coastline land mask (``land_mask=coastline``): the GSHHG shoreline on the scene's pixel grid,
widened by a buffer in metres (docs/algorithms/landmask.md, "Coastline").

Shoreline: GSHHG, the Global Self-consistent, Hierarchical, High-resolution Geography database
(Wessel and Smith 1996, docs/references.md#wessel1996), full resolution, level 1 (the
land/ocean boundary), as shipped and queried by the ``roaring-landmask`` package (optional
extra ``coastline``): ``RoaringLandmask.contains_many(lon, lat)`` is exact point-in-polygon on
the GSHHG polygons behind a raster pre-check (``mask``: a bitmap of 1/240-degree cells, about
463 m of latitude; as the package documents, a point is land only when its cell is set and it
is then inside a polygon, so ``land(p)`` implies ``mask(p)``).

Pixel -> lon/lat
    Pixel ``(r, c)`` is land when its centre ``(r + 1/2, c + 1/2)``, taken to WGS84 lon/lat by
    the scene's geo model (:func:`geo_model`: the one call that maps pixels to the ground, the
    same model that georeferences the detections), is inside the shoreline. Pixels outside the
    scene (the buffer's halo) use the same model, extrapolated, so land just beyond the scene
    edge still widens into it.

Coarse grid and refinement (cost)
    The exact test costs 0.1-2.5 us a pixel in scan order (open sea to a fjord's land; up to
    9 us for scattered points), too much for every pixel of a 4e8-pixel band (bench/RESULTS.md). The scene is covered by a global lattice of pixel centres every
    ``s`` pixels (rows and columns ``k s``); lattice block ``(i, j)`` is the pixels
    ``[i s, (i + 1) s) x [j s, (j + 1) s)``. On the lattice points we evaluate the exact test
    ``L`` and the mask ``M``. With ``N(i, j)`` the lattice points ``i - 2 .. i + 3`` by
    ``j - 2 .. j + 3`` (the block's four corners and two rings)::

        block is sea   if  M = 0 on all of N(i, j)                                   (C1)
        block is land  if  L = 1 on all of N(i, j)                                   (C2)
        otherwise every pixel of the block is tested exactly.                        (C3)

    (C1) is exact when a mask cell is at least ``2 sqrt(2)`` lattice steps wide: a land pixel
    ``p`` of the block lies in a set mask cell; a square of side ``c >= 2 d`` holding ``p``
    holds a square of side ``d = sqrt(2) s dx`` holding ``p`` (``dx`` the largest pixel
    spacing), which holds a lattice point (its inscribed disc exceeds the lattice's covering
    radius ``s dx / sqrt(2)``) within ``2 s dx`` of ``p``, i.e. in ``N(i, j)``. ``s`` is chosen
    so: ``s = floor(c_min / (3 dx))``, ``c_min`` the mask cell's shorter side in metres at the
    scene's largest latitude, at most :data:`MAX_STEP_PX`. (C2) can miss a sea feature that
    passes between lattice points (narrower than ``s dx``, about 150 m at 10 m pixels near the
    equator) inside land: it is kept as land, the safe side, and narrower than GSHHG's own
    accuracy and than the default buffer's width ``2 b``. Every decision depends on global
    lattice points only, so the mask of a region does not depend on how the scene is cut into
    strips or tiles.

Buffer
    ``land_buffer_m = b``: a pixel is masked when its centre is within ``b`` metres of a land
    pixel centre, distances measured on the pixel grid with the scene's pixel spacing ``(az,
    rg)`` (Euclidean distance transform, :func:`scipy.ndimage.distance_transform_edt` with
    ``sampling=(az, rg)``). A region is computed from land ``ceil(b / az)`` rows and
    ``ceil(b / rg)`` columns wider on each side, so every land pixel within ``b`` is seen:
    the buffered mask of a tile equals the whole scene's bit for bit.

Pure functions and one cached handle on the shoreline; no scene I/O.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from sarship.pipeline.errors import InputError

#: What to run when the shoreline package is missing.
INSTALL_HINT = "pip install 'sarship[coastline]'"
#: Default buffer (metres). GSHHG's full-resolution shoreline is the World Vector Shoreline, nominal
#: scale 1:250 000, vectorised from a 3-arc-second (about 90 m) land/water grid: the US National Map
#: Accuracy Standard's 90 % bound at that scale (1/50 inch on the map) is 127 m on the ground, plus
#: one grid cell, about 220 m; rounded up. A ship in a channel wider than 2 x 250 m keeps sea around it.
DEFAULT_BUFFER_M = 250.0
#: Largest buffer accepted (metres).
MAX_BUFFER_M = 5000.0
#: Largest lattice step (pixels): also the step on coarse (e.g. 100 m) pixels.
MAX_STEP_PX = 32
#: Points per call of the exact test in the refinement (bounds the memory of a strip).
BATCH = 1 << 20
#: Largest side of one distance transform's block (each with its own context): bounded memory
#: (float64 distances and int32 feature transform, ~16 bytes a pixel) on full-width strips, and
#: blocks that are all land or all sea, most of a scene, skip the transform.
EDT_SIDE = 1024
#: Batches of at least this many points use the multi-threaded exact test.
PAR_MIN = 1 << 16
#: Metres per degree of latitude (mean; for the mask cell's size and the spacing estimate).
M_PER_DEG = 111_320.0
#: Earth's mean radius (m), for the spacing estimate from the geo model.
EARTH_R = 6_371_008.8


def available() -> bool:
    """Whether the shoreline package (``roaring-landmask``) is installed."""
    try:
        return importlib.util.find_spec("roaring_landmask") is not None
    except (ImportError, ValueError):  # a blocked or half-installed package
        return False


def require() -> None:
    """One-line :class:`InputError` naming the extra when the shoreline package is missing."""
    if not available():
        raise InputError(
            f"parameter 'land_mask': coastline needs the GSHHG shoreline package roaring-landmask: {INSTALL_HINT}"
        )


@functools.lru_cache(maxsize=1)
def shoreline():
    """The GSHHG shoreline handle (``roaring_landmask.RoaringLandmask``), loaded once per process
    (about 4 s and 1.3 GB resident)."""
    require()
    from roaring_landmask import RoaringLandmask

    return RoaringLandmask.new()


def shoreline_version() -> str:
    from importlib.metadata import version

    try:
        return f"roaring-landmask {version('roaring-landmask')}"
    except Exception:  # pragma: no cover - installed without metadata
        return "roaring-landmask"


def geo_model(attrs: dict) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """The scene's pixel -> WGS84 (lon, lat) model from its georeference attributes (``crs`` +
    ``transform`` or ``gcps``), continuous pixel coordinates (pixel ``(r, c)`` covers ``[r,
    r+1) x [c, c+1)``); None when the scene is not georeferenced. The only place this module
    maps pixels to the ground: the same model as the detections' outlines."""
    from sarship.pipeline.targets.ship_features import Georeference

    g = Georeference(attrs)
    return g.lonlat if g.usable else None


def _wrap(lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lon = np.ascontiguousarray(((np.asarray(lon, np.float64) + 180.0) % 360.0) - 180.0)
    lat = np.ascontiguousarray(np.clip(np.asarray(lat, np.float64), -90.0, 90.0))
    return lon, lat


def spacing_from_geo(lonlat, shape: tuple[int, int]) -> tuple[float, float]:
    """Pixel spacing (azimuth = rows, range = columns) in metres at the scene centre, from the geo
    model (great-circle distance to the next row and the next column)."""
    r, c = shape[0] / 2.0, shape[1] / 2.0
    lon, lat = lonlat(np.array([r, r + 1.0, r]), np.array([c, c, c + 1.0]))
    lon, lat = np.radians(np.asarray(lon, float)), np.radians(np.asarray(lat, float))

    def dist(i: int) -> float:
        dlat, dlon = lat[i] - lat[0], lon[i] - lon[0]
        a = math.sin(dlat / 2) ** 2 + math.cos(lat[0]) * math.cos(lat[i]) * math.sin(dlon / 2) ** 2
        return 2.0 * EARTH_R * math.asin(min(1.0, math.sqrt(a)))

    return dist(1), dist(2)


@dataclass
class Coastline:
    """The buffered GSHHG land mask of one scene: ``read(r0, r1, c0, c1)`` (bool, land = True)
    for any region; built by :func:`open_coastline` (which checks everything first)."""

    shape: tuple[int, int]
    lonlat: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    spacing: tuple[float, float]  # (azimuth = rows, range = columns), metres
    spacing_source: str
    buffer_m: float
    step: int
    landmask: Any = None
    stats: dict = field(default_factory=lambda: {"lattice_points": 0, "refined_px": 0, "pixels": 0})

    @property
    def halo(self) -> tuple[int, int]:
        """Rows and columns of land context the buffer needs on each side."""
        if self.buffer_m <= 0:
            return 0, 0
        return math.ceil(self.buffer_m / self.spacing[0]), math.ceil(self.buffer_m / self.spacing[1])

    # the exact test and the mask at pixel centres (continuous coordinates + 1/2)
    def _test(self, rows: np.ndarray, cols: np.ndarray, mask_only: bool = False) -> np.ndarray:
        lm = self.landmask if self.landmask is not None else shoreline()
        lon, lat = self.lonlat(rows + 0.5, cols + 0.5)
        lon, lat = _wrap(lon, lat)
        ok = np.isfinite(lon) & np.isfinite(lat)
        out = np.zeros(lon.shape, bool)
        if not ok.any():
            return out
        # the exact test of a large batch on every core (rayon threads in roaring-landmask; a pure
        # function of the points, so the result is the same)
        fn = lm.mask.contains_many if mask_only else (lm.contains_many_par if lon.size >= PAR_MIN else lm.contains_many)
        if ok.all():
            return np.asarray(fn(lon.ravel(), lat.ravel()), bool).reshape(lon.shape)
        out[ok] = np.asarray(fn(np.ascontiguousarray(lon[ok]), np.ascontiguousarray(lat[ok])), bool)
        return out

    def land(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """GSHHG land (no buffer) of the pixels ``[r0, r1) x [c0, c1)`` (any integers, also
        outside the scene): the lattice decisions (C1)-(C3) of the module doc."""
        s = self.step
        out = np.zeros((r1 - r0, c1 - c0), bool)
        if out.size == 0:
            return out
        bi0, bi1 = r0 // s, (r1 - 1) // s  # lattice blocks touching the region
        bj0, bj1 = c0 // s, (c1 - 1) // s
        li = np.arange(bi0 - 2, bi1 + 4)  # lattice points: the blocks' N(i, j)
        lj = np.arange(bj0 - 2, bj1 + 4)
        R, C = np.meshgrid(li * s, lj * s, indexing="ij")
        M = self._test(R.astype(np.float64), C.astype(np.float64), mask_only=True)
        L = np.zeros_like(M)
        if M.any():
            L[M] = self._test(R[M].astype(np.float64), C[M].astype(np.float64))
        self.stats["lattice_points"] += int(M.size)
        # over the 6 x 6 lattice neighbourhood N(i, j) of each block (lattice index i - 2 .. i + 3)
        anyM = ndimage.maximum_filter(M.astype(np.uint8), size=6, origin=(-1, -1), mode="constant", cval=0) > 0
        allL = ndimage.minimum_filter(L.astype(np.uint8), size=6, origin=(-1, -1), mode="constant", cval=0) > 0
        # block (i, j) sits at lattice index (i - bi0 + 2, j - bj0 + 2); the filters' windows with
        # origin -1 cover index - 2 .. index + 3
        nb, mb = bi1 - bi0 + 1, bj1 - bj0 + 1
        sea = ~anyM[2 : 2 + nb, 2 : 2 + mb]
        land = allL[2 : 2 + nb, 2 : 2 + mb]
        refine = ~sea & ~land
        # fill: land blocks whole, refined blocks pixel by pixel
        rr = np.arange(r0, r1)
        cc = np.arange(c0, c1)
        bi = rr // s - bi0
        bj = cc // s - bj0
        out[:] = land[bi[:, None], bj[None, :]]
        ref = refine[bi[:, None], bj[None, :]]
        self.stats["pixels"] += int(out.size)
        if ref.any():
            pr, pc = np.nonzero(ref)
            self.stats["refined_px"] += int(pr.size)
            for k in range(0, pr.size, BATCH):
                a, b = pr[k : k + BATCH], pc[k : k + BATCH]
                out[a, b] = self._test((a + r0).astype(np.float64), (b + c0).astype(np.float64))
        return out

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The buffered land mask of ``[r0, r1) x [c0, c1)`` (bool; the module doc's buffer). The
        distance transform runs on blocks of at most :data:`EDT_SIDE` a side, each with its own
        ``ceil(b / az)`` rows and ``ceil(b / rg)`` columns of context: the same result."""
        hr, hc = self.halo
        land = self.land(r0 - hr, r1 + hr, c0 - hc, c1 + hc)
        h, w = r1 - r0, c1 - c0
        if h <= EDT_SIDE and w <= EDT_SIDE:
            return buffered(land, self.spacing, self.buffer_m, hr, hc)
        out = np.empty((h, w), bool)
        for i in range(0, h, EDT_SIDE):
            for j in range(0, w, EDT_SIDE):
                i1, j1 = min(i + EDT_SIDE, h), min(j + EDT_SIDE, w)
                out[i:i1, j:j1] = buffered(land[i : i1 + 2 * hr, j : j1 + 2 * hc], self.spacing, self.buffer_m, hr, hc)
        return out


def buffered(land: np.ndarray, spacing: tuple[float, float], buffer_m: float, hr: int, hc: int) -> np.ndarray:
    """The core of ``land`` (``hr`` rows and ``hc`` columns of context each side) widened by
    ``buffer_m``: pixels whose centre is within ``buffer_m`` metres of a land pixel centre, the
    distances on the grid of pixel spacing ``spacing`` (az, rg): the exact Euclidean distance
    transform :func:`scipy.ndimage.distance_transform_edt` with ``sampling=spacing``,
    thresholded at ``buffer_m``."""
    h, w = land.shape[0] - 2 * hr, land.shape[1] - 2 * hc
    core = land[hr : hr + h, hc : hc + w]
    if buffer_m <= 0 or not land.any():
        return core.copy()
    if land.all():
        return np.ones((h, w), bool)
    d = ndimage.distance_transform_edt(~land, sampling=spacing)
    return d[hr : hr + h, hc : hc + w] <= buffer_m


def lattice_step(lonlat, shape: tuple[int, int], spacing: tuple[float, float], cell_deg: tuple[float, float]) -> int:
    """The lattice step ``s`` of the module doc: ``floor(c_min / (3 dx))`` in [1, MAX_STEP_PX],
    ``c_min`` the mask cell's shorter side (metres) at the largest latitude of the scene's
    corners and centre, ``dx`` the largest pixel spacing."""
    H, W = shape
    r = np.array([0.0, 0.0, H, H, H / 2.0])
    c = np.array([0.0, W, 0.0, W, W / 2.0])
    _, lat = lonlat(r, c)
    lat = np.asarray(lat, float)
    lat_max = float(np.nanmax(np.abs(lat))) if np.isfinite(lat).any() else 90.0
    # a scene of many kilometres: allow for its extent beyond the corners (extrapolated halo)
    coslat = max(math.cos(math.radians(min(lat_max + 0.5, 90.0))), 0.0)
    c_min = min(cell_deg[1] * M_PER_DEG, cell_deg[0] * M_PER_DEG * coslat)
    s = int(c_min // (3.0 * max(spacing)))
    return max(1, min(MAX_STEP_PX, s))


NOT_GEOREFERENCED = (
    "parameter 'land_mask': coastline needs a georeferenced scene (crs + transform, or gcps); "
    "this scene has no georeference"
)


def check_scene(attrs: dict | None) -> None:
    """The cheap checks of :func:`open_coastline` (the package is installed; with ``attrs``, the
    scene is georeferenced), for a service to refuse a job at once."""
    require()
    if attrs is not None and geo_model(attrs) is None:
        raise InputError(NOT_GEOREFERENCED)


def open_coastline(
    attrs: dict, shape: tuple[int, int], buffer_m: float = DEFAULT_BUFFER_M, load: bool = True
) -> Coastline:
    """Check that the coastline mask can be made for a scene (the package is installed, the scene
    is georeferenced, the buffer is valid) and return its reader. Every problem is one
    :class:`InputError` line, raised before any work. ``load=False`` defers loading the
    shoreline (4 s) to the first read."""
    require()
    lonlat = geo_model(attrs)
    if lonlat is None:
        raise InputError(NOT_GEOREFERENCED)
    b = float(buffer_m)
    if not (math.isfinite(b) and 0.0 <= b <= MAX_BUFFER_M):
        raise InputError(f"parameter 'land_buffer_m': must be in [0, {MAX_BUFFER_M:g}] metres, got {buffer_m!r}")
    sp = attrs.get("pixel_spacing_m")
    source = "scene"
    try:
        spacing = (float(sp[0]), float(sp[1])) if sp is not None else None
    except (TypeError, ValueError, IndexError):
        spacing = None
    if spacing is None or not all(math.isfinite(x) and x > 0 for x in spacing):
        spacing = spacing_from_geo(lonlat, shape)
        source = "geo model"
        if not all(math.isfinite(x) and x > 0 for x in spacing):
            raise InputError(
                "parameter 'land_mask': coastline needs the scene's pixel spacing and its georeference "
                "gives none usable"
            )
    lm = shoreline() if load else None
    cell = (float(lm.dx), float(lm.dy)) if lm is not None else (1.0 / 240.0, 1.0 / 240.0)
    step = lattice_step(lonlat, shape, spacing, cell)
    return Coastline(
        shape=tuple(int(x) for x in shape),
        lonlat=lonlat,
        spacing=spacing,
        spacing_source=source,
        buffer_m=b,
        step=step,
        landmask=lm,
    )


def brute_force(cl: Coastline, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """The exact test on every pixel of a region (the reference the lattice must reproduce)."""
    R, C = np.meshgrid(np.arange(r0, r1, dtype=np.float64), np.arange(c0, c1, dtype=np.float64), indexing="ij")
    return cl._test(R, C)
