"""Detector scores on real SAR chips (../shared/data/real), with the detectors' DEFAULT parameters.

What is checked, per core detector (``ca_cfar``, ``os_cfar``, ``two_parameter``), each run through
:func:`sarship.workers.jobs.run_detection` on the session's two-process Dask cluster (``client``):

- SAR-Ship-Dataset (Wang et al., Remote Sensing 11(7):765, 2019; 12 JPEG chips, 68 VOC boxes) and
  HRSID (Wei et al., IEEE Access 8:120234, 2020; 18 JPEG chips, truth = mask components):
  object-level FoM and pd aggregated over the chips (pipeline.products.scoring.aggregate) are at least
  the values measured with ``bench/realdata_eval.py`` minus a small margin (FOM_MARGIN,
  PD_MARGIN), over all the chips and over the held-out half of the cross-validation
  (HALF_B: the defaults were tuned on the other half), and HRSID pixel TPR / FPR stay near
  theirs; ``ca_cfar`` is not behind a published plain CA-CFAR on HRSID (FoM 0.38).
- OpenSARShip GRD Patch chips (Huang et al., IEEE JSTARS 11(1):195, 2018; Sentinel-1 IW, 38
  chips): the AIS-matched ship at the chip centre is detected (a kept detection whose bbox is
  within CENTRE_RADIUS_PX of the chip centre) on every chip but the one whose centre holds no
  ship (NO_SHIP_AT_CENTRE; checked against Ship.xml), with the metre size rule (10 m spacing).
- The command line end to end on one chip: ``sarship ingest`` + ``sarship detect`` +
  ``sarship evaluate --json`` agree with the in-process run.

Only data-specific settings a user would choose are added to the defaults: the OpenSARShip
band (VH, cross-pol: better ship/sea contrast; ``ingest(..., channels=["vh", "vv"],
band="vh")``, i.e. ``sarship ingest --channels vh,vv --band vh``). Everything else is
``spec.params()`` as the code defines it when the test runs.

The thresholds assume the defaults recommended in bench/REALDATA.md (ASSUMED_DEFAULTS); the
assertion messages print the code's defaults next to them when a threshold is missed.
"""

from __future__ import annotations

import glob
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
SSDD = REAL / "sar-ship-dataset"
HRSID = REAL / "hrsid"
OSS = REAL / "opensarship"

pytestmark = [
    pytest.mark.realdata,
    pytest.mark.skipif(not REAL.is_dir(), reason=f"real SAR data not found at {REAL} (see shared/data/README.md)"),
]

DETECTORS = ("ca_cfar", "os_cfar", "two_parameter", "superpixel_cfar")

#: The defaults the thresholds below were measured with (bench/realdata_eval.py, bench/REALDATA.md:
#: tuned by cross-validation on half A of the chips, HALF_B held out). ``looks`` stays None (= the
#: scene attribute: MoLC estimate for the JPEGs, 5 for GRD); two_parameter keeps
#: threshold="student", domain="intensity"; os_cfar keeps k = round(3N/4). The size rule: the JPEG
#: chips have no pixel spacing (min_area_px = auto_min_area_px), the GRD chips have 10 m spacing
#: (min_length_m = auto_min_length_m, min_area_px = the pixels of auto_min_area_m2: 2).
ASSUMED_DEFAULTS = {
    "ca_cfar": {
        "pfa": 1e-5,
        "guard": 41,
        "background": 81,
        "merge_px": 4,
        "land_mask": "texture",
        "auto_min_area_px": 10,
        "auto_min_length_m": 25.0,
        "auto_min_area_m2": 200.0,
    },
    "os_cfar": {
        "pfa": 1e-6,
        "guard": 21,
        "background": 41,
        "merge_px": 4,
        "land_mask": "texture",
        "auto_min_area_px": 10,
        "auto_min_length_m": 25.0,
        "auto_min_area_m2": 200.0,
    },
    "two_parameter": {
        "pfa": 1e-6,
        "guard": 41,
        "background": 81,
        "merge_px": 2,
        "land_mask": "texture",
        "auto_min_area_px": 10,
        "auto_min_length_m": 25.0,
        "auto_min_area_m2": 200.0,
    },
    # the paper's settings (docs/algorithms/superpixel_cfar.md) with the contrast floor (tuned on half B)
    "superpixel_cfar": {
        "pfa": 1e-3,
        "merge_px": 4,
        "land_mask": "texture",
        "min_contrast_db": 7.0,
        "min_separation_db": 6.0,
        "auto_min_area_px": 10,
        "auto_min_length_m": 20.0,
        "auto_min_area_m2": 200.0,
    },
}

