"""Detector scores on the real SAR chips under ``../shared/data/real`` and a small parameter sweep.

Datasets (see ``shared/data/README.md``; cite the originals when quoting numbers):

- ``sar-ship-dataset`` (SSDD-like; Wang et al., Remote Sensing 11(7):765, 2019): 12 JPEG chips
  256x256 (8-bit contrast-stretched amplitude, Gaofen-3 and Sentinel-1), 68 VOC ship boxes.
  Object-level scores (``pipeline.scoring.score`` / ``aggregate``).
- ``hrsid`` (Wei et al., IEEE Access 8:120234, 2020): 18 JPEG chips 800x800; truth = the
  8-connected components of ``masks/<name>.png``. Object scores and pixel TPR/FPR of the
  detector's ``mask.zarr``.
- ``opensarship`` GRD ``Patch`` chips (Huang et al., IEEE JSTARS 11(1):195, 2018): Sentinel-1
  IW GRDH float32 amplitude [VH, VV], 25-125 px, each centred on one AIS-matched ship that
  fills about the central quarter; other ships are not annotated. Score: the fraction of
  chips whose centre ship is detected (a kept detection whose bounding box lies within
  ``CENTRE_RADIUS_PX`` of the chip centre), per band; ``extra`` = mean number of other
  detections per chip (other ships or false alarms -- not annotated).

Every chip is ingested with :func:`sarship.pipeline.readers.ingest` (JPEG amplitude -> intensity;
GRD with ``channels=["vh", "vv"]``, the band chosen at detection with the ``channel``
setting) at ``tile`` = the chip side, and every detector runs through
:func:`sarship.workers.jobs.run_detection` on ONE shared Dask ``LocalCluster``.

Sweep. The detection mask depends only on (pfa, guard, background, looks); ``min_area_px``
and ``merge_px`` act afterwards on the mask's connected components. So each mask setting is
run once through ``run_detection`` (with ``min_area_px=1, merge_px=0``) and its
``mask.zarr`` is post-processed for every (min_area_px, merge_px) with the pipeline's own
component code (:func:`sarship.pipeline.components.tile_components` + ``merge_tiles`` +
:func:`sarship.pipeline.ship_features.keep_mask`, bbox/centroid as ``features`` writes them) -- identical to what ``run_detection``
returns for a one-tile scene; a self-check at start-up asserts that on a few chips.

Looks: ``scene`` = the scene's ``looks`` attribute (MoLC estimate for the JPEGs, 0.4-1.2
because they are contrast-stretched 8-bit amplitude; nominal 5 from the SNAP sidecar for
GRD), or a fixed value passed as the ``looks`` parameter.

Choice of one default per detector: highest mean of (SSDD FoM, HRSID FoM, OpenSARShip
centre-detection rate on the chosen band) among settings whose SSDD and HRSID pd are
>= ``MIN_PD``; the best per dataset are listed too.

Usage::

    python bench/realdata_eval.py                 # full grid (about 6-8 min on 2 cores)
    python bench/realdata_eval.py --quick         # a few settings (about 1 min)
    python bench/realdata_eval.py --json out.json --md table.md
    python bench/realdata_eval.py --from-json out.json      # re-report saved rows
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import glob
import itertools
import json
import logging
import math
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "real"

DETECTORS = ("ca_cfar", "os_cfar", "two_parameter")
PFAS = (1e-3, 1e-4, 1e-5, 1e-6)
WINDOWS = ((21, 41), (31, 61), (41, 61), (41, 81))  # (guard, background)
LOOKS = ("scene", 1.0)  # "scene" = the scene attribute; a number = a fixed looks parameter
MIN_AREAS = (1, 3, 5, 10, 15, 20, 30, 40)
MERGES = (0, 2, 4)
BANDS = ("vh", "vv")
#: Detector-specific parameters swept too (first = the code's default).
EXTRA = {"two_parameter": ({"domain": "intensity"}, {"domain": "amplitude"}, {"domain": "db"})}

#: ``min_area_px`` of the mask-only runs (no component survives; the mask is unaffected).
MASK_ONLY_MIN_AREA = 10**9

#: A detection is the centre ship of an OpenSARShip chip when its bbox is this close (pixels).
CENTRE_RADIUS_PX = 3.0
#: Settings with a lower SSDD or HRSID pd, or OpenSARShip centre-detection rate, are not
#: eligible as "the default".
MIN_PD = 0.85
MIN_GRD_PD = 0.95  # 37 of the 38 chips: one chip has no ship at its centre (see REALDATA.md)

DATASETS = ("ssdd", "hrsid", "grd")


# --------------------------------------------------------------------------------------
# chips and truth


@dataclass
class Chip:
    dataset: str          # ssdd | hrsid | grd
    name: str
    scene: Path
    shape: tuple[int, int]
    looks: float | None
    truth: list = field(default_factory=list)      # list[pipeline.truth.Ship] (ssdd, hrsid)
    truth_mask: np.ndarray | None = None           # hrsid
    spacing: tuple[float, float] | None = None


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


def ingest_all(data: Path, work: Path, limit: int | None = None) -> list[Chip]:
    """Ingest every chip of the three datasets into ``work``; attach the truth."""
    from sarship.pipeline.readers import ingest
    from sarship.pipeline.truth import load_voc, read_mask, ships_from_mask

    chips: list[Chip] = []
    work.mkdir(parents=True, exist_ok=True)

    def side_of(p: Path) -> int:
        from PIL import Image

        with Image.open(p) as im:
            return max(im.size)

    ssdd = sorted((data / "sar-ship-dataset").glob("*.jpg"))[:limit]
    for p in ssdd:
        sc = ingest([p], work / f"ssdd_{_safe(p.stem)}.zarr", tile=side_of(p))
        chips.append(Chip("ssdd", p.stem, sc.path, sc.shape, sc.looks,
                          truth=load_voc(p.with_suffix(".xml"))))
    hr = sorted((data / "hrsid" / "images").glob("*.jpg"))[:limit]
    for p in hr:
        sc = ingest([p], work / f"hrsid_{_safe(p.stem)}.zarr", tile=side_of(p))
        m = read_mask(data / "hrsid" / "masks" / f"{p.stem}.png")
        chips.append(Chip("hrsid", p.stem, sc.path, sc.shape, sc.looks,
                          truth=ships_from_mask(m), truth_mask=m))
    grd = sorted(Path(f) for f in glob.glob(str(data / "opensarship" / "S1A_IW_GRDH_*" / "Patch" / "*.tif")))
    grd = grd[:limit] if limit else grd
    import tifffile

    for p in grd:
        with tifffile.TiffFile(p) as t:
            h, w = t.series[0].shape[:2]
        sc = ingest([p], work / f"grd_{_safe(p.parent.parent.name[17:32])}_{_safe(p.stem)}.zarr",
                    tile=max(h, w), channels=["vh", "vv"])
        chips.append(Chip("grd", f"{p.parent.parent.name[17:32]}/{p.stem}", sc.path, sc.shape,
                          sc.looks, spacing=sc.pixel_spacing_m))
    return chips


# --------------------------------------------------------------------------------------
# detection, post-processing, scores


def run_mask(client, chip: Chip, detector: str, settings: dict, out_root: Path) -> tuple[np.ndarray, dict]:
    """One ``run_detection`` on the chip (one tile); returns its mask and run.json."""
    import zarr

    from sarship.workers.jobs import run_detection

    out = Path(tempfile.mkdtemp(prefix="run-", dir=out_root))
    try:
        run = run_detection(chip.scene, detector, dict(settings), out_dir=out, tile=max(chip.shape),
                            client=client, progress=False)
        mask = np.asarray(zarr.open_array(str(out / "mask.zarr" / "mask"), mode="r")[...]) != 0
        dets = json.loads((out / "detections.geojson").read_text())["features"]
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return mask, {"run": run, "features": dets}


class _Filter:
    """The part of the detector parameters that :func:`keep_mask` reads."""

    def __init__(self, min_area_px: int):
        self.min_area_px = min_area_px
        self.max_area_px = None
        self.min_length_m = None
        self.max_length_m = None


def components(mask: np.ndarray, merge_px: int) -> np.ndarray:
    """Component moment records of a one-tile scene mask, as ``run_detection`` builds them."""
    from sarship.pipeline.components import merge_radius, merge_tiles, tile_components

    r = merge_radius(merge_px)
    h, w = mask.shape
    ext = np.zeros((h + 2 * r, w + 2 * r), bool)
    ext[r:r + h, r:r + w] = mask
    z = np.zeros(mask.shape, np.float32)
    comps = tile_components(ext, z, z, r, (0, 0), (0, 0))
    return merge_tiles({(0, 0): comps})


def detections(records: np.ndarray, min_area_px: int, spacing=None) -> list:
    """Kept records as :class:`sarship.pipeline.truth.Ship`: the ``bbox_px`` / ``centroid_px`` /
    ``area_px`` that :func:`sarship.pipeline.ship_features.features` writes, computed vectorised
    (features() is per-record Python; the self-check compares both)."""
    from sarship.pipeline.ship_features import keep_mask
    from sarship.pipeline.truth import Ship

    kept = records[keep_mask(records, _Filter(min_area_px), spacing)]
    n = kept["n"].astype(np.float64)
    cr = kept["sr"] / n + 0.5
    cc = kept["sc"] / n + 0.5
    return [Ship((float(r0), float(c0), float(r1), float(c1)), (float(a), float(b)), False, {"area_px": int(k)})
            for r0, c0, r1, c1, a, b, k in zip(kept["r0"], kept["c0"], kept["r1"], kept["c1"], cr, cc,
                                               kept["n"])]


def centre_hit(ships: list, shape: tuple[int, int], radius: float = CENTRE_RADIUS_PX) -> tuple[bool, int]:
    """(centre ship detected, number of other detections) for an OpenSARShip chip.

    The centre ship is the detection whose bbox (half-open, continuous pixel coordinates)
    lies nearest the chip centre ``(H/2, W/2)``, if within ``radius`` pixels (0 when the
    centre is inside the box).
    """
    cy, cx = shape[0] / 2.0, shape[1] / 2.0
    best = math.inf
    for s in ships:
        r0, c0, r1, c1 = s.bbox
        dy = max(r0 - cy, 0.0, cy - r1)
        dx = max(c0 - cx, 0.0, cx - c1)
        best = min(best, math.hypot(dy, dx))
    hit = best <= radius
    return hit, len(ships) - int(hit)


def chip_scores(chip: Chip, mask: np.ndarray, min_areas=MIN_AREAS, merges=MERGES) -> dict:
    """Scores of one chip's mask for every (min_area_px, merge_px)."""
    from sarship.pipeline.scoring import pixel_counts, score

    out = {}
    px = pixel_counts(mask, chip.truth_mask) if chip.truth_mask is not None else None
    for mg in merges:
        rec = components(mask, mg)
        for ma in min_areas:
            ships = detections(rec, ma, chip.spacing)
            if chip.dataset == "grd":
                hit, extra = centre_hit(ships, chip.shape)
                out[(ma, mg)] = {"hit": int(hit), "extra": extra}
            else:
                s = score(ships, chip.truth)
                if px is not None:
                    s.update(px)
                out[(ma, mg)] = s
    return out


