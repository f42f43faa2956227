"""Issue 17's CPU data path: the land pass's sample is the texture of the grid pixels exactly,
and ``run.json`` records every stage of the run (docs/interfaces/files.md, ``timings``)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from scipy import ndimage

from sarship.pipeline.land import landmask as lm
from sarship.pipeline.tiling.windows import mirror_pad, padded_block


@pytest.mark.parametrize(
    "kind, stride, window", [("float32", 7, 15), ("float64", 23, 15), ("float32", 5, 9), ("complex", 17, 15)]
)
def test_texture_sample_is_the_texture_of_the_grid_pixels_bit_for_bit(kind, stride, window):
    """The sample's window sums are formed at the grid pixels alone (landmask._grid_sums), in the
    order of the tiling-invariant box sums: equal to the whole-scene texture bit for bit, for
    strides below and above the window, and for a stack of complex channels (its span)."""
    rng = np.random.default_rng(7)
    H, W = 150, 170
    I = rng.gamma(1.0, 1.0, (H, W)).astype(np.float32)
    I[40:90, 60:120] *= rng.gamma(0.5, 8.0, (50, 60)).astype(np.float32)  # a textured patch
    I[10:25, 5:30] = np.nan  # absent pixels: some windows under half present -> NaN, not sampled
    I[100, 100] = -1.0  # invalid power: absent
    if kind == "float64":
        I = I.astype(np.float64) * np.pi
    elif kind == "complex":  # two channels whose span is the intensity's order of magnitude
        ph = rng.uniform(0, 2 * np.pi, (H, W, 2))
        I = (np.sqrt(np.abs(np.nan_to_num(I)))[..., None] * np.exp(1j * ph)).astype(np.complex64)
        I[10:25, 5:30] = np.nan
    cfg = lm.TextureConfig(window=window)
    r = cfg.window // 2
    whole = lm.texture(mirror_pad(I, r), r, (-r, -r), cfg.window)
    rows, cols = np.arange(H), np.arange(W)
    ri, ci = rows[rows % stride == 0], cols[cols % stride == 0]
    expect = whole[np.ix_(ri, ci)]
    rr, cc = np.meshgrid(ri, ci, indexing="ij")
    keep = np.isfinite(expect)
    assert 0 < keep.sum() < keep.size  # the NaN rule is exercised
    parts = []
    for r0, r1, c0, c1 in ((0, 64, 0, 90), (0, 64, 90, W), (64, H, 0, 90), (64, H, 90, W)):
        block = padded_block(lambda a, b, c, d: I[a:b, c:d], (H, W), r0, r1, c0, c1, r)
        parts.append(lm.texture_sample(block, r, (r0 - r, c0 - r), cfg, stride))
    got = lm.pool_samples(parts)
    np.testing.assert_array_equal(got, expect[keep])  # bit for bit, in (row, col) order
    # and the windows' mean power in the same order: present pixels' power over their count
    means = lm.pool_samples(parts, "m")
    assert means.shape == got.shape and np.isfinite(means).all()
    P = lm.power(I) if kind == "complex" else np.asarray(I, np.float64)
    Pz = np.where(np.isfinite(P) & (P >= 0), P, 0.0)
    okf = (np.isfinite(P) & (P >= 0)).astype(np.float64)

    def box(a):
        return ndimage.uniform_filter(np.pad(a, r, mode="reflect"), window, mode="constant")[r:-r, r:-r]

    with np.errstate(divide="ignore", invalid="ignore"):
        want = (box(Pz) / box(okf))[rr[keep], cc[keep]]
    np.testing.assert_allclose(means, want, rtol=1e-9)
    rc = np.concatenate([p["rc"] for p in parts])
    assert sorted(map(tuple, rc)) == sorted(zip(rr[keep].tolist(), cc[keep].tolist()))


def test_mask_stores_only_chunks_with_detections(tmp_path):
    """The mask costs what it holds: a tile without a detection stores no chunk (zarr's
    write_empty_chunks off), and the store still reads back 0 there."""
    import zarr
    from conftest import write_scene

    from sarship.workers.jobs import run_detection

    rng = np.random.default_rng(5)
    x = rng.gamma(4.0, 0.25, (128, 128)).astype(np.float32)
    x[20:24, 20:30] += 80.0  # one ship, in tile (0, 0)
    scene = write_scene(tmp_path / "s.zarr", {"intensity": x}, tile=64, looks=4.0)
    run = run_detection(
        scene,
        "ca_cfar",
        {"pfa": 1e-9, "guard": 9, "background": 17, "land_mask": None},
        out_dir=tmp_path / "out",
        progress=False,
    )
    assert run["detections"] == 1
    chunks = sorted(
        p.relative_to(tmp_path / "out" / "mask.zarr" / "mask").as_posix()
        for p in (tmp_path / "out" / "mask.zarr" / "mask" / "c").rglob("*")
        if p.is_file()
    )
    assert chunks == ["c/0/0"]
    m = zarr.open_array(str(tmp_path / "out" / "mask.zarr" / "mask"), mode="r")[:]
    assert m.shape == (128, 128) and m[20:24, 20:30].all() and m.sum() == m[:64, :64].sum()
    t = run["timings"]
    for key in (
        "prepare_s",
        "cluster_start_s",
        "tiles_s",
        "cluster_close_s",
        "consolidate_s",
        "merge_s",
        "geojson_s",
        "total_s",
    ):
        assert t[key] is not None and t[key] >= 0, key
    assert t["cluster_start_s"] <= t["prepare_s"] <= t["total_s"]
    assert all("land_s" in p for p in run["tiles"]["per_tile"])


BACKENDS = ["zarr"] + (["tensorstore"] if importlib.util.find_spec("tensorstore") else [])


@pytest.mark.parametrize("backend", BACKENDS)
def test_write_sparse_writes_only_the_chunks_that_hold_marks(tmp_path, monkeypatch, backend):
    """A tile's mask write encodes only the box of inner chunks its marks fall in (aligned to
    the store's chunk grid, inside the tile's shard): the store reads back exactly what a whole
    tile write gives, the other inner chunks are never written, and an empty tile writes
    nothing; with either writer (``SARSHIP_READER``)."""
    import zarr

    monkeypatch.setenv("SARSHIP_READER", backend)

    from sarship.pipeline.scene import create_mask_store
    from sarship.workers.tasks import write_sparse

    create_mask_store(tmp_path / "m.zarr", (2048, 3072), 1024)  # shards 1024, inner chunks 512
    path = str(tmp_path / "m.zarr" / "mask")
    core = np.zeros((1024, 1024), bool)
    core[600:606, 530:560] = True  # inner chunk (1, 1) of the tile
    core[1000:1010, 1020:1024] = True  # and (1, 1) too: the box is one chunk
    assert write_sparse(path, 1024, 2048, core) == (1024 + 512, 2048, 2048 + 512, 3072)
    assert write_sparse(path, 0, 0, np.zeros((1024, 1024), bool)) is None
    edge = np.zeros((1024, 1024), bool)
    edge[10, 10] = edge[700, 900] = True  # box spans chunks (0, 0) .. (1, 1): the whole tile
    assert write_sparse(path, 0, 1024, edge) == (0, 1024, 1024, 2048)
    got = zarr.open_array(path, mode="r")[:]
    want = np.zeros((2048, 3072), np.uint8)
    want[1024:2048, 2048:3072] = core
    want[0:1024, 1024:2048] = edge
    assert np.array_equal(got, want)
    # only the shards of the two written tiles exist
    shards = sorted(
        p.relative_to(tmp_path / "m.zarr" / "mask" / "c").as_posix()
        for p in (tmp_path / "m.zarr" / "mask" / "c").rglob("*")
        if p.is_file()
    )
    assert shards == ["0/1", "1/2"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_write_points_writes_what_write_sparse_writes(tmp_path, monkeypatch, backend):
    """The mask write from a tile's detected points (the GPU tile's, which never has the whole
    mask on the host) stores the same chunks with the same content as the write of the dense
    tile, and returns the same box; no points write nothing."""
    import zarr

    monkeypatch.setenv("SARSHIP_READER", backend)
    from sarship.pipeline.scene import create_mask_store
    from sarship.workers.tasks import write_points, write_sparse

    rng = np.random.default_rng(3)
    for name in ("a", "b"):
        create_mask_store(tmp_path / f"{name}.zarr", (2048, 3072), 1024)
    for k, (r0, c0) in enumerate([(0, 0), (0, 2048), (1024, 1024)]):
        core = np.zeros((1024, 1024), bool)
        if k:  # tile 0 stays empty
            for _ in range(3 * k):
                r, c = rng.integers(0, 1024 - 8, 2)
                core[r : r + int(rng.integers(1, 8)), c : c + int(rng.integers(1, 8))] = True
        rows, cols = np.nonzero(core)
        box_a = write_sparse(str(tmp_path / "a.zarr" / "mask"), r0, c0, core)
        box_b = write_points(str(tmp_path / "b.zarr" / "mask"), r0, c0, rows, cols, core.shape)
        assert box_a == box_b and (box_a is None) == (k == 0)
    a = tmp_path / "a.zarr" / "mask"
    b = tmp_path / "b.zarr" / "mask"
    assert np.array_equal(zarr.open_array(str(a), mode="r")[:], zarr.open_array(str(b), mode="r")[:])
    files = [sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file()) for d in (a, b)]
    assert files[0] == files[1] and "c/0/0" not in files[1]


def test_points_components_equal_the_dense_labelling():
    """A tile's components from its detected points (coordinates in the margin frame, values
    and statistic at the points) equal those of :func:`tile_components` on the dense mask, for
    masks with ships in the margin, across the core's edges and inside it."""
    from sarship.pipeline.targets.components import mask_points, points_components, tile_components

    rng = np.random.default_rng(5)
    h, w, r = 96, 80, 3
    for trial in range(20):
        mext = np.zeros((h + 2 * r, w + 2 * r), bool)
        for _ in range(int(rng.integers(0, 12))):
            a, b = rng.integers(0, h + 2 * r - 4), rng.integers(0, w + 2 * r - 4)
            mext[a : a + int(rng.integers(1, 5)), b : b + int(rng.integers(1, 5))] = True
        values = rng.gamma(1.0, 1.0, (h, w)).astype(np.float32)
        stat = rng.normal(size=(h, w)).astype(np.float32)
        dense = tile_components(mext, values, stat, r, (1000, 2000), (4, 7))
        rr, cc = mask_points(mext)
        inside = (rr >= r) & (rr < r + h) & (cc >= r) & (cc < r + w)
        vals = np.full(rr.size, np.nan, np.float32)  # margin points carry no value
        st = np.full(rr.size, np.nan, np.float32)
        vals[inside] = values[rr[inside] - r, cc[inside] - r]
        st[inside] = stat[rr[inside] - r, cc[inside] - r]
        pts = points_components(rr, cc, vals, st, (h, w), r, (1000, 2000), (4, 7))
        assert np.array_equal(pts.moments, dense.moments) and np.array_equal(pts.complete, dense.complete)
        assert all(np.array_equal(pts.edges[k], dense.edges[k]) for k in dense.edges), trial


