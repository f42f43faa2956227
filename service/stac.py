"""A STAC 1.0.0 Item per finished job (https://github.com/radiantearth/stac-spec/blob/v1.0.0/item-spec/item-spec.md).

- ``id`` is the job ID; ``geometry`` and ``bbox`` are the scene footprint in WGS84 lon/lat
  (its border, sampled along each edge, through the scene's ``transform`` + ``crs`` or ``gcps``
  with :class:`sarship.pipeline.targets.ship_features.Georeference`, pyproj for projected CRSs); a scene without
  georeference has a null geometry and no bbox, as the Item spec allows.
- ``properties.datetime`` is the scene's ``acquired`` time when the scene knows it (RFC 3339,
  UTC when the attribute has no zone), else the job's finished time; ``created`` is always the
  job's finished time.
- SAR extension v1.1.0 (https://github.com/stac-extensions/sar): its three required fields
  ``sar:instrument_mode``, ``sar:frequency_band`` and ``sar:polarizations`` are filled only from
  what the scene says (``instrument_mode`` / ``frequency_band`` attributes, a Sentinel-1 product
  name, a ``"MISSION MODE"`` sensor of a known mission, the scene's complex channels or
  ``polarisations`` attribute); when any of them is unknown (e.g. a simulated scene) the
  extension is left out rather than filled with guesses. ``sar:product_type`` (deprecated in
  v1.1 but still defined), ``sar:looks_*`` and ``sar:pixel_spacing_*`` are added when known.
- Processing extension v1.1.0 (https://github.com/stac-extensions/processing):
  ``processing:software`` ``{"sarship": version}``, ``processing:level`` ``"L2"`` (geophysical
  variables, here ship detections, derived at the input's resolution, from a Level-1 SAR
  product), ``processing:lineage`` naming the detector, its reference and resolved parameters,
  ``processing:expression`` the same as data.
- The source product's identifiers, when the scene comes from a Sentinel-1 product (the SAFE
  reader's ``product``, ``sensor``, ``mode``, ``product_type``, ``acquisition_start`` /
  ``acquisition_stop``, ``orbit_pass``, ``swath`` attributes, and the product name's fields,
  ESA's naming convention ``MMM_BB_TTTR_LFPP_<start>_<stop>_OOOOOO_DDDDDD_CCCC``): common
  metadata ``platform`` (``sentinel-1a``...), ``constellation`` (``sentinel-1``), ``instruments``
  (``["c-sar"]``), ``start_datetime`` / ``end_datetime``; Satellite extension v1.0.0
  (https://github.com/stac-extensions/sat) ``sat:orbit_state``, ``sat:absolute_orbit`` (the
  name's orbit field or an ``absolute_orbit`` / ``orbit_number`` attribute) and
  ``sat:relative_orbit`` (a ``relative_orbit`` attribute, else from the absolute orbit:
  ``(abs - 73) mod 175 + 1`` for S1A, ``(abs - 27) mod 175 + 1`` for S1B, the 175-orbit repeat
  cycle; both agree with the annotation of the repository's samples); and, outside any
  extension, ``sarship:source_product`` (the product name), ``sarship:datatake_id`` (the name's
  hexadecimal datatake field as an integer), ``sarship:swath`` (a SLC scene's sub-swath).
- Projection extension v2.0.0 (https://github.com/stac-extensions/projection), when the scene
  has a CRS and transform: ``proj:code``, ``proj:shape``, ``proj:transform`` (in the
  extension's ``[a, b, c, d, e, f]`` order).
- Assets: ``mask`` (the COG, role data), ``mask-zarr`` (the Zarr zip), ``detections``
  (GeoJSON), ``metrics`` (run.json + scores), ``preview`` (thumbnail), ``scene`` (the scene
  document of the service, or the store's ``file://`` URI for a scene outside DATA/scenes).
"""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sarship.pipeline import __version__

STAC_VERSION = "1.0.0"
SAR_EXT = "https://stac-extensions.github.io/sar/v1.1.0/schema.json"
PROCESSING_EXT = "https://stac-extensions.github.io/processing/v1.1.0/schema.json"
PROJECTION_EXT = "https://stac-extensions.github.io/projection/v2.0.0/schema.json"
SAT_EXT = "https://stac-extensions.github.io/sat/v1.0.0/schema.json"

