"""``superpixel_cfar``'s CuPy twin (pipeline/gpu/superpixel_cfar.py) against the CPU.

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none);
``bash bench/gpu_suite.sh`` runs it on a GPU machine. Steps 1-5 run on a host copy of the
block (the CPU's code), steps 6-7 (CoV local contrast, eq 11-13; eq 16; the detected fraction
and the superpixel decision) on the device. Equality rule (the twin's docstring): the window
sums and the CoV are bit-identical; CUDA's ``exp`` may differ from NumPy's in the last bit,
and pixels whose eq 16 product lies within ``TIE_REL`` of ``T_cfar`` are decided on the host,
so eq 16's pixel decisions, the fractions, the masks and the superpixel statistic are
identical bit for bit; ``A C_local / T_cfar`` agrees to 1e-13 relative (float64) and, as the
float32 statistic of ``decision="pixel"``, to one float32 rounding.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.detectors import superpixel_cfar as D
from sarship.pipeline.gpu import available
from sarship.pipeline.tiling.windows import mirror_pad
from tests.pipeline.test_superpixel_cfar import SMALL, hires_scene

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


def _scene(seed: int, shape, dtype, n_ships: int = 2, lengths=(40.0, 100.0)) -> np.ndarray:
    """K sea with extended ships (tests/pipeline/test_superpixel_cfar.py), a no-data patch, a no-data
    column band and holes in the hull pixels."""
    x, truth = hires_scene(seed, shape=shape, n_ships=n_ships, lengths=lengths)
    x[20:31, 10:27] = np.nan
    x[:, -5:-2] = np.nan
    hull = np.flatnonzero(truth.ravel() == 1)
    x.ravel()[hull[::5]] = np.nan
    return x.astype(dtype)


CASES = [
    # (seed, shape, params, dtype)
    (7, (301, 257), dict(SMALL), np.float64),
    (5, (211, 193), dict(looks=1.0), np.float32),
    (3, (163, 151), dict(SMALL, min_separation_db=0.0), np.float32),
    (4, (163, 151), dict(SMALL, min_separation_db=0.0, contrast="off"), np.float64),
    (8, (180, 171), dict(SMALL, min_separation_db=0.0, cov_window=5, kappa=0.3), np.float64),
]


def _block(x, p):
    h = D.halo(p)
    return mirror_pad(x, h), h


@pytest.mark.parametrize("case", range(len(CASES)))
def test_pixel_steps_equal_cpu_analysis(cp, case):
    """Eq 16's decisions and the detected fractions bit for bit, A C_local / T_cfar to 1e-13."""
    from sarship.pipeline.gpu import superpixel_cfar as G

    seed, shape, kw, dtype = CASES[case]
    x = _scene(seed, shape, dtype)
    p = D.SuperpixelCFARParams(**kw)
    prep = D.scene_prep(x, p)
    P, h = _block(x, p)
    origin = (-h, -h)
    res = D.analyse(P, h, origin, p, prep)
    host = D.host_steps(D._check(P, h, p), h, origin, p, prep)
    dev = G.pixel_steps(G.device_block(cp.asarray(P)), host, origin, p)
    assert int(res["decided"].sum()) >= 5 and int(res["pixel_det"].sum()) > 50
    np.testing.assert_array_equal(dev["pixel_det"].get(), res["pixel_det"])
    np.testing.assert_array_equal(dev["frac"].get(), res["frac"])
    rc, rg = res["ratio"], dev["ratio"].get()
    np.testing.assert_array_equal(np.isnan(rg), np.isnan(rc))
    np.testing.assert_allclose(rg[np.isfinite(rc)], rc[np.isfinite(rc)], rtol=1e-13, atol=0)
    if kw.get("contrast") == "off":  # no exp: the same operations throughout, the same bits
        np.testing.assert_array_equal(rg, rc)
    assert dev["near_ties"] <= 10  # a handful at most go back to the host


@pytest.mark.parametrize("decision", ["superpixel", "pixel", "boundaries"])
@pytest.mark.parametrize("case", [0, 1, 3])
def test_detect_equals_cpu(cp, case, decision):
    seed, shape, kw, dtype = CASES[case]
    x = _scene(seed, shape, dtype)
    p = D.SuperpixelCFARParams(**kw, decision=decision)
    prep = D.scene_prep(x, p)
    P, h = _block(x, p)
    mc, sc = D.detect(P, h, (-h, -h), p, prep)
    mg, sg = D.detect(cp.asarray(P), h, (-h, -h), p, prep)
    assert isinstance(mg, cp.ndarray) and mg.dtype == cp.bool_ and sg.dtype == cp.float32
    mg, sg = mg.get(), sg.get()
    assert mc.sum() > 50 and not mc[np.isnan(x)].any()
    np.testing.assert_array_equal(mg, mc)
    if decision == "pixel":
        np.testing.assert_allclose(sg, sc, rtol=2.5e-7, atol=0)
        assert np.array_equal(sg == 0, sc == 0) and (sg[mg] > 1).all()
    else:
        np.testing.assert_array_equal(sg, sc)


