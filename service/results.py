"""Result routes of finished jobs: the results document, detections (GeoJSON), the mask (COG, or
Zarr with ``?f=zarr``), the run metrics with scores, the STAC item, the quicklook and XYZ tiles.

Every product is derived from the job's immutable outputs, made once and cached in the job
folder (:mod:`sarship.service.cache`); responses of products carry an ``ETag`` (job ID and finished
time) and ``Cache-Control: immutable`` (``private`` when reads need a token).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, JSONResponse, Response

from sarship.service.common import Problem, base_url, finished, results_doc, settings_of
from sarship.service.openapi import Results, media
from sarship.service.store import iso

router = APIRouter()

COG = "image/tiff; application=geotiff; profile=cloud-optimized"
_IMMUTABLE = {
    "Cache-Control": {"description": "immutable: job outputs never change", "schema": {"type": "string"}},
    "ETag": {"description": "job and product", "schema": {"type": "string"}},
}
_MASK_DOC: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the mask: a Cloud-Optimized GeoTIFF (f=tif, default) or a zipped Zarr v3 store (f=zarr)",
        "headers": _IMMUTABLE,
        "content": {
            COG: {"schema": {"type": "string", "format": "binary"}},
            "application/zip": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}
_PNG_DOC: dict[int | str, dict[str, Any]] = {200: {**media("image/png", "PNG image")[200], "headers": _IMMUTABLE}}

#: ``f`` values of GET /jobs/{id}/results/mask (the OGC API convention for a format choice:
#: a plain link picks the format, caches key on the URL; no Accept negotiation).
MASK_FORMATS = {"tif": "cog", "tiff": "cog", "geotiff": "cog", "cog": "cog", "zarr": "zarr"}


def _job_dir(request: Request, job_id: str) -> Path:
    return settings_of(request).jobs_dir / job_id


def _cache_headers(request: Request, job: dict[str, Any], tag: str) -> dict[str, str]:
    scope = "private" if settings_of(request).protect_reads else "public"
    return {
        "Cache-Control": f"{scope}, max-age=31536000, immutable",
        "ETag": f'"{job["id"]}-{int((job["finished"] or 0) * 1000)}-{tag}"',
    }


def _not_modified(request: Request, headers: dict[str, str]) -> Response | None:
    inm = request.headers.get("if-none-match")
    if inm and (inm.strip() == "*" or headers["ETag"] in [t.strip().removeprefix("W/") for t in inm.split(",")]):
        return Response(status_code=304, headers=headers)
    return None


@contextlib.contextmanager
def _scene_readable(job_id: str) -> Iterator[None]:
    """Quicklooks read the job's scene: one removed since the job ran is a 404 problem, not a 500."""
    from sarship.pipeline.errors import InputError

    try:
        yield
    except InputError as exc:
        raise Problem(404, "scene unavailable", f"job '{job_id}': its scene can no longer be read ({exc})") from None


@router.get(
    "/jobs/{job_id}/results",
    response_model=None,
    responses={200: {"model": Results, "description": "the results document"}},
)
def results(request: Request, job_id: str) -> dict[str, Any]:
    job = finished(request, job_id, ingest_ok=True)
    b = base_url(request)
    if job["process"] == "ingest":  # an ingest job's result is its scene
        return {"scene": {"href": f"{b}/scenes/{job['inputs'].get('scene_id', '')}", "type": "application/json"}}
    doc = results_doc(job, b)
    if _map_formats(request, job_id):  # GeoPackage / KML of the detections (georeferenced scene, gis extra)
        u = f"{b}/jobs/{job_id}/results/detections"
        doc.update(
            {f"detections-{f}": {"href": f"{u}?f={f}", "type": t} for f, t in DETECTION_MEDIA.items() if f != "geojson"}
        )
    return doc


#: ``f`` values of GET /jobs/{id}/results/detections and their media types
DETECTION_MEDIA = {
    "geojson": "application/geo+json",
    "gpkg": "application/geopackage+sqlite3",
    "kml": "application/vnd.google-earth.kml+xml",
}


def _map_formats(request: Request, job_id: str) -> bool:
    """Whether the job's detections can be offered as GeoPackage / KML: the scene was
    georeferenced (run.json's scene attributes) and pyogrio (extra ``gis``) is installed."""
    import importlib.util

    if importlib.util.find_spec("pyogrio") is None:
        return False
    try:
        attrs = json.loads((_job_dir(request, job_id) / "run.json").read_text())["scene"].get("attrs") or {}
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return bool(attrs.get("gcps") or (attrs.get("crs") and attrs.get("transform") is not None))


_DETECTIONS_DOC: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "detected ships: a GeoJSON FeatureCollection (f=geojson, default), a "
        "GeoPackage (f=gpkg) or KML (f=kml) of their WGS84 outlines",
        "content": {
            "application/geo+json": {"schema": {"type": "object"}},
            "application/geopackage+sqlite3": {"schema": {"type": "string", "format": "binary"}},
            "application/vnd.google-earth.kml+xml": {"schema": {"type": "string"}},
        },
    }
}


