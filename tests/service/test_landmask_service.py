"""``land_mask`` through a real ``sarship serve`` (uvicorn on loopback, local Dask, SQLite): the
parameter in the process schema (so the web form offers it), a texture job whose quicklook
(``preview.png``) and ``?layers=land`` tiles show the land tinted blue, a FILE mask inside the
scene folder, and FILE paths outside the allowed folders refused with a 400."""

from __future__ import annotations

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
from svc import blue, check_problem, png, shared_server, wait_job  # noqa: E402


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    import zarr

    from sarship.pipeline.simulate import SimConfig, _land_mask, simulate
    from sarship.pipeline.simulate.model import _model

    root = tmp_path_factory.mktemp("landsvc")  # (outside the server's folders)
    # the test process's shared server, with this module's scene and mask (names of its own) in its folder
    srv = shared_server(tmp_path_factory.getbasetemp())
    data = srv.data
    cfg = SimConfig(
        shape=(320, 288), ships=3, seed=3, looks=4.0, clutter="k", land=True, scr_db=20.0, length_m=(60.0, 150.0)
    )
    simulate(data / "scenes" / "coast.zarr", cfg, tile=128)
    truth = _land_mask(cfg, _model(cfg).land, 0, 320, 0, 288)
    np.save(data / "scenes" / "land.npy", truth.astype(np.uint8))
    np.save(root / "outside.npy", truth.astype(np.uint8))
    u = srv.url + "/processes/ca_cfar/execution"
    jobs = {}
    for name, extra in (
        ("texture", {"land_mask": "texture"}),
        ("none", {"land_mask": "none"}),
        ("file", {"land_mask": "land.npy"}),
    ):
        r = httpx.post(u, json={"inputs": {"scene": "coast", "guard": 21, "background": 41, **extra}})
        assert r.status_code == 201, r.text
        jobs[name] = r.json()["jobID"]
    for j in jobs.values():
        assert wait_job(srv.url, j, timeout=240)["status"] == "successful"
    stored = {
        k: np.asarray(zarr.open_group(str(data / "jobs" / j / "land.zarr"), mode="r")["land"][...]) > 0
        for k, j in jobs.items()
        if k != "none"
    }
    return srv, jobs, truth, stored, root


def test_schema_offers_land_mask(env):
    srv, *_ = env
    p = httpx.get(srv.url + "/processes/os_cfar").json()
    assert "land_mask" in p["inputs"], list(p["inputs"])
    assert "texture" in p["inputs"]["land_mask"]["description"]


def test_quicklook_shows_land(env):
    """The preview of a texture job is tinted blue exactly over the land of land.zarr (at the
    preview's stride), the job without a land mask has no tint; run.json lists land.zarr."""
    srv, jobs, truth, stored, _ = env
    img = png(httpx.get(f"{srv.url}/jobs/{jobs['texture']}/preview.png?size=512"))
    assert img.shape[:2] == (320, 288)
    L = stored["texture"]
    assert (L & truth).sum() >= 0.99 * truth.sum()
    b = blue(img)
    assert b[L].mean() > 0.95, b[L].mean()
    assert b[~L].mean() < 0.01
    assert not blue(png(httpx.get(f"{srv.url}/jobs/{jobs['none']}/preview.png?size=512"))).any()
    import json

    run = json.loads((srv.data / "jobs" / jobs["texture"] / "run.json").read_text())
    assert run["outputs"]["land.zarr"] == str((srv.data / "jobs" / jobs["texture"] / "land.zarr").resolve())
    assert run["land"]["source"] == "texture" and run["land"]["land"] is True
    run0 = json.loads((srv.data / "jobs" / jobs["none"] / "run.json").read_text())
    assert "land.zarr" not in run0["outputs"] and run0["land"] is None


def test_land_tile_layer(env):
    srv, jobs, truth, stored, _ = env
    base = f"{srv.url}/jobs/{jobs['texture']}/tiles"
    t = png(httpx.get(f"{base}/1/0/0.png?layers=scene,land"))
    L = stored["texture"][:256, :256]
    assert blue(t[:256, :256])[L].mean() > 0.95 and not blue(t[:256, :256])[~L].any()
    assert not blue(png(httpx.get(f"{base}/1/0/0.png"))).any()  # the default layers stay scene, mask


def test_file_mask_and_refusals(env):
    """A FILE inside the scene folder (relative to it) is the job's land.zarr; a FILE outside the
    allowed folders, or missing, is a 400 naming land_mask (nothing is run)."""
    srv, jobs, truth, stored, root = env
    assert np.array_equal(stored["file"], truth)
    u = srv.url + "/processes/ca_cfar/execution"
    check_problem(
        httpx.post(u, json={"inputs": {"scene": "coast", "land_mask": str(root / "outside.npy")}}),
        400,
        "land_mask",
        "outside the allowed scene folders",
    )
    check_problem(
        httpx.post(u, json={"inputs": {"scene": "coast", "land_mask": "nope.npy"}}), 400, "land_mask", "no file"
    )
    check_problem(httpx.post(u, json={"inputs": {"scene": "coast", "land_window": 8}}), 400, "land_window")
