"""Issue 11 ("Data safety and clear errors"): ingest refuses kinds that contradict the data,
and reads the metadata an OpenSARShip-style product carries (SNAP ``Abstracted_Metadata``
sidecar beside the chip or in the enclosing product folders, ``Metedata.xml`` included).

Real-data tests read ``../shared/data/real/opensarship`` (relative to the repository root)
and skip when it is absent.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import tifffile

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import PROBE_SIDE, ingest
from sarship.pipeline.scene import open_scene

REPO = Path(__file__).resolve().parents[2]
REAL = REPO.parent / "shared" / "data" / "real"
OSS = REAL / "opensarship"
needs_oss = pytest.mark.skipif(
    not OSS.is_dir(), reason=f"OpenSARShip chips not found at {OSS} (see shared/data/README.md)"
)


def leftovers(folder: Path) -> list[str]:
    return sorted(os.listdir(folder))


def write_tif(path, a, **kw):
    """A TIFF whose last axis (if any) is the bands (samples of one page)."""
    if a.ndim == 3:
        kw.setdefault("photometric", "minisblack")
        kw.setdefault("planarconfig", "contig")
    tifffile.imwrite(path, a, **kw)


def read(scene, name):
    return np.asarray(scene.array(name)[...])


def snap_xml(
    pols=("VV",), sample_type="COMPLEX", az_looks=1.0, rg_looks=1.0, az=13.9, rg=2.33, band_pols_only=False
) -> str:
    """A minimal SNAP metadata file (the OpenSARShip ``Metedata.xml``)."""
    attrs = [
        ("PRODUCT", "S1A_TEST_PRODUCT"),
        ("MISSION", "SENTINEL-1A"),
        ("ACQUISITION_MODE", "IW"),
        ("first_line_time", "06-JUN-2016 22:12:31.646524"),
        ("SAMPLE_TYPE", sample_type),
        ("azimuth_looks", az_looks),
        ("range_looks", rg_looks),
        ("azimuth_spacing", az),
        ("range_spacing", rg),
    ]
    if not band_pols_only:
        attrs += [(f"mds{i + 1}_tx_rx_polar", pols[i] if i < len(pols) else "-") for i in range(4)]
    body = "".join(f'    <attrib name="{k}" value="{v}" />\n' for k, v in attrs)
    if band_pols_only:
        body += "".join(
            f'    <Band_IW1_{p}>\n      <attrib name="polarization" value="{p}" />\n    </Band_IW1_{p}>\n' for p in pols
        )
    return f'<?xml version="1.0"?>\n<Metadata>\n  <Abstracted_Metadata>\n{body}  </Abstracted_Metadata>\n</Metadata>\n'


def slc_bands(shape=(40, 40), npol=1, seed=0) -> np.ndarray:
    """Real (re, im) bands of single-look complex data: about half the values negative."""
    return np.random.default_rng(seed).normal(0, 30, (*shape, 2 * npol)).astype(np.float32)


# --------------------------------------------------------------------------------------
# 1. kinds that contradict the data
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["intensity", "amplitude"])
def test_complex_tiff_bands_refused_as_real_kind(tmp_path, kind):
    prod = tmp_path / "S1A_TEST_PRODUCT"
    (prod / "Patch").mkdir(parents=True)
    (prod / "Metedata.xml").write_text(snap_xml(pols=("VH", "VV")))
    chip = prod / "Patch" / "Cargo_x1_y2.tif"
    write_tif(chip, slc_bands(npol=2))
    with pytest.raises(InputError) as e:
        ingest([chip], tmp_path / "o.zarr", kind=kind)
    msg = str(e.value)
    assert "\n" not in msg
    assert "Cargo_x1_y2.tif" in msg and f"--kind {kind}" in msg and "complex" in msg and "re/im" in msg
    assert "--kind slc" in msg and "auto" in msg
    assert not (tmp_path / "o.zarr").exists() and leftovers(tmp_path) == ["S1A_TEST_PRODUCT"]
    sc = ingest([chip], tmp_path / "o.zarr")  # auto: the two complex channels
    assert sc.attrs["kind"] == "slc" and sc.attrs["channels"] == ["vh", "vv"]


def test_complex_dtype_refused_as_real_kind(tmp_path):
    np.save(tmp_path / "c.npy", (np.ones((8, 8)) + 1j).astype(np.complex64))
    write_tif(tmp_path / "c.tif", (np.ones((8, 8)) + 1j).astype(np.complex64))
    for f in ("c.npy", "c.tif"):
        with pytest.raises(InputError) as e:
            ingest([tmp_path / f], tmp_path / "o.zarr", kind="intensity")
        msg = str(e.value)
        assert f in msg and "--kind intensity, but the data is complex" in msg and "--kind slc" in msg


@pytest.mark.parametrize("kind", ["intensity", "amplitude"])
def test_negative_values_refused_as_real_kind(tmp_path, kind):
    write_tif(tmp_path / "neg.tif", slc_bands())  # no metadata: only the values tell
    with pytest.raises(InputError) as e:
        ingest([tmp_path / "neg.tif"], tmp_path / "o.zarr", kind=kind)
    msg = str(e.value)
    assert "\n" not in msg and "neg.tif" in msg and f"--kind {kind}" in msg and "negative" in msg
    assert leftovers(tmp_path) == ["neg.tif"]


def test_negative_tile_outside_the_probe_aborts_and_leaves_nothing(tmp_path):
    side = 3 * PROBE_SIDE + 200  # the probe windows miss the corner
    a = np.random.default_rng(1).gamma(2.0, 0.5, (side, side)).astype(np.float32)
    a[3, 5] = -0.25
    write_tif(tmp_path / "late.tif", a)
    np.save(tmp_path / "late.npy", a)
    ok = np.ones((16, 16), np.float32)
    np.save(tmp_path / "ok.npy", ok)
    ingest([tmp_path / "ok.npy"], tmp_path / "o.zarr", tile=8)  # an existing scene at out
    for f, kind in (("late.tif", "auto"), ("late.tif", "intensity"), ("late.tif", "amplitude"), ("late.npy", "auto")):
        with pytest.raises(InputError) as e:
            ingest([tmp_path / f], tmp_path / "o.zarr", kind=kind, tile=256)
        msg = str(e.value)
        assert "\n" not in msg and f in msg and "negative" in msg and "-0.25" in msg, msg
        assert leftovers(tmp_path) == ["late.npy", "late.tif", "o.zarr", "ok.npy"]
        np.testing.assert_array_equal(read(open_scene(tmp_path / "o.zarr"), "intensity"), ok)


def test_negative_npy_refused_under_auto(tmp_path):
    np.save(tmp_path / "db.npy", np.random.default_rng(2).normal(-10, 3, (32, 32)).astype(np.float32))
    with pytest.raises(InputError, match=r"db\.npy.*negative"):
        ingest([tmp_path / "db.npy"], tmp_path / "o.zarr")


def test_nan_and_nodata_are_not_errors(tmp_path):
    a = np.random.default_rng(3).gamma(2.0, 0.5, (64, 64)).astype(np.float32)
    a[:4] = np.nan
    a[:, :6] = -9999.0
    write_tif(tmp_path / "nd.tif", a, extratags=[(42113, "s", 0, "-9999", False)])
    for kind in ("auto", "intensity", "amplitude"):
        sc = ingest([tmp_path / "nd.tif"], tmp_path / f"{kind}.zarr", kind=kind, tile=32)
        out = read(sc, "intensity")
        assert np.isnan(out[4:, :6]).all() and np.isnan(out[:4, 6:]).all()  # declared no-data: NaN
    b = a.copy()
    b[:, :6] = 1.0
    np.save(tmp_path / "nan.npy", b)
    ingest([tmp_path / "nan.npy"], tmp_path / "nan.zarr", tile=32)


def test_cli_kind_intensity_of_slc_exit_2_one_line(tmp_path):
    prod = tmp_path / "P"
    (prod / "Patch").mkdir(parents=True)
    (prod / "Metedata.xml").write_text(snap_xml(pols=("VH", "VV")))
    write_tif(prod / "Patch" / "c.tif", slc_bands(npol=2))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "ingest",
            str(prod / "Patch" / "c.tif"),
            "--out",
            str(tmp_path / "o.zarr"),
            "--kind",
            "intensity",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=False,
    )
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "c.tif" in lines[0] and "complex" in lines[0], r.stderr
    assert not (tmp_path / "o.zarr").exists()


# --------------------------------------------------------------------------------------
# 2. product metadata from the sidecar (synthetic)
# --------------------------------------------------------------------------------------


def test_metedata_xml_in_enclosing_product_folder(tmp_path):
    # <scenes>/<product>/Patch/<chip>.tif + <product>/Metedata.xml, single-pol VV product
    prod = tmp_path / "scenes" / "S1A_IW_SLC__1SSV_TEST"
    (prod / "Patch").mkdir(parents=True)
    (prod / "Metedata.xml").write_text(snap_xml(pols=("VV",), az=13.93, rg=2.33))
    chip = prod / "Patch" / "Tanker_x10_y20.tif"
    write_tif(chip, slc_bands())
    sc = ingest([chip], tmp_path / "o.zarr")
    assert sc.attrs["kind"] == "slc" and sc.attrs["channels"] == ["vv"]
    assert sc.attrs["polarisations"] == ["vv"]
    assert sc.attrs["pixel_spacing_m"] == [13.93, 2.33]
    assert "Metedata.xml" in sc.attrs["pixel_spacing_source"]
    assert sc.attrs["looks"] == 1.0 and sc.attrs["looks_source"] == "attribute"
    assert sc.attrs["sensor"] == "SENTINEL-1A IW" and sc.attrs["product"] == "S1A_TEST_PRODUCT"
    assert sc.attrs["acquired"].startswith("2016-06-06T22:12:31")
    assert sc.attrs["metadata_sidecar"] == os.path.join("..", "Metedata.xml")
    assert "SAMPLE_TYPE=COMPLEX" in sc.attrs["quantity_rule"]


def test_grd_chip_nominal_looks_from_nested_sidecar(tmp_path):
    # GRD amplitude chip two folders below the product's metadata: looks = 1 x 5 (not estimated)
    prod = tmp_path / "S1A_IW_GRDH_TEST"
    (prod / "chips" / "Patch").mkdir(parents=True)
    (prod / "Metedata.xml").write_text(
        snap_xml(pols=("VH", "VV"), sample_type="DETECTED", rg_looks=5.0, az=10.0, rg=10.0)
    )
    amp = np.random.default_rng(4).integers(1, 400, (64, 64, 2)).astype(np.float32)
    chip = prod / "chips" / "Patch" / "Cargo_x1_y1.tif"
    write_tif(chip, amp)
    sc = ingest([chip], tmp_path / "o.zarr")
    assert sc.attrs["channels"] == ["vh", "vv"] and sc.attrs["kind"] == "intensity"
    assert sc.attrs["looks"] == 5.0 and sc.attrs["looks_source"] == "attribute"
    assert sc.attrs["pixel_spacing_m"] == [10.0, 10.0]


def test_one_channel_of_dual_pol_product_named_from_file_name(tmp_path):
    prod = tmp_path / "P"
    (prod / "Patch").mkdir(parents=True)
    (prod / "Metedata.xml").write_text(snap_xml(pols=("VH", "VV")))
    write_tif(prod / "Patch" / "Cargo_x1_y1_vv.tif", slc_bands())
    sc = ingest([prod / "Patch" / "Cargo_x1_y1_vv.tif"], tmp_path / "o.zarr")
    assert sc.attrs["channels"] == ["vv"] and sc.attrs["pixel_spacing_m"] == [13.9, 2.33]
    # one detected band of a VV product: the channel is named too
    (tmp_path / "Q" / "Patch").mkdir(parents=True)
    (tmp_path / "Q" / "Metedata.xml").write_text(snap_xml(pols=("VV",), sample_type="DETECTED"))
    write_tif(tmp_path / "Q" / "Patch" / "c.tif", np.full((16, 16), 3.5, np.float32))
    sc = ingest([tmp_path / "Q" / "Patch" / "c.tif"], tmp_path / "q.zarr")
    assert sc.attrs["channels"] == ["vv"]


def test_band_polarisations_when_no_mds_items(tmp_path):
    prod = tmp_path / "P"
    (prod / "Patch").mkdir(parents=True)
    (prod / "Metadata.xml").write_text(snap_xml(pols=("HH", "HV"), band_pols_only=True))
    write_tif(prod / "Patch" / "c.tif", slc_bands(npol=2))
    sc = ingest([prod / "Patch" / "c.tif"], tmp_path / "o.zarr")
    assert sc.attrs["channels"] == ["hh", "hv"]


def test_sidecar_search_is_bounded(tmp_path):
    from sarship.pipeline.readers.tiff import SIDECAR_LEVELS, _sidecar_candidates

    deep = tmp_path / "a" / "b" / "c" / "d" / "e"
    deep.mkdir(parents=True)
    write_tif(deep / "c.tif", slc_bands())
    (tmp_path / "a" / "Metedata.xml").write_text(snap_xml())  # 4 folders above the chip's: too far
    assert SIDECAR_LEVELS == 3
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr")
    assert "pixel_spacing_m" not in sc.attrs and "metadata_sidecar" not in sc.attrs
    (tmp_path / "a" / "b" / "Metedata.xml").write_text(snap_xml())  # 3 above: found
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr")
    assert sc.attrs["pixel_spacing_m"] == [13.9, 2.33]
    # never above the folder the user gave
    cands = _sidecar_candidates(deep / "c.tif", stop=tmp_path / "a" / "b" / "c")
    assert all(tmp_path / "a" / "b" / "c" in [c.parent, *c.parents] for c in cands)
    assert tmp_path / "a" / "b" / "Metedata.xml" not in cands
    # ingest honours the bound: with the chip's folder as the root, the product sidecar
    # 3 levels up is not read; with False, not even one beside the chip
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr", sidecar_root=deep)
    assert "pixel_spacing_m" not in sc.attrs and "metadata_sidecar" not in sc.attrs
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr", sidecar_root=tmp_path / "a" / "b")
    assert sc.attrs["pixel_spacing_m"] == [13.9, 2.33]
    (deep / "c.xml").write_text(snap_xml(az=7.0, rg=7.0))
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr", sidecar_root=False)
    assert "pixel_spacing_m" not in sc.attrs and "metadata_sidecar" not in sc.attrs
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr", sidecar_root=deep)
    assert sc.attrs["pixel_spacing_m"] == [7.0, 7.0]
    (deep / "c.xml").unlink()
    # a nearer sidecar wins over one further up; a non-SNAP xml is skipped
    (deep / "Metadata.xml").write_text("<ShipList/>")
    (tmp_path / "a" / "b" / "c" / "Metedata.xml").write_text(snap_xml(az=5.0, rg=4.0))
    sc = ingest([deep / "c.tif"], tmp_path / "o.zarr")
    assert sc.attrs["pixel_spacing_m"] == [5.0, 4.0]


# --------------------------------------------------------------------------------------
# 2. product metadata on the real OpenSARShip chips
# --------------------------------------------------------------------------------------


def _product_meta(xml: Path) -> dict:
    am = ET.parse(xml).getroot().find(".//Abstracted_Metadata")
    a = {e.get("name"): e.get("value") for e in am.findall("attrib")}
    pols = [a[f"mds{i}_tx_rx_polar"].lower() for i in range(1, 5) if a.get(f"mds{i}_tx_rx_polar", "-") != "-"]
    return {
        "pols": pols,
        "looks": float(a["azimuth_looks"]) * float(a["range_looks"]),
        "spacing": [float(a["azimuth_spacing"]), float(a["range_spacing"])],
        "complex": a["SAMPLE_TYPE"] == "COMPLEX",
    }


def _real_chips():
    out = []
    for prod in sorted(OSS.glob("S1A_*")):
        xml = prod / f"{prod.name}.xml"
        for sub in ("Patch", "Patch_Cal"):
            chips = sorted(glob.glob(str(prod / sub / "*.tif")))[:3]
            out += [(Path(c), xml, sub) for c in chips]
    return out


def _check_real(sc, meta, sub):
    assert sc.attrs["channels"] == meta["pols"]
    assert sc.attrs["looks"] == meta["looks"] and sc.attrs["looks_source"] == "attribute"
    assert sc.attrs["pixel_spacing_m"] == pytest.approx(meta["spacing"])
    if meta["complex"] and sub == "Patch":
        assert sc.attrs["kind"] == "slc"
        assert sc.attrs["looks"] == 1.0


@needs_oss
def test_real_opensarship_chips_read_product_metadata(tmp_path):
    chips = _real_chips()
    assert chips
    for k, (chip, xml, sub) in enumerate(chips):
        sc = ingest([chip], tmp_path / f"o{k}.zarr")
        _check_real(sc, _product_meta(xml), sub)


@needs_oss
def test_real_opensarship_chips_in_product_layout_with_metedata_xml(tmp_path):
    # the distribution's own layout: <product>/Patch/<chip>.tif beside <product>/Metedata.xml
    for k, (chip, xml, sub) in enumerate(_real_chips()):
        prod = tmp_path / "OpenSARShip" / chip.parents[1].name
        (prod / sub).mkdir(parents=True, exist_ok=True)
        if not (prod / "Metedata.xml").exists():
            shutil.copy(xml, prod / "Metedata.xml")
        shutil.copy(chip, prod / sub / chip.name)
        sc = ingest([prod / sub / chip.name], tmp_path / f"o{k}.zarr")
        _check_real(sc, _product_meta(xml), sub)
        assert sc.attrs["metadata_sidecar"] == os.path.join("..", "Metedata.xml")


@needs_oss
def test_real_slc_chip_as_intensity_refused(tmp_path):
    chip = next(c for c, _, sub in _real_chips() if "_SLC_" in str(c) and sub == "Patch")
    with pytest.raises(InputError) as e:
        ingest([chip], tmp_path / "o.zarr", kind="intensity")
    assert chip.name in str(e.value) and "complex" in str(e.value) and "\n" not in str(e.value)
    assert leftovers(tmp_path) == []


def test_infinite_intensity_is_refused_nan_is_no_data(tmp_path):
    """Issue 12: +inf in detected data is no measurement (all-inf input ended in an internal
    JSON error at detection): refused at ingest, wherever it lies; NaN stays a no-data pixel."""
    x = np.random.default_rng(3).gamma(2.0, 0.5, (300, 280)).astype(np.float32)
    y = x.copy()
    y[290:, 5:9] = np.inf  # outside the probe windows of the first tile row: found as the tile is written
    np.save(tmp_path / "inf.npy", y)
    with pytest.raises(InputError, match=r"infinite values \(40 pixels"):
        ingest([tmp_path / "inf.npy"], tmp_path / "o.zarr", tile=128)
    assert leftovers(tmp_path) == ["inf.npy"]
    write_tif(tmp_path / "inf.tif", y)
    with pytest.raises(InputError, match="infinite values"):
        ingest([tmp_path / "inf.tif"], tmp_path / "o.zarr", kind="amplitude")
    z = x.copy()
    z[:40] = np.nan
    np.save(tmp_path / "nan.npy", z)
    sc = ingest([tmp_path / "nan.npy"], tmp_path / "n.zarr")
    assert np.isnan(read(sc, "intensity")[:40]).all() and np.isfinite(read(sc, "intensity")[40:]).all()


def test_declared_zero_nodata_is_absent_and_undeclared_zeros_are_data(tmp_path):
    """GDAL_NODATA 0 (a Sentinel-1-style zero border) is stored as NaN, which every detector
    leaves out (issue 12); zeros without a declaration stay data (8-bit chips have real zeros)."""
    a = np.random.default_rng(4).gamma(2.0, 0.5, (64, 64)).astype(np.float32)
    a[:, :8] = 0.0
    write_tif(tmp_path / "z.tif", a, extratags=[(42113, "s", 0, "0", False)])
    out = read(ingest([tmp_path / "z.tif"], tmp_path / "z.zarr", tile=32), "intensity")
    assert np.isnan(out[:, :8]).all() and np.isfinite(out[:, 8:]).all()
    write_tif(tmp_path / "u.tif", a)
    out = read(ingest([tmp_path / "u.tif"], tmp_path / "u.zarr", tile=32), "intensity")
    assert (out[:, :8] == 0).all()


# --------------------------------------------------------------------------------------
# issue 30: an SLC chip's channel is never named after a polarisation its product lacks
# --------------------------------------------------------------------------------------


def test_one_pair_of_a_dual_pol_chip_is_not_stored_as_hh(tmp_path):
    """The OpenSARShip layout ``<product>/Patch/<chip>.tif`` + ``<product>/<product>.xml``: a chip
    holding one (re, im) pair of a VH + VV product, nothing in its name saying which, was
    stored as ``hh`` (the default by count); now refused in one line asking for --channels."""
    prod = tmp_path / "S1A_IW_SLC__1SDV_TEST"
    (prod / "Patch").mkdir(parents=True)
    (prod / f"{prod.name}.xml").write_text(snap_xml(pols=("VH", "VV")))
    chip = prod / "Patch" / "Cargo_x1_y2.tif"
    write_tif(chip, slc_bands())
    with pytest.raises(InputError) as e:
        ingest([chip], tmp_path / "o.zarr")
    msg = str(e.value)
    assert "\n" not in msg and "Cargo_x1_y2.tif" in msg and "vh, vv" in msg and "--channels" in msg, msg
    assert not (tmp_path / "o.zarr").exists()
    sc = ingest([chip], tmp_path / "o.zarr", channels=["vv"])
    assert sc.attrs["channels"] == ["vv"] and sc.attrs["kind"] == "slc"


def test_vv_sidecar_band_element_names_the_channel(tmp_path):
    """A SNAP sidecar of a VV product whose ``Band_IW1_VV`` element has no ``polarization``
    item (nor ``mdsN_tx_rx_polar``): the element's name says VV, so the chip is ``vv``, not ``hh``."""
    prod = tmp_path / "S1A_IW_SLC__1SSV_TEST"
    (prod / "Patch").mkdir(parents=True)
    xml = snap_xml(pols=("VV",), band_pols_only=True).replace('<attrib name="polarization" value="VV" />', "")
    assert "polarization" not in xml and "Band_IW1_VV" in xml
    (prod / "Metedata.xml").write_text(xml)
    chip = prod / "Patch" / "Tanker_x3_y4.tif"
    write_tif(chip, slc_bands())
    sc = ingest([chip], tmp_path / "o.zarr")
    assert sc.attrs["kind"] == "slc" and sc.attrs["channels"] == ["vv"] and set(sc.variables) == {"vv"}
    assert sc.attrs["polarisations"] == ["vv"]


