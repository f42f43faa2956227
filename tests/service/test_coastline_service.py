"""``land_mask=coastline`` through a real ``sarship serve`` (uvicorn on loopback, local Dask, SQLite):
the parameters in the process schema (the web form offers them), a coastline job on a georeferenced
simulated scene whose quicklook shows the GSHHG land tinted blue exactly where ``land.zarr`` has it,
and a coastline job on a scene without georeference refused with a 400 when posted (no job)."""

from __future__ import annotations

import json

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
from conftest import write_scene  # noqa: E402
from svc import Server, blue, check_problem, free_port, png, wait_job  # noqa: E402


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    import zarr

    from sarship.pipeline.simulate import SimConfig, _land_mask, simulate
    from sarship.pipeline.simulate.model import _model

    root = tmp_path_factory.mktemp("coastsvc")
    data = root / "data"
    (data / "scenes").mkdir(parents=True)
    cfg = SimConfig(
        shape=(320, 288),
        ships=3,
        seed=3,
        looks=4.0,
        clutter="k",
        land=True,
        scr_db=20.0,
        length_m=(60.0, 150.0),
        geo=(10.6, 59.8),
    )
    simulate(data / "scenes" / "fjord.zarr", cfg, tile=128)
    truth = _land_mask(cfg, _model(cfg).land, 0, 320, 0, 288)
    rng = np.random.default_rng(1)
    write_scene(
        data / "scenes" / "plain.zarr",
        {"intensity": rng.gamma(4.0, 0.25, (64, 64)).astype(np.float32)},
        tile=64,
        looks=4.0,
    )
    srv = Server(data, free_port()).start()
    try:
        r = httpx.post(
            srv.url + "/processes/ca_cfar/execution",
            json={
                "inputs": {
                    "scene": "fjord",
                    "guard": 21,
                    "background": 41,
                    "land_mask": "coastline",
                    "land_buffer_m": 100,
                }
            },
        )
        assert r.status_code == 201, r.text
        job = r.json()["jobID"]
        assert wait_job(srv.url, job, timeout=240)["status"] == "successful"
        stored = np.asarray(zarr.open_group(str(data / "jobs" / job / "land.zarr"), mode="r")["land"][...]) > 0
        yield srv, job, truth, stored
    finally:
        srv.stop()


def test_schema_offers_coastline(env):
    srv, *_ = env
    p = httpx.get(srv.url + "/processes/ca_cfar").json()
    assert "coastline" in p["inputs"]["land_mask"]["description"]
    assert "land_buffer_m" in p["inputs"], list(p["inputs"])


def test_coastline_job_quicklook_shows_the_shoreline_land(env):
    srv, job, truth, stored = env
    assert not (truth & ~stored).any() and (stored & ~truth).any()  # the land and its 100 m buffer
    img = png(httpx.get(f"{srv.url}/jobs/{job}/preview.png?size=512"))
    assert img.shape[:2] == (320, 288)
    b = blue(img)
    assert b[stored].mean() > 0.95 and b[~stored].mean() < 0.01
    run = json.loads((srv.data / "jobs" / job / "run.json").read_text())
    assert run["land"]["source"] == "coastline" and run["land"]["buffer_m"] == 100.0
    fc = json.loads((srv.data / "jobs" / job / "detections.geojson").read_text())
    mask = np.zeros_like(stored)
    for f in fc["features"]:
        r0, c0, r1, c1 = f["properties"]["bbox_px"]
        mask[r0:r1, c0:c1] = True
    assert not (mask & truth).any()  # no detection box reaches the land


def test_coastline_on_a_scene_without_georeference_is_a_400(env):
    srv, *_ = env
    check_problem(
        httpx.post(
            srv.url + "/processes/ca_cfar/execution",
            json={"inputs": {"scene": "plain", "land_mask": "coastline+texture"}},
        ),
        400,
        "land_mask",
        "georeferenced",
    )
