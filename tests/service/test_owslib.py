"""OWSLib's OGC API - Processes client, unchanged, against a real ``sarship serve``: list and
describe the processes, execute asynchronously (then follow the ``Location`` to the job and
its results) and synchronously (``Prefer: respond-sync`` returns the results document), with
and without a base URL query string (``?f=json``, which OWSLib then appends to every request).

OWSLib 0.35 has no job status or job results calls: the job is followed with
``owslib.util.http_get``, OWSLib's own transport, at the URL the service gave.
"""

from __future__ import annotations

import time

import pytest

owslib_processes = pytest.importorskip("owslib.ogcapi.processes")
from owslib.util import http_get  # noqa: E402
from svc import shared_server  # noqa: E402

SMALL = {"scene": "s1", "pfa": 1e-4, "guard": 11, "background": 31, "min_area_px": 1}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    return shared_server(tmp_path_factory.getbasetemp())  # its scene s1; one server per test process


@pytest.fixture(autouse=True)
def _clean_owslib_headers():
    """OWSLib keeps its request headers in one module-level dict that ``execute`` mutates
    (``Prefer``) for every later client: reset it so each test starts as a fresh program."""
    from owslib import ogcapi

    saved = dict(ogcapi.REQUEST_HEADERS)
    yield
    ogcapi.REQUEST_HEADERS.clear()
    ogcapi.REQUEST_HEADERS.update(saved)


def follow(url: str, timeout: float = 60.0) -> dict:
    t_end = time.time() + timeout
    while time.time() < t_end:
        st = http_get(url).json()
        if st["status"] in ("successful", "failed", "dismissed"):
            return st
        time.sleep(0.2)
    raise AssertionError(f"job at {url} did not finish: {st}")


@pytest.mark.parametrize("query", ["", "?f=json"])
def test_list_describe_execute_async(server, query):
    p = owslib_processes.Processes(server.url + query)
    assert {"conformance", "service-desc"} <= {x["rel"].rsplit("/", 1)[-1] for x in p.links}
    assert any(c.endswith("/conf/core") for c in p.conformance()["conformsTo"])
    assert "openapi" in p.api()  # the service-desc link OWSLib looks for
    procs = {x["id"]: x for x in p.processes()}
    assert {"ca_cfar", "os_cfar", "two_parameter"} <= set(procs)
    assert "async-execute" in procs["ca_cfar"]["jobControlOptions"]
    desc = p.process("ca_cfar")
    assert desc["id"] == "ca_cfar" and {"scene", "pfa", "guard"} <= set(desc["inputs"])
    assert desc["inputs"]["pfa"]["schema"]["type"] == "number"

    st = p.execute("ca_cfar", SMALL, async_=True)
    assert st["status"] in ("accepted", "running") and st["processID"] == "ca_cfar"
    location = p.response_headers["Location"]
    assert location.endswith(f"/jobs/{st['jobID']}")
    final = follow(location)
    assert final["status"] == "successful" and final["progress"] == 100, final
    res_link = next(x["href"] for x in final["links"] if x["rel"].endswith("/results"))
    results = http_get(res_link).json()
    assert set(results) >= {"detections", "mask", "metrics"}
    fc = http_get(results["detections"]["href"]).json()
    assert fc["type"] == "FeatureCollection" and len(fc["features"]) >= 5


def test_execute_sync_returns_results(server):
    p = owslib_processes.Processes(server.url)
    res = p.execute("ca_cfar", SMALL, async_=False)  # OWSLib sends Prefer: respond-sync
    assert set(res) >= {"detections", "mask", "metrics"}, res
    assert p.response_headers.get("Preference-Applied") == "respond-sync"
    metrics = http_get(res["metrics"]["href"]).json()
    assert metrics["detector"] == "ca_cfar" and metrics["detections"] >= 5
    job = http_get(p.response_headers["Location"]).json()
    assert job["status"] == "successful"


def test_bad_input_is_an_error_owslib_reports(server):
    """OWSLib raises ``RuntimeError(response text)`` on a 4xx: the problem document's detail
    reaches the user."""
    p = owslib_processes.Processes(server.url)
    with pytest.raises(RuntimeError, match="pfa"):
        p.execute("ca_cfar", {**SMALL, "pfa": 2}, async_=True)
    with pytest.raises(RuntimeError, match="no process 'nope'"):
        p.process("nope")