def summarise(dataset: str, per_chip: list[dict], names: list[str] | None = None) -> dict:
    """Aggregate one dataset's per-chip scores of one setting."""
    from sarship.pipeline.scoring import aggregate

    if dataset == "grd":
        n = len(per_chip)
        return {"n": n, "pd": sum(s["hit"] for s in per_chip) / max(n, 1),
                "hits": sum(s["hit"] for s in per_chip),
                "extra": sum(s["extra"] for s in per_chip) / max(n, 1),
                "missed": [nm for nm, s in zip(names or [], per_chip) if not s["hit"]]}
    a = aggregate(per_chip)
    return {k: a[k] for k in ("n_truth", "n_detections", "n_hit", "n_false", "pd", "precision", "fom",
                              "tpr", "fpr") if k in a}


# --------------------------------------------------------------------------------------
# sweep


def mask_settings(detector: str, pfas, windows, looks, extra=EXTRA) -> list[dict]:
    out = []
    from sarship.pipeline import detectors

    needs_looks = detectors.get(detector).needs_looks
    for pfa, (g, b), L, ex in itertools.product(pfas, windows, looks if needs_looks else ("scene",),
                                                extra.get(detector, ({},))):
        # min_area_px huge: run_detection writes no features (the mask is all we use; it
        # does not depend on min_area_px / merge_px), which keeps the client side cheap
        s = {"pfa": pfa, "guard": g, "background": b, "min_area_px": MASK_ONLY_MIN_AREA, "merge_px": 0, **ex}
        if L != "scene":
            s["looks"] = float(L)
        out.append(s)
    return out


