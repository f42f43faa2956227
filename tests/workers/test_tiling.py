"""Tiled execution on a real Dask cluster equals the whole-scene computation exactly.

For every detector: odd scene sizes, tiles smaller than the window, tiles not dividing the
scene; masks must be bit-identical and detections identical (components joined across
tile borders, the same as labelling the whole-scene mask at once).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr
from scipy import ndimage

from sarship.pipeline import detectors
from sarship.pipeline.targets.components import merge_radius
from sarship.pipeline.tiling.windows import mirror_pad, padded_block, reflect_index
from sarship.workers.jobs import run_detection
from tests.conftest import blobs_scene, write_scene

SETTINGS = {
    "two_parameter": {"pfa": "1e-3", "guard": "11", "background": "31", "domain": "db"},
    "ca_cfar": {"pfa": "1e-3", "guard": "11", "background": "31"},
    "os_cfar": {"pfa": "1e-3", "guard": "11", "background": "31"},
    "g0_cfar": {"pfa": "1e-3", "guard": "11", "background": "31"},
    "k_cfar": {"pfa": "1e-3", "guard": "11", "background": "31", "censor": "6"},
    "ggd_cfar": {"pfa": "1e-3", "guard": "11", "background": "31"},
    "superpixel_cfar": {"spacing": "6", "reach": "6", "clutter_radius": "18", "min_size": "8"},
}


def test_reflect_index_matches_numpy_pad():
    for n in (1, 2, 5, 17):
        x = np.arange(n)
        for h in (0, 1, 4, 23, 60):
            np.testing.assert_array_equal(
                x[reflect_index(-h, n + h, n)], np.pad(x, h, mode="reflect") if n > 1 else np.zeros(n + 2 * h, int)
            )


def test_padded_block_is_a_slice_of_the_mirrored_scene():
    rng = np.random.default_rng(0)
    x = rng.random((23, 9))
    h = 15  # halo wider than the scene
    P = mirror_pad(x, h)
    for r0, r1, c0, c1 in [(0, 5, 0, 3), (20, 23, 6, 9), (7, 8, 4, 5)]:
        blk = padded_block(lambda a, b, c, d: x[a:b, c:d], x.shape, r0, r1, c0, c1, h)
        np.testing.assert_array_equal(blk, P[r0 : r1 + 2 * h, c0 : c1 + 2 * h])


def test_padded_block_random_cuts_any_halo():
    rng = np.random.default_rng(1)
    for H, W in [(1, 7), (2, 2), (5, 3), (23, 9), (40, 41), (100, 77)]:
        x = rng.random((H, W))
        for h in (0, 1, 3, 15, 60):
            P = mirror_pad(x, h)
            for _ in range(15):
                r0 = int(rng.integers(0, H))
                r1 = int(rng.integers(r0 + 1, H + 1))
                c0 = int(rng.integers(0, W))
                c1 = int(rng.integers(c0 + 1, W + 1))
                blk = padded_block(lambda a, b, c, d: x[a:b, c:d], x.shape, r0, r1, c0, c1, h)
                np.testing.assert_array_equal(blk, P[r0 : r1 + 2 * h, c0 : c1 + 2 * h])


def _run(tmp_path, client, scene, det, tile, settings, tag):
    out = tmp_path / f"{det}-{tag}"
    run = run_detection(scene, det, settings, out_dir=out, tile=tile, client=client, progress=False)
    fc = json.loads((out / "detections.geojson").read_text())
    mask = zarr.open_array(str(out / "mask.zarr" / "detected"), mode="r")[:]
    return run, fc["features"], mask


#: The smallest tile (13 px, narrower than the 15-px halo of the 31-pixel window: a tile's halo
#: reaches past its neighbours) for ca_cfar in the default run, where every detector's tiling
#: machinery is the same, on SMALL_SHAPE (10 x 9 tiles of 13 px; the 301 x 257 scene would take
#: 480, most of the test's time); 29 (also smaller than the window) and 64 (ragged at both edges)
#: for every detector on DEFAULT_SHAPE (6 x 5 and 3 x 3 tiles, 13-36 components, 3 of them across
#: the 29-px tiles' borders). Every tile on the 301 x 257 scene for every other detector under
#: ``-m slow`` (test_tiled_equals_untiled_smallest_tile).
DEFAULT_TILES = (29, 64)
DEFAULT_SHAPE = (161, 137)  # odd sizes, divided by neither tile
SMALL_SHAPE = (127, 113)  # odd sizes, not divided by 13
#: Detectors whose whole run is slow here and whose own module tests tiled == whole in the
#: default run (test_superpixel_cfar.test_tiled_equals_whole_scene_bit_for_bit).
SLOW_DETECTORS = {"superpixel_cfar"}


@pytest.mark.parametrize(
    "det", [pytest.param(d, marks=pytest.mark.slow) if d in SLOW_DETECTORS else d for d in SETTINGS]
)
def test_tiled_equals_untiled(tmp_path, client, det):
    _tiled_equals_untiled(tmp_path, client, det, DEFAULT_TILES, shape=DEFAULT_SHAPE)
    if det == "ca_cfar":
        _tiled_equals_untiled(tmp_path / "small", client, det, (13,), shape=SMALL_SHAPE)


@pytest.mark.slow
@pytest.mark.parametrize("det", [d for d in SETTINGS if d != "ca_cfar"])
def test_tiled_equals_untiled_smallest_tile(tmp_path, client, det):
    _tiled_equals_untiled(tmp_path, client, det, (13, *DEFAULT_TILES))


def _tiled_equals_untiled(tmp_path, client, det, tiles, shape=(301, 257)):
    if det not in detectors.names():
        pytest.skip(f"{det} not registered")
    tmp_path.mkdir(parents=True, exist_ok=True)
    x = blobs_scene(shape, looks=2.0, seed=1)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=2.0)
    settings = {**SETTINGS[det], "min_area_px": "1"}
    spec = detectors.get(det)
    run1, whole, mask1 = _run(tmp_path, client, scene, det, 4096, settings, "whole")
    # whole-scene reference without Dask
    p = spec.params(**{**{k: v for k, v in settings.items()}, "looks": 2.0})
    h = spec.halo(p)
    ref_mask, _ = spec.detect(mirror_pad(x, h), h, (-h, -h), p, spec.prepare(p))
    np.testing.assert_array_equal(mask1.astype(bool), ref_mask)
    assert run1["detections"] > 5
    for tile in tiles:  # 13 and 29 are smaller than the 31-pixel window
        run, feats, mask = _run(tmp_path, client, scene, det, tile, settings, f"t{tile}")
        np.testing.assert_array_equal(mask, mask1)
        assert feats == whole, f"tile {tile}: detections differ"
        assert run["tiles"]["count"] == int(np.ceil(shape[0] / tile) * np.ceil(shape[1] / tile))


# merge_px 1 and 2 join with the same radius (merge_radius: ceil(merge_px / 2) = 1): 2 stands for both
@pytest.mark.parametrize("merge_px", [0, 2, 5])
def test_components_equal_global_labelling(tmp_path, client, merge_px):
    # 139 x 127 in 7 x 6 tiles of 23 px (the whole detector mask: 6 / 29 / 43 components across
    # tile borders at merge_px 0 / 2 / 5); was 211 x 199 with 40 blobs, 90 tiles
    x = blobs_scene((139, 127), looks=1.0, seed=5, n=20, amp=30.0)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=32, looks=1.0)
    # every component kept (no line rule: chance-collinear false alarms at pfa 1e-2 would be joined)
    settings = {
        "pfa": "1e-2",
        "guard": "7",
        "background": "15",
        "min_area_px": "1",
        "merge_px": str(merge_px),
        "line_gap_px": "none",
    }
    run, feats, mask = _run(tmp_path, client, scene, "ca_cfar", 23, settings, f"m{merge_px}")
    m = mask.astype(bool)
    r = merge_radius(merge_px)
    grown = ndimage.maximum_filter(m.astype(np.uint8), size=2 * r + 1, mode="constant") > 0 if r else m
    lab, n = ndimage.label(grown, structure=np.ones((3, 3)))
    lab = np.where(m, lab, 0)
    ids = np.unique(lab[lab > 0])
    assert len(feats) == len(ids)
    ref = sorted(
        (int((lab == i).sum()), *[round(float(v) + 0.5, 6) for v in ndimage.center_of_mass(lab == i)]) for i in ids
    )
    got = sorted((f["properties"]["area_px"], *[round(v, 6) for v in f["properties"]["centroid_px"]]) for f in feats)
    assert got == ref


def test_merge_px_joins_fragments(tmp_path, client):
    x = np.ones((64, 64), np.float32)
    x[30, 10:14] = 1000.0
    x[30, 16:20] = 1000.0  # gap of 2 pixels
    x[30, 23:27] = 1000.0  # gap of 3 pixels
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=16, looks=50.0)
    # a 1-px-wide line of fragments (17 x 1 px joined): no shape filter here
    base = {"pfa": "1e-4", "guard": "9", "background": "15", "min_area_px": "1", "max_elongation": "none"}
    n = {}
    for mp in (0, 2, 3):
        run, feats, _ = _run(tmp_path, client, scene, "ca_cfar", 16, {**base, "merge_px": str(mp)}, f"mp{mp}")
        n[mp] = len(feats)
    assert n == {0: 3, 2: 2, 3: 1}


@pytest.mark.parametrize("seed", range(6))
def test_min_labels_equals_connected_components(seed):
    """The client's merge labels (numpy label propagation) are scipy's connected components,
    each labelled by its smallest node; chains numbered against the hooking order (the slow case
    of label propagation) included."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from sarship.pipeline.targets.components import min_labels

    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    m = int(rng.integers(0, 2 * n))
    a, b = rng.integers(0, n, m), rng.integers(0, n, m)
    if seed % 2:  # a long chain in descending node order, plus the random edges
        chain = rng.permutation(n)
        a = np.r_[a, chain[:-1]]
        b = np.r_[b, chain[1:]]
    got = min_labels(n, a, b)
    _, comp = connected_components(coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)), directed=False)
    smallest = np.full(comp.max() + 1, n)
    np.minimum.at(smallest, comp, np.arange(n))
    np.testing.assert_array_equal(got, smallest[comp])


def test_min_labels_without_edges():
    from sarship.pipeline.targets.components import min_labels

    np.testing.assert_array_equal(min_labels(4, np.zeros(0, int), np.zeros(0, int)), np.arange(4))
    assert min_labels(0, np.zeros(0, int), np.zeros(0, int)).size == 0
