"""Discrimination of components and the CONTRACT ``detections.geojson``.

Size filters: ``min_area_px`` / ``max_area_px`` on the pixel count, ``min_length_m`` /
``max_length_m`` on the moment length in metres (only when the scene's pixel spacing is
known; otherwise the metre filters are skipped and ``run.json`` says so).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.components import MOMENT_DTYPE, shape_from_moments


def keep_mask(records: np.ndarray, params: Any, spacing: tuple[float, float] | None) -> np.ndarray:
    """Which components pass the size filters of ``params``."""
    keep = records["n"] >= params.min_area_px
    if params.max_area_px is not None:
        keep &= records["n"] <= params.max_area_px
    if spacing is not None and (params.min_length_m is not None or params.max_length_m is not None):
        lengths = np.array([shape_from_moments(r, spacing)["length_m"] for r in records]) if len(records) else np.zeros(0)
        if params.min_length_m is not None:
            keep &= lengths >= params.min_length_m
        if params.max_length_m is not None:
            keep &= lengths <= params.max_length_m
    return keep


def pixel_to_lonlat(transform: list[float], row: float, col: float) -> tuple[float, float]:
    """GDAL geotransform [c, a, b, f, d, e]: x = c + a*col + b*row, y = f + d*col + e*row."""
    c, a, b, f, d, e = transform
    return c + a * col + b * row, f + d * col + e * row


def _outline(props: dict, spacing, transform) -> dict | None:
    if transform is None:
        return None
    cr, cc = props["centroid_px"]
    th = math.radians(props["heading_deg"])
    # unit vectors along the ship axis and across it, in (row, col) pixel coordinates
    ur, uc = -math.cos(th), math.sin(th)
    vr, vc = uc, -ur
    hl, hw = props["length_px"] / 2.0, props["width_px"] / 2.0
    ring = []
    for sl, sw in ((1, 1), (1, -1), (-1, -1), (-1, 1), (1, 1)):
        r = cr + sl * hl * ur + sw * hw * vr
        c = cc + sl * hl * uc + sw * hw * vc
        ring.append(list(pixel_to_lonlat(transform, r, c)))
    return {"type": "Polygon", "coordinates": [ring]}


def features(records: np.ndarray, spacing: tuple[float, float] | None, geo: dict | None = None) -> list[dict]:
    """One GeoJSON Feature per component record (CONTRACT properties).

    ``geo``: scene georeference ``{"crs": "EPSG:4326", "transform": [...]}``; geometry is
    the oriented ship rectangle in lon/lat when the CRS is geographic WGS84, else null.
    """
    transform = None
    if geo and str(geo.get("crs", "")).upper() in ("EPSG:4326", "OGC:CRS84", "WGS84") and geo.get("transform"):
        transform = [float(v) for v in geo["transform"]]
    out = []
    for rec in records:
        props = shape_from_moments(rec, spacing)
        props["peak"] = float(rec["peak"])
        props["mean"] = float(rec["sumv"]) / float(rec["n"])
        props["score"] = float(rec["score"]) if math.isfinite(float(rec["score"])) else None
        props["peak_px"] = [int(rec["peak_r"]), int(rec["peak_c"])]
        out.append({"type": "Feature", "geometry": _outline(props, spacing, transform), "properties": props})
    return out


def collection(feats: list[dict], **members: Any) -> dict:
    fc = {"type": "FeatureCollection", "features": feats}
    fc.update(members)
    return fc


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write JSON via a temporary file and rename (never half-written)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1, allow_nan=False, default=_default)
        f.write("\n")
    os.replace(tmp, path)


def _default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


__all__ = ["MOMENT_DTYPE", "keep_mask", "features", "collection", "write_json"]
