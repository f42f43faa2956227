"""Iterative kurtosis segmentation (seed 004 section 5.2) and Otsu (pipeline/targets/kurtosis_seg.py), and
``csk``'s ``ship_segmentation`` (the segmented geometry of each detection, pipeline/detectors/csk.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

from sarship.pipeline.detectors import csk
from sarship.pipeline.targets import kurtosis_seg as ks
from sarship.pipeline.targets.components import shape_from_moments


def _chip(rng, db):
    z = (rng.standard_normal((64, 64)) + 1j * rng.standard_normal((64, 64))) / math.sqrt(2)
    ship = np.zeros((64, 64), bool)
    ship[22:42, 30:35] = True  # 20 x 5 px
    z[ship] *= math.sqrt(10 ** (db / 10))
    return z, ship


def test_curve_is_the_excess_kurtosis_of_each_prefix():
    rng = np.random.default_rng(0)
    z, _ = _chip(rng, 15.0)
    t, k = ks.kurtosis_curve(z)
    a = np.abs(z).ravel()
    for q in (40, 500, 2000, a.size):
        x = z.ravel()[np.argsort(a, kind="stable")[:q]].real
        assert k[q - 1] == pytest.approx(np.mean(x**4) / np.mean(x**2) ** 2 - 3.0, rel=1e-9, abs=1e-12)
    assert np.all(np.diff(t) >= 0)
    _, kb = ks.kurtosis_curve(z, "both")
    assert kb.shape == k.shape


def test_segments_simulated_ships_better_than_otsu():
    """20 chips: Gaussian sea, a 20 x 5 px speckled ship 10-20 dB brighter. Measured: mean IoU
    0.74 (Otsu 0.47), mean length 19.7 px (Otsu 23.0) for 20."""
    rng = np.random.default_rng(1)
    iou_k, iou_o, lengths = [], [], []
    for _ in range(20):
        z, ship = _chip(rng, rng.uniform(10.0, 20.0))
        m = np.abs(z) > ks.kurtosis_threshold(z)
        mo = np.abs(z) > ks.otsu_threshold(z)
        iou_k.append((m & ship).sum() / (m | ship).sum())
        iou_o.append((mo & ship).sum() / (mo | ship).sum())
        lengths.append(ks.ship_geometry(m, (1.0, 1.0)).length_m)
    assert np.mean(iou_k) > 0.65 and np.mean(iou_k) > np.mean(iou_o) + 0.1
    assert abs(np.median(lengths) - 20.0) <= 2.0


def test_pure_gaussian_sea_has_almost_no_ship_pixels():
    rng = np.random.default_rng(2)
    above = []
    for _ in range(20):
        z = rng.standard_normal((64, 64)) + 1j * rng.standard_normal((64, 64))
        t = ks.kurtosis_threshold(z)
        above.append(float((np.abs(z) > t).mean()))
    assert np.mean(above) < 0.01  # truncated Gaussian real parts stay sub-Gaussian until the end


def test_otsu_against_brute_force():
    rng = np.random.default_rng(3)
    a = np.concatenate([rng.rayleigh(1.0, 3000), rng.rayleigh(8.0, 1000)])
    t = ks.otsu_threshold(a.astype(np.complex128))
    hi = np.percentile(a, 99.5)
    g = np.clip(np.floor(a / hi * 255), 0, 255)
    best = max(
        range(255),
        key=lambda L: (lambda c0, c1: c0.size * c1.size * (c0.mean() - c1.mean()) ** 2 if c0.size and c1.size else -1)(
            g[g <= L], g[g > L]
        ),
    )
    assert t == pytest.approx((best + 1) / 255 * hi)
    assert 1.0 < t < 8.0


def test_ship_geometry_and_inputs():
    m = np.zeros((30, 40), bool)
    m[10:14, 5:35] = True  # 4 rows x 30 columns
    m[0, 0] = True  # another component, far from the centre
    g = ks.ship_geometry(m, (10.0, 2.0))
    assert g.pixels == 120 and g.length_m == pytest.approx(60.0) and g.width_m == pytest.approx(40.0)
    assert g.heading_deg == pytest.approx(90.0)  # along the columns
    assert ks.ship_geometry(np.zeros((5, 5), bool), (1.0, 1.0)) is None
    with pytest.raises(ValueError, match="complex"):
        ks.kurtosis_threshold(np.ones((8, 8)))
    with pytest.raises(ValueError, match="part"):
        ks.kurtosis_curve(np.ones((8, 8), complex), "abs")
    with pytest.raises(ValueError, match="start"):
        ks.kurtosis_threshold(np.ones((8, 8), complex), start=0.0)


def test_ship_geometry_is_the_products_moment_geometry():
    """A hull with a one-pixel streak joined to it (a sidelobe): the length is the product's moment
    length (components.shape_from_moments), not the extent along the main axis (which counted the
    streak whole: 50 m here instead of the moment length)."""
    m = np.zeros((40, 40), bool)
    m[15:25, 18:22] = True  # 10 rows x 4 columns
    m[25:35, 20] = True  # a 10-pixel streak below it
    g = ks.ship_geometry(m, (10.0, 5.0))
    ref = shape_from_moments(ks.moment_record(m)[0], (10.0, 5.0))
    assert g.pixels == 50
    assert g.length_m == pytest.approx(ref["length_m"]) and g.width_m == pytest.approx(ref["width_m"])
    assert g.heading_deg == pytest.approx(ref["heading_deg"])
    assert g.length_m < 180.0  # extent: 200 m


def test_segment_finds_the_known_ship_length_and_heading():
    """``segment`` + ``component_of`` (what the product runs) on 10 chips: a 20 x 5 px ship at
    12-18 dB, 10 m x 5 m pixels: length 200 m within 10 % on each, heading 0 (along the rows)."""
    rng = np.random.default_rng(4)
    for _ in range(10):
        z, ship = _chip(rng, rng.uniform(12.0, 18.0))
        seg, t = ks.segment(z, "kurtosis")
        comp = ks.component_of(seg, np.abs(z), ship)
        g = shape_from_moments(ks.moment_record(comp)[0], (10.0, 5.0))
        assert abs(g["length_m"] - 200.0) <= 20.0, g
        assert min(g["heading_deg"], 180.0 - g["heading_deg"]) < 5.0
        assert np.isfinite(t) and not seg[np.abs(z) <= t].any()


def test_segment_leaves_absent_pixels_out():
    rng = np.random.default_rng(5)
    z, ship = _chip(rng, 15.0)
    zn = z.copy()
    zn[:, :8] = np.nan  # a no-data stripe
    zn[30, 32] = complex(np.nan, 1.0)  # a ship pixel with a NaN part
    seg, t = ks.segment(zn, "kurtosis")
    ok = np.isfinite(zn.real) & np.isfinite(zn.imag)
    assert t == ks.kurtosis_threshold(zn[ok]) and not seg[~ok].any()
    assert (seg & ship).sum() >= 0.8 * ship.sum()
    seg_o, t_o = ks.segment(zn, "otsu")
    assert t_o == pytest.approx(ks.otsu_threshold(zn[ok])) and not seg_o[~ok].any()
    empty, t0 = ks.segment(np.full((6, 6), np.nan, complex), "kurtosis")
    assert not empty.any() and t0 == math.inf
    with pytest.raises(ValueError, match="method"):
        ks.segment(z, "watershed")
    assert not ks.component_of(seg, np.abs(z), np.zeros_like(seg)).any()


def test_csk_segmentation_parameters_validated():
    assert csk.CSKParams().ship_segmentation == "kurtosis"
    assert csk.CSKParams(ship_segmentation="otsu", segmentation_margin_px="5").segmentation_margin_px == 5
    assert csk.CSKParams(ship_segmentation=None).ship_segmentation == "none"  # --set ship_segmentation=none
    for bad in (
        {"ship_segmentation": "watershed"},
        {"ship_segmentation": ""},
        {"segmentation_margin_px": 0},
        {"segmentation_margin_px": 65},
    ):
        with pytest.raises(ValidationError, match=next(iter(bad))):
            csk.CSKParams(**bad)
    from sarship.pipeline import detectors
    from sarship.pipeline.errors import InputError
    from sarship.workers.request import parse_params

    with pytest.raises(InputError, match="parameter 'ship_segmentation'"):  # as the CLI and the API report it
        parse_params(detectors.get("csk"), {"ship_segmentation": "watershed"})
    assert parse_params(detectors.get("csk"), {"ship_segmentation": "none"}).ship_segmentation == "none"


def _scene(seed=11):
    """Circular Gaussian SLC (160 x 200), six speckled ships 16 x 4 px along the rows at 18 dB
    (10 m x 5 m pixels: 160 m x 20 m), a NaN block beside one ship."""
    rng = np.random.default_rng(seed)
    H, W = 160, 200
    z = ((rng.standard_normal((H, W)) + 1j * rng.standard_normal((H, W))) / math.sqrt(2)).astype(np.complex64)
    ships = []
    for k in range(6):
        r, c = 20 + 70 * (k // 3), 25 + 60 * (k % 3)
        z[r : r + 16, c : c + 4] *= np.float32(math.sqrt(10**1.8))
        ships.append((r, c))
    z[20:40, 14:22] = np.nan
    return z, ships


def _segmented_reference(z, mask, props, method):
    """The geometry of the segmented ship in the detection's last chip, recomputed from the array."""
    r0, c0, r1, c1 = props["bbox_px"]
    ra, ca, rb, cb = props["segmentation_window_px"]
    assert ra <= r0 and ca <= c0 and rb >= r1 and cb >= c1
    chip = z[ra:rb, ca:cb].astype(np.complex128)
    seed = np.zeros(chip.shape, bool)
    seed[r0 - ra : r1 - ra, c0 - ca : c1 - ca] = mask[r0:r1, c0:c1]
    seg, _ = ks.segment(chip, method)
    comp = ks.component_of(seg, np.abs(np.where(np.isfinite(chip), chip, 0)), seed)
    return shape_from_moments(ks.moment_record(comp, (ra, ca))[0], (10.0, 5.0))


