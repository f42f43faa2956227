"""Detections (and AIS vessels) as GeoPackage or KML, the files a GIS opens (``sarship export``,
``sarship detect --formats``).

``detections.geojson`` (docs/interfaces/files.md) is converted, not re-derived: one feature per
ship, its WGS84 outline polygon, and its properties as columns. Lists become scalar columns a
GIS can style and filter on (``centroid_lonlat`` -> ``centroid_lon``, ``centroid_lat``;
``centroid_px`` -> ``centroid_row``, ``centroid_col``; ``bbox_px`` -> ``bbox_row0``, ``bbox_col0``,
``bbox_row1``, ``bbox_col1``; ``peak_px`` -> ``peak_row``, ``peak_col``); the AIS record ``ais``
(docs/ais.md) becomes ``ais_mmsi``, ``ais_name``, ``ais_score``, ``ais_distance_m``, ``ais_dt_s``,
``ais_length_m``, ``ais_displacement_m`` (null where no vessel matched) beside ``dark``; other
nested values are kept as JSON text. Each feature gets ``name`` = ``ship <n>`` (n from 1, the
GeoJSON order), the label a KML viewer shows. The collection's ``detector`` and ``scene`` members
go into the file's metadata (GeoPackage ``gpkg_metadata``; KML document description).

``ais_unmatched.geojson`` (the reporting vessels a run matched to nothing: Points) becomes a Point
layer ``ais_unmatched``, its properties as columns and ``name`` the vessel's name, or ``MMSI
<mmsi>`` where the AIS gave none (``vessel <n>`` without an MMSI either). Which layer: Points or Polygons from the features' geometry
(one kind in a file); an empty collection is a Point layer when the file is named
``ais_unmatched*``. Columns a run always writes have a fixed type (:data:`TYPES`: an integer
``ais_mmsi``, a boolean ``dark``), also where every value is null.

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
#: the fields of a detection's ``ais`` record (docs/ais.md), flattened into ``ais_<field>`` columns
AIS_FIELDS = ("mmsi", "name", "score", "distance_m", "dt_s", "ais_length_m", "displacement_m")
#: columns of a fixed type (``int``, ``float``, ``str``, ``bool``), whatever their values (all null too)
TYPES = {
    "ais_mmsi": "int",
    "ais_name": "str",
    "ais_score": "float",
    "ais_distance_m": "float",
    "ais_dt_s": "float",
    "ais_length_m": "float",
    "ais_displacement_m": "float",
    "dark": "bool",
    # ais_unmatched.geojson
    "mmsi": "int",
    "length_m": "float",
    "time": "float",
    "gap_s": "float",
    "extrapolated": "bool",
    "detectable": "bool",
}
#: geometry type -> (layer name, KML document name)
LAYERS = {"Polygon": ("detections", "sarship detections"), "Point": ("ais_unmatched", "sarship AIS vessels unmatched")}


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


def point_wkb(lon: float, lat: float) -> bytes:
    """ISO WKB (little endian) of a point.

    Parameters
    ----------
    lon, lat : float
        WGS84 degrees.

    Returns
    -------
    bytes
        21 bytes: byte order, type 1, x, y.
    """
    return struct.pack("<BIdd", 1, 1, float(lon), float(lat))


def _ais_column(key: str) -> str:
    return key if key.startswith("ais_") else f"ais_{key}"


def _geometry(f: Any, i: int, source: str) -> tuple[bytes, str]:
    """WKB and type (``Polygon`` or ``Point``) of feature ``i``; InputError otherwise."""
    g = f.get("geometry") if isinstance(f, dict) else None
    if g is None:
        raise InputError(
            f"'{source}': detection {i + 1} has no WGS84 outline (geometry null): the scene is "
            "not georeferenced (no crs + transform or GCPs), so there is nothing to put on a map"
        )
    kind, coords = g.get("type"), g.get("coordinates")
    if kind == "Polygon" and coords:
        return polygon_wkb(coords[0]), kind
    if kind == "Point" and isinstance(coords, list) and len(coords) >= 2:
        return point_wkb(coords[0], coords[1]), kind
    raise InputError(f"'{source}': feature {i + 1} has a {kind} geometry; Polygon (ships) or Point (vessels) expected")


def _row(props: dict[str, Any], label: str, kind: str) -> dict[str, Any]:
    """One feature's columns (module docstring): lists split, ``ais`` flattened, nested values as JSON."""
    row: dict[str, Any] = {"name": label}
    if kind == "Point" and props.get("name"):
        row["name"] = props["name"]
    elif kind == "Point" and props.get("mmsi") is not None:
        row["name"] = f"MMSI {props['mmsi']}"
    for k, v in props.items():
        if kind == "Point" and k == "name":
            continue
        if k in SPLIT and (v is None or (isinstance(v, list) and len(v) == len(SPLIT[k]))):
            for name, x in zip(SPLIT[k], v if v is not None else [None] * len(SPLIT[k])):
                row[name] = x
        elif k == "ais" and (v is None or isinstance(v, dict)):
            rec = v or {}
            for field in (*AIS_FIELDS, *(x for x in rec if x not in AIS_FIELDS)):
                x = rec.get(field)
                row[_ais_column(field)] = json.dumps(x, separators=(",", ":")) if isinstance(x, (list, dict)) else x
        elif isinstance(v, (list, dict)):
            row[k] = json.dumps(v, separators=(",", ":"))
        else:
            row[k] = v
    return row


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _column(vals: list[Any], typ: str | None) -> np.ndarray:
    """A column's array: of type ``typ`` (:data:`TYPES`) when its values allow it, else inferred."""
    present = [v for v in vals if v is not None]
    if typ is None or not present:
        pass
    elif typ == "int" and not all(_is_int(v) for v in present):
        typ = None
    elif typ == "float" and not all(_is_int(v) or isinstance(v, float) for v in present):
        typ = None
    elif typ == "bool" and not all(isinstance(v, bool) for v in present):
        typ = None
    if typ is None:
        if not present:  # null everywhere (e.g. score of a detector without a statistic): a Real column
            typ = "float"
        elif all(isinstance(v, bool) for v in present):
            typ = "bool"
        elif all(_is_int(v) for v in present):
            typ = "int"
        elif all(_is_int(v) or isinstance(v, float) for v in present):
            typ = "float"
        else:
            typ = "str"
    if typ == "bool":
        return np.array([bool(v) if v is not None else False for v in vals], bool)
    if typ == "int":
        ints = [v if v is not None else 0 for v in vals]
        small = all(-(2**31) <= v < 2**31 for v in ints)  # Integer (32-bit): KML's int, GPKG's INTEGER
        return np.array(ints, np.int32 if small else np.int64)
    if typ == "float":
        return np.array([float(v) if v is not None else np.nan for v in vals], np.float64)
    return np.array([None if v is None else str(v) for v in vals], object)