#: Measured with ASSUMED_DEFAULTS (land_mask=texture: the choice of the fold tuned on half A with
#: the land mask, bench/REALDATA.md "Sea-land segmentation"), aggregated over ALL the chips:
#:   ca_cfar       SSDD FoM 0.537 pd 0.853                          HRSID FoM 0.605 pd 0.839 (26/31, 12 false)
#:                 HRSID pixels TPR 0.454 FPR 2.1e-4               GRD VH centre ship 37/38
#:   os_cfar       SSDD FoM 0.343 pd 0.853                          HRSID FoM 0.553 pd 0.839 (26/31, 16 false)
#:                 HRSID pixels TPR 0.430 FPR 1.5e-4               GRD VH centre ship 37/38
#:   two_parameter SSDD FoM 0.548 pd 0.838                          HRSID FoM 0.295 pd 0.839 (26/31, 57 false)
#:                 HRSID pixels TPR 0.340 FPR 3.8e-3               GRD VH centre ship 37/38
#:   superpixel_cfar SSDD FoM 0.607 pd 0.794                        HRSID FoM 0.703 pd 0.839 (26/31, 6 false)
#:                 HRSID pixels TPR 0.918 FPR 1.5e-3               GRD VH centre ship 37/38
#: (ca_cfar re-measured 2026-11-27 with max_elongation 15: SSDD 0.547, HRSID 0.650 (9 false); its
#: pixel scores and the other two detectors' rows are from before that filter, which only drops
#: detections, so they remain lower bounds. superpixel_cfar: bench/REALDATA.md "The local-contrast
#: floor", min_contrast_db 7 tuned on half B: its held-out half is A, MEASURED_HELD_OUT
#: holds its half-B figures as the regression check they are.)
#: (Without the land mask, the previous defaults (ca_cfar pfa 1e-6, os_cfar 1e-7): SSDD FoM 0.458 /
#: 0.309 / 0.463, HRSID 0.518 / 0.468 / 0.221 at HRSID pd 0.935: the 5 HRSID ships the mask loses are
#: moored against quays.)
MEASURED = {
    "ca_cfar": {"ssdd": (0.547, 0.853), "hrsid": (0.650, 0.839), "hrsid_px": (0.454, 2.1e-4)},
    "os_cfar": {"ssdd": (0.343, 0.853), "hrsid": (0.553, 0.839), "hrsid_px": (0.430, 1.5e-4)},
    "two_parameter": {"ssdd": (0.548, 0.838), "hrsid": (0.295, 0.839), "hrsid_px": (0.340, 3.8e-3)},
    "superpixel_cfar": {"ssdd": (0.607, 0.794), "hrsid": (0.703, 0.839), "hrsid_px": (0.918, 1.5e-3)},
}
#: The held-out half (B) of the cross-validation: the defaults never saw these chips. Its
#: scores (FoM, pd), measured with ASSUMED_DEFAULTS:
HALF_B = {
    "ssdd": {
        "Gao_ship_hh_02017010717010109",
        "Gao_ship_hh_02017110638010408",
        "Gao_ship_vh_020170115650701803",
        "Sen_ship_hh_0201705190105404",
        "Sen_ship_vv_02017091501054029",
        "ship050304",
    },
    "hrsid": {
        "P0003_2400_3200_4800_5600",
        "P0005_1200_2000_3600_4400",
        "P0005_2400_3200_5400_6200",
        "P0008_0_800_9000_9800",
        "P0011_1800_2600_7200_8000",
        "P0011_4200_5000_2400_3200",
        "P0015_4200_5000_6000_6800",
        "P0017_2400_3200_4800_5600",
        "P0021_4200_5000_7200_8000",
    },
}
MEASURED_HELD_OUT = {
    "ca_cfar": {"ssdd": (0.610, 0.818), "hrsid": (0.536, 0.789)},
    "os_cfar": {"ssdd": (0.347, 0.795), "hrsid": (0.441, 0.789)},
    "two_parameter": {"ssdd": (0.625, 0.795), "hrsid": (0.242, 0.789)},
    "superpixel_cfar": {"ssdd": (0.739, 0.773), "hrsid": (0.600, 0.789)},
}
#: A published plain CA-CFAR reaches HRSID FoM 0.38 on these chips (the users' issue): ours must not be behind.
PEER_CA_CFAR_HRSID_FOM = 0.38
#: Allowed drop below the measured FoM; pd may lose about one HRSID ship (1/31) or two SSDD ships.
FOM_MARGIN = 0.03
PD_MARGIN = 0.035
#: Pixel level: TPR may drop by this much, FPR may grow by this factor.
TPR_MARGIN = 0.05
FPR_FACTOR = 2.0

