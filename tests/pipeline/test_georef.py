"""Ship outlines in WGS84: affine transforms in any CRS (pyproj), and GCP-georeferenced scenes."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Transformer

from sarship.pipeline.targets.components import MOMENT_DTYPE
from sarship.pipeline.targets.ship_features import Georeference, features


def _record(r0, c0, r1, c1):
    rr, cc = np.mgrid[r0:r1, c0:c1]
    rec = np.zeros(1, MOMENT_DTYPE)
    rec["n"] = rr.size
    rec["sr"], rec["sc"] = rr.sum(), cc.sum()
    rec["srr"], rec["scc"], rec["src"] = (rr * rr).sum(), (cc * cc).sum(), (rr * cc).sum()
    rec["r0"], rec["c0"], rec["r1"], rec["c1"] = r0, c0, r1, c1
    rec["peak"], rec["sumv"], rec["score"] = 9.0, 5.0 * rr.size, 3.0
    return rec


def test_projected_crs_converted_to_lonlat():
    # UTM 33N, 10 m pixels, north up
    attrs = {"crs": "EPSG:32633", "transform": [500000.0, 10.0, 0.0, 6000000.0, 0.0, -10.0]}
    feats = features(_record(100, 200, 104, 230), (10.0, 10.0), attrs)
    ring = np.array(feats[0]["geometry"]["coordinates"][0])
    lon_c, lat_c = ring[:4].mean(axis=0)
    x = 500000.0 + 10.0 * 215.0
    y = 6000000.0 - 10.0 * 102.0
    lon, lat = Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True).transform(x, y)
    assert lon_c == pytest.approx(lon, abs=1e-6) and lat_c == pytest.approx(lat, abs=1e-6)  # corner mean vs centre: ~mm
    # the outline is ~300 m long east-west
    assert feats[0]["properties"]["heading_deg"] == pytest.approx(90.0)


def test_gcp_georeference_fits_polynomial():
    rng = np.random.default_rng(0)
    rows, cols = rng.uniform(0, 1000, 12), rng.uniform(0, 800, 12)

    def truth(r, c):  # a gently curved mapping, exactly quadratic
        return 10.0 + 1e-4 * c + 2e-6 * r + 1e-9 * c * r, 50.0 - 1e-4 * r + 1e-9 * c * c

    lon, lat = truth(rows, cols)
    attrs = {"gcps": [{"row": r, "col": c, "x": x, "y": y, "z": 0.0} for r, c, x, y in zip(rows, cols, lon, lat)]}
    g = Georeference(attrs)
    assert g.usable and g.crs == "EPSG:4326"
    x, y = g.lonlat([500.5], [400.25])
    tx, ty = truth(500.5, 400.25)
    assert x[0] == pytest.approx(tx, abs=1e-10) and y[0] == pytest.approx(ty, abs=1e-10)


def test_no_or_unknown_georeference_gives_null_geometry():
    assert features(_record(0, 0, 2, 2), None, None)[0]["geometry"] is None
    assert (
        features(_record(0, 0, 2, 2), None, {"crs": "EPSG:999999", "transform": [0, 1, 0, 0, 0, -1]})[0]["geometry"]
        is None
    )


# ------------------------------------------------------------------ geolocation grids (pipeline/targets/georef.py)

from pathlib import Path  # noqa: E402

from sarship.pipeline.targets import georef as G  # noqa: E402
from sarship.pipeline.targets.ship_features import geolocate  # noqa: E402

SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
SLC = next(iter(sorted(SAFE_DIR.glob("S1B_IW_SLC_*.SAFE"))), None) if SAFE_DIR.is_dir() else None

#: Bound on the median held-out error (m) of the bilinear grid on the real annotations. The
#: sample products lie over the Alps (grid heights 15-2955 m): a grid point at height h sits
#: ~h/tan(incidence) (up to ~4 km) across track from a sea-level geometry, so the grid's own
#: points are rough at the scale of its spacing and no interpolant reproduces a left-out point to
#: metres there. Measured (docs/sentinel1.md "Georeferencing"): medians 163-536 m for the grid,
#: 415-641 m for the polynomial. Over sea (OpenSARShip products, tests/pipeline/test_opensarship_ais.py)
#: the same held-out grid error is 6-35 m.
TERRAIN_MEDIAN_BOUND_M = 600.0


def _gcps(rows, cols, lon, lat):
    return [
        {"row": float(r), "col": float(c), "x": float(x), "y": float(y), "z": 0.0}
        for r, c, x, y in zip(np.ravel(rows), np.ravel(cols), np.ravel(lon), np.ravel(lat))
    ]


def _grid(n=5, m=7, f=None):
    rows = np.array([0.0, 900.0, 2100.0, 3000.0, 4400.0][:n])
    cols = np.linspace(0.0, 6000.0, m)
    R, C = np.meshgrid(rows, cols, indexing="ij")
    f = f or (lambda r, c: (8.0 + 1e-4 * c - 2e-5 * r + 3e-10 * r * c, 54.0 - 9e-5 * r + 1e-5 * c - 4e-10 * r * c))
    lon, lat = f(R, C)
    return rows, cols, R, C, lon, lat


def test_grid_detected_in_any_order_and_reproduces_its_points():
    rows, cols, R, C, lon, lat = _grid()
    g = _gcps(R, C, lon, lat)
    rng = np.random.default_rng(1)
    shuffled = [g[i] for i in rng.permutation(len(g))]
    m = G.from_gcps(shuffled)
    assert isinstance(m, G.GridGeoreference) and m.shape == (5, 7) and m.method.startswith("geolocation grid")
    x, y = m.lonlat(R, C)
    np.testing.assert_allclose(x, lon, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, lat, rtol=0, atol=1e-12)


def test_bilinear_exact_for_bilinear_mapping_inside_and_extrapolated():
    # lon/lat bilinear in (row, col): interpolation and the edge cells' extension are exact
    rows, cols, R, C, lon, lat = _grid()
    m = G.from_gcps(_gcps(R, C, lon, lat))
    rng = np.random.default_rng(2)
    r = rng.uniform(-50, 4450, 200)  # a little past the first and last grid rows
    c = rng.uniform(-30, 6040, 200)
    x, y = m.lonlat(r, c)
    tx, ty = 8.0 + 1e-4 * c - 2e-5 * r + 3e-10 * r * c, 54.0 - 9e-5 * r + 1e-5 * c - 4e-10 * r * c
    np.testing.assert_allclose(x, tx, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y, ty, rtol=0, atol=1e-9)
    # a bilinear field is a quadratic polynomial too: the polynomial is exact here as well
    p = G.from_gcps(_gcps(R, C, lon, lat), method="polynomial")
    px, py = p.lonlat(r, c)
    np.testing.assert_allclose(px, tx, rtol=0, atol=1e-9)


def test_scattered_gcps_use_the_polynomial_and_grid_can_be_refused():
    rng = np.random.default_rng(0)
    r, c = rng.uniform(0, 1000, 12), rng.uniform(0, 800, 12)
    g = _gcps(r, c, 10 + 1e-4 * c, 50 - 1e-4 * r)
    assert isinstance(G.from_gcps(g), G.PolynomialGeoreference)
    with pytest.raises(ValueError, match="rectilinear grid"):
        G.from_gcps(g, method="grid")
    with pytest.raises(ValueError, match="method"):
        G.from_gcps(g, method="spline")
    # a grid with a missing point or a duplicate is not a grid
    rows, cols, R, C, lon, lat = _grid()
    full = _gcps(R, C, lon, lat)
    assert G.as_grid(full[:-1]) is None
    assert G.as_grid(full[:-1] + [full[0]]) is None
    assert G.as_grid(full) is not None


def test_antimeridian_grid_interpolates_through_it():
    rows, cols = np.array([0.0, 1000.0]), np.array([0.0, 1000.0])
    R, C = np.meshgrid(rows, cols, indexing="ij")
    lon = np.array([[179.9, -179.9], [179.9, -179.9]])  # 0.2 degrees across the antimeridian
    lat = np.array([[10.0, 10.0], [10.1, 10.1]])
    m = G.from_gcps(_gcps(R, C, lon, lat))
    x, y = m.lonlat([500.0, 500.0, 500.0], [0.0, 500.0, 750.0])
    np.testing.assert_allclose(x, [179.9, -180.0, -179.95], atol=1e-9)
    assert np.all((x >= -180) & (x < 180))
    p = G.from_gcps(_gcps(R, C, lon, lat), method="polynomial")
    assert abs(p.lonlat([500.0], [250.0])[0][0] - 179.95) < 1e-9


def test_projected_gcp_grid_interpolated_then_converted():
    # a GCP grid in UTM 33N metres (no wrapping of x), converted to lon/lat with pyproj
    rows, cols = np.array([0.0, 500.0, 1000.0]), np.array([0.0, 400.0, 800.0])
    R, C = np.meshgrid(rows, cols, indexing="ij")
    X, Y = 500000.0 + 10.0 * C, 6000000.0 - 10.0 * R
    g = Georeference({"crs": "EPSG:32633", "gcps": _gcps(R, C, X, Y)})
    assert g.usable and g.method.startswith("geolocation grid")
    lon, lat = g.lonlat([250.0], [100.0])
    tl, tt = Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True).transform(501000.0, 5997500.0)
    assert lon[0] == pytest.approx(tl, abs=1e-9) and lat[0] == pytest.approx(tt, abs=1e-9)


def test_held_out_errors_measure_a_curved_grid():
    # a grid whose lon depends on c**3 (range non-linearity): bilinear from every other point
    # errs by the cubic's curvature; the global quadratic errs more; a corrupted grid fails
    def f(r, c):
        u = c / 6000.0
        return 8.0 + 0.6 * u + 0.15 * u**3 + 1e-6 * r, 54.0 - 1e-4 * r + 0.02 * u * u * u

    rows, cols, R, C, lon, lat = _grid(m=21, f=f)
    g = _gcps(R, C, lon, lat)
    for scheme in ("alternate", "row", "col"):
        e = G.held_out_errors(g, scheme)
        assert e["grid"]["median_m"] < e["polynomial"]["median_m"], (scheme, e)
    # linear interpolation over a gap h errs by at most max|f''| h^2 / 8 (h = 600 px with one column
    # out): lon 0.9/6000^2 deg/px^2 (65.4 km/deg at 54N) and lat 0.12/6000^2 (111.2 km/deg): 75.5 m
    bound = np.hypot(0.9 * 65.4e3, 0.12 * 111.2e3) / 6000.0**2 * 600.0**2 / 8.0
    assert G.held_out_errors(g, "col")["grid"]["max_m"] <= bound
    bad = [dict(p) for p in g]
    for p in bad:  # one grid column's longitudes off by 0.05 degrees (~3 km)
        if p["col"] == cols[10]:
            p["x"] += 0.05
    assert G.held_out_errors(bad, "col")["grid"]["max_m"] > 1000.0
    with pytest.raises(ValueError, match="scheme"):
        G.held_out_errors(g, "random")


def _annotation_gcps(product: Path, group: str) -> list[dict]:
    import xarray as xr

    g = xr.open_dataset(product, engine="sentinel-1", group=f"{group}/gcp")
    gl, gp = g["line"].values, g["pixel"].values
    lat, lon, h = g["latitude"].values, g["longitude"].values, g["height"].values
    return [
        {"row": float(gl[i]), "col": float(gp[j]), "x": float(lon[i, j]), "y": float(lat[i, j]), "z": float(h[i, j])}
        for i in range(len(gl))
        for j in range(len(gp))
    ]


@pytest.mark.skipif(GRD is None or SLC is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
@pytest.mark.parametrize("which,group", [("grd", "IW/VV"), ("slc", "IW1/VV"), ("slc", "IW2/VH")])
def test_real_annotation_grid_beats_polynomial(which, group):
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    g = _annotation_gcps(GRD if which == "grd" else SLC, group)
    assert isinstance(G.from_gcps(g), G.GridGeoreference)
    fit = G.held_out_errors(g, "polynomial_fit")["polynomial"]
    assert fit["median_m"] > 300.0  # the polynomial misses the grid's own points by hundreds of metres
    for scheme in ("alternate", "row", "col"):
        e = G.held_out_errors(g, scheme)
        assert e["grid"]["median_m"] < e["polynomial"]["median_m"], (scheme, e)
        assert e["grid"]["rms_m"] < e["polynomial"]["rms_m"] * 1.01, (scheme, e)
        assert e["grid"]["median_m"] < TERRAIN_MEDIAN_BOUND_M, (scheme, e)


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
@pytest.mark.parametrize("box", [(16300, 1000, 16304, 1030), (16200, 1500, 16230, 1504), (16250, 1200, 16270, 1220)])
def test_grd_detection_lonlat_and_metres(box):
    """A detection of the real GRD grid: centre = the grid's bilinear value, the outline closed,
    and the outline's geodesic sides = length_m / width_m from the annotation's 10 m spacing
    (ground range; within 3 %: the near-sea corner of the scene, grid heights 25-141 m)."""
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    from pyproj import Geod

    gcps = _annotation_gcps(GRD, "IW/VV")
    spacing = (10.0, 10.0)  # azimuthPixelSpacing, rangePixelSpacing of the sample (tests/pipeline/test_safe.py)
    f = features(_record(*box), spacing, {"gcps": gcps})[0]
    p = f["properties"]
    m = G.from_gcps(gcps)
    x, y = m.lonlat([p["centroid_px"][0]], [p["centroid_px"][1]])
    assert p["centroid_lonlat"] == pytest.approx([x[0], y[0]], abs=1e-12)
    ring = np.array(f["geometry"]["coordinates"][0])
    assert ring.shape == (5, 2) and np.array_equal(ring[0], ring[-1])
    geod = Geod(ellps="WGS84")
    sides = [geod.inv(*ring[k], *ring[k + 1])[2] for k in range(4)]
    assert max(sides) == pytest.approx(p["length_m"], rel=0.03)
    assert min(sides) == pytest.approx(p["width_m"], rel=0.03)
    # the centre lies inside the outline
    assert _inside(p["centroid_lonlat"], ring)


def _inside(pt, ring) -> bool:
    x, y = pt
    inside = False
    for (x1, y1), (x2, y2) in zip(ring[:-1], ring[1:]):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def test_geolocate_follows_replaced_geometry_and_nulls_without_georeference():
    rows, cols, R, C, lon, lat = _grid()
    geo = {"gcps": _gcps(R, C, lon, lat)}
    f = features(_record(100, 200, 104, 230), (10.0, 10.0), geo)
    before = list(f[0]["properties"]["centroid_lonlat"])
    f[0]["properties"]["centroid_px"] = [300.5, 400.5]  # as a sidelobe core or a segmented ship does
    geolocate(f, geo)
    m = G.from_gcps(geo["gcps"])
    x, y = m.lonlat([300.5], [400.5])
    assert f[0]["properties"]["centroid_lonlat"] == pytest.approx([x[0], y[0]], abs=1e-12)
    assert f[0]["properties"]["centroid_lonlat"] != before
    assert geolocate(f, None)[0]["geometry"] is None and f[0]["properties"]["centroid_lonlat"] is None
    assert features(_record(0, 0, 2, 2), None, None)[0]["properties"]["centroid_lonlat"] is None


# ------------------------------------------------------------------ the grid moved to sea level


def test_sea_level_removes_a_synthetic_terrain_displacement():
    """Grid points displaced across track by (h - h_min) / tan(incidence), as a side-looking radar
    places terrain, are moved back onto the smooth sea-level geometry."""
    rows = np.linspace(0.0, 16000.0, 9)
    cols = np.linspace(0.0, 25000.0, 21)
    R, C = np.meshgrid(rows, cols, indexing="ij")
    k = G.EARTH_RADIUS_M * np.pi / 180.0
    lat0 = 46.0 - 9e-5 * R / 10 + 1e-5 * C / 10
    lon0 = 10.0 + (10.0 * C - 2.0 * R) / (k * np.cos(np.radians(46.0)))  # range ~ east, 10 m px
    inc = 30.0 + 15.0 * C / C.max()
    h = np.random.default_rng(3).uniform(0.0, 2500.0, R.shape)
    h[-1, 0] = 0.0  # a sea point: the lowest
    # across track = the direction of increasing column of the sea-level geometry
    e, n = 10.0, 1e-5 * k / 10
    ue, un = e / np.hypot(e, n), n / np.hypot(e, n)
    d = h / np.tan(np.radians(inc))
    lon = lon0 + d * ue / (k * np.cos(np.radians(lat0)))
    lat = lat0 + d * un / k
    g = [dict(p, z=float(hh), incidence=float(ii)) for p, hh, ii in zip(_gcps(R, C, lon, lat), h.ravel(), inc.ravel())]
    m = G.from_gcps(g)
    assert m.method == "geolocation grid moved to 0 m height, bilinear"
    x, y = m.lonlat(R, C)
    err = G.distance_m(x, y, lon0, lat0)
    assert err.max() < 15.0, err.max()  # the direction comes from a fit to the displaced points
    plain = G.from_gcps(g, to_sea_level=False)
    x, y = plain.lonlat(R, C)
    assert G.distance_m(x, y, lon0, lat0).max() > 2000.0  # the terrain's displacement, kept
    assert G.from_gcps([{k_: v for k_, v in p.items() if k_ != "incidence"} for p in g]).method == plain.method
    with pytest.raises(ValueError, match="incidence"):
        G.sea_level(rows, cols, lon, lat, h, np.zeros_like(h))


def _annotation_gcps_with_incidence(product: Path, group: str) -> list[dict]:
    import xarray as xr

    inc = xr.open_dataset(product, engine="sentinel-1", group=f"{group}/gcp")["incidenceAngle"].values.ravel()
    return [dict(p, incidence=float(i)) for p, i in zip(_annotation_gcps(product, group), inc)]


#: Bound on the median held-out error (m) of the grid moved to sea level, on the real annotations:
#: measured 9-52 m (docs/sentinel1.md "Georeferencing").
SEA_LEVEL_MEDIAN_BOUND_M = 60.0


@pytest.mark.skipif(GRD is None or SLC is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
@pytest.mark.parametrize("which,group", [("grd", "IW/VV"), ("slc", "IW1/VV"), ("slc", "IW2/VH")])
def test_real_annotation_grid_at_sea_level(which, group):
    """With each point's incidence angle the Alpine grids become smooth: held-out medians drop from
    hundreds of metres to tens, below the polynomial's on the same moved points in two of three schemes
    (on the GRD the polynomial's smooth azimuth fit wins leave-one-row-out: 36 m vs 52 m)."""
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    g = _annotation_gcps_with_incidence(GRD if which == "grd" else SLC, group)
    assert G.from_gcps(g).method.startswith("geolocation grid moved to")
    for scheme in ("alternate", "row", "col"):
        raw = G.held_out_errors(g, scheme)["grid"]
        e = G.held_out_errors(g, scheme, to_sea_level=True)
        assert e["grid"]["median_m"] < SEA_LEVEL_MEDIAN_BOUND_M, (scheme, e)
        assert e["grid"]["median_m"] < raw["median_m"] / 5, (scheme, e, raw)
        if scheme != "row":
            assert e["grid"]["median_m"] < e["polynomial"]["median_m"], (scheme, e)


def test_pixel_of_inverts_the_grid_and_land_files_use_it():
    """lon/lat -> pixel by Newton on the bilinear grid: round trip within 1e-3 px on a curved,
    unevenly spaced grid where the quadratic polynomial's inverse is off by pixels; the vector
    land-mask files (pipeline/land/landmask_files.lonlat_to_pixel) place lon/lat with it."""
    from sarship.pipeline.land.landmask_files import lonlat_to_pixel
    from sarship.pipeline.targets.georef import GridGeoreference, from_gcps, pixel_of

    rows = np.array([0.0, 700.0, 1500.0, 2600.0, 3999.0])
    cols = np.linspace(0.0, 5999.0, 7)
    R, C = np.meshgrid(rows, cols, indexing="ij")
    lon = 10.0 + 1e-4 * C + 2e-5 * R + 3e-9 * C**2 + 0.004 * np.sin(R / 900.0)
    lat = 59.0 - 9e-5 * R + 1e-5 * C + 2e-9 * R * C
    gcps = [
        {"row": float(r), "col": float(c), "x": float(x), "y": float(y), "z": 0.0}
        for r, c, x, y in zip(R.ravel(), C.ravel(), lon.ravel(), lat.ravel())
    ]
    geo = from_gcps(gcps)
    assert isinstance(geo, GridGeoreference)
    rng = np.random.default_rng(5)
    rr, cc = rng.uniform(0, 3999, 300), rng.uniform(0, 5999, 300)
    x, y = geo.lonlat(rr, cc)
    r0 = np.full_like(rr, 2000.0)
    c0 = np.full_like(cc, 3000.0)
    r1, c1 = pixel_of(geo, x, y, r0, c0)
    assert np.max(np.abs(r1 - rr)) < 1e-3 and np.max(np.abs(c1 - cc)) < 1e-3
    r2, c2 = lonlat_to_pixel(x, y, {"gcps": gcps})
    assert np.max(np.abs(r2 - rr)) < 1e-3 and np.max(np.abs(c2 - cc)) < 1e-3

    # what the land files did before: a quadratic fitted from lon/lat to pixels on the grid
    # points, pixels off by more than a pixel on this grid
    def design(a, b):
        return np.stack([np.ones_like(a), a, b, a * a, a * b, b * b], -1)

    coef, *_ = np.linalg.lstsq(design(lon.ravel(), lat.ravel()), np.stack([R.ravel(), C.ravel()], -1), rcond=None)
    old = design(x, y) @ coef
    assert np.max(np.hypot(old[:, 0] - rr, old[:, 1] - cc)) > 1.0