SETTING_KEYS = ("pfa", "guard", "background", "looks", "min_area_px", "merge_px", "extra")


def key_of(detector: str, s: dict, ma: int, mg: int) -> dict:
    ex = {k: v for k, v in s.items() if k not in SETTING_KEYS}
    return {"detector": detector, "pfa": s["pfa"], "guard": s["guard"], "background": s["background"],
            "looks": s.get("looks", "scene"), "min_area_px": ma, "merge_px": mg, "extra": ex}


def sweep(client, chips: list[Chip], detectors_: list[str], grid: dict, work: Path, threads: int,
          log=print) -> list[dict]:
    """Every mask setting x chip through run_detection; rows of aggregated scores."""
    rows = []
    runs_root = work / "runs"
    runs_root.mkdir(exist_ok=True)
    jobs = []  # (chip, band channel or None)
    for c in chips:
        if c.dataset == "grd":
            jobs += [(c, b) for b in grid["bands"]]
        else:
            jobs.append((c, None))

    def one(det, s, chip, band):
        st = dict(s)
        if band is not None:
            st["channel"] = f"intensity_{band}"
        mask, _ = run_mask(client, chip, det, st, runs_root)
        return chip_scores(chip, mask, grid["min_areas"], grid["merges"])

    with cf.ThreadPoolExecutor(threads) as pool:
        for det in detectors_:
            settings = mask_settings(det, grid["pfas"], grid["windows"], grid["looks"])
            for i, s in enumerate(settings):
                t0 = time.perf_counter()
                futs = [pool.submit(one, det, s, c, b) for c, b in jobs]
                res = [f.result() for f in futs]
                for ma, mg in itertools.product(grid["min_areas"], grid["merges"]):
                    row = key_of(det, s, ma, mg)
                    for ds in ("ssdd", "hrsid"):
                        per = [r[(ma, mg)] for (c, b), r in zip(jobs, res) if c.dataset == ds]
                        if per:
                            row[ds] = summarise(ds, per)
                    for band in grid["bands"]:
                        sel = [(c.name, r[(ma, mg)]) for (c, b), r in zip(jobs, res)
                               if c.dataset == "grd" and b == band]
                        if sel:
                            row[f"grd_{band}"] = summarise("grd", [x[1] for x in sel], [x[0] for x in sel])
                    rows.append(row)
                log(f"  {det} {i + 1}/{len(settings)} pfa={s['pfa']:g} g/b={s['guard']}/{s['background']} "
                    f"looks={s.get('looks', 'scene')}: {time.perf_counter() - t0:.1f} s")
    return rows


