"""Coastline land mask (``land_mask=coastline``, pipeline/land/coastline.py, docs/algorithms/landmask.md).

The scenes sit on a real coast: the Oslofjord (10.6 E, 59.8 N) at 10 m, north-up, georeferenced
by the simulator (``SimConfig(geo=...)``, ``sarship simulate --geo``), whose land is the GSHHG
shoreline's own (so the simulated land is what the mask knows). End-to-end runs go through
``run_detection`` on the two-process Dask cluster of the ``client`` fixture.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr
from conftest import write_scene
from scipy import ndimage

from sarship.pipeline.detectors import get as get_detector
from sarship.pipeline.land import coastline as co
from sarship.pipeline.simulate import SimConfig, _land_mask, simulate
from sarship.pipeline.simulate.land import geo_attrs
from sarship.pipeline.simulate.model import _model
from sarship.workers.jobs import run_detection

AT = (10.6, 59.8)  # the Oslofjord: land on the east half of a 3.8 km scene, islands
SHAPE = (384, 384)
SP = 10.0


def north_up(lon: float, lat: float, shape: tuple[int, int], sp: float, spacing: bool = True) -> dict:
    cfg = SimConfig(shape=shape, geo=(lon, lat), pixel_spacing_m=(sp, sp))
    a = geo_attrs(cfg)
    if spacing:
        a["pixel_spacing_m"] = [sp, sp]
    return a


def land(run_dir: Path, name: str = "land") -> np.ndarray:
    return np.asarray(zarr.open_group(str(run_dir / "land.zarr"), mode="r")[name][...]) > 0


def mask(run_dir: Path) -> np.ndarray:
    """The detector's per-pixel decision (``mask.zarr/detected``: what these land tests are about;
    ``mask.zarr/mask`` holds only the kept detections' pixels)."""
    return np.asarray(zarr.open_group(str(run_dir / "mask.zarr"), mode="r")["detected"][...]) > 0


def land_truth(cfg: SimConfig) -> np.ndarray:
    H, W = cfg.shape
    return _land_mask(cfg, _model(cfg).land, 0, H, 0, W)


@pytest.fixture(scope="module")
def geo_coast(tmp_path_factory):
    """A 384 x 384 K-distributed sea (4 looks, 10 m) on the Oslofjord with GSHHG land and 4 ships."""
    d = tmp_path_factory.mktemp("geocoast")
    cfg = SimConfig(
        shape=SHAPE, ships=4, seed=3, looks=4.0, clutter="k", land=True, scr_db=22.0, length_m=(60.0, 150.0), geo=AT
    )
    simulate(d / "s.zarr", cfg, tile=128)
    return d / "s.zarr", cfg, land_truth(cfg)


# ---------------------------------------------------------------------------------------------
# the lattice and the buffer


@pytest.mark.parametrize(
    "at,sp,shape",
    [
        (AT, 10.0, (256, 256)),
        ((18.95, 69.65), 20.0, (200, 240)),
        ((4.55, 52.45), 10.0, (256, 256)),
        ((-70.25, 41.6), 40.0, (160, 160)),
    ],
)
def test_lattice_equals_exact_test_on_every_pixel(at, sp, shape):
    """(C1)-(C3) reproduce the exact GSHHG test on every pixel (Oslofjord islands; Tromso at 69.6 N,
    where the mask cell is 160 m wide; the straight Dutch coast; Nantucket Sound), also in a region
    reaching 40 px outside the scene; and the refinement tests a small part of the pixels."""
    cl = co.open_coastline(north_up(*at, shape, sp), shape, 0.0)
    H, W = shape
    got = cl.land(-40, H, -17, W + 40)
    ref = co.brute_force(cl, -40, H, -17, W + 40)
    assert 0.02 < ref.mean() < 0.98, ref.mean()  # a coast, not open sea or inland
    assert np.array_equal(got, ref), int((got != ref).sum())
    assert cl.stats["refined_px"] < 0.6 * cl.stats["pixels"], cl.stats


def test_lattice_step_keeps_condition_c1():
    """s dx <= c_min / 3 (the mask cell's shorter side at the scene's latitude): 7 px at 59.8 N and
    10 m, coarser pixels give smaller steps, never below 1."""
    cl = co.open_coastline(north_up(*AT, SHAPE, SP), SHAPE, 0.0)
    c_min = co.M_PER_DEG / 240.0 * math.cos(math.radians(59.8 + 0.5))
    assert cl.step * SP <= c_min / 3.0 and (cl.step + 1) * SP > c_min / 3.0
    assert cl.step == 7
    assert co.open_coastline(north_up(*AT, SHAPE, 200.0), SHAPE, 0.0).step == 1