@router.get("/jobs/{job_id}/results/detections", responses=_DETECTIONS_DOC)
def detections_out(request: Request, job_id: str, f: str = "geojson") -> Response:
    """The detections as GeoJSON (default), or with ``f=gpkg`` / ``f=kml`` as a GeoPackage / KML
    (:mod:`sarship.pipeline.products.export`, built once and cached in the job folder) when the scene was
    georeferenced and the ``gis`` extra is installed."""
    from sarship.pipeline.errors import InputError
    from sarship.service.cache import build_once

    fmt = f.lower()
    if fmt not in DETECTION_MEDIA:
        raise Problem(400, "invalid request", f"'f' must be one of {', '.join(DETECTION_MEDIA)} (got {f!r})")
    job = finished(request, job_id)
    d = _job_dir(request, job_id)
    if fmt == "geojson":
        return FileResponse(
            d / "detections.geojson", media_type="application/geo+json", filename=f"{job_id}-detections.geojson"
        )
    from sarship.pipeline.products import export

    try:
        export.require_pyogrio()
    except InputError as exc:
        raise Problem(501, "format not available", str(exc)) from None
    headers = _cache_headers(request, job, f"detections-{fmt}")
    nm = _not_modified(request, headers)
    if nm is not None:
        return nm
    try:
        out = build_once(
            d / f"detections.{fmt}",
            lambda tmp: export.write(
                export.read_detections(d / "detections.geojson"), tmp, source=f"job {job_id}", fmt=fmt
            ),
        )
    except InputError as exc:  # the scene had no georeference: no outlines to map
        raise Problem(404, "no such result", str(exc)) from None
    return FileResponse(out, media_type=DETECTION_MEDIA[fmt], filename=f"{job_id}-detections.{fmt}", headers=headers)


@router.get(
    "/jobs/{job_id}/results/ais_unmatched",
    responses=media("application/geo+json", "the AIS vessels that matched no detection", schema={"type": "object"}),
)
def ais_unmatched_out(request: Request, job_id: str) -> Response:
    """``ais_unmatched.geojson``: the vessels that reported inside the scene's footprint and
    matched no detection (docs/ais.md); a 404 problem for a job given no AIS files."""
    finished(request, job_id)
    p = _job_dir(request, job_id) / "ais_unmatched.geojson"
    if not p.is_file():
        raise Problem(404, "no such result", f"job '{job_id}' was given no AIS files (input 'ais'): no ais_unmatched")
    return FileResponse(p, media_type="application/geo+json", filename=f"{job_id}-ais_unmatched.geojson")


@router.get("/jobs/{job_id}/results/metrics", response_model=None)
def metrics_out(request: Request, job_id: str) -> dict[str, Any]:
    """run.json (with AIS files, its ``ais`` record: docs/ais.md), plus ``scores``
    (``sarship evaluate``'s) when the scene has ground truth."""
    from sarship.service.scores import job_scores

    finished(request, job_id)
    d = _job_dir(request, job_id)
    run = json.loads((d / "run.json").read_text())
    scores = job_scores(d, run)
    if scores is not None:
        run["scores"] = scores
    doc: dict[str, Any] = _without_paths(run, settings_of(request).hide_paths)  # a dict, as run is
    return doc


def _without_paths(doc: Any, hide: Callable[[str], str]) -> Any:
    """``doc`` (run.json) with the server's data folder taken out of every string
    (:meth:`Settings.hide_paths`): the scene, the outputs and a land-mask file are named as a
    client names them (``SCENE.zarr``, ``jobs/ID/mask.zarr``), never by the server's path."""
    if isinstance(doc, str):
        return hide(doc)
    if isinstance(doc, dict):
        return {k: _without_paths(v, hide) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_without_paths(v, hide) for v in doc]
    return doc


@router.get("/jobs/{job_id}/results/mask", responses=_MASK_DOC)
def mask_out(request: Request, job_id: str, f: str = "tif") -> Response:
    """The mask as a Cloud-Optimized GeoTIFF (default; ``f=tif|tiff|geotiff|cog``) or, with
    ``f=zarr``, the mask's Zarr v3 store as a zip (``application/zip``)."""
    from sarship.service.cog import mask_cog, mask_zarr_zip

    fmt = MASK_FORMATS.get(f.lower())
    if fmt is None:
        raise Problem(400, "invalid request", f"'f' must be one of {', '.join(MASK_FORMATS)} (got {f!r})")
    job = finished(request, job_id)
    headers = _cache_headers(request, job, f"mask-{fmt}")
    nm = _not_modified(request, headers)
    if nm is not None:
        return nm
    d = _job_dir(request, job_id)
    if fmt == "zarr":
        return FileResponse(
            mask_zarr_zip(d), media_type="application/zip", filename=f"{job_id}-mask.zarr.zip", headers=headers
        )
    return FileResponse(mask_cog(d), media_type=COG, filename=f"{job_id}-mask.tif", headers=headers)


