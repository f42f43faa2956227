"""Detections as GeoPackage / KML (pipeline/products/export.py; ``sarship export``, ``sarship detect --formats``)."""

from __future__ import annotations

import json
import os
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.products import export as E
from sarship.pipeline.targets.components import MOMENT_DTYPE
from sarship.pipeline.targets.ship_features import collection, features
from tests.cli.test_cli import assert_clean_error, sarship
from tests.conftest import write_scene

pyogrio = pytest.importorskip("pyogrio", reason="pyogrio not installed (pip install 'sarship[gis]')")

UTM = {"crs": "EPSG:32633", "transform": [500000.0, 10.0, 0.0, 6000000.0, 0.0, -10.0]}
KML = "{http://www.opengis.net/kml/2.2}"


def _record(r0, c0, r1, c1, score=3.0):
    rr, cc = np.mgrid[r0:r1, c0:c1]
    rec = np.zeros(1, MOMENT_DTYPE)
    rec["n"] = rr.size
    rec["sr"], rec["sc"] = rr.sum(), cc.sum()
    rec["srr"], rec["scc"], rec["src"] = (rr * rr).sum(), (cc * cc).sum(), (rr * cc).sum()
    rec["r0"], rec["c0"], rec["r1"], rec["c1"] = r0, c0, r1, c1
    rec["peak"], rec["sumv"], rec["score"] = 9.0, 5.0 * rr.size, score
    rec["peak_r"], rec["peak_c"] = r0, c0
    return rec


def _collection(geo=UTM) -> dict:
    recs = np.concatenate(
        [_record(100, 200, 104, 230), _record(300, 300, 320, 306, score=np.nan), _record(50, 60, 57, 63)]
    )
    f = features(recs, (10.0, 10.0), geo)
    f[1]["properties"]["sidelobes"] = True
    f[0]["properties"]["sidelobes"] = False  # the third has none: a null in the column
    f[2]["properties"]["note"] = {"a": [1, 2]}
    return json.loads(json.dumps(collection(f, detector="ca_cfar", scene="/data/s.zarr")))


def _geojson(tmp_path: Path, geo=UTM) -> Path:
    p = tmp_path / "detections.geojson"
    p.write_text(json.dumps(_collection(geo)))
    return p


def test_wkb_of_a_polygon_is_iso():
    b = E.polygon_wkb([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 0.0]])
    assert b[:1] == b"\x01" and int.from_bytes(b[1:5], "little") == 3 and int.from_bytes(b[5:9], "little") == 1
    assert int.from_bytes(b[9:13], "little") == 4 and len(b) == 13 + 4 * 16


def test_gpkg_round_trip(tmp_path):
    src = _geojson(tmp_path)
    fc = json.loads(src.read_text())
    dst = tmp_path / "ships.gpkg"
    assert E.export(src, dst) == 3
    assert sorted(os.listdir(tmp_path)) == ["detections.geojson", "ships.gpkg"]  # nothing else left
    info = pyogrio.read_info(dst)
    assert info["driver"] == "GPKG" and info["crs"] == "EPSG:4326" and info["features"] == 3
    assert info["geometry_type"] == "Polygon" and info["layer_name"] == "detections"
    assert info["dataset_metadata"] == {"detector": "ca_cfar", "scene": "/data/s.zarr"}
    meta, _, geoms, fields = pyogrio.raw.read(dst)
    cols = dict(zip(meta["fields"], fields))
    types = dict(zip(meta["fields"], info["ogr_types"]))
    assert list(cols["name"]) == ["ship 1", "ship 2", "ship 3"]
    for i, f in enumerate(fc["features"]):
        p = f["properties"]
        assert [cols["centroid_lon"][i], cols["centroid_lat"][i]] == pytest.approx(p["centroid_lonlat"], abs=1e-12)
        assert [cols[k][i] for k in ("bbox_row0", "bbox_col0", "bbox_row1", "bbox_col1")] == p["bbox_px"]
        assert cols["length_m"][i] == pytest.approx(p["length_m"])
        # the outline: the GeoJSON ring, lon/lat order, from the WKB GDAL stored
        ring = np.frombuffer(geoms[i][13:], "<f8").reshape(-1, 2)
        np.testing.assert_allclose(ring, f["geometry"]["coordinates"][0], rtol=0, atol=1e-12)
    assert types["bbox_row0"] == "OFTInteger" and types["length_m"] == "OFTReal" and types["name"] == "OFTString"
    # score null where the detector had none; sidelobes boolean with a null; nested values as JSON text
    assert np.isnan(cols["score"][1]) and cols["score"][0] == 3.0
    assert cols["sidelobes"][1] and not cols["sidelobes"][0]
    assert json.loads(cols["note"][2]) == {"a": [1, 2]}