def self_check(client, chips: list[Chip], detectors_: list[str], work: Path) -> None:
    """Local post-processing == run_detection's own detections (default min_area/merge)."""
    from sarship.pipeline import detectors

    runs_root = work / "runs"
    runs_root.mkdir(exist_ok=True)
    picks = []
    for ds in DATASETS:
        picks += [c for c in chips if c.dataset == ds][:2]
    for det in detectors_:
        d = detectors.get(det).params()
        for c in picks:
            for ma, mg in ((d.min_area_px, d.merge_px), (5, 4), (1, 0)):
                mask, out = run_mask(client, c, det, {"min_area_px": ma, "merge_px": mg}, runs_root)
                direct = sorted(tuple(f["properties"]["bbox_px"]) + (f["properties"]["area_px"],)
                                + tuple(round(v, 6) for v in f["properties"]["centroid_px"])
                                for f in out["features"])
                local = sorted(tuple(int(v) for v in s.bbox) + (s.properties["area_px"],)
                               + tuple(round(v, 6) for v in s.centroid)
                               for s in detections(components(mask, mg), ma, c.spacing))
                assert direct == local, f"self-check failed: {det} {c.name} min_area={ma} merge={mg}"


# --------------------------------------------------------------------------------------


def grd(row: dict, band: str) -> dict | None:
    return row.get(f"grd_{band}")


