"""Issue 30: hostile and damaged Sentinel-1 SAFE products are refused in one line, before any
pixel is read (pipeline/readers/safe.py, limits.py).

The products are small copies of the shared GRD sample (../shared/data/real/sentinel1-safe:
its real manifest and VV annotation) with an edited annotation, a measurement GeoTIFF made
here (sparse: a header and tile tables, no pixel bytes) and, for calibration, the SLC
sample's real calibration/noise vectors renamed to the GRD's file name (as tests/pipeline/test_safe.py
does). Checked: ``--max-ratio`` and ``--max-pixels`` apply to SAFE folders and zips (the
annotation's size against the measurement's bytes, compressed in the zip or on disk), a zip
member inflating beyond its ratio or an XML member beyond ``--max-xml-mb`` is refused from
the zip's directory (nothing inflated: quick, low memory), the annotation's size must be the
measurement's, and a calibration or noise LUT with a NaN, infinite or non-positive node is
refused (it would blank or zero the scene: "0 ships, exit 0").
"""

from __future__ import annotations

import re
import resource
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import InputLimits, ingest
from sarship.pipeline.simulate.crafted import crafted_tiff

REPO = Path(__file__).resolve().parents[2]
SAFE_DIR = REPO.parent / "shared" / "data" / "real" / "sentinel1-safe"
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
SLC = next(iter(sorted(SAFE_DIR.glob("S1B_IW_SLC_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
H, W = 16685, 25788  # the sample's annotation

pytestmark = pytest.mark.skipif(GRD is None or SLC is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")

#: no ratio limit: a sparse measurement of the right size gets past it to the checks after it
NO_RATIO = InputLimits(max_ratio=1e15)


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "sarship", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=False,
    )


def _product(
    tmp_path: Path,
    lines: int = H,
    samples: int = W,
    tiff: tuple[int, int] | None = None,
    calibration: str | None = None,
    noise: str | None = None,
) -> Path:
    """A GRD SAFE folder: the sample's manifest and VV annotation declaring ``lines x samples``,
    a sparse float32 measurement of ``tiff`` (default: the annotation's size) and optionally
    the given calibration / noise XML texts."""
    pytest.importorskip("xarray_sentinel")
    prod = tmp_path / GRD.name
    (prod / "annotation" / "calibration").mkdir(parents=True)
    (prod / "measurement").mkdir()
    shutil.copyfile(GRD / "manifest.safe", prod / "manifest.safe")
    ann = next((GRD / "annotation").glob("s1?-iw-grd-vv-*.xml"))
    text = ann.read_text()
    text = text.replace(f"<numberOfLines>{H}</numberOfLines>", f"<numberOfLines>{lines}</numberOfLines>")
    text = text.replace(f"<numberOfSamples>{W}</numberOfSamples>", f"<numberOfSamples>{samples}</numberOfSamples>")
    (prod / "annotation" / ann.name).write_text(text)
    th, tw = tiff or (lines, samples)
    crafted_tiff(prod / "measurement" / f"{ann.stem}.tiff", th, tw, tile=1024, counts_zero=True)  # no pixel bytes
    if calibration is not None:
        (prod / "annotation" / "calibration" / f"calibration-{ann.stem}.xml").write_text(calibration)
    if noise is not None:
        (prod / "annotation" / "calibration" / f"noise-{ann.stem}.xml").write_text(noise)
    return prod


def _zip(prod: Path, dest: Path, extra: dict[str, int] | None = None) -> Path:
    """``prod`` zipped (deflate); ``extra``: member name -> bytes of spaces replacing that member
    (streamed in: the test never holds it)."""
    extra = extra or {}
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(prod.rglob("*")):
            rel = str(f.relative_to(prod))
            if f.is_file() and rel not in extra:
                z.write(f, f"{prod.name}/{rel}")
        for rel, n in extra.items():
            with z.open(f"{prod.name}/{rel}", "w", force_zip64=True) as out:
                block = b" " * 2**20
                for _ in range(n // 2**20):
                    out.write(block)
    return dest


def _one_line_exit_2(r: subprocess.CompletedProcess, *words: str) -> None:
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in r.stderr, r.stderr


# --------------------------------------------------------------------------------------
# sizes: the ratio, pixel and XML limits
# --------------------------------------------------------------------------------------


def test_tiny_zip_declaring_a_huge_scene_is_refused_by_max_ratio(tmp_path):
    """A ~0.3 MB zip whose annotation and measurement declare 44000 x 44000 pixels (7 GiB of
    float32 in a sparse TIFF): exit 2 and one line naming --max-ratio, nothing written."""
    z = _zip(_product(tmp_path, 44000, 44000), tmp_path / "bomb.zip")
    assert z.stat().st_size < 2**20
    r = _cli("ingest", z, "--out", tmp_path / "o.zarr")
    _one_line_exit_2(r, "bomb.zip", "measurement/", "--max-ratio", "decompression bomb")
    assert not (tmp_path / "o.zarr").exists()
    # the folder too; and the pixel limit from the annotation before it
    prod = tmp_path / GRD.name
    with pytest.raises(InputError, match=r"measurement/.*\(on disk\).*--max-ratio"):
        ingest([prod], tmp_path / "o.zarr")
    with pytest.raises(InputError, match=r"1\.94e\+09 pixels, above the limit of 1e\+09 \(--max-pixels\)"):
        ingest([prod], tmp_path / "o.zarr", limits=InputLimits(max_pixels=1e9))
    assert not (tmp_path / "o.zarr").exists()


def test_zip_member_inflating_absurdly_is_refused_from_the_directory(tmp_path):
    """An annotation replaced by 80 MiB of spaces (~80 KiB deflated, ~1030:1) in a small zip:
    refused from the zip's directory, without inflating it, by the XML size cap (--max-xml-mb)
    and, with that raised, by the member's ratio (--max-ratio): time and memory stay low."""
    prod = _product(tmp_path)
    ann = next((prod / "annotation").glob("*.xml")).relative_to(prod)
    z = _zip(prod, tmp_path / "xml_bomb.zip", {str(ann): 80 * 2**20})
    assert z.stat().st_size < 2**20
    t0 = time.perf_counter()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match=r"annotation/.* is 80 MiB, above the limit of 64 MiB .*--max-xml-mb") as e:
        ingest([z], tmp_path / "o.zarr")
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match=r"zip member annotation/.*\(ratio 10\d\d:1, .*--max-ratio.*bomb"):
        ingest([z], tmp_path / "o.zarr", limits=InputLimits(max_xml_mb=100))
    assert time.perf_counter() - t0 < 30  # inflating and parsing 80 MiB of XML is what would take long
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 64 * 1024  # KiB: never inflated
    r = _cli("ingest", z, "--out", tmp_path / "o.zarr", "--max-xml-mb", "8")
    _one_line_exit_2(r, "xml_bomb.zip", "above the limit of 8 MiB", "--max-xml-mb")
    assert not (tmp_path / "o.zarr").exists()


def test_xml_reads_stop_at_the_cap_whatever_the_header_says(tmp_path):
    """The reader of an XML member inflates at most the cap (+1 byte), in chunks, and refuses
    in one line: a member whose directory entry understates its size cannot go further."""
    from sarship.pipeline.readers.safe import _Product, safe_layout

    prod = _product(tmp_path)
    ann = str(next((prod / "annotation").glob("*.xml")).relative_to(prod))
    product = _Product(prod, safe_layout(prod), InputLimits(max_xml_mb=0.5))
    with pytest.raises(InputError, match=r"inflates to more than 0\.5 MiB.*--max-xml-mb.*read stopped"):
        product.open_member(ann)
    product = _Product(prod, safe_layout(prod), InputLimits(max_xml_mb=2))  # the real 1.6 MiB fits
    assert product.open_member(ann).read() == (prod / ann).read_bytes()


def test_annotation_size_must_be_the_measurements(tmp_path):
    """An annotation of 100 x 100 over a full-size measurement used to crop it silently, and
    0 lines gave a 0 x 25788 scene: both refused in one line."""
    prod = _product(tmp_path, 100, 100, tiff=(H, W))
    r = _cli("ingest", prod, "--out", tmp_path / "o.zarr")
    _one_line_exit_2(r, "declares 100 x 100 pixels but the measurement", f"is {H} x {W}")
    shutil.rmtree(prod)
    prod = _product(tmp_path, 0, W, tiff=(H, W))
    with pytest.raises(InputError, match=r"declares an empty image \(0 x 25788 pixels\)"):
        ingest([prod], tmp_path / "o.zarr", limits=NO_RATIO)
    assert not (tmp_path / "o.zarr").exists()


# --------------------------------------------------------------------------------------
# calibration and noise LUTs
# --------------------------------------------------------------------------------------


def _cal_text() -> str:
    return next((SLC / "annotation" / "calibration").glob("calibration-s1b-iw1-slc-vv-*.xml")).read_text()


def _noise_text() -> str:
    return next((SLC / "annotation" / "calibration").glob("noise-s1b-iw1-slc-vv-*.xml")).read_text()


def _edit_values(text: str, tag: str, fn) -> str:
    """``text`` with ``fn(values, k)`` applied to the value list of the k-th ``<tag>`` element."""
    k = [0]

    def sub(m):
        vals = m.group(2).split()
        out = fn(vals, k[0])
        k[0] += 1
        return f"{m.group(1)}{' '.join(out)}</{tag}>"

    return re.sub(rf"(<{tag}[^>]*>)([^<]*)</{tag}>", sub, text)


def test_bad_sigma_nought_nodes_are_refused(tmp_path):
    """One NaN node made 99.9 % of the scene NaN, an all-NaN or infinite LUT an all-NaN or
    all-zero scene (0 ships, exit 0): such a LUT is refused in one line naming the product and
    the LUT (every rule of the check: test_check_lut_rules)."""
    from sarship.pipeline.readers.entry import _open_source

    one_nan = _edit_values(
        _cal_text(), "sigmaNought", lambda vals, k: ["NaN" if (k == 3 and i == 7) else v for i, v in enumerate(vals)]
    )
    prod = _product(tmp_path, calibration=one_nan)
    with pytest.raises(InputError) as e:
        _open_source(prod, limits=NO_RATIO)
    msg = str(e.value)
    assert "\n" not in msg and GRD.name in msg and "sigmaNought calibration LUT of VV (calibration-" in msg, msg
    assert "has 1 of" in msg and "not finite positive" in msg and ": nan)" in msg, msg
    shutil.rmtree(prod)
    prod = _product(tmp_path, calibration=_edit_values(_cal_text(), "sigmaNought", lambda vals, k: ["INF"] * len(vals)))
    r = _cli("ingest", prod, "--out", tmp_path / "o.zarr", "--max-ratio", "1e15")
    _one_line_exit_2(r, "sigmaNought calibration LUT of VV", "not finite positive", ": inf)")
    assert not (tmp_path / "o.zarr").exists()


def test_bad_noise_nodes_are_refused_and_good_luts_pass(tmp_path):
    from sarship.pipeline.readers.entry import _open_source

    noisy = _edit_values(
        _noise_text(),
        "noiseRangeLut",
        lambda vals, k: ["NaN" if (k == 0 and i == 0) else v for i, v in enumerate(vals)],
    )
    prod = _product(tmp_path, calibration=_cal_text(), noise=noisy)
    with pytest.raises(InputError, match=r"noise range LUT of VV .* 1 of \d+ nodes that are not finite non-negative"):
        _open_source(prod, limits=NO_RATIO)
    shutil.rmtree(prod)
    prod = _product(tmp_path, calibration=_cal_text(), noise=_noise_text())  # the real vectors: accepted
    src = _open_source(prod, limits=NO_RATIO)
    src.close()


def test_check_lut_rules():
    from sarship.pipeline.readers.safe import check_lut

    lines, pixels = np.array([0.0, 10.0]), np.array([0.0, 5.0, 9.0])
    check_lut("p", "LUT", lines, pixels, np.ones((2, 3)))
    check_lut("p", "noise", lines, pixels, np.zeros((2, 3)), positive=False)
    for vals, match in (
        (np.zeros((2, 3)), "finite positive"),
        (np.full((2, 3), np.inf), "6 of 6"),
        (np.ones((3, 3)), r"\(3, 3\) values for 2 lines x 3 pixels"),
    ):
        with pytest.raises(InputError, match=match):
            check_lut("p", "LUT", lines, pixels, vals)
    with pytest.raises(InputError, match="pixel coordinates that are not finite and increasing"):
        check_lut("p", "LUT", lines, np.array([0.0, 5.0, 5.0]), np.ones((2, 3)))
