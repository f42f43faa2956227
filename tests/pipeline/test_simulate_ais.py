"""The simulator's moving ships and AIS reports (issue 33): azimuth displacement, truth, AIS CSV.

Ground truth the simulator does not use: the displacement is measured on the rendered pixels
(the ship alone: the scene minus the same scene without ships, whose clutter is bit-identical)
and compared with ``R v_toward / V`` computed here from the scene's ``sar_geometry`` and the
ship's SOG/COG; the AIS reports are read back from the CSV text and interpolated here; the
report intervals are those of ITU-R M.1371-5 table 1, written out here.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate import SimConfig, sar_geometry, simulate_array, truth_collection, validate
from sarship.pipeline.simulate.ais_reports import AisOptions, ais_reports, csv_text

KNOT = 1852.0 / 3600.0
M_PER_DEG = 111_320.0
GEO = (10.6, 57.5)
#: A moving, reporting scene: class A and B ships (10-300 m), every speed of the default mix.
AIS_SCENE = SimConfig(
    shape=(640, 640), ships=14, seed=3, length_m=(10.0, 300.0), geo=GEO, moving=True, ais=True, dark_fraction=0.25
)
MOVING_OPTS = {"moving", "speed_kn", "anchored_fraction", "ais", "dark_fraction", "ais_outside", "ais_small"}
NEW_PROPS = {"sog_kn", "cog_deg", "bow_deg", "v_toward_m_s", "true_position_px", "displaced_position_px"}
NEW_PROPS |= {"displacement_px", "displacement_m", "zero_doppler_time", "lon", "lat"}
NEW_PROPS |= {"mmsi", "dark", "ais_class", "ais_name"}


def _posix(text: str) -> float:
    return dt.datetime.fromisoformat(text).timestamp()


def _formula_rows(p: dict, geom: dict, d_az: float, d_rg: float) -> float:
    """``R v_toward / V`` in rows, from the geometry attribute and the ship's SOG/COG (range east):
    ``v_toward`` its line-of-sight velocity, the ground-range velocity times ``sin(incidence)``, the
    incidence from the slant range's growth per ground metre of range (the range table)."""
    t = geom["range_table"]
    R = float(np.interp(p["true_position_px"][1], t["col"], t["slant_range_m"]))
    sin_inc = (t["slant_range_m"][-1] - t["slant_range_m"][0]) / (t["col"][-1] - t["col"][0]) / d_rg
    v_toward = -p["sog_kn"] * KNOT * math.sin(math.radians(p["cog_deg"])) * sin_inc
    return R * v_toward / geom["platform_velocity_m_s"] / d_az


def _read_csv(text: str) -> dict[int, dict[str, np.ndarray]]:
    rows = list(csv.DictReader(io.StringIO(text)))
    out: dict[int, dict[str, list]] = {}
    for r in rows:
        v = out.setdefault(int(r["mmsi"]), {k: [] for k in ("t", "lon", "lat", "sog", "heading", "length")})
        v["t"].append(_posix(r["time"]))
        v["lon"].append(float(r["lon"]))
        v["lat"].append(float(r["lat"]))
        v["sog"].append(float(r["sog"]))
        v["heading"].append(float(r["heading"]) if r["heading"] else math.nan)
        v["length"].append(float(r["length_m"]))
    return {m: {k: np.asarray(a) for k, a in v.items()} for m, v in out.items()}


def _at(track: dict[str, np.ndarray], t: float) -> tuple[float, float]:
    o = np.argsort(track["t"])
    return float(np.interp(t, track["t"][o], track["lon"][o])), float(np.interp(t, track["t"][o], track["lat"][o]))


def _track_velocity(track: dict[str, np.ndarray]) -> tuple[float, float]:
    """East and north velocity (m/s) of a straight-line fit to a track's reports."""
    t = track["t"] - track["t"].mean()
    east = (track["lon"] - track["lon"].mean()) * M_PER_DEG * math.cos(math.radians(GEO[1]))
    north = (track["lat"] - track["lat"].mean()) * M_PER_DEG
    return float(np.polyfit(t, east, 1)[0]), float(np.polyfit(t, north, 1)[0])


def _dist_m(lon1: float, lat1: float, lon2: float, lat2: float) -> float:
    return math.hypot((lon1 - lon2) * M_PER_DEG * math.cos(math.radians(lat2)), (lat1 - lat2) * M_PER_DEG)


# --------------------------------------------------------------------------- the image


