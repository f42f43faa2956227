"""The size rule of the core detectors (pipeline.detectors.base.resolve_size): metres when the
scene's pixel spacing is known, a small-ship pixel default otherwise, explicit values win.

Issue evidence: real ships of 10-55 px (10 m pixels) were removed by the old pixel defaults
(min_area_px 20; 15 for two_parameter). Tiny scenes; the end-to-end runs use the session's
two-process Dask cluster (``client``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import write_scene

CORE = ("ca_cfar", "os_cfar", "two_parameter")


def _scene(tmp_path, name, ship_px: int, **attrs):
    """Gamma clutter (L=4) with one bright ship of ``ship_px`` pixels (a 2-px wide bar) at the centre."""
    rng = np.random.default_rng(3)
    x = rng.gamma(4.0, 0.25, (96, 96)).astype(np.float32)
    w = ship_px // 2
    x[47:49, 48 - w // 2 : 48 - w // 2 + w] += 80.0
    assert int((x > 20).sum()) == ship_px
    return write_scene(tmp_path / f"{name}.zarr", {"intensity": x}, tile=96, looks=4.0, **attrs)


def _run(client, scene, detector, out, **settings):
    from sarship.pipeline.products.truth import load_detections
    from sarship.workers.jobs import run_detection

    run = run_detection(scene, detector, settings, out_dir=out, tile=96, client=client, progress=False)
    return load_detections(out / "detections.geojson"), run


def _hits_centre(dets) -> bool:
    return any(s.bbox[0] <= 48 <= s.bbox[2] and s.bbox[1] <= 48 <= s.bbox[3] for s in dets)


# ----------------------------------------------------------------------------- the rule, in process


@pytest.mark.parametrize("detector", CORE)
def test_resolve_size_defaults(detector):
    from sarship.pipeline import detectors
    from sarship.pipeline.detectors.base import area_px, resolve_size

    P = detectors.get(detector).params
    p = P()
    assert p.min_area_px is None and p.min_length_m is None  # None = the automatic rule
    # spacing known: metres, the pixel default does not apply (only the default area in m^2:
    # a tiny floor at 10 m, more pixels at finer spacing)
    r, rule = resolve_size(p, (10.0, 10.0))
    assert rule.startswith("metres") and r.min_length_m == P.auto_min_length_m
    assert 15.0 <= r.min_length_m <= 25.0
    assert r.min_area_px == area_px(P.auto_min_area_m2, (10.0, 10.0)) <= 3
    r3, _ = resolve_size(p, (3.0, 3.0))
    assert r3.min_area_px == area_px(P.auto_min_area_m2, (3.0, 3.0)) > r.min_area_px
    assert r3.min_length_m == r.min_length_m
    # spacing unknown: a pixel default that keeps ships of 10 px
    r, rule = resolve_size(p, None)
    assert rule.startswith("pixels") and r.min_area_px == P.auto_min_area_px <= 10 and r.min_length_m is None
    # explicit values win
    r, rule = resolve_size(P(min_area_px=20), (10.0, 10.0))
    assert (r.min_area_px, r.min_length_m) == (20, None) and "given" in rule
    r, rule = resolve_size(P(min_length_m=50.0), (10.0, 10.0))
    assert (r.min_area_px, r.min_length_m) == (area_px(P.auto_min_area_m2, (10.0, 10.0)), 50.0) and "given" in rule
    r, rule = resolve_size(P(min_area_px=4, min_length_m=30.0), (10.0, 10.0))
    assert (r.min_area_px, r.min_length_m) == (4, 30.0)
    # a given length cannot apply without spacing: the pixel default, and the rule says so
    r, rule = resolve_size(P(min_length_m=50.0), None)
    assert r.min_area_px == P.auto_min_area_px and "ignored" in rule
    # an automatic pixel default never exceeds a given max_area_px
    r, _ = resolve_size(P(max_area_px=3), None)
    assert r.min_area_px == 3
    # the resolved parameters round-trip (tile workers rebuild them from model_dump)
    r, rule = resolve_size(p, (10.0, 10.0))
    again, _ = resolve_size(P(**r.model_dump()), (10.0, 10.0))
    assert again == r


def test_keep_mask_metres_and_pixels():
    """keep_mask applies the rule itself for unresolved parameters; lengths_m == shape_from_moments."""
    from sarship.pipeline.detectors.base import area_px
    from sarship.pipeline.detectors.ca_cfar import CAParams
    from sarship.pipeline.targets.components import MOMENT_DTYPE, shape_from_moments
    from sarship.pipeline.targets.ship_features import keep_mask, lengths_m

    rng = np.random.default_rng(0)
    recs = np.zeros(200, MOMENT_DTYPE)
    for rec in recs:  # random pixel sets: moments as components.py sums them
        k = int(rng.integers(1, 40))
        rr = rng.integers(0, 30, k).astype(float)
        cc = rng.integers(0, 30, k).astype(float)
        rec["n"], rec["sr"], rec["sc"] = k, rr.sum(), cc.sum()
        rec["srr"], rec["scc"], rec["src"] = (rr * rr).sum(), (cc * cc).sum(), (rr * cc).sum()
    for spacing in ((10.0, 10.0), (2.3, 13.9)):
        ref = np.array([shape_from_moments(r, spacing)["length_m"] for r in recs])
        assert np.array_equal(lengths_m(recs, spacing), ref)
    from sarship.pipeline.targets.ship_features import elongations

    def el(spacing):  # length / width as shape_from_moments measures them
        out = []
        for r in recs:
            f = shape_from_moments(r, spacing)
            out.append(f["length_m"] / f["width_m"] if spacing else f["length_px"] / f["width_px"])
        return np.array(out)

    for spacing in ((10.0, 10.0), (2.3, 13.9), None):
        np.testing.assert_allclose(elongations(recs, spacing), el(spacing), rtol=1e-9)
    slim = el((10.0, 10.0)) <= 15.0
    assert 0 < slim.sum() < len(recs)  # the random sets hold both kinds
    p = CAParams()
    with_spacing = keep_mask(recs, p, (10.0, 10.0))
    ref = np.array([shape_from_moments(r, (10.0, 10.0))["length_m"] for r in recs]) >= CAParams.auto_min_length_m
    assert np.array_equal(with_spacing, ref & slim & (recs["n"] >= area_px(CAParams.auto_min_area_m2, (10.0, 10.0))))
    assert np.array_equal(keep_mask(recs, p, None), (recs["n"] >= CAParams.auto_min_area_px) & (el(None) <= 15.0))
    assert np.array_equal(keep_mask(recs, CAParams(min_area_px=7), (10.0, 10.0)), (recs["n"] >= 7) & slim)
    assert np.array_equal(keep_mask(recs, CAParams(min_area_px=7, max_elongation=None), (10.0, 10.0)), recs["n"] >= 7)


def test_detectors_json_states_the_rule():
    """``sarship detectors --json`` (DetectorSpec.describe): defaults None = the rule, whose
    effective values are listed under size_defaults and stated in the help text."""
    from sarship.pipeline import detectors
    from sarship.pipeline.detectors.base import area_px

    for name in CORE:
        d = detectors.get(name).describe()
        P = detectors.get(name).params
        assert d["defaults"]["min_area_px"] is None and d["defaults"]["min_length_m"] is None
        sd = d["size_defaults"]
        assert sd["spacing_known"]["min_length_m"] == P.auto_min_length_m
        assert sd["spacing_known"]["min_area_m2"] == P.auto_min_area_m2
        assert sd["spacing_known"]["min_area_px"] == area_px(P.auto_min_area_m2, (10.0, 10.0))
        assert sd["spacing_unknown"] == {
            "min_area_px": P.auto_min_area_px,
            "min_length_m": None,
            "rule": sd["spacing_unknown"]["rule"],
        }
        assert f"{P.auto_min_area_px} px" in d["parameters"]["min_area_px"]["description"]
        assert f"{P.auto_min_length_m:g} m" in d["parameters"]["min_length_m"]["description"]
        assert f"{P.auto_min_area_m2:g} m^2" in d["parameters"]["min_area_px"]["description"]
    # detectors with a fixed pixel default keep it whatever the spacing, and say so
    d = detectors.get("pcdm").describe()
    assert d["size_defaults"]["spacing_known"]["min_area_px"] == d["defaults"]["min_area_px"]
    assert d["size_defaults"]["spacing_known"]["min_length_m"] is None


# ----------------------------------------------------------------------------- end to end


@pytest.mark.parametrize("detector", CORE)
def test_spacing_known_keeps_a_12px_ship(client, tmp_path, detector):
    """10 m pixels, a 12-px ship (about 60 m x 20 m): kept at the defaults (the old pixel
    default 20 / 15 removed it); run.json shows the effective values and the rule."""
    scene = _scene(tmp_path, "s10", 12, pixel_spacing_m=[10.0, 10.0])
    dets, run = _run(client, scene, detector, tmp_path / "o")
    assert _hits_centre(dets), (detector, run["parameters"], run.get("size_rule"))
    P = run["parameters"]
    assert P["min_length_m"] is not None and P["min_length_m"] >= 15.0
    assert P["min_area_px"] <= 3
    assert run["size_rule"].startswith("metres")
    on_disk = json.loads((tmp_path / "o" / "run.json").read_text())
    assert on_disk["parameters"] == P and on_disk["size_rule"] == run["size_rule"]


@pytest.mark.parametrize("detector", CORE)
def test_spacing_unknown_keeps_a_10px_ship(client, tmp_path, detector):
    scene = _scene(tmp_path, "nosp", 10)
    dets, run = _run(client, scene, detector, tmp_path / "o")
    assert _hits_centre(dets), (detector, run["parameters"], run.get("size_rule"))
    assert run["parameters"]["min_area_px"] <= 10 and run["parameters"]["min_length_m"] is None
    assert run["size_rule"].startswith("pixels")


def test_explicit_min_area_wins(client, tmp_path):
    scene = _scene(tmp_path, "s10", 12, pixel_spacing_m=[10.0, 10.0])
    dets, run = _run(client, scene, "ca_cfar", tmp_path / "o", min_area_px=20)
    assert not _hits_centre(dets)
    assert run["parameters"]["min_area_px"] == 20 and run["parameters"]["min_length_m"] is None
    assert run["size_rule"] == "pixels: min_area_px 20 (given)"
    # and an explicit length, too
    dets, run = _run(client, scene, "ca_cfar", tmp_path / "o2", min_length_m=100.0)
    assert not _hits_centre(dets) and run["parameters"]["min_length_m"] == 100.0


def test_length_without_spacing_warns(client, tmp_path):
    scene = _scene(tmp_path, "nosp", 10)
    dets, run = _run(client, scene, "ca_cfar", tmp_path / "o", min_length_m=100.0)
    assert _hits_centre(dets)  # the length bound cannot apply; the pixel default keeps 10 px
    assert any("min_length_m" in w for w in run["warnings"])
    assert "ignored" in run["size_rule"]


def test_max_elongation_needs_square_pixels_or_spacing(tmp_path):
    """A ship that is long in pixels only because the pixels are not square (an SLC's azimuth x
    slant range): the default shape filter is off on a complex scene; asked for, it needs the
    spacing (else a run.json warning) and measures metres; on an intensity scene it applies."""
    from sarship.pipeline.readers import ingest
    from sarship.workers.jobs import run_detection

    rng = np.random.default_rng(2)
    z = ((rng.standard_normal((160, 160)) + 1j * rng.standard_normal((160, 160))) / np.sqrt(2)).astype(np.complex64)
    z[80:82, 40:100] = 40.0  # 2 x 60 px: 30 in pixels; 28 m x 138 m at 14 m x 2.3 m
    np.save(tmp_path / "slc.npy", z)
    np.save(tmp_path / "int.npy", (np.abs(z) ** 2).astype(np.float32))
    settings = {"pfa": 1e-6, "land_mask": None, "guard": 9, "background": 21, "min_area_px": 20}

    def run(src, name, **kw):
        sc = ingest([tmp_path / src], tmp_path / f"{name}.zarr", tile=160, **kw)
        r = run_detection(sc.path, "ca_cfar", settings, out_dir=tmp_path / name, progress=False)
        return r, json.loads((tmp_path / name / "detections.geojson").read_text())["features"]

    r, f = run("slc.npy", "slc")  # the default: off on a complex scene
    assert len(f) == 1 and r["parameters"]["max_elongation"] is None and not r["warnings"]
    settings["max_elongation"] = 15
    r, f = run("slc.npy", "slc_set")  # asked for, but no spacing: not applied, said
    assert len(f) == 1 and any("max_elongation not applied" in w for w in r["warnings"])
    r, f = run("slc.npy", "slc_sp", spacing=(14.0, 2.3))  # asked for, with spacing: metres
    assert len(f) == 1 and r["parameters"]["max_elongation"] == 15 and not r["warnings"]
    assert f[0]["properties"]["length_m"] / f[0]["properties"]["width_m"] < 15
    del settings["max_elongation"]
    r, f = run("int.npy", "int")  # detected product, the default: 30 x 2 px is a line, dropped
    assert f == [] and r["parameters"]["max_elongation"] == 15