def objective(row: dict, band: str = "vh") -> float:
    """mean(SSDD FoM, HRSID FoM, OpenSARShip centre-detection rate on ``band``) over the sets present."""
    parts = [row[ds]["fom"] for ds in ("ssdd", "hrsid") if ds in row]
    if grd(row, band):
        parts.append(grd(row, band)["pd"])
    return float(np.mean(parts)) if parts else 0.0


def eligible(row: dict, band: str = "vh") -> bool:
    """pd high enough everywhere: SSDD and HRSID pd >= MIN_PD, OpenSARShip >= MIN_GRD_PD."""
    ok = all(row[ds]["pd"] >= MIN_PD for ds in ("ssdd", "hrsid") if ds in row)
    g = grd(row, band)
    return ok and (g is None or g["pd"] >= MIN_GRD_PD)


def fmt_setting(r: dict) -> str:
    L = r["looks"] if r["looks"] == "scene" else f"{r['looks']:g}"
    ex = "".join(f" {k}={v}" for k, v in r.get("extra", {}).items())
    return (f"pfa={r['pfa']:.0e} g/b={r['guard']}/{r['background']} L={L} "
            f"min_area={r['min_area_px']} merge={r['merge_px']}{ex}")


def fmt_row(r: dict, bands, band: str) -> str:
    cells = [f"{r['detector']:<13}", f"{fmt_setting(r):<62}"]
    for ds in ("ssdd", "hrsid"):
        s = r.get(ds)
        cells.append(f"{s['fom']:.3f} {s['pd']:.3f} {s['precision']:.3f}" if s else " " * 17)
    h = r.get("hrsid")
    cells.append(f"{h['tpr']:.3f} {h['fpr']:.1e}" if h and "tpr" in h else " " * 13)
    for b in bands:
        g = grd(r, b)
        cells.append(f"{g['hits']:>2}/{g['n']} {g['extra']:4.2f}" if g else " " * 10)
    cells.append(f"{objective(r, band):.3f}")
    return " | ".join(cells)


def header(bands) -> str:
    cells = [f"{'detector':<13}", f"{'setting':<62}", "SSDD fom pd  prec", "HRSID fom pd prec",
             "HRSID tpr fpr"]
    cells += [f"GRD-{b.upper()} extra" for b in bands]
    cells.append("mean")
    return " | ".join(cells)


def same_setting(r: dict, st: dict) -> bool:
    return all(r[k] == st[k] for k in ("pfa", "guard", "background", "looks", "min_area_px", "merge_px")) and \
        r.get("extra", {}) == st.get("extra", {})


def default_row(rows: list[dict], detector: str) -> dict | None:
    """The row of the code's current defaults (looks default = the scene attribute)."""
    from sarship.pipeline import detectors

    d = detectors.get(detector).params()
    for r in rows:
        if (r["detector"] == detector and r["pfa"] == d.pfa and r["guard"] == d.guard
                and r["background"] == d.background and r["looks"] == "scene"
                and r["min_area_px"] == d.min_area_px and r["merge_px"] == d.merge_px
                and all(getattr(d, k) == v for k, v in r.get("extra", {}).items())):
            return r
    return None