def test_kml_placemarks(tmp_path):
    src = _geojson(tmp_path)
    fc = json.loads(src.read_text())
    dst = tmp_path / "ships.kml"
    assert E.export(src, dst) == 3
    root = ET.parse(dst).getroot()
    marks = root.findall(f".//{KML}Placemark")
    assert [m.find(f"{KML}name").text for m in marks] == ["ship 1", "ship 2", "ship 3"]
    for m, f in zip(marks, fc["features"]):
        text = m.find(f".//{KML}Polygon//{KML}coordinates").text.split()
        pts = np.array([[float(v) for v in t.split(",")[:2]] for t in text])
        np.testing.assert_allclose(pts, f["geometry"]["coordinates"][0], rtol=0, atol=1e-9)
        data = {d.get("name"): d.text for d in m.iter(f"{KML}SimpleData")}
        assert float(data["centroid_lat"]) == pytest.approx(f["properties"]["centroid_lonlat"][1], abs=1e-9)
        assert int(data["area_px"]) == f["properties"]["area_px"]
    assert "ca_cfar" in (root.find(f".//{KML}description").text or "")
    assert sorted(os.listdir(tmp_path)) == ["detections.geojson", "ships.kml"]


def test_refusals(tmp_path):
    plain = tmp_path / "plain.geojson"
    plain.write_text(json.dumps(_collection(None)))
    with pytest.raises(InputError, match="not georeferenced"):
        E.export(plain, tmp_path / "x.gpkg")
    with pytest.raises(InputError, match=r"\.gpkg.*\.kml"):
        E.export(_geojson(tmp_path), tmp_path / "x.shp")
    (tmp_path / "bad.geojson").write_text("{nope")
    with pytest.raises(InputError, match="not readable JSON"):
        E.export(tmp_path / "bad.geojson", tmp_path / "x.kml")
    (tmp_path / "list.geojson").write_text("[]")
    with pytest.raises(InputError, match="FeatureCollection"):
        E.export(tmp_path / "list.geojson", tmp_path / "x.kml")
    with pytest.raises(InputError, match="no such folder"):
        E.export(_geojson(tmp_path), tmp_path / "missing" / "x.kml")
    assert not list(tmp_path.glob("x.*")) and not list(tmp_path.glob(".x*"))


def test_missing_extra_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyogrio", None)  # import pyogrio -> ImportError
    with pytest.raises(InputError, match=r"sarship\[gis\]"):
        E.export(_geojson(tmp_path), tmp_path / "x.gpkg")
    assert not (tmp_path / "x.gpkg").exists()


def test_gdal_failure_leaves_nothing(tmp_path, monkeypatch):
    def fail(path, *a, **k):
        Path(path).write_bytes(b"half")  # a partial file, as an interrupted write leaves
        raise RuntimeError("disk full")

    monkeypatch.setattr(pyogrio.raw, "write", fail)
    with pytest.raises(InputError, match="cannot write GPKG.*disk full"):
        E.export(_geojson(tmp_path), tmp_path / "x.gpkg")
    assert sorted(os.listdir(tmp_path)) == ["detections.geojson"]