def test_buffer_is_the_distance_to_land_on_the_pixel_grid():
    """read() with a 300 m buffer on an anisotropic grid (8 m x 14 m) equals, pixel by pixel, the
    brute-force minimum over every land pixel centre of sqrt((dr az)^2 + (dc rg)^2) <= 300; and a
    buffer of 0 is the land itself."""
    shape, sp = (120, 100), (8.0, 14.0)
    a = north_up(*AT, shape, 10.0)
    a["pixel_spacing_m"] = list(sp)
    # a transform of 8 m rows and 14 m columns to match the spacing
    lat = AT[1]
    a["transform"] = [
        AT[0],
        sp[1] / (co.M_PER_DEG * math.cos(math.radians(lat))),
        0.0,
        lat + 0.006,
        0.0,
        -sp[0] / co.M_PER_DEG,
    ]
    b = 300.0
    cl = co.open_coastline(a, shape, b)
    hr, hc = cl.halo
    assert (hr, hc) == (38, 22)
    got = cl.read(0, shape[0], 0, shape[1])
    L = co.brute_force(cl, -hr, shape[0] + hr, -hc, shape[1] + hc)
    lr, lc = np.nonzero(L)
    lr, lc = lr - hr, lc - hc
    assert 0.05 < L.mean() < 0.95
    want = np.zeros(shape, bool)
    for r in range(shape[0]):
        d2 = ((lr[None, :] - r) * sp[0]) ** 2 + ((lc[None, :] - np.arange(shape[1])[:, None]) * sp[1]) ** 2
        want[r] = d2.min(axis=1) <= b * b
    assert np.array_equal(got, want), int((got != want).sum())
    assert got.sum() > L[hr : hr + shape[0], hc : hc + shape[1]].sum()  # the buffer widened the land
    assert np.array_equal(
        co.open_coastline(a, shape, 0.0).read(0, shape[0], 0, shape[1]), L[hr : hr + shape[0], hc : hc + shape[1]]
    )
    edt = ndimage.distance_transform_edt(~L, sampling=sp)[hr : hr + shape[0], hc : hc + shape[1]] <= b
    assert np.array_equal(got, edt)  # scipy's exact EDT agrees


def test_regions_do_not_depend_on_the_cut(monkeypatch):
    """The buffered mask of tiles of 37 x 53 px (not dividing the scene) pieced together equals the
    whole scene's bit for bit, and so does the whole scene's with the distance transform cut into
    blocks of 50 px."""
    cl = co.open_coastline(north_up(*AT, SHAPE, SP), SHAPE, 250.0)
    whole = cl.read(0, SHAPE[0], 0, SHAPE[1])
    with monkeypatch.context() as m:
        m.setattr(co, "EDT_SIDE", 50)
        assert np.array_equal(cl.read(0, SHAPE[0], 0, SHAPE[1]), whole)
    pieces = np.zeros(SHAPE, bool)
    for r0 in range(0, SHAPE[0], 37):
        for c0 in range(0, SHAPE[1], 53):
            r1, c1 = min(r0 + 37, SHAPE[0]), min(c0 + 53, SHAPE[1])
            pieces[r0:r1, c0:c1] = cl.read(r0, r1, c0, c1)
    assert 0.3 < whole.mean() < 0.7
    assert np.array_equal(pieces, whole)


def test_spacing_from_the_geo_model_when_the_scene_has_none():
    cl = co.open_coastline(north_up(*AT, SHAPE, SP, spacing=False), SHAPE, 250.0)
    assert cl.spacing_source == "geo model"
    assert cl.spacing == pytest.approx((SP, SP), rel=0.01)


