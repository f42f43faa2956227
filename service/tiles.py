"""XYZ quicklook tiles over a scene's pixel grid (the contract the web page is built against).

Tile scheme (the "XYZ" / slippy-map convention of OpenStreetMap and Leaflet: zoom z, column x,
row y, origin at the top-left, 256-pixel tiles, each zoom doubling the resolution; TileJSON 3.0.0,
https://github.com/mapbox/tilejson-spec/tree/master/3.0.0), applied to the scene's own pixel
grid instead of Web Mercator:

- ``Z = max(0, ceil(log2(max(H, W) / 256)))`` is the deepest zoom; at zoom Z one tile pixel is one
  scene pixel; at zoom z a tile covers ``256 * 2^(Z - z)`` scene pixels a side;
- tile (z, x, y) covers scene rows ``y*s .. (y+1)*s`` and columns ``x*s .. (x+1)*s``
  (``s = 256 * 2^(Z - z)``); it exists when ``0 <= z <= Z`` and its top-left is in the scene;
- a tile is a 256 x 256 RGBA PNG: the scene grey (:mod:`sarship.service.render`'s one stretch per
  job), detected pixels red; outside the scene transparent.

Reads are bounded by the tile: the grey of tile pixel (i, j) is the scene pixel
``(y*s + i*f, x*s + j*f)`` with ``f = 2^(Z - z)``, read with stride f, from the job's small
decimated grey base when f is a multiple of its step (the coarse zooms, where a strided read
would decompress the whole scene) and else straight from the scene's Zarr window (fine zooms:
at most ``256 f`` pixels a side). The mask is max-pooled (a tile pixel is red when any mask
pixel under it is set, so ships stay visible at every zoom): it is exactly one tile of the
job's COG (:mod:`sarship.service.cog`), whose overview k is the mask max-pooled by 2^k on the same
256-pixel grid, so the deepest zoom reads one full-resolution tile and zoom 0 one overview tile.

A georeferenced scene's TileJSON also carries ``lonlat`` (:func:`lonlat_grid`): the WGS84
position of a 17 x 17 grid of pixel positions, from which a map in lon/lat places each tile
(the web page draws each tile warped onto its four corners' map position).

Rendered PNGs are kept in an in-memory LRU (:data:`CACHE_TILES` tiles, a few tens of MiB):
rendering is cheap once the job's pyramid exists (a tile decode, a PNG encode), browsers keep
tiles under ``Cache-Control: immutable``, and an on-disk cache would grow job folders with
every tile ever viewed.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sarship.service.cog import TILE, cog_tile, mask_cog
from sarship.service.render import grey, grey_base, job_stretch, land_array, source_of, strided_reader, tint_land

#: ``land``: the job's land mask (``land.zarr``, jobs run with ``land_mask``), tinted blue over the
#: scene as in the preview; asked for explicitly (``?layers=scene,mask,land``).
LAYERS = ("scene", "mask", "land")
MASK_RGBA = (255, 40, 40, 255)
CACHE_TILES = 1024


def max_zoom(shape: tuple[int, int], tile: int = TILE) -> int:
    """``max(0, ceil(log2(max(H, W) / tile)))``, in integers."""
    z = 0
    while tile << z < max(shape):
        z += 1
    return z


@dataclass(frozen=True)
class Window:
    """The scene rectangle ``r0:r1, c0:c1`` of a tile, read with stride ``f``; the tile's pixels
    ``[:rows, :cols]`` are inside the scene."""

    r0: int
    r1: int
    c0: int
    c1: int
    f: int
    level: int  # COG level = Z - z

    @property
    def rows(self) -> int:
        return -(-(self.r1 - self.r0) // self.f)

    @property
    def cols(self) -> int:
        return -(-(self.c1 - self.c0) // self.f)


def tile_window(shape: tuple[int, int], z: int, x: int, y: int, tile: int = TILE) -> Window | None:
    """The scene window of XYZ tile (z, x, y), or None when there is no such tile."""
    H, W = shape
    Z = max_zoom(shape, tile)
    if not 0 <= z <= Z or x < 0 or y < 0:
        return None
    f = 1 << (Z - z)
    s = tile * f
    r0, c0 = y * s, x * s
    if r0 >= H or c0 >= W:
        return None
    return Window(r0, min(r0 + s, H), c0, min(c0 + s, W), f, Z - z)


def tile_counts(shape: tuple[int, int], z: int, tile: int = TILE) -> tuple[int, int]:
    """Number of tile columns and rows at zoom z."""
    s = tile << (max_zoom(shape, tile) - z)
    return -(-shape[1] // s), -(-shape[0] // s)


def parse_layers(text: str | None) -> tuple[str, ...]:
    """``"scene,mask"`` -> ``("scene", "mask")`` (canonical order); ValueError naming a bad one."""
    names = [t.strip() for t in (text if text is not None else "scene,mask").split(",")]
    if not names or any(not n for n in names):
        raise ValueError(f"'layers' must be a comma list of {', '.join(LAYERS)}, got {text!r}")
    bad = [n for n in names if n not in LAYERS]
    if bad:
        raise ValueError(f"'layers': unknown layer {bad[0]!r} (known: {', '.join(LAYERS)})")
    return tuple(n for n in LAYERS if n in names)


def scene_grey(job_dir: Path, w: Window, base_max: int | None = None) -> np.ndarray:
    """The grey (job stretch) of a tile window: ``(w.rows, w.cols)`` uint8."""
    meta = job_stretch(job_dir)
    step, base = grey_base(job_dir) if base_max is None else grey_base(job_dir, base_max)
    if w.f % step == 0:  # coarse zoom: sampled from the decimated base (same pixels as a strided read)
        k = w.f // step
        out = base[w.r0 // step : -(-w.r1 // step) : k, w.c0 // step : -(-w.c1 // step) : k]
    else:
        src = source_of(meta)
        out = grey(src, strided_reader(src)(w.r0, w.r1, w.c0, w.c1, w.f), meta)
    assert out.shape == (w.rows, w.cols), (out.shape, w)
    return out


def mask_tile(job_dir: Path, w: Window, x: int, y: int) -> np.ndarray:
    """The max-pooled mask of a tile window: ``(w.rows, w.cols)`` bool (one COG tile)."""
    return cog_tile(mask_cog(job_dir), w.level, y, x)[: w.rows, : w.cols] > 0


def render_tile(
    job_dir: Path,
    shape: tuple[int, int],
    z: int,
    x: int,
    y: int,
    layers: tuple[str, ...],
    base_max: int | None = None,
) -> bytes | None:
    """PNG bytes of XYZ tile (z, x, y), or None when there is no such tile."""
    from PIL import Image

    w = tile_window(shape, z, x, y)
    if w is None:
        return None
    rgba = np.zeros((TILE, TILE, 4), np.uint8)
    if "scene" in layers:
        g = scene_grey(job_dir, w, base_max)
        rgba[: w.rows, : w.cols, 0] = g
        rgba[: w.rows, : w.cols, 1] = g
        rgba[: w.rows, : w.cols, 2] = g
        rgba[: w.rows, : w.cols, 3] = 255
    if "land" in layers:
        land = land_array(job_dir)
        if land is not None:
            lm = np.asarray(land[w.r0 : w.r1 : w.f, w.c0 : w.c1 : w.f]) > 0
            view = rgba[: w.rows, : w.cols]
            view[..., :3] = tint_land(view[..., :3], lm)
            view[..., 3][lm] = 255
    if "mask" in layers:
        m = mask_tile(job_dir, w, x, y)
        rgba[: w.rows, : w.cols][m] = MASK_RGBA
    buf = io.BytesIO()
    # zlib level 1: on speckled sea 4 ms and ~100 KB a tile, where level 6 took 20 ms and gave
    # ~190 KB (PIL picks its filters by level; measured on a 4096^2 simulated scene)
    Image.fromarray(rgba, "RGBA").save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


_lru_lock = threading.Lock()
_lru: OrderedDict[tuple[str, str, int, int, int, tuple[str, ...]], bytes] = OrderedDict()


def cached_tile(
    job_dir: Path, version: str, shape: tuple[int, int], z: int, x: int, y: int, layers: tuple[str, ...]
) -> bytes | None:
    """:func:`render_tile` through the in-memory LRU (key: job folder, job version, tile, layers)."""
    key = (str(job_dir), version, z, x, y, layers)
    with _lru_lock:
        if key in _lru:
            _lru.move_to_end(key)
            return _lru[key]
    png = render_tile(job_dir, shape, z, x, y, layers)
    if png is not None:
        with _lru_lock:
            _lru[key] = png
            while len(_lru) > CACHE_TILES:
                _lru.popitem(last=False)
    return png


#: Cells a side of the lon/lat grid of a georeferenced scene's TileJSON (:func:`lonlat_grid`).
GRID_CELLS = 16


def lonlat_grid(attrs: dict[str, Any], shape: tuple[int, int], n: int = GRID_CELLS) -> dict[str, Any] | None:
    """The WGS84 position of a regular grid of scene pixel coordinates, for a map drawing the
    scene in lon/lat (the web page warps each tile between the grid's nodes, bilinearly).

    Parameters
    ----------
    attrs : dict
        The scene's attributes: ``crs`` + ``transform`` or ``gcps``
        (:class:`sarship.pipeline.targets.ship_features.Georeference`).
    shape : tuple of int
        The scene's (rows, columns).
    n : int
        Cells a side: nodes at rows ``0, H/n, ..., H`` and columns ``0, W/n, ..., W``
        (continuous pixel coordinates: pixel (r, c) covers [r, r+1) x [c, c+1)).

    Returns
    -------
    dict or None
        ``{"rows": [n+1], "cols": [n+1], "lon": [[n+1] * (n+1)], "lat": [...], "method": str}``
        (``lon[i][j]`` at ``rows[i]``, ``cols[j]``; longitudes unwrapped around ``lon[0][0]``, so
        continuous across the antimeridian, possibly past +-180); None when the scene is not georeferenced or
        its georeference gives no finite WGS84 position.
    """
    from sarship.pipeline.targets.ship_features import Georeference

    geo = {k: attrs[k] for k in ("crs", "transform", "gcps") if k in attrs}
    if not geo:
        return None
    try:
        g = Georeference(geo)
        if not g.usable:
            return None
        rows = np.linspace(0.0, float(shape[0]), n + 1)
        cols = np.linspace(0.0, float(shape[1]), n + 1)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        lon, lat = (np.asarray(v, float).reshape(rr.shape) for v in g.lonlat(rr.ravel(), cc.ravel()))
    except Exception:  # a georeference that cannot be evaluated: the page keeps pixel coordinates
        return None
    # continuous across the antimeridian: unwrapped around the first node (values may pass +-180)
    lon = lon[0, 0] + (lon - lon[0, 0] + 180.0) % 360.0 - 180.0
    if not (
        np.isfinite(lon).all() and np.isfinite(lat).all() and (np.abs(lon) <= 360).all() and (np.abs(lat) <= 90).all()
    ):
        return None
    # 1e-7 degree: about a centimetre
    return {
        "rows": rows.tolist(),
        "cols": cols.tolist(),
        "lon": np.round(lon, 7).tolist(),
        "lat": np.round(lat, 7).tolist(),
        "method": g.method,
    }


def tilejson(base: str, job_id: str, shape: tuple[int, int], attrs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The TileJSON 3.0.0 document of a job's tiles (plus the scene's ``width`` and ``height``,
    and ``lonlat``, :func:`lonlat_grid`, when the scene's attributes ``attrs`` georeference it)."""
    H, W = shape
    doc: dict[str, Any] = {
        "tilejson": "3.0.0",
        "tiles": [f"{base}/jobs/{job_id}/tiles/{{z}}/{{x}}/{{y}}.png"],
        "minzoom": 0,
        "maxzoom": max_zoom(shape),
        "tileSize": TILE,
        "width": int(W),
        "height": int(H),
    }
    grid = lonlat_grid(attrs or {}, shape)
    if grid is not None:
        doc["lonlat"] = grid
    return doc
