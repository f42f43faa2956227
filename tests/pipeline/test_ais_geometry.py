"""The azimuth displacement, the look geometry and the line times of a scene
(pipeline/ais/displacement.py, pipeline/ais/scene_time.py, safe_geometry's ``first_line_time``).

Checked: ``dx = R v_los / V`` against a hand computation and its sign (a ship moving towards the
radar is imaged ahead along the flight); the look geometry of a simulated scene (north-up, rows
southward, columns eastward, slant range ``800 km + col d sin 35 deg``) gives flight = south,
range = east and ``sin(theta_i) = sin 35 deg``; on the real Sentinel-1 GRD annotation of
../shared (skipped where absent) the look geometry from the scene's own GCPs and range table
reproduces the annotation's ``incidenceAngle`` at its grid points and ``platformHeading``, and the
line times reproduce ``productLastLineUtcTime`` from the first line time (neither is read by the
code under test); the time fallbacks (acquisition middle, ``acquired``, none).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.ais.displacement import azimuth_shift_m, look_geometry, look_vectors, slant_range_m
from sarship.pipeline.ais.scene_time import iso_seconds, line_times, scene_time
from sarship.pipeline.targets.ship_features import Georeference

SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None


def test_displacement_hand_computation_and_sign():
    # radar to the west (range grows eastward); ship sailing west at 10 m/s: towards the radar
    R, V, sin_i = 850_000.0, 7600.0, 0.6
    got = azimuth_shift_m(np.array([-10.0]), np.array([0.0]), 1.0, 0.0, R, V, sin_i)
    assert got[0] == pytest.approx(850_000.0 * 10.0 * 0.6 / 7600.0)  # 671.05 m, ahead along the flight
    assert got[0] > 0
    # sailing away: behind; across the line of sight: no shift
    assert azimuth_shift_m(10.0, 0.0, 1.0, 0.0, R, V, sin_i) == pytest.approx(-got[0])
    assert azimuth_shift_m(0.0, 7.0, 1.0, 0.0, R, V, sin_i) == pytest.approx(0.0, abs=1e-9)
    # 45 degrees off the line of sight: cos 45 of it; the ground-range form without sin(theta_i)
    u = np.array([math.sqrt(0.5), math.sqrt(0.5)])  # range towards the north-east
    v = -10.0 * np.array([1.0, 0.0])  # west
    assert azimuth_shift_m(v[0], v[1], u[0], u[1], R, V) == pytest.approx(R * 10.0 * math.sqrt(0.5) / V)


def _sim_attrs(shape=(2000, 3000), spacing=(10.0, 10.0), lon=3.0, lat=54.0, gcps=False):
    from sarship.pipeline.simulate.config import SimConfig
    from sarship.pipeline.simulate.geometry import sar_geometry
    from sarship.pipeline.simulate.land import geo_attrs

    cfg = SimConfig(shape=shape, pixel_spacing_m=spacing, geo=(lon, lat), geo_gcps=gcps)
    return {**geo_attrs(cfg), "sar_geometry": sar_geometry(shape, spacing)}


@pytest.mark.parametrize("gcps", [False, True])
def test_look_geometry_of_a_simulated_scene(gcps):
    attrs = _sim_attrs(gcps=gcps)
    rows, cols = np.array([10.5, 1000.0, 1999.0]), np.array([0.5, 1500.0, 2999.5])
    g = look_geometry(attrs, Georeference(attrs), rows, cols)
    assert g is not None and g.valid().all()
    np.testing.assert_allclose(g.flight_east, 0.0, atol=1e-9)  # rows southward
    np.testing.assert_allclose(g.flight_north, -1.0, atol=1e-9)
    np.testing.assert_allclose(g.range_east, 1.0, atol=1e-9)  # columns eastward, slant range grows
    np.testing.assert_allclose(g.range_north, 0.0, atol=1e-9)
    # the simulator's own flat-Earth geometry: R = 800 km + (col - 1/2) d sin 35 deg
    np.testing.assert_allclose(g.slant_range_m, 800_000.0 + (cols - 0.5) * 10.0 * math.sin(math.radians(35.0)))
    # sin(theta_i) = dR/dg; the simulator's north-up grid holds one longitude step for all rows
    # (its metres per column change with cos(latitude) by 0.2 % over 10 km) and takes 111 320 m
    # per degree against our sphere's 111 195 (0.1 %)
    np.testing.assert_allclose(g.sin_incidence, math.sin(math.radians(35.0)), rtol=5e-3)
    assert g.platform_velocity_m_s[0] == attrs["sar_geometry"]["platform_velocity_m_s"]


def test_look_geometry_needs_sar_geometry():
    attrs = _sim_attrs()
    geo = Georeference(attrs)
    assert look_geometry({k: v for k, v in attrs.items() if k != "sar_geometry"}, geo, [1.0], [1.0]) is None
    assert look_geometry({**attrs, "sar_geometry": {"unavailable": "no annotation"}}, geo, [1.0], [1.0]) is None
    assert np.isnan(slant_range_m({"range_table": {"col": [0.0], "slant_range_m": [1.0]}}, [3.0])).all()
    # a reversed azimuth axis (time decreasing with the row) reverses the flight direction
    sg = dict(attrs["sar_geometry"], azimuth_time_interval_s=-attrs["sar_geometry"]["azimuth_time_interval_s"])
    g = look_geometry({**attrs, "sar_geometry": sg}, geo, [5.0], [5.0])
    assert g.flight_north[0] == pytest.approx(1.0)
    fe, fn, re_, rn = look_vectors(geo, [5.0], [5.0])  # raw axes: unchanged
    assert fn[0] == pytest.approx(-1.0) and re_[0] == pytest.approx(1.0)


def test_line_times_and_fallbacks():
    sg = {"first_line_time": "2021-04-01T05:26:23.5Z", "azimuth_time_interval_s": 0.002}
    t0 = iso_seconds("2021-04-01T05:26:23.5+00:00")
    np.testing.assert_allclose(line_times({"sar_geometry": sg}, np.array([0.5, 1000.5])), [t0, t0 + 2.0])
    assert iso_seconds("2021-04-01T07:26:23.5+02:00") == t0 == iso_seconds("2021-04-01T05:26:23.5")
    # no line times: the middle of the acquisition, else acquired, else none at all
    a = {"acquisition_start": "2021-04-01T05:26:23", "acquisition_stop": "2021-04-01T05:26:48"}
    np.testing.assert_allclose(line_times(a, np.arange(3.0)), iso_seconds("2021-04-01T05:26:35.5"))
    assert scene_time({"acquired": "2020-01-01T00:00:00Z"}) == 1577836800.0
    assert line_times({"acquired": "not a time"}, np.arange(2.0)) is None
    assert line_times({"sar_geometry": {"azimuth_time_interval_s": 0.002}}, np.arange(2.0)) is None


@pytest.fixture(scope="module")
def grd():
    if GRD is None:
        pytest.skip(f"the Sentinel-1 SAFE sample is not at {SAFE_DIR}")
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    from sarship.pipeline.readers.safe import _grd_gcps, _Product, safe_layout
    from sarship.pipeline.readers.safe_geometry import read_geometry

    prod = _Product(GRD, safe_layout(GRD))
    attrs = {"sar_geometry": read_geometry(prod, "IW", "vv"), "gcps": _grd_gcps(prod, "IW/VV"), "crs": "EPSG:4326"}
    root = ET.parse(next((GRD / "annotation").glob("s1?-iw-grd-vv-*.xml"))).getroot()
    return attrs, root


def test_safe_line_times_reach_the_last_line(grd):
    attrs, root = grd
    info = root.find("imageAnnotation/imageInformation")
    first, last = info.findtext("productFirstLineUtcTime"), info.findtext("productLastLineUtcTime")
    assert attrs["sar_geometry"]["first_line_time"] == first + "Z"
    n = int(info.findtext("numberOfLines"))
    t = line_times(attrs, np.array([0.5, n - 0.5]))
    assert t[0] == pytest.approx(iso_seconds(first + "Z"), abs=1e-6)
    assert t[1] == pytest.approx(iso_seconds(last), abs=2e-3)  # within about one line (1.5 ms)


def test_safe_look_geometry_against_the_annotation(grd):
    attrs, root = grd
    pts = root.findall("geolocationGrid/geolocationGridPointList/geolocationGridPoint")
    line = np.array([float(p.findtext("line")) for p in pts]) + 0.5
    pix = np.array([float(p.findtext("pixel")) for p in pts]) + 0.5
    inc = np.array([float(p.findtext("incidenceAngle")) for p in pts])
    H, W = attrs["sar_geometry"]["shape"]
    # grid points inside the image, off its outermost columns (one-sided differences there)
    keep = (pix > 1) & (pix < W - 2) & (line > 1) & (line < H - 2)
    g = look_geometry(attrs, Georeference(attrs), line[keep], pix[keep])
    assert g is not None and g.valid().all()
    err = np.degrees(np.arcsin(g.sin_incidence)) - inc[keep]
    assert np.median(np.abs(err)) < 0.2 and np.abs(err).max() < 0.6, err  # measured 0.08, 0.30
    heading = float(root.findtext("generalAnnotation/productInformation/platformHeading"))
    az = np.degrees(np.arctan2(g.flight_east, g.flight_north))
    d_az = (az - heading + 180.0) % 360.0 - 180.0
    # the heading is the platform's at nadir; 300-550 km west of it the meridians converge by
    # dlon sin(lat) = 3-6 degrees at 47 N (measured 3.2-5.7): a wrong axis would be >= 90 off
    assert np.abs(d_az).max() < 8.0, d_az
    # right-looking: range points 90 degrees clockwise of the flight
    rz = np.degrees(np.arctan2(g.range_east, g.range_north))
    assert np.abs((rz - az - 90.0 + 180.0) % 360.0 - 180.0).max() < 5.0
