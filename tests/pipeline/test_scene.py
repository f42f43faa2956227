"""The scene store: Zarr v3 layout, xarray compatibility, sharded tiles, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
import zarr

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import atomic_store, create_scene, finalize_scene, open_scene
from sarship.workers.jobs import run_detection
from tests.conftest import blobs_scene, write_scene


def test_sharded_tiles_read_by_xarray_and_detect(tmp_path, client):
    x = blobs_scene((1100, 1050), looks=2.0, seed=9, n=30)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=1024, looks=2.0, pixel_spacing_m=[5.0, 5.0])
    sc = open_scene(scene)
    arr = sc.array("intensity")
    assert sc.tile == 1024 and arr.shards == (1024, 1024) and arr.chunks == (512, 512)
    ds = xr.open_zarr(scene)
    assert ds.attrs["kind"] == "intensity" and ds.attrs["pixel_spacing_m"] == [5.0, 5.0]
    np.testing.assert_array_equal(ds["intensity"].values, x)
    settings = {"pfa": "1e-4", "guard": "11", "background": "31"}
    run_detection(scene, "ca_cfar", settings, out_dir=tmp_path / "a", client=client, progress=False)
    run_detection(scene, "ca_cfar", settings, out_dir=tmp_path / "b", tile=300, client=client, progress=False)
    ma = zarr.open_array(str(tmp_path / "a" / "mask.zarr" / "mask"))
    mb = zarr.open_array(str(tmp_path / "b" / "mask.zarr" / "mask"))
    assert ma.shards == (1024, 1024)
    dm = xr.open_zarr(tmp_path / "a" / "mask.zarr")
    assert dm["mask"].dims == ("y", "x") and dm.attrs["detector"] == "ca_cfar"
    np.testing.assert_array_equal(ma[:], mb[:])
    fa = json.loads((tmp_path / "a" / "detections.geojson").read_text())["features"]
    fb = json.loads((tmp_path / "b" / "detections.geojson").read_text())["features"]
    assert fa == fb and len(fa) >= 10


def test_processing_tile_doubles_the_stored_tile_for_large_scenes_only():
    """The default processing tile: the stored tile, doubled up to 4096 while the scene keeps at
    least 32 tiles of the doubled size; always a multiple of the stored tile."""
    from sarship.pipeline.scene import AUTO_TILE_MAX, AUTO_TILE_MIN_COUNT, processing_tile

    assert (AUTO_TILE_MAX, AUTO_TILE_MIN_COUNT) == (4096, 32)
    assert processing_tile((25000, 16700), 2048) == 4096  # the band: 7 x 5 = 35 tiles of 4096
    assert processing_tile((25000, 16700), 512) == 4096
    assert processing_tile((16384, 16384), 2048) == 2048  # 16 tiles of 4096: too few
    assert processing_tile((1500, 21000), 2048) == 2048  # an IW SLC burst
    assert processing_tile((8192, 8192), 2048) == 2048
    assert processing_tile((301, 257), 64) == 64
    assert processing_tile((1024, 1024), 64) == 128  # 64 tiles of 128; 16 of 256
    assert processing_tile((24576, 16384), 2048) == 2048  # 6 x 4 = 24 tiles of 4096: too few
    assert processing_tile((20480, 24576), 4096) == 4096  # already at the cap


def test_a_large_scene_runs_in_doubled_tiles_with_the_same_detections(tmp_path, client):
    """A scene of 32+ tiles of twice its stored tile is processed in the doubled tile by default
    (recorded in run.json), with the mask and detections of a run in its stored tile."""
    x = blobs_scene((720, 720), looks=2.0, seed=4, n=40)  # 36 tiles of 128 (the least is 32), 144 of 64
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=2.0)
    settings = {"pfa": "1e-4", "guard": "11", "background": "31"}
    a = run_detection(scene, "ca_cfar", settings, out_dir=tmp_path / "a", client=client, progress=False)
    b = run_detection(scene, "ca_cfar", settings, out_dir=tmp_path / "b", tile=64, client=client, progress=False)
    assert (a["tiles"]["size"], a["tiles"]["size_source"], a["tiles"]["count"]) == (128, "scene tile x 2", 36)
    assert (b["tiles"]["size"], b["tiles"]["size_source"]) == (64, "given")
    np.testing.assert_array_equal(
        zarr.open_array(str(tmp_path / "a" / "mask.zarr" / "mask"))[:],
        zarr.open_array(str(tmp_path / "b" / "mask.zarr" / "mask"))[:],
    )
    fa = json.loads((tmp_path / "a" / "detections.geojson").read_text())["features"]
    fb = json.loads((tmp_path / "b" / "detections.geojson").read_text())["features"]
    assert fa == fb and len(fa) >= 10


def test_atomic_store_leaves_nothing_on_failure(tmp_path):
    final = tmp_path / "s.zarr"
    with pytest.raises(RuntimeError):
        with atomic_store(final) as tmp:
            create_scene(tmp, (10, 10), {"intensity": "float32"}, tile=8)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_store(final) as tmp:
        g = create_scene(tmp, (10, 10), {"intensity": "float32"}, tile=8, attrs={"kind": "intensity"})
        g["intensity"][:] = 1.0
        finalize_scene(tmp)
    assert open_scene(final).shape == (10, 10)
    # a failed rewrite keeps the previous store
    with pytest.raises(RuntimeError):
        with atomic_store(final) as tmp:
            raise RuntimeError("boom")
    assert open_scene(final).array("intensity")[0, 0] == 1.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_open_scene_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_scene(tmp_path / "nope.zarr")
    (tmp_path / "f.zarr").write_text("not a store")
    with pytest.raises(InputError, match="not a Zarr scene"):
        open_scene(tmp_path / "f.zarr")
    g = zarr.open_group(str(tmp_path / "e.zarr"), mode="w", zarr_format=3)
    g.attrs["kind"] = "intensity"
    with pytest.raises(InputError, match="no 2-D variable"):
        open_scene(tmp_path / "e.zarr")
