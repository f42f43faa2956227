"""Detections as GeoPackage or KML, the files a GIS opens (``sarship export``, ``sarship detect
--formats``).

``detections.geojson`` (docs/interfaces/files.md) is converted, not re-derived: one feature per
ship, its WGS84 outline polygon, and its properties as columns. Lists become scalar columns a
GIS can style and filter on (``centroid_lonlat`` -> ``centroid_lon``, ``centroid_lat``;
``centroid_px`` -> ``centroid_row``, ``centroid_col``; ``bbox_px`` -> ``bbox_row0``, ``bbox_col0``,
``bbox_row1``, ``bbox_col1``; ``peak_px`` -> ``peak_row``, ``peak_col``); other nested values are
kept as JSON text. Each feature gets ``name`` = ``ship <n>`` (n from 1, the GeoJSON order), the
label a KML viewer shows. The collection's ``detector`` and ``scene`` members go into the
file's metadata (GeoPackage ``gpkg_metadata``; KML document description).

Formats: OGC GeoPackage 1.3 and OGC KML 2.2 (docs/references.md [geopackage], [kml]).
Writing is GDAL's, through ``pyogrio`` (optional extra ``gis``: its wheels bundle GDAL with the
GPKG, KML and LIBKML drivers): a GeoPackage is a SQLite database with an R-tree index and
spatial reference tables, and its validity is better left to GDAL than to a hand-written
writer; KML goes through LIBKML (``ExtendedData`` with a typed ``Schema``) when the GDAL build
has it, else GDAL's plain KML driver. The file is written under a temporary name beside the
target and renamed into place; an existing target is refused unless ``overwrite``.
"""

from __future__ import annotations

import json
import os
import secrets
import struct
import types
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

#: output suffix -> format name
FORMATS = {".gpkg": "gpkg", ".kml": "kml"}
#: list properties split into scalar columns
SPLIT = {
    "centroid_lonlat": ("centroid_lon", "centroid_lat"),
    "centroid_px": ("centroid_row", "centroid_col"),
    "bbox_px": ("bbox_row0", "bbox_col0", "bbox_row1", "bbox_col1"),
    "peak_px": ("peak_row", "peak_col"),
}
EXTRA_HINT = "pip install 'sarship[gis]'"


def require_pyogrio() -> types.ModuleType:
    """The ``pyogrio`` module, or InputError naming the extra to install."""
    try:
        import pyogrio
    except ImportError:
        raise InputError(f"GeoPackage/KML output needs pyogrio (GDAL), not installed: {EXTRA_HINT}") from None
    return pyogrio


