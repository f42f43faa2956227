"""lmm on a CuPy block with the robust ring fit (refusal of a foreign light tail component, censoring).

The GPU twin (``pipeline/gpu/lmm.py``) transcribes the plain fit only; a fit that uses the
refusal rule or censoring (``refuse_weight``, ``censor``, ``censor_low`` > 0: the default
``refuse_weight`` 0.15 included) is decided by the CPU kernels for a CuPy block
(``detectors.lmm.cpu_only_fit``). These tests hold that route to the CPU result bit for bit
(CuPy arrays back), and the CUDA twin itself, reached with ``refuse_weight=0``, to the CPU
forms' agreement rule on the K-sea contamination scene. Marked ``gpu``; skipped cleanly where
CuPy or a CUDA device is missing (CI has none).
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


def _ksea_block(p, n=256):
    from sarship.pipeline.simulate import SimConfig, simulate_array

    cfg = SimConfig(
        kind="intensity", shape=(n, n), ships=4, seed=3, looks=4.0, clutter="k", scr_db=15.0, length_m=(120.0, 400.0)
    )
    arrs, _ = simulate_array(cfg)
    spec = detectors.get("lmm")
    halo = spec.halo(p)
    return np.pad(arrs["intensity"].astype(np.float32), halo, constant_values=np.nan), halo


@pytest.mark.parametrize(
    "kw",
    [{}, {"method": "fast", "guard": 11, "background": 21}, {"censor": 0.1, "censor_level": 0.03}, {"censor_low": 0.1}],
)
def test_robust_fit_on_cupy_block_equals_cpu(cp, kw):
    spec = detectors.get("lmm")
    p = spec.params(**kw)
    prep = spec.prepare(p)
    blk, halo = _ksea_block(p)
    mc, sc = spec.detect(blk, halo, (-halo, -halo), p, prep)
    mg, sg = spec.detect(cp.asarray(blk), halo, (-halo, -halo), p, prep)
    assert isinstance(mg, cp.ndarray) and isinstance(sg, cp.ndarray)
    assert mc.sum() > 0
    np.testing.assert_array_equal(mg.get(), mc)
    np.testing.assert_array_equal(sg.get(), sc)


@pytest.mark.parametrize("method", ["fast", "grid"])
def test_plain_fit_cuda_twin_on_contamination_scene(cp, method):
    """refuse_weight=0: the CUDA twin (the transcribed plain fit) against the CPU."""
    spec = detectors.get("lmm")
    # pfa 1e-3: the plain fit (refuse_weight=0) leaves these ships' pixels mostly undetected
    # (the contamination the default refuses); 1e-3 still detects 11 pixels to compare
    p = spec.params(method=method, refuse_weight=0.0, guard=11, background=21, pfa=1e-3)
    prep = spec.prepare(p)
    blk, halo = _ksea_block(p, 160)
    mc, sc = spec.detect(blk, halo, (-halo, -halo), p, prep)
    mg, sg = spec.detect(cp.asarray(blk), halo, (-halo, -halo), p, prep)
    mg, sg = mg.get(), sg.get()
    assert mc.sum() > 8
    diff = int((mc != mg).sum())
    assert diff <= max(1, int(0.001 * mc.size)), (diff, int(mc.sum()), int(mg.sum()))
    both = mc & mg
    np.testing.assert_allclose(sg[both], sc[both], rtol=1e-6)
