"""Schemathesis fuzzing of the live OpenAPI schema of a real ``sarship serve`` (uvicorn on
loopback, its own local Dask cluster, SQLite store, one small scene).

Every operation the server's ``/openapi.json`` lists is called with schema-valid and
schema-invalid requests (schemathesis' examples, coverage and fuzzing phases; a fixed seed
and Hypothesis' derandomized generation, so CI is reproducible; a bounded number of examples
per operation). Checked on every response: no 5xx, the status code, content type, headers
and body are the ones the schema declares, schema-invalid requests are rejected with a 4xx,
undeclared methods answer 405 with ``Allow``, and every 4xx is a problem document
``{type, title, detail}``.

The live schema is fetched as is and only *steered*: the ids of real jobs (a successful and
a dismissed one) and of the real scene are offered next to arbitrary strings, so that the
fuzzing reaches the result, tile and scene code with real data behind it, not just 404s.
Executions it submits are real (small) jobs on the small scene.
"""

from __future__ import annotations

import collections
import copy
import os
from typing import Any

import pytest

httpx = pytest.importorskip("httpx")
schemathesis = pytest.importorskip("schemathesis")
from svc import Server, data_with_scene, free_port, wait_job  # noqa: E402

#: Hypothesis examples per operation in the fuzzing phase (the examples and coverage phases add
#: their own deterministic cases, bounded by the schema); SARSHIP_FUZZ_EXAMPLES raises it for a
#: deeper run (the default keeps the suite within its time; 25, the earlier default, passes too).
MAX_EXAMPLES = int(os.environ.get("SARSHIP_FUZZ_EXAMPLES", "12"))
SEED = 20261122


@schemathesis.check
def problem_document(ctx, response, case) -> None:
    """Every 4xx is an RFC 7807 problem document that says what was wrong."""
    if not 400 <= response.status_code < 500 or case.method.upper() == "HEAD":
        return None
    ctype = (response.headers.get("content-type") or [""])[0]
    if not ctype.startswith("application/problem+json"):
        raise AssertionError(f"{response.status_code} answered with content type {ctype!r}, not a problem document")
    body = response.json()
    missing = {"type", "title", "detail"} - set(body) if isinstance(body, dict) else {"type", "title", "detail"}
    if missing:
        raise AssertionError(f"{response.status_code} problem document lacks {sorted(missing)}: {body}")
    if not all(isinstance(body[k], str) and body[k] for k in ("type", "title", "detail")):
        raise AssertionError(f"{response.status_code} problem document has empty or non-text members: {body}")
    return None


CHECKS = [
    schemathesis.checks.not_a_server_error,
    schemathesis.checks.status_code_conformance,
    schemathesis.checks.content_type_conformance,
    schemathesis.checks.response_schema_conformance,
    schemathesis.checks.response_headers_conformance,
    schemathesis.checks.negative_data_rejection,
    schemathesis.checks.unsupported_method,
    problem_document,
]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = data_with_scene(tmp_path_factory.mktemp("fuzz"))
    # sync executions wait at most 5 s (then answer 201 with the status): the run stays bounded
    srv = Server(data, free_port(), SARSHIP_MAX_UPLOAD_MB="1", SARSHIP_SYNC_TIMEOUT_S="5").start()
    yield srv
    srv.kill()  # SIGKILL to the process group: the jobs the fuzzing queued need not run to the end


@pytest.fixture(scope="module")
def real_ids(server) -> dict[str, str]:
    """A successful and a dismissed job on the small scene, and a successful job for DELETE to
    dismiss (dismissing a finished job removes its results, so DELETE gets its own job)."""
    u = server.url
    inputs = {"scene": "s1", "guard": 11, "background": 31, "min_area_px": 1}
    # submitted together (the server runs two jobs at once); the third is dismissed at once
    ok, victim, gone = (
        httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": inputs}).json()["jobID"] for _ in range(3)
    )
    httpx.delete(f"{u}/jobs/{gone}")
    assert wait_job(u, gone)["status"] == "dismissed"
    assert wait_job(u, ok)["status"] == "successful"
    assert wait_job(u, victim)["status"] == "successful"
    return {"successful": ok, "dismissed": gone, "victim": victim}


def steer(doc: dict[str, Any], ids: dict[str, str]) -> dict[str, Any]:
    """The live schema with real ids offered besides arbitrary values (generation only)."""
    doc = copy.deepcopy(doc)
    for item in doc.get("paths", {}).values():
        for method, op in item.items():
            if not isinstance(op, dict):
                continue
            jobs = sorted([ids["dismissed"], ids["victim" if method.lower() == "delete" else "successful"]])
            known = {"job_id": jobs, "scene_id": ["s1"], "jobID": jobs}
            for p in op.get("parameters", []):
                if p.get("in") == "path" and p["name"] in known and p.get("schema", {}).get("type") == "string":
                    p["schema"] = {"anyOf": [{"type": "string", "enum": known[p["name"]]}, p["schema"]]}
            body = op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema", {})
            scene = body.get("properties", {}).get("inputs", {}).get("properties", {}).get("scene")
            if scene is not None:
                body["properties"]["inputs"]["properties"]["scene"] = {"anyOf": [{"enum": ["s1"]}, scene]}
                body["example"] = {"inputs": {"scene": "s1", "guard": 11, "background": 31, "min_area_px": 1}}
    return doc


