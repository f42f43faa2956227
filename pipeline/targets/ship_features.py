"""Discrimination of components and ``detections.geojson`` (docs/interfaces/files.md).

Size filters: ``min_area_px`` / ``max_area_px`` on the pixel count, ``min_length_m`` /
``max_length_m`` on the moment length in metres (only when the scene's pixel spacing is
known; otherwise the metre filters are skipped and ``run.json`` says so). Unset
``min_area_px`` / ``min_length_m`` follow the detector's size rule
(:func:`sarship.pipeline.detectors.base.resolve_size`: metres when the spacing is known,
pixels otherwise).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.targets.components import MOMENT_DTYPE, shape_from_moments


def _moment_axes(records: np.ndarray, spacing: tuple[float, float] | None) -> tuple[np.ndarray, np.ndarray]:
    """Half the trace and the discriminant root of every record's position covariance (the
    pixel's own 1/12 variance added; scaled by ``spacing`` when given): its eigenvalues are
    ``tr/2 +- disc``. The operations and their order are those of
    :func:`sarship.pipeline.targets.components.shape_from_moments`, so the same float64 values."""
    n = records["n"].astype(np.float64)
    mr = records["sr"] / n
    mc = records["sc"] / n
    vrr = np.maximum(records["srr"] / n - mr * mr, 0.0) + 1.0 / 12.0
    vcc = np.maximum(records["scc"] / n - mc * mc, 0.0) + 1.0 / 12.0
    vrc = records["src"] / n - mr * mc
    az, rg = (float(spacing[0]), float(spacing[1])) if spacing is not None else (1.0, 1.0)
    a, b, c = vrr * az * az, vrc * az * rg, vcc * rg * rg
    tr, det = a + c, a * c - b * b
    return tr / 2.0, np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))


def lengths_m(records: np.ndarray, spacing: tuple[float, float]) -> np.ndarray:
    """Moment length in metres of every record: ``shape_from_moments(rec, spacing)["length_m"]``,
    vectorised (the same float64 values)."""
    half, disc = _moment_axes(records, spacing)
    return np.sqrt(12.0 * (half + disc))


def elongations(records: np.ndarray, spacing: tuple[float, float] | None) -> np.ndarray:
    """Moment length over moment width of every record, ``sqrt(l1 / l2)`` of the (spacing-scaled,
    when known) position covariance, as :func:`sarship.pipeline.targets.components.shape_from_moments`
    measures length and width: 1 for a single pixel, n for a 1 x n line."""
    half, disc = _moment_axes(records, spacing)
    return np.sqrt((half + disc) / np.maximum(half - disc, 1e-300))


def keep_mask(records: np.ndarray, params: Any, spacing: tuple[float, float] | None) -> np.ndarray:
    """Which components pass the size filters of ``params`` (unset sizes: the detector's size
    rule) and its shape filter ``max_elongation`` (length / width, in metres when the spacing is
    known)."""
    if getattr(params, "min_area_px", 1) is None:
        from sarship.pipeline.detectors.base import resolve_size

        params, _ = resolve_size(params, spacing)
    keep = records["n"] >= params.min_area_px
    if params.max_area_px is not None:
        keep &= records["n"] <= params.max_area_px
    max_el = getattr(params, "max_elongation", None)
    if max_el is not None and len(records):
        keep &= elongations(records, spacing) <= max_el
    if spacing is not None and (params.min_length_m is not None or params.max_length_m is not None):
        lengths = lengths_m(records, spacing) if len(records) else np.zeros(0)
        if params.min_length_m is not None:
            keep &= lengths >= params.min_length_m
        if params.max_length_m is not None:
            keep &= lengths <= params.max_length_m
    return keep


def size_prefilter(params: Any, line_join: bool) -> Any:
    """The filter a tile applies to its own complete components before the merge: the whole
    :func:`keep_mask` rule, or, when collinear pieces are joined into lines on the client
    (:mod:`sarship.pipeline.targets.lines`, ``line_join``), the area rule only: a line's pieces must
    reach the join whatever their shape (each may be thinner or shorter than a ship), and the
    client applies the same area rule before the join, so the pieces joined do not depend on
    the tiling."""
    if not line_join:
        return params
    return params.model_copy(update={"max_elongation": None, "min_length_m": None, "max_length_m": None})


_WGS84 = ("EPSG:4326", "OGC:CRS84", "WGS84", "CRS84")


class Georeference:
    """Scene pixel (row, col) -> WGS84 (lon, lat), from the scene's georeference attributes.

    Pixel coordinates are continuous with pixel (r, c) covering [r, r+1) x [c, c+1), the
    GDAL/GeoTIFF PixelIsArea convention. Sources, in order: ``transform`` (GDAL affine), or
    ``gcps`` (ground control points ``{row, col, x, y}``, :func:`sarship.pipeline.targets.georef.from_gcps`:
    bilinear interpolation on the geolocation grid when the GCPs form one, as a Sentinel-1
    annotation's do; else a least-squares polynomial, affine for < 6 points, quadratic from 6,
    as GDAL's GCP transformer does), in the scene ``crs`` (default EPSG:4326 for GCPs); any CRS
    other than WGS84 is converted with pyproj. ``method`` names the mapping used.
    """

    def __init__(self, attrs: dict):
        from sarship.pipeline.targets.georef import from_gcps

        self.transform = attrs.get("transform")
        self.gcps = attrs.get("gcps")
        crs = attrs.get("crs") or ("EPSG:4326" if self.gcps else None)
        self.crs = str(crs) if crs else None
        self._proj = None
        self._gcp_map = None
        self.method = "affine transform" if self.transform is not None else None
        if self.transform is None and self.gcps:
            try:
                self._gcp_map = from_gcps(self.gcps, geographic=self.crs is not None and self.crs.upper() in _WGS84)
                self.method = self._gcp_map.method
            except (ValueError, KeyError, TypeError, np.linalg.LinAlgError):
                self._gcp_map = None  # unusable GCPs: no geometry rather than a wrong one
        if self.crs and self.crs.upper() not in _WGS84 and (self.transform is not None or self._gcp_map is not None):
            try:
                from pyproj import Transformer

                self._proj = Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)
            except Exception:
                self.crs = None  # unknown CRS: no geometry rather than a wrong one

    @property
    def usable(self) -> bool:
        if self.crs is None:
            return False
        return self.transform is not None or self._gcp_map is not None

    def lonlat(self, rows, cols) -> tuple[np.ndarray, np.ndarray]:
        rows = np.asarray(rows, float)
        cols = np.asarray(cols, float)
        if self.transform is not None:
            c, a, b, f, d, e = (float(v) for v in self.transform)
            x, y = c + a * cols + b * rows, f + d * cols + e * rows
        else:
            x, y = self._gcp_map.lonlat(rows, cols)
        if self._proj is not None:
            x, y = self._proj.transform(x, y)
        return np.asarray(x), np.asarray(y)


def _outline(props: dict, spacing, geo: Georeference | None) -> dict | None:
    if geo is None or not geo.usable:
        return None
    cr, cc = props["centroid_px"]
    th = math.radians(props["heading_deg"])
    # unit vectors along the ship axis and across it, in (row, col) pixel coordinates
    ur, uc = -math.cos(th), math.sin(th)
    vr, vc = uc, -ur
    hl, hw = props["length_px"] / 2.0, props["width_px"] / 2.0
    rows, cols = [], []
    for sl, sw in ((1, 1), (1, -1), (-1, -1), (-1, 1), (1, 1)):
        rows.append(cr + sl * hl * ur + sw * hw * vr)
        cols.append(cc + sl * hl * uc + sw * hw * vc)
    lon, lat = geo.lonlat(rows, cols)
    ring = [[float(a), float(b)] for a, b in zip(lon, lat)]
    return {"type": "Polygon", "coordinates": [ring]}


def features(records: np.ndarray, spacing: tuple[float, float] | None, geo: dict | None = None) -> list[dict]:
    """One GeoJSON Feature per component record (the properties of docs/interfaces/files.md).

    ``geo``: the scene's georeference attributes (``crs`` + ``transform``, or ``gcps``);
    geometry is the oriented ship rectangle in WGS84 lon/lat (:class:`Georeference`), and
    ``centroid_lonlat`` its centre [lon, lat]; both null when the scene is not georeferenced.
    """
    georef = Georeference(geo) if geo else None
    out = []
    for rec in records:
        props = shape_from_moments(rec, spacing)
        props["peak"] = float(rec["peak"])
        props["mean"] = float(rec["sumv"]) / float(rec["n"])
        props["score"] = float(rec["score"]) if math.isfinite(float(rec["score"])) else None
        props["peak_px"] = [int(rec["peak_r"]), int(rec["peak_c"])]
        props["centroid_lonlat"] = _centre(props, georef)
        out.append({"type": "Feature", "geometry": _outline(props, spacing, georef), "properties": props})
    return out


def add_contrast(feats: list[dict], sea: float | None) -> list[dict]:
    """Each detection's target-to-clutter ratio ``tcr_db`` = 10 log10(``mean`` / ``sea``): its
    mean pixel power over the sea's mean power of the texture land pass
    (:func:`sarship.pipeline.land.landmask.sea_mean`); null without that reference (no texture land
    pass, or no sea in it) or for a detection whose mean is not positive. The seed's
    discrimination by "scattering characteristics" (docs/references.md#liu2017, step 4) reads
    such a ratio; the product reports it and drops nothing by it (bench/REALDATA.md: no
    threshold serves the 8-bit and the calibrated chips alike)."""
    for f in feats:
        mean = f["properties"].get("mean")
        ok = sea is not None and sea > 0 and mean is not None and mean > 0 and math.isfinite(mean)
        f["properties"]["tcr_db"] = round(10.0 * math.log10(mean / sea), 3) if ok else None
    return feats


def _centre(props: dict, geo: Georeference | None) -> list[float] | None:
    if geo is None or not geo.usable:
        return None
    lon, lat = geo.lonlat([props["centroid_px"][0]], [props["centroid_px"][1]])
    return [float(lon[0]), float(lat[0])]


def geolocate(feats: list[dict], geo: dict | None) -> list[dict]:
    """Every feature's ``geometry`` (WGS84 outline) and ``centroid_lonlat`` [lon, lat] from its
    final pixel geometry (``centroid_px``, ``length_px``, ``width_px``, ``heading_deg``), after
    any step that replaced that geometry (sidelobe cores, segmented ships); ``null`` both when
    the scene is not georeferenced. In place; returns ``feats``."""
    georef = Georeference(geo) if geo else None
    for f in feats:
        f["geometry"] = _outline(f["properties"], None, georef)
        f["properties"]["centroid_lonlat"] = _centre(f["properties"], georef)
    return feats


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


__all__ = [
    "MOMENT_DTYPE",
    "keep_mask",
    "size_prefilter",
    "lengths_m",
    "features",
    "geolocate",
    "collection",
    "write_json",
]
