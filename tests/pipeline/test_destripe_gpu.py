"""GPU twins of the destriping maths (CuPy arrays through the same functions) against the CPU.

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none).
The scene-pass sums are integers (exact on both devices); the gain is one multiply per pixel.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline.gpu import available
from sarship.pipeline.image import destripe as D
from sarship.pipeline.simulate import SimConfig, simulate_array

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.fixture(scope="module")
def scene():
    I = simulate_array(SimConfig(shape=(1024, 768), ships=5, seed=1, clutter="k", stripes=True, land=True))[0][
        "intensity"
    ]
    I = I.copy()
    I[:20] = np.nan
    return I


@pytest.mark.parametrize("along", ["azimuth", "range"])
def test_segment_sums_on_device_equal_cpu(scene, along):
    import cupy as cp

    p = D.DestripeParams(stripes_along=along)
    for r0, c0, blk in ((0, 0, scene), (100, 200, scene[100:611, 200:517])):
        a = D.segment_sums(blk, r0, c0, p)
        b = D.segment_sums(cp.asarray(blk), r0, c0, p)
        assert a["j0"] == b["j0"] and a["b0"] == b["b0"]
        assert isinstance(b["sums"], np.ndarray)
        # float32 ln on the device may differ from the host's in the last ulp (at most 32
        # units of 2**-24 for |ln P| < 64): bound each sum by 64 units a pixel
        assert (np.abs(a["sums"] - b["sums"]) <= 64 * a["counts"]).all()
        assert np.array_equal(a["counts"], b["counts"])


def test_gain_on_device_equal_cpu(scene):
    import cupy as cp

    p = D.DestripeParams()
    est = D.estimate(*D.assemble([D.segment_sums(scene, 0, 0, p)], scene.shape, p), p)
    assert est.stop.any()
    want = D.apply_gain(scene, est.profile, p)
    got = D.apply_gain(cp.asarray(scene), est.profile, p)
    assert isinstance(got, cp.ndarray) and got.dtype == want.dtype
    np.testing.assert_allclose(got.get(), want, rtol=2e-7, equal_nan=True)
    z = (scene * np.exp(1j * 0.3)).astype(np.complex64)
    np.testing.assert_allclose(
        D.apply_gain(cp.asarray(z), est.profile, p).get(), D.apply_gain(z, est.profile, p), rtol=2e-7, equal_nan=True
    )