def test_cli_export_overwrite_rules(tmp_path):
    src = _geojson(tmp_path)
    dst = tmp_path / "ships.gpkg"
    res = sarship("export", src, "--to", dst)
    assert res.returncode == 0, res.stderr
    assert "3 ships" in res.stdout
    before = dst.read_bytes()
    res = sarship("export", src, "--to", dst)
    assert_clean_error(res, "exists", "--overwrite")
    assert dst.read_bytes() == before
    res = sarship("export", src, "--to", dst, "--overwrite")
    assert res.returncode == 0, res.stderr
    assert pyogrio.read_info(dst)["features"] == 3
    plain = tmp_path / "plain.geojson"
    plain.write_text(json.dumps(_collection(None)))
    assert_clean_error(sarship("export", plain, "--to", tmp_path / "p.kml"), "not georeferenced")
    assert_clean_error(sarship("export", src, "--to", tmp_path / "p.csv"), ".gpkg")
    res = sarship("export", src, "--to", tmp_path / "p.kml", env={"PYTHONPATH": str(_no_pyogrio(tmp_path))})
    assert_clean_error(res, "sarship[gis]")
    assert not (tmp_path / "p.kml").exists()


def _no_pyogrio(tmp_path: Path) -> Path:
    """A folder whose ``pyogrio`` package fails to import, first on the path: the extra absent."""
    d = tmp_path / "nogis" / "pyogrio"
    d.mkdir(parents=True)
    (d / "__init__.py").write_text("raise ImportError('pyogrio hidden by the test')\n")
    return d.parent


def test_cli_detect_formats(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.gamma(2.0, 0.5, (96, 80)).astype(np.float32)
    x[40:44, 30:36] += 60.0
    geo = write_scene(tmp_path / "geo.zarr", {"intensity": x}, tile=64, looks=2.0, pixel_spacing_m=[10.0, 10.0], **UTM)
    plain = write_scene(tmp_path / "plain.zarr", {"intensity": x}, tile=64, looks=2.0)
    out = tmp_path / "run"
    res = sarship(
        "detect",
        geo,
        "--detector",
        "ca_cfar",
        "--out",
        out,
        "--formats",
        "geojson,gpkg,kml",
        "--set",
        "min_area_px=2",
        "--set",
        "guard=9",
        "--set",
        "background=21",
    )
    assert res.returncode == 0, res.stderr
    assert {"detections.geojson", "detections.gpkg", "detections.kml"} <= set(os.listdir(out))
    assert not [p for p in os.listdir(out) if p.startswith(".")]
    fc = json.loads((out / "detections.geojson").read_text())
    assert fc["features"] and pyogrio.read_info(out / "detections.gpkg")["features"] == len(fc["features"])
    # refused before any work: unknown format, a scene without georeference
    assert_clean_error(
        sarship("detect", geo, "--detector", "ca_cfar", "--out", tmp_path / "r2", "--formats", "shp"),
        "--formats",
        "shp",
    )
    res = sarship("detect", plain, "--detector", "ca_cfar", "--out", tmp_path / "r3", "--formats", "kml")
    assert_clean_error(res, "not georeferenced")
    assert not (tmp_path / "r2").exists() and not (tmp_path / "r3").exists()


# ------------------------------------------------------------------ AIS fields (docs/ais.md) and the unmatched vessels

AIS = {
    "mmsi": 257996179,
    "name": "SARSHIP 0001",
    "score": 0.999,
    "distance_m": 19.8,
    "dt_s": 0.6,
    "ais_length_m": None,  # a vessel that sent no dimensions
    "displacement_m": 434.6,
}
AIS_TYPES = {
    "ais_mmsi": "OFTInteger",
    "ais_name": "OFTString",
    "ais_score": "OFTReal",
    "ais_distance_m": "OFTReal",
    "ais_dt_s": "OFTReal",
    "ais_length_m": "OFTReal",
    "ais_displacement_m": "OFTReal",
    "dark": "OFTInteger",
}


def _ais_geojson(tmp_path: Path, records=(AIS, None, None), dark=(False, True, None)) -> Path:
    """Three detections as a run with --ais writes them: matched, dark, not covered."""
    fc = _collection()
    for f, a, d in zip(fc["features"], records, dark):
        f["properties"]["ais"], f["properties"]["dark"] = a, d
    p = tmp_path / "detections.geojson"
    p.write_text(json.dumps(fc))
    return p


def _vessel(mmsi, name, lon, lat, length_m=12.0, detectable=True) -> dict:
    props = {
        "mmsi": mmsi,
        "name": name,
        "length_m": length_m,
        "time": 1577836805.376,
        "gap_s": 4.3,
        "extrapolated": False,
        "detectable": detectable,
    }
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon, lat]}, "properties": props}


