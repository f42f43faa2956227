"""Land masks a user supplies (``land_mask=FILE``): a raster or a vector file, checked and
rasterised onto the scene's pixel grid (docs/algorithms/landmask.md, "FILE").

Raster: a GeoTIFF/TIFF, PNG/JPEG, ``.npy`` (any bands) or a Zarr array (or a Zarr group with
one 2-D array, e.g. an earlier run's ``land.zarr``) of exactly the scene's shape; a pixel is
land where any band is finite and non-zero.

Vector: GeoJSON (a FeatureCollection, Feature or geometry) of Polygon / MultiPolygon
geometries. Coordinates are WGS84 lon/lat (RFC 7946), converted to scene pixels with the
scene's georeference (the inverse of :class:`sarship.pipeline.targets.ship_features.Georeference`:
the affine ``transform`` in the scene ``crs``; for ``gcps`` that form a geolocation grid the
inverse of its bilinear interpolation (:func:`sarship.pipeline.targets.georef.pixel_of`, Newton's method),
so a land polygon lands where the detections are placed; for scattered ``gcps`` a least-squares
polynomial fitted from lon/lat to pixels, affine under 6 points and quadratic from 6, as GDAL's
GCP transformer does, which also starts the grid's inversion); or scene pixel coordinates ``[x = column, y = row]`` (pixel ``(r, c)``
covers ``[c, c+1) x [r, r+1)``) when the top-level member ``"pixel_coordinates": true`` is
set. A pixel is land where its centre ``(c + 1/2, r + 1/2)`` is inside a polygon (even-odd
rule over the polygon's rings, so holes are sea); polygons are united.

Every problem is one :class:`~sarship.pipeline.errors.InputError` line naming the file,
raised by :func:`open_land_file` before any tile runs.

Only a regular file (or a folder: a Zarr store) is opened: a FIFO, a device or a socket is
refused from its ``stat`` (a FIFO would block the reader forever), and the file is opened
``O_NONBLOCK`` and checked again on the open descriptor, so a FIFO swapped in meanwhile cannot
hang it either. A GeoJSON file is at most ``SARSHIP_LAND_MAX_MB`` MiB
(:data:`DEFAULT_LAND_MAX_MB` by default; checked from its size before it is read) and nested at
most :data:`MAX_GEOJSON_DEPTH` deep (counted by a linear scan before it is parsed, so a file
nested 200 000 deep is one line, not a ``RecursionError``).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline import settings
from sarship.pipeline.errors import InputError

#: Largest GeoJSON land-mask file read, MiB, unless ``SARSHIP_LAND_MAX_MB`` says otherwise.
DEFAULT_LAND_MAX_MB = settings.VARIABLES["land_max_mb"].default
#: Deepest nesting of ``[``/``{`` in a GeoJSON land mask (a FeatureCollection of MultiPolygons
#: is 7 deep; GeometryCollections nest further).
MAX_GEOJSON_DEPTH = 64
#: Suffixes of files read as GeoJSON (besides content starting with ``{``).
GEOJSON_SUFFIXES = (".geojson", ".json")


def land_max_bytes() -> int:
    """The largest GeoJSON land-mask file, bytes: ``SARSHIP_LAND_MAX_MB`` MiB (a positive
    number), else :data:`DEFAULT_LAND_MAX_MB`. InputError for a bad value."""
    return int(settings.read("land_max_mb") * 2**20)


@dataclass
class LandFile:
    """A checked land-mask file: ``read(r0, r1, c0, c1) -> bool`` on the scene grid."""

    path: str
    kind: str  # "raster" | "vector"
    format: str
    read: Callable[[int, int, int, int], np.ndarray]
    info: dict[str, Any] = field(default_factory=dict)


def _bad(path: Any, what: str) -> InputError:
    return InputError(f"parameter 'land_mask': '{path}' {what}")


def check_land_path(path: str | os.PathLike, max_bytes: int | None = None) -> os.stat_result:
    """The cheap checks of a land-mask FILE, from its ``stat`` alone (nothing is opened): it
    exists, is a regular file or a folder (a Zarr store), and a GeoJSON file (by its suffix)
    is at most ``max_bytes`` (default :func:`land_max_bytes`). Its ``stat``; InputError
    otherwise."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise _bad(path, "does not exist (land_mask is none, texture or a raster/GeoJSON file)") from None
    except OSError as exc:
        raise _bad(path, f"cannot be read ({exc.strerror})") from None
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise _bad(
            path, "is not a regular file (a FIFO, device or socket): give a raster or GeoJSON file, or a Zarr folder"
        )
    if stat.S_ISREG(st.st_mode) and Path(path).suffix.lower() in GEOJSON_SUFFIXES:
        _check_size(path, st.st_size, max_bytes)
    return st


