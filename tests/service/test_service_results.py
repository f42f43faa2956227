"""Job products against a real ``sarship serve`` (uvicorn on loopback, local Dask, SQLite): the
mask as a COG and as a zipped Zarr, XYZ tiles and their TileJSON, the STAC item, and scores in
the metrics of a simulated scene with ground truth."""

from __future__ import annotations

import io
import json
import math
import threading
import zipfile

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
tifffile = pytest.importorskip("tifffile")
from conftest import blobs_scene, write_scene  # noqa: E402
from svc import check_problem, shared_server, wait_job  # noqa: E402

GEO_ATTRS = {
    "sensor": "SENTINEL-1A IW",
    "product": "S1A_IW_GRDH_1SDV_20210601T102030_20210601T102055_000000",
    "polarisations": ["vv"],
    "acquired": "2021-06-01T10:20:30",
    "crs": "EPSG:32631",
    "transform": [500000.0, 10.0, 0.0, 5000000.0, 0.0, -10.0],
    "pixel_spacing_m": [10.0, 10.0],
}


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    from sarship.pipeline.simulate import SimConfig, simulate, validate

    # the test process's shared server, with this module's scenes (names of its own) in its folder
    srv = shared_server(tmp_path_factory.getbasetemp())
    data = srv.data
    write_scene(
        data / "scenes" / "res_geo.zarr",
        {"intensity": blobs_scene((300, 260), looks=2.0, seed=3)},
        tile=128,
        looks=2.0,
        **GEO_ATTRS,
    )
    cfg = validate(
        SimConfig(
            shape=(300, 260),
            ships=5,
            seed=1,
            looks=4,
            clutter="gamma",
            scr_db=20,
            length_m=(60, 150),
            pixel_spacing_m=(5.0, 5.0),
        )
    )
    simulate(data / "scenes" / "sim.zarr", cfg, tile=128)  # truth: scenes/sim.zarr.truth.geojson
    u = srv.url + "/processes/ca_cfar/execution"
    geo = httpx.post(u, json={"inputs": {"scene": "res_geo", "guard": 11, "background": 31, "min_area_px": 1}})
    sim = httpx.post(u, json={"inputs": {"scene": "sim", "guard": 21, "background": 41}})
    jobs = {"geo": geo.json()["jobID"], "sim": sim.json()["jobID"]}
    for j in jobs.values():
        assert wait_job(srv.url, j)["status"] == "successful"
    return srv, jobs


def stored_mask(srv, job_id):
    import zarr

    return zarr.open_group(str(srv.data / "jobs" / job_id / "mask.zarr"), mode="r")["mask"][:]


def test_mask_is_a_cog_and_a_zarr_zip(env):
    srv, jobs = env
    jid = jobs["geo"]
    url = f"{srv.url}/jobs/{jid}/results/mask"
    r = httpx.get(url)
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/tiff; application=geotiff")
    assert "profile=cloud-optimized" in r.headers["content-type"]
    mask = stored_mask(srv, jid)
    with tifffile.TiffFile(io.BytesIO(r.content)) as tif:
        assert np.array_equal(tif.asarray(), mask) and mask.sum() > 0
        assert [lv.shape for lv in tif.series[0].levels] == [(300, 260), (150, 130)]
        assert all(p.is_tiled and p.tilewidth == 256 and p.compression == 8 for p in tif.pages)
        assert tif.geotiff_metadata["ProjectedCSTypeGeoKey"] == 32631
        assert tif.gdal_structural_metadata["LAYOUT"] == "IFDS_BEFORE_DATA"
    from tests.service.test_products import cog_layout_errors

    assert cog_layout_errors(srv.data / "jobs" / jid / "mask.tif") == []
    assert "immutable" in r.headers["cache-control"]
    again = httpx.get(url, headers={"If-None-Match": r.headers["etag"]})
    assert again.status_code == 304 and not again.content
    z = httpx.get(url + "?f=zarr")
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    import zarr

    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        assert "zarr.json" in zf.namelist() and "mask/zarr.json" in zf.namelist()
    path = srv.data.parent / "mask.zarr.zip"
    path.write_bytes(z.content)
    assert np.array_equal(zarr.open_group(zarr.storage.ZipStore(path, mode="r"), mode="r")["mask"][:], mask)
    check_problem(httpx.get(url + "?f=png"), 400, "'f'")
    check_problem(httpx.get(f"{srv.url}/jobs/nosuchjob/results/mask"), 404, "nosuchjob")