def _unmatched(tmp_path: Path, feats=None) -> Path:
    if feats is None:
        feats = [
            _vessel(257752068, "SARSHIP S001", 15.51, 54.12),
            _vessel(412966071, None, 15.49, 54.13, length_m=None, detectable=None),
        ]
    p = tmp_path / "ais_unmatched.geojson"
    p.write_text(json.dumps({"type": "FeatureCollection", "features": feats, "scene": "/data/s.zarr"}))
    return p


def _gpkg(dst: Path) -> tuple[dict, dict]:
    info = pyogrio.read_info(dst)
    meta, _, _, fields = pyogrio.raw.read(dst)
    types = {k: (t, st) for k, t, st in zip(info["fields"], info["ogr_types"], info["ogr_subtypes"])}
    return dict(zip(meta["fields"], fields)), types


def test_gpkg_ais_columns_typed_and_null_where_no_match(tmp_path):
    src = _ais_geojson(tmp_path)
    assert E.export(src, tmp_path / "ships.gpkg") == 3
    cols, types = _gpkg(tmp_path / "ships.gpkg")
    assert "ais" not in cols and {k: types[k][0] for k in AIS_TYPES} == AIS_TYPES
    assert types["dark"][1] == "OFSTBoolean"
    assert (int(cols["ais_mmsi"][0]), cols["ais_name"][0]) == (257996179, "SARSHIP 0001")
    assert [cols[f"ais_{k}"][0] for k in ("score", "distance_m", "dt_s", "displacement_m")] == [0.999, 19.8, 0.6, 434.6]
    assert np.isnan(cols["ais_length_m"][0])  # null inside the record
    for k in AIS_TYPES:  # no vessel matched: null
        if k != "dark":
            assert all(v is None or np.isnan(v) for v in cols[k][1:]), k
    assert cols["dark"][0] == 0 and cols["dark"][1] == 1 and np.isnan(cols["dark"][2])  # null: not covered


def test_gpkg_ais_columns_keep_their_types_when_all_null(tmp_path):
    """No detection matched and the AIS did not cover the scene: the columns are still typed."""
    src = _ais_geojson(tmp_path, records=(None, None, None), dark=(None, None, None))
    E.export(src, tmp_path / "ships.gpkg")
    cols, types = _gpkg(tmp_path / "ships.gpkg")
    assert {k: types[k][0] for k in AIS_TYPES} == AIS_TYPES and types["dark"][1] == "OFSTBoolean"
    assert all(np.isnan(v) for v in cols["ais_mmsi"]) and list(cols["ais_name"]) == [None] * 3


def test_kml_ais_extended_data(tmp_path):
    src = _ais_geojson(tmp_path)
    E.export(src, tmp_path / "ships.kml")
    root = ET.parse(tmp_path / "ships.kml").getroot()
    schema = {f.get("name"): f.get("type") for f in root.iter(f"{KML}SimpleField")}
    assert {k: schema[k] for k in AIS_TYPES} == {
        **{k: "double" for k in AIS_TYPES},
        "ais_mmsi": "int",
        "ais_name": "string",
        "dark": "bool",
    }
    data = [{d.get("name"): d.text for d in m.iter(f"{KML}SimpleData")} for m in root.iter(f"{KML}Placemark")]
    assert (data[0]["ais_mmsi"], data[0]["ais_name"], float(data[0]["ais_score"])) == (
        "257996179",
        "SARSHIP 0001",
        0.999,
    )
    assert data[0]["dark"] == "false" and "ais_length_m" not in data[0]  # a null is left out
    assert data[1]["dark"] == "true" and not [k for k in data[1] if k.startswith("ais_")]
    assert "dark" not in data[2]