@needs_oss
def test_real_slc_chip_vv_pair_with_its_product_sidecar(tmp_path):
    """The VV pair of a real OpenSARShip SLC chip, beside a copy of its product's sidecar: named
    ``vv`` when the file name says so, refused (never ``hh``) when nothing does."""
    src = sorted(OSS.glob("S1A_IW_SLC_*"))[0]
    chip = sorted((src / "Patch").glob("*.tif"))[0]
    prod = tmp_path / src.name
    (prod / "Patch").mkdir(parents=True)
    shutil.copyfile(src / f"{src.name}.xml", prod / f"{src.name}.xml")
    vv = np.ascontiguousarray(tifffile.imread(chip)[:, :, 2:4])  # [VH re, VH im, VV re, VV im]
    write_tif(prod / "Patch" / (chip.stem + "_vv.tif"), vv)
    sc = ingest([prod / "Patch" / (chip.stem + "_vv.tif")], tmp_path / "vv.zarr")
    assert sc.attrs["channels"] == ["vv"]
    np.testing.assert_array_equal(read(sc, "vv"), vv[..., 0] + 1j * vv[..., 1])
    write_tif(prod / "Patch" / chip.name, vv)
    with pytest.raises(InputError, match="--channels"):
        ingest([prod / "Patch" / chip.name], tmp_path / "o.zarr")
