"""Adaptive PWF-CFAR (``apwf``): maths against brute force and closed forms, exact
calibration, tiling invariance on a real Dask cluster, detection on simulated ships."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import zarr
from scipy import special

from sarship.pipeline import detectors
from sarship.pipeline.detectors import apwf
from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import open_scene
from sarship.pipeline.simulate import SimConfig, sea_covariance, simulate
from sarship.pipeline.tiling.inputs import polarimetric_source
from sarship.pipeline.tiling.windows import mirror_pad, padded_block
from sarship.workers.jobs import run_detection
from tests.conftest import write_scene


def _cn(rng, shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / math.sqrt(2.0)


def _clutter(rng, shape, sigma):
    """Rows of X ~ CN(0, sigma) on a (H, W, p) grid, complex64."""
    L = np.linalg.cholesky(sigma)
    return (_cn(rng, shape + (sigma.shape[0],)) @ L.T).astype(np.complex64)


def _detect_whole(x, prm):
    h = prm.background // 2
    return apwf.detect(mirror_pad(x, h), h, (-h, -h), prm, apwf.prepare(prm))


def test_closed_form_inverse_matches_numpy():
    rng = np.random.default_rng(0)
    for p in (2, 3):
        for _k in range(200):
            M = _cn(rng, (p, p + int(rng.integers(0, 6))))
            A = M @ M.conj().T * 10.0 ** rng.uniform(-3, 3)
            ref = np.linalg.inv(A)
            got = apwf.herm_inv(A)
            np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())


@pytest.mark.parametrize("estimator,p", [("ring", 3), ("window", 3), ("ring", 2), ("window", 2)])
def test_y_matches_brute_force(estimator, p):
    rng = np.random.default_rng(1)
    H, W = 23, 19
    x = _cn(rng, (H, W, p)).astype(np.complex64)
    x[5, 7] *= 20.0
    prm = apwf.APWFParams(pfa=1e-3, guard=3, background=9, estimator=estimator)
    mask, stat = _detect_whole(x, prm)
    h = 4
    P = mirror_pad(x, h).astype(np.complex128)
    y = np.empty((H, W))
    for i in range(H):
        for j in range(W):
            B = P[i : i + 9, j : j + 9].reshape(-1, p)
            S = B.T @ B.conj()  # sum of X X^H
            n = 81
            if estimator == "ring":
                G = P[i + 3 : i + 6, j + 3 : j + 6].reshape(-1, p)
                S = S - G.T @ G.conj()
                n = 72
            X = P[i + h, j + h]
            y[i, j] = np.real(X.conj() @ np.linalg.solve(S / n, X))
    np.testing.assert_allclose(stat, y, rtol=2e-6)
    T = apwf.prepare(prm)["thresholds"][str(p)]
    np.testing.assert_array_equal(mask, y > T)
    assert mask[5, 7]


def test_pwf_equals_eq_2_8_for_reflection_symmetric_sigma():
    """With Sigma known, X^H Sigma^-1 X is eq 2-8 (rho = E[hh vv*]/sqrt(...))."""
    rng = np.random.default_rng(2)
    s_hh, eps, gam, rho = 2.5, 0.05, 1.7, 0.6 * np.exp(0.4j)
    sg = math.sqrt(gam)
    sigma = s_hh * np.array([[1, 0, rho * sg], [0, eps, 0], [np.conj(rho) * sg, 0, gam]])
    X = _cn(rng, (500, 3)) * 3.0
    hh, hv, vv = X[:, 0], X[:, 1], X[:, 2]
    d = s_hh * (1 - abs(rho) ** 2)
    y28 = (
        abs(hh) ** 2 / d
        + abs(vv) ** 2 / (d * gam)
        + abs(hv) ** 2 / (s_hh * eps)
        - 2 * np.real(rho * np.conj(hh) * vv) / (d * sg)
    )
    Ai = apwf.herm_inv(sigma)
    y = np.real(np.einsum("ni,ij,nj->n", X.conj(), Ai, X))
    np.testing.assert_allclose(y, y28, rtol=1e-10)


def test_thresholds_exact_and_eq_2_10_is_the_large_n_limit():
    for p in (2, 3):
        for pfa in (1e-3, 1e-6, 1e-9):
            for n in (20, 96, 1000):
                T = apwf.threshold(pfa, p, n, "ring")
                assert apwf.pfa_exact(T, p, n, "ring") == pytest.approx(pfa, rel=1e-8)
                # beta-prime(p, N-p+1) of y/N, direct form: 1 - I_{T/(T+N)}(p, N-p+1)
                assert 1 - special.betainc(p, n - p + 1, T / (T + n)) == pytest.approx(pfa, rel=1e-5)
                Tw = apwf.threshold(pfa, p, n, "window")
                assert 1 - special.betainc(p, n - p, Tw / n) == pytest.approx(pfa, rel=1e-5)
            T10 = apwf.threshold_large_n(pfa, p)
            # eq 2-10 literally
            assert math.exp(-T10) * sum(T10**k / math.factorial(k) for k in range(p)) == pytest.approx(pfa, rel=1e-10)
            prev = None
            for n in (10**2, 10**3, 10**4, 10**5, 10**6):
                err = abs(apwf.threshold(pfa, p, n, "ring") / T10 - 1.0)
                errw = abs(apwf.threshold(pfa, p, n, "window") / T10 - 1.0)
                if prev is not None:
                    assert err < prev
                prev = err
            assert err < 1e-4 and errw < 1e-4


def test_calibration_exact_vs_large_n_threshold():
    """>= 4 Mpx of reflection-symmetric quad-pol speckle, N = 96 (guard 5, background 11)."""
    rng = np.random.default_rng(3)
    x = _clutter(rng, (2048, 2048), sea_covariance() * 3.0)
    pfa = 1e-3
    npx = x.shape[0] * x.shape[1]
    Mp = npx * pfa
    bound = 5 * math.sqrt(1.5 * Mp)
    for est, n in (("ring", 96), ("window", 121)):
        prm = apwf.APWFParams(pfa=pfa, guard=5, background=11, estimator=est)
        assert prm.n_samples() == n
        mask, stat = _detect_whole(x, prm)
        K = int(mask.sum())
        assert abs(K - Mp) <= bound, (est, K, Mp, bound)
        K10 = int((stat > apwf.threshold_large_n(pfa, 3)).sum())
        assert abs(K10 - Mp) > bound, (est, K10, Mp, bound)  # eq 2-10 is measurably off at N = 96


def test_params_validation():
    with pytest.raises(ValueError):
        apwf.APWFParams(target=3)
    with pytest.raises(ValueError):
        apwf.APWFParams(estimator="median")
    assert apwf.APWFParams(estimator="window", guard=1, background=31).n_samples() == 961
    assert detectors.get("apwf").describe()["input"] == "polarimetric"


def test_padded_block_trailing_axes():
    rng = np.random.default_rng(4)
    x = rng.random((23, 9)) + 1j * rng.random((23, 9))
    x3 = np.stack([x, 2 * x, 3 * x], axis=-1)
    for h in (0, 3, 15):
        P = mirror_pad(x3, h)
        for r0, r1, c0, c1 in [(0, 5, 0, 3), (20, 23, 6, 9), (7, 8, 4, 5), (0, 23, 0, 9)]:
            blk = padded_block(lambda a, b, c, d: x3[a:b, c:d], x.shape, r0, r1, c0, c1, h)
            np.testing.assert_array_equal(blk, P[r0 : r1 + 2 * h, c0 : c1 + 2 * h])
            np.testing.assert_array_equal(blk[..., 1], mirror_pad(2 * x, h)[r0 : r1 + 2 * h, c0 : c1 + 2 * h])
    x1 = x3[:1]  # one-row scene: the gather path
    blk = padded_block(lambda a, b, c, d: x1[a:b, c:d], x1.shape[:2], 0, 1, 2, 5, 4)
    np.testing.assert_array_equal(blk, mirror_pad(x1, 4)[0:9, 2:13])


def test_polarimetric_source(tmp_path):
    z = np.zeros((20, 20), np.complex64)
    s = write_scene(tmp_path / "q.zarr", {"hh": z, "hv": z, "vv": z}, tile=16)
    assert polarimetric_source(open_scene(s)) == (("hh", "hv", "vv"), "stack")
    s = write_scene(tmp_path / "d.zarr", {"vh": z, "vv": z}, tile=16)
    assert polarimetric_source(open_scene(s)) == (("vh", "vv"), "stack")
    s = write_scene(tmp_path / "one.zarr", {"hh": z, "intensity": z.real}, tile=16)
    with pytest.raises(InputError, match=r"hh.*complex64.*intensity"):
        polarimetric_source(open_scene(s))
    with pytest.raises(InputError, match="complex"):
        run_detection(s, "apwf", {}, out_dir=tmp_path / "o", client=object(), progress=False)


def _ship_scene(rng, H, W, p):
    sig = sea_covariance()[:p, :p] if p == 3 else np.array([[0.05, 0.0], [0.0, 1.5]])
    x = _clutter(rng, (H, W), sig)
    for _ in range(10):
        r, c = int(rng.integers(0, H - 4)), int(rng.integers(0, W - 9))
        x[r : r + 3, c : c + 8] += (8.0 * _cn(rng, (3, 8, p))).astype(np.complex64)
    x[0:2, 0:5] += 10.0  # on the corner, across the mirrored border
    return x


@pytest.mark.parametrize("p,estimator", [(3, "ring"), (3, "window"), (2, "ring")])
def test_tiled_equals_untiled(tmp_path, client, p, estimator):
    rng = np.random.default_rng(5 + p)
    H, W = 151, 133
    x = _ship_scene(rng, H, W, p)
    names = ("hh", "hv", "vv") if p == 3 else ("vh", "vv")
    arrays = {n: np.ascontiguousarray(x[..., k]) for k, n in enumerate(names)}
    scene = write_scene(tmp_path / "s.zarr", arrays, tile=32, kind="quadpol" if p == 3 else "slc")
    settings = {
        "pfa": "1e-4",
        "guard": "9",
        "background": "41",
        "min_area_px": "1",
        "merge_px": "2",
        "estimator": estimator,
    }
    out = {}
    for tile in (4096, 32, 27):
        o = tmp_path / f"o{tile}"
        run = run_detection(scene, "apwf", settings, out_dir=o, tile=tile, client=client, progress=False)
        assert run["channel"] == list(names)
        fc = json.loads((o / "detections.geojson").read_text())
        mask = zarr.open_array(str(o / "mask.zarr" / "detected"), mode="r")[:]
        out[tile] = (fc["features"], mask)
    prm = apwf.APWFParams(**{k: v for k, v in settings.items()})
    ref, stat = _detect_whole(x, prm)
    assert ref.sum() > 30
    for tile, (feats, mask) in out.items():
        np.testing.assert_array_equal(mask.astype(bool), ref, err_msg=f"tile {tile}")
        assert feats == out[4096][0], f"tile {tile}"
    # detections' values are the span of the stacked channels
    span = (np.abs(x.astype(np.complex128)) ** 2).sum(-1)
    f = max(out[4096][0], key=lambda f: f["properties"]["peak"])
    r0, c0, r1, c1 = f["properties"]["bbox_px"]
    inside = np.where(ref[r0:r1, c0:c1], span[r0:r1, c0:c1], 0)
    assert f["properties"]["peak"] == pytest.approx(inside.max(), rel=1e-5)


def test_detects_simulated_quadpol_ships(tmp_path, client):
    """SCR 10 dB (span), single-look Rayleigh quad-pol sea, 2048 x 2048, 25 ships.

    Parameters: pfa 1e-6, ring estimator, guard 41, background 61 (N = 2040),
    min_area_px 2, merge_px 5 (the detector's defaults).
    """
    cfg = SimConfig(kind="quadpol", shape=(2048, 2048), ships=25, seed=11, clutter="rayleigh", scr_db=10.0)
    scene = tmp_path / "q.zarr"
    truth = tmp_path / "q.truth.geojson"
    simulate(scene, cfg, tile=1024, truth_path=truth)
    from sarship.pipeline.products.scoring import evaluate

    run_detection(scene, "apwf", {"pfa": "1e-6"}, out_dir=tmp_path / "o", client=client, progress=False)
    s = evaluate(tmp_path / "o" / "detections.geojson", truth)
    assert s["n_truth"] == 25
    assert s["fom"] >= 0.9, s
