"""AIS scores of ``sarship evaluate`` (issue 33; pipeline/products/scoring.py, docs/interfaces/files.md "Scores").

Hand-built truth and detections, one hit of each kind (matched to the ship's own MMSI, to
another's, unmatched, called dark rightly and wrongly, a dark ship matched, a dark ship with the
coverage unknown) beside detections that are no hits (false alarms, on a difficult ship) and a
missed ship, whose counts are worked out by hand; every 0/0 (null) and when the scores are absent;
aggregation; bad values refused in one line. Then one small simulated scene (moving ships, AIS,
dark ships) through ``sarship detect --ais --formats gpkg,kml`` and ``sarship evaluate``: the
command's scores against an independent count of the same hits, and the GeoPackage / KML of the
run carrying the AIS fields.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.products.scoring import AIS_COUNTS, aggregate, evaluate, format_scores, match, score
from sarship.pipeline.products.truth import Ship, write_geojson
from sarship.pipeline.simulate import SimConfig, simulate
from tests.cli.test_cli import assert_clean_error, sarship, sarship_here

SCORES = ("ais_precision", "ais_recall", "dark_precision", "dark_recall")
RECORD = {"name": "V", "score": 0.9, "distance_m": 12.0, "dt_s": 1.0, "ais_length_m": 50.0, "displacement_m": 0.0}


def truth_ship(k: int, mmsi: int | None, **props) -> Ship:
    """Truth ship ``k``: a 10 x 10 box on a diagonal, far from every other."""
    props.setdefault("dark", mmsi is None)
    return Ship.from_bbox((100 * k, 100 * k, 100 * k + 10, 100 * k + 10), mmsi=mmsi, **props)


def det(k: int, mmsi: int | None, dark: bool | None) -> Ship:
    """A detection on truth ship ``k``'s box (an empty place for ``k`` beyond the truth)."""
    ais = None if mmsi is None else {"mmsi": mmsi, **RECORD}
    return Ship.from_bbox((100 * k + 1, 100 * k + 1, 100 * k + 9, 100 * k + 9), ais=ais, dark=dark)


def ais_part(s: dict) -> dict:
    return {k: s[k] for k in (*AIS_COUNTS, *SCORES)}


# ----------------------------------------------------------------------------- hand-built cases


def test_every_case_counted_by_hand():
    truth = [
        truth_ship(0, 111111111),  # reporting, matched to its own MMSI
        truth_ship(1, 222222222),  # reporting, matched to another vessel's MMSI
        truth_ship(2, 333333333),  # reporting, unmatched and called dark (wrongly)
        truth_ship(3, 444444444),  # reporting, unmatched, coverage unknown (dark null)
        truth_ship(4, None),  # dark, called dark
        truth_ship(5, None),  # dark, matched to a vessel (wrongly)
        truth_ship(6, None),  # dark, coverage unknown
        truth_ship(7, 777777777),  # reporting, missed: not a hit, counts nowhere
        truth_ship(8, 888888888, difficult=True),  # a detection on it is ignored, not a hit
        truth_ship(9, 999999999, dark=True),  # an MMSI known but silent: dark, called dark
    ]
    dets = [
        det(0, 111111111, False),
        det(1, 999999999, False),
        det(2, None, True),
        det(3, None, None),
        det(4, None, True),
        det(5, 222222222, False),
        det(6, None, None),
        det(8, 888888888, False),
        det(9, None, True),
        det(20, 123456789, False),  # false alarms: matched, called dark: not hits, count nowhere
        det(21, None, True),
    ]
    s = score(dets, truth)
    assert (s["n_hit"], s["n_false"], s["n_ignored"], s["n_missed"]) == (8, 2, 1, 1)
    assert ais_part(s) == {
        "n_ais_matched": 3,  # ships 0, 1, 5
        "n_ais_correct": 1,  # ship 0
        "n_ais_reporting": 4,  # ships 0-3
        "n_ais_found": 1,
        "n_dark_called": 3,  # ships 2, 4, 9
        "n_dark_correct": 2,  # 4, 9
        "n_dark_ships": 4,  # 4, 5, 6, 9
        "n_dark_found": 2,
        "ais_precision": pytest.approx(1 / 3),
        "ais_recall": 0.25,
        "dark_precision": pytest.approx(2 / 3),
        "dark_recall": 0.5,
    }
    # the hits are scoring.match's: the same pairs
    assert [d for d, t in match(dets, truth) if not truth[t].difficult] == list(range(7)) + [8]