def test_unmatched_vessels_as_a_point_layer(tmp_path):
    src = _unmatched(tmp_path)
    assert E.export(src, tmp_path / "v.gpkg") == 2
    info = pyogrio.read_info(tmp_path / "v.gpkg")
    assert (info["layer_name"], info["geometry_type"], info["crs"]) == ("ais_unmatched", "Point", "EPSG:4326")
    assert info["dataset_metadata"] == {"scene": "/data/s.zarr"}
    meta, _, geoms, fields = pyogrio.raw.read(tmp_path / "v.gpkg")
    cols = dict(zip(meta["fields"], fields))
    _, types = _gpkg(tmp_path / "v.gpkg")
    assert list(cols["name"]) == ["SARSHIP S001", "MMSI 412966071"]  # the vessel's name, else its MMSI
    assert list(cols["mmsi"]) == [257752068, 412966071] and types["mmsi"][0] == "OFTInteger"
    assert types["detectable"][1] == types["extrapolated"][1] == "OFSTBoolean"
    assert cols["detectable"][0] == 1 and np.isnan(cols["detectable"][1]) and np.isnan(cols["length_m"][1])
    assert cols["time"][0] == 1577836805.376 and cols["gap_s"][1] == 4.3
    assert [struct_point(g) for g in geoms] == [(15.51, 54.12), (15.49, 54.13)]
    assert E.export(src, tmp_path / "v.kml") == 2
    root = ET.parse(tmp_path / "v.kml").getroot()
    marks = root.findall(f".//{KML}Placemark")
    assert [m.find(f"{KML}name").text for m in marks] == ["SARSHIP S001", "MMSI 412966071"]
    pt = marks[0].find(f".//{KML}Point/{KML}coordinates").text.split(",")
    assert (float(pt[0]), float(pt[1])) == (15.51, 54.12)
    data = {d.get("name"): d.text for d in marks[0].iter(f"{KML}SimpleData")}
    assert data["mmsi"] == "257752068" and data["detectable"] == "true"
    assert root.find(f".//{KML}Document/{KML}name").text == "sarship AIS vessels unmatched"


def struct_point(wkb: bytes) -> tuple[float, float]:
    assert wkb[:1] == b"\x01" and int.from_bytes(wkb[1:5], "little") == 1
    x, y = np.frombuffer(wkb[5:21], "<f8")
    return float(x), float(y)


def test_point_layer_edge_cases(tmp_path):
    empty = _unmatched(tmp_path, feats=[])  # every reporting vessel matched: an empty Point layer
    assert E.export(empty, tmp_path / "e.gpkg") == 0
    info = pyogrio.read_info(tmp_path / "e.gpkg")
    assert (info["layer_name"], info["geometry_type"], info["features"]) == ("ais_unmatched", "Point", 0)
    fc = _collection()
    fc["features"].append(_vessel(257752068, "X", 15.5, 54.1))
    mixed = tmp_path / "mixed.geojson"
    mixed.write_text(json.dumps(fc))
    with pytest.raises(InputError, match="mixes Polygon and Point"):
        E.export(mixed, tmp_path / "m.gpkg")
    bad = _vessel(257752068, "X", 15.5, 54.1)
    bad["geometry"]["coordinates"] = []
    with pytest.raises(InputError, match="Point geometry"):
        E.export(_unmatched(tmp_path, feats=[bad]), tmp_path / "b.kml")
    line = {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}, "properties": {}}
    with pytest.raises(InputError, match="LineString geometry; Polygon"):
        E.export(_unmatched(tmp_path, feats=[line]), tmp_path / "b.kml")
    assert not list(tmp_path.glob("[mb].*")) and not list(tmp_path.glob(".[mb]*"))


def test_cli_export_unmatched(tmp_path):
    src = _unmatched(tmp_path)
    res = sarship("export", src, "--to", tmp_path / "v.kml")
    assert res.returncode == 0, res.stderr
    assert "2 vessels" in res.stdout and len(ET.parse(tmp_path / "v.kml").getroot().findall(f".//{KML}Placemark")) == 2


# ------------------------------------------------------------------ the STAC item names the source product


SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
GRD_NAME = "S1B_IW_GRDH_1SDV_20210401T052623_20210401T052648_026269_032297_ECC8"


