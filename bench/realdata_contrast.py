"""The local-contrast floor ``min_contrast_db`` on the real chips, chosen by cross-validation.

Every detector named runs once per chip at its shipped defaults with ``min_contrast_db=-30`` (which
measures every detection's contrast and, as the script checks, drops none)
(and, optionally, a small grid of its own settings: ``--grid``) through
:func:`sarship.workers.jobs.run_detection` on one shared two-process Dask ``LocalCluster``; each
detection keeps its ``contrast_db`` (pipeline/targets/local_contrast.py) and whether it is a true ship.
A floor only drops detections, so every floor of ``--floors`` is applied afterwards to the same
runs, exactly as the pipeline applies it (a detection whose contrast was not measured is kept).

Data, halves and scores are those of ``bench/realdata_eval.py`` (its module docstring): object
FoM summed over the chips for SAR-Ship-Dataset and HRSID, and for the OpenSARShip GRD chips (VH)
the centre ship found or not and the FoM proxy that counts every other detection as false.
A detection is a true ship when :func:`sarship.pipeline.products.scoring.match` pairs it with a truth
box (SSDD, HRSID), or, on a GRD chip, when its box lies within ``CENTRE_RADIUS_PX`` of the chip
centre.

Choice on a half, as ``realdata_eval.choose``: the highest mean of the three sets' FoM on that
half among the candidates (setting x floor, "none" included) whose SSDD and HRSID pd are within
``PD_SLACK`` of the best pd any candidate reaches there and that find every GRD centre ship of
the half; ties go to fewer SSDD + HRSID false alarms, then to the lower floor. Both folds are
reported (tuned on A -> reported on B, and the swap). The other studies ship the A-tuned choice;
for ``superpixel_cfar`` the shipped floor is the B-tuned one, held out on A, because every HRSID
false alarm it removes lies in half B (bench/REALDATA.md, "The local-contrast floor").

Usage::

    python bench/realdata_contrast.py --detectors superpixel_cfar,ca_cfar --json contrast.json
    python bench/realdata_contrast.py --from-json contrast.json          # re-report, no runs
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import realdata_eval as R  # noqa: E402  (the chips, halves and constants of the main study)

#: the tag of the run at the detector's own defaults (always run first: the "no floor" baseline)
DEFAULTS = json.dumps({})
FLOORS = (None, 0.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0)


def run_all(client, chips: list, detector: str, settings: dict, work: Path) -> list[dict]:
    """One run per chip; a row per detection: dataset, chip, half, ship (bool), contrast_db."""
    from sarship.pipeline.products.scoring import match
    from sarship.pipeline.products.truth import Ship
    from sarship.workers.jobs import run_detection

    rows = []
    for c in chips:
        st = dict(settings, min_contrast_db=-30.0)  # measures every detection's contrast
        if c.dataset == "grd":
            st["channel"] = "intensity_vh"
        out = Path(tempfile.mkdtemp(prefix="contrast-", dir=work))
        run = run_detection(
            c.scene, detector, st, out_dir=out, tile=max(c.shape), client=client, progress=False, overwrite=True
        )
        assert run["contrast"]["dropped"] == 0, (c.name, run["contrast"])  # -30 dB drops nothing here
        feats = json.loads((out / "detections.geojson").read_text())["features"]
        shutil.rmtree(out, ignore_errors=True)
        ships = [
            Ship(bbox=tuple(f["properties"]["bbox_px"]), centroid=tuple(f["properties"]["centroid_px"])) for f in feats
        ]
        if c.dataset == "grd":
            centre = c.name.split("/")[-1] not in R.NO_SHIP_AT_CENTRE
            true = [centre and R.centre_hit([s], c.shape)[0] for s in ships]
        else:
            paired = {d for d, _ in match(ships, c.truth)}
            true = [i in paired for i in range(len(ships))]
        for f, t in zip(feats, true):
            rows.append(
                {
                    "dataset": c.dataset,
                    "chip": c.name,
                    "half": c.half,
                    "ship": bool(t),
                    "contrast_db": f["properties"]["contrast_db"],
                }
            )
    return rows


def truth_counts(chips: list) -> dict:
    """(dataset, half) -> number of true ships (GRD: chips with a centre ship)."""
    out: dict = {}
    for c in chips:
        n = int(c.name.split("/")[-1] not in R.NO_SHIP_AT_CENTRE) if c.dataset == "grd" else len(c.truth)
        for h in (c.half, "all"):
            out[(c.dataset, h)] = out.get((c.dataset, h), 0) + n
    return out


def scores(rows: list[dict], floor: float | None, half: str, counts: dict) -> dict:
    out = {}
    for ds in ("ssdd", "hrsid", "grd"):
        kept = [
            r
            for r in rows
            if r["dataset"] == ds
            and (half == "all" or r["half"] == half)
            and (floor is None or r["contrast_db"] is None or r["contrast_db"] >= floor)
        ]
        hit = sum(r["ship"] for r in kept)
        fa = len(kept) - hit
        n = counts.get((ds, half), 0)
        out[ds] = {"hit": hit, "false": fa, "truth": n, "pd": hit / max(n, 1), "fom": hit / max(n + fa, 1)}
    out["mean"] = sum(out[d]["fom"] for d in ("ssdd", "hrsid", "grd")) / 3
    return out


def choose(runs: dict, floors, half: str, counts: dict):
    cands = [(tag, f) for tag in runs for f in floors]
    sc = {c: scores(runs[c[0]], c[1], half, counts) for c in cands}
    best = {d: max(s[d]["pd"] for s in sc.values()) for d in ("ssdd", "hrsid")}
    ok = [
        c
        for c in cands
        if all(sc[c][d]["pd"] >= best[d] - R.PD_SLACK - 1e-12 for d in best) and sc[c]["grd"]["pd"] >= R.MIN_GRD_PD
    ]
    pool = ok or cands
    pool.sort(
        key=lambda c: (
            -round(sc[c]["mean"], 6),
            sc[c]["ssdd"]["false"] + sc[c]["hrsid"]["false"],
            -1e9 if c[1] is None else c[1],
        )
    )
    return pool[0], bool(ok)


def fmt(s: dict) -> str:
    return (
        " | ".join(
            f"{s[d]['hit']}/{s[d]['truth']}, {s[d]['false']} false, FoM {s[d]['fom']:.3f}"
            for d in ("ssdd", "hrsid", "grd")
        )
        + f" | {s['mean']:.3f}"
    )


def report(results: dict, floors, log=print) -> dict:
    rep = {}
    for det, res in results.items():
        runs, counts = res["runs"], {tuple(k.split("|")): v for k, v in res["counts"].items()}
        log(f"\n## {det}")
        log(
            "| tuned on | choice | reported on | SSDD hit/truth, false, FoM | HRSID | GRD-VH centre/chips, other, FoM proxy | mean |"
        )
        log("|---|---|---|---|---|---|---|")
        rep[det] = {}
        for tune, held in (("A", "B"), ("B", "A")):
            (tag, floor), eligible = choose(runs, floors, tune, counts)
            for where in (tune, held, "all"):
                s = scores(runs[tag], floor, where, counts)
                log(
                    f"| {tune} | {tag} min_contrast_db={floor} | {where}{' (held out)' if where == held else ''} | "
                    + fmt(s)
                    + " |"
                )
            log(f"| - | {DEFAULTS} no floor | {held} | " + fmt(scores(runs[DEFAULTS], None, held, counts)) + " |")
            rep[det][tune] = {
                "setting": tag,
                "floor": floor,
                "eligible": eligible,
                "held_out": scores(runs[tag], floor, held, counts),
                "all": scores(runs[tag], floor, "all", counts),
            }
        lows = {}
        for ds in ("ssdd", "hrsid", "grd"):
            base = runs[DEFAULTS]
            vals = sorted(
                r["contrast_db"] for r in base if r["dataset"] == ds and r["ship"] and r["contrast_db"] is not None
            )
            fals = sorted(
                r["contrast_db"] for r in base if r["dataset"] == ds and not r["ship"] and r["contrast_db"] is not None
            )
            lows[ds] = {
                "ships_lowest": [round(v, 2) for v in vals[:4]],
                "false_lowest": [round(v, 2) for v in fals[:8]],
            }
            log(
                f"- {ds}: the dimmest true ships {lows[ds]['ships_lowest']} dB; the dimmest other detections "
                f"{lows[ds]['false_lowest']} dB"
            )
        rep[det]["lowest"] = lows
    return rep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "shared" / "data" / "real")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--detectors", default="superpixel_cfar")
    ap.add_argument("--grid", default="{}", help="JSON {detector: {param: [values]}} of settings to sweep too")
    ap.add_argument("--floors", default=",".join("none" if f is None else str(f) for f in FLOORS))
    ap.add_argument("--json", type=Path, help="write the runs and the report here")
    ap.add_argument("--from-json", type=Path, help="re-report an earlier --json without running")
    a = ap.parse_args(argv)
    floors = [None if x.strip() == "none" else float(x) for x in a.floors.split(",")]
    if a.from_json:
        results = json.loads(a.from_json.read_text())["results"]
        report(results, floors)
        return 0
    if not a.data.is_dir():
        print(f"real data not found at {a.data}", file=sys.stderr)
        return 2
    from distributed import Client, LocalCluster

    from sarship.pipeline import detectors

    work = a.work or Path(tempfile.mkdtemp(prefix="realdata-contrast-"))
    t0 = time.perf_counter()
    chips = R.ingest_all(a.data, work / "chips")
    R.split_halves(chips)
    counts = {f"{k[0]}|{k[1]}": v for k, v in truth_counts(chips).items()}
    grid = json.loads(a.grid)
    results = {}
    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.ERROR
        ) as cl,
        Client(cl) as client,
    ):
        for det in a.detectors.split(","):
            detectors.get(det)  # an unknown name fails here, before any run
            g = grid.get(det, {})
            # the detector's defaults first (the "no floor" baseline), then the grid's other settings
            settings = [{}] + [st for st in (dict(zip(g, v)) for v in itertools.product(*g.values())) if st]
            runs = {}
            for st in settings:
                t1 = time.perf_counter()
                runs[json.dumps(st, sort_keys=True)] = run_all(client, chips, det, st, work)
                print(f"{det} {st}: {time.perf_counter() - t1:.0f} s", file=sys.stderr, flush=True)
            results[det] = {"runs": runs, "counts": counts}
    rep = report(results, floors)
    print(f"\n{time.perf_counter() - t0:.0f} s in all", file=sys.stderr)
    if a.json:
        a.json.write_text(json.dumps({"results": results, "report": rep}, indent=1, default=str))
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
