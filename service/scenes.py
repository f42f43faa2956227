"""Scene routes: uploads (``POST /scenes``, ingested by a background job), the scene list,
deletion (``DELETE /scenes/{id}``) and the scene retention (``SARSHIP_SCENE_RETENTION_DAYS``)."""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from sarship.service.common import Problem, base_url, check_text, receive_upload, settings_of, store_of
from sarship.service.inbox_files import scene_key
from sarship.service.openapi import problems
from sarship.service.settings import Settings
from sarship.service.store import JobStore, iso

log = logging.getLogger("sarship.service")
router = APIRouter()

#: Scene attributes the service adds at ingest (:func:`label_scene`).
UPLOADED_FILENAME, INGESTED = "uploaded_filename", "ingested"
#: Seconds between two passes of the scene retention (after the one at start-up).
RETENTION_PERIOD_S = 3600.0


@router.post("/scenes", responses=problems(400, 413, 507))
async def upload(request: Request, filename: str | None = None) -> JSONResponse:
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
    try:
        with open(tmp, "wb") as out:
            too_large = f"upload exceeds the limit of {limit} bytes"
            n, form_name = await receive_upload(request, out, limit, h, too_large)
        filename = filename or form_name
        if n == 0:
            raise Problem(400, "empty upload", "the upload is empty")
        check_text(filename or "", "the file name")  # (a multipart file name too)
        name = Path(filename or "").name
        ext = "".join(Path(name).suffixes).lower()
        if not name or not re.fullmatch(r"(\.[a-z0-9]{1,8}){1,3}", ext):
            raise Problem(
                400,
                "missing filename",
                "give the file name with its extension (?filename=scene.tif "
                "or the multipart file name): it selects the reader",
            )
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
    doc: dict[str, Any] = {
        "sceneID": scene_id,
        "sha256": h.hexdigest(),
        "bytes": n,
        "filename": name,
        "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}],
    }
    if (settings.scenes_dir / f"{scene_id}.zarr").exists():
        return JSONResponse({**doc, "status": "ready"}, status_code=200)
    # an ingest of this content already under way (an earlier upload, an inbox pass) is reused
    job, _ = store_of(request).create_ingest(
        {"upload": str(final), "scene_id": scene_id, "filename": name, "sha256": h.hexdigest(), "bytes": n}
    )
    request.app.state.runner.wake.set()
    return JSONResponse(
        {
            **doc,
            "status": "ingesting",
            "jobID": job["id"],
            "links": doc["links"] + [{"href": f"{b}/jobs/{job['id']}", "rel": "monitor", "type": "application/json"}],
        },
        status_code=201,
        headers={"Location": f"{b}/scenes/{scene_id}"},
    )


def inside_roots(settings: Settings, p: Path) -> bool:
    """Whether scene store ``p``, symlinks followed, lies in ``DATA/scenes`` or an allowed root:
    a store that leads elsewhere (``DATA/scenes/x.zarr -> /elsewhere``) is no scene of this
    service (a job naming it is refused, see ``job_inputs.scene_path``), so it is not listed."""
    try:
        real = p.resolve(strict=True)
    except (OSError, RuntimeError):
        return False
    return any(real == r or r in real.parents for r in settings.roots())


def scene_doc(settings: Settings, scene_id: str, b: str) -> dict[str, Any] | None:
    from sarship.pipeline.scene import open_scene

    p = settings.scenes_dir / f"{scene_id}.zarr"
    if not p.is_dir() or not inside_roots(settings, p):
        return None
    try:
        sc = open_scene(p)
    except Exception as exc:
        return {"sceneID": scene_id, "status": "unreadable", "detail": settings.hide_paths(str(exc))}
    return {
        "sceneID": scene_id,
        "status": "ready",
        **scene_names(sc.attrs),
        "ingested": iso(ingested_at(p, sc.attrs)),
        "shape": list(sc.shape),
        "kind": sc.kind,
        "looks": sc.looks,
        "variables": list(sc.variables),
        "tile": sc.tile,
        "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}],
    }


def scene_names(attrs: dict[str, Any]) -> dict[str, str | None]:
    """What a client knows a scene by: ``filename``, the file uploaded or taken from an inbox
    (its base name, recorded at ingest), else the file the scene was ingested from (the
    ingest's ``source``; None when unknown); ``product``, the product's name (a SAFE
    product's, as the reader records it), else that file's name without its extensions;
    ``acquired``, the acquisition (start) time where the product says it (Sentinel-1
    annotation, GeoTIFF metadata), else None."""
    name = attrs.get(UPLOADED_FILENAME)
    if not name:
        src = attrs.get("source")
        name = src[0] if isinstance(src, list) and len(src) == 1 else (src if isinstance(src, str) else None)
    name = Path(str(name)).name if name else None
    product = attrs.get("product") or (name.split(".", 1)[0] if name else None)
    acquired = attrs.get("acquired")
    return {
        "filename": name,
        "product": str(product) if product else None,
        "acquired": str(acquired) if acquired and str(acquired) != "None" else None,
    }


