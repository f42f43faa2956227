"""GPU twins of the intensity detectors on scenes with absent pixels (NaN border, declared
zero border, NaN wedge): the same mask and statistic as the CPU (tests/pipeline/test_nodata_cfar.py).

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing. Equality rule as in
tests/workers/test_gpu.py: masks may differ only where the statistic is within float rounding of the
threshold (a handful at most); statistics agree to 1e-6 relative. ``ca_cfar`` and ``os_cfar``
(and ``two_parameter`` in the intensity domain) are in fact expected bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline.gpu import available

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]

CASES = ["nan_border", "zero_border", "nan_wedge"]
NAMES = ["ca_cfar", "os_cfar", "two_parameter", "lmm"]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


@pytest.fixture(scope="module")
def nd():
    import tests.pipeline.test_nodata_cfar as nd

    return nd


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", NAMES)
def test_gpu_equals_cpu_with_absent_pixels(cp, nd, name, case):
    clutter = nd.SETTINGS[name][1]
    X = nd._scene(clutter, case)
    spec, p, prep, h, blk = nd._prep(name, X, nd._kw(name, case))
    m_c, s_c = spec.detect(blk, h, (-h, -h), p, prep)
    m_g, s_g = spec.detect(cp.asarray(blk), h, (-h, -h), p, prep)
    assert isinstance(m_g, cp.ndarray) and isinstance(s_g, cp.ndarray)
    m_g, s_g = m_g.get(), s_g.get()
    a = nd._absent(case)
    assert not m_g[a].any() and not s_g[a].any()
    diff = m_c != m_g
    assert int(diff.sum()) <= (0 if name in ("ca_cfar", "os_cfar") else 3), int(diff.sum())
    both = m_c & m_g
    np.testing.assert_allclose(s_g[both], s_c[both], rtol=1e-6)
    if name in ("ca_cfar", "os_cfar", "two_parameter"):
        np.testing.assert_array_equal(s_g, s_c)


@pytest.mark.parametrize("name", ["ca_cfar", "os_cfar", "two_parameter"])
def test_gpu_complete_scene_unchanged(cp, nd, name):
    """No absent pixel: the GPU path is the complete-data kernel (no redo)."""
    clutter = nd.SETTINGS[name][1]
    X = nd._clean(clutter)
    spec, p, prep, h, blk = nd._prep(name, X, nd.SETTINGS[name][0])
    m_c, s_c = spec.detect(blk, h, (-h, -h), p, prep)
    m_g, s_g = spec.detect(cp.asarray(blk), h, (-h, -h), p, prep)
    np.testing.assert_array_equal(m_g.get(), m_c)
    np.testing.assert_array_equal(s_g.get(), s_c)
