"""Each detection's local contrast (pipeline/targets/local_contrast.py) and the ``min_contrast_db`` rule.

Pure functions against hand-computed rings; end to end on the session's two-process Dask
cluster: a bright and a dim ship on gamma sea, the dim one dropped by the rule and both kept
without it, values independent of the tiling, land and other detections out of the ring.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import write_scene

from sarship.pipeline.targets.local_contrast import GAP_PX, RING_PX, add_local_contrast, keep_contrast, ring_mean


def _reader(a):
    return lambda ra, rb, ca, cb: a[ra:rb, ca:cb]


def test_ring_mean_leaves_out_the_grown_box_and_the_excluded():
    power = np.arange(100, dtype=np.float64).reshape(10, 10)
    excluded = np.zeros((10, 10), bool)
    excluded[0, :] = True
    # box rows 4-5, cols 4-5 (half-open 4..6), gap 1: rows/cols 3..6 left out
    m, n = ring_mean(power, excluded.copy(), (4, 6, 4, 6), (0, 10, 0, 10), gap=1)
    use = ~excluded
    use[3:7, 3:7] = False
    assert n == int(use.sum()) == 100 - 10 - 16
    assert m == pytest.approx(power[use].mean())
    # a window offset in the scene: the same ring in window coordinates
    m2, n2 = ring_mean(power[2:, 1:], excluded[2:, 1:].copy(), (4, 6, 4, 6), (2, 10, 1, 10), gap=1)
    use2 = use[2:, 1:]
    assert n2 == int(use2.sum()) and m2 == pytest.approx(power[2:, 1:][use2].mean())


def _features(*boxes_means):
    return [
        {"type": "Feature", "geometry": None, "properties": {"bbox_px": list(b), "mean": m}} for b, m in boxes_means
    ]


def test_add_local_contrast_values_land_mask_and_edges():
    H = W = 80
    power = np.full((H, W), 2.0)
    power[:, 50:] = 50.0  # "land" to the right
    mask = np.zeros((H, W), np.uint8)
    mask[30:34, 30:34] = 1  # the ship
    mask[30:32, 40:42] = 1  # another detection inside the first one's ring: left out
    power[30:32, 40:42] = 1000.0
    land = np.zeros((H, W), np.uint8)
    land[:, 50:] = 1
    feats = _features(((30, 30, 34, 34), 200.0))
    add_local_contrast(feats, _reader(power), _reader(mask), (H, W), _reader(land))
    p = feats[0]["properties"]
    assert p["contrast_db"] == pytest.approx(10 * math.log10(200.0 / 2.0), abs=1e-3)
    # the ring: the 4x4 box grown by GAP_PX + RING_PX, less the land from col 50, the box grown by
    # GAP_PX and the other detection's 4 pixels
    assert 34 + GAP_PX + RING_PX > 50 and 41 > 34 + GAP_PX
    outer = (34 + GAP_PX + RING_PX - (30 - GAP_PX - RING_PX)) * (50 - (30 - GAP_PX - RING_PX))
    inner = (4 + 2 * GAP_PX) ** 2
    assert p["contrast_ring_px"] == outer - inner - 4
    # without the land mask the bright land enters the ring and the contrast falls
    feats2 = _features(((30, 30, 34, 34), 200.0))
    add_local_contrast(feats2, _reader(power), _reader(mask), (H, W), None)
    assert feats2[0]["properties"]["contrast_db"] < p["contrast_db"] - 3
    # absent pixels (NaN, nodata) are out of the ring too
    pw = power.copy()
    pw[:20, :] = np.nan
    pw[20:25, :] = -1.0
    feats3 = _features(((30, 30, 34, 34), 200.0))
    add_local_contrast(feats3, _reader(pw), _reader(mask), (H, W), _reader(land), nodata=-1.0)
    assert feats3[0]["properties"]["contrast_db"] == pytest.approx(p["contrast_db"], abs=1e-3)
    assert feats3[0]["properties"]["contrast_ring_px"] < p["contrast_ring_px"]
    # a detection whose ring is all land or off the scene measures nothing and is kept
    feats4 = _features(((70, 70, 80, 80), 200.0))
    add_local_contrast(feats4, _reader(power), _reader(mask), (H, W), _reader(land))
    assert feats4[0]["properties"]["contrast_db"] is None
    assert keep_contrast(feats4, 50.0) == [True]


def test_keep_contrast():
    feats = _features(((0, 0, 1, 1), 1.0), ((0, 0, 1, 1), 1.0), ((0, 0, 1, 1), 1.0))
    for f, c in zip(feats, (3.0, 7.0, None)):
        f["properties"]["contrast_db"] = c
    assert keep_contrast(feats, 7.0) == [False, True, True]
    assert keep_contrast(feats, None) == [True, True, True]


# ----------------------------------------------------------------------------- end to end


def _two_ships(tmp_path, tile):
    """Gamma sea (L = 4, mean 1) with a bright ship (mean 100: 20 dB) and a dim one (mean 8:
    9 dB), both 4 x 10 px, far apart."""
    rng = np.random.default_rng(7)
    x = rng.gamma(4.0, 0.25, (160, 200)).astype(np.float32)
    x[40:44, 40:50] = rng.gamma(4.0, 25.0, (4, 10))
    x[110:114, 140:150] = rng.gamma(16.0, 0.5, (4, 10))
    return write_scene(tmp_path / f"two_{tile}.zarr", {"intensity": x}, tile=tile, looks=4.0)


def _run(client, scene, out, tile, **settings):
    from sarship.workers.jobs import run_detection

    settings = {"land_mask": "none", "min_area_px": 8, "pfa": 1e-6, **settings}
    run = run_detection(scene, "ca_cfar", settings, out_dir=out, tile=tile, client=client, progress=False)
    return json.loads((out / "detections.geojson").read_text())["features"], run


def test_min_contrast_db_end_to_end(client, tmp_path):
    scene = _two_ships(tmp_path, 200)
    # no floor: nothing measured (the property is null), nothing dropped
    plain, run0 = _run(client, scene, tmp_path / "plain", 200)
    assert len(plain) == 2 and all(f["properties"]["contrast_db"] is None for f in plain)
    assert run0["contrast"] == {"min_contrast_db": None, "measured": False}
    # a floor of -30 dB measures every detection and drops none here
    feats, run = _run(client, scene, tmp_path / "all", 200, min_contrast_db=-30)
    by_row = sorted(feats, key=lambda f: f["properties"]["bbox_px"][0])
    assert len(by_row) == 2, [f["properties"]["bbox_px"] for f in feats]
    bright, dim = (f["properties"]["contrast_db"] for f in by_row)
    assert 17.0 < bright < 23.0 and 6.0 < dim < 12.0, (bright, dim)
    assert run["contrast"]["measured"] and run["contrast"]["dropped"] == 0
    assert run["contrast"]["ring_px"] == RING_PX and run["contrast"]["unmeasured"] == 0

    floor = (bright + dim) / 2
    kept, run2 = _run(client, scene, tmp_path / "floor", 200, min_contrast_db=floor)
    assert [f["properties"]["bbox_px"] for f in kept] == [by_row[0]["properties"]["bbox_px"]]
    assert run2["contrast"]["dropped"] == 1 and run2["parameters"]["min_contrast_db"] == floor
    assert all(f["properties"]["contrast_db"] >= floor for f in kept)
    # ids stay 0..n-1 over the kept detections
    assert [f["properties"]["id"] for f in kept] == [0]

    # the tiling does not change the values: 48-px tiles against the one tile
    scene48 = _two_ships(tmp_path, 48)
    feats48, _ = _run(client, scene48, tmp_path / "t48", 48, min_contrast_db=-30)
    a = {tuple(f["properties"]["bbox_px"]): f["properties"]["contrast_db"] for f in feats}
    b = {tuple(f["properties"]["bbox_px"]): f["properties"]["contrast_db"] for f in feats48}
    assert a == b


def test_min_contrast_db_is_validated_and_superpixel_default():
    from sarship.pipeline import detectors
    from sarship.pipeline.errors import InputError
    from sarship.workers.request import parse_params

    spec = detectors.get("ca_cfar")
    assert spec.params().min_contrast_db is None
    assert parse_params(spec, {"min_contrast_db": "none"}).min_contrast_db is None
    assert parse_params(spec, {"min_contrast_db": "5.5"}).min_contrast_db == 5.5
    with pytest.raises((InputError, ValueError)) as e:
        parse_params(spec, {"min_contrast_db": "100"})
    assert "min_contrast_db" in str(e.value)
    sp = detectors.get("superpixel_cfar").params()
    assert sp.min_contrast_db == 7.0


# ----------------------------------------------------------------------------- the window cache


def test_cached_windows_equal_direct_reads_and_read_each_block_once():
    from sarship.pipeline.tiling.window_cache import CachedWindows

    rng = np.random.default_rng(0)
    a = rng.random((300, 257)).astype(np.float32)
    stack = rng.random((300, 257, 2)).astype(np.complex64)
    calls = []

    def read(ra, rb, ca, cb):
        calls.append((ra, rb, ca, cb))
        return a[ra:rb, ca:cb]

    cw = CachedWindows(read, a.shape, block=64)
    for _ in range(3):
        for ra, rb, ca, cb in (
            (0, 10, 0, 10),
            (60, 70, 60, 130),
            (250, 300, 200, 257),
            (-5, 400, -3, 300),
            (100, 100, 5, 9),
        ):
            got = cw(ra, rb, ca, cb)
            want = a[max(ra, 0) : min(rb, 300), max(ca, 0) : min(cb, 257)]
            assert got.shape == want.shape and np.array_equal(got, want)
    n_blocks = 5 * 5  # 300 / 64 -> 5 block rows, 257 / 64 -> 5 block columns
    assert cw.reads == n_blocks  # every block read once over the three passes
    got = cw(0, 10, 0, 10)
    got[:] = -1  # a copy: the cache is not changed through it
    assert np.array_equal(cw(0, 10, 0, 10), a[:10, :10])
    # trailing axes (stacked channels) and a budget of one block: still right, read again as needed
    cs = CachedWindows(
        lambda ra, rb, ca, cb: stack[ra:rb, ca:cb], stack.shape[:2], block=64, max_bytes=stack[:64, :64].nbytes
    )
    for ra, rb, ca, cb in ((0, 130, 0, 70), (5, 9, 250, 257), (0, 130, 0, 70)):
        assert np.array_equal(cs(ra, rb, ca, cb), stack[ra:rb, ca:cb])
    assert cs.reads > 6 and len(cs._blocks) == 1


@pytest.mark.parametrize("kind,detector", [("quadpol", "apwf"), ("slc", "csk")])
def test_contrast_of_complex_scenes(tmp_path, client, kind, detector):
    """Complex scenes: the contrast is that of the detector's pixel power (span of the channels,
    |z|^2 of an SLC), measured on every detection; simulated ships at SCR 15 dB stand out."""
    from sarship.pipeline.simulate import SimConfig, simulate
    from sarship.workers.jobs import run_detection

    cfg = SimConfig(kind=kind, shape=(512, 512), ships=4, seed=5, clutter="rayleigh", scr_db=15.0)
    scene = tmp_path / "c.zarr"
    simulate(scene, cfg, tile=512, truth_path=tmp_path / "c.truth.geojson")
    run = run_detection(
        scene, detector, {"min_contrast_db": -30}, out_dir=tmp_path / "o", client=client, progress=False
    )
    feats = json.loads((tmp_path / "o" / "detections.geojson").read_text())["features"]
    assert run["contrast"]["measured"] and run["contrast"]["dropped"] == 0 and feats
    values = [f["properties"]["contrast_db"] for f in feats]
    assert all(v is not None and math.isfinite(v) for v in values), values
    assert max(values) > 8.0, values


def test_land_file_is_left_out_of_the_ring_end_to_end(client, tmp_path):
    """A land FILE beside a ship: the product's contrast equals the ring computed by hand with the
    land left out (and differs from the ring with it); ``run.json`` says the land was excluded."""
    import zarr

    rng = np.random.default_rng(7)
    x = rng.gamma(4.0, 0.25, (160, 200)).astype(np.float32)
    x[110:114, 140:150] = rng.gamma(16.0, 0.5, (4, 10))  # the dim ship (9 dB)
    x[100:125, 156:200] = rng.gamma(4.0, 1.0, (25, 44))  # land 4x brighter than the sea, in its ring
    scene = write_scene(tmp_path / "land.zarr", {"intensity": x}, tile=200, looks=4.0)
    land = np.zeros(x.shape, np.uint8)
    land[100:125, 156:200] = 1
    np.save(tmp_path / "land.npy", land)
    feats, run = _run(client, scene, tmp_path / "o", 200, min_contrast_db=-30, land_mask=str(tmp_path / "land.npy"))
    assert run["contrast"]["land_excluded"] and run["land"]["source"] != "texture"
    ship = [f["properties"] for f in feats if f["properties"]["bbox_px"] == [110, 140, 114, 150]]
    assert len(ship) == 1, [f["properties"]["bbox_px"] for f in feats]
    p = ship[0]
    detected = np.asarray(zarr.open_array(str(tmp_path / "o" / "mask.zarr" / "detected"), mode="r")[...]) != 0
    m = GAP_PX + RING_PX
    win = (slice(110 - m, 114 + m), slice(140 - m, 150 + m))
    ring = np.ones(x.shape, bool)
    ring[110 - GAP_PX : 114 + GAP_PX, 140 - GAP_PX : 150 + GAP_PX] = False
    ring &= ~detected
    keep = np.zeros(x.shape, bool)
    keep[win] = True
    ref_land_out = x[keep & ring & (land == 0)].astype(np.float64).mean()
    ref_land_in = x[keep & ring].astype(np.float64).mean()
    assert p["contrast_ring_px"] == int((keep & ring & (land == 0)).sum())
    assert p["contrast_db"] == pytest.approx(10 * math.log10(p["mean"] / ref_land_out), abs=2e-3)
    assert 10 * math.log10(p["mean"] / ref_land_in) < p["contrast_db"] - 1.0
