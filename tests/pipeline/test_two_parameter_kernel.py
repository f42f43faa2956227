"""The fused two-parameter kernel, bit for bit, against a plain numpy statement of its maths.

``two_parameter.detect`` streams all its window sums in one SIMD kernel. It promises the
results of the plain pipeline, to the last bit, for every input: y = the tile as float64,
transformed (identity, sqrt(max(x, 0)) or 10 log10(max(x, 1e-30)), by numpy); the window
sums of y and y * y over the background and guard windows (and of y over the target
window) in the van Herk order of :mod:`sarship.pipeline.tiling.boxsum` (stated below with
``np.add.accumulate``, a strictly sequential running sum, one block at a time); then
s1 = s1b - s1g, s2 = s2b - s2g, mu = s1 / N, var = (s2 - s1 mu) / (N - 1), d = x_t - mu,
statistic d / sqrt(var) (inf if var <= 0 < d, else 0 if var <= 0), mask = statistic > t.
Checked for every dtype, domain, window, origin, tile shape and strip width, including
tiles smaller than the window, 1-pixel tiles, signed zeros, infinities and NaNs, and for
any tiling of a scene.
"""

from __future__ import annotations

import numpy as np
import pytest
from boxsum_helpers import SPECIAL, assert_bits, box_sum_ref, cfar_cases, tiles, values
from numba import njit, uint64

from sarship.pipeline.detectors import simd
from sarship.pipeline.detectors import two_parameter as tp
from sarship.pipeline.tiling.boxsum import centered_box_sum
from sarship.pipeline.tiling.windows import mirror_pad


def _transform(block, domain):
    x = block.astype(np.float64)
    with np.errstate(all="ignore"):
        if domain == "amplitude":
            return np.sqrt(np.maximum(x, 0.0))
        if domain == "db":
            return 10.0 * np.log10(np.maximum(x, 1e-30))
    return x


def _decide(xt, s1b, s1g, s2b, s2g, prep):
    n = float(prep["n_ring"])
    with np.errstate(all="ignore"):
        s1 = s1b - s1g
        s2 = s2b - s2g
        mu = s1 / n
        var = (s2 - s1 * mu) / (n - 1.0)
        d = xt - mu
        s = np.where(var > 0.0, d / np.sqrt(var), np.where(d > 0.0, np.inf, 0.0))
    return s > float(prep["threshold"]), s.astype(np.float32)


def two_parameter_ref(block, halo, origin, p, prep, box=box_sum_ref):
    """The plain pipeline; ``box`` = the numpy reference or ``boxsum.centered_box_sum``."""
    y = _transform(block, p.domain)
    with np.errstate(all="ignore"):
        y2 = y * y
    s1b, s1g = box(y, p.background, halo, origin), box(y, p.guard, halo, origin)
    s2b, s2g = box(y2, p.background, halo, origin), box(y2, p.guard, halo, origin)
    if p.target == 1:
        xt = y[halo : y.shape[0] - halo, halo : y.shape[1] - halo]
    else:
        xt = box(y, p.target, halo, origin) / float(p.target**2)
    return _decide(xt, s1b, s1g, s2b, s2g, prep)


#: inputs of the "special" kind also hold 1e-35 (below the ``db`` floor); "nonfinite" ones
#: fewer infinities and NaNs than in tests/pipeline/test_boxsum.py
_SPECIAL = SPECIAL + ((0.095, 0.097, 1e-35),)
_NONFINITE = ((0.097, 0.098, np.inf), (0.098, 0.099, -np.inf), (0.099, 0.0995, np.nan))
KINDS = [
    ("gamma", np.float32),
    ("wide", np.float64),
    ("special", np.float32),
    ("nonfinite", np.float64),
    ("decades", np.float64),
    ("wide", np.float32),
    ("special", np.float64),
    ("nonfinite", np.float32),
    ("flat", np.float32),
    ("int16", None),
]
DOMAINS = ["intensity", "amplitude", "db"]