def test_options_off_or_still_leave_the_scene_unchanged():
    """Motion/AIS fields without their switch, AIS on (still ships) and moving at 0 kn render
    the scene bit for bit as without them; the truth only gains the new properties."""
    plain = SimConfig(shape=(300, 300), ships=6, seed=11, geo=GEO, ambiguities=True)
    a, ta = simulate_array(plain)
    for extra in (
        {"speed_kn": (3.0, 9.0), "anchored_fraction": 0.5, "dark_fraction": 0.5, "ais_outside": 2},
        {"ais": True},
        {"moving": True, "speed_kn": (0.0, 0.0), "anchored_fraction": 0.0},
    ):
        b, tb = simulate_array(SimConfig(**{**plain.as_dict(), **extra}))
        assert np.array_equal(a["intensity"].view(np.uint32), b["intensity"].view(np.uint32)), extra
        assert {k: v for k, v in tb.items() if k not in ("simulation", "ais", "features")} == {
            k: v for k, v in ta.items() if k not in ("simulation", "features")
        }
        for fa, fb in zip(ta["features"], tb["features"]):
            pb = fb["properties"]
            assert {k: v for k, v in pb.items() if k not in NEW_PROPS} == fa["properties"]
            if "sog_kn" in pb:  # at 0 kn: not displaced
                assert pb["sog_kn"] == 0.0 and pb["displacement_px"] == 0.0
                assert pb["true_position_px"] == pb["displaced_position_px"]
    assert "mmsi" not in ta["features"][0]["properties"] and "ais" not in ta


def test_moving_ship_is_imaged_at_its_doppler_displacement():
    d_az = 20.0
    base = dict(shape=(400, 400), seed=5, looks=16.0, scr_db=30.0, pixel_spacing_m=(d_az, d_az), length_m=(40.0, 200.0))
    data, truth = simulate_array(SimConfig(ships=10, moving=True, **base))
    sea, _ = simulate_array(SimConfig(ships=0, moving=True, **base))
    ship_only = data["intensity"] - sea["intensity"]  # exactly 0 off the ships (same clutter bits)
    labels, n = ndimage.label(ship_only > 0, structure=np.ones((3, 3)))
    assert n == 10
    geom = sar_geometry(base["shape"], base["pixel_spacing_m"])
    signs = set()
    for f in truth["features"]:
        p = f["properties"]
        r0, c0, r1, c1 = p["bbox_px"]
        ids = np.unique(labels[r0:r1, c0:c1])
        ids = ids[ids > 0]
        assert ids.size == 1
        rows, _cols = np.nonzero(labels == ids[0])
        measured = rows.mean() + 0.5 - p["true_position_px"][0]
        expected = _formula_rows(p, geom, d_az, base["pixel_spacing_m"][1])
        assert abs(measured - expected) < 0.6, (p["id"], measured, expected)
        if abs(expected) > 2.0:  # towards the radar (west, columns run east): later rows
            assert np.sign(measured) == np.sign(-math.sin(math.radians(p["cog_deg"])))
            signs.add(int(np.sign(measured)))
        # the hull points along its course under way
        if p["sog_kn"] >= 2.0:
            assert abs((p["cog_deg"] - p["bow_deg"] + 180.0) % 360.0 - 180.0) < 10.0
    assert signs == {-1, 1}  # both directions seen


# --------------------------------------------------------------------------- AIS


@pytest.fixture(scope="module")
def ais_case():
    truth = truth_collection(AIS_SCENE)
    reports, info = ais_reports(AIS_SCENE)
    return truth, _read_csv(csv_text(reports, info)), csv_text(reports, info)


def test_ais_reports_pass_through_the_true_position(ais_case):
    truth, tracks, text = ais_case
    assert text.splitlines()[0] == "mmsi,time,lon,lat,sog,cog,heading,name,length_m,width_m"
    cfg = validate(AIS_SCENE)
    from sarship.pipeline.simulate.land import geo_attrs

    c, a, _b, f, _d, e = geo_attrs(cfg)["transform"]
    far = 0
    for feat in truth["features"]:
        p = feat["properties"]
        row, col = p["true_position_px"]
        assert math.isclose(p["lon"], c + a * col, abs_tol=1e-9) and math.isclose(p["lat"], f + e * row, abs_tol=1e-9)
        if p["dark"]:
            continue
        lon, lat = _at(tracks[p["mmsi"]], _posix(p["zero_doppler_time"]))
        assert _dist_m(lon, lat, p["lon"], p["lat"]) < 50.0  # 5 sigma of the 10 m noise
        if p["sog_kn"] >= 2.0:  # the track's own velocity (least squares over the reports) is the SOG/COG
            ve, vn = _track_velocity(tracks[p["mmsi"]])
            assert abs(math.hypot(ve, vn) / KNOT - p["sog_kn"]) < 0.2
            assert abs((math.degrees(math.atan2(ve, vn)) - p["cog_deg"] + 180.0) % 360.0 - 180.0) < 2.0
        if abs(p["displacement_m"]) > 80.0:  # AIS is where the ship is, not where it is imaged
            seen_lat = f + e * p["displaced_position_px"][0]
            assert abs(_dist_m(lon, lat, p["lon"], seen_lat) - abs(p["displacement_m"])) < 50.0
            far += 1
    assert far >= 3


