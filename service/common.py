"""Pieces every route module shares: problem documents (RFC 7807), the request's base URL,
the store, job look-ups and the OGC status and results documents."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse

from sarship.service.settings import Settings
from sarship.service.store import JobStore, iso


class Problem(Exception):
    def __init__(self, status: int, title: str, detail: str):
        self.status, self.title, self.detail = status, title, detail


def problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse({"type": "about:blank", "title": title, "detail": detail, "status": status},
                        status_code=status, media_type="application/problem+json")


def base_url(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def status_doc(job: dict, base: str) -> dict:
    links = [{"href": f"{base}/jobs/{job['id']}", "rel": "self", "type": "application/json", "title": "status"}]
    if job["status"] == "accepted" and job.get("waits_for"):
        links.append({"href": f"{base}/jobs/{job['waits_for']}", "rel": "related", "type": "application/json",
                      "title": "the ingest job of the job's scene: the job runs when it has succeeded"})
    if job["status"] == "successful":
        links.append({"href": f"{base}/jobs/{job['id']}/results", "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                      "type": "application/json", "title": "results"})
    return {"jobID": job["id"], "processID": job["process"], "type": "process", "status": job["status"],
            "message": job["message"], "progress": int(job["progress"]), "created": iso(job["created"]),
            "started": iso(job["started"]), "finished": iso(job["finished"]), "updated": iso(job["updated"]),
            "attempts": int(job["attempts"]), "links": links}


def results_doc(job: dict, base: str) -> dict:
    u = f"{base}/jobs/{job['id']}/results"
    return {"detections": {"href": f"{u}/detections", "type": "application/geo+json"},
            "mask": {"href": f"{u}/mask", "type": "image/tiff; application=geotiff"},
            "metrics": {"href": f"{u}/metrics", "type": "application/json"},
            "stac": {"href": f"{u}/stac", "type": "application/geo+json"}}



def settings_of(request: Request) -> Settings:
    return request.app.state.settings


def store_of(request: Request) -> JobStore:
    return request.app.state.store


def job_or_404(request: Request, job_id: str) -> dict:
    job = store_of(request).get(job_id)
    if job is None:
        raise Problem(404, "no such job", f"no job '{job_id}'")
    return job


def finished(request: Request, job_id: str, ingest_ok: bool = False) -> dict:
    """The job if it finished successfully; else a 404 problem saying why there is no result.
    An ``ingest`` job's only result is its scene: without ``ingest_ok`` it is a 404 too."""
    job = job_or_404(request, job_id)
    if job["status"] != "successful":
        detail = {"failed": f"job failed: {job['message']}", "dismissed": "job was dismissed (its results, if any, are removed)"}.get(
            job["status"], f"result not ready (job is {job['status']})")
        raise Problem(404, "result not ready" if job["status"] not in ("failed", "dismissed") else "no result",
                      detail)
    if job["process"] == "ingest" and not ingest_ok:
        raise Problem(404, "no such result", f"job '{job_id}' ingested a scene; it has no detection products "
                                             f"(the scene is /scenes/{job['inputs'].get('scene_id', '')})")
    return job