def _safe_attrs(product=GRD_NAME, **extra) -> dict:
    """A SAFE scene's attributes as pipeline/readers/safe.py writes them."""
    return {
        "product": product,
        "sensor": "SENTINEL-1B",
        "mode": "IW",
        "product_type": "GRD (GRDH)",
        "acquired": "2021-04-01T05:26:23.794457",
        "acquisition_start": "2021-04-01T05:26:23.794457",
        "acquisition_stop": "2021-04-01T05:26:48.793373",
        "orbit_pass": "DESCENDING",
        "polarisations": ["vv"],
        "looks": 4.4,
        "pixel_spacing_m": [10.0, 10.0],
        "pixel_spacing_source": "SAFE annotation imageInformation azimuthPixelSpacing, rangePixelSpacing",
        "gcps": [
            {"row": r, "col": c, "x": 10.0 + c * 1e-4, "y": 46.0 - r * 1e-4, "z": 0.0}
            for r in (0.0, 500.0)
            for c in (0.0, 800.0)
        ],
        **extra,
    }


def test_stac_item_carries_the_product_identifiers(tmp_path):
    from sarship.service import stac

    run = {
        "scene": {"path": str(tmp_path / "s1.zarr"), "shape": [500, 800], "attrs": _safe_attrs()},
        "detector": "ca_cfar",
        "parameters": {"pfa": 1e-5},
        "channel": "intensity",
    }
    item = stac.stac_item({"id": "j1"}, run, "http://h", tmp_path, "2026-11-26T12:00:00Z")
    p = item["properties"]
    assert stac.SAT_EXT in item["stac_extensions"] and stac.SAR_EXT in item["stac_extensions"]
    assert (p["platform"], p["constellation"], p["instruments"]) == ("sentinel-1b", "sentinel-1", ["c-sar"])
    assert p["sarship:source_product"] == GRD_NAME and p["sarship:datatake_id"] == 0x032297
    assert (p["sat:orbit_state"], p["sat:absolute_orbit"], p["sat:relative_orbit"]) == ("descending", 26269, 168)
    assert p["start_datetime"] == "2021-04-01T05:26:23.794457Z" and p["end_datetime"] == "2021-04-01T05:26:48.793373Z"
    assert p["datetime"] == p["start_datetime"]
    assert (p["sar:instrument_mode"], p["sar:polarizations"], p["sar:frequency_band"]) == ("IW", ["VV"], "C")
    assert p["sar:product_type"] == "GRD"  # the reader's "GRD (GRDH)"
    assert item["geometry"]["type"] == "Polygon"
    json.dumps(item, allow_nan=False)
    # attributes win over the name; S1A's relative orbit; an SLC sub-swath
    f, _ = stac.product_fields(
        _safe_attrs(
            "S1A_IW_SLC__1SDV_20160606T221231_20160606T221258_011596_011B8A_3FF3",
            sensor="SENTINEL-1A",
            swath="IW2",
            relative_orbit=5,
        )
    )
    assert f["sat:absolute_orbit"] == 11596 and f["sat:relative_orbit"] == 5 and f["sarship:swath"] == "IW2"
    f, _ = stac.product_fields(
        _safe_attrs("S1A_IW_SLC__1SDV_20160606T221231_20160606T221258_011596_011B8A_3FF3", sensor="SENTINEL-1A")
    )
    assert f["sat:relative_orbit"] == 149  # the product's REL_ORBIT (OpenSARShip's SNAP metadata of this product)
    assert f["sarship:datatake_id"] == 72586
    # not a Sentinel-1 product: nothing claimed
    assert stac.product_fields({"sensor": "sarship-simulator", "product": "x"}) == ({}, [])
    f, ext = stac.product_fields({"sensor": "SENTINEL-1A IW"})  # a SNAP GeoTIFF: the unit, no orbit
    assert f["platform"] == "sentinel-1a" and "sat:absolute_orbit" not in f and ext == []