def test_gcp_scene_gets_the_same_mask_as_its_transform():
    """The same north-up mapping stored as a 6 x 6 GCP grid (``geo_gcps``) gives the transform's
    mask (the GCP model reproduces an affine mapping to rounding: at most a few boundary pixels)."""
    t = SimConfig(shape=SHAPE, geo=AT)
    g = SimConfig(shape=SHAPE, geo=AT, geo_gcps=True)
    ga = geo_attrs(g)
    assert "gcps" in ga and "transform" not in ga and len(ga["gcps"]) == 36
    mt = co.open_coastline({**geo_attrs(t), "pixel_spacing_m": [SP, SP]}, SHAPE, 250.0).read(0, 384, 0, 384)
    mg = co.open_coastline({**ga, "pixel_spacing_m": [SP, SP]}, SHAPE, 250.0).read(0, 384, 0, 384)
    assert (mt != mg).sum() <= 20, int((mt != mg).sum())


# ---------------------------------------------------------------------------------------------
# the simulator


def test_simulated_land_is_the_shoreline(geo_coast):
    scene, cfg, truth = geo_coast
    attrs = dict(zarr.open_group(str(scene), mode="r").attrs)
    assert attrs["crs"] == "EPSG:4326" and len(attrs["transform"]) == 6
    cl = co.open_coastline(attrs, SHAPE, 0.0)
    assert np.array_equal(truth, cl.land(0, SHAPE[0], 0, SHAPE[1]))
    assert 0.3 < truth.mean() < 0.5
    I = np.asarray(zarr.open_group(str(scene), mode="r")["intensity"][...])
    assert np.median(I[truth]) > 5.0 * np.median(I[~truth])  # land 8-12 dB over the sea
    # ships on free sea, at least 8 px from the shoreline's land
    far = ndimage.distance_transform_edt(~truth) >= 8
    for s in _model(cfg).ships:
        rr, cc = np.nonzero(s.mask)
        assert far[rr + s.r0, cc + s.c0].all()


