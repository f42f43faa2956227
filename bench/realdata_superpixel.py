"""``superpixel_cfar`` on the real chips (SAR-Ship-Dataset, HRSID) beside ``two_parameter``, in the
paper's table form (pixel FPR / TPR, zhang2023 Table 2) with the object scores.

Zhang et al. 2023 (docs/references.md, ``zhang2023``) report, on a 1 m TerraSAR-X image, FPR 0.31 %
/ TPR 87.93 % against the two-parameter CFAR's 3.19 % / 83.41 %. Here: the chips and the halves
of ``realdata_eval`` (``ingest_all``, ``split_halves``), one ``run_detection`` per chip and
setting (one tile, the scene pass included), the object scores with each setting's ``merge_px``
and the pixel size rule (the chips have no pixel spacing: ``min_area_px`` 10, the detectors'
default), pixel TPR/FPR on HRSID (the only set with masks). No tuning: the settings below are
fixed before the run; both halves are reported.

``nice -n 10 python bench/realdata_superpixel.py [--limit N] [--only 0,2] [--sets hrsid] [--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import realdata_eval as rd

SETTINGS = [
    ("superpixel_cfar", "defaults", {}),
    ("superpixel_cfar", "contrast=off pfa=0.1", {"contrast": "off", "pfa": 0.1}),
    ("superpixel_cfar", "land_mask=texture", {"land_mask": "texture"}),
    ("two_parameter", "defaults (pfa 1e-6, 41/81)", {}),
    ("two_parameter", "pfa 1e-3 (superpixel_cfar's)", {"pfa": 1e-3}),
    ("two_parameter", "defaults, land_mask=texture", {"land_mask": "texture"}),
    ("two_parameter", "pfa 1e-3, land_mask=texture", {"pfa": 1e-3, "land_mask": "texture"}),
    # two_parameter's PFA raised until its pixel TPR reaches superpixel_cfar's (the paper's "at
    # equal or higher TPR" comparison of pixel FPR)
    ("two_parameter", "pfa 1e-2, land_mask=texture", {"pfa": 1e-2, "land_mask": "texture"}),
    ("two_parameter", "pfa 0.1, land_mask=texture", {"pfa": 0.1, "land_mask": "texture"}),
    ("two_parameter", "pfa 0.3, land_mask=texture", {"pfa": 0.3, "land_mask": "texture"}),
    ("two_parameter", "pfa 0.45, land_mask=texture", {"pfa": 0.45, "land_mask": "texture"}),
]
SETS = ("ssdd", "hrsid")


#: Issue 31 candidates: ``point_pfa`` (small ships; a job each) and the largest ship kept, in pixels
#: where the spacing is unknown (``max_ship_px``: SSDD, HRSID) and in m^2 where it is known
#: (``max_ship_m2``: the OpenSARShip GRD chips); None: off
POINT_PFAS = (None, 1e-5, 1e-7)
MAX_SHIP_PX = (None, 1000, 2000, 3000, 5000, 10000)
MAX_SHIP_M2 = (None, 30000.0, 100000.0, 300000.0)


def issue31_sweep(client, chips, work: Path, sets) -> dict:
    """Issue 31: ``superpixel_cfar`` at its defaults but ``point_pfa`` (one job per chip and value)
    and the largest ship kept (applied to the job's mask components, as ``max_area_px``), scored
    per set and half (min_area_px 10 where the spacing is unknown, the metre rule on GRD). The
    values are chosen on half A (mean over the sets of FoM, GRD: centre-ship FoM), reported on B."""
    from sarship.pipeline.detectors import get
    from sarship.pipeline.detectors.base import area_px, resolve_size
    from sarship.pipeline.products.scoring import score

    per: dict = {}
    for pp in POINT_PFAS:
        for c in chips:
            mask, _ = rd.run_mask(
                client, c, "superpixel_cfar", {"point_pfa": "none" if pp is None else str(pp), "min_area_px": "1"}, work
            )
            rec = rd.components(mask, 4)
            caps = MAX_SHIP_M2 if c.spacing else MAX_SHIP_PX
            for cap in caps:
                flt = rd._Filter(10)
                if c.spacing:  # the detector's metre rule (resolve_size), as run_detection applies it
                    r, _ = resolve_size(get("superpixel_cfar").params(), c.spacing)
                    flt = rd._Filter(r.min_area_px, r.min_length_m)
                flt.max_area_px = None if cap is None else (area_px(cap, c.spacing) if c.spacing else cap)
                ships = rd.detections(rec, flt, c.spacing)
                if c.dataset == "grd":
                    hit, extra = rd.centre_hit(ships, c.shape)
                    sc = {
                        "hit": int(hit),
                        "extra": extra,
                        "ship": int(c.name.split("/")[-1] not in rd.NO_SHIP_AT_CENTRE),
                    }
                else:
                    sc = score(ships, c.truth)
                per.setdefault((pp, cap, c.dataset, c.half), []).append(sc)
    table = {k: rd.summarise(k[2], rows) for k, rows in per.items()}

    def mean_fom(pp, cap_px, cap_m2, half):
        return float(np.mean([table[(pp, cap_m2 if ds == "grd" else cap_px, ds, half)]["fom"] for ds in sets]))

    px_caps = MAX_SHIP_PX if any(ds != "grd" for ds in sets) else (None,)
    m2_caps = MAX_SHIP_M2 if "grd" in sets else (None,)
    best = max(
        ((pp, cp, cm) for pp in POINT_PFAS for cp in px_caps for cm in m2_caps),
        # ties on half A: the point rule on (issue 31's small ships, tests/pipeline/test_superpixel_cfar.py),
        # then the tightest largest ship (a merged land-and-ships detection dropped sooner)
        key=lambda t: (mean_fom(*t, "A"), t[0] is not None, -(t[1] or 10**12), -(t[2] or 10**12)),
    )
    print(
        f"chosen on half A (mean FoM of {', '.join(sets)}): point_pfa {best[0]}, max_ship_px {best[1]}, "
        f"max_ship_m2 {best[2]}; half A {mean_fom(*best, 'A'):.3f} (in-sample), half B {mean_fom(*best, 'B'):.3f}"
    )
    print("| point_pfa | largest ship | set | half | precision / recall / FoM (false) |")
    print("|---|---|---|---|---|")
    for (pp, cap, ds, half), v in sorted(
        table.items(), key=lambda kv: (str(kv[0][0]), str(kv[0][1]), kv[0][2], kv[0][3])
    ):
        tag = " (in-sample)" if half == "A" else ""
        unit = " m^2" if ds == "grd" and cap is not None else (" px" if cap is not None else "")
        if ds == "grd":
            print(
                f"| {pp} | {cap}{unit} | {ds} | {half}{tag} | centre {v['hits']}/{v['n_ship']}, extra/chip "
                f"{v['extra']:.2f}, FoM {v['fom']:.3f} |"
            )
        else:
            print(
                f"| {pp} | {cap}{unit} | {ds} | {half}{tag} | {v['precision']:.3f} / {v['pd']:.3f} / "
                f"{v['fom']:.3f} ({v['n_false']}) |"
            )
    return {"chosen": best, "table": {" | ".join(map(str, k)): v for k, v in table.items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--only", default=None, help="comma list of SETTINGS indices to run (default: all)")
    ap.add_argument("--sets", default=",".join(SETS), help="comma list of data sets (default: ssdd,hrsid)")
    ap.add_argument(
        "--issue31",
        action="store_true",
        help="issue 31: choose point_pfa, max_ship_px, max_ship_m2 on half A, report half B",
    )
    a = ap.parse_args()
    sets = tuple(a.sets.split(","))
    todo = [SETTINGS[int(i)] for i in a.only.split(",")] if a.only else SETTINGS
    from distributed import Client, LocalCluster

    from sarship.pipeline import detectors

    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="spx-real-"))
    chips = [c for c in rd.ingest_all(rd.DATA, work, a.limit) if c.dataset in sets]
    rd.split_halves(chips)
    out = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as lc, Client(lc) as client:
        if a.issue31:
            res = issue31_sweep(client, chips, work, sets)
            if a.json:
                Path(a.json).write_text(json.dumps(res, indent=1, default=str))
            return
        for det, label, kw in todo:
            p = detectors.get(det).params(**{k: v for k, v in kw.items()})
            grid = {"merges": [p.merge_px], "min_areas": [10], "min_lengths": [], "areas_m2": []}
            per = {}
            t = time.perf_counter()
            for c in chips:
                mask, _ = rd.run_mask(client, c, det, {**{k: str(v) for k, v in kw.items()}, "min_area_px": 1}, work)
                s = rd.chip_scores(c, mask, grid)[("px10", p.merge_px)]
                per.setdefault((c.dataset, c.half), []).append(s)
                per.setdefault((c.dataset, "all"), []).append(s)
            secs = time.perf_counter() - t
            for (ds, half), rows in sorted(per.items()):
                out[f"{det} | {label} | {ds} | {half}"] = {**rd.summarise(ds, rows), "seconds": round(secs, 1)}
    print(f"{len(chips)} chips, {time.perf_counter() - t0:.0f} s")
    print("| detector | setting | set | half | precision / recall / FoM | pixel FPR / TPR |")
    print("|---|---|---|---|---|---|")
    for k, v in out.items():
        det, label, ds, half = k.split(" | ")
        px = f"{100 * v['fpr']:.2f} % / {100 * v['tpr']:.2f} %" if "fpr" in v else "-"
        print(f"| {det} | {label} | {ds} | {half} | {v['precision']:.3f} / {v['pd']:.3f} / {v['fom']:.3f} | {px} |")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
