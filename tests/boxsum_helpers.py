"""Shared by the bit-for-bit tests of the window sums (tests/pipeline/test_boxsum.py) and of the fused
two-parameter kernel (tests/pipeline/test_two_parameter_kernel.py): the van Herk summation order of
:mod:`sarship.pipeline.tiling.boxsum` stated in numpy, a bit-for-bit comparison, random inputs and
CFAR cases, and the tiles of a scene.
"""

from __future__ import annotations

import numpy as np


def vh_ref(a: np.ndarray, m: int, g0: int, zero_start: bool) -> np.ndarray:
    """Sums of ``m`` consecutive elements along the last axis of float64 ``a``, whose first
    element has global coordinate ``g0``, in the van Herk order: blocks ``[s, s + m)`` with
    ``(g0 + s) % m == 0``; suffix from the block end down, prefix of the next block from its
    start up, both starting from 0.0 (``zero_start``, horizontal pass) or from the first
    element (vertical pass); window ``suffix[i]`` when ``i`` starts a block, else
    ``suffix[i] + prefix[i + m - 1]``. ``np.add.accumulate`` is a strictly sequential
    running sum."""
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
            suf = run(a[..., lo : e + 1][..., ::-1])[..., ::-1]  # suf[..., c - lo], c in [lo, e]
            if lo == s:
                out[..., s] = suf[..., 0]
            first = max(lo, s + 1)
            if first < hi:
                pre = run(a[..., s + m : hi + m - 1])  # pre[..., k]: rows s + m .. s + m + k
                for i in range(first, hi):
                    out[..., i] = suf[..., i - lo] + pre[..., i - s - 1]
        s += m
    return out


def box_sum_ref(block, m, halo, origin):
    """:func:`sarship.pipeline.tiling.boxsum.centered_box_sum` in numpy: rows, then columns."""
    r = m // 2
    off = halo - r
    h = block.shape[0] - 2 * halo
    w = block.shape[1] - 2 * halo
    sub = np.asarray(block[off : off + h + m - 1, off : off + w + m - 1], dtype=np.float64)
    with np.errstate(all="ignore"):  # inf - inf and the like are part of the test inputs
        horiz = vh_ref(sub, m, origin[1] + off, zero_start=True)
        return np.ascontiguousarray(vh_ref(horiz.T, m, origin[0] + off, zero_start=False).T)


def assert_bits(got, ref):
    """Same shape, dtype and bits (NaN payloads aside)."""
    assert got.shape == ref.shape and got.dtype == ref.dtype, (got.shape, ref.shape, got.dtype, ref.dtype)
    if got.dtype == np.bool_:
        np.testing.assert_array_equal(got, ref)
        return
    nan_g, nan_r = np.isnan(got), np.isnan(ref)
    np.testing.assert_array_equal(nan_g, nan_r)
    if got[~nan_g].tobytes() != ref[~nan_r].tobytes():
        d = np.flatnonzero((got != ref) & ~nan_g)
        raise AssertionError(
            f"{d.size} values differ, first at {np.unravel_index(d[0], got.shape)}: "
            f"{got.flat[d[0]]!r} != {ref.flat[d[0]]!r}"
        )


#: Values of the "special" kind: (lo, hi, value), the cells whose uniform draw u is in
#: [lo, hi) get the value, in this order; "nonfinite" adds NONFINITE.
SPECIAL = ((0.0, 0.05, 0.0), (0.05, 0.08, -0.0), (0.08, 0.09, -2.5), (0.09, 0.095, 1e30))
NONFINITE = ((0.095, 0.097, np.inf), (0.097, 0.098, -np.inf), (0.098, 0.099, np.nan))


def values(rng, shape, kind, dtype, special=SPECIAL, nonfinite=NONFINITE):
    """Random test input of ``kind``, as ``dtype`` (int16 for "int16")."""
    if kind == "int16":
        return rng.integers(-1000, 1000, shape).astype(np.int16)
    if kind == "gamma":
        x = rng.gamma(1.5, 1.0, shape)
    elif kind == "wide":  # magnitudes over 16 decades: any change of order shows
        x = rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 9, shape)
    elif kind == "decades":  # positive, over 80 decades (the dB domain's range)
        x = 10.0 ** rng.uniform(-40, 40, shape)
    elif kind == "flat":  # constant: var = 0 exactly
        x = np.full(shape, 3.0)
    else:  # special values
        x = rng.gamma(2.0, 1.0, shape)
        u = rng.random(shape)
        for lo, hi, v in special + (nonfinite if kind == "nonfinite" else ()):
            x[(u >= lo) & (u < hi)] = v
    return x.astype(dtype)


def cfar_cases(seed, n, kinds, fixed, **tables):
    """``n`` random CFAR cases ``(rng, k, block, halo, origin, (target, guard, background))``:
    random windows, or ``fixed[k % 7]`` where given; a halo of background // 2 + 0 or 3; a
    1 x 1, tiny or up to 149 x 149 tile at a random origin; input of ``kinds[k % len(kinds)]``
    (``tables``: ``values``' special and nonfinite tables). The caller draws the rest of its
    parameters from ``rng`` before taking the next case."""
    rng = np.random.default_rng(seed)
    for k in range(n):
        t = int(rng.choice([1, 1, 1, 3, 5]))
        g = t + 2 * int(rng.integers(0, 12))
        b = g + 2 * int(rng.integers(1, 20))
        t, g, b = fixed.get(k % 7, (t, g, b))
        halo = b // 2 + int(rng.choice([0, 0, 3]))
        if k % 5 == 0:
            h, w = 1, 1
        elif k % 5 == 1:
            h, w = int(rng.integers(1, 8)), int(rng.integers(1, 8))
        else:
            h, w = int(rng.integers(1, 150)), int(rng.integers(1, 150))
        origin = (int(rng.integers(-400, 900)), int(rng.integers(-400, 900)))
        kind, dtype = kinds[k % len(kinds)]
        block = values(rng, (h + 2 * halo, w + 2 * halo), kind, dtype, **tables)
        yield rng, k, block, halo, origin, (t, g, b)


def tiles(P, halo, shape, sizes=((1, 1), (5, 9), (13, 4), (40, 83))):
    """Every tile of the tilings of a scene of ``shape`` into tiles of ``sizes``, the scene
    padded by ``halo`` into ``P``: ``(core, block, origin)``, ``core`` the tile's slices of
    the scene."""
    for th, tw in sizes:
        for r0 in range(0, shape[0], th):
            for c0 in range(0, shape[1], tw):
                r1, c1 = min(r0 + th, shape[0]), min(c0 + tw, shape[1])
                yield (
                    (slice(r0, r1), slice(c0, c1)),
                    P[r0 : r1 + 2 * halo, c0 : c1 + 2 * halo],
                    (r0 - halo, c0 - halo),
                )