#: Frequency bands of SAR missions (STAC sar extension, "Common Frequency Band Names").
MISSION_BANDS = (
    (r"SENTINEL-?1|^S1[A-D]?\b", "C"),
    (r"RADARSAT|^RCM", "C"),
    (r"ENVISAT|ASAR", "C"),
    (r"^ERS", "C"),
    (r"GAOFEN-?3|^GF-?3", "C"),
    (r"RISAT", "C"),
    (r"TERRASAR|TANDEM|^TSX|^TDX", "X"),
    (r"COSMO|^CSK|^CSG", "X"),
    (r"^PAZ", "X"),
    (r"KOMPSAT-?5", "X"),
    (r"ICEYE", "X"),
    (r"CAPELLA", "X"),
    (r"UMBRA", "X"),
    (r"ALOS|PALSAR|^JERS", "L"),
    (r"SAOCOM", "L"),
    (r"NISAR", "L"),
)
_POLS = ("HH", "HV", "VH", "VV")
_S1_NAME = re.compile(r"^S1[A-D]_([A-Z0-9]{2})_(GRD|SLC|OCN)", re.I)


def rfc3339(value: Any) -> str | None:
    """An ISO 8601 time as RFC 3339 UTC (``...Z``); a time without zone is taken as UTC (SAR
    product times are); None when it does not parse."""
    if not isinstance(value, str) or not value.strip():
        return None
    try:
        t = datetime.fromisoformat(value.strip().replace("z", "Z"))
    except ValueError:
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


def footprint(
    attrs: dict[str, Any], shape: tuple[int, int], n: int = 16
) -> tuple[dict[str, Any] | None, list[float] | None]:
    """``(geometry, bbox)`` of the scene border in WGS84, or ``(None, None)`` without georeference."""
    from sarship.pipeline.targets.ship_features import Georeference

    geo = {k: attrs[k] for k in ("crs", "transform", "gcps") if k in attrs}
    if not geo:
        return None, None
    try:
        g = Georeference(geo)
        if not g.usable:
            return None, None
        H, W = shape
        rows: list[float] = []
        cols: list[float] = []
        t = [i / n for i in range(n)]
        for a in t:
            rows.append(0.0)
            cols.append(a * W)
        for a in t:
            rows.append(a * H)
            cols.append(float(W))
        for a in t:
            rows.append(float(H))
            cols.append((1 - a) * W)
        for a in t:
            rows.append((1 - a) * H)
            cols.append(0.0)
        lon, lat = g.lonlat(rows, cols)
        ring = [[float(x), float(y)] for x, y in zip(lon, lat)]
    except Exception:
        return None, None
    if not all(abs(x) <= 180 and abs(y) <= 90 for x, y in ring):
        return None, None
    area = sum(ring[i][0] * ring[i - 1][1] - ring[i - 1][0] * ring[i][1] for i in range(len(ring)))
    if area < 0:  # RFC 7946: exterior rings counterclockwise
        ring.reverse()
    ring.append(ring[0])
    xs, ys = [p[0] for p in ring], [p[1] for p in ring]
    return {"type": "Polygon", "coordinates": [ring]}, [min(xs), min(ys), max(xs), max(ys)]