def table(collection: dict, source: str = "detections") -> tuple[list[bytes], list[str], list[np.ndarray], list, str]:
    """The layer of a FeatureCollection (module docstring).

    Parameters
    ----------
    collection : dict
        ``detections.geojson``'s content (Polygons) or ``ais_unmatched.geojson``'s (Points).
    source : str
        The file it was read from, for messages (and the layer of an empty collection).

    Returns
    -------
    wkb : list of bytes
        Each feature's geometry.
    names : list of str
        The columns.
    arrays : list of numpy.ndarray
        Each column's values.
    masks : list of numpy.ndarray or None
        Each column's nulls (None: none).
    geometry_type : str
        ``"Polygon"`` or ``"Point"``.

    Raises
    ------
    InputError
        Not a FeatureCollection; a feature without a geometry (the scene was not
        georeferenced), with one other than a Polygon or a Point, or Polygons and Points mixed.
    """
    if (
        not isinstance(collection, dict)
        or collection.get("type") != "FeatureCollection"
        or not isinstance(collection.get("features"), list)
    ):
        raise InputError(f"'{source}' is not a GeoJSON FeatureCollection")
    feats = collection["features"]
    wkb: list[bytes] = []
    rows: list[dict[str, Any]] = []
    kinds: set[str] = set()
    for i, f in enumerate(feats):
        geom, kind = _geometry(f, i, source)
        kinds.add(kind)
        if len(kinds) > 1:
            raise InputError(f"'{source}': mixes Polygon and Point features; one kind per file")
        wkb.append(geom)
        rows.append(_row(f.get("properties") or {}, f"{'ship' if kind == 'Polygon' else 'vessel'} {i + 1}", kind))
    if not kinds:
        kinds.add("Point" if Path(source).name.startswith("ais_unmatched") else "Polygon")
    names: list[str] = []
    for row in rows:
        names += [k for k in row if k not in names]
    arrays, masks = [], []
    for k in names:
        vals = [row.get(k) for row in rows]
        mask = np.array([v is None for v in vals], bool)
        arrays.append(_column(vals, TYPES.get(k)))
        masks.append(mask if mask.any() else None)
    return wkb, names, arrays, masks, kinds.pop()


def write(
    collection: dict,
    dst: str | os.PathLike,
    overwrite: bool = False,
    source: str = "detections",
    fmt: str | None = None,
) -> int:
    """Write ``collection`` (detections.geojson's or ais_unmatched.geojson's content) to ``dst``;
    returns the number of features. ``fmt``: ``"gpkg"`` or ``"kml"`` (default: from the suffix of ``dst``). Temporary
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
    wkb, names, arrays, masks, geometry_type = table(collection, source)
    layer, title = LAYERS[geometry_type]
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
                "NAME": title,
                "DESCRIPTION": "; ".join(f"{k}: {v}" for k, v in meta.items()) or "sarship",
            }
        pyogrio.raw.write(
            str(tmp),
            np.array(wkb, dtype=object),
            arrays,
            names,
            field_mask=masks,
            layer=layer,
            driver=driver,
            geometry_type=geometry_type,
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
    """``sarship export SRC --to DST``: detections.geojson (or ais_unmatched.geojson) -> GeoPackage / KML."""
    format_of(dst)
    return write(read_detections(src), dst, overwrite=overwrite, source=str(src))


__all__ = [
    "AIS_FIELDS",
    "FORMATS",
    "TYPES",
    "export",
    "format_of",
    "point_wkb",
    "polygon_wkb",
    "read_detections",
    "require_pyogrio",
    "table",
    "write",
]
