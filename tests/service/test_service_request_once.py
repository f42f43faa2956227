"""A REST job is one normalized request: validated once when it is posted (its detector
parameters parsed once in the API), stored as validated, and run as stored (its parameters
parsed once in the runner); its outputs are staged once, run.json written once, and published
through :func:`sarship.pipeline.run.outputs.publish` in the transaction that finishes the job.

Counted through the application's real routes, job store, runner threads and Dask cluster."""

from __future__ import annotations

import collections
import threading
import time

import pytest
from conftest import blobs_scene, write_scene


@pytest.fixture
def counted(monkeypatch):
    """Calls of the parameter parser, the request validation, the run's temporary folder,
    publication and run.json writes, by thread: ``runner`` (the job runner's threads) or
    ``api`` (the threads serving requests)."""
    import sarship.pipeline.run.outputs as outputs
    import sarship.pipeline.targets.ship_features as ship_features
    import sarship.workers.jobs as jobs
    import sarship.workers.request as request

    counts: collections.Counter = collections.Counter()

    def role() -> str:
        return "runner" if threading.current_thread().name.startswith("sarship-runner") else "api"

    def wrap(mod, name: str, key: str, when=lambda *a: True) -> None:
        f = getattr(mod, name)

        def counting(*args, **kwargs):
            if when(*args):
                counts[role(), key] += 1
            return f(*args, **kwargs)

        monkeypatch.setattr(mod, name, counting)

    wrap(request, "parse_params", "parse")
    from_inputs = request.JobRequest.from_inputs.__func__
    monkeypatch.setattr(
        request.JobRequest,
        "from_inputs",
        classmethod(lambda cls, *a, **k: (counts.update([(role(), "validate")]), from_inputs(cls, *a, **k))[1]),
    )
    wrap(jobs, "prepare_out", "stage")
    wrap(outputs, "publish", "publish")
    for mod in (jobs, ship_features):
        wrap(mod, "write_json", "run.json", lambda path, *a: str(path).endswith("run.json"))
    return counts


def test_rest_job_is_validated_parsed_staged_and_published_once(tmp_path, client, counted):
    from fastapi.testclient import TestClient

    from sarship.service.app import create_app
    from sarship.service.settings import Settings

    data = tmp_path / "data"
    write_scene(data / "scenes" / "s1.zarr", {"intensity": blobs_scene((96, 96), seed=5, n=4)}, tile=64, looks=2.0)
    settings = Settings(data=data, workers=1)
    with TestClient(create_app(settings, client=client)) as http:
        r = http.post(
            "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "pfa": "1e-6", "land_mask": "none"}}
        )
        assert r.status_code == 201, r.text
        job_id = r.json()["jobID"]
        # the API's part, once the POST has answered (the runner may have started the job already)
        assert {k: n for k, n in counted.items() if k[0] == "api"} == {("api", "validate"): 1, ("api", "parse"): 1}, (
            counted
        )
        stored = http.app.state.store.get(job_id)["inputs"]
        assert stored == {"scene": "s1", "device": "auto", "pfa": "1e-6", "land_mask": "none"}  # normalized
        t_end = time.monotonic() + 60
        while (job := http.get(f"/jobs/{job_id}").json())["status"] not in ("successful", "failed"):
            assert time.monotonic() < t_end, job
            time.sleep(0.05)
    assert job["status"] == "successful", job
    assert counted == {
        ("api", "validate"): 1,
        ("api", "parse"): 1,
        ("runner", "parse"): 1,
        ("runner", "stage"): 1,
        ("runner", "run.json"): 1,
        ("runner", "publish"): 1,
    }, counted
    out = data / "jobs" / job_id
    assert sorted(p.name for p in out.iterdir()) == ["detections.geojson", "mask.zarr", "run.json"]


def test_stored_request_keeps_its_parse_and_a_new_param_updates_it():
    from sarship.workers.request import JobRequest

    req = JobRequest.from_inputs("ca_cfar", {"scene": "s1", "pfa": "1e-6", "land_mask": "a.npy"})
    parsed = req.detector_params()
    assert req.detector_params() is parsed and req.model_copy(update={"scene": "/x"}).detector_params() is parsed
    raster = req.with_param("land_mask", "/r/land.zarr")
    assert raster.params["land_mask"] == "/r/land.zarr"
    assert raster.detector_params() == JobRequest.from_inputs("ca_cfar", raster.inputs()).detector_params()
    other = req.model_copy(update={"detector": "os_cfar"})
    assert other.detector_params() is not parsed and type(other.detector_params()).__name__ != type(parsed).__name__
    again = JobRequest.from_stored("ca_cfar", req.inputs())
    assert again.inputs() == req.inputs() and again.detector_params() == parsed