def sar_fields(attrs: dict[str, Any], variables: dict[str, str]) -> dict[str, Any]:
    """The sar extension fields the scene's attributes and channels determine (see the module doc);
    empty when any required one is unknown."""
    sensor = str(attrs.get("sensor") or "")
    product = str(attrs.get("product") or "")
    s1 = _S1_NAME.match(product)
    mode = attrs.get("instrument_mode") or (s1.group(1).upper() if s1 else None)
    parts = sensor.split()
    band = attrs.get("frequency_band")
    mission = parts[0] if parts else (product[:3] if s1 else "")
    if not band and mission:
        band = next((b for pat, b in MISSION_BANDS if re.search(pat, mission.upper())), None)
    if not mode and len(parts) == 2 and band:  # "SENTINEL-1A IW" (SNAP MISSION + ACQUISITION_MODE)
        mode = parts[1]
    pols = [v.upper() for v in _POLS if "complex" in str(variables.get(v.lower(), ""))]
    if not pols:
        named = attrs.get("polarizations") or attrs.get("polarisations") or []
        pols = [v.upper() for v in named if isinstance(v, str) and v.upper() in _POLS]
    if not pols and all(k in variables for k in ("c11", "c12", "c13", "c22", "c23", "c33")):
        pols = list(_POLS)  # C3 covariance: a fully polarimetric acquisition
    if set(pols) >= {"HH", "HV", "VV"}:
        pols = list(_POLS)  # fully polarimetric: all four (sar extension, sar:polarizations)
    if not (mode and band and pols):
        return {}
    out: dict[str, Any] = {
        "sar:instrument_mode": str(mode),
        "sar:frequency_band": str(band),
        "sar:polarizations": sorted(set(pols), key=_POLS.index),
    }
    ptype = attrs.get("product_type") or (s1.group(2).upper() if s1 else None)
    if ptype:  # the SAFE reader's "GRD (GRDH)": the type, as the extension's examples ("GRD", "SLC")
        out["sar:product_type"] = str(ptype).split(" (")[0]
    looks, src = attrs.get("looks"), str(attrs.get("looks_source") or "")
    if src == "single-look complex":
        out["sar:looks_range"] = out["sar:looks_azimuth"] = 1
    if isinstance(looks, (int, float)) and looks > 0:
        out["sar:looks_equivalent_number"] = float(looks)
    sp, sp_src = attrs.get("pixel_spacing_m"), str(attrs.get("pixel_spacing_source") or "")
    if sp and len(sp) == 2 and (not sp_src or "azimuth" in sp_src):  # not a map grid's spacing
        out["sar:pixel_spacing_azimuth"], out["sar:pixel_spacing_range"] = float(sp[0]), float(sp[1])
    return out


#: ESA Sentinel-1 product name: mission, mode, type + resolution, level/class/polarisation, start,
#: stop, absolute orbit, datatake ID (hex), product unique ID
_S1_FULL = re.compile(
    r"^(S1[A-D])_([A-Z0-9]{2})_([A-Z]{3})([FHM_])_(\d)([SA])(SH|SV|DH|DV|HH|HV|VV|VH)_"
    r"(\d{8}T\d{6})_(\d{8}T\d{6})_(\d{6})_([0-9A-F]{6})_([0-9A-F]{4})",
    re.I,
)
#: relative orbit = (absolute - offset) mod 175 + 1 (175 orbits per 12-day repeat cycle)
_S1_RELATIVE_OFFSET = {"S1A": 73, "S1B": 27}


def _int(v: Any) -> int | None:
    try:
        i = int(v)
    except (TypeError, ValueError):
        return None
    return i if i > 0 else None


