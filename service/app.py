"""The FastAPI application: OGC API - Processes 1.0 shaped job API (docs/interfaces/rest.md).

``create_app(settings)`` only assembles: the settings, the middleware, the problem handlers
(``service/problem_handlers.py``), the OpenAPI document and the routers, one module per thing
served (``landing``, ``processes``, ``jobs``, ``health``, ``results``, ``scenes``,
``ais_files``, ``ingest_routes``, ``web``); its lifespan opens the job store, connects to Dask (a local
cluster, or ``settings.scheduler``) and runs the job runner, the inbox and the scene retention
for the application's lifetime. How to add a route: docs/adding-an-endpoint.md.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING

from fastapi import FastAPI

from sarship.pipeline import __version__
from sarship.service import (
    ais_files,
    health,
    ingest_routes,
    jobs,
    landing,
    problem_handlers,
    processes,
    results,
    scenes,
    web,
)
from sarship.service.auth import BearerAuth
from sarship.service.limits import RequestLimits
from sarship.service.metrics import Metrics
from sarship.service.openapi import install as install_openapi
from sarship.service.runner import Runner
from sarship.service.settings import Settings
from sarship.service.store import JobStore

if TYPE_CHECKING:
    from distributed import Client

    from sarship.service.scheduler_link import SchedulerLink

#: The routers, in the order their routes are matched and listed in the OpenAPI document.
ROUTERS = (
    landing.router,
    processes.router,
    jobs.router,
    health.router,
    results.router,
    scenes.router,
    ais_files.router,
    ingest_routes.router,
    web.router,
)


def connect_cluster(settings: Settings, stack: contextlib.ExitStack[bool | None]) -> Client | SchedulerLink:
    """The Dask client of the service: to ``settings.scheduler`` (made again when the scheduler
    restarts), else a local cluster of CPU workers and one pinned worker per GPU
    (``SARSHIP_GPUS``), closed with ``stack``."""
    from sarship.workers.cluster import connect, dashboard_address_on

    if settings.scheduler:
        from sarship.service.scheduler_link import open_link

        c = open_link(settings.scheduler, settings.reconnect_s, settings.reconnect_max_s)
        stack.callback(c.close)
        return c
    # the local cluster's dashboard listens where the API does (never wider: it has no tokens),
    # on any free port; GET /dashboard redirects to it
    dash = dashboard_address_on(settings.host)
    gpu_ids, n_cpu = settings.local_workers()
    local: Client = stack.enter_context(
        connect(
            None,
            n_workers=n_cpu,
            dashboard_address=dash,
            echo=True,
            gpus=gpu_ids,
            cpu_workers=n_cpu,
            threads=settings.worker_threads,
        )
    )
    return local


def lifespan_of(
    settings: Settings, client: Client | None = None
) -> Callable[[FastAPI], contextlib.AbstractAsyncContextManager[None]]:
    """The application's lifespan: data folders, job store, metrics, Dask client, runner, inbox
    (scheduled ingest, idle without ``SARSHIP_INBOX``) and scene retention
    (``SARSHIP_SCENE_RETENTION_DAYS``), all stopped when the application stops."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        for d in (settings.data, settings.scenes_dir, settings.jobs_dir):
            d.mkdir(parents=True, exist_ok=True)
        store = JobStore(settings.db_path)
        metrics = Metrics()
        metrics.watch_store(store)
        app.state.metrics = metrics
        with contextlib.ExitStack() as stack:
            c = client if client is not None else connect_cluster(settings, stack)
            runner = Runner(settings, store, c, metrics)
            runner.start()
            from sarship.service.inbox import start_inbox

            app.state.inbox = start_inbox(settings, store, runner)
            app.state.retention = scenes.Retention(settings, store).start()
            app.state.store, app.state.client, app.state.runner = store, c, runner
            try:
                yield
            finally:
                app.state.inbox.stop()
                app.state.retention.stop()
                runner.stop()

    return lifespan


def create_app(settings: Settings | None = None, client: Client | None = None) -> FastAPI:
    """The service's application for ``settings`` (default: from the environment); ``client``:
    a connected Dask client to use instead of the one the lifespan makes."""
    settings = settings or Settings()
    app = FastAPI(
        title="sarship",
        version=__version__,
        lifespan=lifespan_of(settings, client),
        description="Ship detection in SAR scenes: OGC API - Processes shaped job API",
        docs_url=None,
        redoc_url=None,
    )  # /docs: web.py, Swagger UI served from here (no CDN)
    app.state.settings = settings
    app.state.sync_waits = 0  # 'Prefer: respond-sync' executions waiting now
    # set by `sarship serve` (uvicorn's Server.should_exit): sync waits end at SIGTERM
    app.state.should_exit = lambda: False
    # body size (max_body_kb; POST /scenes has its own) and NUL in paths, before any route (service/limits.py)
    app.add_middleware(RequestLimits, max_body=int(settings.max_body_kb * 1024))
    # bearer tokens (settings.tokens) for POST/DELETE, and for reads with protect_reads (service/auth.py);
    # added last, so it runs first: a request without a token is refused before its body is read
    app.add_middleware(
        BearerAuth, tokens=settings.tokens, protect_reads=settings.protect_reads, open_paths=health.OPEN_PATHS
    )
    problem_handlers.install(app)
    install_openapi(
        app, tokens=bool(settings.tokens), protect_reads=settings.protect_reads, open_paths=health.OPEN_PATHS
    )
    for router in ROUTERS:
        app.include_router(router)
    return app