def test_simulate_cli_geo(tmp_path):
    out = tmp_path / "g.zarr"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship.cli",
            "simulate",
            str(out),
            "--shape",
            "64x64",
            "--ships",
            "0",
            "--geo",
            "10.6,59.8",
            "--geo-gcps",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    a = dict(zarr.open_group(str(out), mode="r").attrs)
    assert a["crs"] == "EPSG:4326" and len(a["gcps"]) == 36 and a["simulation"]["geo"] == [10.6, 59.8]
    bad = subprocess.run(
        [sys.executable, "-m", "sarship.cli", "simulate", str(tmp_path / "b.zarr"), "--geo", "10.6"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "LON,LAT" in bad.stderr and not (tmp_path / "b.zarr").exists()


# ---------------------------------------------------------------------------------------------
# parameters


def test_land_mask_parameter_parsing():
    P = get_detector("ca_cfar").params
    assert P(land_mask="Coastline + TEXTURE").land_mask == "coastline+texture"
    assert P(land_mask="coastline").land_mask == "coastline"
    assert P(land_mask="none").land_mask is None
    assert P(land_mask="/data/a+b.geojson").land_mask == "/data/a+b.geojson"  # a FILE
    assert P().land_buffer_m == co.DEFAULT_BUFFER_M
    for bad, name in (
        ({"land_mask": "texture+texture"}, "land_mask"),
        ({"land_buffer_m": -1}, "land_buffer_m"),
        ({"land_buffer_m": 6000}, "land_buffer_m"),
    ):
        with pytest.raises(ValueError, match=name):
            P(**bad)
    with pytest.raises(ValueError, match="land_mask"):
        get_detector("csk").params(land_mask="coastline+texture")
    assert get_detector("csk").params(land_mask="coastline").land_mask == "coastline"


def _cli_detect(args: list[str], block_package: bool = False) -> subprocess.CompletedProcess:
    pre = "import sys; sys.modules['roaring_landmask'] = None; " if block_package else "import sys; "
    code = pre + f"from sarship.cli import main; sys.exit(main({args!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_without_the_extra_one_line_and_nothing_written(geo_coast, tmp_path):
    scene, _, _ = geo_coast
    out = tmp_path / "o"
    r = _cli_detect(
        ["detect", str(scene), "--detector", "ca_cfar", "--set", "land_mask=coastline", "--out", str(out)],
        block_package=True,
    )
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "pip install 'sarship[coastline]'" in lines[0], r.stderr
    assert not out.exists()


def test_non_georeferenced_scene_one_line_and_nothing_written(tmp_path):
    scene = write_scene(tmp_path / "plain.zarr", {"intensity": np.ones((64, 64), np.float32)}, tile=64)
    out = tmp_path / "o"
    r = _cli_detect(
        ["detect", str(scene), "--detector", "ca_cfar", "--set", "land_mask=coastline+texture", "--out", str(out)]
    )
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "georeferenced" in lines[0], r.stderr
    assert not out.exists()


# ---------------------------------------------------------------------------------------------
# end to end


def _found(fc: dict, ship_boxes: list) -> int:
    cents = [f["properties"]["centroid_px"] for f in fc["features"]]
    return sum(any(b[0] <= r < b[2] and b[1] <= c < b[3] for r, c in cents) for b in ship_boxes)


@pytest.mark.parametrize("detector", ["ca_cfar", "lmm"])
def test_no_detection_on_land_ships_at_sea_found(geo_coast, client, tmp_path, detector):
    """With land_mask=coastline no detected pixel lies on the (GSHHG) land or in its buffer, and every
    ship is found (buffer 50 m: the ships keep 80 m of sea); without a mask the same detector
    alarms on the land (so the check can fail)."""
    scene, cfg, truth = geo_coast
    boxes = [[s.r0, s.c0, s.r0 + s.mask.shape[0], s.c0 + s.mask.shape[1]] for s in _model(cfg).ships]
    st = {"land_mask": "coastline", "land_buffer_m": 50.0}
    run = run_detection(scene, detector, st, out_dir=tmp_path / "c", client=client, tile=128, progress=False)
    M, L = mask(tmp_path / "c"), land(tmp_path / "c")
    assert run["land"]["source"] == "coastline" and run["land"]["buffer_m"] == 50.0
    assert run["land"]["land_px"] == int(L.sum()) and run["land"]["refined_px"] < L.size
    assert (L & ~truth).sum() > 0 and not (truth & ~L).any()  # the land and a 5 px fringe
    assert not (M & L).any()
    fc = json.loads((tmp_path / "c" / "detections.geojson").read_text())
    assert _found(fc, boxes) == len(boxes) == 4
    assert all(f["geometry"] is not None for f in fc["features"])  # georeferenced detections
    run_detection(
        scene, detector, {"land_mask": "none"}, out_dir=tmp_path / "n", client=client, tile=128, progress=False
    )
    assert (mask(tmp_path / "n") & truth).sum() > 50


def test_buffer_masks_a_ship_within_it_and_keeps_one_beyond(client, tmp_path):
    """Gamma sea (L = 4) at the Oslofjord with three bright 3 x 3 targets at 120-180 m, 400-500 m and ~1 km
    from the GSHHG land: a 300 m buffer masks the first and keeps the others; a 0 m buffer keeps all."""
    attrs = north_up(*AT, SHAPE, SP)
    cl = co.open_coastline(attrs, SHAPE, 0.0)
    hr = 120
    Lx = cl.land(-hr, SHAPE[0] + hr, -hr, SHAPE[1] + hr)
    dist = ndimage.distance_transform_edt(~Lx, sampling=(SP, SP))[hr:-hr, hr:-hr]
    rng = np.random.default_rng(5)
    I = rng.gamma(4.0, 0.25, SHAPE).astype(np.float32)
    targets = {}
    for name, (lo, hi) in {"near": (120.0, 180.0), "mid": (400.0, 500.0), "far": (900.0, 1100.0)}.items():
        ok = (dist > lo) & (dist < hi)
        ok &= ndimage.minimum_filter(ok, size=3)  # the whole 3 x 3 target in the band
        ok[:20], ok[-20:], ok[:, :20], ok[:, -20:] = False, False, False, False
        rr, cc = np.nonzero(ok)
        assert rr.size, name
        r, c = int(rr[rr.size // 2]), int(cc[rr.size // 2])
        I[r - 1 : r + 2, c - 1 : c + 2] = 300.0
        targets[name] = (r, c)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": I}, tile=128, looks=4.0, **attrs)
    st = {"guard": 11, "background": 21, "min_area_px": 1}
    runs = {}
    for b in (300.0, 0.0):
        out = tmp_path / f"b{int(b)}"
        runs[b] = run_detection(
            scene,
            "ca_cfar",
            {**st, "land_mask": "coastline", "land_buffer_m": b},
            out_dir=out,
            client=client,
            tile=128,
            progress=False,
        )
        runs[b] = (mask(out), land(out))
    M, L = runs[300.0]
    r, c = targets["near"]
    assert L[r, c] and not M[r - 1 : r + 2, c - 1 : c + 2].any()
    for name in ("mid", "far"):
        r, c = targets[name]
        assert not L[r, c] and M[r, c], name
    M0, L0 = runs[0.0]
    for name in ("near", "mid", "far"):
        r, c = targets[name]
        assert M0[r, c] and not L0[r, c], name
    assert np.array_equal(L, dist <= 300.0)  # the written mask is the buffer's definition


def test_union_with_texture_and_tiled_equals_whole(geo_coast, client, tmp_path):
    """coastline+texture: its land.zarr is the union of the coastline's and the texture's, bit for bit;
    the coastline array is kept beside it; tiles of 64 and of the whole scene give the same land and
    detection masks, with every land mask."""
    scene, cfg, truth = geo_coast
    st = {"guard": 11, "background": 21}
    out = {}
    for lm_ in ("coastline", "texture", "coastline+texture"):
        for tile in (384, 64):
            d = tmp_path / f"{lm_}-{tile}"
            run = run_detection(
                scene, "ca_cfar", {**st, "land_mask": lm_}, out_dir=d, client=client, tile=tile, progress=False
            )
            out[lm_, tile] = (land(d), mask(d), run, d)
    for lm_ in ("coastline", "texture", "coastline+texture"):
        assert np.array_equal(out[lm_, 64][0], out[lm_, 384][0]), lm_
        assert np.array_equal(out[lm_, 64][1], out[lm_, 384][1]), lm_
    C, T, U = out["coastline", 64][0], out["texture", 64][0], out["coastline+texture", 64][0]
    assert np.array_equal(U, C | T)
    assert (T & ~C).any() or (C & ~T).any()  # the two masks differ: the union is a real test
    assert np.array_equal(land(out["coastline+texture", 64][3], "coastline"), C)
    rec = out["coastline+texture", 64][2]["land"]
    assert rec["source"] == "coastline+texture" and rec["coastline"]["land_px"] == int(C.sum())
    assert rec["land_px"] == int(U.sum())
    assert not (out["coastline+texture", 64][1] & U).any()


def test_scene_pass_with_no_data_and_coastline(geo_coast, client, tmp_path):
    """A scene with a no-data (NaN) band and a NaN block over sea, run by a detector with a scene
    pass (gamma_mrf: its mixture and MRF statistics are scene-wide) with coastline+texture: the run
    finishes, the texture fit sees only present sea and land, nothing is detected in the no-data or
    on the land, and the ships outside the no-data are found."""
    scene, cfg, truth = geo_coast
    g = zarr.open_group(str(scene), mode="r")
    I = np.asarray(g["intensity"][...]).copy()
    I[200:230, :] = np.nan
    I[20:60, 20:60] = np.nan
    attrs = {k: v for k, v in dict(g.attrs).items() if k in ("crs", "transform", "pixel_spacing_m", "looks")}
    s2 = write_scene(tmp_path / "nan.zarr", {"intensity": I}, tile=128, **attrs)
    run = run_detection(
        s2,
        "gamma_mrf",
        {"land_mask": "coastline+texture"},
        out_dir=tmp_path / "r",
        client=client,
        tile=128,
        progress=False,
    )
    M, L = mask(tmp_path / "r"), land(tmp_path / "r")
    assert not M[~np.isfinite(I)].any() and not (M & L).any() and not (M & truth).any()
    sp_ = run["scene_pass"]
    assert sp_ is not None and all(
        np.isfinite(v).all()
        for v in sp_["values"].values()
        if isinstance(v, (int, float, list)) and not isinstance(v, bool)
    ), sp_
    # the texture sample (stride 1 here) holds only windows at least half present: none in the NaN band
    assert run["land"]["coastline"]["land"] and run["land"]["texture_land"]
    assert run["land"]["sample"] <= int(np.isfinite(I).sum()) + 2 * 7 * (SHAPE[1] + 80)
    boxes = [[s.r0, s.c0, s.r0 + s.mask.shape[0], s.c0 + s.mask.shape[1]] for s in _model(cfg).ships]
    present = [b for b in boxes if np.isfinite(I[b[0] : b[2], b[1] : b[3]]).all()]
    fc = json.loads((tmp_path / "r" / "detections.geojson").read_text())
    assert _found(fc, present) == len(present) >= 2