def _check_size(path: Any, size: int, max_bytes: int | None) -> None:
    limit = land_max_bytes() if max_bytes is None else int(max_bytes)
    if size > limit:
        raise _bad(
            path,
            f"is {size / 2**20:.1f} MiB, larger than the {limit / 2**20:g} MiB a GeoJSON land mask "
            "may be (SARSHIP_LAND_MAX_MB)",
        )


def open_land_file(path: str, shape: tuple[int, int], attrs: dict, max_bytes: int | None = None) -> LandFile:
    """Check the land-mask file ``path`` against a scene of ``shape`` with georeference
    ``attrs`` (``crs``, ``transform``, ``gcps``) and return its reader. ``max_bytes``: the
    largest GeoJSON file (default :func:`land_max_bytes`)."""
    p = Path(path)
    st = check_land_path(p, max_bytes)
    if stat.S_ISDIR(st.st_mode):
        return _zarr_mask(p, shape)
    try:  # O_NONBLOCK: a FIFO put in its place since the stat cannot block the open or the read
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise _bad(path, f"cannot be read ({exc.strerror})") from None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise _bad(
                path,
                "is not a regular file (a FIFO, device or socket): give a raster or GeoJSON file, or a Zarr folder",
            )
        try:
            head = fh.read(64)
        except OSError as exc:
            raise _bad(path, f"cannot be read ({exc.strerror})") from None
        if not head:
            raise _bad(path, "is empty")
        if head.lstrip()[:1] in (b"{",) or p.suffix.lower() in GEOJSON_SUFFIXES:
            _check_size(path, st.st_size, max_bytes)
            fh.seek(0)
            try:
                raw = fh.read(st.st_size + 1)
            except (OSError, MemoryError) as exc:
                raise _bad(path, f"cannot be read ({getattr(exc, 'strerror', None) or type(exc).__name__})") from None
            return _vector_mask(p, raw, shape, attrs, max_bytes)
    return _raster_mask(p, shape)


def json_depth(raw: bytes, chunk: int = 1 << 22) -> int:
    """The deepest nesting of ``[``/``{`` in JSON text ``raw`` (brackets inside strings do not
    count), in linear time without parsing and without recursion, ``chunk`` bytes at a time
    (the memory it needs stays a few times ``chunk``, whatever the size of ``raw``)."""
    step = np.zeros(256, np.int64)
    step[[ord("["), ord("{")]], step[[ord("]"), ord("}")]] = 1, -1
    deepest, depth, inside, carry = 0, 0, False, 0  # carry: backslashes ending the previous chunk
    for k in range(0, len(raw), chunk):
        b = np.frombuffer(raw, np.uint8, count=min(chunk, len(raw) - k), offset=k)
        pos = np.arange(b.size)
        # last_other[i]: the last position <= i that is not a backslash (-1: none in this chunk)
        last_other = np.maximum.accumulate(np.where(b == ord("\\"), -1, pos))
        run = np.empty(b.size, np.int64)  # backslashes right before each character
        run[0] = carry
        run[1:] = pos[:-1] - last_other[:-1] + np.where(last_other[:-1] < 0, carry, 0)
        quote = (b == ord('"')) & (run % 2 == 0)  # an unescaped quote opens or closes a string
        ins = (np.cumsum(quote) % 2 == 1) != inside  # inside a string after each character
        d = depth + np.cumsum(np.where(ins, 0, step[b]))
        deepest, depth, inside = max(deepest, int(d.max())), int(d[-1]), bool(ins[-1])
        carry = b.size - 1 - int(last_other[-1]) + (carry if last_other[-1] < 0 else 0)
    return deepest