@pytest.mark.parametrize("tile", [64, 1024])
def test_readers_agree_bit_for_bit(tmp_path, monkeypatch, tile):
    """tensorstore and zarr-python read the scene stores to the same values: float32 intensity
    in each codec, complex channels stacked, covariance matrices; rectangles inside, across
    chunks and clipped at the edges (sharded tiles of 512 inner chunks, and plain chunks)."""
    if "tensorstore" not in BACKENDS:
        pytest.skip("tensorstore is not installed")
    from sarship.pipeline.scene import create_scene, finalize_scene
    from sarship.pipeline.tiling.inputs import make_reader

    rng = np.random.default_rng(11)
    # sharded tiles need a scene past one 1024 shard; plain 64 px chunks are crossed and clipped by a
    # scene a few chunks a side (the same rectangles, placed by the scene's size)
    H, W = (1100, 1300) if tile > 512 else (150, 190)
    x = rng.gamma(1.0, 1.0, (H, W)).astype(np.float32)
    x[5:9, 7:11] = np.nan
    hh = (rng.normal(size=(H, W)) + 1j * rng.normal(size=(H, W))).astype(np.complex64)
    vv = (rng.normal(size=(H, W)) + 1j * rng.normal(size=(H, W))).astype(np.complex64)
    cov = {
        f"c{i}{j}": (rng.normal(size=(H, W)) + (1j * rng.normal(size=(H, W)) if i != j else 0)).astype(
            np.complex64 if i != j else np.float32
        )
        for i, j in ((1, 1), (1, 2), (2, 2))
    }
    stores = []
    for codec in ("lz4", "zstd", "none"):
        g = create_scene(
            tmp_path / f"{codec}.zarr",
            (H, W),
            {"intensity": np.float32, "hh": np.complex64, "vv": np.complex64, **{k: v.dtype for k, v in cov.items()}},
            tile=tile,
            attrs={"kind": "intensity"},
            codec=codec,
        )
        g["intensity"][:] = x
        g["hh"][:] = hh
        g["vv"][:] = vv
        for k, v in cov.items():
            g[k][:] = v
        finalize_scene(tmp_path / f"{codec}.zarr")
        stores.append(str(tmp_path / f"{codec}.zarr"))
    rects = [
        (0, 10, 0, 10),
        (H // 2 - 50, H, 20, W),
        (H - 100, H, W - 50, W),
        (3, 4, W - 1, W),
        (H // 2 + 50, H // 2 + 50, 0, 5),
    ]  # for 1100 x 1300: (500, 1100, 20, 1300), ...
    for path in stores:
        for var, transform in (
            ("intensity", "real"),
            ("hh", "abs2"),
            ("hh", "complex"),
            (("hh", "vv"), "stack"),
            (("c11", "c12", "c22"), "covariance"),
        ):
            got = {}
            for backend in ("zarr", "tensorstore"):
                monkeypatch.setenv("SARSHIP_READER", backend)
                read = make_reader(path, var, transform)
                got[backend] = [read(*r) for r in rects]
            for a, b in zip(got["zarr"], got["tensorstore"]):
                assert a.dtype == b.dtype and a.shape == b.shape
                np.testing.assert_array_equal(a, b)
    # slices as NumPy takes them: clipped at the edges, negative, stepped, empty
    from sarship.pipeline.tiling.inputs import open_array

    monkeypatch.setenv("SARSHIP_READER", "tensorstore")
    ts_arr = open_array(stores[0] + "/intensity")
    monkeypatch.setenv("SARSHIP_READER", "zarr")
    z_arr = open_array(stores[0] + "/intensity")
    assert type(ts_arr).__name__ == "_TensorStoreArray" and ts_arr.shape == (H, W)
    for key in (
        (slice(H - 100, H + 300), slice(-20, None)),
        (slice(3, 40, 7), slice(90, 1000, 3)),
        (slice(900, 50), slice(0, 3)),
        (slice(None), slice(10, 11)),
    ):
        np.testing.assert_array_equal(ts_arr[key], z_arr[key])


def test_reader_setting_is_checked(monkeypatch):
    from sarship.pipeline.errors import InputError
    from sarship.pipeline.tiling.inputs import reader_backend

    monkeypatch.setenv("SARSHIP_READER", "hdf5")
    with pytest.raises(InputError, match="SARSHIP_READER must be one of tensorstore, zarr, got 'hdf5'"):
        reader_backend()
    monkeypatch.setenv("SARSHIP_READER", "zarr")
    assert reader_backend() == "zarr"
    monkeypatch.delenv("SARSHIP_READER")
    assert reader_backend() == ("tensorstore" if "tensorstore" in BACKENDS else "zarr")


def test_a_store_tensorstore_cannot_open_is_read_by_zarr_python(tmp_path, monkeypatch):
    """A Zarr v2 array (tensorstore's zarr3 driver does not open it) is read through zarr-python,
    with a warning naming the store, and gives its values."""
    if "tensorstore" not in BACKENDS:
        pytest.skip("tensorstore is not installed")
    import zarr

    from sarship.pipeline.tiling.inputs import open_array

    monkeypatch.delenv("SARSHIP_READER", raising=False)
    a = zarr.create_array(str(tmp_path / "v2.zarr"), shape=(10, 12), dtype="f4", chunks=(5, 5), zarr_format=2)
    a[:] = np.arange(120, dtype="f4").reshape(10, 12)
    with pytest.warns(UserWarning, match="tensorstore cannot open .*v2.zarr.*using zarr-python"):
        b = open_array(str(tmp_path / "v2.zarr"))
    np.testing.assert_array_equal(b[2:4, 3:5], a[2:4, 3:5])