def format_of(path: str | os.PathLike) -> str:
    """``"gpkg"`` or ``"kml"`` from the file's suffix; InputError otherwise."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InputError(
            f"'{path}': the output must end in .gpkg (GeoPackage) or .kml (KML), not '{suffix or '(no suffix)'}'"
        )
    return FORMATS[suffix]


def polygon_wkb(ring: list[list[float]]) -> bytes:
    """ISO WKB (little endian) of a one-ring polygon [[lon, lat], ...] (closed)."""
    pts = np.asarray(ring, dtype="<f8").reshape(-1, 2)
    return struct.pack("<BIII", 1, 3, 1, len(pts)) + pts.tobytes()


def table(collection: dict, source: str = "detections") -> tuple[list[bytes], list[str], list[np.ndarray], list]:
    """``(wkb, field names, field arrays, field masks)`` of a detections FeatureCollection.

    InputError when a feature has no WGS84 outline (the scene was not georeferenced) or a
    geometry other than a Polygon."""
    if (
        not isinstance(collection, dict)
        or collection.get("type") != "FeatureCollection"
        or not isinstance(collection.get("features"), list)
    ):
        raise InputError(f"'{source}' is not a GeoJSON FeatureCollection")
    feats = collection["features"]
    wkb: list[bytes] = []
    rows: list[dict[str, Any]] = []
    for i, f in enumerate(feats):
        g = f.get("geometry") if isinstance(f, dict) else None
        if g is None:
            raise InputError(
                f"'{source}': detection {i + 1} has no WGS84 outline (geometry null): the scene is "
                "not georeferenced (no crs + transform or GCPs), so there is nothing to put on a map"
            )
        if g.get("type") != "Polygon" or not g.get("coordinates"):
            raise InputError(f"'{source}': detection {i + 1} has a {g.get('type')} geometry; Polygon expected")
        wkb.append(polygon_wkb(g["coordinates"][0]))
        row: dict[str, Any] = {"name": f"ship {i + 1}"}
        for k, v in (f.get("properties") or {}).items():
            if k in SPLIT and (v is None or (isinstance(v, list) and len(v) == len(SPLIT[k]))):
                for name, x in zip(SPLIT[k], v if v is not None else [None] * len(SPLIT[k])):
                    row[name] = x
            elif isinstance(v, (list, dict)):
                row[k] = json.dumps(v, separators=(",", ":"))
            else:
                row[k] = v
        rows.append(row)
    names: list[str] = []
    for row in rows:
        names += [k for k in row if k not in names]
    arrays, masks = [], []
    for k in names:
        vals = [row.get(k) for row in rows]
        present = [v for v in vals if v is not None]
        mask = np.array([v is None for v in vals], bool)
        if not present:  # null everywhere (e.g. score of a detector without a statistic): a Real column
            arr = np.full(len(vals), np.nan)
        elif all(isinstance(v, bool) for v in present):
            arr = np.array([bool(v) if v is not None else False for v in vals], bool)
        elif all(isinstance(v, int) and not isinstance(v, bool) for v in present):
            ints = [v if v is not None else 0 for v in vals]
            small = all(-(2**31) <= v < 2**31 for v in ints)  # Integer (32-bit): KML's int, GPKG's INTEGER
            arr = np.array(ints, np.int32 if small else np.int64)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            arr = np.array([float(v) if v is not None else np.nan for v in vals], np.float64)
        else:
            arr = np.array([None if v is None else str(v) for v in vals], object)
        arrays.append(arr)
        masks.append(mask if mask.any() else None)
    return wkb, names, arrays, masks


def write(
    collection: dict,
    dst: str | os.PathLike,
    overwrite: bool = False,
    source: str = "detections",
    fmt: str | None = None,
) -> int:
    """Write ``collection`` (detections.geojson's content) to ``dst``; returns the number of
    features. ``fmt``: ``"gpkg"`` or ``"kml"`` (default: from the suffix of ``dst``). Temporary
    file beside ``dst`` (with the format's suffix, a name of its own per call), renamed into place."""
    dst = Path(dst)
    if fmt is None:
        fmt = format_of(dst)
    elif fmt not in FORMATS.values():
        raise InputError(f"format must be one of {', '.join(FORMATS.values())}, got {fmt!r}")
    if dst.exists() and not overwrite:
        raise InputError(f"'{dst}' exists; use --overwrite to replace it")
    if dst.is_dir():
        raise InputError(f"'{dst}' is a folder")
    if not dst.parent.is_dir():
        raise InputError(f"'{dst.parent}': no such folder")
    wkb, names, arrays, masks = table(collection, source)
    pyogrio = require_pyogrio()
    if fmt == "kml":
        driver = "LIBKML" if "LIBKML" in pyogrio.list_drivers(write=True) else "KML"
    else:
        driver = "GPKG"
    meta = {k: str(collection[k]) for k in ("detector", "scene") if isinstance(collection.get(k), (str, int, float))}
    tmp = dst.with_name(f".{dst.name}.partial-{os.getpid()}-{secrets.token_hex(4)}.{fmt}")
    try:
        kwargs: dict[str, Any] = {}
        if driver == "GPKG":
            kwargs["dataset_metadata"] = meta or None
        elif driver == "LIBKML":
            kwargs["dataset_options"] = {
                "NAME": "sarship detections",
                "DESCRIPTION": "; ".join(f"{k}: {v}" for k, v in meta.items()) or "sarship",
            }
        pyogrio.raw.write(
            str(tmp),
            np.array(wkb, dtype=object),
            arrays,
            names,
            field_mask=masks,
            layer="detections",
            driver=driver,
            geometry_type="Polygon",
            crs="EPSG:4326",
            **kwargs,
        )
        os.replace(tmp, dst)
    except InputError:
        raise
    except Exception as exc:  # GDAL's errors: one line naming the file
        raise InputError(
            f"'{dst}': cannot write {fmt.upper()} ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None
    finally:
        for p in (
            tmp,
            tmp.with_name(tmp.name + "-journal"),
            tmp.with_name(tmp.name + "-wal"),
            tmp.with_name(tmp.name + "-shm"),
        ):
            if p.exists():
                p.unlink()
    return len(wkb)


def read_detections(src: str | os.PathLike) -> dict:
    """detections.geojson's content; InputError (one line) when unreadable."""
    src = Path(src)
    try:
        return json.loads(src.read_text())
    except FileNotFoundError:
        raise InputError(f"'{src}': no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"'{src}' is not readable JSON ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None


def export(src: str | os.PathLike, dst: str | os.PathLike, overwrite: bool = False) -> int:
    """``sarship export SRC --to DST``: detections.geojson -> GeoPackage / KML."""
    format_of(dst)
    return write(read_detections(src), dst, overwrite=overwrite, source=str(src))


__all__ = ["FORMATS", "export", "format_of", "polygon_wkb", "read_detections", "require_pyogrio", "table", "write"]
