"""Discrimination of lines, smear and land edges (pipeline/targets/lines.py) and its place in ``sarship detect``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import write_scene

from sarship.pipeline.targets.components import merge_radius, tile_components
from sarship.pipeline.targets.lines import collinear_pairs, discard_lines, near_land, segments
from sarship.pipeline.targets.ship_features import elongations

R = merge_radius(2)


def _records(mask: np.ndarray, values: np.ndarray | None = None) -> np.ndarray:
    """The components of a whole-scene mask (merge_px 2), as the pipeline measures them."""
    v = np.where(mask, 100.0, 0.0).astype(np.float32) if values is None else values.astype(np.float32)
    return tile_components(np.pad(mask, R), v, v, R, (0, 0), (0, 0)).complete


def _dashed(mask, r, c, n, piece=14, gap=4, thick=3, vertical=False):
    """``n`` pieces of a straight line (each ``thick`` x ``piece`` px, ``gap`` px apart)."""
    for k in range(n):
        a = c + k * (piece + gap)
        if vertical:
            mask[a : a + piece, r : r + thick] = True
        else:
            mask[r : r + thick, a : a + piece] = True


def _rule(recs, **kw):
    args = dict(gap_px=8, angle_deg=10.0, dominant_db=10.0, max_elongation=15.0, max_length_m=None, spacing=None)
    args.update(kw)
    return discard_lines(recs, **args)


def test_segments_measure_like_shape_from_moments():
    m = np.zeros((40, 80), bool)
    m[10:14, 10:70] = True
    seg = segments(_records(m))
    assert np.allclose(seg["centre"][0], [12.0, 40.0])
    assert np.allclose(np.abs(seg["axis"][0]), [0.0, 1.0], atol=1e-9)
    assert abs(2 * seg["half"][0] - 60.0) < 0.1 and abs(seg["width"][0] - 4.0) < 0.1
    assert np.isclose(seg["elongation"][0], elongations(_records(m), None)[0])


def test_dashed_line_is_dropped_whole_and_azimuth_streak_is_smear():
    m = np.zeros((120, 300), bool)
    _dashed(m, 20, 5, 15)  # a range line: 15 pieces, each passing the shape test alone
    _dashed(m, 285, 5, 6, vertical=True)  # an azimuth streak (along the rows)
    recs = _records(m)
    assert len(recs) == 21 and (elongations(recs, None) <= 15.0).all()
    why = _rule(recs)
    vertical = segments(recs)["axis"][:, 0] ** 2 > 0.5
    assert (why[~vertical] == "line").all() and (why[vertical] == "smear").all()
    # off: nothing dropped (no join, or no shape test to apply to the joined object)
    assert (_rule(recs, gap_px=None) == "").all() and (_rule(recs, max_elongation=None) == "").all()
    # a gap wider than the setting does not join
    assert (_rule(recs, gap_px=3) == "").all()


def test_convoy_side_by_side_ships_in_a_column_and_a_long_ship_are_kept():
    m = np.zeros((200, 300), bool)
    for k in range(5):  # a convoy: parallel ships side by side, 6 px apart
        m[10 + 10 * k : 14 + 10 * k, 20:50] = True
    m[100:106, 20:50] = True  # two ships bow to stern, 5 px apart
    m[100:106, 55:85] = True
    m[150:158, 100:200] = True  # one long ship (elongation 12.5)
    recs = _records(m)
    assert len(recs) == 8
    assert (_rule(recs) == "").all()
    assert len(collinear_pairs(segments(recs), 8, 10.0)) == 1  # only the two bow to stern are joined


def test_bright_ship_in_its_streak_is_kept_the_streak_dropped():
    m = np.zeros((200, 60), bool)
    _dashed(m, 20, 5, 4, vertical=True)  # streak above
    m[80:110, 18:26] = True  # the ship, on the streak's axis
    _dashed(m, 20, 114, 4, vertical=True)  # streak below
    v = np.where(m, 2.0, 0.0)
    v[80:110, 18:26] = 1000.0  # 27 dB above the streak
    recs = _records(m, v)
    why = _rule(recs)
    ship = recs["peak"] == 1000.0
    assert ship.sum() == 1 and why[ship][0] == "" and (why[~ship] == "smear").all()
    assert (_rule(recs, dominant_db=None) == "smear").all()


def test_near_land():
    land = np.zeros((50, 50), bool)
    land[:, 40:] = True
    m = np.zeros((50, 50), bool)
    m[10:14, 30:36] = True  # 4 px from land
    m[30:34, 5:11] = True  # far
    recs = _records(m)
    read = lambda a, b, c, d: land[a:b, c:d]  # noqa: E731
    assert near_land(recs, read, land.shape, 4).tolist() == [True, False]
    assert near_land(recs, read, land.shape, 3).tolist() == [False, False]


# ----------------------------------------------------------------------------- end to end


def _lines_scene(tmp_path, tile):
    """Gamma sea (L = 4, mean 1) with, at 23 dB: a dashed range line across the scene (14 pieces
    of 3 x 14 px, 6 px apart: more than ca_cfar's merge_px 4), a convoy of 4 ships side by side
    (6 px apart) and one long ship."""
    rng = np.random.default_rng(3)
    x = rng.gamma(4.0, 0.25, (240, 320)).astype(np.float32)
    m = np.zeros(x.shape, bool)
    _dashed(m, 60, 20, 14, gap=6)
    for k in range(4):
        m[150 + 10 * k : 154 + 10 * k, 30:46] = True
    m[180:188, 170:250] = True
    x[m] = rng.gamma(4.0, 50.0, int(m.sum()))
    return write_scene(tmp_path / f"lines_{tile}.zarr", {"intensity": x}, tile=tile, looks=4.0)


def _detect(client, scene, out, tile, **settings):
    from sarship.workers.jobs import run_detection

    settings = {"land_mask": "none", "min_area_px": 8, "pfa": 1e-6, "sidelobes": False, **settings}
    run = run_detection(scene, "ca_cfar", settings, out_dir=out, tile=tile, client=client, progress=False)
    return json.loads((out / "detections.geojson").read_text())["features"], run


def test_line_across_tiles_dropped_convoy_and_long_ship_kept_end_to_end(client, tmp_path):
    boxes = {}
    for tile in (48, 320):
        feats, run = _detect(client, _lines_scene(tmp_path, tile), tmp_path / f"t{tile}", tile)
        boxes[tile] = sorted(tuple(f["properties"]["bbox_px"]) for f in feats)
        assert run["discarded"]["line"] == 14, run["discarded"]
        assert run["parameters"]["line_gap_px"] == 16 and run["parameters"]["line_angle_deg"] == 10.0
        assert not any(55 <= b[0] <= 65 for b in boxes[tile]), boxes[tile]  # nothing of the line
        assert sum(b[0] >= 148 and b[3] <= 48 for b in boxes[tile]) == 4  # the convoy
        assert sum(b[0] >= 178 and b[3] >= 240 for b in boxes[tile]) == 1  # the long ship
    assert boxes[48] == boxes[320]
    # the join off: the line's pieces pass the shape test one by one
    feats, run = _detect(client, _lines_scene(tmp_path, 48), tmp_path / "off", 48, line_gap_px=None)
    assert run["discarded"]["line"] == 0 and sum(55 <= f["properties"]["bbox_px"][0] <= 65 for f in feats) == 14


@pytest.mark.parametrize("bad", [{"line_gap_px": -1}, {"line_angle_deg": 90}, {"land_gap_px": "x"}])
def test_line_settings_are_validated(bad):
    from pydantic import ValidationError

    from sarship.pipeline import detectors

    with pytest.raises(ValidationError):
        detectors.get("ca_cfar").params(**bad)


def test_land_gap_drops_detections_at_the_land_edge_end_to_end(client, tmp_path):
    """``land_gap_px`` with a land FILE: the ship 3 px from the land is dropped (``discarded.land``),
    the one in open sea kept; off by default (both kept)."""
    rng = np.random.default_rng(11)
    x = rng.gamma(4.0, 0.25, (160, 200)).astype(np.float32)
    x[40:44, 40:52] = rng.gamma(4.0, 50.0, (4, 12))  # open sea
    x[110:114, 140:152] = rng.gamma(4.0, 50.0, (4, 12))  # 3 px from the land
    scene = write_scene(tmp_path / "coast.zarr", {"intensity": x}, tile=200, looks=4.0)
    land = np.zeros(x.shape, np.uint8)
    land[:, 155:] = 1
    np.save(tmp_path / "land.npy", land)
    feats, run = _detect(client, scene, tmp_path / "gap", 200, land_mask=str(tmp_path / "land.npy"), land_gap_px=4)
    assert [f["properties"]["bbox_px"] for f in feats] == [[40, 40, 44, 52]] and run["discarded"]["land"] == 1
    feats, run = _detect(client, scene, tmp_path / "off", 200, land_mask=str(tmp_path / "land.npy"))
    assert len(feats) == 2 and run["discarded"]["land"] == 0 and run["parameters"]["land_gap_px"] is None
