"""Pieces every route module shares: problem documents (RFC 7807), the request's base URL,
the store, job look-ups and the OGC status and results documents."""

from __future__ import annotations

import errno
import json
from typing import Any, BinaryIO

from fastapi import Request
from fastapi.responses import JSONResponse

from sarship.service.settings import Settings
from sarship.service.store import JobStore, iso


class Problem(Exception):
    def __init__(self, status: int, title: str, detail: str, headers: dict[str, str] | None = None):
        self.status, self.title, self.detail = status, title, detail
        self.headers = headers


def problem(status: int, title: str, detail: str, headers: dict[str, str] | None = None) -> JSONResponse:
    # a detail may quote the request (a lone surrogate in a JSON string): always encodable as UTF-8
    detail = str(detail).encode("utf-8", "backslashreplace").decode("utf-8")
    return JSONResponse(
        {"type": "about:blank", "title": title, "detail": detail, "status": status},
        status_code=status,
        media_type="application/problem+json",
        headers=headers,
    )


#: Deepest nesting of arrays and objects accepted in a JSON body (an execution body is 2-3 deep).
MAX_JSON_DEPTH = 32


def json_depth(raw: bytes) -> int:
    """The deepest nesting of ``[``/``{`` in JSON text ``raw`` (brackets inside strings do not
    count), found in linear time without parsing, so that a body nested 100000 deep is refused
    before ``json.loads`` recurses into it."""
    import numpy as np

    b = np.frombuffer(raw, np.uint8)
    if not b.size:
        return 0
    pos = np.arange(b.size)
    bs = b == ord("\\")
    # backslashes right before each character: odd means the character is escaped
    last_other = np.maximum.accumulate(np.where(bs, -1, pos))
    run_before = np.empty(b.size, np.int64)
    run_before[0] = 0
    run_before[1:] = pos[:-1] - last_other[:-1]
    quote = (b == ord('"')) & (run_before % 2 == 0)
    inside = (np.cumsum(quote) % 2 == 1) | quote
    step = np.zeros(256, np.int32)
    step[[ord("["), ord("{")]], step[[ord("]"), ord("}")]] = 1, -1
    return int(max(np.cumsum(np.where(inside, 0, step[b])).max(), 0))


def parse_json_body(raw: bytes) -> Any:
    """The JSON document of a request body (empty: ``None``); a 400 problem when it is not JSON,
    is nested deeper than :data:`MAX_JSON_DEPTH`, or holds a string that cannot be a name
    (:func:`check_text`)."""
    if not raw:
        return None
    if json_depth(raw) > MAX_JSON_DEPTH:
        raise Problem(400, "bad request", f"the JSON body is nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        doc = json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError):
        raise Problem(400, "bad request", "the body is not valid JSON") from None
    _check_strings(doc, "body")
    return doc


def check_text(value: str, what: str) -> None:
    """A 400 problem when ``value`` holds a NUL character or an unpaired UTF-16 surrogate (valid
    in a JSON string, but no file name, no store key and no UTF-8 text can hold it)."""
    if "\x00" in value:
        raise Problem(400, "invalid input", f"{what} contains a NUL character")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise Problem(400, "invalid input", f"{what} contains an unpaired surrogate (not valid Unicode text)") from None


def _check_strings(doc: Any, where: str) -> None:
    if isinstance(doc, str):
        check_text(doc, where)
    elif isinstance(doc, dict):
        for k, v in doc.items():
            check_text(k, f"{where}: a key")
            _check_strings(v, f"{where}.{k}")
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            _check_strings(v, f"{where}[{i}]")


#: errno values of a write that failed for want of space (EFBIG: a file-size limit, RLIMIT_FSIZE)
_NO_SPACE = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}


def storage_problem(exc: BaseException) -> Problem | None:
    """The problem for a failure of the data folder's storage: ``507 insufficient storage`` for a
    disk (or quota, or file-size limit) that is full, from a file write (``OSError``) or from the
    SQLite job store (``database or disk is full``, or a write I/O error); ``503`` with
    ``Retry-After`` for a job store that is busy or locked. ``None`` for anything else (a bug)."""
    import sqlite3

    if isinstance(exc, OSError) and exc.errno in _NO_SPACE:
        return Problem(507, "insufficient storage", f"the server's data folder is full: {exc.strerror or exc}")
    if isinstance(exc, sqlite3.OperationalError):
        code = getattr(exc, "sqlite_errorcode", None)
        name = getattr(exc, "sqlite_errorname", "") or ""
        text = str(exc)
        if (
            code == sqlite3.SQLITE_FULL
            or "disk is full" in text
            or name.startswith("SQLITE_IOERR_WRITE")
            or name in ("SQLITE_IOERR_FSYNC", "SQLITE_IOERR_TRUNCATE")
        ):
            return Problem(507, "insufficient storage", f"the job store cannot be written: {text}")
        if code in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED) or "locked" in text or "busy" in text:
            return Problem(503, "store busy", f"the job store is busy: {text}; try again", {"Retry-After": "1"})
    return None


