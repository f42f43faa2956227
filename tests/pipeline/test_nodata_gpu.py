"""GPU twins of the polarimetric detectors against the CPU with absent pixels (NaN / zero).

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing. The same equality
rules as tests/workers/test_gpu.py (window sums and valid-cell counts bit-identical, masks differ at
most at a handful of pixels within rounding of the threshold); in addition the untested
pixels (absent, too few valid cells, pcdm's halo band) must be the same on both.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.gpu import available

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


def _quadpol(shape, p=3, seed=2):
    from sarship.pipeline.simulate import SimConfig, simulate_array

    cfg = SimConfig(kind="quadpol", shape=shape, ships=6, seed=seed, clutter="rayleigh", scr_db=10.0)
    arrs, _ = simulate_array(cfg)
    names = ["hh", "hv", "vv"] if p == 3 else ["hh", "vv"]
    return np.stack([arrs[k] for k in names], -1).astype(np.complex64)


def _absent(X, case, halo):
    """X with a NaN border / zero border / NaN wedge (the block already carries its halo)."""
    H, W = X.shape[:2]
    X = X.copy()
    r, c = np.mgrid[:H, :W]
    if case == "wedge":
        a = (c >= W // 2) & (np.abs(r - H // 2) <= (c - W // 2) * 0.7)
    else:
        a = np.ones((H, W), bool)
        b = halo + 40
        a[b : H - b, b + 15 : W - b] = False
    X[a] = np.nan if case != "zero_border" else 0
    return X, a


def _flips(m_cpu, s_cpu, m_gpu, thr, rel=1e-6):
    d = m_cpu != m_gpu
    near = np.abs(s_cpu.astype(np.float64) - thr) <= rel * max(abs(thr), 1e-30)
    return int(d.sum()), int((d & ~near).sum())


def _run_both(name, block, halo, origin, prep=None, **kw):
    import cupy

    spec = detectors.get(name)
    p = spec.params(**kw)
    prep = spec.prepare(p) if prep is None else prep
    mc, sc = spec.detect(block, halo, origin, p, prep)
    mg, sg = spec.detect(cupy.asarray(block), halo, origin, p, prep)
    assert isinstance(mg, cupy.ndarray) and mg.dtype == cupy.bool_ and sg.dtype == cupy.float32
    return mc, sc, mg.get(), sg.get(), prep


@pytest.mark.parametrize("case", ["nan_border", "zero_border", "wedge"])
@pytest.mark.parametrize("p,estimator", [(3, "ring"), (3, "window"), (2, "ring")])
def test_apwf_absent_matches_cpu(cp, case, p, estimator):
    kw = {"estimator": estimator, "pfa": 1e-3, "guard": 9, "background": 31}
    halo = 15
    X, a = _absent(_quadpol((2 * halo + 300, 2 * halo + 290), p, seed=6), case, halo)
    mc, sc, mg, sg, prep = _run_both("apwf", X, halo, (-halo, 11), **kw)
    core = a[halo:-halo, halo:-halo]
    assert not mc[core].any() and not mg[core].any()
    assert mc.sum() > 20
    untested_c = (sc == 0) & ~mc
    untested_g = (sg == 0) & ~mg
    np.testing.assert_array_equal(untested_c, untested_g)
    total, far = _flips(mc, sc, mg, prep["thresholds"][str(p)])
    assert far == 0 and total <= 2, (total, far)
    fin = np.isfinite(sc)
    np.testing.assert_allclose(sg[fin], sc[fin], rtol=1e-6)


def test_apwf_covariance_absent_matches_cpu(cp):
    halo = 15
    X, a = _absent(_quadpol((2 * halo + 220, 2 * halo + 210), 3, seed=5), "nan_border", halo)
    C = (X[..., :, None] * X[..., None, :].conj()).astype(np.complex64)
    mc, sc, mg, sg, prep = _run_both("apwf", C, halo, (-halo, -halo), pfa=1e-3, guard=9, background=31)
    total, far = _flips(mc, sc, mg, prep["thresholds"]["3"], rel=1e-9)
    assert far == 0 and total <= 2
    assert not mc[a[halo:-halo, halo:-halo]].any()
    np.testing.assert_array_equal(sc == 0, sg == 0)
    fin = np.isfinite(sc) & (sc > 0)
    np.testing.assert_allclose(sg[fin], sc[fin], rtol=1e-5)


@pytest.mark.parametrize("case", ["nan_border", "zero_border", "wedge"])
@pytest.mark.parametrize("lw", [1, 3])
def test_pcdm_absent_matches_cpu(cp, case, lw):
    from sarship.pipeline.detectors.pcdm import span_psh

    spec = detectors.get("pcdm")
    prm = spec.params(looks_window=lw, pfa=1e-3)
    halo = spec.halo(prm)
    X, _ = _absent(_quadpol((2 * halo + 257, 2 * halo + 263), 3, seed=3), case, halo)
    sc, pc = span_psh(X, halo, (-halo, -halo), prm)
    sg, pg = span_psh(cp.asarray(X), halo, (-halo, -halo), prm)
    sg, pg = sg.get(), pg.get()
    assert np.isnan(sc).any()
    assert np.array_equal(sc, sg, equal_nan=True)  # same sums, same untested pixels
    np.testing.assert_array_equal(np.isnan(pc), np.isnan(pg))
    np.testing.assert_allclose(pg, pc, rtol=1e-9, atol=1e-12)
    prep = spec.prepare(prm)
    a = spec.scene_pass(X, halo, (-halo, -halo), prm, prep)
    b = spec.scene_pass(cp.asarray(X), halo, (-halo, -halo), prm, prep)
    assert a["min"] == b["min"] and a["max"] == b["max"] and a["n"] == b["n"]
    assert np.abs(a["hist"] - b["hist"]).sum() <= 4
    prep = {**prep, **spec.reduce([a], prm, prep)}
    mc, stc = spec.detect(X, halo, (-halo, -halo), prm, prep)
    mg, stg = spec.detect(cp.asarray(X), halo, (-halo, -halo), prm, prep)
    assert np.array_equal(mc, mg.get()) and np.array_equal(stc, stg.get())


@pytest.mark.parametrize("case", ["nan_border", "zero_border", "wedge"])
@pytest.mark.parametrize("p", [2, 3])
def test_vb_polsar_absent_matches_cpu(cp, case, p):
    spec = detectors.get("vb_polsar")
    prm = spec.params(sample_stride=4, pfa=1e-3)
    X, a = _absent(_quadpol((400, 380), p, seed=9), case, 0)
    prep = spec.prepare(prm)
    prep = {**prep, **spec.reduce([spec.scene_pass(X, 0, (0, 0), prm, prep)], prm, prep)}
    mc, sc = spec.detect(X, 0, (0, 0), prm, prep)
    mg, sg = spec.detect(cp.asarray(X), 0, (0, 0), prm, prep)
    mg, sg = mg.get(), sg.get()
    assert mc.sum() > 5 and not mc[a].any() and not mg[a].any()
    assert np.all(sc[a] == -np.inf) and np.all(sg[a] == -np.inf)
    thr = float(np.log1p(-prep["alpha0"]) - np.log(prep["alpha0"]))
    total, far = _flips(mc, sc, mg, thr, rel=1e-5)
    assert far == 0 and total <= 2, (total, far)
    np.testing.assert_allclose(sg, sc, rtol=1e-5, atol=1e-5)
