"""Issue 31: the clutter-model fit and ``--detector auto`` on the shared real chips, by half.

Every chip of ``bench/realdata_eval.py`` (SSDD-like, HRSID, OpenSARShip GRD VH) is run through
:func:`sarship.workers.jobs.run_detection` at the shipped defaults with ``ca_cfar``, ``k_cfar``,
``g0_cfar`` (the ``auto`` candidates) and ``os_cfar``; each run's ``model_fit`` record is kept.
``auto``'s choice on a chip is :func:`sarship.pipeline.stats.model_fit.choose` of the three candidates'
records (what ``--detector auto`` computes: its candidates run with the request's parameters,
here the defaults), its detections those of the chosen detector. Scores per half
(:func:`realdata_eval.split_halves`): SSDD / HRSID object FoM (pd / precision / false), GRD VH
centre-ship pd and FoM proxy, as ``bench/realdata_eval.py`` computes them.

Usage::

    python bench/modelfit_eval.py --json /tmp/modelfit.json --md /tmp/modelfit.md
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import realdata_eval as rd  # noqa: E402

#: The runs per chip: auto's candidates, and (``--detectors``) any other detector with a fit.
DETECTORS = ("ca_cfar", "k_cfar", "g0_cfar")


def run_chip(client, chip, detector: str, work: Path) -> dict:
    """One run at the defaults: its detections as truth.Ship and its model_fit record."""
    from sarship.pipeline.products.truth import Ship
    from sarship.workers.jobs import run_detection

    out = Path(tempfile.mkdtemp(prefix="mf-", dir=work))
    settings = {"channel": "intensity_vh"} if chip.dataset == "grd" else {}
    try:
        run = run_detection(
            chip.scene, detector, settings, out_dir=out, tile=max(chip.shape), client=client, progress=False
        )
        feats = json.loads((out / "detections.geojson").read_text())["features"]
    finally:
        shutil.rmtree(out, ignore_errors=True)
    ships = []
    for f in feats:
        p = f["properties"]
        ships.append(
            Ship(
                tuple(float(v) for v in p["bbox_px"]),
                tuple(float(v) for v in p["centroid_px"]),
                False,
                {"area_px": p["area_px"]},
            )
        )
    return {"ships": ships, "fit": run["model_fit"]}


def chip_score(chip, ships) -> dict:
    from sarship.pipeline.products.scoring import score

    if chip.dataset == "grd":
        hit, extra = rd.centre_hit(ships, chip.shape)
        return {"hit": int(hit), "extra": extra, "ship": int(chip.name.split("/")[-1] not in rd.NO_SHIP_AT_CENTRE)}
    return score(ships, chip.truth)


def main(argv=None) -> int:
    global DETECTORS
    from distributed import Client, LocalCluster

    from sarship.pipeline.stats import model_fit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=rd.DATA)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--md", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2, help="chips run at once")
    ap.add_argument("--detectors", default=",".join(DETECTORS), help="comma list, auto's candidates among them")
    a = ap.parse_args(argv)
    DETECTORS = tuple(d.strip() for d in a.detectors.split(",") if d.strip())
    t0 = time.time()
    work = Path(tempfile.mkdtemp(prefix="modelfit-eval-"))
    cluster = LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True, silence_logs=logging.ERROR)
    client = Client(cluster)
    try:
        chips = rd.ingest_all(a.data, work)
        rd.split_halves(chips)

        def one(chip) -> dict:
            res = {d: run_chip(client, chip, d, work) for d in DETECTORS}
            fits = {d: res[d]["fit"] for d in model_fit.AUTO_CANDIDATES}
            chosen, _why = model_fit.choose(fits)
            row = {
                "dataset": chip.dataset,
                "name": chip.name,
                "half": chip.half,
                "auto": chosen,
                "fit": {
                    d: {k: res[d]["fit"][k] for k in ("verdict", "ratio", "sample", "exceedances")} for d in DETECTORS
                },
                "scores": {d: chip_score(chip, res[d]["ships"]) for d in DETECTORS},
            }
            row["scores"]["auto"] = row["scores"][chosen]
            print(
                f"{chip.dataset} {chip.half} {chip.name}: auto={chosen} "
                + " ".join(f"{d}={res[d]['fit']['verdict']}({res[d]['fit']['ratio'] or 0:.2g}x)" for d in DETECTORS),
                file=sys.stderr,
                flush=True,
            )
            return row

        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(a.threads) as ex:
            rows = list(ex.map(one, chips))
    finally:
        client.close()
        cluster.close()
        shutil.rmtree(work, ignore_errors=True)
    rep = report(rows)
    rep["seconds"] = round(time.time() - t0, 1)
    if a.json:
        a.json.write_text(json.dumps({"rows": rows, "report": rep}, indent=1, default=str))
    text = markdown(rep)
    if a.md:
        a.md.write_text(text)
    print(text)
    return 0


def report(rows: list[dict]) -> dict:
    """Per half and dataset: each detector's (and auto's) summary, the verdicts and auto's choices."""
    out: dict = {}
    for half in ("A", "B"):
        for ds in rd.DATASETS:
            sel = [r for r in rows if r["half"] == half and r["dataset"] == ds]
            if not sel:
                continue
            names = [r["name"] for r in sel]
            out[f"{half}/{ds}"] = {
                "chips": len(sel),
                "scores": {d: rd.summarise(ds, [r["scores"][d] for r in sel], names) for d in (*DETECTORS, "auto")},
                "verdicts": {d: dict(Counter(r["fit"][d]["verdict"] for r in sel)) for d in DETECTORS},
                "auto_chose": dict(Counter(r["auto"] for r in sel)),
            }
    return out


def _fmt(ds: str, s: dict) -> str:
    if ds == "grd":
        return f"pd {s['pd']:.2f}, FoM {s['fom']:.3f}"
    return f"FoM {s['fom']:.3f} ({s['pd']:.2f} / {s['precision']:.2f} / {s['n_false']})"


def markdown(rep: dict) -> str:
    lines = []
    for half, label in (("A", "half A (in-sample: looked at while fixing the rule)"), ("B", "half B (held out)")):
        lines += [
            f"**{label}**",
            "",
            "| set | chips | "
            + " | ".join(DETECTORS)
            + " | auto | auto chose | verdicts at 1e-3 (fits / too many / too few / undetermined) |",
            "|---|---|" + "---|" * (len(DETECTORS) + 3),
        ]
        for ds in rd.DATASETS:
            r = rep.get(f"{half}/{ds}")
            if r is None:
                continue
            sc = " | ".join(_fmt(ds, r["scores"][d]) for d in (*DETECTORS, "auto"))
            chose = ", ".join(f"{k} {v}" for k, v in sorted(r["auto_chose"].items()))
            ver = "; ".join(
                f"{d} {v.get('fits', 0)}/{v.get('too many false alarms', 0)}/{v.get('too few', 0)}/"
                f"{v.get('undetermined', 0)}"
                for d, v in r["verdicts"].items()
            )
            lines.append(f"| {ds} | {r['chips']} | {sc} | {chose} | {ver} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
