"""Scores and truth readers: hand-built matching cases, arithmetic, 0/0 cases, file formats."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.products.scoring import aggregate, evaluate, format_scores, match, score
from sarship.pipeline.products.truth import (
    Ship,
    detections_scene,
    load_detections,
    load_ships,
    load_voc,
    load_voc_folder,
    read_mask,
    ships_from_mask,
    write_geojson,
)

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
SSDD = REAL / "sar-ship-dataset"
HRSID_MASKS = REAL / "hrsid" / "masks"


def box(r0, c0, r1, c1, difficult=False):
    return Ship.from_bbox((r0, c0, r1, c1), difficult=difficult)


def ship(bbox, centroid, difficult=False):
    return Ship(tuple(float(v) for v in bbox), tuple(float(v) for v in centroid), difficult)


# ----------------------------------------------------------------------------- matching rules


def test_centroid_in_box_matches_without_iou():
    truth = [box(0, 0, 10, 10)]
    # a huge detection box (IoU = 100/10000 = 0.01) whose centroid lies inside the truth box
    det = [ship((0, 0, 100, 100), (5.0, 5.0))]
    assert match(det, truth) == [(0, 0)]
    # same box, centroid outside the truth box: no match
    det = [ship((0, 0, 100, 100), (50.0, 50.0))]
    assert match(det, truth) == []


def test_centroid_half_open_edges():
    truth = [box(0, 0, 10, 10)]
    tiny = (0, 0, 0.5, 0.5)  # negligible IoU: only the centroid rule can match
    assert match([ship(tiny, (0.0, 0.0))], truth) == [(0, 0)]  # row0/col0 inclusive
    assert match([ship(tiny, (9.999, 9.999))], truth) == [(0, 0)]
    assert match([ship(tiny, (10.0, 5.0))], truth) == []  # row1 exclusive
    assert match([ship(tiny, (5.0, 10.0))], truth) == []  # col1 exclusive


def test_iou_threshold_exactly_point_one():
    truth = [box(0, 0, 10, 10)]  # area 100
    # det cols [8, 20): inter 10*2 = 20, union 100 + 120 - 20 = 200 -> IoU = 0.1 exactly;
    # its centroid (5, 14) lies outside the truth box, so only IoU can match it
    det = [box(0, 8, 10, 20)]
    assert det[0].centroid == (5.0, 14.0)
    assert match(det, truth) == [(0, 0)]
    # det cols [8, 21): inter 20, union 210 -> IoU 0.0952 < 0.1: no match
    assert match([box(0, 8, 10, 21)], truth) == []
    # slightly above 0.1: det cols [8, 19): 20 / 190 = 0.105
    assert match([box(0, 8, 10, 19)], truth) == [(0, 0)]


def test_one_to_one_two_detections_on_one_ship():
    truth = [box(10, 10, 30, 20)]
    dets = [box(10, 10, 30, 20), box(12, 11, 28, 19)]
    assert match(dets, truth) == [(0, 0)]  # the higher IoU wins
    s = score(dets, truth)
    assert (s["n_hit"], s["n_false"], s["n_missed"], s["n_detections"]) == (1, 1, 0, 2)


def test_greedy_highest_iou_first():
    # d0 overlaps t0 (IoU 0.5) and t1 (IoU 0.6); d1 overlaps only t1 (IoU 0.3).
    t0, t1 = box(0, 0, 10, 10), box(0, 10, 10, 20)
    d0 = box(0, 5, 10, 17)  # IoU with t0: 50/170; with t1: 70/170
    d1 = box(0, 13, 10, 33)  # IoU with t1: 70/(100+200-70) = 0.304
    dets, truth = [d0, d1], [t0, t1]
    # greedy (not optimal assignment): d0-t1 (0.41) is taken first, then d1 has nothing left
    # and t0 is left to ... d0 is used, so t0 is missed.
    assert match(dets, truth) == [(0, 1)]
    s = score(dets, truth)
    assert (s["n_hit"], s["n_false"], s["n_missed"]) == (1, 1, 1)


def test_centroid_only_pairs_ordered_by_distance_after_iou_pairs():
    truth = [box(0, 0, 20, 20)]
    far = ship((0, 0, 0.1, 0.1), (1.0, 1.0))  # centroid-only, 13.4 px from the centre
    near = ship((0, 0, 0.1, 0.1), (9.0, 9.0))  # centroid-only, 1.4 px from the centre
    assert match([far, near], truth) == [(1, 0)]
    overlap = box(5, 15, 25, 35)  # IoU 75/725 = 0.103, centroid outside: an IoU pair
    assert match([near, overlap], truth) == [(1, 0)]  # IoU pairs come before centroid-only ones


def test_match_is_deterministic_on_ties():
    truth = [box(0, 0, 10, 10)]
    dets = [box(0, 0, 10, 10), box(0, 0, 10, 10)]
    assert match(dets, truth) == [(0, 0)]
    assert match(list(reversed(dets)), truth) == [(0, 0)]


def test_many_objects_vectorised_pairs():
    rng = np.random.default_rng(0)
    r = rng.integers(0, 2000, 700)
    c = rng.integers(0, 2000, 700)
    truth = [box(a, b, a + 8, b + 4) for a, b in zip(r.tolist(), c.tolist())]
    dets = [box(a + 1, b, a + 9, b + 4) for a, b in zip(r.tolist(), c.tolist())]
    s = score(dets, truth)
    assert s["n_hit"] >= 690  # overlapping random ships can steal a few
    assert s["n_hit"] + s["n_false"] == 700


# ----------------------------------------------------------------------------- difficult


def test_difficult_truth_is_neither_missed_nor_false_alarm():
    truth = [box(0, 0, 10, 10), box(50, 50, 60, 60, difficult=True), box(100, 100, 110, 110, difficult=True)]
    dets = [box(0, 0, 10, 10), box(50, 50, 60, 60)]  # the second difficult ship is not detected
    s = score(dets, truth)
    assert s["n_truth"] == 1 and s["n_difficult"] == 2
    assert s["n_ignored"] == 1
    assert s["n_detections"] == 1  # the detection on the difficult ship is not counted
    assert (s["n_hit"], s["n_false"], s["n_missed"]) == (1, 0, 0)
    assert s["pd"] == s["precision"] == s["fom"] == s["f1"] == 1.0


def test_second_detection_on_difficult_ship_is_false_alarm():
    truth = [box(50, 50, 60, 60, difficult=True)]
    dets = [box(50, 50, 60, 60), box(51, 51, 59, 59)]
    s = score(dets, truth)
    assert (s["n_ignored"], s["n_detections"], s["n_hit"], s["n_false"]) == (1, 1, 0, 1)


def test_ordinary_ship_matched_before_difficult_one():
    # d0 overlaps a difficult ship better (IoU 1) than an ordinary one (IoU 0.25);
    # d1 overlaps only the difficult ship: best outcome is d0 -> ordinary, d1 -> difficult.
    ordinary = box(0, 0, 10, 10)
    hard = box(0, 6, 10, 16, difficult=True)
    d0 = box(0, 6, 10, 16)
    d1 = box(0, 10, 10, 20)
    assert match([d0, d1], [ordinary, hard]) == [(0, 0), (1, 1)]
    s = score([d0, d1], [ordinary, hard])
    assert (s["n_hit"], s["n_false"], s["n_missed"], s["n_ignored"]) == (1, 0, 0, 1)
    # a single greedy pass would spend d0 on the difficult ship and miss the ordinary one
    assert match([d0, d1], [ordinary, hard], difficult_last=False) == [(0, 1)]


# ----------------------------------------------------------------------------- arithmetic


def test_score_arithmetic():
    truth = [box(10 * i, 0, 10 * i + 5, 5) for i in range(5)]  # 5 ships
    dets = [box(10 * i, 0, 10 * i + 5, 5) for i in range(3)]  # 3 hits
    dets += [box(200, 200, 205, 205), box(300, 300, 305, 305)]  # 2 false alarms
    s = score(dets, truth)
    assert (s["n_truth"], s["n_detections"], s["n_hit"], s["n_false"], s["n_missed"]) == (5, 5, 3, 2, 2)
    assert s["pd"] == pytest.approx(3 / 5)
    assert s["precision"] == pytest.approx(3 / 5)
    assert s["fom"] == pytest.approx(3 / 7)
    p, r = 3 / 5, 3 / 5
    assert s["f1"] == pytest.approx(2 * p * r / (p + r))


def test_thesis_fom_figure():
    # thesis (docs/references.md#sun2020) table 2.2: 118 ships, 117 detected, 6 false alarms -> FoM 0.943
    truth = [box(20 * i, 0, 20 * i + 5, 5) for i in range(118)]
    dets = [box(20 * i, 0, 20 * i + 5, 5) for i in range(117)]
    dets += [box(5000 + 20 * i, 5000, 5000 + 20 * i + 5, 5005) for i in range(6)]
    s = score(dets, truth)
    assert s["fom"] == pytest.approx(117 / 124)  # 0.9435, quoted (truncated) as 0.943
    assert abs(s["fom"] - 0.943) < 1e-3


def test_f1_is_harmonic_mean():
    truth = [box(10 * i, 0, 10 * i + 5, 5) for i in range(4)]
    dets = [box(0, 0, 5, 5), box(500, 0, 505, 5), box(600, 0, 605, 5)]
    s = score(dets, truth)
    p, r = 1 / 3, 1 / 4
    assert s["f1"] == pytest.approx(2 * p * r / (p + r))


def test_zero_over_zero_cases_are_finite():
    s = score([], [])
    assert (s["pd"], s["precision"], s["fom"], s["f1"]) == (1.0, 1.0, 1.0, 1.0)
    s = score([box(0, 0, 5, 5)], [])  # false alarms on an empty scene
    assert (s["pd"], s["precision"], s["fom"], s["f1"]) == (1.0, 0.0, 0.0, 0.0)
    s = score([], [box(0, 0, 5, 5)])  # nothing detected
    assert (s["pd"], s["precision"], s["fom"], s["f1"]) == (0.0, 1.0, 0.0, 0.0)
    s = score([], [box(0, 0, 5, 5, difficult=True)])  # only a difficult ship
    assert s["n_truth"] == 0 and s["pd"] == 1.0 and s["fom"] == 1.0
    empty = np.zeros((4, 4), bool)
    s = score([], [], det_mask=empty, truth_mask=empty)
    assert (s["tpr"], s["fpr"]) == (1.0, 0.0)
    for s in (score([], []), aggregate([]), aggregate([score([], [])])):
        json.dumps(s, allow_nan=False)
        assert all(math.isfinite(v) for v in s.values() if isinstance(v, float))


def test_pixel_tpr_fpr():
    t = np.zeros((10, 10), bool)
    t[2:4, 2:7] = True  # 10 ship pixels, 90 clutter
    d = np.zeros((10, 10), np.uint8)
    d[2:4, 2:5] = 1  # 6 true pixels
    d[8, 0:3] = 1  # 3 false pixels
    s = score(ships_from_mask(d), ships_from_mask(t), det_mask=d, truth_mask=t)
    assert s["tpr"] == pytest.approx(0.6)
    assert s["fpr"] == pytest.approx(3 / 90)
    with pytest.raises(InputError):
        score([], [], det_mask=np.zeros((3, 3)), truth_mask=np.zeros((4, 4)))
    assert "tpr" not in score([], [], det_mask=d)


def test_aggregate_is_micro_average():
    a = score([box(0, 0, 5, 5)], [box(0, 0, 5, 5)])  # 1 hit
    b = score([box(50, 50, 55, 55)], [box(0, 0, 5, 5), box(20, 20, 25, 25)])  # 1 false, 2 missed
    m = np.zeros((4, 4), bool)
    m[0, 0] = True
    c = score([], [], det_mask=m, truth_mask=m)
    agg = aggregate([a, b, c])
    assert agg["n_images"] == 3
    assert (agg["n_truth"], agg["n_detections"], agg["n_hit"], agg["n_false"], agg["n_missed"]) == (3, 2, 1, 1, 2)
    assert agg["pd"] == pytest.approx(1 / 3)
    assert agg["precision"] == pytest.approx(1 / 2)
    assert agg["fom"] == pytest.approx(1 / 4)
    assert agg["n_images_pixel"] == 1 and agg["tpr"] == 1.0 and agg["fpr"] == 0.0
    assert agg["pd"] != pytest.approx((a["pd"] + b["pd"] + c["pd"]) / 3)  # not a macro-average


def test_format_scores_block():
    s = score([box(0, 0, 5, 5), box(9, 9, 12, 12)], [box(0, 0, 5, 5), box(30, 30, 35, 35, difficult=True)])
    text = format_scores(s)
    assert "FoM" in text and "precision" in text and "Pd" in text
    assert "1 difficult" in text
    assert "TPR" not in text
    m = np.ones((3, 3), bool)
    assert "TPR" in format_scores(score([], [], m, m))


# ----------------------------------------------------------------------------- truth files


VOC_XML = """<annotation>
  <filename>chip.jpg</filename>
  <size><width>64</width><height>32</height><depth>1</depth></size>
  <object><name>ship</name><difficult>0</difficult>
    <bndbox><xmin>1</xmin><ymin>1</ymin><xmax>10</xmax><ymax>4</ymax></bndbox></object>
  <object><name>ship</name><Difficult>1</Difficult>
    <bndbox><xmin>21</xmin><ymin>11</ymin><xmax>30</xmax><ymax>20</ymax></bndbox></object>
  <object><name>ship</name>
    <bndbox><xmin>55</xmin><ymin>30</ymin><xmax>64</xmax><ymax>32</ymax></bndbox></object>