@router.get(
    "/jobs/{job_id}/results/stac",
    responses=media("application/geo+json", "the job's STAC 1.0.0 Item", schema={"type": "object"}),
)
def stac_out(request: Request, job_id: str) -> JSONResponse:
    """The job's STAC Item (application/geo+json), see :mod:`sarship.service.stac`."""
    from sarship.service.stac import stac_item

    job = finished(request, job_id)
    d = _job_dir(request, job_id)
    run = json.loads((d / "run.json").read_text())
    item = stac_item(job, run, base_url(request), settings_of(request).scenes_dir, iso(job["finished"]))
    return JSONResponse(item, media_type="application/geo+json")


#: Sizes the preview is rendered at: a request is rounded down to one of them (so at most
#: these few PNGs exist per job), capped at the largest.
PREVIEW_LEVELS = (64, 128, 256, 512, 1024, 2048)


def preview_level(size: int) -> int:
    """The preview size served for ``?size=size`` (64..4096): the largest of
    :data:`PREVIEW_LEVELS` not above it."""
    return max(v for v in PREVIEW_LEVELS if v <= max(size, PREVIEW_LEVELS[0]))


@router.get("/jobs/{job_id}/preview.png", responses=_PNG_DOC)
def preview(request: Request, job_id: str, size: int = 1024) -> Response:
    """Quicklook PNG, at most ``size`` pixels a side, rendered at a few fixed sizes
    (:data:`PREVIEW_LEVELS`: ``size`` is rounded down to one) and cached in the job folder; the
    cached previews of all jobs together take at most ``preview_cache_mb`` (the oldest are
    removed beyond it)."""
    from sarship.service.cache import trim_oldest
    from sarship.service.render import preview_png

    if not 64 <= size <= 4096:
        raise Problem(400, "invalid request", f"'size' must be in 64..4096, got {size}")
    level = preview_level(size)
    job = finished(request, job_id)
    headers = _cache_headers(request, job, f"preview-{level}")
    nm = _not_modified(request, headers)
    if nm is not None:
        return nm
    settings = settings_of(request)
    d = _job_dir(request, job_id)
    for attempt in range(3):  # a concurrent trim may remove the file between its build and this read
        built = not (d / f"preview-{level}.png").exists()
        with _scene_readable(job_id):
            png = preview_png(d, level)
        try:
            data = png.read_bytes()
            break
        except FileNotFoundError:
            if attempt == 2:
                raise
    if built:  # a new file in the cache: keep the cache within its size
        trim_oldest(settings.jobs_dir.glob("*/preview-*.png"), int(settings.preview_cache_mb * 2**20))
    return Response(data, media_type="image/png", headers=headers)


def _shape(request: Request, job_id: str) -> tuple[int, int]:
    run = json.loads((_job_dir(request, job_id) / "run.json").read_text())
    return int(run["scene"]["shape"][0]), int(run["scene"]["shape"][1])


@router.get("/jobs/{job_id}/tiles.json", response_model=None)
def tiles_json(request: Request, job_id: str) -> dict[str, Any]:
    """TileJSON 3.0.0 of the job's XYZ quicklook tiles (see :mod:`sarship.service.tiles`)."""
    from sarship.service.tiles import tilejson

    finished(request, job_id)
    attrs = json.loads((_job_dir(request, job_id) / "run.json").read_text())["scene"].get("attrs") or {}
    return tilejson(base_url(request), job_id, _shape(request, job_id), attrs)


@router.get("/jobs/{job_id}/tiles/{z}/{x}/{y}.png", responses=_PNG_DOC)
def tile(request: Request, job_id: str, z: int, x: int, y: int, layers: str | None = None) -> Response:
    """XYZ tile (z, x, y) of the job's quicklook: 256 x 256 RGBA PNG, ``layers`` a comma list of
    ``scene``, ``mask`` (default both)."""
    from sarship.service.tiles import cached_tile, max_zoom, parse_layers, tile_counts

    try:
        lay = parse_layers(layers)
    except ValueError as exc:
        raise Problem(400, "invalid request", str(exc)) from None
    job = finished(request, job_id)
    shape = _shape(request, job_id)
    Z = max_zoom(shape)
    if not 0 <= z <= Z:
        raise Problem(404, "no such tile", f"zoom {z} is outside 0..{Z} for this {shape[0]}x{shape[1]} scene")
    nx, ny = tile_counts(shape, z)
    if not (0 <= x < nx and 0 <= y < ny):
        raise Problem(404, "no such tile", f"tile {z}/{x}/{y}: at zoom {z} x is in 0..{nx - 1} and y in 0..{ny - 1}")
    headers = _cache_headers(request, job, f"tile-{z}-{x}-{y}-{'+'.join(lay)}")
    nm = _not_modified(request, headers)
    if nm is not None:
        return nm
    with _scene_readable(job_id):
        png = cached_tile(_job_dir(request, job_id), headers["ETag"], shape, z, x, y, lay)
    return Response(png, media_type="image/png", headers=headers)