def product_fields(attrs: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """``(properties, extensions)`` naming the source Sentinel-1 product (see the module doc);
    empty when the scene does not come from one."""
    product = str(attrs.get("product") or "")
    m = _S1_FULL.match(product)
    sensor = str(attrs.get("sensor") or "").upper()
    sm = re.match(r"SENTINEL-?1([A-D])\b", sensor)
    unit = m.group(1).upper()[2] if m else (sm.group(1) if sm else None)
    if unit is None:
        return {}, []
    out: dict[str, Any] = {
        "platform": f"sentinel-1{unit.lower()}",
        "constellation": "sentinel-1",
        "instruments": ["c-sar"],
    }
    start, end = rfc3339(attrs.get("acquisition_start")), rfc3339(attrs.get("acquisition_stop"))
    if start and end:
        out["start_datetime"], out["end_datetime"] = start, end
    if m:
        out["sarship:source_product"] = product
        out["sarship:datatake_id"] = int(m.group(11), 16)
    if attrs.get("swath"):
        out["sarship:swath"] = str(attrs["swath"])
    sat: dict[str, Any] = {}
    state = str(attrs.get("orbit_pass") or "").strip().lower()
    if state in ("ascending", "descending"):
        sat["sat:orbit_state"] = state
    absolute = _int(attrs.get("absolute_orbit") or attrs.get("orbit_number")) or (_int(m.group(10)) if m else None)
    if absolute:
        sat["sat:absolute_orbit"] = absolute
    relative = _int(attrs.get("relative_orbit") or attrs.get("relative_orbit_number"))
    if relative is None and absolute and f"S1{unit}" in _S1_RELATIVE_OFFSET:
        relative = (absolute - _S1_RELATIVE_OFFSET[f"S1{unit}"]) % 175 + 1
    if relative:
        sat["sat:relative_orbit"] = relative
    out.update(sat)
    return out, ([SAT_EXT] if sat else [])


def _epsg_code(crs: Any) -> str | None:
    m = re.fullmatch(r"\s*EPSG:(\d+)\s*", str(crs or ""), re.I)
    return f"EPSG:{m.group(1)}" if m else None


def stac_item(
    job: dict[str, Any], run: dict[str, Any], base: str, scenes_dir: Path, finished: str | None
) -> dict[str, Any]:
    """The STAC Item of a finished job (see the module doc). ``run``: the job's run.json."""
    from sarship.pipeline.scene import open_scene

    jid = job["id"]
    u = f"{base}/jobs/{jid}"
    sc = run["scene"]
    attrs = dict(sc.get("attrs") or {})
    shape = (int(sc["shape"][0]), int(sc["shape"][1]))
    scene_path = Path(sc["path"])
    try:
        variables = open_scene(scene_path).variables
    except Exception:
        variables = {}
    geometry, bbox = footprint(attrs, shape)
    acquired = rfc3339(attrs.get("acquired"))
    props: dict[str, Any] = {"datetime": acquired or finished, "created": finished}
    exts = []
    sar = sar_fields(attrs, variables)
    if sar:
        exts.append(SAR_EXT)
        props.update(sar)
    ident, ident_exts = product_fields(attrs)
    props.update(ident)
    exts += ident_exts
    params = run.get("parameters") or {}
    pstr = ", ".join(f"{k}={v}" for k, v in params.items())
    props.update(
        {
            "processing:software": {"sarship": run.get("sarship_version", __version__)},
            "processing:level": "L2",
            "processing:lineage": (
                f"Ships detected by sarship detector '{run.get('detector')}' "
                f"({run.get('reference', '')}) on channel {run.get('channel')} of scene "
                f"'{scene_path.name}' with {pstr}"
            ),
            "processing:expression": {
                "format": "sarship-detector",
                "expression": {"detector": run.get("detector"), "parameters": params},
            },
        }
    )
    exts.append(PROCESSING_EXT)
    code = _epsg_code(attrs.get("crs"))
    if code and attrs.get("transform"):
        c, a, b, f, d, e = (float(v) for v in attrs["transform"][:6])
        props.update({"proj:code": code, "proj:shape": list(shape), "proj:transform": [a, b, c, d, e, f]})
        exts.append(PROJECTION_EXT)
    try:
        inside = scene_path.resolve().parent == scenes_dir.resolve() and scene_path.name.endswith(".zarr")
    except OSError:
        inside = False
    scene_asset = (
        {
            "href": f"{base}/scenes/{scene_path.name[:-5]}",
            "type": "application/json",
            "title": "input scene (service scene document)",
            "roles": ["metadata"],
        }
        if inside
        else {
            "href": scene_path.resolve().as_uri(),
            "type": "application/vnd+zarr",
            "title": "input scene (Zarr store)",
            "roles": ["data"],
        }
    )
    item = {
        "type": "Feature",
        "stac_version": STAC_VERSION,
        "stac_extensions": exts,
        "id": jid,
        "geometry": geometry,
        **({"bbox": bbox} if bbox else {}),
        "properties": props,
        "links": [
            {"rel": "self", "href": f"{u}/results/stac", "type": "application/geo+json"},
            {"rel": "related", "href": u, "type": "application/json", "title": "job status"},
            {"rel": "related", "href": f"{u}/results", "type": "application/json", "title": "job results"},
            {"rel": "related", "href": f"{u}/tiles.json", "type": "application/json", "title": "XYZ tiles (TileJSON)"},
        ],
        "assets": {
            "mask": {
                "href": f"{u}/results/mask",
                "type": "image/tiff; application=geotiff; profile=cloud-optimized",
                "title": "detection mask (uint8, 1 = ship), max-pooled overviews",
                "roles": ["data"],
            },
            "mask-zarr": {
                "href": f"{u}/results/mask?f=zarr",
                "type": "application/zip",
                "title": "detection mask as a zipped Zarr v3 store",
                "roles": ["data"],
            },
            "detections": {
                "href": f"{u}/results/detections",
                "type": "application/geo+json",
                "title": "detected ships",
                "roles": ["data"],
            },
            "metrics": {
                "href": f"{u}/results/metrics",
                "type": "application/json",
                "title": "run record (run.json) and scores",
                "roles": ["metadata"],
            },
            "preview": {
                "href": f"{u}/preview.png?size=512",
                "type": "image/png",
                "title": "quicklook",
                "roles": ["thumbnail"],
            },
            "scene": scene_asset,
        },
    }
    json.dumps(item, allow_nan=False)  # fails loudly on a NaN rather than emitting invalid JSON
    return item
