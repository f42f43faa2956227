"""Process routes (OGC API - Processes core): the detectors as processes (``GET /processes``,
``GET /processes/{id}``) and their execution (``POST /processes/{id}/execution``).

An execution is validated once (:func:`~sarship.service.job_inputs.validate_inputs`) and the
job store keeps that normalized request; the runner runs it as stored. ``Prefer:
respond-sync`` waits for the job on the event loop (:func:`wait_sync`), up to
``max_sync_waits`` such requests at a time.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import anyio
from fastapi import APIRouter, Header, Path, Request
from fastapi.responses import JSONResponse

from sarship.pipeline import __version__, detectors
from sarship.service.common import Problem, base_url, parse_json_body, results_doc, settings_of, status_doc, store_of
from sarship.service.job_inputs import pending_ingest, validate_inputs
from sarship.service.openapi import (
    EXECUTE_BODY,
    PREFER_DOC,
    ProcessDescription,
    ProcessList,
    Results,
    StatusInfo,
    problems,
)
from sarship.service.store import FINAL, JobStore
from sarship.workers.request import DEVICES, MAX_AIS_FILES

router = APIRouter()

#: The ``ais`` input: one AIS id or path, or a list of them.
AIS_SCHEMA: dict[str, Any] = {
    "oneOf": [
        {"type": "null"},
        {"type": "string", "minLength": 1},
        {"type": "array", "items": {"type": "string", "minLength": 1}, "maxItems": MAX_AIS_FILES},
    ]
}
#: Inputs every process takes besides its detector parameters.
COMMON_INPUTS = {
    "scene": {
        "title": "scene",
        "description": "scene id (uploaded) or path of a scene store inside an allowed folder",
        "schema": {"type": "string"},
        "minOccurs": 1,
        "maxOccurs": 1,
    },
    "device": {
        "title": "device",
        "description": "where tiles run: auto (GPU workers if any), gpu or cpu",
        "schema": {"type": "string", "enum": list(DEVICES), "default": "auto"},
        "minOccurs": 0,
        "maxOccurs": 1,
    },
    "ais": {
        "title": "AIS files",
        "description": "AIS files matched to the detections (docs/ais.md): uploaded AIS ids (POST /ais) or "
        "paths of files inside an allowed folder; each detection gets 'ais' and 'dark', and the "
        "vessels that matched nothing are the result ais_unmatched",
        "schema": AIS_SCHEMA,
        "minOccurs": 0,
        "maxOccurs": 1,
    },
}
PROCESS_PARAM = Path(description="the process (detector) id", json_schema_extra={"enum": detectors.names()})
LOCATION_HEADER = {"description": "the job's status URL", "schema": {"type": "string"}}


def process_summary(name: str, base: str) -> dict[str, Any]:
    """The process list's entry of detector ``name``."""
    spec = detectors.get(name)
    return {
        "id": name,
        "title": name,
        "description": spec.summary,
        "version": __version__,
        "jobControlOptions": ["async-execute", "sync-execute", "dismiss"],
        "outputTransmission": ["reference"],
        "links": [{"href": f"{base}/processes/{name}", "rel": "self", "type": "application/json"}],
    }


def process_description(name: str, base: str) -> dict[str, Any]:
    """The process description of detector ``name``: its inputs (the common ones and its
    parameter model's JSON schema) and outputs."""
    spec = detectors.get(name)
    schema = spec.params.model_json_schema()
    defs = schema.get("$defs", {})
    inputs: dict[str, Any] = dict(COMMON_INPUTS)
    for key, prop in schema.get("properties", {}).items():
        prop = dict(prop)
        if defs:
            prop["$defs"] = defs
        inputs[key] = {
            "title": prop.get("title", key),
            "description": prop.get("description", ""),
            "schema": prop,
            "minOccurs": 0,
            "maxOccurs": 1,
        }
    return {
        **process_summary(name, base),
        "reference": spec.reference,
        "inputs": inputs,
        "outputs": {
            k: {"title": k, "schema": {"type": "string", "contentMediaType": v["type"]}}
            # (ais_unmatched: with the input 'ais')
            for k, v in results_doc({"id": "ID", "result": {"outputs": {"ais_unmatched.geojson": ""}}}, base).items()
        },
    }


def known_process(name: str) -> None:
    """A 404 problem unless ``name`` is a detector (process)."""
    if name not in detectors.names():
        raise Problem(404, "no such process", f"no process '{name}' (known: {', '.join(detectors.names())})")


@router.get("/processes", response_model=None, responses={200: {"model": ProcessList}})
def processes(request: Request) -> dict[str, Any]:
    b = base_url(request)
    return {
        "processes": [process_summary(n, b) for n in detectors.names()],
        "links": [{"href": f"{b}/processes", "rel": "self", "type": "application/json"}],
    }


