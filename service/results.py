"""Result routes of finished jobs: the results document, detections (GeoJSON), the mask,
the run metrics and the quicklook."""

from __future__ import annotations

import json

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse

from service.common import Problem, base_url, finished, results_doc, settings_of
from service.render import mask_geotiff, preview_png

router = APIRouter()


@router.get("/jobs/{job_id}/results")


def results(request: Request, job_id: str):
    return results_doc(finished(request, job_id), base_url(request))


@router.get("/jobs/{job_id}/results/detections")


def detections_out(request: Request, job_id: str):
    finished(request, job_id)
    return FileResponse(settings_of(request).jobs_dir / job_id / "detections.geojson", media_type="application/geo+json",
                        filename=f"{job_id}-detections.geojson")


@router.get("/jobs/{job_id}/results/metrics")


def metrics_out(request: Request, job_id: str):
    finished(request, job_id)
    return json.loads((settings_of(request).jobs_dir / job_id / "run.json").read_text())


@router.get("/jobs/{job_id}/results/mask")


def mask_out(request: Request, job_id: str):
    finished(request, job_id)
    return FileResponse(mask_geotiff(settings_of(request).jobs_dir / job_id), media_type="image/tiff; application=geotiff",
                        filename=f"{job_id}-mask.tif")


@router.get("/jobs/{job_id}/preview.png")


def preview(request: Request, job_id: str, size: int = 1024):
    if not 64 <= size <= 4096:
        raise Problem(400, "invalid request", f"'size' must be in 64..4096, got {size}")
    finished(request, job_id)
    return FileResponse(preview_png(settings_of(request).jobs_dir / job_id, size), media_type="image/png")
