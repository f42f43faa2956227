"""Issue 31: a sea-referenced texture land rule (candidate) against the shipped one on the shared real chips.

For every chip of ``../shared/data/real`` (SSDD-like, HRSID, OpenSARShip GRD VH; ingested and split
into the fixed halves A and B exactly as :mod:`realdata_eval` does) and every detector asked for, at
the detector's defaults, three land masks: ``none``, ``shipped``
(:func:`sarship.pipeline.land.landmask.decide` at the shipped defaults: a 2-class mixture, land only where
Ashman's D >= 2, threshold ``t*``) and ``sea_ref`` (the candidate of issue 31, :func:`sea_ref_decision`:
3 classes, no D gate, threshold ``max(t*, sea mean + 3 sea sd)``, land when >= 2 % of the sample is
above it and the scene is at least ``land_open_px`` on both sides; chosen on half A, worse on half B,
so not shipped: bench/REALDATA.md, "Issue 31"). The mask is computed on the whole
chip (mirror-padded, as a one-tile run computes it), land is set to NaN, the detector runs on the
whole chip in-process and its mask is post-processed with the pipeline's component code and size /
shape rules (:func:`realdata_eval.components`, :func:`realdata_eval.detections`), as the eval does.

Reported per detector, mask and half: pooled object scores (SSDD, HRSID), the GRD centre-ship score,
and the ships whose centre lies under the land mask. Choose on half A, report half B
(bench/REALDATA.md, "The split").

Usage::

    python bench/realdata_landmask.py --detectors ca_cfar,k_cfar [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import realdata_eval as ev  # noqa: E402


def image(scene: Path) -> np.ndarray:
    """The chip's intensity (GRD: the VH band, the eval's default band)."""
    import zarr

    g = zarr.open_group(str(scene), mode="r")
    name = "intensity_vh" if "intensity_vh" in g else "intensity"
    return np.asarray(g[name][...], np.float64)


#: The candidate's floor: texture above the sea component's mean + SEA_Z sds is not sea (chosen on
#: half A among 2.33, 3 and 4, with 3 and 4 classes).
SEA_Z = 3.0


def sea_ref_decision(t: np.ndarray, cfg, shape: tuple[int, int]) -> dict:
    """The candidate rule (module doc): no Ashman's D gate; the threshold is referred to the sea's
    own component (the lowest of ``cfg.classes``)."""
    from sarship.pipeline.land import landmask as lm

    t = t[np.isfinite(t)]
    fit = lm.fit_mixture(t, cfg.classes)
    t_star = lm.threshold(fit)
    floor = float(fit["means"][0] + SEA_Z * fit["sds"][0])
    thr = floor if t_star is None else max(t_star, floor)
    land = float(np.mean(t > thr)) >= lm.MIN_LAND_WEIGHT and min(shape) >= cfg.open_px
    return {"land": bool(land), "threshold": thr if land else None}


def land_mask(I: np.ndarray, kind: str) -> np.ndarray:
    """The whole chip's land mask: ``none``, ``shipped`` or ``sea_ref`` (module doc)."""
    from sarship.pipeline.land import landmask as lm
    from sarship.pipeline.tiling.windows import mirror_pad

    if kind == "none":
        return np.zeros(I.shape, bool)
    cfg = lm.TextureConfig(classes=2 if kind == "shipped" else 3, open_px=51)  # the detectors' defaults
    r = cfg.window // 2
    t = lm.texture(mirror_pad(I, r), r, (-r, -r), cfg.window)
    st = lm.sample_stride(I.shape)
    ts = t[::st, ::st].ravel()
    dec = lm.decide(ts, cfg) if kind == "shipped" else sea_ref_decision(ts, cfg, I.shape)
    h = cfg.halo
    return lm.classify(mirror_pad(I, h), h, (-h, -h), cfg, dec)


