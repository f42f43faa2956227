"""Ship metres of a slant-range scene (a Sentinel-1 SLC sub-swath states ``pixel_spacing_m`` =
[azimuth, slant range] and ``ground_range_spacing_m`` beside it): ``length_m`` / ``width_m``
and the metre size rules use the ground spacing (``Scene.ground_spacing_m``), run.json records
both."""

from __future__ import annotations

import json

import pytest
import zarr

from sarship.pipeline.scene import finalize_scene, open_scene
from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers.jobs import run_detection


def _set_attrs(store, **kw):
    g = zarr.open_group(str(store), mode="r+")
    g.attrs.update(kw)
    finalize_scene(store)


def _dims(d):
    feats = json.loads((d / "detections.geojson").read_text())["features"]
    return sorted(
        (
            f["properties"]["bbox_px"],
            f["properties"]["length_px"],
            f["properties"]["width_px"],
            f["properties"]["length_m"],
            f["properties"]["width_m"],
            f["properties"]["heading_deg"],
        )
        for f in feats
    )


def test_slant_range_scene_measures_ground_metres(tmp_path):
    cfg = SimConfig(
        shape=(256, 256), ships=3, seed=4, looks=4.0, clutter="gamma", scr_db=22.0, pixel_spacing_m=(10.0, 10.0)
    )
    simulate(tmp_path / "s.zarr", cfg, tile=128)
    settings = {"pfa": 1e-6, "land_mask": None, "min_area_px": 4}
    _set_attrs(tmp_path / "s.zarr", pixel_spacing_m=[10.0, 5.0])
    run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "a", progress=False)
    _set_attrs(tmp_path / "s.zarr", ground_range_spacing_m=10.0)
    assert open_scene(tmp_path / "s.zarr").ground_spacing_m == (10.0, 10.0)
    ground = run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "b", progress=False)
    assert ground["scene"]["pixel_spacing_m"] == [10.0, 5.0] and ground["scene"]["ground_spacing_m"] == [10.0, 10.0]
    _set_attrs(tmp_path / "s.zarr", pixel_spacing_m=[10.0, 10.0], ground_range_spacing_m=None)
    run_detection(tmp_path / "s.zarr", "ca_cfar", settings, out_dir=tmp_path / "c", progress=False)
    a, b, c = _dims(tmp_path / "a"), _dims(tmp_path / "b"), _dims(tmp_path / "c")
    assert len(b) >= 2 and [x[:3] for x in a] == [x[:3] for x in b] == [x[:3] for x in c]
    for (_, _, _, lb, wb, _), (_, _, _, lc, wc, _) in zip(b, c):  # ground = the 10 x 10 m scene's metres
        assert lb == pytest.approx(lc) and wb == pytest.approx(wc)
    assert any(abs(la - lb) > 1.0 or abs(wa - wb) > 1.0 for (_, _, _, la, wa, _), (_, _, _, lb, wb, _) in zip(a, b))