@pytest.mark.skipif(not SAFE_DIR.is_dir(), reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
@pytest.mark.parametrize("pattern", ["S1B_IW_GRDH_*.SAFE", "S1B_IW_SLC_*.SAFE"])
def test_product_fields_agree_with_the_manifest(pattern):
    """Orbit numbers, datatake and pass derived from the name agree with the real manifest."""
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    import xarray as xr

    from sarship.service import stac

    product = next(iter(sorted(SAFE_DIR.glob(pattern))))
    root = xr.open_dataset(product, engine="sentinel-1").attrs
    f, _ = stac.product_fields(
        {
            "product": product.name.removesuffix(".SAFE"),
            "orbit_pass": root["pass"],
            "sensor": f"{root['family_name']}{root['number']}",
        }
    )
    assert f["sat:absolute_orbit"] == root["orbit_number"]
    assert f["sat:relative_orbit"] == root["relative_orbit_number"]
    assert f["sarship:datatake_id"] == root["mission_data_take_id"]
    assert f["sat:orbit_state"] == root["pass"].lower() and f["platform"] == f"sentinel-1{root['number'].lower()}"


# ------------------------------------------------------------------ the service offers them too


def test_service_results_offer_gpkg_and_kml(tmp_path, tmp_path_factory):
    """``/jobs/{id}/results`` links ``detections-gpkg`` / ``detections-kml`` for a georeferenced
    scene (``/results/detections?f=gpkg|kml``, built once, cached), not for one without."""
    httpx = pytest.importorskip("httpx")
    from svc import check_problem, shared_server, wait_job  # (svc, as the other modules import it: one shared server)

    # the test process's shared server, with this test's scenes (names of their own) in its folder
    srv = shared_server(tmp_path_factory.getbasetemp())
    data = srv.data
    rng = np.random.default_rng(1)
    x = rng.gamma(2.0, 0.5, (160, 140)).astype(np.float32)
    x[40:44, 30:40] += 60.0
    x[100:110, 90:93] += 60.0
    write_scene(
        data / "scenes" / "exp_geo.zarr", {"intensity": x}, tile=80, looks=2.0, pixel_spacing_m=[10.0, 10.0], **UTM
    )
    write_scene(data / "scenes" / "exp_plain.zarr", {"intensity": x}, tile=80, looks=2.0)
    u = srv.url + "/processes/ca_cfar/execution"
    body = {"guard": 9, "background": 21, "min_area_px": 2}
    jobs = {k: httpx.post(u, json={"inputs": {"scene": f"exp_{k}", **body}}).json()["jobID"] for k in ("geo", "plain")}
    for j in jobs.values():
        assert wait_job(srv.url, j)["status"] == "successful"
    res = httpx.get(f"{srv.url}/jobs/{jobs['geo']}/results").json()
    assert res["detections-gpkg"]["type"] == "application/geopackage+sqlite3"
    assert res["detections-kml"]["type"] == "application/vnd.google-earth.kml+xml"
    fc = httpx.get(res["detections"]["href"]).json()
    assert len(fc["features"]) == 2
    g = httpx.get(res["detections-gpkg"]["href"])
    assert g.status_code == 200 and g.headers["content-type"] == "application/geopackage+sqlite3"
    (tmp_path / "d.gpkg").write_bytes(g.content)
    assert pyogrio.read_info(tmp_path / "d.gpkg")["features"] == 2
    k = httpx.get(res["detections-kml"]["href"])
    assert k.status_code == 200 and k.headers["content-type"].startswith("application/vnd.google-earth.kml+xml")
    assert len(ET.fromstring(k.content).findall(f".//{KML}Placemark")) == 2
    assert (data / "jobs" / jobs["geo"] / "detections.gpkg").is_file()  # cached in the job folder
    assert httpx.get(res["detections-gpkg"]["href"], headers={"If-None-Match": g.headers["etag"]}).status_code == 304
    plain = httpx.get(f"{srv.url}/jobs/{jobs['plain']}/results").json()
    assert "detections-gpkg" not in plain and "detections-kml" not in plain
    check_problem(httpx.get(plain["detections"]["href"] + "?f=kml"), 404, "not georeferenced")
    check_problem(httpx.get(res["detections"]["href"] + "?f=shp"), 400, "'f'")