#: The one OpenSARShip GRD chip whose centre holds no ship: its annotation puts the ship's
#: head (15534, 12581) and tail (15539, 12588) about 13 px from the chip centre (15542, 12596),
#: at the top edge of the 29 x 29 chip (Ship.xml also flags Interference=1); the chip centre is
#: open sea, so no detector can (or should) find a ship there. Every other chip's centre
#: ship must be found: 37 of 38.
NO_SHIP_AT_CENTRE = {"Tanker_x15542_y12596"}

CENTRE_RADIUS_PX = 3.0


# ----------------------------------------------------------------------------- helpers


def _needs(path: Path) -> None:
    if not path.exists():
        pytest.skip(f"real data absent: {path}")


def _side(p: Path) -> int:
    from PIL import Image

    with Image.open(p) as im:
        return max(im.size)


def _code_defaults(detector: str) -> dict:
    from sarship.pipeline import detectors

    P = detectors.get(detector).params
    d = P()
    out = {
        k: getattr(d, k) for k in ("pfa", "guard", "background", "looks", "merge_px", "land_mask", "min_contrast_db")
    }
    out.update(
        auto_min_area_px=P.auto_min_area_px,
        auto_min_length_m=P.auto_min_length_m,
        auto_min_area_m2=P.auto_min_area_m2,
        min_area_px=d.min_area_px,
        min_length_m=d.min_length_m,
    )
    return out


def _why(detector: str) -> str:
    return (
        f"thresholds assume defaults {ASSUMED_DEFAULTS[detector]}; the code's defaults are {_code_defaults(detector)}"
    )


def _detect(client, scene, detector: str, out: Path, **settings):
    """Default-parameter run on one chip (one tile); returns (detections as Ships, mask, run)."""
    from sarship.pipeline.products.truth import load_detections, read_mask
    from sarship.pipeline.scene import open_scene
    from sarship.workers.jobs import run_detection

    shape = open_scene(scene).shape
    run = run_detection(scene, detector, settings, out_dir=out, tile=max(shape), client=client, progress=False)
    return load_detections(out / "detections.geojson"), read_mask(out / "mask.zarr"), run


#: Chips ingested / run at once on the session's cluster (as the service's runner threads share one
#: client): one chip's run is mostly round trips and small writes, so a few in flight keep both
#: workers busy.
CONCURRENT_CHIPS = 4