</annotation>
"""


def test_voc_synthetic_one_based(tmp_path):
    p = tmp_path / "chip.xml"
    p.write_text(VOC_XML)
    ships, mask = load_ships(p)
    assert mask is None
    assert [s.bbox for s in ships] == [(0, 0, 4, 10), (10, 20, 20, 30), (29, 54, 32, 64)]
    assert [s.difficult for s in ships] == [False, True, False]
    assert ships[0].centroid == (2.0, 5.0)  # the box centre
    assert ships[0].properties["name"] == "ship"
    zero = load_voc(p, one_based=False)
    assert zero[0].bbox == (1, 1, 5, 11)
    assert zero[2].bbox == (30, 55, 32, 64)  # clipped to the <size>


def test_voc_folder_and_evaluate_scene_choice(tmp_path):
    folder = tmp_path / "voc"
    folder.mkdir()
    (folder / "a.xml").write_text(VOC_XML)
    (folder / "b.xml").write_text(
        VOC_XML.replace("<xmin>1</xmin><ymin>1</ymin><xmax>10</xmax>", "<xmin>41</xmin><ymin>1</ymin><xmax>50</xmax>")
    )
    d = load_voc_folder(folder)
    assert list(d) == ["a", "b"] and len(d["a"]) == 3
    with pytest.raises(InputError, match="no scene name"):
        load_ships(folder)
    assert load_ships(folder, scene="b.zarr")[0][0].bbox[1] == 40
    with pytest.raises(InputError, match="'c'"):
        load_ships(folder, scene="/data/c.zarr")

    out = tmp_path / "run"
    out.mkdir()
    dets = out / "detections.geojson"
    write_geojson(dets, [Ship.from_bbox((0, 40, 4, 50))])
    with pytest.raises(InputError):
        evaluate(dets, folder)  # two xml and no scene name
    (out / "run.json").write_text(json.dumps({"scene": "/scenes/b.zarr"}))
    assert detections_scene(dets) == "b"
    s = evaluate(dets, folder)
    assert s["scene"] == "b" and (s["n_hit"], s["n_truth"], s["n_difficult"]) == (1, 2, 1)
    write_geojson(dets, [Ship.from_bbox((0, 40, 4, 50))], scene="a.zarr")  # the file's own name wins
    assert evaluate(dets, folder)["n_hit"] == 0
    json.dumps(s, allow_nan=False)


@pytest.mark.realdata
def test_voc_real_sar_ship_dataset():
    if not SSDD.is_dir():
        pytest.skip(f"real data absent: {SSDD}")
    d = load_voc_folder(SSDD)
    assert len(d) == 12
    assert sum(len(v) for v in d.values()) == 68  # data README: 68 ship boxes
    for stem, ships in d.items():
        assert (SSDD / f"{stem}.jpg").exists()
        assert ships
        for s in ships:
            r0, c0, r1, c1 = s.bbox
            assert 0 <= r0 < r1 <= 256 and 0 <= c0 < c1 <= 256
            assert not s.difficult
    # 1-based inclusive: the smallest index 1 maps to 0, the largest 256 to the image edge
    allb = np.array([s.bbox for v in d.values() for s in v])
    assert allb[:, :2].min() == 0 and allb[:, 2:].max() == 256
    # one file on its own gives the same ships
    f = SSDD / "Gao_ship_hh_0201611139301040015.xml"
    ships, _ = load_ships(f)
    assert len(ships) == 6 and ships[0].bbox == (127, 0, 148, 26)


# ----------------------------------------------------------------------------- masks


def _save_png(path, arr):
    from PIL import Image

    Image.fromarray(arr).save(path)


def test_mask_components_synthetic(tmp_path):
    m = np.zeros((40, 50), np.uint8)
    m[2:5, 3:9] = 255  # ship A: rows 2-4, cols 3-8
    m[10, 10] = m[11, 11] = m[12, 12] = 255  # ship B: diagonal, one 8-connected component
    m[30:32, 40:50] = 255  # ship C, touching the right border
    ships = ships_from_mask(m > 0)
    boxes = sorted(s.bbox for s in ships)
    assert boxes == [(2, 3, 5, 9), (10, 10, 13, 13), (30, 40, 32, 50)]
    a = [s for s in ships if s.bbox == (2, 3, 5, 9)][0]
    assert a.centroid == pytest.approx((3.5, 6.0))  # continuous coordinates: pixel centres at +0.5
    assert a.properties["area_px"] == 18

    grey = tmp_path / "grey.png"
    _save_png(grey, m)
    rgb = np.zeros((40, 50, 3), np.uint8)
    rgb[m > 0] = (0, 255, 0)
    rgb[20, 20] = (255, 0, 0)  # a red pixel is not a ship
    rgb[25, 25] = (40, 200, 30)  # dominantly green: a ship pixel
    col = tmp_path / "hrsid.png"
    _save_png(col, rgb)
    g_ships, g_mask = load_ships(grey)
    c_ships, c_mask = load_ships(col)
    assert g_mask.dtype == bool and g_mask.shape == (40, 50)
    assert len(g_ships) == 3 and len(c_ships) == 4
    assert np.array_equal(c_mask & ~g_mask, np.eye(1, 40 * 50, 25 * 50 + 25, dtype=bool).reshape(40, 50))
    np.save(tmp_path / "m.npy", m)
    assert len(load_ships(tmp_path / "m.npy")[0]) == 3


def test_evaluate_mask_truth_with_mask_zarr(tmp_path):
    import zarr

    t = np.zeros((32, 32), np.uint8)
    t[4:8, 4:12] = 255
    t[20:24, 20:22] = 255
    truth = tmp_path / "truth.png"
    _save_png(truth, t)
    out = tmp_path / "out"
    out.mkdir()
    d = np.zeros((32, 32), np.uint8)
    d[4:8, 4:10] = 1
    write_geojson(out / "detections.geojson", ships_from_mask(d))
    s = evaluate(out / "detections.geojson", truth)
    assert "tpr" not in s and s["n_hit"] == 1 and s["n_missed"] == 1
    g = zarr.open_group(str(out / "mask.zarr"), mode="w")
    arr = g.create_array("mask", shape=d.shape, dtype="uint8", chunks=(16, 16))
    arr[...] = d
    s = evaluate(out / "detections.geojson", truth)
    assert s["tpr"] == pytest.approx(24 / 40) and s["fpr"] == 0.0
    assert "TPR" in format_scores(s)
    bad = tmp_path / "bad.zarr"
    zarr.open_array(str(bad), mode="w", shape=(8, 8), dtype="uint8")
    with pytest.raises(InputError, match="differs"):
        evaluate(out / "detections.geojson", truth, mask_path=bad)
    assert read_mask(bad).shape == (8, 8)


@pytest.mark.realdata
def test_hrsid_real_masks():
    if not HRSID_MASKS.is_dir():
        pytest.skip(f"real data absent: {HRSID_MASKS}")
    files = sorted(HRSID_MASKS.glob("*.png"))
    assert files
    for f in files:
        ships, mask = load_ships(f)
        assert mask.shape == (800, 800) and mask.dtype == bool
        if mask.any():
            assert len(ships) >= 1
        assert sum(s.properties["area_px"] for s in ships) == int(mask.sum())
        for s in ships:
            r0, c0, r1, c1 = s.bbox
            assert mask[int(r0) : int(r1), int(c0) : int(c1)].any()
            assert r0 <= s.centroid[0] <= r1 and c0 <= s.centroid[1] <= c1
        # the truth scored against itself is perfect
        sc = score(ships, ships, det_mask=mask, truth_mask=mask)
        assert sc["fom"] == 1.0 and sc["tpr"] == 1.0 and sc["fpr"] == 0.0


# ----------------------------------------------------------------------------- GeoJSON


def test_geojson_round_trip(tmp_path):
    ships = [
        Ship((1.0, 2.0, 5.0, 9.0), (3.2, 5.7), False, {"score": 12.5, "area_px": 20, "length_m": None}),
        Ship.from_bbox((10, 10, 12.5, 20), difficult=True),
    ]
    p = tmp_path / "truth.geojson"
    write_geojson(p, ships, scene="x.zarr")
    doc = json.loads(p.read_text())
    assert doc["type"] == "FeatureCollection" and doc["scene"] == "x.zarr"
    assert doc["features"][0]["properties"]["bbox_px"] == [1, 2, 5, 9]
    assert doc["features"][0]["geometry"] is None
    assert doc["features"][1]["properties"]["difficult"] is True
    back, mask = load_ships(p)
    assert mask is None
    assert back == ships
    assert load_detections(p) == ships
    assert detections_scene(p) == "x"
    # a feature without centroid_px gets its box centre
    doc["features"][0]["properties"].pop("centroid_px")
    p.write_text(json.dumps(doc))
    assert load_detections(p)[0].centroid == (3.0, 5.5)


# ----------------------------------------------------------------------------- garbage


@pytest.mark.parametrize(
    "name, content",
    [
        ("a.geojson", b"{not json"),
        ("b.geojson", b'{"type": "Feature"}'),
        ("c.geojson", b'{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}}]}'),
        (
            "d.geojson",
            b'{"type": "FeatureCollection", "features": [{"type": "Feature", '
            b'"properties": {"bbox_px": [1, 2, "x", 4]}}]}',
        ),
        (
            "e.geojson",
            b'{"type": "FeatureCollection", "features": [{"type": "Feature", '
            b'"properties": {"bbox_px": [5, 5, 1, 1]}}]}',
        ),
        ("f.geojson", b"\xff\xfe\x00garbage"),
        ("g.xml", b"<annotation><object><bndbox><xmin>1</xmin></bndbox></object>"),
        (
            "h.xml",
            b"<annotation><object><bndbox><xmin>a</xmin><ymin>1</ymin><xmax>2</xmax>"
            b"<ymax>2</ymax></bndbox></object></annotation>",
        ),
        ("i.xml", b"<html><body>hello</body></html>"),
        ("j.png", b"\x89PNG\r\n\x1a\n not really a png"),
        ("k.tif", b"II*\x00garbage"),
        ("l.dat", b"\x00\x01\x02\x03 random bytes"),
        ("m.npy", b"\x93NUMPY garbage"),
    ],
)
def test_garbage_files_raise_input_error(tmp_path, name, content):
    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(InputError) as exc:
        load_ships(p)
    msg = str(exc.value)
    assert "\n" not in msg and name in msg
    if name.endswith(".geojson"):
        with pytest.raises(InputError):
            load_detections(p)


def test_missing_and_empty_inputs(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_ships(tmp_path / "nope.geojson")
    with pytest.raises(InputError, match="no such file"):
        evaluate(tmp_path / "nope.geojson", tmp_path / "nope.xml")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no PASCAL-VOC"):
        load_ships(empty)
    with pytest.raises(InputError):
        load_detections(empty)
    z = tmp_path / "nomask.zarr"
    import zarr

    zarr.open_group(str(z), mode="w")
    with pytest.raises(InputError, match="no 'mask'"):
        read_mask(z)


def test_ignore_flagged_leaves_out_unmatched_flagged_detections_only():
    truth = [box(0, 0, 10, 10), box(50, 50, 60, 60, difficult=True), box(100, 100, 110, 110)]
    dets = [
        Ship.from_bbox((1, 1, 9, 9), ambiguity_of=7),  # flagged but on a ship: a hit
        Ship.from_bbox((51, 51, 59, 59), ambiguity_of=None),  # on the difficult ship: ignored
        Ship.from_bbox((200, 200, 205, 205), ambiguity_of=0),  # flagged ghost: left out with the option
        Ship.from_bbox((300, 300, 305, 305)),
    ]  # unflagged stray: a false alarm either way
    plain = score(dets, truth)
    assert (plain["n_hit"], plain["n_false"], plain["n_detections"], plain["n_ignored"]) == (1, 2, 3, 1)
    assert "n_flagged_ignored" not in plain
    kept = score(dets, truth, ignore_flagged=True)
    assert (kept["n_hit"], kept["n_false"], kept["n_detections"], kept["n_flagged_ignored"]) == (1, 1, 2, 1)
    assert kept["n_missed"] == plain["n_missed"] == 1
    assert kept["fom"] == pytest.approx(1 / (1 + 2)) and plain["fom"] == pytest.approx(1 / (2 + 2))
    agg = aggregate([kept, kept])
    assert agg["n_flagged_ignored"] == 2 and agg["n_false"] == 2
    assert "n_flagged_ignored" not in aggregate([plain])
    assert "1 flagged ambiguities matching no ship ignored" in format_scores(kept)