def ingested_at(p: Path, attrs: dict[str, Any]) -> float | None:
    """When scene store ``p`` was ingested (POSIX time): the service's record (``ingested``),
    else the time its metadata was last written."""
    from datetime import datetime

    t = attrs.get(INGESTED)
    if isinstance(t, str):
        try:
            return datetime.fromisoformat(t.replace("Z", "+00:00")).timestamp()
        except ValueError:
            pass
    try:
        return max(p.stat().st_mtime, (p / "zarr.json").stat().st_mtime)
    except OSError:
        return None


def label_scene(store: Path, filename: str | None) -> None:
    """Record on a scene store the service has just ingested the name of the file it came from
    (its base name) and the time (:func:`scene_names`, :func:`ingested_at`)."""
    from sarship.pipeline.scene import finalize_scene

    attrs = {INGESTED: iso(time.time())}
    if filename:
        attrs[UPLOADED_FILENAME] = Path(str(filename)).name
    finalize_scene(store, attrs)


class SceneInUse(Exception):
    """The scene is named by an accepted or running job (or being ingested)."""


def scene_users(settings: Settings, store: JobStore, scene_id: str) -> list[str]:
    """IDs of the accepted or running jobs that name scene ``scene_id`` (by id, or by the path of
    its store), and of its accepted or running ingest job."""
    from sarship.pipeline.errors import InputError
    from sarship.service.job_inputs import scene_path

    target = settings.scenes_dir / f"{scene_id}.zarr"
    out = []
    for j in store.active_jobs():
        if j["process"] == "ingest":
            if j["inputs"].get("scene_id") == scene_id:
                out.append(j["id"])
            continue
        s = j["inputs"].get("scene")
        if not isinstance(s, str):
            continue
        if s.strip() == scene_id:
            out.append(j["id"])
            continue
        try:
            if scene_path(settings, s) == target.resolve():
                out.append(j["id"])
        except (InputError, OSError):
            pass
    return out


def delete_scene(settings: Settings, store: JobStore, scene_id: str) -> bool:
    """Remove scene ``scene_id`` (``DATA/scenes/ID.zarr`` and its uploaded file): renamed aside
    first (no reader sees it half-removed; a job submitted from then on is refused: no such
    scene), then removed. :class:`SceneInUse` (the store put back) when an accepted or running
    job names it; False when there is no such scene."""
    p = settings.scenes_dir / f"{scene_id}.zarr"
    if p.is_symlink() or not p.is_dir():
        return False
    users = scene_users(settings, store, scene_id)
    if users:
        raise SceneInUse(users)
    gone = settings.scenes_dir / f".deleted-{scene_id}-{uuid.uuid4().hex[:6]}"
    try:
        os.rename(p, gone)
    except FileNotFoundError:  # deleted meanwhile
        return False
    users = scene_users(settings, store, scene_id)  # a job accepted between the check and the rename
    if users:
        os.rename(gone, p)
        raise SceneInUse(users)
    shutil.rmtree(gone, ignore_errors=True)
    if settings.uploads_dir.is_dir():
        for f in settings.uploads_dir.glob(f"{scene_id}.*"):
            f.unlink(missing_ok=True)
    return True


def expire_scenes(settings: Settings, store: JobStore, now: float | None = None) -> list[str]:
    """The scene retention: remove the scenes of ``DATA/scenes`` ingested more than
    ``scene_retention_days`` ago (:func:`ingested_at`) that no accepted or running job names;
    also what earlier deletions left renamed aside (a process stopped mid-removal). The ids
    removed (none when the retention is off)."""
    d = settings.scenes_dir
    if not d.is_dir():
        return []
    for stale in d.glob(".deleted-*"):
        shutil.rmtree(stale, ignore_errors=True)
    days = settings.scene_retention_days
    if not days:
        return []
    from sarship.pipeline.scene import open_scene

    cutoff = (time.time() if now is None else now) - days * 86400.0
    removed = []
    for p in sorted(d.glob("*.zarr")):
        if p.is_symlink() or not p.is_dir():
            continue
        try:
            attrs = open_scene(p).attrs
        except Exception:
            attrs = {}
        t = ingested_at(p, attrs)
        if t is None or t >= cutoff:
            continue
        sid = p.name[:-5]
        try:
            if delete_scene(settings, store, sid):
                removed.append(sid)
        except SceneInUse:
            continue
    if removed:
        log.info("scene retention (%g days): removed %s", days, ", ".join(removed))
    return removed