def test_csk_detections_carry_the_segmented_geometry(tmp_path, client):
    """End to end: ``csk`` on a simulated SLC scene; each ship's detection carries the segmented
    geometry (length 160 m within 15 %, heading along the rows), the method, the mask's own
    geometry as ``<name>_raw``; the same properties for any tiling; ``none`` keeps the mask's."""
    import zarr

    from sarship.workers.jobs import run_detection
    from tests.conftest import write_scene

    z, ships = _scene()
    scene = write_scene(tmp_path / "s.zarr", {"hh": z}, tile=64, kind="slc", looks=1.0, pixel_spacing_m=[10.0, 5.0])
    settings = {"pfa": "1e-4", "min_area_px": "1", "min_length_m": "0"}
    props = {}
    for tile in (4096, 37):
        run_detection(scene, "csk", settings, out_dir=tmp_path / f"t{tile}", tile=tile, client=client, progress=False)
        feats = json.loads((tmp_path / f"t{tile}" / "detections.geojson").read_text())["features"]
        props[tile] = [f["properties"] for f in feats]
    assert props[37] == props[4096]
    mask = np.asarray(zarr.open_array(str(tmp_path / "t4096" / "mask.zarr" / "detected"), mode="r")[:]) > 0
    found = set()
    for p in props[4096]:
        assert p["segmentation"] == "kurtosis" and p["segmented_area_px"] >= 0
        if p["segmented_area_px"] == 0:
            continue
        ref = _segmented_reference(z, mask, p, "kurtosis")
        assert p["length_m"] == pytest.approx(ref["length_m"], rel=1e-9)
        assert p["heading_deg"] == pytest.approx(ref["heading_deg"], abs=1e-9)
        assert "length_m_raw" in p and "centroid_px_raw" in p
        r, c = p["centroid_px"]
        hit = [i for i, s in enumerate(ships) if s[0] <= r < s[0] + 16 and s[1] <= c < s[1] + 4]
        if hit:  # (csk may find a ship's two ends: both fragments segment to the whole ship)
            found.update(hit)
            assert abs(p["length_m"] - 160.0) <= 24.0, p
            assert min(p["heading_deg"], 180.0 - p["heading_deg"]) < 8.0, p
    assert found == set(range(len(ships)))
    run_detection(
        scene,
        "csk",
        {**settings, "ship_segmentation": "none"},
        out_dir=tmp_path / "none",
        client=client,
        progress=False,
    )
    raw = [f["properties"] for f in json.loads((tmp_path / "none" / "detections.geojson").read_text())["features"]]
    assert len(raw) == len(props[4096])
    for a, b in zip(raw, props[4096]):
        assert "segmentation" not in a and a["length_m"] == b.get("length_m_raw", b["length_m"])