def _cases(seed, n):
    fixed = {0: (1, 21, 41), 3: (3, 21, 41)}  # the defaults, and with a target window
    for rng, k, block, halo, origin, (t, g, b) in cfar_cases(
        seed, n, KINDS, fixed, special=_SPECIAL, nonfinite=_NONFINITE
    ):
        p = tp.TwoParameterParams(
            pfa=float(rng.choice([1e-1, 1e-2, 1e-5])),
            target=t,
            guard=g,
            background=b,
            domain=DOMAINS[(k // len(KINDS)) % 3 if k % 2 else k % 3],
            threshold=str(rng.choice(["student", "gaussian"])),
            min_area_px=1,
        )
        yield block, halo, origin, p


def _check(block, halo, origin, p, box=box_sum_ref):
    prep = tp.prepare(p)
    # the fused kernel's bits on every input; with NaN / inf (absent pixels since the no-data
    # rule) detect() recomputes the pixels next to them: tests/pipeline/test_nodata_cfar.py
    run = tp.detect if np.isfinite(block).all() else tp._detect_complete
    mask, stat = run(block, halo, origin, p, prep)
    ref_mask, ref_stat = two_parameter_ref(block, halo, origin, p, prep, box)
    assert_bits(mask, ref_mask)
    assert_bits(stat, ref_stat)
    return mask, stat


@pytest.mark.parametrize("seed", range(4))
def test_kernel_matches_reference_order(seed):
    for block, halo, origin, p in _cases(300 + seed, 30):
        _check(block, halo, origin, p)


def test_kernel_matches_boxsum_pipeline():
    """The former implementation: transform, ``centered_box_sum`` x 4 (5), decision."""
    for block, halo, origin, p in _cases(400, 20):
        _check(block, halo, origin, p, box=centered_box_sum)


@pytest.mark.parametrize("strip", [1, 3, 17])
def test_kernel_strips_change_nothing(monkeypatch, strip):
    monkeypatch.setattr(tp, "STRIP", strip)
    for block, halo, origin, p in _cases(500 + strip, 8):
        _check(block, halo, origin, p)


@pytest.mark.parametrize("domain", DOMAINS)
@pytest.mark.parametrize("target", [1, 3])
def test_kernel_default_windows_on_a_large_tile(domain, target):
    """The production shape class: default windows, several strips, many row blocks and
    (``db``) several bands of the logarithm."""
    rng = np.random.default_rng(6)
    p = tp.TwoParameterParams(domain=domain, target=target)
    halo = p.background // 2
    block = rng.gamma(2.0, 0.5, (170 + 2 * halo, 1700 + 2 * halo)).astype(np.float32)
    block[100:104, 500:506] = 40.0
    mask, _ = _check(block, halo, (1234, -30), p)
    assert mask[100 - halo : 104 - halo, 500 - halo : 506 - halo].any()


def test_kernel_non_contiguous_input():
    rng = np.random.default_rng(8)
    big = values(rng, (120, 150), "gamma", np.float64)
    block = big[3:110, 140:10:-1]  # strided, reversed columns
    for domain in DOMAINS:
        p = tp.TwoParameterParams(guard=5, background=13, target=3, domain=domain)
        _check(block, 9, (-7, 11), p)


@pytest.mark.parametrize("domain", DOMAINS)
def test_kernel_tiling_invariant(domain):
    rng = np.random.default_rng(3)
    x = rng.gamma(1.5, 1.0, (97, 83)).astype(np.float32)
    x[40:43, 20:24] = 30.0
    for t in (1, 3):
        p = tp.TwoParameterParams(pfa=1e-2, target=t, guard=9, background=21, domain=domain)
        prep = tp.prepare(p)
        halo = p.background // 2 + 2
        P = mirror_pad(x, halo)
        whole_m, whole_s = tp.detect(P, halo, (-halo, -halo), p, prep)
        for core, blk, origin in tiles(P, halo, x.shape):
            m, s = tp.detect(blk, halo, origin, p, prep)
            assert_bits(m, whole_m[core])
            assert_bits(s, whole_s[core])


def test_kernel_empty_tiles():
    p = tp.TwoParameterParams(guard=3, background=7)
    prep = tp.prepare(p)
    for h, w in [(0, 0), (0, 5), (5, 0)]:
        mask, stat = tp.detect(np.ones((h + 6, w + 6), np.float32), 3, (0, 0), p, prep)
        assert mask.shape == (h, w) and stat.shape == (h, w) and stat.dtype == np.float32


@njit
def _divn(a, n, out):
    nv = simd.vsplat(n)
    yv = simd.vsplat(1.0 / n)
    for j in range(0, a.size, 4):
        simd.vstore(out, uint64(j), simd.vdivn(simd.vload(a, uint64(j)), nv, yv))


def test_division_by_integer_is_correctly_rounded():
    """``simd.vdivn`` (FMA correction instead of the divider) equals IEEE division, including
    near rounding boundaries, for the divisors the kernel uses (ring sizes, N - 1, t^2)."""
    rng = np.random.default_rng(11)
    N = 1 << 16
    for n in [
        8.0,
        7.0,
        9.0,
        1240.0,
        1239.0,
        48.0,
        47.0,
        65025.0,
        1023**2 - 1021**2 - 1.0,
        *rng.integers(7, 1 << 20, 6).astype(float),
    ]:
        q = rng.uniform(1, 2, N) * 2.0 ** rng.integers(-60, 60, N)
        with np.errstate(all="ignore"):
            a = np.concatenate(
                [
                    rng.standard_normal(N) * 10.0 ** rng.uniform(-300, 300, N),
                    np.nextafter(q * n, rng.choice([-np.inf, np.inf], N)),  # near exact quotients
                    (rng.integers(-(2**52), 2**52, N) * 0.5) * n,  # quotients at half-integers
                    rng.standard_normal(N) * 2.0 ** rng.integers(-1075, 1024, N),  # subnormal to huge
                    np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 5e-324, -5e-324, 1.7e308] * 4),
                ]
            )
        out = np.empty_like(a)
        with np.errstate(all="ignore"):
            _divn(a, n, out)
            ref = a / n
        assert_bits(out, ref)


