"""The FastAPI application: OGC API - Processes 1.0 shaped job API (CONTRACT.md "REST API").

``create_app(settings)`` opens the job store, connects to Dask (a local cluster, or
``settings.scheduler``) and starts the job runner for the application's lifetime.
Every error is a problem document (RFC 7807: ``type``, ``title``, ``detail``, ``status``);
bad input is always a ``4xx``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import uuid
from pathlib import Path
from typing import Any, Optional

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from pipeline import __version__, detectors
from pipeline.errors import InputError
from service.metrics import Metrics
from service.runner import INGEST, Runner, scene_path, wait_final
from service.settings import Settings
from service.store import FINAL, JobStore, iso

log = logging.getLogger("sarship.service")

OGC = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
CONFORMANCE = [OGC + c for c in ("core", "json", "job-list", "dismiss", "oas30")]
#: Inputs every process takes besides its detector parameters.
COMMON_INPUTS = {
    "scene": {"title": "scene", "description": "scene id (uploaded) or path of a scene store inside an allowed folder",
              "schema": {"type": "string"}, "minOccurs": 1, "maxOccurs": 1},
    "device": {"title": "device", "description": "where tiles run: auto (GPU workers if any), gpu or cpu",
               "schema": {"type": "string", "enum": ["auto", "cpu", "gpu"], "default": "auto"},
               "minOccurs": 0, "maxOccurs": 1},
}
RESERVED = ("scene", "device", "channel")


class Problem(Exception):
    def __init__(self, status: int, title: str, detail: str):
        self.status, self.title, self.detail = status, title, detail


def problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse({"type": "about:blank", "title": title, "detail": detail, "status": status},
                        status_code=status, media_type="application/problem+json")


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def status_doc(job: dict, base: str) -> dict:
    links = [{"href": f"{base}/jobs/{job['id']}", "rel": "self", "type": "application/json", "title": "status"}]
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
            "metrics": {"href": f"{u}/metrics", "type": "application/json"}}


def process_summary(name: str, base: str) -> dict:
    spec = detectors.get(name)
    return {"id": name, "title": name, "description": spec.summary, "version": __version__,
            "jobControlOptions": ["async-execute", "sync-execute", "dismiss"],
            "outputTransmission": ["reference"],
            "links": [{"href": f"{base}/processes/{name}", "rel": "self", "type": "application/json"}]}


def process_description(name: str, base: str) -> dict:
    spec = detectors.get(name)
    schema = spec.params.model_json_schema()
    defs = schema.get("$defs", {})
    inputs: dict[str, Any] = dict(COMMON_INPUTS)
    for key, prop in schema.get("properties", {}).items():
        prop = dict(prop)
        if defs:
            prop["$defs"] = defs
        inputs[key] = {"title": prop.get("title", key), "description": prop.get("description", ""),
                       "schema": prop, "minOccurs": 0, "maxOccurs": 1}
    return {**process_summary(name, base), "reference": spec.reference, "inputs": inputs,
            "outputs": {k: {"title": k, "schema": {"type": "string", "contentMediaType": v["type"]}}
                        for k, v in results_doc({"id": "ID"}, base).items()}}


def known_process(name: str) -> None:
    """A 404 problem unless ``name`` is a detector (process)."""
    if name not in detectors.names():
        raise Problem(404, "no such process", f"no process '{name}' (known: {', '.join(detectors.names())})")


def validate_inputs(settings: Settings, name: str, body: Any) -> dict:
    """The job's inputs, validated now (so that bad input is a 400, not a failed job)."""
    from workers.run import parse_settings

    if not isinstance(body, dict) or not isinstance(body.get("inputs"), dict):
        raise Problem(400, "bad request", "the body must be a JSON object {\"inputs\": {\"scene\": ..., ...}}")
    inputs = dict(body["inputs"])
    if "scene" not in inputs:
        raise Problem(400, "missing input", "input 'scene' is required (a scene id or a path)")
    device = inputs.get("device", "auto")
    if device not in ("auto", "cpu", "gpu"):
        raise Problem(400, "invalid input", f"input 'device' must be auto, cpu or gpu, got {device!r}")
    spec = detectors.get(name)
    params = {k: v for k, v in inputs.items() if k not in RESERVED}
    for k, v in params.items():
        if isinstance(v, (dict, list)):
            raise Problem(400, "invalid input", f"parameter '{k}' must be a number or a string, got {type(v).__name__}")
    try:
        parse_settings(spec, params)
        scene_path(settings, inputs["scene"])
    except InputError as exc:
        raise Problem(400, "invalid input", str(exc)) from None
    return inputs


