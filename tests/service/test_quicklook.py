"""The quicklook's grey stretch (service/render.py) on what users upload: an 8-bit amplitude chip
(PNG, as HRSID / SSDD / SAR-Ship-Dataset ship chips are) ingested by the project's own ingest
is shown with contrast (sea dark to mid grey, ship white), not washed out by the dB of data
already scaled for display; float intensity keeps its 2-98 % dB stretch. And the lon/lat grid
of a georeferenced scene's TileJSON, which the web page draws its lon/lat map with
(service/tiles.py; the page itself: tests/service/test_web.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

Image = pytest.importorskip("PIL.Image")
import zarr  # noqa: E402
from conftest import blobs_scene, write_scene  # noqa: E402

from sarship.pipeline.readers import ingest  # noqa: E402
from sarship.service import render, tiles  # noqa: E402

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"


def job_on(scene: Path, tmp: Path) -> Path:
    """A finished job's folder on ``scene`` as the runner leaves it (run.json, an empty mask, no
    detections): what the quicklook reads."""
    sc = zarr.open_group(str(scene), mode="r")
    H, W = sc["intensity"].shape
    job = tmp / "job"
    job.mkdir()
    g = zarr.open_group(str(job / "mask.zarr"), mode="w", zarr_format=3)
    g.create_array("mask", shape=(H, W), chunks=(128, 128), dtype="uint8", fill_value=0)
    (job / "run.json").write_text(
        json.dumps(
            {
                "scene": {"path": str(scene), "shape": [H, W], "attrs": dict(sc.attrs)},
                "channel": "intensity",
                "detector": "ca_cfar",
                "parameters": {},
            }
        )
    )
    (job / "detections.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    return job


def chip_png(path: Path, seed: int = 0) -> np.ndarray:
    """An HRSID-like 8-bit amplitude chip: Rayleigh sea of mean ~25 DN (HRSID's sea is 13-50 DN),
    a few zero (no data) pixels, one bright ship of 220-255 DN; returns the ship mask."""
    rng = np.random.default_rng(seed)
    amp = np.clip(rng.rayleigh(20.0, (256, 256)), 0, 255)
    amp[rng.random(amp.shape) < 0.01] = 0
    ship = np.zeros(amp.shape, bool)
    ship[120:128, 90:150] = True
    amp[ship] = rng.uniform(220, 255, ship.sum())
    Image.fromarray(amp.astype(np.uint8)).save(path)
    return ship


def test_8bit_amplitude_chip_is_shown_with_contrast(tmp_path):
    ship = chip_png(tmp_path / "chip.png")
    ingest(
        [tmp_path / "chip.png"], tmp_path / "chip.zarr", looks=1.0, codec="none"
    )  # no estimate, no codec trial: cheap
    job = job_on(tmp_path / "chip.zarr", tmp_path)
    g = render.grey_base(job)[1]  # the grey every tile and the preview are cut from
    assert g.shape == ship.shape
    sea = g[~ship & (np.asarray(Image.open(tmp_path / "chip.png")) > 0)]
    lo, hi = np.percentile(g, [2, 98])
    assert hi - lo >= 180, (lo, hi)  # the grey levels span most of 0..255
    assert np.median(sea) < 110, np.median(sea)  # the sea is not washed out (dB of the chip: ~165)
    assert g[ship].mean() - sea.mean() >= 120, (g[ship].mean(), sea.mean())  # the ship stands out
    assert render.job_stretch(job)["scale"] == "amplitude"
    # the preview PNG and a full-resolution tile are the same grey
    prev = np.asarray(Image.open(render.preview_png(job, 256)).convert("L"))
    assert np.array_equal(prev, g)
    w = tiles.tile_window(g.shape, 0, 0, 0)
    assert np.array_equal(tiles.scene_grey(job, w), g)


@pytest.mark.skipif(not (REAL / "hrsid").is_dir(), reason=f"real HRSID chips absent ({REAL / 'hrsid'})")
def test_real_hrsid_chip_ships_stand_out(tmp_path):
    img = REAL / "hrsid" / "images" / "P0001_4200_5000_600_1400.jpg"  # Sentinel-1B, 800 x 800, 4 ships
    ships = np.asarray(Image.open(REAL / "hrsid" / "masks" / f"{img.stem}.png").convert("RGB"))[..., 1] > 128
    ingest([img], tmp_path / "chip.zarr", looks=1.0, codec="none")
    g = render.grey_base(job_on(tmp_path / "chip.zarr", tmp_path))[1]
    assert np.median(g[~ships]) < 110 and g[ships].mean() - g[~ships].mean() >= 100


def test_float_intensity_keeps_the_db_stretch(tmp_path):
    x = blobs_scene((200, 180), seed=3)
    scene = write_scene(tmp_path / "f.zarr", {"intensity": x}, tile=128, sample_dtype="float32", quantity="intensity")
    meta = render.job_stretch(job_on(scene, tmp_path))
    assert meta["scale"] == "db" and meta["percentiles"] == [2.0, 98.0]
    assert (meta["lo"], meta["hi"]) == pytest.approx(render.percentile_range(render.to_db(x)))


@pytest.mark.parametrize(
    "attrs, scale",
    [
        ({"sample_dtype": "uint8", "quantity": "amplitude (squared to intensity)"}, "amplitude"),
        (
            {"sample_dtype": "float32", "quantity": "amplitude (squared to intensity)", "source": ["P0001.JPG"]},
            "amplitude",
        ),
        ({"sample_dtype": "uint8", "quantity": "intensity"}, "linear"),
        ({"sample_dtype": "uint16", "quantity": "amplitude (squared to intensity)", "source": ["s1.tiff"]}, "db"),
        ({}, "db"),
    ],
)
def test_display_scale_from_the_scene_attributes(attrs, scale):
    assert render.display_scale(attrs) == scale


def test_a_stretch_saved_before_scales_existed_reads_as_db(tmp_path):
    meta = {"lo": 1.0, "hi": 2.0, "path": "x", "var": "intensity", "transform": "real", "shape": [4, 4]}
    assert render.source_of(meta).scale == "db"


# --------------------------------------------------------------------------- the map's lon/lat grid


def test_tilejson_lonlat_grid_of_a_georeferenced_scene():
    from sarship.pipeline.targets.ship_features import Georeference

    H, W = 300, 500
    affine = {"crs": "EPSG:32631", "transform": [500000.0, 10.0, 0.0, 5000000.0, 0.0, -10.0]}
    doc = tiles.tilejson("http://x", "J", (H, W), affine)
    g = doc["lonlat"]
    n = tiles.GRID_CELLS
    assert g["rows"][0] == 0 and g["rows"][-1] == H and g["cols"][-1] == W and len(g["rows"]) == n + 1
    want_lon, want_lat = Georeference(affine).lonlat([0, 0, H, H], [0, W, W, 0])
    got = [(g["lon"][i][j], g["lat"][i][j]) for i, j in ((0, 0), (0, n), (n, n), (n, 0))]
    assert np.allclose(got, np.c_[want_lon, want_lat], atol=1e-6)
    assert g["method"] == "affine transform"
    # GCPs (a 3 x 3 geolocation grid) give their own positions at the nodes they share
    gcps = [
        {"row": r, "col": c, "x": 3.0 + c * 1e-4, "y": 45.0 - r * 1e-4, "z": 0.0}
        for r in (0, H / 2, H)
        for c in (0, W / 2, W)
    ]
    g2 = tiles.lonlat_grid({"gcps": gcps}, (H, W))
    assert g2["lon"][n][n] == pytest.approx(3.0 + W * 1e-4) and g2["lat"][n][0] == pytest.approx(45.0 - H * 1e-4)
    # across the antimeridian the grid stays continuous (no jump of 360 degrees between nodes)
    g3 = tiles.lonlat_grid({"crs": "EPSG:4326", "transform": [179.99, 1e-4, 0.0, -16.0, 0.0, -1e-4]}, (H, W))
    assert g3["lon"][0][n] == pytest.approx(180.04) and np.all(np.diff(g3["lon"], axis=1) > 0)
    # no georeference, or one that cannot be evaluated: no grid, the page keeps pixel coordinates
    assert "lonlat" not in tiles.tilejson("http://x", "J", (H, W), {})
    assert tiles.lonlat_grid({"crs": "EPSG:99999999", "transform": [0, 1, 0, 0, 0, -1]}, (H, W)) is None
