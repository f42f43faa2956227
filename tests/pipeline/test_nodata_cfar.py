"""Absent pixels (NaN, or a declared ``nodata`` value) in the intensity detectors.

Issue: ``ca_cfar`` on sea with a NaN border flagged a band of valid pixels along the border
as one detection that swallowed a real ship, and a zero border gave false alarms at the
corners. For ``ca_cfar``, ``os_cfar``, ``two_parameter`` and ``lmm``, each with a NaN border,
a zero border (declared ``nodata=0``) and a NaN wedge cutting into the sea:

- no absent pixel is ever detected, and the detections in the band next to the absent region
  (where the windows reach it) are within the binomial expectation of the PFA;
- a ship a few pixels from the absent region is found;
- on the valid pixels whose windows do not reach the absent region the mask and statistic
  equal those of the same scene without it, bit for bit;
- tiled == whole scene with absent pixels.

Rule (:mod:`sarship.pipeline.tiling.intensity_absent`): K present ring cells, exact threshold for K,
not tested when K < ceil(N/2) or the target window is not all present.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage, stats

from sarship.pipeline import detectors
from sarship.pipeline.tiling.windows import mirror_pad, padded_block

H = W = 192
B = 30  # border width
SHIPS = [(60, 60), (130, 90), (90, 140)]
EDGE_SHIP = (96, B + 4)  # 4 px inside the left border
WEDGE_SHIP = (52, 150)  # a few px above the wedge's upper edge
PFA = 1e-3
WIN = {"pfa": PFA, "guard": 7, "background": 15, "min_area_px": 1}
#: detector -> (parameters, clutter, PFA factor allowed (lmm: fitted tail, calibrated approximately))
SETTINGS = {
    "ca_cfar": ({**WIN, "looks": 4.0}, "gamma", 1.0),
    "os_cfar": ({**WIN, "looks": 4.0}, "gamma", 1.0),
    "two_parameter": (dict(WIN), "gauss", 1.0),
    "lmm": ({**WIN, "method": "fast", "components": 2, "max_iter": 50, "tol": 1e-3}, "gamma", 3.0),
}
CASES = ["nan_border", "zero_border", "nan_wedge"]
D = WIN["background"] // 2  # the band where the windows reach the absent region


def _absent(case: str) -> np.ndarray:
    r, c = np.mgrid[:H, :W]
    if case in ("nan_border", "zero_border"):
        a = np.ones((H, W), bool)
        a[B : H - B, B : W - B] = False
        return a
    # a NaN wedge from the right edge: apex at (96, 110), base rows 30 .. 162 on the last column
    return (c >= 110) & (np.abs(r - 96) <= (c - 110) * 66.0 / 81.0)


def _clean(clutter: str) -> np.ndarray:
    rng = np.random.default_rng(11)
    if clutter == "gamma":
        x = rng.gamma(4.0, 0.25, (H, W))
        amp = 30.0
    else:
        x = 10.0 + rng.standard_normal((H, W))
        amp = 12.0
    for r, c in SHIPS + [EDGE_SHIP, WEDGE_SHIP]:
        x[r : r + 3, c : c + 6] += amp
    return x.astype(np.float32)


def _scene(clutter: str, case: str) -> np.ndarray:
    x = _clean(clutter)
    x[_absent(case)] = np.nan if case.startswith("nan") else 0.0
    return x


def _kw(name, case):
    kw = dict(SETTINGS[name][0])
    if case == "zero_border":
        kw["nodata"] = 0.0
    return kw


def _prep(name, X, kw):
    spec = detectors.get(name)
    p = spec.params(**kw)
    prep = spec.prepare(p)
    h = spec.halo(p)
    return spec, p, prep, h, mirror_pad(X, h)


def _detect(name, X, kw):
    spec, p, prep, h, blk = _prep(name, X, kw)
    return spec.detect(blk, h, (-h, -h), p, prep)


@pytest.fixture(scope="module")
def results():
    out = {}
    for name, (kw, clutter, _) in SETTINGS.items():
        out[name, "clean"] = _detect(name, _clean(clutter), kw)
        for case in CASES:
            out[name, case] = _detect(name, _scene(clutter, case), _kw(name, case))
    return out


def _near(a: np.ndarray, d: int) -> np.ndarray:
    """Valid pixels within ``d`` px (Chebyshev) of the absent region."""
    return ndimage.binary_dilation(a, np.ones((2 * d + 1, 2 * d + 1), bool)) & ~a


def _ship_px(pad=2):
    m = np.zeros((H, W), bool)
    for r, c in SHIPS + [EDGE_SHIP, WEDGE_SHIP]:
        m[max(r - pad, 0) : r + 3 + pad, max(c - pad, 0) : c + 6 + pad] = True
    return m


def _bound(n: int, p: float) -> int:
    """Counts above this have probability < 1e-6 for independent cells (inflated 1.5x in
    variance for the cells' shared rings)."""
    e = p * n
    return int(max(stats.binom.isf(1e-6, n, p), e + 5.0 * math.sqrt(1.5 * e) + 2))


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_absent_never_detected_and_band_within_pfa(results, name, case):
    a = _absent(case)
    m, s = results[name, case]
    assert m.dtype == bool and m.shape == a.shape
    assert not m[a].any(), f"{int(m[a].sum())} absent pixels detected"
    assert not s[a].any()
    thr_n = {"ca_cfar": "threshold", "two_parameter": "threshold", "os_cfar": "alpha", "lmm": None}[name]
    if thr_n:  # the statistic agrees with the mask (rescaled where the ring is incomplete)
        spec = detectors.get(name)
        t_n = spec.prepare(spec.params(**_kw(name, case)))[thr_n]
        np.testing.assert_array_equal(s > t_n, m)
    else:
        np.testing.assert_array_equal(s > 1.0, m)
    factor = SETTINGS[name][2]
    for zone, where in (("band", _near(a, D) & ~_ship_px()), ("touching", _near(a, 1) & ~_ship_px())):
        n = int(where.sum())
        k = int(m[where].sum())
        assert k <= _bound(n, factor * PFA), (zone, k, n)
    lab, _ = ndimage.label(m)
    assert np.bincount(lab.ravel())[1:].max() <= 3 * 6 + 40  # no band-wide detection
    far = int((m & ~a & ~_ship_px()).sum())
    assert far <= _bound(int((~a).sum()), factor * PFA), far


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_ship_near_absent_region_is_found(results, name, case):
    m, _ = results[name, case]
    r, c = WEDGE_SHIP if case == "nan_wedge" else EDGE_SHIP
    assert m[r : r + 3, c : c + 6].any()
    for r, c in SHIPS:
        if not _absent(case)[r : r + 3, c : c + 6].any():
            assert m[r : r + 3, c : c + 6].any(), (r, c)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_valid_part_equals_scene_without_absent_pixels(results, name, case):
    a = _absent(case)
    m0, s0 = results[name, "clean"]
    m, s = results[name, case]
    # the windows of the pixels within D of the scene edge see the mirror of the absent region
    edge = np.zeros((H, W), bool)
    edge[D : H - D, D : W - D] = True
    far = ~a & ~_near(a, D) & (edge | ~_near(mirror_pad(a, D), D)[D : H + D, D : W + D])
    assert far.sum() > 5000
    np.testing.assert_array_equal(m[far], m0[far])
    np.testing.assert_array_equal(s[far], s0[far])


@pytest.mark.parametrize("name", list(SETTINGS))
def test_tiled_equals_whole_with_absent_pixels(name):
    """Tiles smaller than the windows, not dividing the scene, some all absent."""
    kw, clutter, _ = SETTINGS[name]
    X = _scene(clutter, "nan_border")
    a = _absent("nan_border")
    spec, p, prep, h, blk = _prep(name, X, kw)
    ts = 29
    tiles = [(r0, min(r0 + ts, H), c0, min(c0 + ts, W)) for r0 in range(0, H, ts) for c0 in range(0, W, ts)]
    assert any(a[r0:r1, c0:c1].all() for r0, r1, c0, c1 in tiles)
    ref_m, ref_s = spec.detect(blk, h, (-h, -h), p, prep)
    got_m = np.zeros((H, W), bool)
    got_s = np.zeros((H, W), np.float32)
    for r0, r1, c0, c1 in tiles:
        b = padded_block(lambda ra, rb, ca, cb: X[ra:rb, ca:cb], (H, W), r0, r1, c0, c1, h)
        got_m[r0:r1, c0:c1], got_s[r0:r1, c0:c1] = spec.detect(b, h, (r0 - h, c0 - h), p, prep)
    np.testing.assert_array_equal(got_m, ref_m)
    np.testing.assert_array_equal(got_s, ref_s)
    assert ref_m.sum() > 5


def _edge_setup(name):
    """A scene with NaN in its first 20 columns; the pixel (i, j) next to the edge, its
    present ring cells (brute force) and K."""
    kw, clutter, _ = SETTINGS[name]
    x = _clean(clutter)[:60, :60].copy()
    x[:, :20] = np.nan
    i, j = 30, 22
    x[i, j] = 8.0 if clutter == "gamma" else 14.0
    g, b = kw["guard"] // 2, kw["background"] // 2
    cells = np.array(
        [
            x[r, c]
            for r in range(i - b, i + b + 1)
            for c in range(j - b, j + b + 1)
            if (abs(r - i) > g or abs(c - j) > g) and not np.isnan(x[r, c])
        ],
        np.float64,
    )
    return kw, x, i, j, cells


def test_ca_cfar_threshold_uses_the_valid_count():
    kw, x, i, j, cells = _edge_setup("ca_cfar")
    K = cells.size
    N = kw["background"] ** 2 - kw["guard"] ** 2
    assert N / 2 <= K < N
    m, s = _detect("ca_cfar", x, kw)
    ratio = float(x[i, j]) / cells.mean()
    T = stats.f.isf(PFA, 2 * 4.0, 2 * K * 4.0)
    TN = stats.f.isf(PFA, 2 * 4.0, 2 * N * 4.0)
    assert s[i, j] == pytest.approx(ratio * TN / T, rel=1e-6)  # rescaled: stat > T(N) <=> detected
    assert m[i, j] == (ratio > T)
    assert not m[:, :20].any() and not s[:, :20].any()
    # a corner pixel with fewer than N/2 present ring cells is not tested
    y = x.copy()
    y[:20, :] = np.nan
    y[21, 21] = 1e6
    m2, s2 = _detect("ca_cfar", y, kw)
    assert not m2[21, 21] and s2[21, 21] == 0


def test_two_parameter_threshold_uses_the_valid_count():
    kw, x, i, j, cells = _edge_setup("two_parameter")
    K = cells.size
    m, s = _detect("two_parameter", x, kw)
    N = kw["background"] ** 2 - kw["guard"] ** 2
    z = (float(x[i, j]) - cells.mean()) / cells.std(ddof=1)
    T = math.sqrt(1.0 + 1.0 / K) * stats.t.isf(PFA, K - 1)
    TN = math.sqrt(1.0 + 1.0 / N) * stats.t.isf(PFA, N - 1)
    assert s[i, j] == pytest.approx(z * TN / T, rel=1e-6)
    assert m[i, j] == (z > T)


def test_os_cfar_rank_and_multiplier_use_the_valid_count():
    from sarship.pipeline.detectors.os_cfar import (
        default_k,
        os_threshold_multiplier,
        rank_for,
    )

    kw, x, i, j, cells = _edge_setup("os_cfar")
    K = cells.size
    N = kw["background"] ** 2 - kw["guard"] ** 2
    k = rank_for(default_k(N), N, K)
    assert k == round(K * default_k(N) / N) and rank_for(default_k(N), N, N) == default_k(N)
    xk = np.sort(cells)[k - 1]
    alpha = os_threshold_multiplier(K, k, PFA, 4.0, 1)
    m, s = _detect("os_cfar", x, kw)
    assert m[i, j] == (float(x[i, j]) > alpha * xk)
    alpha_n = os_threshold_multiplier(N, default_k(N), PFA, 4.0, 1)
    if m[i, j]:
        assert s[i, j] == pytest.approx(float(x[i, j]) / xk * alpha_n / alpha, rel=1e-6)


def test_zero_is_data_unless_declared():
    """Exact zeros are samples unless ``nodata=0``: 8-bit chips have zeros in dark sea."""
    kw = SETTINGS["ca_cfar"][0]
    X = _scene("gamma", "zero_border")
    m_data, _ = _detect("ca_cfar", X, kw)
    m_abs, _ = _detect("ca_cfar", X, {**kw, "nodata": 0.0})
    a = _absent("zero_border")
    # zero cells in the ring lower the mean: more alarms next to the border than with nodata=0
    band = _near(a, D) & ~_ship_px()
    assert m_data[band].sum() > m_abs[band].sum()


def test_os_cfar_matches_bruteforce_with_scattered_absent_pixels():
    """Random NaN / inf (5 %) and negative values: every pixel against a brute force of the rule
    (K present ring cells, rank round(K k / N), exact multiplier for (K, rank))."""
    from sarship.pipeline.detectors.os_cfar import (
        OSParams,
        os_threshold_multiplier,
        prepare,
        rank_for,
    )

    rng = np.random.default_rng(3)
    p = OSParams(guard=5, background=11, target=1, looks=1.0, pfa=1e-2)
    prep = prepare(p)
    halo, rb, rg = 5, 5, 2
    block = rng.standard_exponential(size=(31 + 2 * halo, 30 + 2 * halo))
    block[rng.random(block.shape) < 0.05] = np.nan
    block[rng.random(block.shape) < 0.02] *= 50
    block[rng.random(block.shape) < 0.01] = -1.0
    block[3, 7] = np.inf
    mask, stat = detectors.get("os_cfar").detect(block, halo, (0, 0), p, prep)
    N, k0 = prep["n_ring"], prep["k"]
    n_tested = 0
    for i in range(31):
        for j in range(30):
            ci, cj = i + halo, j + halo
            xt = block[ci, cj]
            win = block[ci - rb : ci + rb + 1, cj - rb : cj + rb + 1].copy()
            win[rb - rg : rb + rg + 1, rb - rg : rb + rg + 1] = np.nan
            v = np.sort(win[np.isfinite(win)])
            K = v.size
            if not np.isfinite(xt) or K < (N + 1) // 2:
                assert not mask[i, j] and stat[i, j] == 0, (i, j)
                continue
            n_tested += 1
            k = rank_for(k0, N, K)
            alpha = os_threshold_multiplier(K, k, 1e-2, 1.0, 1)
            assert mask[i, j] == (xt > alpha * v[k - 1]), (i, j, K)
            assert (stat[i, j] > prep["alpha"]) == mask[i, j]
    assert n_tested > 500 and mask.sum() > 5