def test_dark_ships_never_report(ais_case):
    truth, tracks, _ = ais_case
    props = [f["properties"] for f in truth["features"]]
    dark = [p for p in props if p["dark"]]
    assert len(dark) == round(0.25 * len(props)) == truth["ais"]["ships_dark"]
    assert all(p["mmsi"] is None for p in dark) and all(isinstance(p["mmsi"], int) for p in props if not p["dark"])
    expected = {p["mmsi"] for p in props if not p["dark"]} | {v["mmsi"] for v in truth["ais"]["vessels"]}
    assert set(tracks) == expected
    for frac, n_dark in ((0.0, 0), (1.0, 14)):
        cfg = SimConfig(**{**AIS_SCENE.as_dict(), "dark_fraction": frac})
        t = truth_collection(cfg)
        assert sum(f["properties"]["dark"] for f in t["features"]) == n_dark
        if frac == 1.0:
            assert set(ais_reports(cfg)[0].mmsi.tolist()) == {v["mmsi"] for v in t["ais"]["vessels"]}


def _itu_interval(class_a: bool, sog: float) -> float:
    if not class_a:
        return 180.0 if sog <= 2.0 else 30.0
    if sog < 1.0:  # the default mix: under way from 2 kn, at anchor below 1 kn
        return 180.0
    return 10.0 if sog <= 14.0 else 6.0 if sog <= 23.0 else 2.0


def test_report_intervals_gaps_and_window(ais_case):
    truth, tracks, _ = ais_case
    vessels = [f["properties"] for f in truth["features"] if not f["properties"]["dark"]] + truth["ais"]["vessels"]
    t_mid = _posix(truth["features"][0]["properties"]["zero_doppler_time"])
    seen = set()
    for v in vessels:
        tr = tracks[v["mmsi"]]
        t = np.sort(tr["t"])
        assert t[0] >= t_mid - 602.0 and t[-1] <= t_mid + 602.0  # +-600 s of the middle row's time
        T = _itu_interval(v["ais_class"] == "A", v["sog_kn"])
        seen.add((v["ais_class"], T))
        gaps = np.diff(t)
        assert gaps.min() >= 0.8 * T - 1e-6
        assert abs(np.median(gaps) / T - 1.0) < 0.1
        assert gaps.max() <= max(180.0, 1.2 * T) + 1e-6
        assert np.all(np.isnan(tr["heading"])) == (v["ais_class"] == "B")
    assert {("A", 10.0), ("A", 180.0), ("B", 30.0)} <= seen and any(c == "A" and T < 10 for c, T in seen)


def test_ais_only_vessels_outside_the_swath_or_too_small(ais_case):
    truth, tracks, _ = ais_case
    cfg = validate(AIS_SCENE)
    H, W = cfg.shape
    vs = truth["ais"]["vessels"]
    assert sum(v["kind"] == "outside" for v in vs) == cfg.ais_outside
    assert sum(v["kind"] == "small" for v in vs) == cfg.ais_small
    geom = sar_geometry(cfg.shape, cfg.pixel_spacing_m)
    v_max = cfg.speed_kn[1] * KNOT
    reach_px = geom["range_table"]["slant_range_m"][1] * v_max / geom["platform_velocity_m_s"] / 10.0
    shortest = min(f["properties"]["length_m"] for f in truth["features"])
    for v in vs:
        r, c = v["true_position_px"]
        lon, lat = _at(tracks[v["mmsi"]], _posix(v["zero_doppler_time"]))
        assert _dist_m(lon, lat, v["lon"], v["lat"]) < 50.0
        if v["kind"] == "outside":  # could not be imaged here, even displaced
            assert max(-r, r - H, -c, c - W) > reach_px
        else:
            assert 0 <= r < H and 0 <= c < W
            assert v["length_m"] < min(shortest, 10.0) and tracks[v["mmsi"]]["length"][0] <= 10.0


