"""Stripe-noise removal (pipeline/image/destripe.py, workers/enhance.py, ``sarship enhance``).

Otsu against a brute-force reference, Hough on planted lines, stripes of simulated K-sea
scenes removed (stripe-to-background ratio before/after against the same scene without
stripes), nothing changed on scenes without stripes, the scene pass exact for any tiling
and the tiled filter bit-identical to the whole scene, the CLI end to end.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.image import destripe as D
from sarship.pipeline.simulate import SimConfig, simulate, simulate_array
from sarship.pipeline.simulate.artefacts import _stripes_gain
from sarship.pipeline.simulate.land import _land_mask, _land_model


def _otsu_brute(v: np.ndarray, bins: int = 256) -> float:
    """Otsu by definition: for every cut between histogram bins, the between-class variance
    computed from the two classes' weights and means (no cumulative sums); the best cut."""
    lo, hi = v.min(), v.max()
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    best, arg = -1.0, None
    for k in range(bins - 1):
        w0, w1 = hist[: k + 1].sum(), hist[k + 1 :].sum()
        if w0 == 0 or w1 == 0:
            continue
        m0 = (hist[: k + 1] * centres[: k + 1]).sum() / w0
        m1 = (hist[k + 1 :] * centres[k + 1 :]).sum() / w1
        sb = w0 * w1 * (m0 - m1) ** 2
        if sb > best:
            best, arg = sb, edges[k + 1]
    return float(arg)


def test_otsu_matches_brute_force_and_splits_two_modes():
    rng = np.random.default_rng(1)
    for n0, n1, gap in ((5000, 1000, 6.0), (300, 3000, 3.0), (2000, 2000, 8.0)):
        v = np.concatenate([rng.normal(0, 1, n0), rng.normal(gap, 1, n1)])
        t = D.otsu_threshold(v)
        assert t == pytest.approx(_otsu_brute(v), abs=1e-12)
        if gap >= 6:  # well separated: the threshold lies between the modes, near the valley
            assert 1.5 < t < gap - 1.5
    # a known two-level case: half at 0, half at 10 -> any cut between them; Otsu's is the first
    v = np.r_[np.zeros(100), np.full(100, 10.0)]
    t = D.otsu_threshold(v)
    assert 0.0 < t <= 10.0 and (v > t).sum() == 100
    assert D.otsu_threshold(np.full(10, 3.0)) == 3.0
    with pytest.raises(ValueError):
        D.otsu_threshold(np.array([np.nan]))


def test_hough_finds_planted_lines_and_not_noise():
    rng = np.random.default_rng(2)
    G, K = 8, 200
    b = rng.random((G, K)) < 0.03
    b[:, 57] = True  # a vertical line (constant bin)
    g = np.arange(G)
    k_slant = np.rint(120 + g * math.tan(math.radians(15))).astype(int)
    b[g, k_slant] = True  # a slanted one (drifting bin)
    lines = D.hough_lines(b, theta_max_deg=20, min_votes=7)
    found = {(round(ln["rho"]), round(ln["theta_deg"])) for ln in lines}
    assert (57, 0) in found
    # the slanted line: theta steps of 4 degrees, so its bins within one of the planted ones
    slant = [ln for ln in lines if np.abs(D.line_bins(ln, G) - k_slant).max() <= 1]
    assert slant and all(-16 <= ln["theta_deg"] <= -12 for ln in slant)
    # every reported line crosses >= 7 rows on set pixels
    for ln in lines:
        kb = D.line_bins(ln, G)
        ok = (kb >= 0) & (kb < K)
        assert b[g[ok], kb[ok]].sum() >= 7
    # pure sparse noise: no line of 7 votes in 8 rows
    noise = rng.random((G, K)) < 0.03
    assert D.hough_lines(noise, 20, 7) == []


def _scene(seed: int, land: bool, stripes: bool, shape=(2048, 1024)):
    cfg = SimConfig(shape=shape, ships=8, seed=seed, clutter="k", looks=1, land=land, sidelobes=True, stripes=stripes)
    return cfg, simulate_array(cfg)[0]["intensity"]


def _destripe(I, p=None):
    p = D.DestripeParams() if p is None else p
    est = D.estimate(*D.assemble([D.segment_sums(I, 0, 0, p)], I.shape, p), p)
    return est, D.apply_gain(I, est.profile, p)


@pytest.fixture(scope="module")
def striped():
    out = {}
    for seed, land in ((1, False), (2, True)):
        cfg, I = _scene(seed, land, True)
        _, ref = _scene(seed, land, False)
        sea = ~_land_mask(cfg, _land_model(cfg), 0, cfg.shape[0], 0, cfg.shape[1]) if land else None
        out[(seed, land)] = (cfg, I, ref, sea)
    return out


