"""Window sums and CA-CFAR, bit for bit, against a plain numpy statement of the summation order.

``pipeline.boxsum`` promises more than "the right sums": every sum is formed by one fixed
sequence of float64 additions, set by global pixel coordinates alone (module docstring),
so that tiled and whole-scene runs agree to the last bit. The reference below states that
sequence with ``np.add.accumulate`` (a strictly sequential running sum) one block at a time,
and the fast streamed kernels must reproduce it exactly (NaN payloads aside) for every
window, origin, tile shape, strip width and dtype, including tiles smaller than the window,
1-pixel tiles, signed zeros, infinities and NaNs.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline import boxsum
from sarship.pipeline.boxsum import centered_box_sum
from sarship.pipeline.detectors import ca_cfar
from sarship.pipeline.windows import mirror_pad


def _vh_ref(a: np.ndarray, m: int, g0: int, zero_start: bool) -> np.ndarray:
    """Sums of ``m`` consecutive elements along the last axis of float64 ``a``, whose first
    element has global coordinate ``g0``, in the van Herk order: blocks ``[s, s + m)`` with
    ``(g0 + s) % m == 0``; suffix from the block end down, prefix of the next block from its
    start up, both starting from 0.0 (``zero_start``, horizontal pass) or from the first
    element (vertical pass); window ``suffix[i]`` when ``i`` starts a block, else
    ``suffix[i] + prefix[i + m - 1]``."""
    n = a.shape[-1] - m + 1
    out = np.empty(a.shape[:-1] + (n,))
    zero = np.zeros(a.shape[:-1] + (1,))

    def run(seg):
        if zero_start:
            return np.add.accumulate(np.concatenate([zero, seg], axis=-1), axis=-1)[..., 1:]
        return np.add.accumulate(seg, axis=-1)

    s = -(g0 % m)
    while s < n:
        lo, hi = max(s, 0), min(s + m, n)
        if lo < hi:
            e = s + m - 1
            suf = run(a[..., lo:e + 1][..., ::-1])[..., ::-1]  # suf[..., c - lo], c in [lo, e]
            if lo == s:
                out[..., s] = suf[..., 0]
            first = max(lo, s + 1)
            if first < hi:
                pre = run(a[..., s + m: hi + m - 1])  # pre[..., k]: rows s + m .. s + m + k
                for i in range(first, hi):
                    out[..., i] = suf[..., i - lo] + pre[..., i - s - 1]
        s += m
    return out


def box_sum_ref(block, m, halo, origin):
    r = m // 2
    off = halo - r
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    sub = np.asarray(block[off: off + h + m - 1, off: off + w + m - 1], dtype=np.float64)
    with np.errstate(all="ignore"):  # inf - inf and the like are part of the test inputs
        horiz = _vh_ref(sub, m, origin[1] + off, zero_start=True)
        return np.ascontiguousarray(_vh_ref(horiz.T, m, origin[0] + off, zero_start=False).T)


def ca_cfar_ref(block, halo, origin, p, prep):
    bg = box_sum_ref(block, p.background, halo, origin)
    gd = box_sum_ref(block, p.guard, halo, origin)
    if p.target == 1:
        xt = block[halo: block.shape[0] - halo, halo: block.shape[1] - halo]
    else:
        xt = box_sum_ref(block, p.target, halo, origin) / float(p.target**2)
    with np.errstate(all="ignore"):
        mean = (bg - gd) * (1.0 / float(prep["n_ring"]))
        q = xt / mean
        s = np.where(mean > 0.0, q, np.where(xt > 0.0, np.inf, 0.0))
    return s > float(prep["threshold"]), s.astype(np.float32)


def assert_bits(got, ref):
    assert got.shape == ref.shape and got.dtype == ref.dtype, (got.shape, ref.shape, got.dtype, ref.dtype)
    if got.dtype == np.bool_:
        np.testing.assert_array_equal(got, ref)
        return
    nan_g, nan_r = np.isnan(got), np.isnan(ref)
    np.testing.assert_array_equal(nan_g, nan_r)
    bad = got[~nan_g].tobytes() != ref[~nan_r].tobytes()
    if bad:
        d = np.flatnonzero((got != ref) & ~nan_g)
        raise AssertionError(f"{d.size} values differ, first at {np.unravel_index(d[0], got.shape)}: "
                             f"{got.flat[d[0]]!r} != {ref.flat[d[0]]!r}")


def _values(rng, shape, kind, dtype):
    if kind == "int16":
        return rng.integers(-1000, 1000, shape).astype(np.int16)
    if kind == "gamma":
        x = rng.gamma(1.5, 1.0, shape)
    elif kind == "wide":  # magnitudes over 16 decades: any change of order shows
        x = rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 9, shape)
    else:  # special values
        x = rng.gamma(2.0, 1.0, shape)
        u = rng.random(shape)
        x[u < 0.05] = 0.0
        x[(u >= 0.05) & (u < 0.08)] = -0.0
        x[(u >= 0.08) & (u < 0.09)] = -2.5
        x[(u >= 0.09) & (u < 0.095)] = 1e30
        if kind == "nonfinite":
            x[(u >= 0.095) & (u < 0.097)] = np.inf
            x[(u >= 0.097) & (u < 0.098)] = -np.inf
            x[(u >= 0.098) & (u < 0.099)] = np.nan
    return x.astype(dtype)


KINDS = [("gamma", np.float32), ("wide", np.float64), ("special", np.float32),
         ("nonfinite", np.float64), ("wide", np.float32), ("int16", None)]


def _box_cases(seed, n):
    rng = np.random.default_rng(seed)
    for k in range(n):
        m = int(rng.choice([1, 3, 5, 7, 9, 11, 21, 41, 61, 63, 127, 255, 2 * int(rng.integers(0, 128)) + 1]))
        halo = m // 2 + int(rng.choice([0, 0, 1, 4]))
        if k % 6 == 0:
            h, w = 1, 1
        elif k % 6 == 1:
            h, w = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        else:
            top = 200 if m <= 63 else 40
            h, w = int(rng.integers(1, top)), int(rng.integers(1, top))
        origin = (int(rng.integers(-700, 700)), int(rng.integers(-700, 700)))
        kind, dtype = KINDS[k % len(KINDS)]
        yield _values(rng, (h + 2 * halo, w + 2 * halo), kind, dtype), m, halo, origin


@pytest.mark.parametrize("seed", range(4))
def test_centered_box_sum_matches_reference_order(seed):
    for block, m, halo, origin in _box_cases(seed, 40):
        assert_bits(centered_box_sum(block, m, halo, origin), box_sum_ref(block, m, halo, origin))


@pytest.mark.parametrize("strip", [1, 2, 5, 64])
def test_box_sum_strips_change_nothing(monkeypatch, strip):
    monkeypatch.setattr(boxsum, "STRIP", strip)
    for block, m, halo, origin in _box_cases(10 + strip, 12):
        assert_bits(centered_box_sum(block, m, halo, origin), box_sum_ref(block, m, halo, origin))


def test_box_sum_non_contiguous_input_and_exact_values():
    rng = np.random.default_rng(7)
    big = _values(rng, (90, 120), "wide", np.float64)
    block = big[3:80, 100:20:-1]  # strided, reversed columns
    for m, origin in [(5, (-13, 4)), (21, (40, -41)), (1, (0, 0))]:
        halo = m // 2 + 2
        assert_bits(centered_box_sum(block, m, halo, origin), box_sum_ref(block, m, halo, origin))
    # sanity of the maths (not only of the order): integers are summed exactly
    x = rng.integers(0, 1000, (40, 50)).astype(np.float32)
    s = centered_box_sum(x, 7, 3, (5, -9))
    ref = np.array([[x[i:i + 7, j:j + 7].sum(dtype=np.float64) for j in range(44)] for i in range(34)])
    np.testing.assert_array_equal(s, ref)


def test_box_sum_tiling_invariant():
    rng = np.random.default_rng(3)
    x = _values(rng, (97, 83), "wide", np.float32)
    m, halo = 11, 7
    P = mirror_pad(x, halo)
    whole = centered_box_sum(P, m, halo, (-halo, -halo))
    for th, tw in [(1, 1), (5, 9), (13, 4), (40, 83)]:
        for r0 in range(0, 97, th):
            for c0 in range(0, 83, tw):
                r1, c1 = min(r0 + th, 97), min(c0 + tw, 83)
                blk = P[r0: r1 + 2 * halo, c0: c1 + 2 * halo]
                assert_bits(centered_box_sum(blk, m, halo, (r0 - halo, c0 - halo)), whole[r0:r1, c0:c1])


def _cfar_cases(seed, n):
    rng = np.random.default_rng(seed)
    for k in range(n):
        t = int(rng.choice([1, 1, 1, 3, 5]))
        g = t + 2 * int(rng.integers(0, 12))
        b = g + 2 * int(rng.integers(1, 20))
        if k % 7 == 0:
            t, g, b = 1, 41, 61
        halo = b // 2 + int(rng.choice([0, 0, 3]))
        if k % 5 == 0:
            h, w = 1, 1
        elif k % 5 == 1:
            h, w = int(rng.integers(1, 8)), int(rng.integers(1, 8))
        else:
            h, w = int(rng.integers(1, 150)), int(rng.integers(1, 150))
        origin = (int(rng.integers(-400, 900)), int(rng.integers(-400, 900)))
        kind, dtype = KINDS[k % len(KINDS)]
        block = _values(rng, (h + 2 * halo, w + 2 * halo), kind, dtype)
        p = ca_cfar.CAParams(pfa=float(rng.choice([1e-1, 1e-2, 1e-5])), target=t, guard=g, background=b,
                             looks=float(rng.choice([1.0, 2.0, 4.5])), min_area_px=1)
        yield block, halo, origin, p


@pytest.mark.parametrize("seed", range(3))
def test_ca_cfar_matches_reference_order(seed):
    for block, halo, origin, p in _cfar_cases(100 + seed, 25):
        prep = ca_cfar.prepare(p)
        mask, stat = ca_cfar.detect(block, halo, origin, p, prep)
        ref_mask, ref_stat = ca_cfar_ref(block, halo, origin, p, prep)
        assert_bits(mask, ref_mask)
        assert_bits(stat, ref_stat)


@pytest.mark.parametrize("strip", [1, 3, 17])
def test_ca_cfar_strips_change_nothing(monkeypatch, strip):
    monkeypatch.setattr(boxsum, "STRIP", strip)
    for block, halo, origin, p in _cfar_cases(200 + strip, 8):
        prep = ca_cfar.prepare(p)
        mask, stat = ca_cfar.detect(block, halo, origin, p, prep)
        ref_mask, ref_stat = ca_cfar_ref(block, halo, origin, p, prep)
        assert_bits(mask, ref_mask)
        assert_bits(stat, ref_stat)


def test_ca_cfar_default_windows_on_a_large_tile():
    """The production shape class: default windows, a tile much wider than a strip."""
    rng = np.random.default_rng(5)
    p = ca_cfar.CAParams(pfa=1e-3, looks=2.0)
    halo = p.background // 2
    block = rng.gamma(2.0, 0.5, (300 + 2 * halo, 2100 + 2 * halo)).astype(np.float32)
    block[100:104, 500:506] = 40.0
    prep = ca_cfar.prepare(p)
    mask, stat = ca_cfar.detect(block, halo, (1234, -30), p, prep)
    ref_mask, ref_stat = ca_cfar_ref(block, halo, (1234, -30), p, prep)
    assert_bits(mask, ref_mask)
    assert_bits(stat, ref_stat)
    assert mask[100 - halo:104 - halo, 500 - halo:506 - halo].all()
