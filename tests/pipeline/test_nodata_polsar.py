"""Absent pixels (NaN, or no signal: all channels 0) in the polarimetric detectors.

The scene store marks absent pixels as NaN (a declared no-data value becomes NaN or 0); SNAP's
known bug is that NaN backgrounds become targets. For ``apwf``, ``pcdm`` and ``vb_polsar``,
each with a NaN border, a zero border and a NaN wedge cutting into the sea:

- no absent pixel is ever detected, and the detections in the band next to the absent region
  (where the windows reach it) are within the binomial expectation of the PFA over the valid
  pixels of that band;
- a ship a few pixels from the absent region is found;
- on the valid pixels whose windows do not reach the absent region the result equals that of
  the same scene without it (with the scene-wide values of the complete scene for the two-pass
  detectors, whose threshold is fitted to the pixels present);
- tiled == whole scene with absent pixels (tiles cut from the mirror-extended scene), and an
  all-absent tile is harmless in the scene pass.

Rules (module docstrings): ``apwf`` counts the valid ring cells K and uses the exact T(K),
not testing pixels with K < max(N/2, p+1); ``pcdm`` tests a pixel only when its whole
``(looks_window + 2)^2`` neighbourhood is present; ``vb_polsar`` (halo 0) leaves absent
pixels out of its samples.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from sarship.pipeline import detectors
from sarship.pipeline.simulate import sea_covariance
from sarship.pipeline.tiling.windows import mirror_pad, padded_block

H = W = 224
B = 32  # border width
SHIPS = [(60, 60), (150, 90), (100, 160), (170, 150)]
EDGE_SHIP = (112, B + 5)  # 5 px inside the left border
WEDGE_SHIP = (62, 178)  # 6-10 px above the wedge's upper edge
PFA = 1e-3
#: detector -> (parameters, the band (px, Chebyshev) next to the absent region where its windows reach it,
#: factor on the PFA allowed for its approximate scene-wide rules)
SETTINGS = {
    "apwf": ({"pfa": PFA, "guard": 5, "background": 11, "min_area_px": 1}, 5, 1.0),
    "pcdm": ({"pfa": PFA, "min_area_px": 1}, 2, 2.0),
    "vb_polsar": ({"pfa": PFA, "sample_stride": 4, "calibration_stride": 2, "min_area_px": 1}, 1, 2.0),
}


def _cn(rng, shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / math.sqrt(2.0)


def _absent(case: str) -> np.ndarray:
    r, c = np.mgrid[:H, :W]
    if case in ("nan_border", "zero_border"):
        a = np.ones((H, W), bool)
        a[B : H - B, B : W - B] = False
        return a
    # a NaN wedge from the right edge: apex at (112, 128), base rows 40 .. 184 on the last column
    return (c >= 128) & (np.abs(r - 112) <= (c - 128) * 72.0 / 95.0)


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(7)
    L = np.linalg.cholesky(sea_covariance())
    x = (_cn(rng, (H, W, 3)) @ L.T).astype(np.complex64)
    for r, c in SHIPS + [EDGE_SHIP, WEDGE_SHIP]:
        x[r : r + 3, c : c + 6] += (8.0 * _cn(rng, (3, 6, 3))).astype(np.complex64)
    out = {"clean": (x, np.zeros((H, W), bool))}
    for case in ("nan_border", "zero_border", "nan_wedge"):
        a = _absent(case)
        y = x.copy()
        y[a] = np.nan if case.startswith("nan") else 0
        out[case] = (y, a)
    return out


def _prep(name, X, kw):
    spec = detectors.get(name)
    p = spec.params(**kw)
    prep = spec.prepare(p)
    h = spec.halo(p)
    blk = mirror_pad(X, h) if h else X
    if spec.scene_pass is not None:
        prep = {**prep, **spec.reduce([spec.scene_pass(blk, h, (-h, -h), p, prep)], p, prep)}
    return spec, p, prep, h, blk


def _detect(name, X, kw, prep=None):
    spec, p, own, h, blk = _prep(name, X, kw)
    m, s = spec.detect(blk, h, (-h, -h), p, prep if prep is not None else own)
    return m, s, own


@pytest.fixture(scope="module")
def results(scenes):
    out = {}
    for name, (kw, _, _) in SETTINGS.items():
        ref = _detect(name, scenes["clean"][0], kw)
        out[name, "clean"] = ref
        for case in ("nan_border", "zero_border", "nan_wedge"):
            X, _ = scenes[case]
            out[name, case] = _detect(name, X, kw)
            out[name, case, "ref_prep"] = _detect(name, X, kw, prep=ref[2])
    return out


def _near(a: np.ndarray, d: int) -> np.ndarray:
    """Valid pixels within ``d`` px (Chebyshev) of the absent region."""
    return ndimage.binary_dilation(a, np.ones((2 * d + 1, 2 * d + 1), bool)) & ~a


CASES = ["nan_border", "zero_border", "nan_wedge"]


def _ship_px(pad=2):
    m = np.zeros((H, W), bool)
    for r, c in SHIPS + [EDGE_SHIP, WEDGE_SHIP]:
        m[max(r - pad, 0) : r + 3 + pad, max(c - pad, 0) : c + 6 + pad] = True
    return m


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_absent_never_detected_and_band_within_pfa(results, scenes, name, case):
    _, a = scenes[case]
    m, s, _ = results[name, case]
    assert m.dtype == bool and m.shape == a.shape
    assert not m[a].any(), f"{int(m[a].sum())} absent pixels detected"
    kw, d, factor = SETTINGS[name]
    band = _near(a, d) & ~_ship_px()
    for zone, where in (("band", band), ("touching", _near(a, 1) & ~_ship_px())):
        n = int(where.sum())
        e = factor * kw["pfa"] * n
        k = int(m[where].sum())
        # binomial expectation of the PFA over the zone's valid pixels (inflation 1.5 for shared cells)
        assert k <= e + 5.0 * math.sqrt(1.5 * e) + 2, (zone, k, n, e)
    # and overall the valid pixels alarm at the PFA's rate (not a border of alarms)
    far = int((m & ~a & ~_ship_px()).sum())
    e = factor * kw["pfa"] * int((~a).sum())
    assert far <= e + 5.0 * math.sqrt(1.5 * e) + 2, (far, e)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_ship_near_absent_region_is_found(results, name, case):
    m, _, _ = results[name, case]
    r, c = WEDGE_SHIP if case == "nan_wedge" else EDGE_SHIP
    assert m[r : r + 3, c : c + 6].any()
    for r, c in SHIPS:  # ships away from the absent region
        if not _absent(case)[r : r + 3, c : c + 6].any():
            assert m[r : r + 3, c : c + 6].any(), (r, c)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(SETTINGS))
def test_valid_part_equals_scene_without_absent_pixels(results, scenes, name, case):
    """Where the windows do not reach the absent region: the same mask and statistic as the
    complete scene (two-pass detectors: given the complete scene's scene-wide values)."""
    _, a = scenes[case]
    m0, s0, prep0 = results[name, "clean"]
    m, s, _ = results[name, case, "ref_prep"]
    d = SETTINGS[name][1]
    far = ~a & ~_near(a, d)
    np.testing.assert_array_equal(m[far], m0[far])
    np.testing.assert_array_equal(s[far], s0[far])


@pytest.mark.parametrize("case", CASES)
def test_scene_wide_values_use_the_pixels_present(results, case):
    """pcdm's T_SPAN and vb_polsar's mixture come from the pixels present: the same sea gives
    nearly the same values with or without the absent region (before the fix, NaN made them NaN
    and a zero border put a cluster at the origin into the mixture)."""
    t0 = results["pcdm", "clean"][2]
    t = results["pcdm", case][2]
    assert math.isfinite(t["t_span"]) and t["t_span"] == pytest.approx(t0["t_span"], rel=0.1)
    v0 = results["vb_polsar", "clean"][2]
    v = results["vb_polsar", case][2]
    assert math.isfinite(v["t_init"]) and v["t_init"] == pytest.approx(v0["t_init"], rel=0.1)
    assert math.isfinite(v["threshold"])  # (its tail fit on ~10^4 samples varies by tens of % with the sample)
    st = SETTINGS["vb_polsar"][0]["sample_stride"]
    assert v["n_sample"] == int((~_absent(case))[::st, ::st].sum())  # the absent pixels are not sampled


@pytest.mark.parametrize("name", list(SETTINGS))
def test_tiled_equals_whole_with_absent_pixels(scenes, name):
    """Tiles cut from the mirror-extended scene (smaller than the windows, not dividing the
    scene, one of them all absent) give the whole-scene mask bit for bit."""
    X, a = scenes["nan_border"]
    kw = SETTINGS[name][0]
    spec, p, prep, h, blk = _prep(name, X, kw)
    tiles = [(r0, min(r0 + 29, H), c0, min(c0 + 29, W)) for r0 in range(0, H, 29) for c0 in range(0, W, 29)]
    assert any(a[r0:r1, c0:c1].all() for r0, r1, c0, c1 in tiles)
    blocks = [
        (padded_block(lambda ra, rb, ca, cb: X[ra:rb, ca:cb], (H, W), r0, r1, c0, c1, h), (r0 - h, c0 - h))
        for r0, r1, c0, c1 in tiles
    ]
    if spec.scene_pass is not None:
        base = spec.prepare(p)
        parts = [spec.scene_pass(b, h, o, p, base) for b, o in blocks]
        red = spec.reduce(parts, p, base)
        whole = spec.reduce([spec.scene_pass(blk, h, (-h, -h), p, base)], p, base)
        assert red == whole
        prep = {**base, **red}
    ref, _ = spec.detect(blk, h, (-h, -h), p, prep)
    got = np.zeros((H, W), bool)
    for (b, o), (r0, r1, c0, c1) in zip(blocks, tiles):
        got[r0:r1, c0:c1] = spec.detect(b, h, o, p, prep)[0]
    np.testing.assert_array_equal(got, ref)
    assert ref.sum() > 5


def test_apwf_threshold_uses_the_valid_count():
    """A pixel next to a straight edge: its ring has K < N valid cells; its y uses K and is
    compared with T(K); y / N-scaled stat keeps stat > T(N) where detected; a corner pixel
    (K < N/2) is not tested."""
    from sarship.pipeline.detectors import apwf

    rng = np.random.default_rng(3)
    L = np.linalg.cholesky(sea_covariance())
    x = (_cn(rng, (40, 40, 3)) @ L.T).astype(np.complex64)
    x[:, :10] = np.nan
    x[:10, :] = np.nan
    prm = apwf.APWFParams(pfa=1e-3, guard=5, background=11)
    prep = apwf.prepare(prm)
    S, K, ok = apwf.window_sums_counts(mirror_pad(x, 5), 5, (-5, -5), prm)
    N = prep["n_samples"]
    assert K[20, 10] == N - (3 * 11 + 2 * 6)  # edge pixel: 3 ring columns and 2 half-columns lost
    assert K[20, 20] == N and K[10, 10] < N / 2  # interior; the inner corner
    # brute force of y at the edge pixel over its valid ring cells
    i, j = 20, 10
    cells = [
        (a, b)
        for a in range(i - 5, i + 6)
        for b in range(j - 5, j + 6)
        if (abs(a - i) > 2 or abs(b - j) > 2) and not np.isnan(x[a, b]).any()
    ]
    assert len(cells) == K[i, j]
    Xc = np.array([x[a, b] for a, b in cells]).astype(np.complex128)
    sig = Xc.T @ Xc.conj() / len(cells)
    v = x[i, j].astype(np.complex128)
    y = float(np.real(v.conj() @ np.linalg.solve(sig, v)))
    T = apwf.count_thresholds([K[i, j]], 1e-3, 3)[0]
    assert T > prep["thresholds"]["3"]
    x2 = x.copy()
    x2[i, j] *= math.sqrt(1.02 * T / y)  # just above its own threshold T(K)
    m, s = apwf.detect(mirror_pad(x2, 5), 5, (-5, -5), prm, prep)
    assert m[i, j] and s[i, j] > prep["thresholds"]["3"]
    x2[i, j] = x[i, j] * np.float32(math.sqrt(0.98 * T / y))  # just below: not detected
    m, s = apwf.detect(mirror_pad(x2, 5), 5, (-5, -5), prm, prep)
    assert not m[i, j]
    x2[10, 10] = 1e3 * x[20, 20]  # the inner corner: not tested
    m, s = apwf.detect(mirror_pad(x2, 5), 5, (-5, -5), prm, prep)
    assert not m[10, 10] and s[10, 10] == 0


def test_pcdm_scene_pass_all_absent():
    spec = detectors.get("pcdm")
    p = spec.params()
    x = np.full((20, 20, 3), np.nan, np.complex64)
    part = spec.scene_pass(mirror_pad(x, 2), 2, (-2, -2), p, {})
    assert part["n"] == 0 and part["min"] is None
    red = spec.reduce([part], p, {})
    m, s = spec.detect(mirror_pad(x, 2), 2, (-2, -2), p, {**spec.prepare(p), **red})
    assert not m.any() and not s.any()


@pytest.mark.parametrize("lw", [1, 3])
@pytest.mark.parametrize("case", CASES)
def test_pcdm_untested_band_is_its_halo(scenes, case, lw):
    """SPAN_P and PSH are NaN (not tested) exactly on the absent pixels and the valid pixels
    within 1 + looks_window // 2 px (Chebyshev) of them, finite elsewhere; a zero border
    (no signal) is treated as NaN, bit for bit."""
    from sarship.pipeline.detectors import pcdm

    X, a = scenes[case]
    prm = pcdm.PCDMParams(looks_window=lw)
    h = pcdm.halo(prm)
    span, psh = pcdm.span_psh(mirror_pad(X, h), h, (-h, -h), prm)
    untested = a | _near(a, h)
    np.testing.assert_array_equal(np.isnan(span), untested)
    np.testing.assert_array_equal(np.isnan(psh), untested)
    if case == "zero_border":
        s2, _ = pcdm.span_psh(mirror_pad(scenes["nan_border"][0], h), h, (-h, -h), prm)
        np.testing.assert_array_equal(span, s2)


def test_present_rule():
    """present(): finite data and some signal; the Numba pass equals the array expression
    (the one the GPU evaluates), for channels and covariances, views included."""
    from sarship.pipeline.tiling.polsar_absent import present

    rng = np.random.default_rng(1)
    x = _cn(rng, (40, 50, 3)).astype(np.complex64)
    x[:3] = np.nan
    x[3:5] = 0
    x[6, 3, 1] = np.inf
    x[7, 4, 0] = complex(0, np.nan)
    x[8, 5] = 0
    x[8, 5, 2] = 1e-30j  # tiny but not zero: present
    with np.errstate(invalid="ignore"):
        C = x[..., :, None] * x[..., None, :].conj()
    C[9, 6, 0, 1] = np.nan
    for a in (x, x[2:30, 3:41], C, C[1:20, 2:33]):
        if a.ndim == 3:
            ref = np.isfinite(a).all(axis=2) & (a != 0).any(axis=2)
        else:
            ref = np.isfinite(a).all(axis=(2, 3)) & (np.diagonal(a, axis1=2, axis2=3).real != 0).any(axis=2)
        np.testing.assert_array_equal(present(a), ref)
    ok = present(x)
    assert not ok[:5].any() and not ok[6, 3] and not ok[7, 4] and ok[8, 5] and ok[10:].all()
    assert not present(C)[9, 6]


def test_apwf_covariance_input_with_an_absent_border_runs_on_cpu():
    """Covariance (C3) input with a NaN border: pixels with too few valid ring cells have a
    singular (all-zero) ring covariance; the whole batch used to fail with LinAlgError
    ('Singular matrix', found on the GPU machine's CPU reference). Absent pixels are never
    detected, and the valid part is tested."""
    from tests.pipeline.test_nodata_gpu import _absent, _quadpol

    halo = 15
    X, a = _absent(_quadpol((2 * halo + 220, 2 * halo + 210), 3, seed=5), "nan_border", halo)
    C = (X[..., :, None] * X[..., None, :].conj()).astype(np.complex64)
    spec = detectors.get("apwf")
    p = spec.params(pfa=1e-3, guard=9, background=31)
    m, s = spec.detect(C, halo, (-halo, -halo), p, spec.prepare(p))
    assert not m[a[halo:-halo, halo:-halo]].any()
    assert np.isfinite(s).all() and (s[~a[halo:-halo, halo:-halo]] > 0).any()
