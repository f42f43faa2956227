"""``mask.zarr/mask`` holds exactly the pixels of the detections kept; ``detected`` the raw decision."""

from __future__ import annotations

import json

import numpy as np
import zarr
from conftest import write_scene
from scipy import ndimage


def _scene(tmp_path, tile):
    """Gamma sea (L = 4, mean 1) with a bright ship (20 dB, 4 x 10 px), a dim one (9 dB, 4 x 10
    px: under a contrast floor) and a bright speck (2 x 2 px: under min_area_px)."""
    rng = np.random.default_rng(7)
    x = rng.gamma(4.0, 0.25, (160, 200)).astype(np.float32)
    x[40:44, 40:50] = rng.gamma(4.0, 25.0, (4, 10))
    x[110:114, 140:150] = rng.gamma(16.0, 0.5, (4, 10))
    x[120:122, 30:32] = 200.0
    return write_scene(tmp_path / f"kept_{tile}.zarr", {"intensity": x}, tile=tile, looks=4.0)


def _components(detected: np.ndarray, merge_px: int) -> np.ndarray:
    """Whole-scene labels of the raw decision, fragments within ``merge_px`` joined (the
    pipeline's rule: the mask dilated by a square of half-side ceil(merge_px / 2))."""
    r = -(-merge_px // 2)
    lab, _ = ndimage.label(ndimage.binary_dilation(detected, np.ones((2 * r + 1,) * 2, bool)), np.ones((3, 3)))
    return np.where(detected, lab, 0)


def test_mask_holds_the_kept_detections_pixels_for_any_tiling(client, tmp_path):
    from sarship.workers.jobs import run_detection

    settings = {"land_mask": "none", "min_area_px": 8, "pfa": 1e-6, "min_contrast_db": 14.0}
    masks = {}
    for tile in (200, 48):
        out = tmp_path / f"t{tile}"
        run = run_detection(
            _scene(tmp_path, tile), "ca_cfar", settings, out_dir=out, tile=tile, client=client, progress=False
        )
        feats = json.loads((out / "detections.geojson").read_text())["features"]
        g = zarr.open_group(str(out / "mask.zarr"), mode="r")
        mask, det = np.asarray(g["mask"][...]) != 0, np.asarray(g["detected"][...]) != 0
        assert [f["properties"]["bbox_px"][:2] for f in feats] == [[40, 40]]  # the bright ship only
        assert run["discarded"]["contrast"] == 1 and run["discarded"]["size"] >= 1, run["discarded"]
        assert det[110:114, 140:150].any() and det[120:122, 30:32].all()  # both dropped ones were detected
        lab = _components(det, run["parameters"]["merge_px"])
        kept = {int(lab[tuple(f["properties"]["peak_px"])]) for f in feats}
        assert np.array_equal(mask, np.isin(lab, sorted(kept)) & det)
        assert run["mask_px"] == int(mask.sum()) == feats[0]["properties"]["area_px"]
        assert run["detected_px"] == int(det.sum()) > run["mask_px"]
        masks[tile] = (mask, det)
    assert np.array_equal(masks[200][0], masks[48][0]) and np.array_equal(masks[200][1], masks[48][1])


def test_pixel_scores_read_the_kept_mask(client, tmp_path):
    """``sarship score``'s pixel figures (pipeline/products/scoring.py) count the kept detections' pixels:
    a false alarm the size rule dropped is no false pixel."""
    from sarship.pipeline.products.scoring import evaluate
    from sarship.workers.jobs import run_detection

    out = tmp_path / "o"
    run_detection(
        _scene(tmp_path, 200),
        "ca_cfar",
        {"land_mask": "none", "min_area_px": 8, "pfa": 1e-6},
        out_dir=out,
        tile=200,
        client=client,
        progress=False,
    )
    truth = np.zeros((160, 200), np.uint8)
    truth[40:44, 40:50] = 1
    truth[110:114, 140:150] = 1
    np.save(tmp_path / "truth.npy", truth)
    s = evaluate(out / "detections.geojson", str(tmp_path / "truth.npy"))
    g = zarr.open_group(str(out / "mask.zarr"), mode="r")
    mask = np.asarray(g["mask"][...]) != 0
    assert not mask[120:122, 30:32].any() and np.asarray(g["detected"][120:122, 30:32]).all()
    assert s["px_fp"] == int((mask & (truth == 0)).sum()) and s["px_tp"] == int((mask & (truth > 0)).sum()), s
    assert s["px_tp"] > 0


def test_merge_members_give_each_record_its_pixels_tile_by_tile():
    """``merge_tiles(members=True)``: the tiles' component ids of each merged record, picked from
    the tiles' own labels (as ``run_tile_keep`` picks them), are exactly that component's pixels."""
    from conftest import blobs_scene

    from sarship.pipeline.targets.components import (
        mask_points,
        merge_radius,
        merge_tiles,
        point_labels,
        tile_components,
    )

    m = blobs_scene((150, 130), seed=4, n=30) > 4.0
    r, t = merge_radius(2), 32
    H, W = m.shape
    pad = np.pad(m, r)
    tiles, labels = {}, np.zeros((H, W), np.int64)
    owner = {}
    for i in range(0, H, t):
        for j in range(0, W, t):
            h, w = min(t, H - i), min(t, W - j)
            ext = pad[i : i + h + 2 * r, j : j + w + 2 * r]
            v = np.ones((h, w), np.float32)
            tiles[(i // t, j // t)] = tile_components(ext, v, v, r, (i, j), (i // t, j // t))
            rr, cc = mask_points(ext)
            comp = point_labels(rr, cc, (h, w), r)
            core = (rr >= r) & (rr < r + h) & (cc >= r) & (cc < r + w)
            labels[rr[core] - r + i, cc[core] - r + j] = comp[core]
            owner[(i // t, j // t)] = (slice(i, i + h), slice(j, j + w))
    recs, members = merge_tiles(tiles, members=True)
    assert np.array_equal(recs, merge_tiles(tiles)) and len(recs) > 10
    got = np.full((H, W), -1)
    for key, (ids, rec) in members.items():
        sl = owner[key]
        lut = dict(zip(ids.tolist(), rec.tolist()))
        sub = np.where(m[sl], [[lut.get(int(x), -2) for x in row] for row in labels[sl]], -1)
        got[sl] = sub
    assert (got[m] >= 0).all() and (got[~m] == -1).all()
    for k, rec in enumerate(recs):
        rows, cols = np.nonzero(got == k)
        assert len(rows) == rec["n"] and (rows.min(), cols.min(), rows.max() + 1, cols.max() + 1) == (
            rec["r0"],
            rec["c0"],
            rec["r1"],
            rec["c1"],
        )