@pytest.fixture(scope="module")
def api_schema(server, real_ids):
    live = httpx.get(server.url + "/openapi.json").json()
    config = schemathesis.Config.from_dict(
        {
            "seed": SEED,
            "base-url": server.url,
            "request-timeout": 60,
            "generation": {"mode": "all", "max-examples": MAX_EXAMPLES, "deterministic": True, "database": "none"},
            "phases": {"stateful": {"enabled": False}},
        }
    )
    return schemathesis.openapi.from_dict(steer(live, real_ids), config=config)


schema = schemathesis.pytest.from_fixture("api_schema")


#: (operation, status) -> responses seen by the fuzzing (to check what it reached)
SEEN: collections.Counter = collections.Counter()


@schema.parametrize()
def test_api_fuzz(case):
    r = case.call_and_validate(checks=CHECKS, timeout=60)
    SEEN[(f"{case.method.upper()} {case.operation.path}", r.status_code)] += 1


def test_fuzzing_reached_the_real_data():
    """The steering works: the fuzzing got past 404s to real jobs, results and executions."""
    if not SEEN:
        pytest.skip("runs after test_api_fuzz in the same session")
    ok = {op for (op, code), n in SEEN.items() if code < 300}
    assert {
        "GET /jobs/{job_id}",
        "GET /jobs/{job_id}/results",
        "GET /jobs/{job_id}/results/detections",
        "POST /processes/{process_id}/execution",
        "DELETE /jobs/{job_id}",
    } <= ok, sorted(SEEN.items())
    assert sum(SEEN.values()) >= 300, sum(SEEN.values())


def test_schema_declares_the_api(server):
    """The schema says what the service does: the execution body, problem responses, no 422."""
    doc = httpx.get(server.url + "/openapi.json").json()
    ex = doc["paths"]["/processes/{process_id}/execution"]["post"]
    body = ex["requestBody"]["content"]["application/json"]["schema"]
    assert body["required"] == ["inputs"] and body["properties"]["inputs"]["required"] == ["scene"]
    assert {"201", "200", "400", "404"} <= set(ex["responses"])
    assert "Location" in ex["responses"]["201"]["headers"]
    assert {p["name"] for p in ex["parameters"]} == {"process_id", "Prefer"}
    for path, item in doc["paths"].items():
        for method, op in item.items():
            assert "422" not in op["responses"], (method, path)  # validation errors are 400 problems here
            assert "application/problem+json" in op["responses"]["4XX"]["content"], (method, path)
    assert doc["paths"]["/jobs/{job_id}"]["get"]["responses"]["200"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/StatusInfo"
    }
    assert set(doc["components"]["schemas"]["Problem"]["required"]) >= {"type", "title", "detail"}


def test_tokens_in_schema_and_odd_authorization_headers(tmp_path):
    """With API tokens the schema declares the bearer scheme where it applies, and malformed or
    non-ASCII ``Authorization`` headers are a 401/403 problem, never a 500."""
    data = tmp_path / "data"
    (data / "scenes").mkdir(parents=True)
    srv = Server(data, free_port(), SARSHIP_WORKERS="1", SARSHIP_TOKENS='["t0ken"]').start()
    try:
        doc = httpx.get(srv.url + "/openapi.json").json()
        assert doc["components"]["securitySchemes"]["bearer"] == {"type": "http", "scheme": "bearer"}
        ex = doc["paths"]["/processes/{process_id}/execution"]["post"]
        assert ex["security"] == [{"bearer": []}] and {"401", "403"} <= set(ex["responses"])
        assert "security" not in doc["paths"]["/jobs"]["get"]  # reads stay open without protect_reads
        assert httpx.get(srv.url + "/jobs").status_code == 200  # (test_service.py::test_tokens: protect_reads)
        url = srv.url + "/jobs/nosuchjob"
        for header, status in (
            (b"Bearer t\xe9st", 403),
            (b"Bearer \xff\xfe", 403),
            (b"Basic dDow", 401),
            (b"Bearer", 401),
            (b"Bearer  t0ken2", 403),
            (b"bearer t0ken", 404),
        ):
            r = httpx.delete(url, headers={"Authorization": header})
            assert r.status_code == status, (header, r.status_code, r.text)
            assert {"type", "title", "detail"} <= set(r.json()), r.text
        assert httpx.delete(url).headers["www-authenticate"] == "Bearer"
    finally:
        srv.stop()
