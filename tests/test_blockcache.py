"""workers/blockcache.py (issue 17): the texture land pass's reads serve the detection pass on
``sarship detect``'s in-process threaded worker, so the scene is decoded once. Checked: the
cache's bounded put/take/drop; end to end through the local threaded cluster the detection pass
takes every tile's block from the land pass (run.json ``per_tile[*].block_from``), and the mask,
land mask and detections are identical to a run with the cache off (``SARSHIP_BLOCK_CACHE_MB=0``),
with land present (the kept block is used with its land halo) and absent (trimmed); nothing is
left in the cache after a job."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers import blockcache
from sarship.workers.jobs import run_detection


def test_put_take_drop_and_limit(monkeypatch):
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "1")  # 1 MiB
    a = np.zeros((256, 256), np.float32)  # 256 KiB
    assert blockcache.put("t1", (0, 0), a) and blockcache.put("t1", (0, 1), a) and blockcache.put("t2", (0, 0), a)
    assert blockcache.held_bytes() == 3 * a.nbytes
    assert not blockcache.put("t2", (0, 1), np.zeros((400, 400), np.float32))  # 625 KiB: over the limit
    assert blockcache.take("t1", (0, 0)) is a and blockcache.take("t1", (0, 0)) is None
    assert blockcache.drop("t1") == 1 and blockcache.drop("t2") == 1 and blockcache.held_bytes() == 0
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "0")
    assert not blockcache.put("t3", (0, 0), a) and blockcache.held_bytes() == 0
    monkeypatch.delenv("SARSHIP_BLOCK_CACHE_MB")
    assert 0 < blockcache.limit_bytes() <= 2 * 2**30


def _outputs(d):
    g = json.loads((d / "detections.geojson").read_text())
    feats = sorted((f["properties"]["bbox_px"], f["properties"]["area_px"], f["properties"]["peak"])
                   for f in g["features"])
    return (np.asarray(zarr.open_array(str(d / "mask.zarr" / "mask"), mode="r")[:]),
            np.asarray(zarr.open_array(str(d / "land.zarr" / "land"), mode="r")[:]), feats)


def _same_outputs(a, b) -> np.ndarray:
    """Mask, land mask and detections of two runs identical (at least 3 ships); the land mask."""
    m_a, l_a, f_a = _outputs(a)
    m_b, l_b, f_b = _outputs(b)
    np.testing.assert_array_equal(m_a, m_b)
    np.testing.assert_array_equal(l_a, l_b)
    assert f_a == f_b and len(f_a) >= 3
    return l_a


@pytest.mark.parametrize("land", [True, False])
def test_detection_reuses_land_pass_reads(tmp_path, monkeypatch, land):
    cfg = SimConfig(shape=(400, 340), ships=5, seed=11, looks=4.0, clutter="k", land=land, scr_db=20.0)
    simulate(tmp_path / "s.zarr", cfg, tile=128)
    settings = {"land_mask": "texture", "pfa": 1e-5, "guard": 15, "background": 31}
    monkeypatch.delenv("SARSHIP_BLOCK_CACHE_MB", raising=False)
    on = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "on", progress=False)
    assert on["land"]["land"] is land
    assert [t["block_from"] for t in on["tiles"]["per_tile"]] == ["land pass"] * on["tiles"]["count"]
    assert blockcache.held_bytes() == 0
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "0")
    off = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "off", progress=False)
    assert {t["block_from"] for t in off["tiles"]["per_tile"]} == {"scene"}
    assert bool(_same_outputs(tmp_path / "on", tmp_path / "off").any()) is land


def test_worker_processes_keep_and_drop_blocks(tmp_path, monkeypatch):
    """On a cluster of worker processes each tile's detection is sent to the worker that kept its
    block; the outputs equal the cache-off run's and no worker holds a block after the job."""
    from distributed import Client, LocalCluster

    cfg = SimConfig(shape=(384, 384), ships=5, seed=12, looks=4.0, clutter="k", land=True, scr_db=20.0)
    simulate(tmp_path / "s.zarr", cfg, tile=128)
    settings = {"land_mask": "texture", "pfa": 1e-5, "guard": 15, "background": 31}
    monkeypatch.delenv("SARSHIP_BLOCK_CACHE_MB", raising=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
            Client(cl) as client:
        on = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "on", client=client,
                           progress=False)
        kept = [t["block_from"] for t in on["tiles"]["per_tile"]]
        assert kept.count("land pass") >= on["tiles"]["count"] // 2, kept
        assert set(client.run(blockcache.held_bytes).values()) == {0}
        client.run(lambda: __import__("os").environ.__setitem__("SARSHIP_BLOCK_CACHE_MB", "0"))
        off = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "off", client=client,
                            progress=False)
        assert {t["block_from"] for t in off["tiles"]["per_tile"]} == {"scene"}
    _same_outputs(tmp_path / "on", tmp_path / "off")
