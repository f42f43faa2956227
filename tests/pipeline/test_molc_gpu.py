"""GPU twin of ``g0_cfar``, ``k_cfar``, ``ggd_cfar`` (:mod:`sarship.pipeline.gpu.molc`) against the
CPU on the same blocks. Marked ``gpu``; skipped cleanly without CuPy and a CUDA device.

Equality rule (tests/workers/test_gpu.py): the window sums are bit-identical; CUDA's log / log1p /
sqrt / exp may differ from the CPU's in the last bit, so statistics agree to 1e-6 relative
(float32 output) and masks differ only at pixels whose statistic lies within 1e-6 of the
threshold 1 (counted: none expected in practice, at most a handful allowed).
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.gpu import available
from sarship.pipeline.tiling.windows import mirror_pad

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


def _scene(n, seed):
    rng = np.random.default_rng(seed)
    a, L = 3.0, 2.0
    x = ((a - 1) * rng.gamma(L, 1 / L, (n, n)) / rng.gamma(a, 1.0, (n, n))).astype(np.float32)
    for _ in range(max(4, n // 40)):
        i, j = rng.integers(8, n - 12, 2)
        x[i : i + 3, j : j + 5] *= 80.0
    x[: n // 7, : n // 5] = np.nan  # no-data corner
    x[n // 2, n // 3] = 0.0  # unusable for ln x
    return x


def _both(cp, det, x, **kw):
    spec = detectors.get(det)
    p = spec.params(**{"looks": 2.0, **kw})
    prep = spec.prepare(p)
    h = spec.halo(p)
    blk = mirror_pad(x, h)
    mc, sc = spec.detect(blk, h, (-h, -h), p, prep)
    mg, sg = spec.detect(cp.asarray(blk), h, (-h, -h), p, prep)
    return mc, sc, mg.get(), sg.get()


def _check(mc, sc, mg, sg):
    d = mc != mg
    near = np.abs(sc.astype(np.float64) - 1.0) <= 1e-6
    assert int((d & ~near).sum()) == 0 and int(d.sum()) <= 3, (int(d.sum()), int(mc.sum()))
    np.testing.assert_allclose(sg, sc, rtol=1e-6, atol=0)
    assert np.array_equal(sg == 0, sc == 0)  # the same pixels untested


@pytest.mark.parametrize("det", ["g0_cfar", "k_cfar", "ggd_cfar"])
@pytest.mark.parametrize(
    "kw", [{"pfa": 1e-3, "guard": 11, "background": 31}, {"pfa": 1e-2, "guard": 7, "background": 21, "censor": 5.0}, {}]
)
def test_gpu_matches_cpu(cp, det, kw):
    x = _scene(700, 3)
    mc, sc, mg, sg = _both(cp, det, x, **kw)
    assert mc.sum() > 20
    _check(mc, sc, mg, sg)


@pytest.mark.parametrize("det,seed", [("g0_cfar", 1), ("k_cfar", 2), ("ggd_cfar", 3)])
def test_gpu_calibration_count_matches_cpu_on_4mpx(cp, det, seed):
    """2048^2 of the detector's own clutter at pfa 1e-3 (the CPU calibration test's setting):
    the GPU's false-alarm count equals the CPU's (up to near-threshold flips)."""
    rng = np.random.default_rng(seed)
    n, L = 2048, 2.0
    if det == "g0_cfar":
        x = 2.0 * rng.gamma(L, 1 / L, (n, n)) / rng.gamma(3.0, 1.0, (n, n))
    elif det == "k_cfar":
        x = rng.gamma(2.0, 0.5, (n, n)) * rng.gamma(L, 1 / L, (n, n))
    else:
        x = (rng.gamma(3.0, 1.0, (n, n)) / 3.0) ** (1 / 0.7)
    mc, sc, mg, sg = _both(cp, det, x.astype(np.float32), pfa=1e-3)
    assert abs(int(mc.sum()) - n * n * 1e-3) < 400
    _check(mc, sc, mg, sg)


def test_gpu_tiles_equal_whole_block(cp):
    """Tiling invariance holds on the device too (the strips and tiles change no sum)."""
    x = _scene(300, 5)
    spec = detectors.get("k_cfar")
    p = spec.params(looks=2.0, pfa=1e-2, guard=7, background=21, censor=6.0)
    prep = spec.prepare(p)
    h = spec.halo(p)
    P = mirror_pad(x, h)
    mw, sw = spec.detect(cp.asarray(P), h, (-h, -h), p, prep)
    mw, sw = mw.get(), sw.get()
    for t in (37, 128):
        for r0 in range(0, 300, t):
            for c0 in range(0, 300, t):
                r1, c1 = min(r0 + t, 300), min(c0 + t, 300)
                m, s = spec.detect(cp.asarray(P[r0 : r1 + 2 * h, c0 : c1 + 2 * h]), h, (r0 - h, c0 - h), p, prep)
                np.testing.assert_array_equal(m.get(), mw[r0:r1, c0:c1])
                np.testing.assert_array_equal(s.get(), sw[r0:r1, c0:c1])