def ships_under(chip: ev.Chip, L: np.ndarray) -> tuple[int, int]:
    """(ships whose centre pixel is land, ships): the GRD chip's centre ship, the others' truth."""
    if chip.dataset == "grd":
        return int(L[L.shape[0] // 2, L.shape[1] // 2]), 1
    n = 0
    for s in chip.truth:
        r, c = s.centroid
        n += int(L[min(int(r), L.shape[0] - 1), min(int(c), L.shape[1] - 1)])
    return n, len(chip.truth)


def detect(detector: str, chip: ev.Chip, I: np.ndarray, L: np.ndarray) -> list:
    from sarship.pipeline import detectors
    from sarship.pipeline.tiling.windows import mirror_pad

    spec = detectors.get(detector)
    p = spec.params(looks=chip.looks)
    h = spec.halo(p)
    J = I.copy()
    J[L] = np.nan
    m, _ = spec.detect(mirror_pad(J, h), h, (-h, -h), p, spec.prepare(p))
    return ev.detections(ev.components(m, p.merge_px), p, chip.spacing)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ev.DATA)
    ap.add_argument("--detectors", default="ca_cfar,k_cfar")
    ap.add_argument("--masks", default="none,shipped,sea_ref")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--halves", default="AB", help="the halves run: A, B or AB")
    a = ap.parse_args(argv)
    from sarship.pipeline.products.scoring import score

    if not a.data.is_dir():
        print(f"realdata_landmask: no data at {a.data}", file=sys.stderr)
        return 2
    dets, kinds = a.detectors.split(","), a.masks.split(",")
    with tempfile.TemporaryDirectory() as work:
        chips = ev.ingest_all(a.data, Path(work))
        ev.split_halves(chips)
        per: dict = {}
        lost: dict = {}
        halves = a.halves
        for chip in chips:
            if chip.half not in halves:
                continue
            I = image(chip.scene)
            for kind in kinds:
                L = land_mask(I, kind)
                u, n = ships_under(chip, L)
                k = (kind, chip.dataset, chip.half)
                lost[k] = [x + y for x, y in zip(lost.get(k, [0, 0, 0]), (u, n, int(L.any())))]
                for det in dets:
                    ships = detect(det, chip, I, L)
                    if chip.dataset == "grd":
                        hit, extra = ev.centre_hit(ships, chip.shape)
                        s = {
                            "hit": int(hit),
                            "extra": extra,
                            "ship": int(chip.name.split("/")[-1] not in ev.NO_SHIP_AT_CENTRE),
                        }
                    else:
                        s = score(ships, chip.truth)
                    per.setdefault((det, kind, chip.dataset, chip.half), ([], []))
                    per[(det, kind, chip.dataset, chip.half)][0].append(s)
                    per[(det, kind, chip.dataset, chip.half)][1].append(chip.name)
    rows = []
    print(
        "| detector | mask | half | SSDD FoM (pd / prec / false) | HRSID FoM (pd / prec / false) | GRD VH pd / FoM | mean FoM |"
    )
    print("|---|---|---|---|---|---|---|")
    for det in dets:
        for half in a.halves:
            for kind in kinds:
                sm = {ds: ev.summarise(ds, *per[(det, kind, ds, half)]) for ds in ev.DATASETS}
                mean = float(np.mean([sm[ds]["fom"] for ds in ev.DATASETS]))
                rows.append(
                    {
                        "detector": det,
                        "mask": kind,
                        "half": half,
                        "mean_fom": mean,
                        **{ds: sm[ds] for ds in ev.DATASETS},
                    }
                )
                f = {
                    ds: f"{sm[ds]['fom']:.3f} ({sm[ds]['pd']:.3f} / {sm[ds]['precision']:.3f} / {sm[ds]['n_false']})"
                    for ds in ("ssdd", "hrsid")
                }
                print(
                    f"| {det} | {kind} | {half} | {f['ssdd']} | {f['hrsid']} | {sm['grd']['pd']:.3f} / "
                    f"{sm['grd']['fom']:.3f} | {mean:.3f} |"
                )
    print(
        "\n| mask | half | ships under the mask SSDD | HRSID | GRD centre ships | chips with land (SSDD, HRSID, GRD) |"
    )
    print("|---|---|---|---|---|---|")
    for half in a.halves:
        for kind in kinds:
            v = {ds: lost[(kind, ds, half)] for ds in ev.DATASETS}
            print(
                f"| {kind} | {half} | {v['ssdd'][0]}/{v['ssdd'][1]} | {v['hrsid'][0]}/{v['hrsid'][1]} | "
                f"{v['grd'][0]}/{v['grd'][1]} | {v['ssdd'][2]}, {v['hrsid'][2]}, {v['grd'][2]} |"
            )
    if a.json:
        a.json.write_text(
            json.dumps(
                {"rows": rows, "lost": {"/".join(k): v for k, v in lost.items()}},
                indent=1,
                default=lambda o: None if isinstance(o, float) and math.isnan(o) else str(o),
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