def _map(fn, items) -> list:
    """``fn`` over ``items``, CONCURRENT_CHIPS at a time (each chip its own store), in order."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(CONCURRENT_CHIPS) as ex:
        return list(ex.map(fn, items))


def _detect_all(client, scenes, detector: str, out: Path, **settings) -> list:
    """:func:`_detect` on each scene path (``out / o{i}``), CONCURRENT_CHIPS at a time, in order."""
    return _map(lambda a: _detect(client, a[1], detector, out / f"o{a[0]}", **settings), list(enumerate(scenes)))


def _check_held_out(detector: str, dataset: str, per: list) -> None:
    """The scores on the held-out half B (chips the defaults were not tuned on)."""
    from sarship.pipeline.products.scoring import aggregate

    assert len(per) == len(HALF_B[dataset])
    a = aggregate(per)
    fom, pd = MEASURED_HELD_OUT[detector][dataset]
    msg = f"{detector} on the held-out half of {dataset}: {a}; {_why(detector)}"
    assert a["fom"] >= fom - FOM_MARGIN, msg
    assert a["pd"] >= pd - PD_MARGIN, msg


def centre_hit(ships, shape, radius: float = CENTRE_RADIUS_PX) -> bool:
    """Some detection's bbox (half-open, continuous coordinates) lies within ``radius`` px of
    the chip centre (H/2, W/2) -- 0 when the centre is inside the box."""
    cy, cx = shape[0] / 2.0, shape[1] / 2.0
    for s in ships:
        r0, c0, r1, c1 = s.bbox
        if math.hypot(max(r0 - cy, 0.0, cy - r1), max(c0 - cx, 0.0, cx - c1)) <= radius:
            return True
    return False


# ----------------------------------------------------------------------------- scenes


@pytest.fixture(scope="module")
def ssdd_scenes(tmp_path_factory):
    from sarship.pipeline.products.truth import load_voc
    from sarship.pipeline.readers import ingest

    _needs(SSDD)
    d = tmp_path_factory.mktemp("ssdd")

    def one(p):
        sc = ingest([p], d / f"{p.stem}.zarr", tile=_side(p))  # JPEG = amplitude -> intensity
        return p.stem, sc.path, load_voc(p.with_suffix(".xml"))

    out = _map(one, sorted(SSDD.glob("*.jpg")))
    assert len(out) == 12
    return out


@pytest.fixture(scope="module")
def hrsid_scenes(tmp_path_factory):
    from sarship.pipeline.products.truth import read_mask, ships_from_mask
    from sarship.pipeline.readers import ingest

    _needs(HRSID)
    d = tmp_path_factory.mktemp("hrsid")

    def one(p):
        sc = ingest([p], d / f"{p.stem}.zarr", tile=_side(p))
        m = read_mask(HRSID / "masks" / f"{p.stem}.png")
        return p.stem, sc.path, ships_from_mask(m), m

    out = _map(one, sorted((HRSID / "images").glob("*.jpg")))
    assert len(out) == 18
    return out


@pytest.fixture(scope="module")
def grd_scenes(tmp_path_factory):
    import tifffile

    from sarship.pipeline.readers import ingest

    _needs(OSS)
    files = sorted(Path(f) for f in glob.glob(str(OSS / "S1A_IW_GRDH_*" / "Patch" / "*.tif")))
    if not files:
        pytest.skip(f"no OpenSARShip GRD Patch chips under {OSS}")
    d = tmp_path_factory.mktemp("grd")

    def one(a):
        i, p = a
        with tifffile.TiffFile(p) as t:
            side = max(t.series[0].shape[:2])
        # the band is the user's choice for dual-pol GRD: VH (cross-pol) has the better contrast
        sc = ingest([p], d / f"g{i:02d}.zarr", tile=side, channels=["vh", "vv"], band="vh")
        return f"{p.parent.parent.name[17:32]}/{p.stem}", sc.path, sc.shape

    return _map(one, list(enumerate(files)))


# ----------------------------------------------------------------------------- tests


def _slow_for(*slow: str) -> list:
    """DETECTORS, those named marked slow: the costliest (dataset, detector) pairs run under -m slow,
    each detector keeping at least one real-data dataset in the default run (os_cfar on SAR-Ship-Dataset
    took 63-76 s of the 2-core machine and on HRSID 21-34 s: its default-run real data is the
    OpenSARShip centre ships; superpixel_cfar on HRSID 25 s)."""
    return [pytest.param(d, marks=pytest.mark.slow) if d in slow else d for d in DETECTORS]


@pytest.mark.parametrize("detector", _slow_for("os_cfar"))
def test_sar_ship_dataset_scores(client, ssdd_scenes, tmp_path, detector):
    from sarship.pipeline.products.scoring import aggregate, score

    runs = _detect_all(client, [scene for _, scene, _ in ssdd_scenes], detector, tmp_path)
    per = [score(dets, truth) for (_, _, truth), (dets, _, _) in zip(ssdd_scenes, runs)]
    a = aggregate(per)
    assert a["n_truth"] == 68
    fom, pd = MEASURED[detector]["ssdd"]
    msg = f"{detector} on SAR-Ship-Dataset: {a}; {_why(detector)}"
    assert a["fom"] >= fom - FOM_MARGIN, msg
    assert a["pd"] >= pd - PD_MARGIN, msg
    _check_held_out(detector, "ssdd", [s for (name, _, _), s in zip(ssdd_scenes, per) if name in HALF_B["ssdd"]])


@pytest.mark.parametrize("detector", _slow_for("os_cfar", "superpixel_cfar"))
def test_hrsid_scores(client, hrsid_scenes, tmp_path, detector):
    from sarship.pipeline.products.scoring import aggregate, pixel_counts, score

    per = []
    runs = _detect_all(client, [scene for _, scene, _, _ in hrsid_scenes], detector, tmp_path)
    for (_name, _scene, truth, tmask), (dets, dmask, _) in zip(hrsid_scenes, runs):
        s = score(dets, truth)
        s.update(pixel_counts(dmask, tmask))
        per.append(s)
    a = aggregate(per)
    assert a["n_truth"] == 31
    fom, pd = MEASURED[detector]["hrsid"]
    tpr, fpr = MEASURED[detector]["hrsid_px"]
    msg = f"{detector} on HRSID: {a}; {_why(detector)}"
    assert a["fom"] >= fom - FOM_MARGIN, msg
    assert a["pd"] >= pd - PD_MARGIN, msg
    # pixel level (CFAR finds the bright part of a ship, not its whole outline)
    assert a["tpr"] >= tpr - TPR_MARGIN, msg
    assert a["fpr"] <= fpr * FPR_FACTOR, msg
    if detector == "ca_cfar":
        assert a["fom"] >= PEER_CA_CFAR_HRSID_FOM, msg
    if detector == "superpixel_cfar":  # issue 14's goal: its object FoM above every other detector's
        assert a["fom"] > max(m["hrsid"][0] for d, m in MEASURED.items() if d != detector), msg
    _check_held_out(detector, "hrsid", [s for (name, *_), s in zip(hrsid_scenes, per) if name in HALF_B["hrsid"]])


@pytest.mark.parametrize("detector", DETECTORS)
def test_opensarship_centre_ship(client, grd_scenes, tmp_path, detector):
    missed = []
    runs = _detect_all(client, [scene for _, scene, _ in grd_scenes], detector, tmp_path)
    for (name, _scene, shape), (dets, _, run) in zip(grd_scenes, runs):
        assert run["channel"] == "intensity"  # = intensity_vh (band chosen at ingest)
        assert run["size_rule"].startswith("metres"), run["size_rule"]  # 10 m spacing: the metre rule
        if not centre_hit(dets, shape):
            missed.append(name)
    unexpected = [m for m in missed if m.split("/")[-1] not in NO_SHIP_AT_CENTRE]
    assert not unexpected, (
        f"{detector}: centre ship not found on {len(unexpected)} of {len(grd_scenes)} "
        f"chips: {unexpected}; {_why(detector)}"
    )


def test_opensarship_chip_without_centre_ship():
    """The exempted chip really has its annotated ship off-centre (head/tail in Ship.xml)."""
    import re

    for stem in NO_SHIP_AT_CENTRE:
        hits = glob.glob(str(OSS / "S1A_IW_GRDH_*" / "Patch" / f"{stem}.tif"))
        if not hits:
            pytest.skip(f"chip {stem} absent")
        chip = Path(hits[0])
        cx, cy = (int(v) for v in re.search(r"_x(\d+)_y(\d+)$", stem).groups())
        text = (chip.parent.parent / "Ship.xml").read_text(errors="replace")  # not well-formed XML: regex
        for block in text.split("<ship>")[1:]:

            def num(tag):
                m = re.search(rf"<{tag}>\s*([-\d.eE+]+)\s*</{tag}>", block)
                return float(m.group(1)) if m else None

            if num("Center_x") == cx and num("Center_y") == cy:
                mx, my = (num("Head_x") + num("Tail_x")) / 2, (num("Head_y") + num("Tail_y")) / 2
                half = max(abs(num("Head_x") - num("Tail_x")), abs(num("Head_y") - num("Tail_y"))) / 2
                # the ship (midpoint +- half its extent) does not come near the chip centre
                assert math.hypot(mx - cx, my - cy) - half > CENTRE_RADIUS_PX + 3
                break
        else:
            pytest.fail(f"{stem} not found in Ship.xml")


def test_cli_end_to_end(client, tmp_path):
    """sarship ingest + detect (on the test cluster) + evaluate --json on one chip."""
    from sarship.pipeline.products.scoring import score
    from sarship.pipeline.products.truth import load_voc

    _needs(SSDD)
    jpg = SSDD / "Gao_ship_hh_0201611139301040015.jpg"
    if not jpg.exists():
        jpg = sorted(SSDD.glob("*.jpg"))[0]
    xml = jpg.with_suffix(".xml")
    scene, out = tmp_path / "chip.zarr", tmp_path / "out"
    env = dict(os.environ, PYTHONWARNINGS="ignore")

    exe = shutil.which("sarship")
    cmd = [exe] if exe else [sys.executable, "-m", "sarship"]  # the console script, else its module

    def sarship(*args):
        r = subprocess.run([*cmd, *args], capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, f"sarship {' '.join(args)} -> {r.returncode}: {r.stderr[-2000:]}"
        return r

    sarship("ingest", str(jpg), "--out", str(scene), "--tile", "256")
    sarship("detect", str(scene), "--detector", "ca_cfar", "--out", str(out), "--scheduler", client.scheduler.address)
    r = sarship("evaluate", str(out / "detections.geojson"), "--truth", str(xml), "--json")
    s = json.loads(r.stdout)
    assert s["n_truth"] == len(load_voc(xml)) and s["n_hit"] >= 1
    # the command line and the library agree
    dets, _, _ = _detect(client, scene, "ca_cfar", tmp_path / "lib")
    ref = score(dets, load_voc(xml))
    assert {k: s[k] for k in ("n_hit", "n_false", "n_detections", "fom")} == {
        k: ref[k] for k in ("n_hit", "n_false", "n_detections", "fom")
    }
    run = json.loads((out / "run.json").read_text())
    assert run["parameters"] == json.loads((tmp_path / "lib" / "run.json").read_text())["parameters"]