def _zarr_mask(p: Path, shape: tuple[int, int]) -> LandFile:
    import zarr

    try:
        node = zarr.open(str(p), mode="r")
    except Exception as exc:
        raise _bad(p, f"is a folder but not a Zarr array or group ({type(exc).__name__})") from None
    if isinstance(node, zarr.Group):
        arrays = [a for _, a in node.arrays() if a.ndim == 2]
        named = [a for a in arrays if a.name.rsplit("/", 1)[-1] in ("land", "mask")]
        if len(named) == 1:
            arr = named[0]
        elif len(arrays) == 1:
            arr = arrays[0]
        else:
            raise _bad(p, f"is a Zarr group with {len(arrays)} 2-D arrays: give one (or an array named 'land')")
    else:
        arr = node
    if tuple(arr.shape[:2]) != tuple(shape) or arr.ndim not in (2, 3):
        raise _bad(p, f"has shape {tuple(arr.shape)}, the scene is {shape[0]}x{shape[1]}")

    def read(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        return _nonzero(np.asarray(arr[r0:r1, c0:c1]))

    return LandFile(str(p), "raster", "zarr", read)


def _nonzero(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if np.iscomplexobj(a):
        a = np.abs(a)
    m = (a != 0) & np.isfinite(a) if a.dtype.kind == "f" else a != 0
    return m.any(axis=tuple(range(2, m.ndim))) if m.ndim > 2 else m


def _raster_mask(p: Path, shape: tuple[int, int]) -> LandFile:
    from sarship.pipeline.readers.entry import _open_source

    try:
        src = _open_source(p)
    except InputError as exc:
        raise _bad(p, f"is not a raster or GeoJSON land mask ({exc})") from None
    if tuple(src.shape) != tuple(shape):
        H, W = src.shape
        src.close()
        raise _bad(
            p, f"is {H}x{W} pixels, the scene is {shape[0]}x{shape[1]} (a raster land mask must have the scene's shape)"
        )

    def read(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        return _nonzero(src.read(r0, r1, c0, c1))

    return LandFile(str(p), "raster", src.fmt, read)


# --------------------------------------------------------------------------------------
# vector
# --------------------------------------------------------------------------------------


def _polygons(obj: Any, p: Path) -> list[list[np.ndarray]]:
    """Every polygon of a GeoJSON object as a list of rings ((n, 2) float arrays of x, y)."""
    out: list[list[np.ndarray]] = []

    def rings(coords) -> list[np.ndarray]:
        rs = []
        for ring in coords:
            a = np.asarray(ring, dtype=np.float64)
            if a.ndim != 2 or a.shape[0] < 3 or a.shape[1] < 2 or not np.isfinite(a[:, :2]).all():
                raise _bad(p, "has a polygon ring that is not a list of at least 3 finite [x, y] positions")
            rs.append(a[:, :2])
        return rs

    def geom(g):
        if g is None:
            return
        if not isinstance(g, dict) or "type" not in g:
            raise _bad(p, "is not GeoJSON (a geometry without a 'type')")
        t = g["type"]
        try:
            if t == "Polygon":
                out.append(rings(g["coordinates"]))
            elif t == "MultiPolygon":
                for poly in g["coordinates"]:
                    out.append(rings(poly))
            elif t == "GeometryCollection":
                for sub in g["geometries"]:
                    geom(sub)
            else:
                raise _bad(p, f"holds a {t} geometry: a land mask needs Polygon or MultiPolygon geometries")
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise _bad(p, f"has a malformed {t} geometry ({type(exc).__name__})") from None

    if not isinstance(obj, dict):
        raise _bad(p, "is not a GeoJSON object")
    t = obj.get("type")
    if t == "FeatureCollection":
        feats = obj.get("features")
        if not isinstance(feats, list):
            raise _bad(p, "is a FeatureCollection without a 'features' list")
        for f in feats:
            if not isinstance(f, dict):
                raise _bad(p, "has a feature that is not an object")
            geom(f.get("geometry"))
    elif t == "Feature":
        geom(obj.get("geometry"))
    else:
        geom(obj)
    if not out:
        raise _bad(p, "holds no polygons")
    return out


def lonlat_to_pixel(lon: np.ndarray, lat: np.ndarray, attrs: dict) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 lon/lat -> continuous scene (row, col), the inverse of the scene's georeference
    (module doc). Raises ValueError when the scene has none usable."""
    transform, gcps = attrs.get("transform"), attrs.get("gcps")
    crs = attrs.get("crs") or ("EPSG:4326" if gcps else None)
    if crs is None or (transform is None and not gcps):
        raise ValueError("the scene is not georeferenced (no crs + transform or gcps)")
    x, y = np.asarray(lon, float), np.asarray(lat, float)
    if str(crs).upper() not in ("EPSG:4326", "OGC:CRS84", "WGS84", "CRS84"):
        from pyproj import Transformer

        x, y = Transformer.from_crs("EPSG:4326", str(crs), always_xy=True).transform(x, y)
        x, y = np.asarray(x, float), np.asarray(y, float)
    if transform is not None:
        c, a, b, f, d, e = (float(v) for v in transform)
        det = a * e - b * d
        if det == 0:
            raise ValueError("the scene's transform is singular")
        u, v = x - c, y - f
        return (a * v - d * u) / det, (e * u - b * v) / det
    gx = np.array([g["x"] for g in gcps], float)
    gy = np.array([g["y"] for g in gcps], float)
    rc = np.array([[g["row"], g["col"]] for g in gcps], float)
    quad = len(gcps) >= 6

    def design(xx, yy):
        cols = [np.ones_like(xx), xx, yy]
        if quad:
            cols += [xx * xx, xx * yy, yy * yy]
        return np.stack(cols, axis=-1)

    coef, *_ = np.linalg.lstsq(design(gx, gy), rc, rcond=None)
    out = design(x, y) @ coef
    from sarship.pipeline.targets.georef import GridGeoreference, from_gcps, pixel_of

    geo = from_gcps(gcps, geographic=str(crs).upper() in ("EPSG:4326", "OGC:CRS84", "WGS84", "CRS84"))
    if isinstance(geo, GridGeoreference):  # the inverse of the grid the detections are placed with
        return pixel_of(geo, x, y, out[..., 0], out[..., 1])
    return out[..., 0], out[..., 1]


def _vector_mask(p: Path, raw: bytes, shape: tuple[int, int], attrs: dict, max_bytes: int | None = None) -> LandFile:
    _check_size(p, len(raw), max_bytes)  # (the file may have grown since its stat)
    if json_depth(raw) > MAX_GEOJSON_DEPTH:
        raise _bad(p, f"is nested deeper than {MAX_GEOJSON_DEPTH} levels (not a GeoJSON land mask)")
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _bad(p, f"is not valid JSON ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
    except RecursionError:  # (the depth scan refuses such files first)
        raise _bad(p, f"is nested deeper than {MAX_GEOJSON_DEPTH} levels (not a GeoJSON land mask)") from None
    polys = _polygons(obj, p)
    pixel = obj.get("pixel_coordinates") is True if isinstance(obj, dict) else False
    if not pixel:
        try:
            conv = []
            for poly in polys:
                rs = []
                for ring in poly:
                    r, c = lonlat_to_pixel(ring[:, 0], ring[:, 1], attrs)
                    if not (np.isfinite(r).all() and np.isfinite(c).all()):
                        raise ValueError("a position falls outside the scene's projection")
                    rs.append(np.stack([c, r], -1))
                conv.append(rs)
        except ValueError as exc:
            raise _bad(
                p,
                f"has lon/lat coordinates but {exc}; for scene pixel coordinates set the "
                'top-level member "pixel_coordinates": true',
            ) from None
        polys = conv
    edges = _edges(polys)

    def read(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        return rasterize(edges, r0, r1, c0, c1)

    H, W = shape
    xs = np.concatenate([ring[:, 0] for poly in polys for ring in poly])
    ys = np.concatenate([ring[:, 1] for poly in polys for ring in poly])
    inside = bool(((xs >= 0) & (xs <= W) & (ys >= 0) & (ys <= H)).any()) or bool(
        xs.min() < W and xs.max() > 0 and ys.min() < H and ys.max() > 0
    )
    info = {"polygons": len(polys), "coordinates": "pixel" if pixel else "lonlat", "overlaps_scene": inside}
    return LandFile(str(p), "vector", "geojson", read, info)


def _edges(polys: list[list[np.ndarray]]) -> np.ndarray:
    """All ring edges as rows ``(x1, y1, x2, y2)`` (rings closed), horizontal edges dropped."""
    parts = []
    for poly in polys:
        for ring in poly:
            a = ring if np.array_equal(ring[0], ring[-1]) else np.vstack([ring, ring[:1]])
            e = np.concatenate([a[:-1], a[1:]], axis=1)
            parts.append(e[e[:, 1] != e[:, 3]])
    return np.concatenate(parts) if parts else np.zeros((0, 4))


def rasterize(edges: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """Boolean ``(r1 - r0, c1 - c0)``: pixels whose centre is inside the polygons (even-odd
    rule; an edge counts for a scanline ``y`` when ``min(y1, y2) <= y < max(y1, y2)``)."""
    out = np.zeros((r1 - r0, c1 - c0), bool)
    if edges.size == 0:
        return out
    x1, y1, x2, y2 = edges.T
    lo, hi = np.minimum(y1, y2), np.maximum(y1, y2)
    xc = np.arange(c0, c1) + 0.5
    for i, r in enumerate(range(r0, r1)):
        y = r + 0.5
        sel = (lo <= y) & (y < hi)
        if not sel.any():
            continue
        xs = np.sort(x1[sel] + (y - y1[sel]) * (x2[sel] - x1[sel]) / (y2[sel] - y1[sel]))
        out[i] = (np.searchsorted(xs, xc, side="right") % 2) == 1
    return out