@router.get(
    "/processes/{process_id}", response_model=None, responses={200: {"model": ProcessDescription}, **problems(404)}
)
def process(request: Request, process_id: str = PROCESS_PARAM) -> dict[str, Any]:
    known_process(process_id)
    return process_description(process_id, base_url(request))


@router.post(
    "/processes/{process_id}/execution",
    status_code=201,
    responses={
        201: {
            "model": StatusInfo,
            "description": "job accepted (asynchronous execution); a job "
            "for a scene id whose upload is still being "
            "ingested waits for that ingest job",
            "headers": {"Location": LOCATION_HEADER},
        },
        200: {
            "model": Results,
            "description": "the results document (Prefer: respond-sync)",
            "headers": {"Location": LOCATION_HEADER},
        },
        **problems(400, 404, 413, 422, 503, 507),
    },
    openapi_extra={"requestBody": EXECUTE_BODY},
)
async def execute(
    request: Request,
    process_id: str = PROCESS_PARAM,
    prefer: str | None = Header(
        None, alias="Prefer", description=PREFER_DOC, examples=["respond-async", "respond-sync"]
    ),
) -> JSONResponse:
    known_process(process_id)
    settings = settings_of(request)
    # (the body is at most max_body_kb here: service/limits.py); nesting depth checked before parsing
    body = parse_json_body(await request.body())
    st = store_of(request)
    inputs = validate_inputs(settings, process_id, body, st)
    prefer = (prefer or "").lower()
    if "respond-sync" not in prefer:
        return await submit(request, st, process_id, inputs, prefer)
    state = request.app.state
    if state.sync_waits >= settings.max_sync_waits:
        # each waiting request holds a connection: beyond the cap, before any job is created
        raise Problem(
            503,
            "too many synchronous executions",
            f"{state.sync_waits} 'Prefer: respond-sync' executions are waiting "
            f"(at most {settings.max_sync_waits}, setting max_sync_waits): try again later, "
            "or execute asynchronously and poll the job",
            {"Retry-After": "10"},
        )
    state.sync_waits += 1  # (taken before the job is created: the cap holds under a burst)
    try:
        job = await create_job(request, st, process_id, inputs)
        job = await wait_sync(request, st, job, settings.sync_timeout_s)
    finally:
        state.sync_waits -= 1
    b = base_url(request)
    if job["status"] == "successful":
        return JSONResponse(
            results_doc(job, b), headers={"Preference-Applied": "respond-sync", "Location": f"{b}/jobs/{job['id']}"}
        )
    if job["status"] in FINAL:
        raise Problem(422, f"job {job['status']}", job["message"] or job["status"])
    return JSONResponse(status_doc(job, b), status_code=201, headers={"Location": f"{b}/jobs/{job['id']}"})


async def create_job(request: Request, st: JobStore, process_id: str, inputs: dict[str, Any]) -> dict[str, Any]:
    """The new job of the validated ``inputs``, committed to the store (waiting for its scene's
    ingest job when that still runs); the runner is woken."""
    settings = settings_of(request)
    waits_for, message = None, ""
    if not (settings.scenes_dir / f"{str(inputs['scene']).strip()}.zarr").exists():
        dep = pending_ingest(settings, st, str(inputs["scene"]))
        if dep is not None:  # the scene's upload is still being ingested: run after it
            waits_for = dep["id"]
            message = f"waiting for scene {str(inputs['scene']).strip()} (ingest job {dep['id']})"
    # the commit waits on the disk (fsync): off the event loop, so status polls are not held up
    job = await anyio.to_thread.run_sync(lambda: st.create(process_id, inputs, waits_for, message))
    request.app.state.metrics.requests.labels(process_id).inc()
    request.app.state.runner.wake.set()
    return job


async def submit(request: Request, st: JobStore, process_id: str, inputs: dict[str, Any], prefer: str) -> JSONResponse:
    """An asynchronous execution: the job created, its status document (201, ``Location``)."""
    job = await create_job(request, st, process_id, inputs)
    b = base_url(request)
    headers = {"Location": f"{b}/jobs/{job['id']}"}
    if "respond-async" in prefer:
        headers["Preference-Applied"] = "respond-async"
    return JSONResponse(status_doc(job, b), status_code=201, headers=headers)


async def wait_sync(request: Request, store: JobStore, job: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Wait for a job of a ``Prefer: respond-sync`` execution on the event loop (no worker
    thread is held): polls the store (a primary-key read) until the job is final, ``timeout``
    has passed, the client has gone, or the server is shutting down (SIGTERM); the job row
    then (the caller answers 201 with its status unless it is final)."""
    t_end = time.monotonic() + timeout
    while True:
        now = store.get(job["id"]) or job
        if now["status"] in FINAL or time.monotonic() > t_end or request.app.state.should_exit():
            return now
        if await request.is_disconnected():
            return now
        await asyncio.sleep(0.2)
