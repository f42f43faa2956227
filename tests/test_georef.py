"""Ship outlines in WGS84: affine transforms in any CRS (pyproj), and GCP-georeferenced scenes."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Transformer

from sarship.pipeline.components import MOMENT_DTYPE
from sarship.pipeline.ship_features import Georeference, features


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
    assert features(_record(0, 0, 2, 2), None, {"crs": "EPSG:999999", "transform": [0, 1, 0, 0, 0, -1]})[0]["geometry"] is None
