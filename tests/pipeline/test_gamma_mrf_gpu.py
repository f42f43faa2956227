"""``gamma_mrf``'s CuPy twin (pipeline/gpu/gamma_mrf.py) against the CPU, bit for bit.

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none). The ICM
energies are float64 in the CPU's order without fused multiply-adds, so labels, energy gaps,
masks, statistics and the scene-pass sums must be identical, not merely close.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.detectors import gamma_mrf as gm
from sarship.pipeline.gpu import available
from tests.conftest import blobs_scene
from tests.pipeline.test_gamma_mrf import scene_values

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]

SPEC = detectors.get("gamma_mrf")


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("nbh,ks", [(4, 3), (8, 3), (8, 2)])
@pytest.mark.parametrize("origin", [(0, 0), (-5, 3), (1001, -7)])
def test_icm_twin_bit_identical(cp, dtype, nbh, ks, origin):
    from sarship.pipeline.gpu.gamma_mrf import icm as gpu_icm

    rng = np.random.default_rng(5)
    H, W = 131, 97
    y = (rng.gamma(1.0, 1.0, (H, W)) * np.where(rng.random((H, W)) < 0.05, 30.0, 1.0)).astype(dtype)
    y[20:40, 10:30] = np.nan
    y[:, 90:] = np.nan
    ok = np.isfinite(y)
    mu = np.array([0.5, 1.0, 2.5, 15.0])
    w = np.array([0.3, 0.4, 0.25, 0.05])
    a0, b0 = np.log(mu) - np.log(w), 1.0 / mu
    A = np.stack([a0 * (1 + 0.01 * s) for s in range(4)])
    B = np.stack([b0 * (1 - 0.02 * s) for s in range(4)])
    lab = np.empty((H, W), np.int8)
    prev = lab.copy()
    gap = np.empty((H, W))
    gm.icm(y, ok, origin[0], origin[1], a0, b0, A, B, 0.9, nbh, ks, lab, prev, gap)
    gl, gp, gg = gpu_icm(cp.asarray(y), cp.asarray(ok), origin[0], origin[1], a0, b0, A, B, 0.9, nbh, ks)
    np.testing.assert_array_equal(gl.get(), lab)
    np.testing.assert_array_equal(gp.get(), prev)
    np.testing.assert_array_equal(gg.get(), gap)


@pytest.mark.parametrize("kw", [dict(), dict(neighbourhood=4, sweeps=2)])
def test_detect_and_scene_pass_twin(cp, kw):
    x = blobs_scene((150, 133), looks=2.0, seed=2, n=12, amp=60.0)
    x[30:50, 0:40] = np.nan
    p = SPEC.params(looks=2.0, sample_stride=2, **kw)
    prep, P, h, _ = scene_values(x, p)
    mc, sc = SPEC.detect(P, h, (-h, -h), p, prep)
    mg, sg = SPEC.detect(cp.asarray(P), h, (-h, -h), p, prep)
    assert isinstance(mg, cp.ndarray) and mg.dtype == cp.bool_ and sg.dtype == cp.float32
    np.testing.assert_array_equal(mg.get(), mc)
    np.testing.assert_array_equal(sg.get(), sc)
    assert mc.sum() > 10
    # scene passes: the EM sample (pass 0) and a re-estimation pass on the device
    p0 = SPEC.prepare(p)
    a = SPEC.scene_pass(P, h, (-h, -h), p, p0)
    b = SPEC.scene_pass(cp.asarray(P), h, (-h, -h), p, p0)
    np.testing.assert_array_equal(a["y"], b["y"])
    np.testing.assert_array_equal(a["rc"], b["rc"])
    mid = {**prep, "sweep_means": prep["sweep_means"][:2]}
    a = SPEC.scene_pass(P, h, (-h, -h), p, mid)
    b = SPEC.scene_pass(cp.asarray(P), h, (-h, -h), p, mid)
    np.testing.assert_array_equal(a["acc"], b["acc"])
    np.testing.assert_array_equal(a["counts"], b["counts"])
    assert a["changed"] == b["changed"]


@pytest.mark.parametrize("side", [24, 40])
def test_small_chip_twin(cp, side):
    """On a small chip both paths take the stride of the shared rule (gamma_mrf.for_scene) and the
    device's mask and statistic equal the CPU's; the EM sample (pass 0) is the same on either."""
    rng = np.random.default_rng(side)
    x = rng.gamma(2.0, 0.5, (side, side)).astype(np.float32)
    x[side // 2 - 2 : side // 2 + 2, side // 2 - 3 : side // 2 + 3] = 60.0
    p, notes = gm.for_scene(SPEC.params(looks=2.0), x.shape)
    assert p.sample_stride < 8 and notes
    prep, P, h, _ = scene_values(x, p)
    a = SPEC.scene_pass(P, h, (-h, -h), p, SPEC.prepare(p))
    b = SPEC.scene_pass(cp.asarray(P), h, (-h, -h), p, SPEC.prepare(p))
    np.testing.assert_array_equal(a["y"], b["y"])
    mc, sc = SPEC.detect(P, h, (-h, -h), p, prep)
    mg, sg = SPEC.detect(cp.asarray(P), h, (-h, -h), p, prep)
    np.testing.assert_array_equal(mg.get(), mc)
    np.testing.assert_array_equal(sg.get(), sc)
    assert mc[side // 2, side // 2]