# measured (docs/algorithms/destripe.md): seed 1 (sea) 11.6 -> 4.6 dB, seed 2 (land on top)
# 8.6 -> 3.3 dB on the sea (K sea, 2048 x 1024, stripe gain 1.09 / 0.75 dB rms)
@pytest.mark.parametrize("seed, land", [(1, False), (2, True)])
def test_stripes_of_simulated_k_sea_removed(striped, seed, land):
    cfg, I, ref, sea = striped[(seed, land)]
    est, out = _destripe(I)
    before = D.stripe_to_background_db(I, reference=ref, valid=sea)
    after = D.stripe_to_background_db(out, reference=ref, valid=sea)
    assert before > 7.0
    assert after < before - 4.0
    # the estimated profile follows the true gain: residual rms well under the stripes' rms
    g = np.log(_stripes_gain(cfg).astype(np.float64))
    g -= g.mean()
    pr = est.profile - est.profile.mean()
    cols = sea.mean(axis=0) > 0.5 if sea is not None else np.ones(g.size, bool)
    assert np.std((g - pr)[cols]) < 0.6 * np.std(g[cols])
    rec = est.record()
    assert rec["stop_bins"] and rec["lines"] and all(b >= 1 for b in rec["stop_bins"])
    json.dumps(rec)


@pytest.mark.parametrize("seed, land", [(1, False), (2, True), (3, False)])
def test_no_stripes_nothing_changes(seed, land):
    _, I = _scene(seed, land, False)
    est, out = _destripe(I)
    assert not est.stop.any() and est.lines == []
    assert np.array_equal(out, I)


def test_periodic_stripes_along_range_fft_along_azimuth():
    """The paper's case: stripes repeating along azimuth (constant along range): peaks at
    mid frequencies of the azimuth spectrum, found and stopped."""
    I = simulate_array(SimConfig(shape=(1024, 1024), ships=5, seed=4, clutter="k"))[0]["intensity"]
    r = np.arange(1024)
    mod = 10 ** ((1.0 * np.sin(2 * np.pi * r / 64) + 0.5 * np.sin(2 * np.pi * r / 23.0 + 1)) / 10)
    J = (I * mod[:, None]).astype(np.float32)
    p = D.DestripeParams(stripes_along="range")
    est, out = _destripe(J, p)
    stop = set(np.flatnonzero(est.stop))
    assert {16, 44} <= stop and len(stop) < 20  # 1024/64 and 1024/23 = 44.5
    before = D.stripe_to_background_db(J, "range", reference=I)
    after = D.stripe_to_background_db(out, "range", reference=I)
    assert before > 6.0 and after < 1.0  # measured 6.97 -> 0.2 dB
    # along azimuth (the wrong axis) finds nothing to stop
    est_wrong, _ = _destripe(J)
    assert not est_wrong.stop.any()


def test_scene_pass_exact_for_any_tiling_and_filter_bit_identical():
    cfg, I = _scene(1, True, True, shape=(700, 530))
    I = I.copy()
    I[:40, :] = np.nan  # absent border
    I[300:310, 100:200] = 0.0  # declared-zero block
    p = D.DestripeParams(segment=32)
    whole = D.assemble([D.segment_sums(I, 0, 0, p)], I.shape, p)
    est = D.estimate(*whole, p)
    for tile in (97, 128, 333):
        parts, outs = [], np.empty_like(I)
        for r0 in range(0, I.shape[0], tile):
            for c0 in range(0, I.shape[1], tile):
                blk = I[r0 : r0 + tile, c0 : c0 + tile]
                parts.append(D.segment_sums(blk, r0, c0, p))
                outs[r0 : r0 + tile, c0 : c0 + tile] = D.apply_gain(blk, est.profile[c0 : c0 + blk.shape[1]], p)
        tiled = D.assemble(parts, I.shape, p)
        assert np.array_equal(tiled[0], whole[0]) and np.array_equal(tiled[1], whole[1])
        assert np.array_equal(outs, D.apply_gain(I, est.profile, p), equal_nan=True)
    out = D.apply_gain(I, est.profile, p)
    assert np.isnan(out[:40]).all() and (out[300:310, 100:200] == 0).all()
    assert out.dtype == np.float32


def test_gain_on_complex_and_stacked_channels():
    rng = np.random.default_rng(0)
    z = (rng.normal(size=(6, 5)) + 1j * rng.normal(size=(6, 5))).astype(np.complex64)
    s = np.linspace(-0.3, 0.3, 5)
    p = D.DestripeParams()
    out = D.apply_gain(z, s, p)
    assert out.dtype == np.complex64
    np.testing.assert_allclose(np.abs(out) ** 2, np.abs(z) ** 2 * np.exp(-s)[None, :], rtol=1e-5)
    cov = D.apply_gain(z, s, p, complex_amplitude=False)  # covariance elements: powers
    np.testing.assert_allclose(cov, z * np.exp(-s)[None, :], rtol=1e-6)
    st = np.stack([z, 2 * z], axis=2)
    np.testing.assert_allclose(D.apply_gain(st, s, p)[..., 1], 2 * out, rtol=1e-6)
    np.testing.assert_allclose(D.log_power(st), np.log(5 * np.abs(z) ** 2), rtol=1e-5)


