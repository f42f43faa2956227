"""Job routes (OGC API - Processes job list and dismiss): ``GET /jobs``, ``GET /jobs/{id}``
(the status clients poll) and ``DELETE /jobs/{id}``. A job's results are ``service/results.py``."""

from __future__ import annotations

import shutil
import uuid
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request

from sarship.service.common import Problem, base_url, job_or_404, settings_of, status_doc, store_of
from sarship.service.openapi import JobList, JobStatus, StatusInfo, problems
from sarship.service.settings import Settings

router = APIRouter()


@router.get("/jobs", response_model=None, responses={200: {"model": JobList}})
def jobs(
    request: Request,
    limit: int = Query(1000, ge=1, le=10000, description="most jobs listed, newest first"),
    status: Annotated[JobStatus | None, Query(description="only jobs in this status")] = None,
) -> dict[str, Any]:
    b = base_url(request)
    return {
        "jobs": [status_doc(j, b) for j in store_of(request).list(limit=limit, status=status)],
        "links": [{"href": f"{b}/jobs", "rel": "self", "type": "application/json"}],
    }


@router.get("/jobs/{job_id}", response_model=None, responses={200: {"model": StatusInfo}})
async def job(request: Request, job_id: str) -> dict[str, Any]:
    # the route clients poll: on the event loop, no threadpool hop (a primary-key read of
    # the WAL-mode store, ~40 us, never waits for writers)
    return status_doc(job_or_404(request, job_id), base_url(request))


@router.delete(
    "/jobs/{job_id}",
    response_model=None,
    responses={
        200: {
            "model": StatusInfo,
            "description": (
                "the job, dismissed: an accepted or running job is cancelled; a finished (successful or "
                "failed) job's results are removed (its results then answer 404); a job already dismissed is "
                "returned unchanged. The job stays in the job list with status 'dismissed'."
            ),
        },
        **problems(404),
    },
)
def dismiss(request: Request, job_id: str) -> dict[str, Any]:
    job, before = store_of(request).dismiss(job_id)
    if job is None:
        raise Problem(404, "no such job", f"no job '{job_id}'")
    if before in ("successful", "failed") and job["process"] != "ingest":
        # outputs of a finished job (an ingest job's scene is shared by every job of that scene: kept)
        remove_job_outputs(settings_of(request), job_id)
    return status_doc(job, base_url(request))


def remove_job_outputs(settings: Settings, job_id: str) -> None:
    """Remove ``DATA/jobs/ID`` (renamed aside first, so that no reader sees it half-removed)."""
    d = settings.jobs_dir / job_id
    if not d.is_dir():
        return
    gone = settings.jobs_dir / f".dismissed-{job_id}-{uuid.uuid4().hex[:6]}"
    try:
        d.rename(gone)
    except OSError:
        gone = d
    shutil.rmtree(gone, ignore_errors=True)
