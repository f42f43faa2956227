"""The OpenAPI description of the job API: documentation models of the documents it answers
with, the execution request body, and :func:`install`, which makes the generated schema say
what the service really does.

FastAPI derives the schema from the route signatures; for this API that alone would be thin
and partly wrong: the execution route reads its JSON body itself (so that a bad body is a
problem document, not a framework error) and would declare no body; every route would
declare FastAPI's ``422`` validation error, which the service answers as a ``400`` problem
document instead; and no route would declare its problem (``application/problem+json``)
responses. Clients (and the schemathesis fuzzing in ``tests/service/test_fuzz.py``) read this schema,
so it has to be right. The models here are used only to *document* responses
(``responses=``): routes return plain dicts, so status polling pays no validation cost.
The API as users see it is described in ``docs/interfaces/rest.md``.
"""

from __future__ import annotations

import json
from typing import Any, Literal, get_args

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel, ConfigDict, Field

from sarship.workers.request import DEVICES, MAX_AIS_FILES

PROBLEM_MEDIA = "application/problem+json"
PROBLEM_REF = "#/components/schemas/Problem"
#: A job's status (the store's ``status`` column), as a type and as its values in order.
JobStatus = Literal["accepted", "running", "successful", "failed", "dismissed"]
JOB_STATUSES: tuple[str, ...] = get_args(JobStatus)


class Problem(BaseModel):
    """An RFC 7807 problem document: every error answer of the service (docs/interfaces/rest.md)."""

    model_config = ConfigDict(extra="allow")
    type: str = Field(description="problem type URI ('about:blank': the title says it)")
    title: str = Field(description="short summary of the problem")
    detail: str = Field(description="what exactly was wrong, naming the input")
    status: int = Field(ge=400, le=599, description="the HTTP status code")


class Link(BaseModel):
    model_config = ConfigDict(extra="allow")
    href: str
    rel: str | None = None
    type: str | None = None
    title: str | None = None


class Landing(BaseModel):
    model_config = ConfigDict(extra="allow")
    title: str
    description: str
    version: str
    links: list[Link]


class Conformance(BaseModel):
    conformsTo: list[str]


class ProcessSummary(BaseModel):
    model_config = ConfigDict(extra="allow")
    id: str
    title: str
    description: str
    version: str
    jobControlOptions: list[str]
    outputTransmission: list[str]
    links: list[Link]


class ProcessList(BaseModel):
    processes: list[ProcessSummary]
    links: list[Link]


class ProcessDescription(ProcessSummary):
    inputs: dict[str, dict[str, Any]] = Field(
        description="input name -> title, description, JSON schema, minOccurs, maxOccurs"
    )
    outputs: dict[str, dict[str, Any]]


class StatusInfo(BaseModel):
    """A job's status (OGC API - Processes ``statusInfo``)."""

    model_config = ConfigDict(extra="allow")
    jobID: str
    processID: str
    type: Literal["process"]
    status: JobStatus
    message: str = Field(
        description="the failure reason or other news, one line; an accepted job whose scene "
        "is still being ingested says 'waiting for scene ID (ingest job JOBID)'"
    )
    progress: int = Field(ge=0, le=100)
    created: str
    started: str | None
    finished: str | None
    updated: str
    attempts: int = Field(ge=0, description="times the job was started (a job whose runner died is re-run)")
    links: list[Link]


class JobList(BaseModel):
    jobs: list[StatusInfo]
    links: list[Link]


class ResultLink(BaseModel):
    model_config = ConfigDict(extra="allow")
    href: str
    type: str


#: The results document: output name -> link (``detections``, ``mask``, ``metrics``, ...).
Results = dict[str, ResultLink]

