"""The SAR scene simulator: determinism, tiling independence, clutter statistics, truth, store.

Statistical tolerances (all 5 standard errors, so a correct simulator fails with
probability well below 1e-5 per check; every check is deterministic for its seed anyway):

* mean of n i.i.d. L-look gamma intensities: relative SE = 1/sqrt(n L).
* ENL = m^2/s^2: by the delta method on (m, s^2) with the gamma moments
  (var 1/L, third central moment 2/L^2, excess kurtosis 6/L) the relative variance of
  the estimate is (4/L + 2 + 6/L - 8/L)/n = (2 + 2/L)/n.
* exceedance fraction of a quantile at probability p: SE = sqrt(p (1 - p) / n).
* lag-1 correlation of i.i.d. samples: SE = 1/sqrt(n).
* sample covariance of n circular complex Gaussian vectors: SE of element (i, j) is
  sqrt(Sigma_ii Sigma_jj / n); the PWF statistic X^H Sigma^-1 X is Gamma(3, 1): SE of
  its mean sqrt(3/n).
* a correlated texture has fewer independent samples: for a Gaussian field with 1/e
  correlation length l the effective count is about n / (1.25 l)^2 (the integral of rho^2
  over the plane); the texture checks use that count.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from scipy import special, stats

from sarship.pipeline import simulate as sim
from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate import (
    SimConfig,
    sea_covariance,
    ship_catalogue,
    simulate,
    simulate_array,
    simulate_tile,
    truth_collection,
    validate,
)

ALL_ON = dict(land=True, sidelobes=True, ambiguities=True, stripes=True, rfi=True)


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return (
        a.shape == b.shape
        and a.dtype == b.dtype
        and np.array_equal(np.ascontiguousarray(a).view(np.uint8), np.ascontiguousarray(b).view(np.uint8))
    )


def ship_free(truth: dict, shape: tuple[int, int], pad: int = 2) -> np.ndarray:
    keep = np.ones(shape, dtype=bool)
    for f in truth["features"]:
        r0, c0, r1, c1 = f["properties"]["bbox_px"]
        keep[max(r0 - pad, 0) : r1 + pad, max(c0 - pad, 0) : c1 + pad] = False
    return keep


# --------------------------------------------------------------------------- determinism


def test_deterministic_for_a_seed():
    cfg = SimConfig(shape=(300, 333), ships=8, clutter="k", seed=7, pixel_spacing_m=(20.0, 20.0), **ALL_ON)
    a, ta = simulate_array(cfg)
    b, tb = simulate_array(SimConfig(**cfg.as_dict()))  # list fields, fresh object
    assert same_bits(a["intensity"], b["intensity"])
    assert ta == tb
    assert json.loads(json.dumps(ta)) == ta
    c, tc = simulate_array(SimConfig(**{**cfg.as_dict(), "seed": 8}))
    assert not np.array_equal(a["intensity"], c["intensity"])
    assert tc != ta


def _random_tiling(shape, rng):
    """Rows cut into bands of random odd heights, each band into random odd widths."""
    H, W = shape
    r = 0
    while r < H:
        h = int(rng.choice([1, 3, 17, 61, 127, 255, 257, 301]))
        r1 = min(H, r + h)
        c = 0
        while c < W:
            w = int(rng.choice([1, 5, 33, 99, 131, 259, 413]))
            c1 = min(W, c + w)
            yield r, r1, c, c1
            c = c1
        r = r1


@pytest.mark.parametrize("kind,clutter", [("intensity", "k"), ("intensity", "gamma"), ("slc", "k"), ("quadpol", "k")])
def test_tiles_are_bit_identical_to_whole_scene(kind, clutter):
    cfg = SimConfig(
        kind=kind,
        clutter=clutter,
        shape=(613, 541),
        ships=12,
        seed=3,
        looks=2.5 if kind == "intensity" and clutter == "gamma" else 1.0,
        pixel_spacing_m=(20.0, 20.0),
        scr_db=25.0,
        **ALL_ON,
    )
    whole, truth = simulate_array(cfg)
    assert truth["ambiguities"], "the test scene should hold azimuth ghosts"
    rng = np.random.default_rng(11)
    got = {k: np.full(v.shape, np.nan, dtype=v.dtype) for k, v in whole.items()}
    for r0, r1, c0, c1 in _random_tiling(cfg.shape, rng):
        t = simulate_tile(cfg, r0, r1, c0, c1)
        for k in got:
            got[k][r0:r1, c0:c1] = t[k]
    for k in whole:
        assert same_bits(got[k], whole[k]), k
    # a truth built without the whole scene has the same pixel statistics
    assert truth_collection(cfg) == truth


def test_components_have_own_streams():
    """Switching an artefact on changes only its own pixels; the sea speckle is unchanged."""
    base = SimConfig(
        shape=(720, 300), ships=6, seed=5, scr_db=25.0, pixel_spacing_m=(15.0, 15.0)
    )  # ghosts ~335 rows off
    off, t_off = simulate_array(base)
    I0 = off["intensity"]

    on, t = simulate_array(SimConfig(**{**base.as_dict(), "sidelobes": True}))
    d = on["intensity"] - I0
    lines = np.zeros(I0.shape, dtype=bool)
    assert t["sidelobes"]
    count = np.zeros(I0.shape, dtype=int)
    for s in t["sidelobes"]:
        r, c, n = s["row"], s["col"], s["extent_px"]
        count[r, max(c - n, 0) : c + n + 1] += 1
        count[max(r - n, 0) : r + n + 1, c] += 1
        count[r, c] -= 2
    lines = count > 0
    assert np.all(d[~lines] == 0)
    assert (d[lines] > 0).mean() > 0.95
    s = max(t["sidelobes"], key=lambda s: s["extent_px"])
    if count[s["row"], s["col"]] == 0:
        assert d[s["row"], s["col"]] == 0  # the scatterer itself is the ship's
    # brightest first sidelobe (k = +-1..3) within a few dB of -13 dB of the scatterer
    pk = I0[s["row"], s["col"]]
    near = d[s["row"], s["col"] - 3 : s["col"] + 4]
    assert 10 * np.log10(near.max() / pk) < -3

    on, t = simulate_array(SimConfig(**{**base.as_dict(), "ambiguities": True}))
    d = on["intensity"] - I0
    inside = np.zeros(I0.shape, dtype=bool)
    assert t["ambiguities"]
    for a in t["ambiguities"]:
        r0, c0, r1, c1 = a["bbox_px"]
        inside[r0:r1, c0:c1] = True
        # where pipeline/targets/ambiguity.py puts the ghost of the ship's centroid (eqs. 1 and 3), to the pixel
        src = t_off["features"][a["source_id"]]["properties"]["centroid_px"]
        want = dict((k, (dr, dc)) for k, dr, dc in sim.ghost_offsets(base.shape, base.pixel_spacing_m, *src))
        assert (a["offset_rows"], a["offset_cols"]) == want[a["order"]] and a["ambiguity_of"] == a["source_id"]
    assert np.all(d[~inside] == 0) and np.all(d[inside] >= 0) and d.max() > 0
    assert t["features"] == t_off["features"]  # ghosts are not ships

    on, t = simulate_array(SimConfig(**{**base.as_dict(), "stripes": True}))
    gain = on["intensity"] / I0
    col_gain = gain[0]
    assert np.allclose(gain, col_gain[None, :], rtol=1e-5)
    db = 10 * np.log10(col_gain)
    assert len(np.unique(np.round(db, 4))) >= 2 and np.abs(db).max() <= 2.5 + 1e-4

    on, t = simulate_array(SimConfig(**{**base.as_dict(), "rfi": True}))
    d = on["intensity"] - I0
    band = np.zeros(I0.shape, dtype=bool)
    for ev in t["rfi"]:
        band[ev["rows"][0] : ev["rows"][1], ev["cols"][0] : ev["cols"][1]] = True
        lvl = 10 ** (ev["level_db"] / 10)
        m = d[ev["rows"][0] : ev["rows"][1], ev["cols"][0] : ev["cols"][1]].mean()
        assert 0.6 * lvl < m < 1.4 * lvl
    assert np.all(d[~band] == 0) and np.all(d[band] > 0)


# --------------------------------------------------------------------------- clutter statistics


@pytest.mark.parametrize(
    "clutter,looks,expect_L", [("rayleigh", 3.0, 1.0), ("gamma", 1.0, 1.0), ("gamma", 3.5, 3.5), ("gamma", 0.7, 0.7)]
)
def test_intensity_clutter_mean_enl_tail_and_independence(clutter, looks, expect_L):
    cfg = SimConfig(shape=(1024, 1024), ships=20, seed=21, clutter=clutter, looks=looks, clutter_mean=2.5)
    assert sim.effective_looks(cfg) == expect_L
    data, truth = simulate_array(cfg)
    I = data["intensity"].astype(np.float64)
    keep = ship_free(truth, I.shape)
    x = I[keep] / cfg.clutter_mean
    n, L = x.size, expect_L
    m, v = x.mean(), x.var()
    assert abs(m - 1) <= 5 / math.sqrt(n * L)
    enl = m * m / v
    assert abs(enl / L - 1) <= 5 * math.sqrt((2 + 2 / L) / n), enl
    for p in (1e-2, 1e-4):
        q = special.gammainccinv(L, p) / L  # upper p-quantile of unit-mean Gamma(L)
        frac = (x > q).mean()
        assert abs(frac - p) <= 5 * math.sqrt(p * (1 - p) / n), (p, frac)
    # neighbours are independent (rows and columns), away from the ships
    for a, b in ((I[:, :-1], I[:, 1:]), (I[:-1, :], I[1:, :])):
        k = ship_free(truth, I.shape)
        k2 = (k[:, :-1] & k[:, 1:]) if a.shape[1] < I.shape[1] else (k[:-1, :] & k[1:, :])
        r = np.corrcoef(a[k2], b[k2])[0, 1]
        assert abs(r) <= 5 / math.sqrt(k2.sum())


def test_slc_is_circular_gaussian():
    cfg = SimConfig(kind="slc", shape=(512, 512), ships=0, seed=2, clutter="gamma", clutter_mean=3.0)
    z = simulate_array(cfg)[0]["hh"].astype(np.complex128).ravel()
    n = z.size
    p = np.abs(z) ** 2 / 3.0
    assert abs(p.mean() - 1) <= 5 / math.sqrt(n)
    assert abs(p.mean() ** 2 / p.var() - 1) <= 5 * math.sqrt(4 / n)
    assert abs((z * z).mean()) / 3.0 <= 5 * math.sqrt(1 / n)  # circular: E[z^2] = 0
    assert abs(z.mean()) <= 5 * math.sqrt(3.0 / n)


def test_k_texture_marginal_and_correlation():
    nu, ell = 2.0, 4.0
    g = sim._gauss_field(9, sim._S_TEXTURE, ell, 0, 1024, 0, 1024).astype(np.float64)
    n_eff = g.size / (1.25 * ell) ** 2
    assert abs(g.mean()) <= 5 / math.sqrt(n_eff)
    assert abs(g.var() - 1) <= 5 * math.sqrt(2 / n_eff)
    # 1/e correlation at lag ell (rows and cols), near 0 at 4 ell
    for ax in (0, 1):
        a = np.moveaxis(g, ax, 0)
        r1 = np.corrcoef(a[:-4].ravel(), a[4:].ravel())[0, 1]
        r4 = np.corrcoef(a[:-16].ravel(), a[16:].ravel())[0, 1]
        assert abs(r1 - math.exp(-1)) < 0.04, r1
        assert abs(r4) < 0.04, r4
    t = sim._gamma_texture(g.astype(np.float32), nu).astype(np.float64)
    # Gamma(nu, 1/nu): mean 1, var 1/nu, excess kurtosis 6/nu
    assert abs(t.mean() - 1) <= 5 * math.sqrt(1 / nu / n_eff)
    assert abs(t.var() * nu - 1) <= 5 * math.sqrt((2 + 6 / nu) / n_eff)
    ks = stats.kstest(t.ravel()[::97], stats.gamma(nu, scale=1 / nu).cdf)
    assert ks.statistic < 0.02


def test_k_intensity_has_the_compound_excess_variance():
    nu, L = 2.0, 1.0
    cfg = SimConfig(shape=(1024, 1024), ships=0, seed=4, clutter="k", looks=L, texture_shape=nu, texture_corr_px=4.0)
    I = simulate_array(cfg)[0]["intensity"].astype(np.float64)
    m = I.mean()
    ratio = I.var() / m**2
    expect = (1 + 1 / nu) * (1 + 1 / L) - 1  # 2.0; plain gamma speckle would give 1.0
    n_eff = I.size / (1.25 * 4.0) ** 2
    assert abs(m - 1) <= 5 * math.sqrt((1 / nu) / n_eff + 1 / I.size)
    assert abs(ratio / expect - 1) < 0.12, ratio
    # spikier than the speckle alone: far more exceedances of the exponential 1e-4 quantile
    assert (I > -math.log(1e-4)).mean() > 10 * 1e-4
    # the scene is spatially textured: local means vary beyond what speckle alone gives
    blk = I.reshape(128, 8, 128, 8).mean(axis=(1, 3))
    assert blk.var() > 3 * (1 / 64)


@pytest.mark.parametrize("clutter", ["gamma", "k"])
def test_quadpol_sea_covariance_matches_sigma(clutter):
    cfg = SimConfig(
        kind="quadpol",
        shape=(512, 512),
        ships=0,
        seed=6,
        clutter=clutter,
        clutter_mean=2.0,
        texture_shape=8.0,
        texture_corr_px=2.0,
    )
    d = simulate_array(cfg)[0]
    X = np.stack([d["hh"].ravel(), d["hv"].ravel(), d["vv"].ravel()]).astype(np.complex128)
    n = X.shape[1]
    C = X @ X.conj().T / n
    S = sea_covariance(cfg)
    # texture of mean 1 keeps the covariance; its variance inflates the error (x (1+1/nu))
    infl = 1.0 if clutter == "gamma" else math.sqrt((1 + 1 / 8.0) * (1.25 * 2.0) ** 2)
    tol = 5 * infl * np.sqrt(np.outer(np.diag(S).real, np.diag(S).real) / n)
    assert np.all(np.abs(C - S) <= tol), (C, S)
    rho = C[0, 2] / math.sqrt(C[0, 0].real * C[2, 2].real)
    assert abs(abs(rho) - abs(sim.SEA_RHO)) < 0.02
    assert abs(np.angle(rho) - np.angle(sim.SEA_RHO)) < 0.03
    if clutter == "gamma":
        y = np.einsum("in,ij,jn->n", X.conj(), np.linalg.inv(S), X).real  # PWF, Gamma(3, 1)
        assert abs(y.mean() - 3) <= 5 * math.sqrt(3 / n)
        assert abs(y.var() - 3) <= 5 * math.sqrt(30 / n)  # var of s^2: (mu4 - s^4)/n = 30/n


def test_quadpol_ships_have_their_own_signature():
    cfg = SimConfig(kind="quadpol", shape=(768, 768), ships=40, seed=12, scr_db=20.0, length_m=(150.0, 300.0))
    d, truth = simulate_array(cfg)
    cat = ship_catalogue(cfg)
    by_cls: dict[str, list[float]] = {}
    for f, c in zip(truth["features"], cat):
        r0, c0, r1, c1 = f["properties"]["bbox_px"]
        hh = np.abs(d["hh"][r0:r1, c0:c1]) ** 2
        hv = np.abs(d["hv"][r0:r1, c0:c1]) ** 2
        by_cls.setdefault(f["properties"]["pol_class"], []).append(hv.sum() / hh.sum())
        assert f["properties"]["pol_class"] == c["pol_class"]
    assert set(by_cls) == set(sim.SHIP_CLASSES)
    assert np.median(by_cls["volume"]) > 5 * sim.SEA_EPS
    assert np.median(by_cls["mixed"]) > 5 * sim.SEA_EPS
    # truth mean is of the span |hh|^2 + 2|hv|^2 + |vv|^2
    f = truth["features"][0]["properties"]
    r0, c0, r1, c1 = f["bbox_px"]
    span = sum(w * np.abs(d[k][r0:r1, c0:c1]) ** 2 for k, w in (("hh", 1), ("hv", 2), ("vv", 1)))
    assert math.isclose(float(span.max()), f["peak"], rel_tol=1e-5)


# --------------------------------------------------------------------------- ships and truth


def test_truth_boxes_contain_the_bright_pixels():
    L = 4.0
    cfg = SimConfig(shape=(1024, 1024), ships=30, seed=13, looks=L, scr_db=20.0, length_m=(40.0, 400.0))
    data, truth = simulate_array(cfg)
    I = data["intensity"]
    H, W = I.shape
    feats = [f["properties"] for f in truth["features"]]
    assert len(feats) == 30 and truth["type"] == "FeatureCollection"
    assert truth["simulation"] == cfg.as_dict()
    # outside the boxes nothing is brighter than the 1e-7 clutter quantile (0.1 expected)
    T = special.gammainccinv(L, 1e-7) / L
    outside = ship_free(truth, I.shape, pad=0)
    assert int((I[outside] > T).sum()) <= 2
    boxes = []
    ratio = []
    for p, f in zip(feats, truth["features"]):
        assert f["geometry"] is None and p["score"] is None and p["difficult"] is False
        r0, c0, r1, c1 = p["bbox_px"]
        assert 5 <= r0 < r1 <= H - 5 and 5 <= c0 < c1 <= W - 5
        assert r0 <= p["centroid_px"][0] <= r1 and c0 <= p["centroid_px"][1] <= c1
        assert 0 < p["area_px"] <= (r1 - r0) * (c1 - c0)
        assert 0 <= p["heading_deg"] < 180 and p["length_px"] >= p["width_px"] >= 1 - 1e-9
        assert math.isclose(p["length_m"], 10 * p["length_px"], rel_tol=1e-9)
        assert abs(p["scr_db"] - cfg.scr_db) <= 2
        box = I[r0:r1, c0:c1]
        assert math.isclose(float(box.max()), p["peak"], rel_tol=1e-6)
        assert p["peak"] > T  # every ship stands out of the clutter
        ratio.append(p["mean"] / (cfg.clutter_mean * (1 + 10 ** (p["scr_db"] / 10))))
        for q in boxes:  # no two ships overlap
            assert r1 <= q[0] or q[2] <= r0 or c1 <= q[1] or q[3] <= c0
        boxes.append((r0, c0, r1, c1))
    # designed SCR: mean over the ship pixels = clutter + 10^(scr/10) clutter (speckled hull)
    assert 0.85 < float(np.mean(ratio)) < 1.15, ratio


def test_catalogue_matches_truth_and_rendered_geometry():
    cfg = SimConfig(
        shape=(400, 500), ships=15, seed=1, pixel_spacing_m=(5.0, 12.0), length_m=(30.0, 200.0), scr_db=30.0, looks=8.0
    )
    cat = ship_catalogue(cfg)
    data, truth = simulate_array(cfg)
    assert len(cat) == 15 and json.loads(json.dumps(cat)) == cat
    m = sim._model(validate(cfg))
    for c, f in zip(cat, truth["features"]):
        p = f["properties"]
        for k in ("bbox_px", "centroid_px", "area_px", "length_px", "width_px", "heading_deg", "length_m", "width_m"):
            assert c[k] == p[k], k
        s = m.ships[c["id"]]
        rr, cc = np.nonzero(s.mask)
        assert p["area_px"] == rr.size
        # ship pixels are bright: at 30 dB SCR with 8 looks nearly all exceed 5x clutter
        vals = data["intensity"][s.r0 + rr, s.c0 + cc]
        assert (vals > 5).mean() > 0.8
        assert len(c["scatterers"]) >= 3
        for sc in c["scatterers"]:
            assert s.mask[sc["row"] - s.r0, sc["col"] - s.c0]
        # pixel heading: the ship's pixel cloud's principal axis (long ships only)
        if p["length_px"] > 4 * p["width_px"] and p["length_px"] > 8:
            cov = np.cov(np.stack([rr, cc]).astype(float))
            w, v = np.linalg.eigh(cov)
            dr, dc = v[:, 1]
            ang = math.degrees(math.atan2(dc, -dr)) % 180
            diff = min(abs(ang - p["heading_deg"]), 180 - abs(ang - p["heading_deg"]))
            assert diff < 8, (ang, p["heading_deg"])


def test_ships_avoid_land_and_land_is_bright():
    cfg = SimConfig(shape=(768, 640), ships=40, seed=17, land=True, looks=4.0)
    data, truth = simulate_array(cfg)
    m = sim._model(validate(cfg))
    land = sim._land_mask(cfg, m.land, 0, 768, 0, 640)
    assert 0.08 < land.mean() < 0.5
    assert truth["land"]["side"] == m.land.side
    dil = land.copy()  # land dilated by the margin: no ship pixel inside
    k = sim.LAND_MARGIN_PX - 1
    for _ in range(k):
        dil[1:] |= dil[:-1]
        dil[:-1] |= dil[1:]
        dil[:, 1:] |= dil[:, :-1]
        dil[:, :-1] |= dil[:, 1:]
    for s in m.ships:
        assert not dil[s.r0 : s.r1, s.c0 : s.c1][s.mask].any()
    I = data["intensity"]
    sea = ~dil & ship_free(truth, I.shape)
    # land median (robust to the urban points) 8..12 dB above the sea median
    db = 10 * np.log10(np.median(I[land]) / np.median(I[sea]))
    assert 6 < db < 13, db
    # the coast is not a straight line (fractal displacement)
    depth = land.sum(axis=0 if m.land.side in ("top", "bottom") else 1)
    assert depth.std() > 3


def test_too_many_ships_and_bad_configs(monkeypatch):
    with pytest.raises(InputError, match="ships"):
        validate(SimConfig(shape=(64, 64), ships=50))
    with pytest.raises(InputError, match="length_m"):  # a 400 px ship in a 100 px scene
        validate(SimConfig(shape=(100, 100), length_m=(20.0, 4000.0)))
    # past the cheap bound of validate(), placement itself reports that ships do not fit
    monkeypatch.setattr(sim.config, "max_ships", lambda cfg: 10**6)
    with pytest.raises(InputError, match="ships: could not place"):
        ship_catalogue(SimConfig(shape=(120, 120), ships=30, length_m=(300.0, 400.0)))


@pytest.mark.parametrize(
    "field,value",
    [
        ("kind", "grd"),
        ("clutter", "weibull"),
        ("shape", (8, 100)),
        ("shape", (100, 70000)),
        ("shape", (100,)),
        ("ships", -1),
        ("ships", 2.5),
        ("looks", 0.0),
        ("looks", -1.0),
        ("looks", float("nan")),
        ("scr_db", 41.0),
        ("scr_db", -11.0),
        ("seed", -1),
        ("pixel_spacing_m", (0.0, 10.0)),
        ("length_m", (50.0, 10.0)),
        ("length_m", (0.0, 10.0)),
        ("texture_shape", 0.0),
        ("texture_corr_px", 0.5),
        ("clutter_mean", -1.0),
        ("land", "yes"),
        ("length_m", (20.0, 40000.0)),
    ],
)
def test_validate_names_the_field(field, value):
    with pytest.raises(InputError) as e:
        validate(SimConfig(**{field: value}))
    msg = str(e.value)
    assert field in msg and "\n" not in msg


def test_validate_normalises():
    c = validate(SimConfig(shape=[100, 120], pixel_spacing_m=[5, 5], length_m=[10, 20], ships=np.int64(3), looks=2))
    assert c.shape == (100, 120) and isinstance(c.shape[0], int)
    assert c.pixel_spacing_m == (5.0, 5.0) and c.ships == 3 and c.looks == 2.0
    hash(c)
    with pytest.raises(InputError, match="tile window"):
        simulate_tile(c, 0, 101, 0, 10)


# --------------------------------------------------------------------------- the store


def test_simulate_writes_store_and_truth(tmp_path):
    import xarray as xr

    from sarship.pipeline.scene import open_scene

    cfg = SimConfig(
        shape=(300, 200), ships=5, seed=4, clutter="rayleigh", looks=3.0, pixel_spacing_m=(20.0, 20.0), **ALL_ON
    )
    calls = []
    out = simulate(tmp_path / "s.zarr", cfg, tile=128, progress=lambda d, t: calls.append((d, t)))
    assert out == tmp_path / "s.zarr"
    assert calls == [(i, 6) for i in range(1, 7)]
    ds = xr.open_zarr(out)
    assert list(ds.data_vars) == ["intensity"] and ds["intensity"].dims == ("y", "x")
    assert ds["intensity"].dtype == np.float32
    whole, truth = simulate_array(cfg)
    assert same_bits(ds["intensity"].values, whole["intensity"])
    a = ds.attrs
    assert a["kind"] == "intensity" and a["looks"] == 1.0  # rayleigh is single-look
    assert a["pixel_spacing_m"] == [20.0, 20.0] and a["sensor"] == "sarship-simulator"
    assert a["acquired"].endswith("Z") and a["simulation"] == cfg.as_dict()
    sc = open_scene(out)
    assert sc.tile == 128 and sc.shape == (300, 200)
    tp = Path(f"{out}.truth.geojson")
    assert json.loads(tp.read_text()) == truth
    assert sorted(os.listdir(tmp_path)) == ["s.zarr", "s.zarr.truth.geojson"]


def test_simulate_quadpol_store_and_truth_path(tmp_path):
    import xarray as xr

    cfg = SimConfig(kind="quadpol", shape=(130, 140), ships=2, seed=1)
    (tmp_path / "t").mkdir()
    simulate(tmp_path / "q.zarr", cfg, tile=64, truth_path=tmp_path / "t" / "truth.json")
    ds = xr.open_zarr(tmp_path / "q.zarr")
    assert sorted(ds.data_vars) == ["hh", "hv", "vv"]
    assert all(ds[v].dtype == np.complex64 for v in ds.data_vars)
    assert ds.attrs["kind"] == "quadpol" and ds.attrs["looks"] == 1.0
    whole, truth = simulate_array(cfg)
    for v in ("hh", "hv", "vv"):
        assert same_bits(ds[v].values, whole[v])
    assert json.loads((tmp_path / "t" / "truth.json").read_text()) == truth


def test_simulate_leaves_nothing_on_failure(tmp_path):
    cfg = SimConfig(shape=(200, 200), ships=3, seed=2)
    # parent is a file, not a folder
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError):
        simulate(tmp_path / "f" / "s.zarr", cfg)
    with pytest.raises(InputError):
        simulate(tmp_path / "nope" / "s.zarr", cfg)
    with pytest.raises(InputError):
        simulate(tmp_path / "s.zarr", cfg, truth_path=tmp_path / "nope" / "t.json")
    with pytest.raises(InputError):
        simulate(tmp_path / "s.zarr", SimConfig(shape=(120, 120), ships=9, length_m=(300.0, 400.0)))
    with pytest.raises(InputError, match="tile"):
        simulate(tmp_path / "s.zarr", cfg, tile=0)
    assert sorted(os.listdir(tmp_path)) == ["f"]

    # interrupted half-way: no store, no truth, no temporaries
    def boom(done, total):
        if done == 2:
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        simulate(tmp_path / "s.zarr", cfg, tile=64, progress=boom)
    assert sorted(os.listdir(tmp_path)) == ["f"]

    # a failed rewrite keeps the previous store and truth intact
    simulate(tmp_path / "s.zarr", cfg, tile=64)
    before = (tmp_path / "s.zarr.truth.geojson").read_text()
    cfg2 = SimConfig(shape=(200, 200), ships=3, seed=99)
    with pytest.raises(RuntimeError):
        simulate(tmp_path / "s.zarr", cfg2, tile=64, progress=boom)
    assert (tmp_path / "s.zarr.truth.geojson").read_text() == before
    assert sorted(os.listdir(tmp_path)) == ["f", "s.zarr", "s.zarr.truth.geojson"]
    import xarray as xr

    assert xr.open_zarr(tmp_path / "s.zarr").attrs["simulation"]["seed"] == 2
