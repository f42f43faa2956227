"""Job products as pure functions on a job folder written here: the mask COG (content, overviews,
the byte layout GDAL's COG validator checks, bounded reads, concurrent first builds), the Zarr zip,
XYZ tile math at the edges, max-pooled mask tiles, the cached one-per-job stretch, polarimetric
scenes, and the STAC pieces (footprint, sar fields, times)."""

from __future__ import annotations

import io
import json
import struct
import threading
from pathlib import Path

import numpy as np
import pytest

tifffile = pytest.importorskip("tifffile")
from conftest import blobs_scene, write_scene  # noqa: E402

from sarship.service import cog, render, stac, tiles  # noqa: E402


def make_job(
    tmp: Path,
    scene_arrays: dict,
    mask: np.ndarray,
    tile: int = 128,
    attrs: dict | None = None,
    channel="intensity",
    mask_attrs: dict | None = None,
) -> Path:
    """A finished job's folder as the runner leaves it: run.json, mask.zarr (group + 'mask')."""
    import zarr

    scene = write_scene(tmp / "scene.zarr", scene_arrays, tile=tile, **(attrs or {}))
    job = tmp / "job"
    job.mkdir()
    g = zarr.open_group(str(job / "mask.zarr"), mode="w", zarr_format=3)
    g.create_array("mask", shape=mask.shape, chunks=(tile, tile), dtype="uint8", fill_value=0)
    g["mask"][:] = mask
    g.attrs.update(mask_attrs or {})
    H, W = mask.shape
    (job / "run.json").write_text(
        json.dumps(
            {
                "scene": {"path": str(scene), "shape": [H, W], "attrs": attrs or {}},
                "channel": channel,
                "detector": "ca_cfar",
                "parameters": {},
            }
        )
    )
    (job / "detections.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    return job


def random_mask(shape, seed=0, p=0.002) -> np.ndarray:
    return (np.random.default_rng(seed).random(shape) < p).astype(np.uint8)


# --------------------------------------------------------------------------- max-pooling and levels


def test_maxpool_matches_a_loop_and_keeps_single_pixels():
    rng = np.random.default_rng(1)
    a = (rng.random((37, 23)) < 0.05).astype(np.uint8) * rng.integers(1, 255, (37, 23)).astype(np.uint8)
    for f in (1, 2, 3, 4, 8, 64):
        got = cog.maxpool(a, f)
        want = np.array([[a[i : i + f, j : j + f].max() for j in range(0, 23, f)] for i in range(0, 37, f)])
        assert np.array_equal(got, want), f
    one = np.zeros((513, 300), np.uint8)
    one[512, 299] = 1  # the last pixel, in the partial edge block of every level
    for f in (2, 4, 256, 1024):
        p = cog.maxpool(one, f)
        assert p.shape == (-(-513 // f), -(-300 // f)) and p.sum() == 1 and p[-1, -1] == 1


@pytest.mark.parametrize("shape", [(1, 1), (256, 256), (257, 3), (300, 260), (4096, 4096), (25000, 16700)])
def test_levels_and_zooms_agree(shape):
    levels = cog.level_shapes(shape)
    Z = tiles.max_zoom(shape)
    assert len(levels) == Z + 1 and max(levels[-1]) <= 256
    assert Z == max(0, int(np.ceil(np.log2(max(shape) / 256))))
    for k, (h, w) in enumerate(levels):
        assert (h, w) == (-(-shape[0] // 2**k), -(-shape[1] // 2**k))
        nx, ny = tiles.tile_counts(shape, Z - k)
        assert (nx, ny) == (-(-w // 256), -(-h // 256))  # XYZ tiles of zoom Z-k = COG tiles of level k


def test_tile_windows_at_the_edges():
    shape = (300, 260)  # Z = 1
    assert tiles.max_zoom(shape) == 1
    w = tiles.tile_window(shape, 1, 1, 1)
    assert (w.r0, w.r1, w.c0, w.c1, w.f, w.rows, w.cols) == (256, 300, 256, 260, 1, 44, 4)
    w0 = tiles.tile_window(shape, 0, 0, 0)
    assert (w0.r1, w0.c1, w0.f, w0.rows, w0.cols, w0.level) == (300, 260, 2, 150, 130, 1)
    for z, x, y in [(2, 0, 0), (-1, 0, 0), (1, 2, 0), (1, 0, 2), (0, 1, 0), (1, -1, 0)]:
        assert tiles.tile_window(shape, z, x, y) is None, (z, x, y)
    big = (25000, 16700)  # Z = 7; zoom 0 is one tile over the whole scene with stride 128
    w = tiles.tile_window(big, 0, 0, 0)
    assert (w.f, w.rows, w.cols) == (128, 196, 131)
    w = tiles.tile_window(big, 7, 65, 97)
    assert (w.r0, w.r1, w.c0, w.c1, w.rows, w.cols) == (24832, 25000, 16640, 16700, 168, 60)
    assert tiles.tile_window(big, 7, 66, 0) is None and tiles.tile_window(big, 7, 0, 98) is None


def test_layers_parse():
    assert tiles.parse_layers(None) == ("scene", "mask")
    assert tiles.parse_layers("mask,scene,mask") == ("scene", "mask")
    assert tiles.parse_layers("mask") == ("mask",)
    for bad in ("", "scene,", "sea", "scene,Mask"):
        with pytest.raises(ValueError):
            tiles.parse_layers(bad)


# --------------------------------------------------------------------------- the COG


def cog_layout_errors(path: Path) -> list[str]:
    """The checks of GDAL's validate_cloud_optimized_geotiff.py, on the bytes: main IFD right
    after the ghost header, IFDs by increasing offset and decreasing size, all IFDs before any
    tile, tile data smallest overview first and full resolution last, row-major increasing
    offsets in each level, and the declared leader (size) / trailer (last 4 bytes) of every tile."""
    errors = []
    raw = path.read_bytes()
    with tifffile.TiffFile(path) as tif:
        ghost = tif.gdal_structural_metadata or {}
        big = tif.is_bigtiff
        pages = list(tif.pages)
        ifds = [p.offset for p in pages]
        offs = [np.asarray(p.dataoffsets, np.int64) for p in pages]
        counts = [np.asarray(p.databytecounts, np.int64) for p in pages]
        shapes = [p.shape for p in pages]
        if not all(p.is_tiled for p in pages):
            errors.append("not tiled")
        if any(p.is_reduced for p in pages[:1]) or not all(p.is_reduced for p in pages[1:]):
            errors.append("NewSubfileType: main must be 0, overviews 1")
    head = 16 if big else 8
    pattern = b"GDAL_STRUCTURAL_METADATA_SIZE="
    if raw[head : head + len(pattern)] == pattern:
        size = int(raw[head + len(pattern) : head + len(pattern) + 6])
        expected = head + len(pattern) + 6 + len(" bytes\n") + size
        expected += expected % 2
    else:
        expected = head
    if ifds[0] != expected:
        errors.append(f"main IFD at {ifds[0]}, expected {expected}")
    if ifds != sorted(ifds):
        errors.append(f"IFD offsets not increasing: {ifds}")
    for a, b in zip(shapes, shapes[1:]):
        if b[0] > a[0] or b[1] > a[1]:
            errors.append(f"overview {b} larger than the level before {a}")
    first = [int(o.min()) for o in offs]
    if min(first) < max(ifds):
        errors.append("tile data before the last IFD")
    if first != sorted(first, reverse=True):
        errors.append(f"level data not smallest-overview-first: {first}")
    for k, o in enumerate(offs):
        if ghost.get("BLOCK_ORDER") == "ROW_MAJOR" and np.any(np.diff(o) <= 0):
            errors.append(f"level {k}: tile offsets not increasing row-major")
        for off, n in zip(o, counts[k]):
            if ghost.get("BLOCK_LEADER") == "SIZE_AS_UINT4" and struct.unpack("<I", raw[off - 4 : off])[0] != n:
                errors.append(f"level {k}: bad leader at {off}")
                break
            trailer_ok = raw[off + n - 4 : off + n] == raw[off + n : off + n + 4]
            if ghost.get("BLOCK_TRAILER") == "LAST_4_BYTES_REPEATED" and not trailer_ok:
                errors.append(f"level {k}: bad trailer at {off}")
                break
    return errors


def test_mask_cog_content_overviews_layout_and_georeference(tmp_path):
    mask = random_mask((700, 1100), seed=2)
    mask[699, 1099] = 1
    attrs = {"crs": "EPSG:32631", "transform": [500000.0, 10.0, 0.0, 5000000.0, 0.0, -10.0]}
    job = make_job(tmp_path, {"intensity": blobs_scene((700, 1100))}, mask, mask_attrs=attrs)
    path = cog.mask_cog(job)
    assert path == job / "mask.tif"
    with tifffile.TiffFile(path) as tif:
        s = tif.series[0]
        assert np.array_equal(s.asarray(), mask)
        assert [lv.shape for lv in s.levels] == [(700, 1100), (350, 550), (175, 275), (88, 138)]
        for k, lv in enumerate(s.levels):
            assert np.array_equal(lv.asarray(), cog.maxpool(mask, 2**k))  # max-pooled: ships stay
        for p in tif.pages:
            assert (p.tilewidth, p.tilelength, p.dtype, p.compression) == (256, 256, np.uint8, 8)
        geo = tif.geotiff_metadata
        assert geo["ProjectedCSTypeGeoKey"] == 32631 and geo["GTModelTypeGeoKey"] == 1
        assert list(geo["ModelPixelScale"][:2]) == [10.0, 10.0]
        assert list(geo["ModelTiepoint"]) == [0.0, 0.0, 0.0, 500000.0, 5000000.0, 0.0]
        assert tif.gdal_structural_metadata["LAYOUT"] == "IFDS_BEFORE_DATA"
    assert cog_layout_errors(path) == []
    for k, (h, w) in enumerate(cog.level_shapes(mask.shape)):  # tile reads as the XYZ tiles do them
        t = cog.cog_tile(path, k, (h - 1) // 256, (w - 1) // 256)
        assert t[(h - 1) % 256, (w - 1) % 256] == 1


def test_layout_check_catches_a_plain_tifffile_pyramid(tmp_path):
    """The checker is not vacuous: tifffile's own pyramid (data next to each IFD) fails it."""
    p = tmp_path / "plain.tif"
    m = random_mask((600, 600))
    with tifffile.TiffWriter(p) as w:
        w.write(m, tile=(256, 256), compression="zlib")
        w.write(cog.maxpool(m, 2), tile=(256, 256), compression="zlib", subfiletype=1)
        w.write(cog.maxpool(m, 4), tile=(256, 256), compression="zlib", subfiletype=1)
    errs = cog_layout_errors(p)
    assert any("data before" in e or "smallest-overview-first" in e for e in errs), errs


def test_cog_reads_in_bounded_strips_and_rotated_or_bigtiff_variants(tmp_path):
    H, W = 1300, 900
    mask = random_mask((H, W), seed=3)
    calls = []

    def read_rows(r0, r1):
        calls.append((r0, r1))
        return mask[r0:r1]

    out = tmp_path / "m.tif"
    cog.write_cog(
        read_rows,
        (H, W),
        out,
        strip=512,
        attrs={"crs": "EPSG:4326", "transform": [10.0, 0.001, 0.0002, 50.0, 0.0001, -0.001]},
    )
    assert calls == [(0, 512), (512, 1024), (1024, 1300)]  # one pass, strips of tile rows, never whole
    with tifffile.TiffFile(out) as tif:
        assert np.array_equal(tif.asarray(), mask)
        geo = tif.geotiff_metadata
        assert geo["GeographicTypeGeoKey"] == 4326 and geo["GTModelTypeGeoKey"] == 2
        assert list(geo["ModelTransformation"][0]) == [0.001, 0.0002, 0.0, 10.0]  # rotated: full matrix
    assert cog_layout_errors(out) == []
    big = tmp_path / "big.tif"
    cog.write_cog(lambda a, b: mask[a:b], (H, W), big, bigtiff=True)
    with tifffile.TiffFile(big) as tif:
        assert tif.is_bigtiff and np.array_equal(tif.asarray(), mask)
        assert [lv.shape for lv in tif.series[0].levels] == cog.level_shapes((H, W))
    assert cog_layout_errors(big) == []
    with pytest.raises(ValueError):
        cog.write_cog(lambda a, b: mask[a:b], (H, W), tmp_path / "x.tif", strip=300)


def test_concurrent_first_requests_build_one_cog(tmp_path):
    mask = random_mask((900, 700), seed=4)
    job = make_job(tmp_path, {"intensity": blobs_scene((900, 700))}, mask)
    got, errs = [], []

    def get():
        try:
            got.append(cog.mask_cog(job).read_bytes())
        except Exception as exc:  # pragma: no cover - reported below
            errs.append(exc)

    ts = [threading.Thread(target=get) for _ in range(8)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errs and len(got) == 8 and len(set(got)) == 1
    assert np.array_equal(tifffile.imread(io.BytesIO(got[0])), mask)
    assert not [p.name for p in job.iterdir() if ".tmp-" in p.name or p.name.startswith(".cog-spool")]


def test_mask_zarr_zip_roundtrip(tmp_path):
    import zarr

    mask = random_mask((300, 260), seed=5)
    job = make_job(tmp_path, {"intensity": blobs_scene((300, 260))}, mask, mask_attrs={"detector": "ca_cfar"})
    z = cog.mask_zarr_zip(job)
    g = zarr.open_group(zarr.storage.ZipStore(z, mode="r"), mode="r")
    assert np.array_equal(g["mask"][:], mask) and g.attrs["detector"] == "ca_cfar"


# --------------------------------------------------------------------------- quicklook and tiles


def test_stretch_is_cached_once_per_job_and_tiles_match_the_scene(tmp_path):
    H, W = 600, 1100  # Z = 3
    x = blobs_scene((H, W), seed=6)
    mask = random_mask((H, W), seed=6, p=0.001)
    job = make_job(tmp_path, {"intensity": x}, mask)
    meta = render.job_stretch(job)
    step = render.base_step((H, W))
    assert step == 1 and meta["step"] == 1 and meta["var"] == "intensity"
    lo, hi = render.percentile_range(render.to_db(x[::step, ::step]))
    assert (meta["lo"], meta["hi"]) == pytest.approx((lo, hi))
    saved = (job / "quicklook.json").stat().st_mtime_ns
    assert render.job_stretch(job) == meta and (job / "quicklook.json").stat().st_mtime_ns == saved
    grey = render.stretch(render.to_db(x), meta["lo"], meta["hi"])
    Z = tiles.max_zoom((H, W))
    for z in range(Z + 1):
        nx, ny = tiles.tile_counts((H, W), z)
        for ty in range(ny):
            for tx in range(nx):
                w = tiles.tile_window((H, W), z, tx, ty)
                want = grey[w.r0 : w.r1 : w.f, w.c0 : w.c1 : w.f]
                assert np.array_equal(tiles.scene_grey(job, w), want)  # from the cached base
                assert np.array_equal(tiles.scene_grey(job, w, base_max=128), want)  # via the Zarr (fine zooms)
                assert np.array_equal(tiles.scene_grey(job, w, base_max=300), want)  # base of step 4, or Zarr
                assert np.array_equal(
                    tiles.mask_tile(job, w, tx, ty), cog.maxpool(mask[w.r0 : w.r1, w.c0 : w.c1], w.f) > 0
                )


def test_rendered_tile_pixels(tmp_path):
    from PIL import Image

    H, W = 300, 260
    x = blobs_scene((H, W), seed=7)
    mask = np.zeros((H, W), np.uint8)
    mask[299, 259] = 1  # one pixel in the corner: red in the partial tile, and max-pooled at zoom 0
    job = make_job(tmp_path, {"intensity": x}, mask)
    t = np.asarray(Image.open(io.BytesIO(tiles.render_tile(job, (H, W), 1, 1, 1, ("scene", "mask")))))
    assert t.shape == (256, 256, 4)
    assert (t[:44, :4, 3] == 255).all() and (t[44:, :, 3] == 0).all() and (t[:, 4:, 3] == 0).all()
    assert tuple(t[43, 3]) == tiles.MASK_RGBA and (t[..., 0] == 255).sum() >= 1
    t0 = np.asarray(Image.open(io.BytesIO(tiles.render_tile(job, (H, W), 0, 0, 0, ("mask",)))))
    assert tuple(t0[149, 129]) == tiles.MASK_RGBA and (t0[..., 3] > 0).sum() == 1  # mask only: the rest clear
    g = np.asarray(Image.open(io.BytesIO(tiles.render_tile(job, (H, W), 0, 0, 0, ("scene",)))))
    assert (g[:150, :130, 3] == 255).all() and (g[..., 0] == g[..., 1]).all()  # grey, no red
    assert tiles.render_tile(job, (H, W), 1, 2, 0, ("scene",)) is None


def test_polarimetric_scenes_use_intensity_source(tmp_path):
    rng = np.random.default_rng(8)
    H, W = 200, 180

    def cplx():
        return ((rng.normal(size=(H, W)) + 1j * rng.normal(size=(H, W))) / np.sqrt(2)).astype(np.complex64)

    hh, hv, vv = cplx(), cplx(), cplx()
    mask = random_mask((H, W), seed=8)
    (tmp_path / "q").mkdir()
    quad = make_job(
        tmp_path / "q", {"hh": hh, "hv": hv, "vv": vv}, mask, attrs={"kind": "quadpol"}, channel=["hh", "hv", "vv"]
    )
    meta = render.job_stretch(quad)
    assert (meta["var"], meta["transform"]) == ("hh", "abs2")
    w = tiles.tile_window((H, W), 0, 0, 0)
    want = render.stretch(render.to_db(np.abs(hh) ** 2), meta["lo"], meta["hi"])
    assert np.array_equal(tiles.scene_grey(quad, w), want)
    c11 = (np.abs(hh) ** 2).astype(np.float32)
    cov = {
        "c11": c11,
        "c12": (hh * np.conj(hv)).astype(np.complex64),
        "c13": (hh * np.conj(vv)).astype(np.complex64),
        "c22": (np.abs(hv) ** 2).astype(np.float32),
        "c23": (hv * np.conj(vv)).astype(np.complex64),
        "c33": (np.abs(vv) ** 2).astype(np.float32),
    }
    (tmp_path / "c").mkdir()
    cj = make_job(tmp_path / "c", cov, mask, attrs={"kind": "covariance"}, channel=list(cov))
    m2 = render.job_stretch(cj)
    assert (m2["var"], m2["transform"]) == ("c11", "real")
    assert tiles.render_tile(cj, (H, W), 0, 0, 0, ("scene", "mask"))[:8] == b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------- STAC pieces


def test_footprint_is_a_counterclockwise_wgs84_ring():
    geom, bbox = stac.footprint(
        {"crs": "EPSG:32631", "transform": [500000.0, 10.0, 0.0, 5000000.0, 0.0, -10.0]}, (300, 260)
    )
    ring = geom["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 65
    area = sum(ring[i][0] * ring[i - 1][1] - ring[i - 1][0] * ring[i][1] for i in range(1, len(ring)))
    assert area > 0
    assert 2.9 < bbox[0] < bbox[2] < 3.1 and 45.1 < bbox[1] < bbox[3] < 45.2  # UTM 31N, 500 km E, 5000 km N
    assert stac.footprint({}, (10, 10)) == (None, None)
    off_earth = {"crs": "EPSG:4326", "transform": [0.0, 1.0, 0.0, 0.0, 0.0, -1.0]}  # 1000 degrees tall
    assert stac.footprint(off_earth, (1000, 1000)) == (None, None)


def test_sar_fields_only_when_known():
    s1 = {
        "sensor": "SENTINEL-1A IW",
        "product": "S1A_IW_GRDH_1SDV_20200101T000000",
        "polarisations": ["vh", "vv"],
        "looks": 4.4,
        "looks_source": "estimated",
        "pixel_spacing_m": [10.0, 10.0],
        "pixel_spacing_source": "GeoTIFF pixel size in projected EPSG:32631 ([row, column] ground spacing)",
    }
    f = stac.sar_fields(s1, {"intensity": "float32"})
    assert f["sar:instrument_mode"] == "IW" and f["sar:frequency_band"] == "C"
    assert f["sar:polarizations"] == ["VH", "VV"] and f["sar:product_type"] == "GRD"
    assert f["sar:looks_equivalent_number"] == 4.4 and "sar:pixel_spacing_range" not in f  # a map grid's spacing
    quad = stac.sar_fields(
        {"sensor": "RADARSAT-2 FQ", "looks_source": "single-look complex", "looks": 1.0},
        {"hh": "complex64", "hv": "complex64", "vv": "complex64"},
    )
    assert quad["sar:polarizations"] == ["HH", "HV", "VH", "VV"] and quad["sar:looks_range"] == 1
    assert stac.sar_fields({"sensor": "sarship-simulator", "polarizations": ["hh", "hv", "vv"]}, {}) == {}
    assert stac.sar_fields({"sensor": "SENTINEL-1A IW"}, {"intensity": "float32"}) == {}  # no polarization known


def test_rfc3339():
    assert stac.rfc3339("2021-06-01T10:20:30") == "2021-06-01T10:20:30Z"
    assert stac.rfc3339("2021-06-01T10:20:30.5Z") == "2021-06-01T10:20:30.500000Z"
    assert stac.rfc3339("2021-06-01T12:20:30+02:00") == "2021-06-01T10:20:30Z"
    assert stac.rfc3339("yesterday") is None and stac.rfc3339(None) is None
