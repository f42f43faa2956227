"""GPU twin of the ratio line detector (CuPy arrays through the same function) against the CPU.

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none).
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline.gpu import available
from sarship.pipeline.targets import sidelobes as S

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.mark.parametrize("along", ["row", "col"])
@pytest.mark.parametrize("gap", [0, 1])
def test_line_response_on_device_equal_cpu(along, gap):
    import cupy as cp

    rng = np.random.default_rng(3)
    p = rng.exponential(1.0, (300, 257)).astype(np.float32)
    p[40, :] *= 30
    p[:, 90] *= 30
    p[5:9, 5:50] = np.nan
    want = S.line_response(p, along, gap)
    got = S.line_response(cp.asarray(p), along, gap)
    assert isinstance(got, cp.ndarray)
    np.testing.assert_allclose(got.get(), want, rtol=1e-12, atol=1e-15)