def report(rows: list[dict], detectors_: list[str], bands, band: str = "vh", top: int = 10, log=print) -> dict:
    choice = {}
    log("\nColumns: SSDD / HRSID = FoM, pd, precision (object level, aggregated over the chips); HRSID "
        "tpr/fpr = pixel level; GRD-<band> = OpenSARShip GRD chips whose centre ship is detected, and "
        "mean other detections per chip; mean = mean(SSDD FoM, HRSID FoM, GRD-"
        f"{band.upper()} rate).")
    for b in bands:
        g = [grd(r, b)["pd"] for r in rows if grd(r, b)]
        if g:
            log(f"GRD band {b.upper()}: centre-detection rate averaged over all {len(g)} rows {np.mean(g):.3f}")
    for det in detectors_:
        rs = [r for r in rows if r["detector"] == det]
        if not rs:
            continue
        log(f"\n=== {det}: top {top} by mean, eligible = SSDD and HRSID pd >= {MIN_PD}, GRD-{band.upper()} "
            f">= {MIN_GRD_PD} ===")
        log(header(bands))
        elig = sorted((r for r in rs if eligible(r, band)), key=lambda r: -objective(r, band))
        for r in elig[:top]:
            log(fmt_row(r, bands, band))
        dr = default_row(rows, det)
        if dr is not None:
            log("current code defaults:")
            log(fmt_row(dr, bands, band))
        best = {}
        for ds in ("ssdd", "hrsid"):
            if any(ds in r for r in rs):
                b = max((r for r in rs if ds in r), key=lambda r: (r[ds]["fom"], r[ds]["pd"]))
                best[ds] = b
                log(f"best {ds.upper()} FoM: {fmt_setting(b)} -> fom {b[ds]['fom']:.3f} pd {b[ds]['pd']:.3f} "
                    f"precision {b[ds]['precision']:.3f}")
        for b_ in bands:
            k = f"grd_{b_}"
            if any(k in r for r in rs):
                b = max((r for r in rs if k in r), key=lambda r: (r[k]["pd"], -r[k]["extra"], objective(r, b_)))
                best[k] = b
                log(f"best GRD {b_.upper()} centre detection: {fmt_setting(b)} -> {b[k]['hits']}/{b[k]['n']} "
                    f"(extra {b[k]['extra']:.2f}/chip)")
        pick = elig[0] if elig else max(rs, key=lambda r: objective(r, band))
        keys = ("pfa", "guard", "background", "looks", "min_area_px", "merge_px", "extra")
        choice[det] = {"setting": {k: pick[k] for k in keys}, "band": band, "row": pick,
                       "eligible": bool(elig),
                       "best_per_dataset": {k: {kk: v[kk] for kk in keys} for k, v in best.items()}}
        log(f"recommended default for {det}: {fmt_setting(pick)}; OpenSARShip band {band.upper()}"
            + ("" if elig else " (no setting met the pd floors: best mean shown)"))
        for b_ in bands:
            if grd(pick, b_):
                log(f"  OpenSARShip {b_.upper()} chips missed with it: {grd(pick, b_)['missed']}")
    return choice


