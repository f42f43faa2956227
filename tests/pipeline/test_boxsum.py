"""Window sums and CA-CFAR, bit for bit, against a plain numpy statement of the summation order.

``pipeline.tiling.boxsum`` promises more than "the right sums": every sum is formed by one fixed
sequence of float64 additions, set by global pixel coordinates alone (module docstring),
so that tiled and whole-scene runs agree to the last bit. The reference
(``boxsum_helpers.box_sum_ref``) states that sequence with ``np.add.accumulate`` (a strictly
sequential running sum) one block at a time, and the fast streamed kernels must reproduce it
exactly (NaN payloads aside) for every window, origin, tile shape, strip width and dtype,
including tiles smaller than the window, 1-pixel tiles, signed zeros, infinities and NaNs.
"""

from __future__ import annotations

import numpy as np
import pytest
from boxsum_helpers import assert_bits, box_sum_ref, cfar_cases, tiles, values

from sarship.pipeline.detectors import ca_cfar
from sarship.pipeline.tiling import boxsum
from sarship.pipeline.tiling.boxsum import centered_box_sum
from sarship.pipeline.tiling.windows import mirror_pad


def ca_cfar_ref(block, halo, origin, p, prep):
    bg = box_sum_ref(block, p.background, halo, origin)
    gd = box_sum_ref(block, p.guard, halo, origin)
    if p.target == 1:
        xt = block[halo : block.shape[0] - halo, halo : block.shape[1] - halo]
    else:
        xt = box_sum_ref(block, p.target, halo, origin) / float(p.target**2)
    with np.errstate(all="ignore"):
        mean = (bg - gd) * (1.0 / float(prep["n_ring"]))
        q = xt / mean
        s = np.where(mean > 0.0, q, np.where(xt > 0.0, np.inf, 0.0))
    return s > float(prep["threshold"]), s.astype(np.float32)


KINDS = [
    ("gamma", np.float32),
    ("wide", np.float64),
    ("special", np.float32),
    ("nonfinite", np.float64),
    ("wide", np.float32),
    ("int16", None),
]


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
        yield values(rng, (h + 2 * halo, w + 2 * halo), kind, dtype), m, halo, origin


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
    big = values(rng, (90, 120), "wide", np.float64)
    block = big[3:80, 100:20:-1]  # strided, reversed columns
    for m, origin in [(5, (-13, 4)), (21, (40, -41)), (1, (0, 0))]:
        halo = m // 2 + 2
        assert_bits(centered_box_sum(block, m, halo, origin), box_sum_ref(block, m, halo, origin))
    # sanity of the maths (not only of the order): integers are summed exactly
    x = rng.integers(0, 1000, (40, 50)).astype(np.float32)
    s = centered_box_sum(x, 7, 3, (5, -9))
    ref = np.array([[x[i : i + 7, j : j + 7].sum(dtype=np.float64) for j in range(44)] for i in range(34)])
    np.testing.assert_array_equal(s, ref)


def test_box_sum_tiling_invariant():
    rng = np.random.default_rng(3)
    x = values(rng, (97, 83), "wide", np.float32)
    m, halo = 11, 7
    P = mirror_pad(x, halo)
    whole = centered_box_sum(P, m, halo, (-halo, -halo))
    for core, blk, origin in tiles(P, halo, x.shape):
        assert_bits(centered_box_sum(blk, m, halo, origin), whole[core])


def _cfar_cases(seed, n):
    for rng, _, block, halo, origin, (t, g, b) in cfar_cases(seed, n, KINDS, {0: (1, 41, 61)}):
        p = ca_cfar.CAParams(
            pfa=float(rng.choice([1e-1, 1e-2, 1e-5])),
            target=t,
            guard=g,
            background=b,
            looks=float(rng.choice([1.0, 2.0, 4.5])),
            min_area_px=1,
        )
        yield block, halo, origin, p


def _check(block, halo, origin, p):
    prep = ca_cfar.prepare(p)
    if np.isfinite(block).all():
        mask, stat = ca_cfar.detect(block, halo, origin, p, prep)
    else:  # the fused kernel's bits; NaN / inf are absent pixels in detect(): tests/pipeline/test_nodata_cfar.py
        mask, stat = ca_cfar._detect_complete(block, halo, origin, p.target, p.guard, p.background, prep)
    ref_mask, ref_stat = ca_cfar_ref(block, halo, origin, p, prep)
    assert_bits(mask, ref_mask)
    assert_bits(stat, ref_stat)
    return mask


@pytest.mark.parametrize("seed", range(3))
def test_ca_cfar_matches_reference_order(seed):
    for case in _cfar_cases(100 + seed, 25):
        _check(*case)


@pytest.mark.parametrize("strip", [1, 3, 17])
def test_ca_cfar_strips_change_nothing(monkeypatch, strip):
    monkeypatch.setattr(boxsum, "STRIP", strip)
    for case in _cfar_cases(200 + strip, 8):
        _check(*case)


def test_ca_cfar_default_windows_on_a_large_tile():
    """The production shape class: default windows, a tile much wider than a strip."""
    rng = np.random.default_rng(5)
    p = ca_cfar.CAParams(pfa=1e-3, looks=2.0)
    halo = p.background // 2
    block = rng.gamma(2.0, 0.5, (300 + 2 * halo, 2100 + 2 * halo)).astype(np.float32)
    block[100:104, 500:506] = 40.0
    mask = _check(block, halo, (1234, -30), p)
    assert mask[100 - halo : 104 - halo, 500 - halo : 506 - halo].all()