def test_the_ais_reader_reads_the_file_back(ais_case, tmp_path):
    from sarship.pipeline.ais.formats import read_ais

    _, _, text = ais_case
    path = tmp_path / "s.ais.csv"
    path.write_text(text)
    reports, info, stats = read_ais([path], None)
    want, want_info = ais_reports(AIS_SCENE)
    assert sum(stats.rejected.values()) == 0
    assert len(reports) == len(want) == stats.kept and np.array_equal(reports.mmsi, want.mmsi)
    assert np.abs(reports.t - want.t).max() <= 0.0005 + 1e-6  # written to the millisecond
    assert np.abs(reports.lat - want.lat).max() < 1e-7 and np.abs(reports.lon - want.lon).max() < 1e-7
    assert np.array_equal(np.isnan(reports.heading_deg), np.isnan(want.heading_deg))
    assert info == want_info


def test_truth_mmsi_and_dark_survive_into_ships(tmp_path):
    from sarship.pipeline.products.truth import load_geojson

    path = tmp_path / "t.geojson"
    path.write_text(json.dumps(truth_collection(AIS_SCENE)))
    ships = load_geojson(path)
    assert len(ships) == 14
    assert {s.properties["dark"] for s in ships} == {True, False}
    assert all((s.properties["mmsi"] is None) == s.properties["dark"] for s in ships)
    assert all(len(s.properties["true_position_px"]) == 2 for s in ships)


# --------------------------------------------------------------------------- command line and checks


def _cli(*args) -> tuple[int, str, str]:
    from sarship.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def test_simulate_command_writes_scene_truth_and_ais(tmp_path):
    import xarray as xr

    scene, ais = tmp_path / "s.zarr", tmp_path / "s.ais.csv"
    args = ("simulate", scene, "--shape", "256x256", "--ships", "3", "--geo", "10.6,57.5", "--moving")
    code, out, err = _cli(*args, "--ais", ais, "--dark-fraction", "0.34", "--time", "2021-06-01T10:30:00Z")
    assert code == 0, err
    assert out.splitlines()[-1] == f"ais: {ais}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ais.csv", "s.zarr", "s.zarr.truth.geojson"]
    g = xr.open_zarr(scene).attrs["sar_geometry"]
    assert g["first_line_time"] == "2021-06-01T10:30:00Z" and g["flight_direction_deg"] == 180.0
    truth = json.loads(Path(f"{scene}.truth.geojson").read_text())
    assert sum(f["properties"]["dark"] for f in truth["features"]) == 1
    t0 = _posix("2021-06-01T10:30:00Z")
    for f in truth["features"]:
        row = f["properties"]["true_position_px"][0]
        assert math.isclose(_posix(f["properties"]["zero_doppler_time"]), t0 + row * g["azimuth_time_interval_s"])
    before = ais.read_bytes()
    code, _, err = _cli(*args, "--ais", ais, "--overwrite")
    assert code == 0 and ais.read_bytes() != before  # replaced (another time: the seed's)
    code, _, err = _cli(
        "simulate", tmp_path / "n.zarr", "--shape", "64x64", "--ships", "1", "--geo", "1,50", "--ais", ais
    )
    assert code == 2 and "already exists" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "n.zarr").exists() and not list(tmp_path.glob(".*partial*"))
    code, _, err = _cli("simulate", tmp_path / "n.zarr", "--shape", "64x64", "--ais", tmp_path / "n.csv")
    assert code == 2 and "--ais needs --geo" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "field,value",
    [
        ("time", "yesterday"),
        ("time", "2150-01-01T00:00:00Z"),
        ("moving", "yes"),
        ("speed_kn", (5.0, 2.0)),
        ("speed_kn", (0.0, 80.0)),
        ("anchored_fraction", 1.5),
        ("dark_fraction", -0.1),
        ("ais_outside", -1),
        ("ais_small", 2.5),
        ("ais", True),  # without geo
    ],
)
def test_bad_options_name_the_field(field, value):
    with pytest.raises(InputError) as e:
        validate(SimConfig(**{field: value}))
    assert field in str(e.value) and "\n" not in str(e.value)


def test_bad_ais_options_and_normalised_time():
    for name, value in (("window_s", 0.0), ("drop_p", 1.0), ("noise_m", -1.0), ("max_gap_s", float("nan"))):
        with pytest.raises(InputError, match=name):
            ais_reports(AIS_SCENE, AisOptions(**{name: value}))
    assert validate(SimConfig(time="2021-06-01T12:30:00+02:00")).time == "2021-06-01T10:30:00Z"
    assert validate(SimConfig(time="2021-06-01T10:30:00.25")).time == "2021-06-01T10:30:00.250000Z"