def test_kernel_threshold_is_strict():
    """mask = statistic > threshold: a statistic equal to the threshold is no detection
    (flat data: var = 0 and d = 0, statistic 0; a spike on a flat ring: statistic inf)."""
    p = tp.TwoParameterParams(guard=3, background=9)
    x = np.full((20, 30), 2.0, np.float32)
    x[10, 10] = 5.0
    P = mirror_pad(x, 4)
    prep = tp.prepare(p)
    for thr in (0.0, np.inf):
        mask, stat = tp.detect(P, 4, (-4, -4), p, {**prep, "threshold": thr})
        ref_mask, ref_stat = two_parameter_ref(P, 4, (-4, -4), p, {**prep, "threshold": thr})
        assert_bits(mask, ref_mask)
        assert_bits(stat, ref_stat)
        assert stat[10, 10] == np.inf and stat[0, 0] == 0.0
        assert mask.sum() == (1 if thr == 0.0 else 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_transform_matches_numpy_bit_for_bit(dtype):
    """y of each domain, as the kernel forms it (the logarithm of ``db`` by numpy in bands),
    against the numpy transform, on special values and over the whole exponent range."""
    rng = np.random.default_rng(12)
    x = np.concatenate(
        [
            np.array([0.0, -0.0, -1.0, 1e-30, 1e-31, 1.0, np.inf, -np.inf, np.nan, -np.nan, 5e-324, 1e-45, 3.4e38]),
            rng.standard_normal(4000) * 10.0 ** rng.uniform(-45, 38, 4000),
            rng.gamma(1.5, 1.0, 4000),
        ]
    ).astype(dtype)
    src = np.ascontiguousarray(np.tile(x, (3, 1)))
    n = x.size
    Y = np.empty((2, n + 5))
    for domain, mode in tp._MODE.items():
        with np.errstate(all="ignore"):
            ref = _transform(x, domain)
        if mode == 2:
            L = np.empty((2, n))
            tp._db_band(src, 1, 2, 0, L)
            tp._transform_row(L, 1, 0, n, mode, Y, 1)
        else:
            tp._transform_row(src, 1, 0, n, mode, Y, 1)
        got = Y[1, :n]
        assert_bits(got, ref)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(ref))  # zeros and NaNs too


def test_fused_kernel_equals_in_module_reference_fallback():
    """detect() and its plain fallback detect_reference() agree bit for bit."""
    from sarship.pipeline.detectors import two_parameter as tp
    from sarship.pipeline.tiling.windows import mirror_pad

    rng = np.random.default_rng(42)
    for domain in ("intensity", "amplitude", "db"):
        for target in (1, 3):
            x = rng.gamma(1.0, 1.0, (57, 61)).astype(np.float32)
            prm = tp.TwoParameterParams(guard=9, background=15, target=target, domain=domain, pfa=1e-2)
            prep = tp.prepare(prm)
            blk = mirror_pad(x, 7)
            m1, s1 = tp.detect(blk, 7, (-7, -7), prm, prep)
            m2, s2 = tp.detect_reference(blk, 7, (-7, -7), prm, prep)
            np.testing.assert_array_equal(m1, m2)
            np.testing.assert_array_equal(s1, s2)
