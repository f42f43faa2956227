"""The scene store: Zarr v3 layout, xarray compatibility, sharded tiles, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
import zarr

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import atomic_store, create_scene, finalize_scene, open_scene
from tests.conftest import blobs_scene, write_scene
from sarship.workers.jobs import run_detection


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