def test_gpu_tiles_equal_whole_block_and_cpu(cp):
    """Tiled == whole on the device (odd scene, tiles not dividing it, smaller than the halo),
    and equal to the CPU's whole-scene mask; the scene pass takes a device block too."""
    x = _scene(7, (301, 257), np.float64, n_ships=3, lengths=(40.0, 120.0))
    p = D.SuperpixelCFARParams(**SMALL)
    prep = D.scene_prep(x, p)
    P, h = _block(x, p)
    mc, sc = D.detect(P, h, (-h, -h), p, prep)
    mw, sw = (a.get() for a in D.detect(cp.asarray(P), h, (-h, -h), p, prep))
    np.testing.assert_array_equal(mw, mc)
    np.testing.assert_array_equal(sw, sc)
    H, W = x.shape
    for t in (29, 64):
        for r0 in range(0, H, t):
            for c0 in range(0, W, t):
                r1, c1 = min(r0 + t, H), min(c0 + t, W)
                blk = P[r0 : r1 + 2 * h, c0 : c1 + 2 * h]
                m, s = D.detect(cp.asarray(blk), h, (r0 - h, c0 - h), p, prep)
                np.testing.assert_array_equal(m.get(), mw[r0:r1, c0:c1])
                np.testing.assert_array_equal(s.get(), sw[r0:r1, c0:c1])
    a = D.scene_pass(P[: 120 + 2 * h, : 100 + 2 * h], h, (-h, -h), p, D.prepare(p))
    b = D.scene_pass(cp.asarray(P[: 120 + 2 * h, : 100 + 2 * h]), h, (-h, -h), p, D.prepare(p))
    np.testing.assert_array_equal(a["counts"], b["counts"])


def test_all_absent_block_on_device(cp):
    y = np.full((90, 77), np.nan, np.float32)
    p = D.SuperpixelCFARParams(**SMALL)
    prep = D.scene_prep(y, p)
    P, h = _block(y, p)
    for decision in ("superpixel", "pixel"):
        q = D.SuperpixelCFARParams(**SMALL, decision=decision)
        m, s = D.detect(cp.asarray(P), h, (-h, -h), q, prep)
        assert m.shape == y.shape and not bool(m.any()) and not bool(s.any())


def test_registered_for_gpu_workers():
    spec = detectors.get("superpixel_cfar")
    assert spec.gpu and spec.gpu_for(spec.params()) and not spec.scene_pass_gpu


def test_local_gpu_cluster_equals_cpu_run(tmp_path):
    """End to end (land mask at its default, scene pass, tiles): GPU workers' mask and detections
    equal the CPU workers'."""
    import zarr

    from sarship.workers.jobs import run_detection
    from tests.conftest import write_scene

    x, _ = hires_scene(11, shape=(700, 650), n_ships=4, lengths=(60.0, 200.0))
    x[100:140, 30:90] = np.nan
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x.astype(np.float32)}, tile=256, looks=1.0)
    g = run_detection(scene, "superpixel_cfar", out_dir=tmp_path / "g", device="gpu", progress=False)
    c = run_detection(scene, "superpixel_cfar", out_dir=tmp_path / "c", device="cpu", progress=False)
    assert g["device"] == "gpu" and c["device"] == "cpu"
    assert {t["device"] for t in g["tiles"]["per_tile"]} == {"gpu"}
    mg = zarr.open_group(str(tmp_path / "g" / "mask.zarr"), mode="r")["mask"][:]
    mc = zarr.open_group(str(tmp_path / "c" / "mask.zarr"), mode="r")["mask"][:]
    assert mc.sum() > 500
    assert np.array_equal(mg, mc)
    fg = json.loads((tmp_path / "g" / "detections.geojson").read_text())["features"]
    fc = json.loads((tmp_path / "c" / "detections.geojson").read_text())["features"]
    assert len(fg) == len(fc) > 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_small_ships_point_rule_twin(cp, dtype):
    """Issue 31's point rule (small ships in background superpixels) on the device path: the same
    host arrays as the CPU's, so mask and statistic equal the CPU's bit for bit."""
    from tests.pipeline.test_superpixel_cfar import small_ships_scene

    x, truth = small_ships_scene(2)
    x = x.astype(dtype)
    p = D.SuperpixelCFARParams(looks=4.0)
    prep = D.scene_prep(x, p)
    h = D.halo(p)
    P = mirror_pad(x, h)
    mc, sc = D.detect(P, h, (-h, -h), p, prep)
    mg, sg = D.detect(cp.asarray(P), h, (-h, -h), p, prep)
    np.testing.assert_array_equal(mg.get(), mc)
    np.testing.assert_array_equal(sg.get(), sc)
    assert len(set(np.unique(truth[mc])) - {0}) == 9