def base_url(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def status_doc(job: dict[str, Any], base: str) -> dict[str, Any]:
    links = [{"href": f"{base}/jobs/{job['id']}", "rel": "self", "type": "application/json", "title": "status"}]
    if job["status"] == "accepted" and job.get("waits_for"):
        links.append(
            {
                "href": f"{base}/jobs/{job['waits_for']}",
                "rel": "related",
                "type": "application/json",
                "title": "the ingest job of the job's scene: the job runs when it has succeeded",
            }
        )
    if job["status"] == "successful":
        links.append(
            {
                "href": f"{base}/jobs/{job['id']}/results",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                "type": "application/json",
                "title": "results",
            }
        )
    return {
        "jobID": job["id"],
        "processID": job["process"],
        "type": "process",
        "status": job["status"],
        "message": job["message"],
        "progress": int(job["progress"]),
        "created": iso(job["created"]),
        "started": iso(job["started"]),
        "finished": iso(job["finished"]),
        "updated": iso(job["updated"]),
        "attempts": int(job["attempts"]),
        "links": links,
    }


def results_doc(job: dict[str, Any], base: str) -> dict[str, Any]:
    """The results document of a finished detector job: its products by reference;
    ``ais_unmatched`` too when the job was given AIS files (its outputs name the file)."""
    u = f"{base}/jobs/{job['id']}/results"
    doc = {
        "detections": {"href": f"{u}/detections", "type": "application/geo+json"},
        "mask": {"href": f"{u}/mask", "type": "image/tiff; application=geotiff"},
        "metrics": {"href": f"{u}/metrics", "type": "application/json"},
        "stac": {"href": f"{u}/stac", "type": "application/geo+json"},
    }
    outputs = (job.get("result") or {}).get("outputs") or {}
    if "ais_unmatched.geojson" in outputs:
        doc["ais_unmatched"] = {"href": f"{u}/ais_unmatched", "type": "application/geo+json"}
    return doc


def settings_of(request: Request) -> Settings:
    settings: Settings = request.app.state.settings  # set by create_app
    return settings


def store_of(request: Request) -> JobStore:
    store: JobStore = request.app.state.store  # set by the lifespan
    return store


def job_or_404(request: Request, job_id: str) -> dict[str, Any]:
    job = store_of(request).get(job_id)
    if job is None:
        raise Problem(404, "no such job", f"no job '{job_id}'")
    return job


def finished(request: Request, job_id: str, ingest_ok: bool = False) -> dict[str, Any]:
    """The job if it finished successfully; else a 404 problem saying why there is no result.
    An ``ingest`` job's only result is its scene: without ``ingest_ok`` it is a 404 too."""
    job = job_or_404(request, job_id)
    if job["status"] != "successful":
        detail = {
            "failed": f"job failed: {job['message']}",
            "dismissed": "job was dismissed (its results, if any, are removed)",
        }.get(job["status"], f"result not ready (job is {job['status']})")
        raise Problem(404, "result not ready" if job["status"] not in ("failed", "dismissed") else "no result", detail)
    if job["process"] == "ingest" and not ingest_ok:
        raise Problem(
            404,
            "no such result",
            f"job '{job_id}' ingested a scene; it has no detection products "
            f"(the scene is /scenes/{job['inputs'].get('scene_id', '')})",
        )
    return job


async def receive_upload(request: Request, out: BinaryIO, limit: int, h: Any, too_large: str) -> tuple[int, str | None]:
    """Stream a request's file (raw body, or multipart field ``file``) into ``out``, fed to the
    hash ``h`` as it arrives: its byte count and the multipart file name (None for a raw body).
    A 413 problem with ``too_large`` as its detail once more than ``limit`` bytes arrived; a 400
    for a multipart body without its ``file``. The uploads of scenes and AIS files share it."""
    n = 0

    def take(chunk: bytes) -> None:
        nonlocal n
        n += len(chunk)
        if n > limit:
            raise Problem(413, "too large", too_large)
        h.update(chunk)
        out.write(chunk)

    if request.headers.get("content-type", "").startswith("multipart/form-data"):
        form = await request.form()
        f = form.get("file")
        if f is None or isinstance(f, str):
            raise Problem(400, "missing file", "multipart upload needs a file field named 'file'")
        while chunk := await f.read(1 << 20):
            take(chunk)
        return n, f.filename
    async for chunk in request.stream():
        take(chunk)
    return n, None
