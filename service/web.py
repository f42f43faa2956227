"""The web page served by the API (``/ui/``): jobs with live status, scene upload, a submit form
built from the process schemas (main parameters open, the others in a collapsed "Advanced
parameters"), a job view with the quicklook tiles on a pan/zoom map (in lon/lat on a Web
Mercator map when the scene is georeferenced: ``tiles.json``'s ``lonlat`` grid,
:func:`sarship.service.tiles.lonlat_grid`; else on the scene's pixel grid) and the detections
drawn and listed, the scheduled-ingest state and a link to the Dask dashboard.

The page is static (``service/static/``: HTML, JavaScript, CSS and the vendored Leaflet); it
reads everything through the public API, so it needs no server-side templates and works with
whatever the API allows (tokens are entered on the page). No CDN: every file is served here.

Caching: ``index.html`` names its assets with ``?v=DIGEST`` (a digest of all static files), is
itself served with ``Cache-Control: no-cache`` (revalidated by ETag on every load), and an
asset requested with the current digest is immutable for a year. So a new release is picked up
on the next page load, and repeated loads cost one conditional request.

``/docs`` is the API's Swagger UI (FastAPI's page) with its script and style sheet from the
vendored ``swagger-ui-dist`` (``static/vendor/swagger-ui/``), so it too works offline; the app
is created with ``docs_url=None`` (FastAPI's own page loads them from a CDN) and ``redoc_url=None``
(ReDoc is not vendored).
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.staticfiles import StaticFiles

from sarship.service.common import Problem

#: The page's files (installed with the package: pyproject ``[tool.setuptools.package-data]``).
STATIC = Path(__file__).with_name("static")
#: Marker in ``index.html`` replaced by the assets' digest.
VERSION_MARK = "__ASSET_VERSION__"
NO_CACHE = "no-cache"
IMMUTABLE = "public, max-age=31536000, immutable"

router = APIRouter(include_in_schema=False)
# Starlette's static file lookup: paths are resolved inside STATIC (no traversal, no symlinks
# out), conditional requests (ETag / If-Modified-Since) answered with 304.
_files = StaticFiles(directory=STATIC)


@functools.lru_cache(maxsize=1)
def asset_version() -> str:
    """A short digest of every static file (names and contents): changes whenever any does."""
    h = hashlib.sha256()
    for p in sorted(STATIC.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(STATIC).as_posix().encode() + b"\0" + p.read_bytes())
    return h.hexdigest()[:12]


@functools.lru_cache(maxsize=1)
def index_html() -> bytes:
    return (STATIC / "index.html").read_text(encoding="utf-8").replace(VERSION_MARK, asset_version()).encode()


@router.get("/ui")
def ui_redirect(request: Request) -> RedirectResponse:
    """``/ui`` -> ``/ui/`` (the page's relative links need the trailing slash)."""
    return RedirectResponse(request.url.replace(path=request.url.path + "/"), status_code=308)


@router.get("/ui/")
def ui_page(request: Request) -> Response:
    """The page: ``index.html`` with its asset links stamped with the current digest."""
    body = index_html()
    etag = f'"{hashlib.sha256(body).hexdigest()[:16]}"'
    headers = {
        "Cache-Control": NO_CACHE,
        "ETag": etag,
        "X-Content-Type-Options": "nosniff",
        "Referrer-Policy": "same-origin",
        # everything the page loads comes from this server; tiles and quicklooks may be blobs
        "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; "
        "style-src 'self'; script-src 'self'; object-src 'none'; "
        "base-uri 'self'; frame-ancestors 'self'",
    }
    if etag in request.headers.get("if-none-match", ""):
        return Response(status_code=304, headers=headers)
    return Response(body, media_type="text/html; charset=utf-8", headers=headers)


@router.get("/ui/static/{path:path}")
async def ui_static(request: Request, path: str) -> Response:
    """A static file of the page (404 problem when there is none). Immutable when asked for
    with the current ``?v=`` digest, else revalidated on every use."""
    try:
        resp = await _files.get_response(path, request.scope)
    except StarletteHTTPException as exc:
        if exc.status_code == 404:
            raise Problem(404, "not found", f"the web page has no file '{path}'") from None
        raise
    fresh = request.query_params.get("v") == asset_version()
    resp.headers["Cache-Control"] = IMMUTABLE if fresh else NO_CACHE
    resp.headers["X-Content-Type-Options"] = "nosniff"
    return resp


#: The vendored Swagger UI (swagger-ui-dist, version in static/vendor/swagger-ui/README.md).
SWAGGER = "ui/static/vendor/swagger-ui"


@router.get("/docs")
def api_docs(request: Request) -> HTMLResponse:
    """The API docs (Swagger UI) with every file served here: nothing from the internet."""
    root = request.scope.get("root_path", "").rstrip("/")
    v = asset_version()
    resp = get_swagger_ui_html(
        openapi_url=root + (request.app.openapi_url or "/openapi.json"),
        title=f"{request.app.title} - API docs",
        swagger_js_url=f"{root}/{SWAGGER}/swagger-ui-bundle.js?v={v}",
        swagger_css_url=f"{root}/{SWAGGER}/swagger-ui.css?v={v}",
        swagger_favicon_url=f"{root}/{SWAGGER}/favicon-32x32.png?v={v}",
        # no validator badge: it would ask validator.swagger.io about the spec
        swagger_ui_parameters={"validatorUrl": None},
    )
    resp.headers["Cache-Control"] = NO_CACHE
    resp.headers["X-Content-Type-Options"] = "nosniff"
    return resp
