"""GPU twin of ``csk`` (:mod:`sarship.pipeline.gpu.csk`) against the CPU on the same blocks.
Marked ``gpu``; skipped cleanly without CuPy and a CUDA device.

Equality rule (tests/workers/test_gpu.py): the window sums are bit-identical and the per-pixel
arithmetic is the same IEEE additions, multiplications and divisions (no transcendental
function), one CuPy element-wise kernel each, so the statistic and the mask are expected to
equal the CPU's bit for bit; masks may differ at most at pixels within 1e-6 of the threshold.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.gpu import available
from sarship.pipeline.tiling.windows import mirror_pad

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


def _slc(n, seed):
    rng = np.random.default_rng(seed)
    z = ((rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) / np.sqrt(2)).astype(np.complex64)
    for _ in range(max(4, n // 40)):
        i, j = rng.integers(8, n - 12, 2)
        z[i : i + 3, j : j + 5] *= 20.0
    z[: n // 7, : n // 5] = np.nan  # no-data corner
    z[n // 2, n // 3] = 0.0
    return z


@pytest.mark.parametrize("cells", ["bright", "window"])
@pytest.mark.parametrize("window,origin", [(7, (-3, -3)), (9, (1234, 567)), (3, (5, -1))])
def test_csk_gpu_equals_cpu(cells, window, origin):
    import cupy

    spec = detectors.get("csk")
    p = spec.params(window=window, pfa=1e-3, cells=cells, nodata=0.0)
    prep = spec.prepare(p)
    h = window // 2
    block = mirror_pad(_slc(512, window), h)
    mc, sc = spec.detect(block, h, origin, p, prep)
    mg, sg = spec.detect(cupy.asarray(block), h, origin, p, prep)
    assert isinstance(mg, cupy.ndarray) and mg.dtype == cupy.bool_ and sg.dtype == cupy.float32
    mg, sg = mg.get(), sg.get()
    d = mc != mg
    near = np.abs(sc.astype(np.float64) - prep["threshold"]) <= 1e-6 * abs(prep["threshold"])
    assert int((d & ~near).sum()) == 0 and int(d.sum()) <= 3
    np.testing.assert_allclose(sg, sc, rtol=1e-6, atol=1e-6)
    assert mc.sum() > 0


def test_csk_gpu_refuses_real_blocks():
    import cupy

    spec = detectors.get("csk")
    p = spec.params(pfa=1e-3)
    with pytest.raises(ValueError, match="complex"):
        spec.detect(cupy.ones((20, 20), cupy.float32), 3, (-3, -3), p, spec.prepare(p))
