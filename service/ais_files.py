"""AIS file routes: uploads (``POST /ais``), the list (``GET /ais``), one upload
(``GET /ais/{id}``) and its deletion (``DELETE /ais/{id}``); and the job input ``ais``
(:func:`ais_paths`): uploaded ids or files inside the allowed folders (docs/ais.md, "Service").

An upload is streamed to a temporary file in ``DATA/ais`` (checked against ``max_ais_upload_mb``
as it arrives), its first MiB checked to be AIS (a CSV header or NMEA sentences, or a compressed
stream the run decompresses), then renamed to ``DATA/ais/ID`` (``ID``: the first 16 hex digits
of its SHA-256: the same content uploaded twice is the same file) beside its record
``ID.json`` (file name, bytes, SHA-256, time).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
import uuid
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from sarship.pipeline.errors import InputError
from sarship.service.common import Problem, base_url, check_text, receive_upload, settings_of, store_of
from sarship.service.openapi import problems
from sarship.service.settings import Settings
from sarship.service.store import JobStore, iso

router = APIRouter()

#: An uploaded AIS file's id: the first 16 hex digits of its SHA-256.
AIS_ID = re.compile(r"[0-9a-f]{16}")
#: Longest file name recorded for an upload.
MAX_NAME = 255


def ais_file(settings: Settings, ais_id: str) -> Path:
    return settings.ais_dir / ais_id


def _record(settings: Settings, ais_id: str) -> dict[str, Any] | None:
    try:
        rec: dict[str, Any] = json.loads((settings.ais_dir / f"{ais_id}.json").read_text())
    except (OSError, ValueError):
        return None
    return rec if ais_file(settings, ais_id).is_file() else None


def _doc(rec: dict[str, Any], b: str) -> dict[str, Any]:
    return {**rec, "links": [{"href": f"{b}/ais/{rec['aisID']}", "rel": "self", "type": "application/json"}]}


def _upload_name(filename: str | None) -> str:
    """The recorded name of an upload: the base name of ``filename`` (checked), else ``ais``."""
    if filename is None or not filename.strip():
        return "ais"
    check_text(filename, "the file name")
    name = Path(filename.replace("\\", "/")).name.strip()
    if not name or name in (".", "..") or len(name) > MAX_NAME or any(ord(c) < 32 for c in name):
        raise Problem(
            400, "invalid input", f"bad file name {filename[:80]!r}: a base name of at most {MAX_NAME} characters"
        )
    return name


def check_head(path: Path, name: str) -> None:
    """A 400 problem unless the file's first MiB is AIS as the reader recognises it (a CSV
    header with MMSI, time, longitude and latitude columns, or NMEA sentences); a compressed
    stream (gzip, zstd, zip) passes: the run decompresses and checks it."""
    from sarship.pipeline.ais.formats import check_ais_head

    try:
        check_ais_head(path, name)
    except InputError as exc:
        raise Problem(400, "not AIS", str(exc)) from None


@router.post(
    "/ais",
    status_code=201,
    responses={
        201: {"description": "a new AIS file, kept", "headers": {"Location": {"schema": {"type": "string"}}}},
        200: {"description": "the same content was uploaded before: that file"},
        **problems(400, 413, 507),
    },
)
async def upload_ais(request: Request, filename: str | None = None) -> JSONResponse:
    """An AIS file (CSV or NMEA, possibly gzip/zstd/zip compressed: docs/ais.md), streamed to
    disk (raw body with optional ``?filename=``, or multipart field ``file``), checked against
    ``max_ais_upload_mb`` as it arrives and to be AIS from its first MiB, and kept as
    ``DATA/ais/ID``; a job names it by ``ID`` in its ``ais`` input. The same content uploaded
    twice is the same file (200; 201 when new)."""
    settings = settings_of(request)
    if filename is not None:
        check_text(filename, "'filename'")
    limit = int(settings.max_ais_upload_mb * 2**20)
    clen = request.headers.get("content-length")
    if clen and clen.isdigit() and int(clen) > limit + 2**16:
        raise Problem(
            413,
            "too large",
            f"AIS upload of {int(clen)} bytes exceeds the limit of {limit} bytes (setting max_ais_upload_mb)",
        )
    d = settings.ais_dir
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".upload-{uuid.uuid4().hex}"
    h = hashlib.sha256()
    try:
        with open(tmp, "wb") as out:
            too_large = f"AIS upload exceeds the limit of {limit} bytes (setting max_ais_upload_mb)"
            n, form_name = await receive_upload(request, out, limit, h, too_large)
        if n == 0:
            raise Problem(400, "empty upload", "the upload is empty")
        name = _upload_name(filename or form_name)
        check_head(tmp, name)
        ais_id = h.hexdigest()[:16]
        final = ais_file(settings, ais_id)
        rec = {"aisID": ais_id, "filename": name, "bytes": n, "sha256": h.hexdigest(), "uploaded": iso(time.time())}
        new = _record(settings, ais_id) is None
        if new:
            os.replace(tmp, final)
            rtmp = d / f".record-{uuid.uuid4().hex}"
            rtmp.write_text(json.dumps(rec))
            os.replace(rtmp, d / f"{ais_id}.json")
        else:
            tmp.unlink()
            rec = _record(settings, ais_id) or rec
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    b = base_url(request)
    return JSONResponse(_doc(rec, b), status_code=201 if new else 200, headers={"Location": f"{b}/ais/{ais_id}"})


@router.get("/ais", response_model=None)
def list_ais(request: Request) -> dict[str, Any]:
    """The uploaded AIS files, by id."""
    settings = settings_of(request)
    b = base_url(request)
    recs = (_record(settings, p.stem) for p in sorted(settings.ais_dir.glob("*.json")) if AIS_ID.fullmatch(p.stem))
    return {"ais": [_doc(r, b) for r in recs if r is not None]}


@router.get("/ais/{ais_id}", response_model=None, responses=problems(404))
def get_ais(request: Request, ais_id: str) -> dict[str, Any]:
    rec = _record(settings_of(request), ais_id) if AIS_ID.fullmatch(ais_id) else None
    if rec is None:
        raise Problem(404, "no such AIS file", f"no uploaded AIS file '{ais_id}'")
    return _doc(rec, base_url(request))


def ais_users(settings: Settings, store: JobStore, path: Path) -> list[str]:
    """IDs of the accepted or running detector jobs whose ``ais`` names ``path`` (the stored
    inputs hold resolved absolute paths)."""
    target = str(path.resolve())
    return [j["id"] for j in store.active_jobs() if target in (j["inputs"].get("ais") or ())]


@router.delete("/ais/{ais_id}", response_model=None, responses=problems(404, 409))
def delete_ais(request: Request, ais_id: str) -> dict[str, str]:
    """Delete an uploaded AIS file; ``409`` while an accepted or running job names it. Finished
    jobs keep their results (``run.json`` names the file it read)."""
    settings = settings_of(request)
    if not AIS_ID.fullmatch(ais_id) or _record(settings, ais_id) is None:
        raise Problem(404, "no such AIS file", f"no uploaded AIS file '{ais_id}'")
    store, path = store_of(request), ais_file(settings, ais_id)
    _not_in_use(ais_id, ais_users(settings, store, path))
    # the record renamed aside first (a job submitted from then on is refused: no such id), then
    # the jobs checked again (one accepted between the check and the rename keeps the file)
    aside = settings.ais_dir / f".deleted-{ais_id}-{uuid.uuid4().hex[:6]}.json"
    try:
        os.rename(settings.ais_dir / f"{ais_id}.json", aside)
    except FileNotFoundError:  # deleted meanwhile
        raise Problem(404, "no such AIS file", f"no uploaded AIS file '{ais_id}'") from None
    users = ais_users(settings, store, path)
    if users:
        os.rename(aside, settings.ais_dir / f"{ais_id}.json")
        _not_in_use(ais_id, users)
    path.unlink(missing_ok=True)
    aside.unlink(missing_ok=True)
    return {"aisID": ais_id, "status": "deleted"}


def _not_in_use(ais_id: str, users: list[str]) -> None:
    if users:
        raise Problem(
            409,
            "AIS file in use",
            f"AIS file '{ais_id}' is named by accepted or running job(s) "
            f"{', '.join(users[:10])}{' ...' if len(users) > 10 else ''}: dismiss them or wait until they finish",
        )


def ais_paths(settings: Settings, names: tuple[str, ...]) -> tuple[str, ...]:
    """The job input ``ais`` resolved: each entry an uploaded AIS id (``DATA/ais/ID``), or a
    path (absolute, or relative to the scene folder) of a regular file inside an allowed
    folder; the resolved absolute paths, in order (a file named twice is read once). A
    one-line :class:`InputError` (a 400) otherwise."""
    # the inbox's AIS folder too: its passes' jobs name its files (service/inbox.py)
    roots = [
        *settings.roots(),
        settings.ais_dir.resolve(),
        *([settings.inbox_ais.resolve()] if settings.inbox_ais else []),
    ]
    out: list[str] = []
    for s0 in names:
        s = s0.strip()
        if "://" in s:
            raise InputError(f"input 'ais': only local files and uploaded AIS ids are accepted, got '{s}'")
        if AIS_ID.fullmatch(s):
            if _record(settings, s) is None:
                raise InputError(f"input 'ais': no uploaded AIS file '{s}' (POST /ais; GET /ais lists them)")
            cand = ais_file(settings, s)
        else:
            cand = Path(s) if Path(s).is_absolute() else settings.scenes_dir / s
        try:
            real = cand.resolve(strict=True)
        except (OSError, RuntimeError):
            raise InputError(
                f"input 'ais': no file '{s}' (an uploaded AIS id, or a path inside the allowed scene folders)"
            ) from None
        if not any(r in real.parents for r in roots):
            raise InputError(f"input 'ais': '{s}' is outside the allowed scene folders")
        if not real.is_file():
            raise InputError(f"input 'ais': '{s}' is not a regular file")
        if str(real) not in out:
            out.append(str(real))
    return tuple(out)