def create_app(settings: Optional[Settings] = None, client=None) -> FastAPI:
    settings = settings or Settings()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.data.mkdir(parents=True, exist_ok=True)
        settings.scenes_dir.mkdir(parents=True, exist_ok=True)
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        store = JobStore(settings.db_path)
        metrics = Metrics()
        metrics.watch_store(store)
        app.state.metrics = metrics
        with contextlib.ExitStack() as stack:
            c = client
            if c is None:
                from workers.cluster import connect

                c = stack.enter_context(connect(settings.scheduler, n_workers=settings.workers,
                                                dashboard_address=":0", echo=True))
            runner = Runner(settings, store, c, metrics)
            runner.start()
            app.state.store, app.state.client, app.state.runner = store, c, runner
            try:
                yield
            finally:
                runner.stop()

    app = FastAPI(title="sarship", version=__version__, lifespan=lifespan,
                  description="Ship detection in SAR scenes: OGC API - Processes shaped job API")
    app.state.settings = settings

    open_paths = ("/livez", "/readyz", "/metrics")

    @app.middleware("http")
    async def _auth(request: Request, call_next):
        """Bearer tokens (settings.tokens): required for POST/DELETE, and for reads when
        ``protect_reads``; 401 without a token, 403 with a wrong one."""
        if settings.tokens and request.url.path not in open_paths and (
                request.method not in ("GET", "HEAD", "OPTIONS") or settings.protect_reads):
            auth = request.headers.get("authorization", "")
            if not auth.lower().startswith("bearer "):
                r = problem(401, "unauthorized", "this request needs 'Authorization: Bearer TOKEN'")
                r.headers["WWW-Authenticate"] = "Bearer"
                return r
            import hmac

            tok = auth[7:].strip()
            if not any(hmac.compare_digest(tok, t) for t in settings.tokens):
                return problem(403, "forbidden", "the token is not valid")
        return await call_next(request)

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        return problem(exc.status, exc.title, exc.detail)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        title = {404: "not found", 405: "method not allowed"}.get(exc.status_code, "error")
        return problem(exc.status_code, title, str(exc.detail))

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        # a bug, not bad input: still a problem document, and logged with its traceback
        log.exception("internal error on %s %s", request.method, request.url.path)
        return problem(500, "internal error", f"{type(exc).__name__}: {exc}")

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        parts = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
            parts.append(f"'{loc}': {e.get('msg', 'invalid')}" if loc else e.get("msg", "invalid"))
        return problem(400, "invalid request", "; ".join(parts))

    def store(request: Request) -> JobStore:
        return request.app.state.store

    def job_or_404(request: Request, job_id: str) -> dict:
        job = store(request).get(job_id)
        if job is None:
            raise Problem(404, "no such job", f"no job '{job_id}'")
        return job

    @app.get("/")
    def landing(request: Request):
        b = _base(request)
        return {"title": "sarship", "description": "Ship detection in SAR scenes", "version": __version__,
                "links": [{"href": f"{b}/", "rel": "self", "type": "application/json"},
                          {"href": f"{b}/openapi.json", "rel": "service-desc",
                           "type": "application/vnd.oai.openapi+json;version=3.0"},
                          {"href": f"{b}/conformance", "rel": "http://www.opengis.net/def/rel/ogc/1.0/conformance",
                           "type": "application/json"},
                          {"href": f"{b}/processes", "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes",
                           "type": "application/json"},
                          {"href": f"{b}/jobs", "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list",
                           "type": "application/json"},
                          {"href": f"{b}/dashboard", "rel": "related", "title": "Dask dashboard"}]}

    @app.get("/conformance")
    def conformance():
        return {"conformsTo": CONFORMANCE}

    @app.get("/processes")
    def processes(request: Request):
        b = _base(request)
        return {"processes": [process_summary(n, b) for n in detectors.names()],
                "links": [{"href": f"{b}/processes", "rel": "self", "type": "application/json"}]}

    @app.get("/processes/{process_id}")
    def process(request: Request, process_id: str):
        known_process(process_id)
        return process_description(process_id, _base(request))

    @app.post("/processes/{process_id}/execution")
    async def execute(request: Request, process_id: str):
        known_process(process_id)
        try:
            body = json.loads(await request.body() or b"null")
        except (ValueError, UnicodeDecodeError):
            raise Problem(400, "bad request", "the body is not valid JSON") from None
        inputs = validate_inputs(settings, process_id, body)
        st = store(request)
        job = st.create(process_id, inputs)
        request.app.state.metrics.requests.labels(process_id).inc()
        request.app.state.runner.wake.set()
        b = _base(request)
        prefer = request.headers.get("prefer", "").lower()
        if "respond-sync" in prefer:
            import anyio

            job = await anyio.to_thread.run_sync(wait_final, st, job["id"], settings.sync_timeout_s)
            if job["status"] == "successful":
                return JSONResponse(results_doc(job, b), headers={"Preference-Applied": "respond-sync",
                                                                  "Location": f"{b}/jobs/{job['id']}"})
            if job["status"] in FINAL:
                raise Problem(422, f"job {job['status']}", job["message"] or job["status"])
            return JSONResponse(status_doc(job, b), status_code=201, headers={"Location": f"{b}/jobs/{job['id']}"})
        headers = {"Location": f"{b}/jobs/{job['id']}"}
        if "respond-async" in prefer:
            headers["Preference-Applied"] = "respond-async"
        return JSONResponse(status_doc(job, b), status_code=201, headers=headers)

    @app.get("/jobs")
    def jobs(request: Request, limit: int = 1000, status: Optional[str] = None):
        if status is not None and status not in ("accepted", "running", "successful", "failed", "dismissed"):
            raise Problem(400, "invalid request", f"'status' must be a job status, got {status!r}")
        if not 1 <= limit <= 10000:
            raise Problem(400, "invalid request", f"'limit' must be in 1..10000, got {limit}")
        b = _base(request)
        return {"jobs": [status_doc(j, b) for j in store(request).list(limit=limit, status=status)],
                "links": [{"href": f"{b}/jobs", "rel": "self", "type": "application/json"}]}

    @app.get("/jobs/{job_id}")
    def job(request: Request, job_id: str):
        return status_doc(job_or_404(request, job_id), _base(request))

    @app.delete("/jobs/{job_id}")
    def dismiss(request: Request, job_id: str):
        job_or_404(request, job_id)
        return status_doc(store(request).dismiss(job_id), _base(request))

    def finished(request: Request, job_id: str) -> dict:
        job = job_or_404(request, job_id)
        if job["status"] != "successful":
            detail = {"failed": f"job failed: {job['message']}", "dismissed": "job was dismissed"}.get(
                job["status"], f"result not ready (job is {job['status']})")
            raise Problem(404, "result not ready" if job["status"] not in ("failed", "dismissed") else "no result",
                          detail)
        return job

    @app.get("/jobs/{job_id}/results")
    def results(request: Request, job_id: str):
        return results_doc(finished(request, job_id), _base(request))

    @app.get("/jobs/{job_id}/results/detections")
    def detections_out(request: Request, job_id: str):
        finished(request, job_id)
        return FileResponse(settings.jobs_dir / job_id / "detections.geojson", media_type="application/geo+json",
                            filename=f"{job_id}-detections.geojson")

    @app.get("/jobs/{job_id}/results/metrics")
    def metrics_out(request: Request, job_id: str):
        finished(request, job_id)
        return json.loads((settings.jobs_dir / job_id / "run.json").read_text())

    @app.get("/jobs/{job_id}/results/mask")
    def mask_out(request: Request, job_id: str):
        finished(request, job_id)
        return FileResponse(mask_geotiff(settings.jobs_dir / job_id), media_type="image/tiff; application=geotiff",
                            filename=f"{job_id}-mask.tif")

    @app.post("/scenes")
    async def upload(request: Request, filename: Optional[str] = None):
        """A scene file, streamed to disk (raw body with ``?filename=``, or multipart field
        ``file``), checked against the size limit as it arrives, named by its SHA-256, and
        ingested to ``DATA/scenes/ID.zarr`` by an ``ingest`` job. The same content uploaded
        twice is the same scene."""
        import hashlib
        import re

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
            name = Path(filename or "").name
            ext = "".join(Path(name).suffixes).lower()
            if not name or not re.fullmatch(r"(\.[a-z0-9]{1,8}){1,3}", ext):
                raise Problem(400, "missing filename", "give the file name with its extension (?filename=scene.tif "
                                                       "or the multipart file name): it selects the reader")
            scene_id = h.hexdigest()[:16]
            final = settings.uploads_dir / f"{scene_id}{ext}"
            if final.exists():
                tmp.unlink()
            else:
                os.replace(tmp, final)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        b = _base(request)
        doc = {"sceneID": scene_id, "sha256": h.hexdigest(), "bytes": n, "filename": name,
               "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}]}
        if (settings.scenes_dir / f"{scene_id}.zarr").exists():
            return JSONResponse({**doc, "status": "ready"}, status_code=200)
        job = store(request).create(INGEST, {"upload": str(final), "scene_id": scene_id, "filename": name,
                                             "sha256": h.hexdigest(), "bytes": n})
        request.app.state.runner.wake.set()
        return JSONResponse({**doc, "status": "ingesting", "jobID": job["id"],
                             "links": doc["links"] + [{"href": f"{b}/jobs/{job['id']}", "rel": "monitor",
                                                       "type": "application/json"}]},
                            status_code=201, headers={"Location": f"{b}/scenes/{scene_id}"})

    def scene_doc(scene_id: str, b: str) -> Optional[dict]:
        from pipeline.scene import open_scene

        p = settings.scenes_dir / f"{scene_id}.zarr"
        if not p.is_dir():
            return None
        try:
            sc = open_scene(p)
        except Exception as exc:
            return {"sceneID": scene_id, "status": "unreadable", "detail": str(exc)}
        return {"sceneID": scene_id, "status": "ready", "shape": list(sc.shape), "kind": sc.kind,
                "looks": sc.looks, "variables": list(sc.variables), "tile": sc.tile,
                "links": [{"href": f"{b}/scenes/{scene_id}", "rel": "self", "type": "application/json"}]}

    @app.get("/scenes")
    def scenes(request: Request):
        b = _base(request)
        ready = [scene_doc(p.name[:-5], b) for p in sorted(settings.scenes_dir.glob("*.zarr"))]
        pending = [{"sceneID": j["inputs"]["scene_id"], "status": "ingesting" if j["status"] != "failed" else "failed",
                    "jobID": j["id"], "message": j["message"]}
                   for j in store(request).list(limit=10000) if j["process"] == INGEST
                   and j["status"] in ("accepted", "running", "failed")
                   and not (settings.scenes_dir / f"{j['inputs']['scene_id']}.zarr").exists()]
        return {"scenes": [d for d in ready if d] + pending}

    @app.get("/scenes/{scene_id}")
    def scene(request: Request, scene_id: str):
        doc = scene_doc(scene_id, _base(request)) if scene_id.replace("_", "").replace("-", "").isalnum() else None
        if doc is None:
            for j in store(request).list(limit=10000):
                if j["process"] == INGEST and j["inputs"].get("scene_id") == scene_id:
                    return {"sceneID": scene_id, "status": "ingesting" if j["status"] in ("accepted", "running")
                            else j["status"], "jobID": j["id"], "message": j["message"]}
            raise Problem(404, "no such scene", f"no scene '{scene_id}'")
        return doc

    @app.get("/metrics")
    def prometheus(request: Request):
        from fastapi.responses import Response

        return Response(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    @app.get("/jobs/{job_id}/preview.png")
    def preview(request: Request, job_id: str, size: int = 1024):
        if not 64 <= size <= 4096:
            raise Problem(400, "invalid request", f"'size' must be in 64..4096, got {size}")
        finished(request, job_id)
        return FileResponse(preview_png(settings.jobs_dir / job_id, size), media_type="image/png")

    @app.get("/livez")
    def livez():
        return {"status": "ok"}

    @app.get("/readyz")
    def readyz(request: Request):
        checks = {}
        try:
            store(request).counts()
            checks["store"] = "ok"
        except Exception as exc:
            checks["store"] = f"error: {exc}"
        try:
            n = len(request.app.state.client.scheduler_info(n_workers=-1).get("workers", {}))
            checks["workers"] = n
        except Exception as exc:
            checks["scheduler"] = f"error: {exc}"
            n = 0
        ok = checks.get("store") == "ok" and n > 0
        return JSONResponse({"status": "ok" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)

    @app.get("/dashboard")
    def dashboard(request: Request):
        link = None
        with contextlib.suppress(Exception):
            link = request.app.state.client.dashboard_link
        if not link:
            raise Problem(404, "no dashboard", "the Dask cluster has no dashboard")
        return RedirectResponse(link, status_code=307)

    return app


def preview_png(job_dir: Path, size: int) -> Path:
    """Quicklook of a finished job (made once per size, atomically): the scene's intensity
    in dB (2-98 % stretch) decimated to at most ``size`` pixels a side, detected pixels in
    red, detection boxes in yellow."""
    out = job_dir / f"preview-{size}.png"
    if out.exists():
        return out
    import numpy as np
    import zarr
    from PIL import Image, ImageDraw

    from pipeline.inputs import intensity_source, make_reader
    from pipeline.scene import open_scene

    run = json.loads((job_dir / "run.json").read_text())
    scene = open_scene(run["scene"]["path"])
    H, W = scene.shape
    step = max(1, -(-max(H, W) // size))
    var, transform = intensity_source(scene)
    read = make_reader(str(scene.path), var, transform)
    rows = []
    for r0 in range(0, H, 1024 * step):  # bounded memory: strips of rows, decimated as read
        r1 = min(r0 + 1024 * step, H)
        rows.append(read(r0, r1, 0, W)[::step, ::step])
    x = np.concatenate(rows).astype(np.float32)
    with np.errstate(all="ignore"):
        db = 10.0 * np.log10(np.where(x > 0, x, np.nan))
    fin = np.isfinite(db)
    lo, hi = (np.percentile(db[fin], [2, 98]) if fin.any() else (0.0, 1.0))
    g = np.clip((np.nan_to_num(db, nan=lo) - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    rgb = np.stack([g, g, g], -1)
    m = zarr.open_group(str(job_dir / "mask.zarr"), mode="r")["mask"]
    mrows = [np.asarray(m[r0: min(r0 + 1024 * step, H), :])[::step, ::step] for r0 in range(0, H, 1024 * step)]
    mk = np.concatenate(mrows).astype(bool)
    rgb[mk] = (255, 40, 40)
    img = Image.fromarray(rgb)
    draw = ImageDraw.Draw(img)
    fc = json.loads((job_dir / "detections.geojson").read_text())
    for f in fc.get("features", []):
        bb = f["properties"].get("bbox_px")
        if bb:
            r0, c0, r1, c1 = bb
            draw.rectangle([c0 // step - 2, r0 // step - 2, c1 // step + 2, r1 // step + 2], outline=(255, 220, 0))
    tmp = job_dir / f".preview-{uuid.uuid4().hex[:8]}.png"
    img.save(tmp, format="PNG")
    os.replace(tmp, out)
    return out


def mask_geotiff(job_dir: Path) -> Path:
    """The job's mask as a tiled, deflate-compressed GeoTIFF (made once, atomically)."""
    out = job_dir / "mask.tif"
    if out.exists():
        return out
    import numpy as np
    import tifffile
    import zarr

    g = zarr.open_group(str(job_dir / "mask.zarr"), mode="r")
    arr = g["mask"]
    tmp = job_dir / f".mask-{uuid.uuid4().hex[:8]}.tif"
    extratags = []
    tr = g.attrs.get("transform")
    if tr:  # ModelPixelScale + ModelTiepoint for a north-up affine (a, b, c, d, e, f)
        a, b, c, d, e, f = tr[:6]
        if b == 0 and d == 0:
            extratags = [(33550, "d", 3, (a, -e, 0.0)), (33922, "d", 6, (0.0, 0.0, 0.0, c, f, 0.0))]
    data = np.asarray(arr[...], dtype=np.uint8)
    tifffile.imwrite(tmp, data, tile=(256, 256), compression="zlib", extratags=extratags,
                     metadata=None, photometric="minisblack")
    os.replace(tmp, out)
    return out
