"""The texture land pass's reads serve the detection pass (issue 17), so the scene is decoded
once: each tile's read is kept as Dask data and handed to its texture sample and detection
(workers/jobs.py, ``read_land_block``), within a memory budget per worker
(workers/blockcache.py). Checked: the budget setting; end to end on the in-process threaded
worker and on worker processes every detection takes its tile's land-pass read (run.json
``per_tile[*].block_from``), the mask, land mask and detections are identical to a run that
keeps none (``SARSHIP_BLOCK_CACHE_MB=0``), with land present (the read is used with its land
halo) and absent (trimmed), and no read is left on a worker after the job; a budget for part of
the tiles keeps the first ones."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zarr

from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers import blockcache
from sarship.workers.jobs import run_detection


def test_budget_setting(monkeypatch):
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "1")
    assert blockcache.limit_bytes() == 2**20
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "0")
    assert blockcache.limit_bytes() == 0
    monkeypatch.delenv("SARSHIP_BLOCK_CACHE_MB")
    assert 0 < blockcache.limit_bytes() <= 2 * 2**30
    from sarship.pipeline.errors import InputError

    for bad in ("lots", "-1", "nan", "inf"):
        monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", bad)
        with pytest.raises(InputError, match="SARSHIP_BLOCK_CACHE_MB"):
            blockcache.limit_bytes()


def test_a_bad_budget_is_one_line_and_leaves_nothing(tmp_path):
    """`sarship detect` with a bad SARSHIP_BLOCK_CACHE_MB: exit 2, one line naming it, no output."""
    from tests.cli.test_cli import assert_clean_error, sarship

    cfg = SimConfig(shape=(200, 180), ships=2, seed=3, looks=4.0, clutter="k", scr_db=20.0)
    simulate(tmp_path / "s.zarr", cfg, tile=128)
    res = sarship(
        "detect",
        tmp_path / "s.zarr",
        "--detector",
        "ca_cfar",
        "--out",
        tmp_path / "o",
        env={"SARSHIP_BLOCK_CACHE_MB": "lots"},
    )
    assert_clean_error(res, "SARSHIP_BLOCK_CACHE_MB", "lots")
    assert not (tmp_path / "o").exists()


def _outputs(d):
    g = json.loads((d / "detections.geojson").read_text())
    feats = sorted(
        (f["properties"]["bbox_px"], f["properties"]["area_px"], f["properties"]["peak"]) for f in g["features"]
    )
    return (
        np.asarray(zarr.open_array(str(d / "mask.zarr" / "mask"), mode="r")[:]),
        np.asarray(zarr.open_array(str(d / "land.zarr" / "land"), mode="r")[:]),
        feats,
    )


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
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "0")
    off = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "off", progress=False)
    assert {t["block_from"] for t in off["tiles"]["per_tile"]} == {"scene"}
    assert bool(_same_outputs(tmp_path / "on", tmp_path / "off").any()) is land


def _worker_keys(client) -> set:
    return {k for keys in client.run(lambda dask_worker: list(dask_worker.data)).values() for k in keys}


def _settled_keys(client, held: set, timeout: float = 10.0) -> set:
    """The workers' keys once the job's are released: the client forgets a run's futures when it
    returns and the scheduler tells the workers asynchronously, so a key can outlive the call by
    a few milliseconds (seen once in a fresh-clone run); polled until no more than ``held`` is
    left, or ``timeout`` seconds."""
    t_end = time.monotonic() + timeout
    keys = _worker_keys(client)
    while not keys <= held and time.monotonic() < t_end:
        time.sleep(0.05)
        keys = _worker_keys(client)
    return keys


def test_worker_processes_take_their_reads_and_release_them(tmp_path, monkeypatch, client):
    """On worker processes (the session's two, tests/conftest.py) every detection takes its
    tile's land-pass read (Dask runs it where the read is), the outputs equal the keep-none
    run's, no read is left on a worker after the job, and a budget for 4 reads keeps the first
    4 tiles' reads only."""
    cfg = SimConfig(shape=(384, 384), ships=5, seed=12, looks=4.0, clutter="k", land=True, scr_db=20.0)
    simulate(tmp_path / "s.zarr", cfg, tile=128)
    settings = {"land_mask": "texture", "pfa": 1e-5, "guard": 15, "background": 31}
    monkeypatch.delenv("SARSHIP_BLOCK_CACHE_MB", raising=False)
    held = _worker_keys(client)  # what other tests of this process left there (nothing, normally)
    on = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "on", client=client, progress=False)
    per = on["tiles"]["per_tile"]
    assert [t["block_from"] for t in per] == ["land pass"] * on["tiles"]["count"] == ["land pass"] * 9
    assert _settled_keys(client, held) <= held
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "0")
    off = run_detection(
        tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "off", client=client, progress=False
    )
    assert {t["block_from"] for t in off["tiles"]["per_tile"]} == {"scene"}
    # one read is about 390 px a side at 8 bytes (1.2 MiB): 2 workers x 2.2 MiB keep a few
    monkeypatch.setenv("SARSHIP_BLOCK_CACHE_MB", "2.2")
    part = run_detection(
        tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "part", client=client, progress=False
    )
    got = {tuple(t["index"]): t["block_from"] for t in part["tiles"]["per_tile"]}
    kept = sorted(k for k, v in got.items() if v == "land pass")
    assert 0 < len(kept) < 9 and kept == sorted(got)[: len(kept)]  # the first tiles in row order
    assert _settled_keys(client, held) <= held
    _same_outputs(tmp_path / "on", tmp_path / "off")
    _same_outputs(tmp_path / "on", tmp_path / "part")
