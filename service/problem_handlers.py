"""The application's exception handlers: every error a problem document (RFC 7807), never a
server path in its detail (:meth:`~sarship.service.settings.Settings.hide_paths`); bad input
a ``4xx``, a full disk ``507``, a busy store ``503``, a bug ``500`` with its traceback logged."""

from __future__ import annotations

import logging
import sqlite3

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from sarship.service.common import Problem, problem, settings_of, storage_problem

log = logging.getLogger("sarship.service")


async def on_problem(request: Request, exc: Problem) -> JSONResponse:
    # no server path in any problem (a scene resolved in DATA/scenes, a land_mask FILE, ...)
    return problem(exc.status, exc.title, settings_of(request).hide_paths(exc.detail), exc.headers)


async def on_storage(request: Request, exc: Exception) -> JSONResponse:
    # a full disk (or a file-size limit, a quota) or a busy job store: 507 / 503, not a bug
    p = storage_problem(exc)
    if p is None:
        return await on_internal(request, exc)
    log.error("%s %s: %s", request.method, request.url.path, p.detail)
    return problem(p.status, p.title, settings_of(request).hide_paths(p.detail), p.headers)


async def on_http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    title = {404: "not found", 405: "method not allowed"}.get(exc.status_code, "error")
    r = problem(exc.status_code, title, settings_of(request).hide_paths(str(exc.detail)))
    for k, v in (exc.headers or {}).items():  # e.g. 405's Allow (RFC 9110 requires it)
        r.headers[k] = v
    return r


async def on_internal(request: Request, exc: Exception) -> JSONResponse:
    # a bug, not bad input: still a problem document, and logged with its traceback
    log.exception("internal error on %s %s", request.method, request.url.path)
    return problem(500, "internal error", settings_of(request).hide_paths(f"{type(exc).__name__}: {exc}"))


async def on_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
        parts.append(f"'{loc}': {e.get('msg', 'invalid')}" if loc else e.get("msg", "invalid"))
    return problem(400, "invalid request", "; ".join(parts))


def install(app: FastAPI) -> None:
    """Register the handlers on ``app`` (its ``state.settings`` hides the paths)."""
    app.add_exception_handler(Problem, on_problem)  # type: ignore[arg-type]
    app.add_exception_handler(OSError, on_storage)
    app.add_exception_handler(sqlite3.OperationalError, on_storage)
    app.add_exception_handler(StarletteHTTPException, on_http)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, on_internal)
    app.add_exception_handler(RequestValidationError, on_validation)  # type: ignore[arg-type]