@pytest.mark.parametrize(
    "field, value",
    [
        ("stripes_along", "diagonal"),
        ("segment", 1),
        ("segment", 2.5),
        ("groups", 0),
        ("z_min", 0.5),
        ("z_min", float("nan")),
        ("min_votes", 0.0),
        ("min_votes", 1.5),
        ("theta_max_deg", 80.0),
        ("notch_halfwidth", -1),
        ("k_min", 0),
        ("bright_db", 0.0),
        ("segment", True),
    ],
)
def test_parameters_validated(field, value):
    with pytest.raises(InputError, match=field):
        D.DestripeParams(**{field: value})


# --------------------------------------------------------------------------- Dask and CLI


def test_enhance_on_the_cluster_matches_the_whole_scene(tmp_path, client):
    from sarship.pipeline.scene import open_scene
    from sarship.workers.enhance import run_enhance

    cfg = SimConfig(shape=(640, 520), ships=4, seed=1, clutter="k", stripes=True, land=True)
    scene = simulate(tmp_path / "s.zarr", cfg, tile=128)
    rec = run_enhance(scene, tmp_path / "o.zarr", client=client, progress=False)
    import zarr

    src = np.asarray(zarr.open_array(str(scene / "intensity"), mode="r")[:])
    got = np.asarray(zarr.open_array(str(tmp_path / "o.zarr" / "intensity"), mode="r")[:])
    est, want = _destripe(src)
    assert np.array_equal(got, want)
    assert rec["destripe"]["stop_bins"] == [int(b) for b in np.flatnonzero(est.stop)]
    o = open_scene(tmp_path / "o.zarr")
    assert o.tile == 128 and o.variables == {"intensity": "float32"}
    assert o.attrs["enhance"][-1]["destripe"]["stop_bins"] == rec["destripe"]["stop_bins"]
    assert o.attrs["simulation"] == open_scene(scene).attrs["simulation"]


def _cli(*args, timeout=180):
    return subprocess.run(
        [sys.executable, "-m", "sarship", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def test_enhance_cli_end_to_end(tmp_path, client, capsys):
    from sarship.cli import main

    sched = client.scheduler.address
    cfg = SimConfig(kind="slc", shape=(256, 256), ships=2, seed=3, stripes=True)
    scene = simulate(tmp_path / "s.zarr", cfg, tile=128)
    # as a subprocess: the real program, its exit codes and stderr
    r = _cli("enhance", scene, "--out", tmp_path / "o.zarr", "--destripe", "--scheduler", sched)
    assert r.returncode == 0, r.stderr
    assert "enhance: destripe" in r.stderr and "scene:" in r.stdout
    import zarr

    a = np.asarray(zarr.open_array(str(scene / "hh"), mode="r")[:])
    b = np.asarray(zarr.open_array(str(tmp_path / "o.zarr" / "hh"), mode="r")[:])
    assert b.dtype == np.complex64 and np.allclose(np.angle(a[a != 0]), np.angle(b[a != 0]), atol=1e-5)
    # an existing OUT without --overwrite: exit 2, one line, the store untouched
    before = (tmp_path / "o.zarr" / "zarr.json").read_bytes()
    r = _cli("enhance", scene, "--out", tmp_path / "o.zarr", "--destripe", "--scheduler", sched)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--overwrite" in r.stderr
    assert (tmp_path / "o.zarr" / "zarr.json").read_bytes() == before
    # the same program in this process (faster): --overwrite replaces it
    capsys.readouterr()
    assert (
        main(
            [
                "enhance",
                str(scene),
                "--out",
                str(tmp_path / "o.zarr"),
                "--destripe",
                "--overwrite",
                "--scheduler",
                sched,
            ]
        )
        == 0
    )
    assert np.array_equal(np.asarray(zarr.open_array(str(tmp_path / "o.zarr" / "hh"), mode="r")[:]), b)
    # never inside the input, never without --destripe, a missing scene: exit 2, one line each
    for args, word in (
        ([str(scene), "--out", str(scene / "x.zarr"), "--destripe", "--overwrite"], "input"),
        ([str(scene), "--out", str(tmp_path / "p.zarr")], "--destripe"),
        ([str(tmp_path / "missing.zarr"), "--out", str(tmp_path / "q.zarr"), "--destripe"], "missing"),
    ):
        capsys.readouterr()
        assert main(["enhance", *args, "--scheduler", sched]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and word in err and err.startswith("sarship enhance: error:")
    # nothing left behind: no partial store, no stray output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.zarr", "s.zarr", "s.zarr.truth.geojson"]
