"""Operations routes: ``GET /metrics`` (Prometheus), the probes ``GET /livez`` and ``GET /readyz``
(store, Dask workers, free disk) and ``GET /dashboard`` (a redirect to the Dask dashboard)."""

from __future__ import annotations

import shutil
from typing import Any

import anyio
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, RedirectResponse, Response

from sarship.service.common import Problem, settings_of, store_of
from sarship.service.openapi import media, problems
from sarship.service.settings import Settings

router = APIRouter()
#: Paths answered without a token, whatever the settings (probes and metrics: service/auth.py).
OPEN_PATHS = ("/livez", "/readyz", "/metrics")


def dashboard_link(request: Request) -> str | None:
    """Where GET /dashboard sends a browser (SARSHIP_DASHBOARD_URL, else the cluster's own link),
    or None when the scheduler serves no dashboard (``workers.cluster.dashboard_url``)."""
    from sarship.workers.cluster import dashboard_url

    client = getattr(request.app.state, "client", None)
    link = dashboard_url(client) if client is not None else None
    return (settings_of(request).dashboard_url or link) if link else None


@router.get("/metrics", responses=media("text/plain; version=0.0.4", "Prometheus text format"))
def prometheus(request: Request) -> Response:
    return Response(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")


@router.get("/livez", response_model=None)
async def livez() -> dict[str, str]:  # on the event loop: answers however busy the worker threads are
    return {"status": "ok"}


@router.get("/readyz")
async def readyz(request: Request) -> JSONResponse:
    state = request.app.state
    if getattr(state, "probe_threads", None) is None:  # readyz's own threads, not the routes' shared pool
        state.probe_threads = anyio.CapacityLimiter(2)
    return await anyio.to_thread.run_sync(ready_check, request, limiter=state.probe_threads)


def ready_check(request: Request) -> JSONResponse:
    """The readiness document: the store answers, the cluster has workers, the disk has room."""
    checks: dict[str, Any] = {}
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
    checks["disk"] = disk_check(settings_of(request))
    ok = checks.get("store") == "ok" and n > 0 and checks["disk"] == "ok"
    return JSONResponse({"status": "ok" if ok else "not ready", "checks": checks}, status_code=200 if ok else 503)


def disk_check(settings: Settings) -> str:
    """ "ok", or why the data folder cannot take more work: less free space than
    ``min_free_mb`` (a full disk fails every ingest and job output)."""
    if not settings.min_free_mb:
        return "ok"
    try:
        free = shutil.disk_usage(settings.data).free
    except OSError as exc:
        return f"error: data folder {settings.data}: {exc.strerror or exc}"
    if free < settings.min_free_mb * 2**20:
        return (
            f"data folder {settings.data} has {free / 2**20:.0f} MiB free, less than min_free_mb "
            f"({settings.min_free_mb:g} MiB)"
        )
    return "ok"


@router.get("/dashboard", responses={307: {"description": "redirect to the Dask dashboard"}, **problems(404)})
def dashboard(request: Request) -> RedirectResponse:
    link = dashboard_link(request)
    if not link:
        from sarship.workers.cluster import DASHBOARD_HINT

        raise Problem(404, "no dashboard", f"the Dask scheduler serves no dashboard: {DASHBOARD_HINT}")
    return RedirectResponse(link, status_code=307)