def test_concurrent_first_mask_requests(env):
    srv, jobs = env
    jid = jobs["sim"]
    assert not (srv.data / "jobs" / jid / "mask.tif").exists()  # first requests below
    bodies, errors = [], []

    def get():
        try:
            r = httpx.get(f"{srv.url}/jobs/{jid}/results/mask", timeout=60)
            assert r.status_code == 200
            bodies.append(r.content)
        except Exception as exc:
            errors.append(exc)

    ts = [threading.Thread(target=get) for _ in range(6)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errors and len(bodies) == 6 and len(set(bodies)) == 1
    assert np.array_equal(tifffile.imread(io.BytesIO(bodies[0])), stored_mask(srv, jid))


def rgba(r) -> np.ndarray:
    from PIL import Image

    assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    img = Image.open(io.BytesIO(r.content))
    assert img.mode == "RGBA" and img.size == (256, 256)
    return np.asarray(img)


def test_tiles_and_tilejson(env):
    from sarship.service.cog import maxpool

    srv, jobs = env
    jid = jobs["geo"]
    tj = httpx.get(f"{srv.url}/jobs/{jid}/tiles.json").json()
    Z = max(0, math.ceil(math.log2(300 / 256)))
    grid = tj.pop(
        "lonlat"
    )  # the scene is georeferenced: the lon/lat of its pixel grid (tests/service/test_quicklook.py)
    assert grid["rows"][-1] == 300 and grid["cols"][-1] == 260 and len(grid["lon"]) == len(grid["rows"])
    assert tj == {
        "tilejson": "3.0.0",
        "tiles": [f"{srv.url}/jobs/{jid}/tiles/{{z}}/{{x}}/{{y}}.png"],
        "minzoom": 0,
        "maxzoom": Z,
        "tileSize": 256,
        "width": 260,
        "height": 300,
    }
    tile_url = tj["tiles"][0]
    mask = stored_mask(srv, jid) > 0
    red = np.array([255, 40, 40, 255], np.uint8)
    full = np.zeros((512, 512, 4), np.uint8)  # the four zoom-1 tiles, stitched, are the scene at 1:1
    for y in range(2):
        for x in range(2):
            r = httpx.get(tile_url.format(z=1, x=x, y=y))
            full[y * 256 : (y + 1) * 256, x * 256 : (x + 1) * 256] = rgba(r)
    assert (full[:300, :260, 3] == 255).all() and (full[300:, :, 3] == 0).all() and (full[:, 260:, 3] == 0).all()
    assert np.array_equal((full[:300, :260] == red).all(-1), mask)
    z0 = rgba(httpx.get(tile_url.format(z=0, x=0, y=0)))
    assert np.array_equal((z0[:150, :130] == red).all(-1), maxpool(mask.astype(np.uint8), 2) > 0)  # max-pooled
    assert (z0[150:, :, 3] == 0).all() and (z0[:, 130:, 3] == 0).all()
    # grey matches across neighbouring tiles: zoom 0 samples the same pixels the zoom-1 tiles show
    scene_only = [rgba(httpx.get(tile_url.format(z=1, x=x, y=y) + "?layers=scene")) for y in range(2) for x in range(2)]
    s0, s1, s2, s3 = (t[..., 0] for t in scene_only)
    stitched = np.block([[s0, s1], [s2, s3]])
    g0 = rgba(httpx.get(tile_url.format(z=0, x=0, y=0) + "?layers=scene"))[..., 0]
    assert np.array_equal(g0[:150, :130], stitched[:300:2, :260:2])
    only_mask = rgba(httpx.get(tile_url.format(z=1, x=0, y=0) + "?layers=mask"))
    assert np.array_equal(only_mask[..., 3] > 0, mask[:256, :256])
    r = httpx.get(tile_url.format(z=1, x=1, y=1))
    assert "immutable" in r.headers["cache-control"] and r.headers["etag"]
    assert httpx.get(tile_url.format(z=1, x=1, y=1), headers={"If-None-Match": r.headers["etag"]}).status_code == 304
    base = f"{srv.url}/jobs/{jid}/tiles"
    check_problem(httpx.get(f"{base}/0/0/0.png?layers=sea"), 400, "sea")
    check_problem(httpx.get(f"{base}/0/0/0.png?layers="), 400, "layers")
    check_problem(httpx.get(f"{base}/2/0/0.png"), 404, "zoom")
    check_problem(httpx.get(f"{base}/1/2/0.png"), 404, "x is in 0..1")
    check_problem(httpx.get(f"{base}/0/0/1.png"), 404)
    check_problem(httpx.get(f"{base}/1/-1/0.png"), 404)
    check_problem(httpx.get(f"{base}/a/0/0.png"), 400)
    check_problem(httpx.get(f"{srv.url}/jobs/nosuchjob/tiles.json"), 404, "nosuchjob")
    check_problem(httpx.get(f"{srv.url}/jobs/nosuchjob/tiles/0/0/0.png"), 404, "nosuchjob")


def test_stac_item(env):
    from sarship.pipeline import __version__

    srv, jobs = env
    jid = jobs["geo"]
    res = httpx.get(f"{srv.url}/jobs/{jid}/results").json()
    assert {"detections", "mask", "metrics", "stac"} <= set(res)
    r = httpx.get(res["stac"]["href"])
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/geo+json")
    item = r.json()
    assert item["type"] == "Feature" and item["stac_version"] == "1.0.0" and item["id"] == jid
    exts = item["stac_extensions"]
    assert "https://stac-extensions.github.io/sar/v1.1.0/schema.json" in exts
    assert "https://stac-extensions.github.io/processing/v1.1.0/schema.json" in exts
    assert all(e.startswith("https://stac-extensions.github.io/") and e.endswith("/schema.json") for e in exts)
    p = item["properties"]
    assert p["datetime"] == "2021-06-01T10:20:30Z" and p["created"].endswith("Z")  # the scene's acquisition
    assert (p["sar:instrument_mode"], p["sar:frequency_band"], p["sar:polarizations"]) == ("IW", "C", ["VV"])
    assert p["sar:product_type"] == "GRD" and p["sar:looks_equivalent_number"] == 2.0
    assert p["processing:software"] == {"sarship": __version__} and p["processing:level"] == "L2"
    assert "ca_cfar" in p["processing:lineage"] and "guard=11" in p["processing:lineage"]
    assert p["proj:code"] == "EPSG:32631" and p["proj:shape"] == [300, 260]
    assert p["proj:transform"] == [10.0, 0.0, 500000.0, 0.0, -10.0, 5000000.0]
    assert item["geometry"]["type"] == "Polygon" and len(item["bbox"]) == 4
    lon, lat = zip(*item["geometry"]["coordinates"][0])
    assert item["bbox"] == [min(lon), min(lat), max(lon), max(lat)] and 2.9 < lon[0] < 3.1 and 45 < lat[0] < 45.2
    assert {"mask", "detections", "metrics", "preview", "scene"} <= set(item["assets"])
    assert item["assets"]["mask"]["roles"] == ["data"] and item["assets"]["preview"]["roles"] == ["thumbnail"]
    for name, a in item["assets"].items():
        got = httpx.get(a["href"], timeout=60)
        assert got.status_code == 200, (name, a["href"], got.text[:200])
        assert got.headers["content-type"].split(";")[0] == a["type"].split(";")[0], (name, got.headers)
    rels = {ln["rel"]: ln["href"] for ln in item["links"]}
    assert rels["self"] == res["stac"]["href"]
    assert all(httpx.get(ln["href"]).status_code == 200 for ln in item["links"])
    # a simulated scene: no georeference (null geometry, no bbox), no SAR mission: no sar fields
    sim = httpx.get(f"{srv.url}/jobs/{jobs['sim']}/results/stac").json()
    assert sim["geometry"] is None and "bbox" not in sim
    assert not any(k.startswith("sar:") for k in sim["properties"])
    assert not any("/sar/" in e for e in sim["stac_extensions"])
    from sarship.pipeline.scene import open_scene

    assert sim["properties"]["datetime"] == open_scene(srv.data / "scenes" / "sim.zarr").attrs["acquired"]
    check_problem(httpx.get(f"{srv.url}/jobs/nosuchjob/results/stac"), 404, "nosuchjob")


def test_metrics_scores_when_the_scene_has_truth(env):
    srv, jobs = env
    met = httpx.get(f"{srv.url}/jobs/{jobs['sim']}/results/metrics").json()
    truth = json.loads((srv.data / "scenes" / "sim.zarr.truth.geojson").read_text())
    n = sum(1 for f in truth["features"] if not f["properties"].get("difficult"))
    s = met["scores"]
    assert s["n_truth"] == n == 5 and s["pd"] > 0.8 and s["n_hit"] <= s["n_detections"] == met["detections"]
    assert {"fom", "precision", "f1", "n_false", "n_missed"} <= set(s)
    assert (srv.data / "jobs" / jobs["sim"] / "scores.json").is_file()  # computed once, cached
    assert httpx.get(f"{srv.url}/jobs/{jobs['sim']}/results/metrics").json()["scores"] == s
    geo = httpx.get(f"{srv.url}/jobs/{jobs['geo']}/results/metrics").json()
    assert "scores" not in geo and geo["detector"] == "ca_cfar"
    # run.json names the scene and outputs as a client does, never by the server's paths
    for doc in (met, geo):
        text = json.dumps(doc)
        assert str(srv.data) not in text and str(srv.data.resolve()) not in text, text[:300]
    assert met["scene"]["path"] == "sim.zarr"
