"""The landing page (``GET /``: the API's links, or the web page for a browser) and
``GET /conformance`` (the OGC API - Processes conformance classes)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse

from sarship.pipeline import __version__
from sarship.service.common import base_url
from sarship.service.health import dashboard_link
from sarship.service.openapi import Conformance, Landing

router = APIRouter()

OGC = "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/"
CONFORMANCE = [OGC + c for c in ("core", "json", "job-list", "dismiss", "oas30")]


@router.get("/", response_model=None, responses={200: {"model": Landing}})
def landing(request: Request) -> dict[str, Any] | RedirectResponse:
    b = base_url(request)
    if "text/html" in request.headers.get("accept", "") and request.query_params.get("f") != "json":
        return RedirectResponse(f"{b}/ui/", status_code=303)  # a browser: the web page (?f=json: this)
    return {
        "title": "sarship",
        "description": "Ship detection in SAR scenes",
        "version": __version__,
        "links": [
            {"href": f"{b}/", "rel": "self", "type": "application/json"},
            {
                "href": f"{b}/openapi.json",
                "rel": "service-desc",
                "type": "application/vnd.oai.openapi+json;version=3.0",
            },
            {
                "href": f"{b}/conformance",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/conformance",
                "type": "application/json",
            },
            {
                "href": f"{b}/processes",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes",
                "type": "application/json",
            },
            {"href": f"{b}/jobs", "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list", "type": "application/json"},
            # the dashboard only where the scheduler serves one (bokeh installed)
            *(
                [{"href": f"{b}/dashboard", "rel": "related", "title": "Dask dashboard"}]
                if dashboard_link(request)
                else []
            ),
            {"href": f"{b}/ui/", "rel": "alternate", "type": "text/html", "title": "web page"},
        ],
    }


@router.get("/conformance", response_model=None, responses={200: {"model": Conformance}})
def conformance() -> dict[str, list[str]]:
    return {"conformsTo": CONFORMANCE}
