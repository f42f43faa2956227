"""Inbox routes: ``GET /ingest`` (the scheduled ingest's state, for the web page) and
``POST /ingest/scan`` (scan the inboxes now)."""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from sarship.service.common import Problem, settings_of, store_of
from sarship.service.inbox import Inbox
from sarship.service.inbox_store import STATUSES

router = APIRouter()

PassStatus = Literal[STATUSES]  # type: ignore[valid-type]


class IngestSchedule(BaseModel):
    interval_s: float | None = Field(description="seconds between scans (null with a cron schedule)")
    cron: str | None = Field(description="cron expression of the scans, UTC (null with an interval)")


class IngestPass(BaseModel):
    key: str | None = Field(
        description="scene key: the first 16 hex digits of the content's SHA-256 (null while waiting)"
    )
    file: str = Field(description="the file's path in its inbox")
    status: PassStatus = Field(description="waiting, ingesting, ingested, submitted, duplicate, quarantined or failed")
    sceneID: str | None = Field(description="the scene (GET /scenes/{id}) once hashed")
    jobs: list[str] = Field(description="IDs of the detector jobs submitted for this pass")
    ingestJob: str | None = Field(description="ID of the ingest job")
    reason: str | None = Field(description="why it was quarantined, failed or is a duplicate")
    seen: str = Field(description="when the file was first seen (RFC 3339)")
    updated: str = Field(description="when the record last changed (RFC 3339)")


class IngestState(BaseModel):
    enabled: bool = Field(description="whether this API process has inbox folders configured")
    inboxes: list[str]
    schedule: IngestSchedule
    leader: str | None = Field(description="the API process running the loop now (null: none)")
    last_scan: str | None
    next_scan: str | None
    backlog: int = Field(description="files seen but not yet ingested")
    counts: dict[str, int] = Field(description="passes by status")
    passes: list[IngestPass] = Field(description="newest first")


class ScanRequested(BaseModel):
    status: Literal["scan requested"]
    inboxes: list[str]


def inbox_of(request: Request) -> Inbox:
    inbox = getattr(request.app.state, "inbox", None)
    if inbox is None:  # the loop was not started in this process: read the shared store anyway
        inbox = Inbox(settings_of(request), store_of(request), "none")
        request.app.state.inbox = inbox
    return inbox


# (response_model=None: the return annotation is for the type checker; FastAPI would take it as the response model)
@router.get("/ingest", response_model=None, responses={200: {"model": IngestState}})
def ingest_state(
    request: Request, limit: int = Query(100, ge=1, le=1000, description="passes listed, newest first")
) -> dict[str, Any]:
    """``{"enabled", "inboxes", "schedule": {"interval_s", "cron"}, "leader", "last_scan",
    "next_scan", "backlog", "counts": {status: n}, "passes": [{"key", "file", "status",
    "sceneID", "jobs", "ingestJob", "reason", "seen", "updated"}]}``, passes newest first
    (``limit``, 1..1000, default 100). ``leader`` is the API process that runs the loop
    now; ``backlog`` counts the files seen but not yet ingested."""
    return inbox_of(request).status(limit)


@router.post("/ingest/scan", status_code=202, responses={202: {"model": ScanRequested}})
def ingest_scan(request: Request) -> JSONResponse:
    """Ask for a scan of the inboxes now (done by the API process that leads the loop,
    whichever it is); ``409`` when no inbox is configured."""
    inbox = inbox_of(request)
    if not inbox.enabled:
        raise Problem(409, "inbox off", "no inbox folders are configured (SARSHIP_INBOX or sarship serve --inbox)")
    inbox.request_scan()
    return JSONResponse(
        {"status": "scan requested", "inboxes": [str(p) for p in inbox.settings.inbox]}, status_code=202
    )