def test_perfect_run():
    truth = [truth_ship(0, 111111111), truth_ship(1, None), truth_ship(2, 222222222)]
    dets = [det(0, 111111111, False), det(1, None, True), det(2, 222222222, False)]
    s = score(dets, truth)
    assert [s[k] for k in SCORES] == [1.0, 1.0, 1.0, 1.0]
    lines = format_scores(s).splitlines()
    assert lines[-2] == (
        "ais: precision 1.0000 (2 of 2 matched hits: own MMSI)   recall 1.0000 (2 of 2 detected reporting ships: own MMSI)"
    )
    assert lines[-1].startswith("dark: precision 1.0000 (1 of 1 hits called dark: dark ships)   recall 1.0000")


def test_zero_over_zero_is_null():
    # no hit at all (a false alarm only): all four undefined, the counts 0
    s = score([det(5, 111111111, False)], [truth_ship(0, 111111111)])
    assert [s[k] for k in SCORES] == [None] * 4 and all(s[k] == 0 for k in AIS_COUNTS)
    assert json.loads(json.dumps(s, allow_nan=False))["ais_precision"] is None
    assert "ais: precision n/a (0 of 0" in format_scores(s)
    # only reporting ships, all matched: nothing called dark, no dark ship detected
    s = score([det(0, 111111111, False)], [truth_ship(0, 111111111), truth_ship(1, None)])
    assert [s[k] for k in SCORES] == [1.0, 1.0, None, None]
    # only dark ships, called dark: no detection matched, no reporting ship detected
    s = score([det(0, None, True)], [truth_ship(0, None)])
    assert [s[k] for k in SCORES] == [None, None, 1.0, 1.0]
    # the AIS did not cover the scene (dark null everywhere): nothing called dark, dark ships not found
    s = score([det(0, None, None), det(1, None, None)], [truth_ship(0, 111111111), truth_ship(1, None)])
    assert [s[k] for k in SCORES] == [None, 0.0, None, 0.0]


def test_absent_without_mmsis_or_ais():
    plain_truth = [Ship.from_bbox((0, 0, 10, 10))]
    s = score([det(0, 111111111, False)], plain_truth)  # truth without MMSIs (VOC, masks, plain GeoJSON)
    assert not set(s) & {*AIS_COUNTS, *SCORES}
    s = score([Ship.from_bbox((1, 1, 9, 9))], [truth_ship(0, 111111111)])  # a run without --ais
    assert not set(s) & {*AIS_COUNTS, *SCORES}
    assert "ais:" not in format_scores(s)
    s = score([], [truth_ship(0, 111111111)])  # no detection: nothing carries 'ais'
    assert "ais_precision" not in s
    # present as soon as one side has the key, null values included
    s = score([det(0, None, None)], [truth_ship(0, None)])
    assert s["dark_recall"] == 0.0 and s["ais_precision"] is None


