"""The FastAPI application: OGC API - Processes 1.0 shaped job API (docs/interfaces/rest.md).

``create_app(settings)`` opens the job store, connects to Dask (a local cluster, or
``settings.scheduler``) and starts the job runner for the application's lifetime.
Every error is a problem document (RFC 7807: ``type``, ``title``, ``detail``, ``status``);
bad input is always a ``4xx``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import time
from typing import Any, Literal, Optional

import anyio
from fastapi import FastAPI, Header, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from sarship.pipeline import __version__, detectors
from sarship.pipeline.errors import InputError
from sarship.service import results, scenes
from sarship.service.auth import BearerAuth
from sarship.service.common import (Problem, base_url, check_text, job_or_404, parse_json_body, problem,
                                    results_doc, status_doc, storage_problem, store_of)
from sarship.service.limits import RequestLimits
from sarship.service.metrics import Metrics
from sarship.service.openapi import (EXECUTE_BODY, JOB_STATUSES, PREFER_DOC, Conformance, JobList, Landing,
                             ProcessDescription, ProcessList, Results, StatusInfo, problems)
from sarship.service.openapi import install as install_openapi
from sarship.service.openapi import media
from sarship.service.job_inputs import check_coastline, land_file_path, scene_path
from sarship.service.runner import Runner
from sarship.service.settings import Settings
from sarship.service.store import FINAL, JobStore
from sarship.workers.request import DEVICES, JobRequest

log = logging.getLogger("sarship.service")

OGC = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
CONFORMANCE = [OGC + c for c in ("core", "json", "job-list", "dismiss", "oas30")]
#: Inputs every process takes besides its detector parameters.
COMMON_INPUTS = {
    "scene": {"title": "scene", "description": "scene id (uploaded) or path of a scene store inside an allowed folder",
              "schema": {"type": "string"}, "minOccurs": 1, "maxOccurs": 1},
    "device": {"title": "device", "description": "where tiles run: auto (GPU workers if any), gpu or cpu",
               "schema": {"type": "string", "enum": list(DEVICES), "default": "auto"},
               "minOccurs": 0, "maxOccurs": 1},
}


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


def validate_inputs(settings: Settings, name: str, body: Any, store: Optional[JobStore] = None) -> dict:
    """The job's inputs, validated now (so that bad input is a 400, not a failed job): the
    execution body's envelope here, the inputs by :class:`~sarship.workers.request.JobRequest`
    (the same model the command line and the runner use), the scene against the allowed
    folders. With ``store``, a scene id that is not in the scene store yet but whose ingest
    job is accepted or running (an upload still being ingested) is valid too: see
    :func:`pending_ingest`."""
    if not isinstance(body, dict) or not isinstance(body.get("inputs"), dict):
        raise Problem(400, "bad request", "the body must be a JSON object {\"inputs\": {\"scene\": ..., ...}}")
    if body.get("response", "document") not in ("document", "raw"):
        raise Problem(400, "bad request", f"'response' must be 'document' or 'raw', got {body['response']!r}")
    if not isinstance(body.get("outputs", {}), dict):
        raise Problem(400, "bad request", "'outputs' must be an object (output name -> options)")
    scene = body["inputs"].get("scene")
    if isinstance(scene, str):  # a NUL or a lone surrogate: no file, no store key can have it
        check_text(scene, "input 'scene'")
    try:
        request = JobRequest.from_inputs(name, body["inputs"])
        land_file_path(settings, request)
        try:
            path = scene_path(settings, request.scene)
        except InputError:
            path = None
            if store is None or pending_ingest(settings, store, request.scene) is None:
                scene_path(settings, request.scene)  # raises again, unless an ingest finished meanwhile
        if path is not None:  # the detector against the scene (csk on amplitude, vb_polsar on a covariance
            check_scene_input(path, request)  # scene, a channel the scene lacks): a 400, not a failed job
        check_coastline(request, path)  # land_mask=coastline: its package, a georeferenced scene
    except InputError as exc:
        title = "missing input" if "is required" in str(exc) else "invalid input"
        detail = str(exc)
        if store is not None and "no scene" in detail and scene_id_like(request_scene(body)):
            last = store.ingest_job_for_scene(request_scene(body).strip())
            if last is not None and last["status"] in ("failed", "dismissed"):
                detail += f" (its ingest job {last['id']} {last['status']}: {last['message']})"
        raise Problem(400, title, detail) from None
    return dict(body["inputs"])


def check_scene_input(path, request: JobRequest) -> None:
    """:class:`InputError` when the request's detector cannot read the scene at ``path`` (its
    ``channel`` a variable the scene lacks or of the wrong kind, a complex-SLC detector on
    amplitude data, a complex-channel detector on a covariance scene): the check the job
    itself makes (:func:`sarship.pipeline.inputs.detector_source`). A store that cannot be
    opened is left to the job, as for every detector."""
    from sarship.pipeline.inputs import detector_source
    from sarship.pipeline.scene import open_scene

    try:
        scene = open_scene(path)
    except Exception:
        return
    detector_source(request.spec, scene, request.channel)
    if request.spec.for_scene is not None:  # a scene too small for the method (gamma_mrf): a 400
        request.spec.for_scene(request.detector_params(), scene.shape, scene.ground_spacing_m)


def request_scene(body: dict) -> str:
    s = body["inputs"].get("scene")
    return s if isinstance(s, str) else ""


def scene_id_like(s: str) -> bool:
    """A scene id (``DATA/scenes/ID.zarr``) rather than a path."""
    s = s.strip()
    return bool(s) and s.replace("_", "").replace("-", "").isalnum()


def pending_ingest(settings: Settings, store: JobStore, scene: str) -> Optional[dict]:
    """The accepted or running ingest job of scene id ``scene`` (an upload being ingested,
    ``POST /scenes``, or an inbox pass), if the scene is not in the scene store yet."""
    if not scene_id_like(scene):
        return None
    return store.active_ingest(scene.strip())


async def wait_sync(request: Request, store: JobStore, job: dict, timeout: float) -> dict:
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


def remove_job_outputs(settings: Settings, job_id: str) -> None:
    """Remove ``DATA/jobs/ID`` (renamed aside first, so that no reader sees it half-removed)."""
    import shutil
    import uuid

    d = settings.jobs_dir / job_id
    if not d.is_dir():
        return
    gone = settings.jobs_dir / f".dismissed-{job_id}-{uuid.uuid4().hex[:6]}"
    try:
        d.rename(gone)
    except OSError:
        gone = d
    shutil.rmtree(gone, ignore_errors=True)


def _dashboard(request: Request) -> Optional[str]:
    """Where GET /dashboard sends a browser (SARSHIP_DASHBOARD_URL, else the cluster's own link),
    or None when the scheduler serves no dashboard (``workers.cluster.dashboard_url``)."""
    from sarship.workers.cluster import dashboard_url

    client = getattr(request.app.state, "client", None)
    link = dashboard_url(client) if client is not None else None
    return (request.app.state.settings.dashboard_url or link) if link else None


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
                from sarship.workers.cluster import connect, dashboard_address_on

                # the local cluster's dashboard listens where the API does (never wider: it has
                # no tokens), on any free port; GET /dashboard redirects to it
                dash = dashboard_address_on(settings.host)
                if settings.scheduler:  # a client made again when the scheduler restarts
                    from sarship.service.scheduler_link import open_link

                    c = open_link(settings.scheduler, settings.reconnect_s, settings.reconnect_max_s)
                    stack.callback(c.close)
                else:  # one pinned worker per GPU (SARSHIP_GPUS) besides the CPU workers
                    gpu_ids, n_cpu = settings.local_workers()
                    c = stack.enter_context(connect(None, n_workers=n_cpu, dashboard_address=dash, echo=True,
                                                    gpus=gpu_ids, cpu_workers=n_cpu,
                                                    threads=settings.worker_threads))
            runner = Runner(settings, store, c, metrics)
            runner.start()
            from sarship.service.inbox import start_inbox  # scheduled ingest (idle without SARSHIP_INBOX)

            app.state.inbox = start_inbox(settings, store, runner)
            from sarship.service.scenes import Retention  # SARSHIP_SCENE_RETENTION_DAYS (idle when off)

            app.state.retention = Retention(settings, store).start()
            app.state.store, app.state.client, app.state.runner = store, c, runner
            try:
                yield
            finally:
                app.state.inbox.stop()
                app.state.retention.stop()
                runner.stop()

    app = FastAPI(title="sarship", version=__version__, lifespan=lifespan,
                  description="Ship detection in SAR scenes: OGC API - Processes shaped job API",
                  docs_url=None, redoc_url=None)  # /docs: web.py, Swagger UI served from here (no CDN)
    app.state.settings = settings
    app.state.sync_waits = 0  # 'Prefer: respond-sync' executions waiting now
    # set by `sarship serve` (uvicorn's Server.should_exit): sync waits end at SIGTERM
    app.state.should_exit = lambda: False

    open_paths = ("/livez", "/readyz", "/metrics")

    # body size (max_body_kb; POST /scenes has its own) and NUL in paths, before any route (service/limits.py)
    app.add_middleware(RequestLimits, max_body=int(settings.max_body_kb * 1024))
    # bearer tokens (settings.tokens) for POST/DELETE, and for reads with protect_reads (service/auth.py);
    # added last, so it runs first: a request without a token is refused before its body is read
    app.add_middleware(BearerAuth, tokens=settings.tokens, protect_reads=settings.protect_reads, open_paths=open_paths)

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem):
        # no server path in any problem (a scene resolved in DATA/scenes, a land_mask FILE, ...)
        return problem(exc.status, exc.title, settings.hide_paths(exc.detail), exc.headers)

    async def _storage(request: Request, exc: Exception):
        # a full disk (or a file-size limit, a quota) or a busy job store: 507 / 503, not a bug
        p = storage_problem(exc)
        if p is None:
            return await _internal(request, exc)
        log.error("%s %s: %s", request.method, request.url.path, p.detail)
        return problem(p.status, p.title, settings.hide_paths(p.detail), p.headers)

    app.add_exception_handler(OSError, _storage)
    app.add_exception_handler(sqlite3.OperationalError, _storage)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        title = {404: "not found", 405: "method not allowed"}.get(exc.status_code, "error")
        r = problem(exc.status_code, title, settings.hide_paths(str(exc.detail)))
        for k, v in (exc.headers or {}).items():  # e.g. 405's Allow (RFC 9110 requires it)
            r.headers[k] = v
        return r

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        # a bug, not bad input: still a problem document, and logged with its traceback
        log.exception("internal error on %s %s", request.method, request.url.path)
        return problem(500, "internal error", settings.hide_paths(f"{type(exc).__name__}: {exc}"))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        parts = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
            parts.append(f"'{loc}': {e.get('msg', 'invalid')}" if loc else e.get("msg", "invalid"))
        return problem(400, "invalid request", "; ".join(parts))

    install_openapi(app, tokens=bool(settings.tokens), protect_reads=settings.protect_reads, open_paths=open_paths)
    process_param = Path(description="the process (detector) id", json_schema_extra={"enum": detectors.names()})
    location_header = {"description": "the job's status URL", "schema": {"type": "string"}}

    @app.get("/", responses={200: {"model": Landing}})
    def landing(request: Request):
        b = base_url(request)
        if "text/html" in request.headers.get("accept", "") and request.query_params.get("f") != "json":
            return RedirectResponse(f"{b}/ui/", status_code=303)  # a browser: the web page (?f=json: this)
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
                          # the dashboard only where the scheduler serves one (bokeh installed)
                          *([{"href": f"{b}/dashboard", "rel": "related", "title": "Dask dashboard"}]
                            if _dashboard(request) else []),
                          {"href": f"{b}/ui/", "rel": "alternate", "type": "text/html", "title": "web page"}]}

    @app.get("/conformance", responses={200: {"model": Conformance}})
    def conformance():
        return {"conformsTo": CONFORMANCE}

    @app.get("/processes", responses={200: {"model": ProcessList}})
    def processes(request: Request):
        b = base_url(request)
        return {"processes": [process_summary(n, b) for n in detectors.names()],
                "links": [{"href": f"{b}/processes", "rel": "self", "type": "application/json"}]}

    @app.get("/processes/{process_id}", responses={200: {"model": ProcessDescription}, **problems(404)})
    def process(request: Request, process_id: str = process_param):
        known_process(process_id)
        return process_description(process_id, base_url(request))

    @app.post("/processes/{process_id}/execution", status_code=201,
              responses={201: {"model": StatusInfo, "description": "job accepted (asynchronous execution); a job "
                                                                "for a scene id whose upload is still being "
                                                                "ingested waits for that ingest job",
                               "headers": {"Location": location_header}},
                         200: {"model": Results, "description": "the results document (Prefer: respond-sync)",
                               "headers": {"Location": location_header}},
                         **problems(400, 404, 413, 422, 503, 507)},
              openapi_extra={"requestBody": EXECUTE_BODY})
    async def execute(request: Request, process_id: str = process_param,
                      prefer: Optional[str] = Header(None, alias="Prefer", description=PREFER_DOC,
                                                     examples=["respond-async", "respond-sync"])):
        known_process(process_id)
        # (the body is at most max_body_kb here: service/limits.py); nesting depth checked before parsing
        body = parse_json_body(await request.body())
        st = store_of(request)
        inputs = validate_inputs(settings, process_id, body, st)
        prefer = (prefer or "").lower()
        sync = "respond-sync" in prefer
        if not sync:
            return await submit(request, st, process_id, inputs, prefer)
        if request.app.state.sync_waits >= settings.max_sync_waits:
            # each waiting request holds a connection: beyond the cap, before any job is created
            raise Problem(503, "too many synchronous executions",
                          f"{request.app.state.sync_waits} 'Prefer: respond-sync' executions are waiting "
                          f"(at most {settings.max_sync_waits}, setting max_sync_waits): try again later, "
                          "or execute asynchronously and poll the job", {"Retry-After": "10"})
        request.app.state.sync_waits += 1  # (taken before the job is created: the cap holds under a burst)
        try:
            job = await create_job(request, st, process_id, inputs)
            job = await wait_sync(request, st, job, settings.sync_timeout_s)
        finally:
            request.app.state.sync_waits -= 1
        b = base_url(request)
        if job["status"] == "successful":
            return JSONResponse(results_doc(job, b), headers={"Preference-Applied": "respond-sync",
                                                              "Location": f"{b}/jobs/{job['id']}"})
        if job["status"] in FINAL:
            raise Problem(422, f"job {job['status']}", job["message"] or job["status"])
        return JSONResponse(status_doc(job, b), status_code=201, headers={"Location": f"{b}/jobs/{job['id']}"})

    async def create_job(request: Request, st: JobStore, process_id: str, inputs: dict) -> dict:
        """The new job, committed to the store (waiting for its scene's ingest job when that still runs)."""
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

    async def submit(request: Request, st: JobStore, process_id: str, inputs: dict, prefer: str):
        job = await create_job(request, st, process_id, inputs)
        b = base_url(request)
        headers = {"Location": f"{b}/jobs/{job['id']}"}
        if "respond-async" in prefer:
            headers["Preference-Applied"] = "respond-async"
        return JSONResponse(status_doc(job, b), status_code=201, headers=headers)

    @app.get("/jobs", responses={200: {"model": JobList}})
    def jobs(request: Request, limit: int = Query(1000, ge=1, le=10000, description="most jobs listed, newest first"),
             status: Optional[Literal[JOB_STATUSES]] = Query(None, description="only jobs in this status")):
        b = base_url(request)
        return {"jobs": [status_doc(j, b) for j in store_of(request).list(limit=limit, status=status)],
                "links": [{"href": f"{b}/jobs", "rel": "self", "type": "application/json"}]}

    @app.get("/jobs/{job_id}", responses={200: {"model": StatusInfo}})
    async def job(request: Request, job_id: str):
        # the route clients poll: on the event loop, no threadpool hop (a primary-key read of
        # the WAL-mode store, ~40 us, never waits for writers)
        return status_doc(job_or_404(request, job_id), base_url(request))

    @app.delete("/jobs/{job_id}", responses={200: {"model": StatusInfo, "description": (
        "the job, dismissed: an accepted or running job is cancelled; a finished (successful or "
        "failed) job's results are removed (its results then answer 404); a job already dismissed is "
        "returned unchanged. The job stays in the job list with status 'dismissed'.")}, **problems(404)})
    def dismiss(request: Request, job_id: str):
        job, before = store_of(request).dismiss(job_id)
        if job is None:
            raise Problem(404, "no such job", f"no job '{job_id}'")
        if before in ("successful", "failed") and job["process"] != "ingest":
            # outputs of a finished job (an ingest job's scene is shared by every job of that scene: kept)
            remove_job_outputs(settings, job_id)
        return status_doc(job, base_url(request))

    @app.get("/metrics", responses=media("text/plain; version=0.0.4", "Prometheus text format"))
    def prometheus(request: Request):
        from fastapi.responses import Response

        return Response(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    @app.get("/livez")
    async def livez():  # on the event loop: answers however busy the worker threads are
        return {"status": "ok"}

    probe_threads = anyio.CapacityLimiter(2)  # readyz's own threads, not the routes' shared pool

    @app.get("/readyz")
    async def readyz(request: Request):
        return await anyio.to_thread.run_sync(ready_check, request, limiter=probe_threads)

    def ready_check(request: Request):
        checks = {}
        try:
            store_of(request).counts()
            checks["store"] = "ok"
        except Exception as exc:
            checks["store"] = f"error: {exc}"
        try:
            workers = request.app.state.client.scheduler_info(n_workers=-1).get("workers", {})
            n = len(workers)
            checks["workers"] = n
            checks["threads"] = sum(int(w.get("nthreads", 0)) for w in workers.values())
        except Exception as exc:
            checks["scheduler"] = f"error: {exc}"
            n = 0
        checks["disk"] = disk_check(settings)
        ok = checks.get("store") == "ok" and n > 0 and checks["disk"] == "ok"
        return JSONResponse({"status": "ok" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)

    def disk_check(settings: Settings) -> str:
        """"ok", or why the data folder cannot take more work: less free space than
        ``min_free_mb`` (a full disk fails every ingest and job output)."""
        import shutil

        if not settings.min_free_mb:
            return "ok"
        try:
            free = shutil.disk_usage(settings.data).free
        except OSError as exc:
            return f"error: data folder {settings.data}: {exc.strerror or exc}"
        if free < settings.min_free_mb * 2**20:
            return (f"data folder {settings.data} has {free / 2**20:.0f} MiB free, less than min_free_mb "
                    f"({settings.min_free_mb:g} MiB)")
        return "ok"

    @app.get("/dashboard", responses={307: {"description": "redirect to the Dask dashboard"}, **problems(404)})
    def dashboard(request: Request):
        link = _dashboard(request)
        if not link:
            from sarship.workers.cluster import DASHBOARD_HINT

            raise Problem(404, "no dashboard", f"the Dask scheduler serves no dashboard: {DASHBOARD_HINT}")
        return RedirectResponse(link, status_code=307)

    app.include_router(results.router)
    app.include_router(scenes.router)
    from sarship.service import ingest_routes  # GET /ingest, POST /ingest/scan

    app.include_router(ingest_routes.router)
    from sarship.service import web  # the web page (/ui/), its static files and the API docs (/docs)

    app.include_router(web.router)
    return app