#: The execution request (OGC ``execute.yaml``): the scene and the detector's parameters
#: in ``inputs``; results are always passed by reference in a results document.
EXECUTE_BODY: dict[str, Any] = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["inputs"],
                "properties": {
                    "inputs": {
                        "type": "object",
                        "required": ["scene"],
                        "description": "'scene' (a scene id or a path inside an allowed folder), optional 'device', "
                        "'channel' and 'ais', and the detector's parameters (GET /processes/{processId} lists them "
                        "with their schemas; docs/interfaces/rest.md and docs/algorithms/ in the sarship "
                        "repository describe them)",
                        "properties": {
                            "scene": {"type": "string", "minLength": 1},
                            "device": {"type": "string", "enum": list(DEVICES), "default": "auto"},
                            "channel": {"type": ["string", "null"]},
                            "ais": {
                                "description": "AIS files matched to the detections: uploaded AIS ids "
                                "(POST /ais) or paths inside an allowed folder",
                                "oneOf": [
                                    {"type": "null"},
                                    {"type": "string", "minLength": 1},
                                    {
                                        "type": "array",
                                        "items": {"type": "string", "minLength": 1},
                                        "maxItems": MAX_AIS_FILES,
                                    },
                                ],
                            },
                        },
                        "additionalProperties": {"type": ["number", "string", "null"]},
                    },
                    "outputs": {
                        "type": "object",
                        "description": "accepted and ignored: every output is returned "
                        "by reference in the results document",
                    },
                    "response": {
                        "type": "string",
                        "enum": ["document", "raw"],
                        "default": "document",
                        "description": "accepted; the results are always a document of links",
                    },
                },
            }
        }
    },
}

PREFER_DOC = (
    "'respond-async' (default: 201 and the job status) or 'respond-sync' (wait for the job and answer "
    "200 with the results document)"
)


def problems(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries: the given statuses answer a problem document."""
    text = {
        400: "invalid request (the detail names the input)",
        401: "a bearer token is needed",
        403: "the token is not valid",
        404: "no such resource",
        413: "the request body is too large",
        422: "the job did not succeed",
        503: "too many synchronous executions waiting, or the job store is busy (see Retry-After)",
        507: "the server's data folder is full",
    }
    return {c: _problem_response(text.get(c, "problem")) for c in codes}


def media(
    media_type: str, description: str, status: int = 200, schema: dict[str, Any] | None = None
) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entry of a route that answers something other than JSON (a file, an
    image, Prometheus text): its media type replaces FastAPI's default ``application/json``."""
    return {
        status: {
            "description": description,
            "content": {media_type: {"schema": schema or {"type": "string", "format": "binary"}}},
        }
    }


def _problem_response(description: str) -> dict[str, Any]:
    return {"description": description, "content": {PROBLEM_MEDIA: {"schema": {"$ref": PROBLEM_REF}}}}


def install(app: FastAPI, tokens: bool = False, protect_reads: bool = False, open_paths: tuple[str, ...] = ()) -> None:
    """Replace ``app.openapi`` by the generated schema corrected for this service, built once:

    - FastAPI's ``422`` ``HTTPValidationError`` becomes the ``400`` problem document the
      validation handler really answers (every operation with parameters or a body);
    - operations with path parameters declare ``404`` (no such job, process, scene);
    - every operation declares ``4XX``: any client error is a problem document;
    - with API tokens, the bearer scheme and the operations that need it (``401``/``403``).
    """

    def build() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        comps = schema.setdefault("components", {})
        schemas = comps.setdefault("schemas", {})
        schemas["Problem"] = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
        for path, item in schema.get("paths", {}).items():
            for method, op in item.items():
                if not isinstance(op, dict) or "responses" not in op:
                    continue
                _fix_operation(
                    path,
                    method,
                    op,
                    tokens and path not in open_paths and (protect_reads or method not in ("get", "head", "options")),
                )
        if "#/components/schemas/HTTPValidationError" not in json.dumps(schema.get("paths", {})):
            schemas.pop("HTTPValidationError", None)
            schemas.pop("ValidationError", None)
        if tokens:
            comps.setdefault("securitySchemes", {})["bearer"] = {"type": "http", "scheme": "bearer"}
        app.openapi_schema = schema
        return schema

    app.openapi = build  # type: ignore[method-assign]


def _fix_operation(path: str, method: str, op: dict[str, Any], secured: bool) -> None:
    res: dict[str, Any] = op["responses"]
    for r in res.values():  # a route that declared its own media type (media()) answers only that
        content = r.get("content", {})
        if len(content) > 1 and content.get("application/json", {}).get("schema") in ({}, None):
            content.pop("application/json")
    had_422 = res.pop("422", None) is not None
    if had_422 or op.get("parameters") or op.get("requestBody"):
        res.setdefault("400", _problem_response("invalid request: the detail names the input"))
    if "{" in path:
        res.setdefault("404", _problem_response("no such resource"))
    res.setdefault("4XX", _problem_response("any other client error: a problem document"))
    if secured:
        op["security"] = [{"bearer": []}]
        res.setdefault("401", _problem_response("a bearer token is needed"))
        res.setdefault("403", _problem_response("the token is not valid"))
