"""Scene routes: uploads (``POST /scenes``, ingested by a background job) and the scene list."""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Optional

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from sarship.service.common import Problem, base_url, check_text, settings_of, store_of
from sarship.service.inbox_files import scene_key
from sarship.service.openapi import problems
from sarship.service.settings import Settings

router = APIRouter()


@router.post("/scenes", responses=problems(400, 413, 507))
async def upload(request: Request, filename: Optional[str] = None):
    """A scene file, streamed to disk (raw body with ``?filename=``, or multipart field
    ``file``), checked against the size limit as it arrives, named by its SHA-256, and
    ingested to ``DATA/scenes/ID.zarr`` by an ``ingest`` job. The same content uploaded
    twice is the same scene."""
    import hashlib
    import re

    settings = settings_of(request)
    if filename is not None:
        check_text(filename, "'filename'")
    limit = int(settings.max_upload_mb * 2**20)
    clen = request.headers.get("content-length")
    if clen and clen.isdigit() and int(clen) > limit + 2**16:
        raise Problem(413, "too large", f"upload of {int(clen)} bytes exceeds the limit of {limit} bytes")
    settings.uploads_dir.mkdir(parents=True, exist_ok=True)
    tmp = settings.uploads_dir / f".upload-{uuid.uuid4().hex}"
    h = hashlib.sha256()
    n = 0

    def take(chunk: bytes, out) -> None:
        nonlocal n
        n += len(chunk)
        if n > limit:
            raise Problem(413, "too large", f"upload exceeds the limit of {limit} bytes")
        h.update(chunk)
        out.write(chunk)

    try:
        with open(tmp, "wb") as out:
            if request.headers.get("content-type", "").startswith("multipart/form-data"):
                form = await request.form()
                f = form.get("file")
                if f is None or isinstance(f, str):
                    raise Problem(400, "missing file", "multipart upload needs a file field named 'file'")
                filename = filename or f.filename
                while chunk := await f.read(1 << 20):
                    take(chunk, out)
            else:
                async for chunk in request.stream():
                    take(chunk, out)
        if n == 0:
            raise Problem(400, "empty upload", "the upload is empty")
        check_text(filename or "", "the file name")  # (a multipart file name too)
        name = Path(filename or "").name
        ext = "".join(Path(name).suffixes).lower()
        if not name or not re.fullmatch(r"(\.[a-z0-9]{1,8}){1,3}", ext):
            raise Problem(400, "missing filename", "give the file name with its extension (?filename=scene.tif "
                                                   "or the multipart file name): it selects the reader")
        scene_id = scene_key(h.hexdigest())
        final = settings.uploads_dir / f"{scene_id}{ext}"
        if final.exists():
            tmp.unlink()
        else:
            os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    b = base_url(request)
    doc = {"sceneID": scene_id, "sha256": h.hexdigest(), "bytes": n, "filename": name,
           "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}]}
    if (settings.scenes_dir / f"{scene_id}.zarr").exists():
        return JSONResponse({**doc, "status": "ready"}, status_code=200)
    # an ingest of this content already under way (an earlier upload, an inbox pass) is reused
    job, _ = store_of(request).create_ingest({"upload": str(final), "scene_id": scene_id, "filename": name,
                                              "sha256": h.hexdigest(), "bytes": n})
    request.app.state.runner.wake.set()
    return JSONResponse({**doc, "status": "ingesting", "jobID": job["id"],
                         "links": doc["links"] + [{"href": f"{b}/jobs/{job['id']}", "rel": "monitor",
                                                   "type": "application/json"}]},
                        status_code=201, headers={"Location": f"{b}/scenes/{scene_id}"})


def inside_roots(settings: Settings, p: Path) -> bool:
    """Whether scene store ``p``, symlinks followed, lies in ``DATA/scenes`` or an allowed root:
    a store that leads elsewhere (``DATA/scenes/x.zarr -> /elsewhere``) is no scene of this
    service (a job naming it is refused, see ``runner.scene_path``), so it is not listed."""
    try:
        real = p.resolve(strict=True)
    except (OSError, RuntimeError):
        return False
    return any(real == r or r in real.parents for r in settings.roots())


def scene_doc(settings: Settings, scene_id: str, b: str) -> Optional[dict]:
    from sarship.pipeline.scene import open_scene

    p = settings.scenes_dir / f"{scene_id}.zarr"
    if not p.is_dir() or not inside_roots(settings, p):
        return None
    try:
        sc = open_scene(p)
    except Exception as exc:
        return {"sceneID": scene_id, "status": "unreadable", "detail": str(exc)}
    return {"sceneID": scene_id, "status": "ready", "shape": list(sc.shape), "kind": sc.kind,
            "looks": sc.looks, "variables": list(sc.variables), "tile": sc.tile,
            "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}]}


@router.get("/scenes")
def scenes(request: Request):
    """Ready scenes (``DATA/scenes/*.zarr``), then the scenes still ingesting and those whose
    newest ingest failed or was dismissed, listed as ``failed`` with the ``reason`` (the newest
    ingest job of each, found through the store's ingest-job index: the cost does not grow
    with the number of detection jobs). A failed scene is never usable: a job naming it is a
    400."""
    settings = settings_of(request)
    b = base_url(request)
    ready = [scene_doc(settings, p.name[:-5], b) for p in sorted(settings.scenes_dir.glob("*.zarr"))]
    pending: dict[str, dict] = {}
    for j in store_of(request).ingest_jobs(("accepted", "running", "failed", "dismissed")):  # newest first
        sid = j["inputs"].get("scene_id")
        if sid in pending or not sid or (settings.scenes_dir / f"{sid}.zarr").exists():
            continue
        pending[sid] = pending_doc(sid, j, b)
    return {"scenes": [d for d in ready if d] + list(pending.values())}


def pending_doc(scene_id: str, job: dict, b: str = "") -> dict:
    """A scene that is not (yet) in the scene store, from its newest ingest job: ``ingesting``
    (ingest accepted or running) or ``failed`` with the ``reason`` (the ingest job's error; an
    ingest dismissed, or one that succeeded but whose scene store is gone, counts as failed)."""
    links = [{"href": f"{b}/jobs/{job['id']}", "rel": "monitor", "type": "application/json"}]
    if job["status"] in ("accepted", "running"):
        return {"sceneID": scene_id, "status": "ingesting", "jobID": job["id"], "message": job["message"],
                "links": links}
    if job["status"] == "failed":
        reason = job["message"] or "ingest failed"
    elif job["status"] == "dismissed":
        reason = f"its ingest job was dismissed ({job['message']})" if job["message"] else "its ingest job was dismissed"
    else:
        reason = "the scene store is missing (it was removed after its ingest)"
    return {"sceneID": scene_id, "status": "failed", "reason": reason, "jobID": job["id"], "message": reason,
            "links": links}


@router.get("/scenes/{scene_id}")
def scene(request: Request, scene_id: str):
    ok = scene_id.replace("_", "").replace("-", "").isalnum()
    doc = scene_doc(settings_of(request), scene_id, base_url(request)) if ok else None
    if doc is None:
        job = store_of(request).ingest_job_for_scene(scene_id) if ok else None
        if job is not None:
            return pending_doc(scene_id, job, base_url(request))
        raise Problem(404, "no such scene", f"no scene '{scene_id}'")
    return doc