class Retention:
    """A thread that runs :func:`expire_scenes` at start-up and then every
    :data:`RETENTION_PERIOD_S` seconds, until :meth:`stop`."""

    def __init__(self, settings: Settings, store: JobStore, period_s: float = RETENTION_PERIOD_S):
        self.settings, self.store, self.period_s = settings, store, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="sarship-retention", daemon=True)

    def start(self) -> Retention:
        self._thread.start()
        return self

    def _loop(self) -> None:
        while True:
            try:
                expire_scenes(self.settings, self.store)
            except Exception:  # a busy store: the next pass tries again
                log.exception("the scene retention pass failed")
            if self._stop.wait(self.period_s):
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@router.get("/scenes", response_model=None)
def scenes(request: Request) -> dict[str, Any]:
    """Ready scenes (``DATA/scenes/*.zarr``), then the scenes still ingesting and those whose
    newest ingest failed or was dismissed, listed as ``failed`` with the ``reason`` (the newest
    ingest job of each, found through the store's ingest-job index: the cost does not grow
    with the number of detection jobs). A failed scene is never usable: a job naming it is a
    400."""
    settings = settings_of(request)
    b = base_url(request)
    ready = [scene_doc(settings, p.name[:-5], b) for p in sorted(settings.scenes_dir.glob("*.zarr"))]
    pending: dict[str, dict[str, Any]] = {}
    for j in store_of(request).ingest_jobs(("accepted", "running", "failed", "dismissed")):  # newest first
        sid = j["inputs"].get("scene_id")
        if sid in pending or not sid or (settings.scenes_dir / f"{sid}.zarr").exists():
            continue
        pending[sid] = pending_doc(sid, j, b)
    return {"scenes": [d for d in ready if d] + list(pending.values())}


def pending_doc(scene_id: str, job: dict[str, Any], b: str = "") -> dict[str, Any]:
    """A scene that is not (yet) in the scene store, from its newest ingest job: ``ingesting``
    (ingest accepted or running) or ``failed`` with the ``reason`` (the ingest job's error; an
    ingest dismissed, or one that succeeded but whose scene store is gone, counts as failed)."""
    links = [{"href": f"{b}/jobs/{job['id']}", "rel": "monitor", "type": "application/json"}]
    if job["status"] in ("accepted", "running"):
        return {
            "sceneID": scene_id,
            "status": "ingesting",
            "jobID": job["id"],
            "message": job["message"],
            "links": links,
        }
    if job["status"] == "failed":
        reason = job["message"] or "ingest failed"
    elif job["status"] == "dismissed":
        reason = (
            f"its ingest job was dismissed ({job['message']})" if job["message"] else "its ingest job was dismissed"
        )
    else:
        reason = "the scene store is missing (it was removed after its ingest)"
    return {
        "sceneID": scene_id,
        "status": "failed",
        "reason": reason,
        "jobID": job["id"],
        "message": reason,
        "links": links,
    }


@router.delete("/scenes/{scene_id}", response_model=None, responses=problems(404, 409))
def remove_scene(request: Request, scene_id: str) -> dict[str, str]:
    """Delete a scene (``DATA/scenes/ID.zarr`` and its uploaded file); ``409`` while an accepted
    or running job names it or its ingest runs, ``404`` when there is no such scene. The
    ingest and detection jobs of the scene stay in the job list (their results too)."""
    ok = scene_id.replace("_", "").replace("-", "").isalnum()
    try:
        done = ok and delete_scene(settings_of(request), store_of(request), scene_id)
    except SceneInUse as exc:
        ids = exc.args[0]
        raise Problem(
            409,
            "scene in use",
            f"scene '{scene_id}' is used by accepted or running job(s) "
            f"{', '.join(ids[:10])}{' ...' if len(ids) > 10 else ''}: "
            "dismiss them (DELETE /jobs/{id}) or wait until they finish",
        ) from None
    if not done:
        job = store_of(request).active_ingest(scene_id) if ok else None
        if job is not None:
            raise Problem(
                409, "scene in use", f"scene '{scene_id}' is being ingested (job {job['id']}): dismiss that job first"
            )
        raise Problem(404, "no such scene", f"no scene '{scene_id}'")
    return {"sceneID": scene_id, "status": "deleted"}


@router.get("/scenes/{scene_id}", response_model=None)
def scene(request: Request, scene_id: str) -> dict[str, Any]:
    ok = scene_id.replace("_", "").replace("-", "").isalnum()
    doc = scene_doc(settings_of(request), scene_id, base_url(request)) if ok else None
    if doc is None:
        job = store_of(request).ingest_job_for_scene(scene_id) if ok else None
        if job is not None and job["status"] != "successful":
            return pending_doc(scene_id, job, base_url(request))
        # (an ingest that succeeded but whose store is gone: the scene was deleted)
        raise Problem(404, "no such scene", f"no scene '{scene_id}'" + (" (it was deleted)" if job else ""))
    return doc
