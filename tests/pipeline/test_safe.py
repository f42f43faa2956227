"""Sentinel-1 GRD SAFE ingest (pipeline/readers/safe.py) on the real product layout of
../shared/data/real/sentinel1-safe (real annotation, constant pixel values: see its README),
plus the calibration arithmetic on a synthetic LUT.

Checked: the full-size GRD (16685 x 25788) ingests from the folder in a subprocess whose
peak RSS stays well below the size of the band as float32; shape, channel, spacing, times,
mode and GCPs (count and a corner against the annotation's geolocation grid, read here
with ElementTree independently of the reader) are right; the constant DN comes through as
DN^2; a zip built from the folder gives the same store; ``calibrate_sigma0`` /
``bilinear_lut`` match a hand computation; bad products fail with one line, exit 2.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.limits import InputLimits
from sarship.pipeline.readers.safe import bilinear_lut, calibrate_sigma0

SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
H, W = 16685, 25788
#: The samples' constant pixels are zstd strips declaring ~1900:1 (GRD) and ~3000:1 (SLC IW1)
#: decoded bytes per byte of file, ~33000:1 and ~53000:1 deflated in a zip: by ``--max-ratio``
#: they are decompression bombs (a real measurement is uncompressed, ~1:1, a few to one
#: zipped), so the tests that read them raise the limit.
SAMPLE_RATIO = 1e5


# --------------------------------------------------------------------------------------
# pure maths: no product needed
# --------------------------------------------------------------------------------------


def test_bilinear_lut_matches_hand_computation():
    lines = np.array([0.0, 10.0, 30.0])
    pixels = np.array([0.0, 4.0, 8.0])
    vals = np.array([[1.0, 2.0, 4.0], [3.0, 5.0, 9.0], [7.0, 7.0, 7.0]])
    got = bilinear_lut(lines, pixels, vals, 5, 21, 2, 7)
    # row 5: halfway between lines 0 and 10; col 2: halfway between pixels 0 and 4
    assert got[0, 0] == pytest.approx(0.25 * (1 + 2 + 3 + 5))
    # row 20 (index 15): halfway between lines 10 and 30; col 6: halfway between pixels 4, 8
    assert got[15, 4] == pytest.approx(0.25 * (5 + 9 + 7 + 7))
    # row 10, col 4: a grid node
    assert got[5, 2] == pytest.approx(5.0)
    # beyond the last line: the edge value is held
    assert bilinear_lut(lines, pixels, vals, 40, 41, 4, 5)[0, 0] == pytest.approx(7.0)


def test_calibrate_sigma0_hand_computation():
    dn = np.array([[100, 0], [30, 65535]], np.uint16)
    a = np.array([[500.0, 500.0], [600.0, 700.0]])
    noise = np.array([[400.0, 0.0], [1000.0, 0.0]])
    got = calibrate_sigma0(dn, a, noise)
    want = np.array([[(100.0**2 - 400) / 500**2, 0.0], [0.0, 65535.0**2 / 700**2]])  # 30^2 - 1000 < 0 -> 0
    np.testing.assert_allclose(got, want, rtol=1e-6)
    np.testing.assert_allclose(calibrate_sigma0(dn, a), np.square(dn.astype(float)) / a**2, rtol=1e-6)
    assert got.dtype == np.float32


# --------------------------------------------------------------------------------------
# the real GRD layout
# --------------------------------------------------------------------------------------


def _annotation_grid(safe: Path) -> tuple[list[tuple[int, int, float, float]], dict[str, str]]:
    ann = next((safe / "annotation").glob("s1?-iw-grd-vv-*.xml"))
    root = ET.parse(ann).getroot()
    pts = [
        (
            int(p.findtext("line")),
            int(p.findtext("pixel")),
            float(p.findtext("latitude")),
            float(p.findtext("longitude")),
        )
        for p in root.iter("geolocationGridPoint")
    ]
    info = root.find(".//imageAnnotation/imageInformation")
    return pts, {e.tag: e.text for e in info}


@pytest.fixture(scope="module")
def grd_store(tmp_path_factory):
    """The full-size GRD ingested from the folder in a fresh process: (store path, peak RSS bytes)."""
    if GRD is None:
        pytest.skip(f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
    if not Path("/proc/self/status").is_file():
        pytest.skip("peak RSS is read from /proc/self/status (Linux)")
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    out = tmp_path_factory.mktemp("safe") / "grd.zarr"
    # VmHWM is this process's own high-water mark: ru_maxrss would carry over the peak of the
    # pytest worker that spawned it (Linux keeps the parent's high-water mark across vfork+exec)
    code = (
        "import sys; from sarship.pipeline.readers import ingest; "
        "from sarship.pipeline.readers import InputLimits; "
        "ingest([sys.argv[1]], sys.argv[2], limits=InputLimits(max_ratio=1e5)); "
        "print(next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmHWM')))"
    )
    r = subprocess.run([sys.executable, "-c", code, str(GRD), str(out)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return out, int(r.stdout.split()[-1])


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
class TestGRD:
    def test_shape_channels_metadata(self, grd_store):
        from sarship.pipeline.scene import open_scene

        sc = open_scene(grd_store[0])
        _, info = _annotation_grid(GRD)
        assert sc.shape == (H, W) == (int(info["numberOfLines"]), int(info["numberOfSamples"]))
        assert sc.kind == "intensity" and list(sc.variables) == ["intensity"]
        a = sc.attrs
        assert a["channels"] == ["vv"] and a["polarisations"] == ["vv"]
        assert a["pixel_spacing_m"] == [float(info["azimuthPixelSpacing"]), float(info["rangePixelSpacing"])]
        assert a["mode"] == "IW" and a["product_type"] == "GRD (GRDH)"
        assert a["acquisition_start"] == "2021-04-01T05:26:23.794457"
        assert a["acquisition_stop"] == "2021-04-01T05:26:48.793373"
        assert a["acquired"] == a["acquisition_start"] and a["sensor"] == "SENTINEL-1B"
        assert a["product"] == GRD.name
        assert a["calibration"] == "none (no calibration annotation in the product)"
        assert a["looks"] == 4.4 and "nominal" in a["looks_note"]

    def test_gcps_match_the_annotation_grid(self, grd_store):
        from sarship.pipeline.scene import open_scene

        gcps = open_scene(grd_store[0]).attrs["gcps"]
        pts, _ = _annotation_grid(GRD)
        assert len(gcps) == len(pts) == 210
        want = {(r, c): (lat, lon) for r, c, lat, lon in pts}
        for g in gcps:
            lat, lon = want[(int(g["row"]), int(g["col"]))]
            assert (g["y"], g["x"]) == pytest.approx((lat, lon), abs=1e-9)
        # the annotation indexes pixels; the gcps give their centres (pixel-is-area: + 1/2)
        assert all(g["row"] % 1 == 0.5 and g["col"] % 1 == 0.5 for g in gcps)
        corner = next(g for g in gcps if g["row"] == H - 0.5 and g["col"] == W - 0.5)
        assert (corner["y"], corner["x"]) == pytest.approx(want[(H - 1, W - 1)], abs=1e-9)

    def test_constant_dn_comes_through_squared(self, grd_store):
        import tifffile

        from sarship.pipeline.scene import open_scene

        meas = next((GRD / "measurement").glob("*.tiff"))
        with tifffile.TiffFile(meas) as t:  # the sample's constant, read independently:
            # the first 64 strips' first 64 samples (the 860 MB page's [:64, :64]), not the page
            strips = itertools.islice(t.pages[0].segments(), 64)
            dn = float(np.mean([seg.reshape(-1)[:64] for seg, _, _ in strips]))
        v = open_scene(grd_store[0]).array("intensity")
        for r, c in [(0, 0), (H - 1, W - 1), (8000, 12000), (H - 1, 0)]:
            assert float(v[r, c]) == dn * dn

    def test_peak_memory_bounded(self, grd_store):
        full = H * W * 4  # the band as float32
        assert grd_store[1] < 0.4 * full, f"peak RSS {grd_store[1] / 2**20:.0f} MiB vs band {full / 2**20:.0f} MiB"

    # slow (a second full ingest of the band, ~25 s of the 2-core machine): a GRD zip is ingested in
    # the default run by test_safe_slc.test_inbox_ingests_a_grd_zip_and_quarantines_a_multi_swath_slc_zip
    @pytest.mark.slow
    def test_zip_gives_the_same_store(self, grd_store, tmp_path):
        from sarship.pipeline.readers import ingest
        from sarship.pipeline.scene import open_scene

        z = tmp_path / (GRD.stem + ".zip")
        with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:  # ~1 MB: the TIFF is compressed
            for f in sorted(GRD.rglob("*")):
                if f.is_file():
                    zf.write(f, f"{GRD.name}/{f.relative_to(GRD)}")
        sz = ingest([z], tmp_path / "z.zarr", limits=InputLimits(max_ratio=SAMPLE_RATIO))
        sd = open_scene(grd_store[0])
        assert sz.shape == sd.shape
        assert {k: v for k, v in sz.attrs.items() if k != "source"} == {
            k: v for k, v in sd.attrs.items() if k != "source"
        }
        a, b = sz.array("intensity"), sd.array("intensity")
        t = sd.attrs["tile"]
        for r in range(0, H, t):  # tile by tile: never both whole bands at once
            np.testing.assert_array_equal(a[r : r + t, :], b[r : r + t, :])


# --------------------------------------------------------------------------------------
# errors: one line, exit 2, nothing left behind
# --------------------------------------------------------------------------------------


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "sarship.cli", *map(str, args)], capture_output=True, text=True, timeout=120
    )


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
def test_safe_without_measurement_fails_one_line(tmp_path):
    pytest.importorskip("xarray_sentinel")
    bad = tmp_path / GRD.name
    (bad / "annotation").mkdir(parents=True)
    (bad / "manifest.safe").write_bytes((GRD / "manifest.safe").read_bytes())
    for f in (GRD / "annotation").glob("*.xml"):
        (bad / "annotation" / f.name).write_bytes(f.read_bytes())
    r = _cli("ingest", bad, "--out", tmp_path / "o.zarr")
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "without measurement" in r.stderr, r.stderr
    assert not (tmp_path / "o.zarr").exists()


def test_not_a_safe_folder_fails_one_line(tmp_path):
    d = tmp_path / "X.SAFE"
    d.mkdir()
    (d / "readme.txt").write_text("no manifest")
    r = _cli("ingest", d, "--out", tmp_path / "o.zarr")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "manifest.safe" in r.stderr, r.stderr
    z = tmp_path / "trunc.zip"
    z.write_bytes(b"PK\x03\x04" + b"\x00" * 40)  # a truncated zip
    r = _cli("ingest", z, "--out", tmp_path / "o.zarr")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "zip" in r.stderr, r.stderr
    assert not (tmp_path / "o.zarr").exists()


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
def test_missing_dependency_names_the_extra(tmp_path, monkeypatch):
    from sarship.pipeline.readers import ingest

    monkeypatch.setitem(sys.modules, "xarray_sentinel", None)  # import fails as if not installed
    with pytest.raises(InputError, match=r"pip install 'sarship\[safe\]'") as e:
        ingest([GRD], tmp_path / "o.zarr")
    assert "\n" not in str(e.value)
    assert not (tmp_path / "o.zarr").exists()


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
def test_limits_checked_before_any_pixel(tmp_path):
    pytest.importorskip("xarray_sentinel")
    from sarship.pipeline.readers import InputLimits, ingest

    with pytest.raises(InputError, match=r"4\.3e\+08 pixels, above the limit of 1e\+08 \(--max-pixels\)"):
        ingest([GRD], tmp_path / "o.zarr", limits=InputLimits(max_pixels=1e8))
    strip = W * 2  # one uint16 row per zstd strip in the sample
    with pytest.raises(InputError, match=r"strip/tile of measurement/.*\(--max-chunk-mb\)"):
        ingest([GRD], tmp_path / "o.zarr", limits=InputLimits(max_chunk_mb=0.9 * strip / 2**20))
    assert not (tmp_path / "o.zarr").exists()


SLC = next(iter(sorted(SAFE_DIR.glob("S1B_IW_SLC_*.SAFE"))), None) if SAFE_DIR.is_dir() else None


def test_azimuth_noise_blocks_hand_computation():
    from sarship.pipeline.readers.safe import azimuth_noise

    blocks = [
        (0, 9, 0, 4, np.array([0.0, 9.0]), np.array([1.0, 10.0])),
        (0, 9, 5, 9, np.array([0.0, 9.0]), np.array([2.0, 2.0])),
    ]
    got = azimuth_noise(blocks, 2, 12, 3, 8)
    assert got[0, 0] == pytest.approx(3.0) and got[0, 1] == pytest.approx(3.0)  # row 2, cols 3-4: block 1
    assert got[7, 1] == pytest.approx(10.0)  # row 9
    assert got[0, 2] == pytest.approx(2.0)  # col 5: block 2
    assert got[8, 0] == 1.0  # row 10: no block


def _lut_from_xml(path: Path, vector: str, name: str):
    root = ET.parse(path).getroot()
    vecs = list(root.iter(vector))
    lines = np.array([int(v.findtext("line")) for v in vecs], float)
    pix = np.array(vecs[0].findtext("pixel").split(), float)
    vals = np.array([np.array(v.findtext(name).split(), float) for v in vecs])
    return lines, pix, vals


@pytest.mark.skipif(GRD is None or SLC is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
@pytest.mark.parametrize("with_noise", [False, True])
def test_calibration_and_noise_wired_from_the_annotation(tmp_path, with_noise):
    """The GRD layout given a real calibration (and noise) annotation (the SLC sample's VV
    IW1 vectors, renamed to the GRD's file name): sigma0 at sampled pixels equals a hand
    computation from the XML read with ElementTree (bilinear between the bracketing vectors)."""
    pytest.importorskip("xarray_sentinel")
    import shutil

    from sarship.pipeline.readers.entry import _open_source

    prod = tmp_path / GRD.name
    shutil.copytree(GRD, prod, copy_function=shutil.copyfile)  # writable copies of read-only samples
    base = next((prod / "annotation").glob("s1?-iw-grd-vv-*.xml")).stem
    (prod / "annotation" / "calibration").mkdir()
    cal = next((SLC / "annotation" / "calibration").glob("calibration-s1b-iw1-slc-vv-*.xml"))
    shutil.copy(cal, prod / "annotation" / "calibration" / f"calibration-{base}.xml")
    noise_xml = next((SLC / "annotation" / "calibration").glob("noise-s1b-iw1-slc-vv-*.xml"))
    if with_noise:
        shutil.copy(noise_xml, prod / "annotation" / "calibration" / f"noise-{base}.xml")
    src = _open_source(prod, limits=InputLimits(max_ratio=SAMPLE_RATIO))
    try:
        a = src.read(600, 640, 50, 130)[:, :, 0]
    finally:
        src.close()
    lines, pix, vals = _lut_from_xml(cal, "calibrationVector", "sigmaNought")
    nl, npix, nv = _lut_from_xml(noise_xml, "noiseRangeVector", "noiseRangeLut")
    az = ET.parse(noise_xml).getroot().find(".//noiseAzimuthVector")
    az_l = np.array(az.findtext("line").split(), float)
    az_v = np.array(az.findtext("noiseAzimuthLut").split(), float)

    def bil(L, P, V, r, c):
        i = np.searchsorted(L, r, side="right") - 1
        j = np.searchsorted(P, c, side="right") - 1
        t, u = (r - L[i]) / (L[i + 1] - L[i]), (c - P[j]) / (P[j + 1] - P[j])
        return (
            (1 - t) * (1 - u) * V[i, j]
            + (1 - t) * u * V[i, j + 1]
            + t * (1 - u) * V[i + 1, j]
            + t * u * V[i + 1, j + 1]
        )

    for r, c in [(600, 50), (611, 77), (639, 129)]:
        A = bil(lines, pix, vals, r, c)
        n = bil(nl, npix, nv, r, c) * np.interp(r, az_l, az_v) if with_noise else 0.0
        want = max(1.0 - n, 0.0) / A**2  # the sample's DN is 1
        assert a[r - 600, c - 50] == pytest.approx(want, rel=1e-5, abs=1e-12)
    if with_noise:  # the sample's noise exceeds DN^2 = 1 there: clipped to 0, not 1/A^2
        assert np.all(a == 0.0)
    else:
        assert np.all(a > 0)


@pytest.mark.skipif(GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
def test_dual_pol_channels_and_band(tmp_path):
    """The sample's VV measurement also given as VH (its annotation is there): two channels
    in the product's order, ``--band`` picks the one stored as ``intensity``."""
    pytest.importorskip("xarray_sentinel")
    import shutil

    from sarship.pipeline.readers import ingest
    from sarship.pipeline.readers.entry import _open_source
    from sarship.pipeline.readers.plan import _plan

    prod = tmp_path / GRD.name
    shutil.copytree(GRD, prod, copy_function=shutil.copyfile)  # writable copies of read-only samples
    vv = next((prod / "measurement").glob("*-vv-*.tiff"))
    vh_ann = next((prod / "annotation").glob("*-vh-*.xml"))
    shutil.copy(vv, prod / "measurement" / (vh_ann.stem + ".tiff"))
    src = _open_source(prod, limits=InputLimits(max_ratio=SAMPLE_RATIO))
    try:
        assert src.nbands == 2 and src.meta["pols"] == ["vv", "vh"]
        plan = _plan([src], "auto", "vh", None)
        assert plan.attrs["channels"] == ["vv", "vh"] and plan.attrs["intensity_band"] == "vh"
        assert set(plan.variables) == {"intensity_vv", "intensity_vh", "intensity"}
        with pytest.raises(InputError, match="--band hh: no such band"):
            _plan([src], "auto", "hh", None)
    finally:
        src.close()
    with pytest.raises(InputError, match="--kind amplitude does not apply"):
        ingest([prod], tmp_path / "o.zarr", kind="amplitude")
    assert not (tmp_path / "o.zarr").exists()