def markdown(rows: list[dict], choice: dict, bands, detectors_, band: str = "vh") -> str:
    lines = ["| detector | setting | SSDD FoM / pd / prec | HRSID FoM / pd / prec | HRSID px TPR / FPR | "
             + " | ".join(f"GRD {b.upper()} centre / extra" for b in bands) + " | mean |",
             "|---|---|---|---|---|" + "---|" * len(bands) + "---|"]

    def line(r, tag=""):
        cells = [r["detector"] + tag, fmt_setting(r)]
        for ds in ("ssdd", "hrsid"):
            s = r.get(ds)
            cells.append(f"{s['fom']:.3f} / {s['pd']:.3f} / {s['precision']:.3f}" if s else "")
        h = r.get("hrsid")
        cells.append(f"{h['tpr']:.3f} / {h['fpr']:.1e}" if h and "tpr" in h else "")
        for b in bands:
            g = grd(r, b)
            cells.append(f"{g['hits']}/{g['n']} / {g['extra']:.2f}" if g else "")
        cells.append(f"{objective(r, band):.3f}")
        return "| " + " | ".join(cells) + " |"

    for det in detectors_:
        if det not in choice:
            continue
        dr = default_row(rows, det)
        if dr is not None:
            lines.append(line(dr, " (code default)"))
        lines.append(line(choice[det]["row"], " **(recommended)**"))
        for k, st in choice[det]["best_per_dataset"].items():
            r = next(r for r in rows if r["detector"] == det and same_setting(r, st))
            lines.append(line(r, f" (best {k})"))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--work", type=Path, help="scratch folder (default: a temporary folder)")
    ap.add_argument("--detectors", default=",".join(DETECTORS))
    ap.add_argument("--quick", action="store_true", help="a few settings only")
    ap.add_argument("--limit", type=int, help="at most this many chips per dataset")
    ap.add_argument("--threads", type=int, default=3, help="concurrent run_detection calls")
    ap.add_argument("--scheduler", help="existing Dask scheduler (default: a 2-process LocalCluster)")
    ap.add_argument("--json", type=Path, help="write every row here")
    ap.add_argument("--md", type=Path, help="write the summary table (markdown) here")
    ap.add_argument("--band", default="vh", choices=BANDS, help="OpenSARShip band used for the choice")
    ap.add_argument("--from-json", type=Path, help="only re-report the rows saved by an earlier --json")
    ap.add_argument("--no-check", action="store_true", help="skip the post-processing self-check")
    a = ap.parse_args(argv)

    if a.from_json:  # re-report saved rows (e.g. after changing the choice rule)
        doc = json.loads(a.from_json.read_text())
        rows = doc["rows"]
        dets = [d for d in a.detectors.split(",") if d and any(r["detector"] == d for r in rows)]
        choice = report(rows, dets, BANDS, a.band)
        md = markdown(rows, choice, BANDS, dets, a.band)
        print("\n" + md)
        if a.md:
            a.md.write_text(md)
        return 0
    if not a.data.is_dir():
        print(f"real data not found at {a.data}", file=sys.stderr)
        return 2
    dets = [d for d in a.detectors.split(",") if d]
    grid = {"pfas": PFAS, "windows": WINDOWS, "looks": LOOKS, "min_areas": MIN_AREAS, "merges": MERGES,
            "bands": BANDS}
    if a.quick:
        grid.update(pfas=(1e-4, 1e-5), windows=((31, 61), (41, 61)), looks=("scene", 1.0))
    t_all = time.perf_counter()
    tmp = None
    work = a.work
    if work is None:
        tmp = tempfile.mkdtemp(prefix="sarship-realdata-")
        work = Path(tmp)
    try:
        t0 = time.perf_counter()
        chips = ingest_all(a.data, work / "scenes", a.limit)
        n = {ds: sum(c.dataset == ds for c in chips) for ds in DATASETS}
        print(f"ingested {n} chips in {time.perf_counter() - t0:.1f} s", flush=True)
        for ds in ("ssdd", "hrsid"):
            Ls = [c.looks for c in chips if c.dataset == ds]
            if Ls:
                print(f"  {ds}: scene looks (MoLC estimate) {min(Ls):.2f} .. {max(Ls):.2f}, "
                      f"median {float(np.median(Ls)):.2f}")
        Lg = sorted({c.looks for c in chips if c.dataset == "grd"})
        if Lg:
            print(f"  grd: scene looks {Lg} (SNAP sidecar, nominal)")

        from distributed import Client, LocalCluster

        if a.scheduler:
            client, cluster = Client(a.scheduler), None
        else:
            cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.ERROR)
            client = Client(cluster)
        try:
            if not a.no_check:
                t0 = time.perf_counter()
                self_check(client, chips, dets, work)
                print(f"self-check (local min_area/merge == run_detection) passed in "
                      f"{time.perf_counter() - t0:.1f} s", flush=True)
            t0 = time.perf_counter()
            rows = sweep(client, chips, dets, grid, work, a.threads,
                         log=lambda m: print(m, flush=True))
            print(f"sweep: {len(rows)} rows in {time.perf_counter() - t0:.1f} s", flush=True)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        choice = report(rows, dets, grid["bands"], a.band)
        md = markdown(rows, choice, grid["bands"], dets, a.band)
        print("\n" + md)
        if a.json:
            a.json.write_text(json.dumps({"rows": rows, "choice": choice}, indent=1, default=str))
        if a.md:
            a.md.write_text(md)
        print(f"total {time.perf_counter() - t_all:.1f} s")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