def test_dark_defaults_to_a_null_mmsi_and_mmsis_as_text():
    truth = [
        Ship.from_bbox((0, 0, 10, 10), mmsi=None),
        Ship.from_bbox((100, 100, 110, 110), mmsi="222222222"),
    ]
    s = score([det(0, None, True), det(1, 222222222, False)], truth)
    assert [s[k] for k in SCORES] == [1.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize(
    "truth_props, det_props, words",
    [
        ({"mmsi": "abc"}, {"ais": None}, ("truth ship 1", "mmsi")),
        ({"mmsi": True}, {"ais": None}, ("truth ship 1", "mmsi")),
        ({"mmsi": 1, "dark": "yes"}, {"ais": None}, ("truth ship 1", "dark")),
        ({"mmsi": 1}, {"ais": 5}, ("detection 1", "'ais'")),
        ({"mmsi": 1}, {"ais": {"name": "x"}}, ("detection 1", "'ais'")),
        ({"mmsi": 1}, {"ais": {"mmsi": [1]}}, ("detection 1", "mmsi")),
        ({"mmsi": 1}, {"ais": None, "dark": 1}, ("detection 1", "dark")),
    ],
)
def test_bad_values_refused_in_one_line(tmp_path, truth_props, det_props, words):
    with pytest.raises(InputError) as err:
        score([Ship.from_bbox((1, 1, 9, 9), **det_props)], [Ship.from_bbox((0, 0, 10, 10), **truth_props)])
    assert "\n" not in str(err.value) and all(w in str(err.value) for w in words)
    write_geojson(tmp_path / "t.geojson", [Ship.from_bbox((0, 0, 10, 10), **truth_props)])
    write_geojson(tmp_path / "d.geojson", [Ship.from_bbox((1, 1, 9, 9), **det_props)])
    assert_clean_error(sarship_here("evaluate", tmp_path / "d.geojson", "--truth", tmp_path / "t.geojson"), *words)


def test_aggregate_sums_the_counts():
    a = score([det(0, 111111111, False), det(1, None, True)], [truth_ship(0, 111111111), truth_ship(1, None)])
    b = score([det(0, 999999999, False), det(1, None, False)], [truth_ship(0, 111111111), truth_ship(1, None)])
    c = score([Ship.from_bbox((1, 1, 9, 9))], [Ship.from_bbox((0, 0, 10, 10))])  # an image without AIS
    tot = aggregate([a, b, c])
    assert tot["n_images"] == 3 and tot["n_images_ais"] == 2
    assert (tot["n_ais_matched"], tot["n_ais_correct"], tot["n_dark_ships"], tot["n_dark_found"]) == (2, 1, 2, 1)
    assert [tot[k] for k in SCORES] == [0.5, 0.5, 1.0, 0.5]
    assert "n_images_ais" not in aggregate([c]) and "ais_precision" not in aggregate([c])


def test_evaluate_files_and_json(tmp_path):
    truth = [truth_ship(0, 111111111), truth_ship(1, None)]
    write_geojson(tmp_path / "t.geojson", truth)
    write_geojson(tmp_path / "d.geojson", [det(0, 111111111, False), det(1, 222222222, False)])
    s = evaluate(tmp_path / "d.geojson", tmp_path / "t.geojson")
    assert [s[k] for k in SCORES] == [0.5, 1.0, None, 0.0]
    res = sarship_here("evaluate", tmp_path / "d.geojson", "--truth", tmp_path / "t.geojson", "--json")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert [out[k] for k in SCORES] == [0.5, 1.0, None, 0.0] and out["n_ais_matched"] == 2


# ----------------------------------------------------------------------------- a simulated scene, end to end

SCENE = dict(
    shape=(512, 512),
    ships=12,
    seed=5,
    looks=4.0,
    scr_db=18.0,
    geo=(5.5, 56.5),
    moving=True,
    ais=True,
    dark_fraction=0.3,
)


@pytest.fixture(scope="module")
def ais_run(tmp_path_factory):
    pytest.importorskip("pyogrio", reason="pyogrio not installed (pip install 'sarship[gis]')")
    tmp = tmp_path_factory.mktemp("ais_scores")
    scene = tmp / "s.zarr"
    simulate(scene, SimConfig(**SCENE), tile=512, ais_path=tmp / "ais.csv")
    res = sarship_here(
        "detect",
        scene,
        "--detector",
        "ca_cfar",
        "--ais",
        tmp / "ais.csv",
        "--formats",
        "gpkg,kml",
        "--out",
        tmp / "run",
    )
    assert res.returncode == 0, res.stderr
    return tmp


def _expected(truth: dict, feats: list[dict]) -> dict:
    """The four scores counted here: a hit is a detection whose centroid lies in a ship's box."""
    ships = [f["properties"] for f in truth["features"]]
    hits = matched = correct = reporting = found = called = called_ok = dark = dark_found = 0
    for f in feats:
        p = f["properties"]
        r, c = p["centroid_px"]
        hit = [t for t in ships if t["bbox_px"][0] <= r < t["bbox_px"][2] and t["bbox_px"][1] <= c < t["bbox_px"][3]]
        assert len(hit) <= 1
        if not hit:
            continue
        t = hit[0]
        hits += 1
        own = p["ais"] is not None and p["ais"]["mmsi"] == t["mmsi"]
        matched += p["ais"] is not None
        correct += own
        reporting += t["mmsi"] is not None
        found += own and t["mmsi"] is not None
        called += p["dark"] is True
        called_ok += p["dark"] is True and t["dark"]
        dark += t["dark"]
        dark_found += t["dark"] and p["dark"] is True
    assert matched and called, "the scene must have matched and dark detections"
    return {
        "n_hit": hits,
        "ais_precision": correct / matched,
        "ais_recall": found / reporting,
        "dark_precision": called_ok / called,
        "dark_recall": dark_found / dark,
    }


def test_evaluate_command_on_a_simulated_run(ais_run):
    tmp = ais_run
    det, truth = tmp / "run" / "detections.geojson", tmp / "s.zarr.truth.geojson"
    res = sarship("evaluate", det, "--truth", truth, "--json")  # a real process for the command
    assert res.returncode == 0, res.stderr
    s = json.loads(res.stdout)
    feats = json.loads(det.read_text())["features"]
    exp = _expected(json.loads(truth.read_text()), feats)
    assert {k: s[k] for k in ("n_hit", *SCORES)} == pytest.approx(exp)
    assert s["n_dark_ships"] >= 2 and s["n_ais_reporting"] >= 5  # both kinds detected
    assert s["ais_precision"] >= 0.98 and s["ais_recall"] >= 0.95 and s["dark_recall"] >= 0.95, s
    text = sarship_here("evaluate", det, "--truth", truth)
    assert text.returncode == 0 and "ais: precision" in text.stdout and "dark: precision" in text.stdout


def test_the_run_gpkg_and_kml_carry_the_ais_fields(ais_run):
    import xml.etree.ElementTree as ET

    import pyogrio

    tmp = ais_run
    feats = json.loads((tmp / "run" / "detections.geojson").read_text())["features"]
    meta, _, _, fields = pyogrio.raw.read(tmp / "run" / "detections.gpkg")
    cols = dict(zip(meta["fields"], fields))
    for i, f in enumerate(feats):
        a, dark = f["properties"]["ais"], f["properties"]["dark"]
        assert bool(cols["dark"][i]) is dark
        if a is None:
            assert np.isnan(cols["ais_mmsi"][i]) and cols["ais_name"][i] is None
        else:
            assert (int(cols["ais_mmsi"][i]), cols["ais_name"][i]) == (a["mmsi"], a["name"])
            assert cols["ais_displacement_m"][i] == pytest.approx(a["displacement_m"])
    kml = "{http://www.opengis.net/kml/2.2}"
    marks = ET.parse(tmp / "run" / "detections.kml").getroot().findall(f".//{kml}Placemark")
    got = [{d.get("name"): d.text for d in m.iter(f"{kml}SimpleData")}.get("ais_mmsi") for m in marks]
    assert got == [None if f["properties"]["ais"] is None else str(f["properties"]["ais"]["mmsi"]) for f in feats]
    # the vessels left unmatched, as a Point layer
    unmatched = json.loads((tmp / "run" / "ais_unmatched.geojson").read_text())["features"]
    res = sarship_here("export", tmp / "run" / "ais_unmatched.geojson", "--to", tmp / "unmatched.gpkg")
    assert res.returncode == 0, res.stderr
    info = pyogrio.read_info(tmp / "unmatched.gpkg")
    assert (info["layer_name"], info["geometry_type"], info["features"]) == ("ais_unmatched", "Point", len(unmatched))
