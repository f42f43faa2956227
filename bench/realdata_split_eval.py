"""Detectors at their shipped defaults on a dataset's official test split, offshore and inshore apart.

Reads a dataset converted by ``bench/datasets.py`` (``dataset.json``, ``images/``, ``truth/*.geojson``,
``splits/*.txt``). Every test image goes the way users' scenes go: ingested with
:func:`sarship.pipeline.readers.ingest` (one tile) and detected with
:func:`sarship.workers.jobs.run_detection` at the detector's defaults (no setting given), on one
Dask ``LocalCluster`` (``bench/realdata_eval.py: run_mask``). Nothing here is tuned: the test
split is only reported.

Two matchers, each one-to-one:

- **IoU >= 0.5** (:func:`match_iou`), the PASCAL-VOC rule the SSDD, HRSID and LS-SSDD papers
  score with. A CFAR detection has no confidence to rank by, so pairs are taken by IoU,
  highest first (ties: detection index, then truth index). A detection matched to no ship is
  a false alarm, a ship matched by none is missed.
- **The project's object matcher** (:func:`sarship.pipeline.products.scoring.score`: centroid in the box
  or IoU >= 0.1), as in ``bench/REALDATA.md``'s other tables, with its FoM
  = hits / (false alarms + ships).

Precision, recall and F1 are micro-averages over the images of a subset (counts summed first):
``test_offshore``, ``test_inshore`` (where the release defines them) and the whole ``test``
split. ``--every K`` scores every K-th image of each subset (sorted ids), for a quicker
look; the table says so.

Usage::

    python bench/datasets.py fetch ssdd_official --to /data/sar --from Official-SSDD-OPEN.rar
    python bench/realdata_split_eval.py --data /data/sar/ssdd_official --md table.md --json rows.json
    python bench/realdata_split_eval.py --data /data/sar/ssdd_official --every 4   # a quarter

Bad input (a folder that is not a converted dataset, an unknown detector) exits 2 with one line
on stderr.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _sibling(name: str):
    """A module of bench/ (not a package) by its path, without adding bench/ to ``sys.path``."""
    import importlib.util

    key = f"sarship_bench_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, Path(__file__).resolve().parent / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[key] = mod
        spec.loader.exec_module(mod)
    return sys.modules[key]


rde = _sibling("realdata_eval")

#: The detectors of issue 31's table, at their shipped defaults.
DETECTORS = ("ca_cfar", "os_cfar", "k_cfar", "g0_cfar", "superpixel_cfar")
#: The subsets reported, in table order; those the dataset lacks are skipped.
SUBSETS = ("test_offshore", "test_inshore", "test")
#: PASCAL-VOC overlap for a hit.
IOU_HIT = 0.5


class EvalError(Exception):
    """A one-line problem with the arguments or the dataset (exit status 2)."""


# --------------------------------------------------------------------------------------
# dataset


def load_subsets(folder: Path, every: int = 1, limit: int | None = None) -> dict[str, list[str]]:
    """Image ids of each subset present in ``folder/splits`` (every ``every``-th of the sorted ids,
    at most ``limit``). Raises :class:`EvalError` when the folder is not a converted dataset."""
    folder = Path(folder)
    if not (folder / "dataset.json").is_file():
        raise EvalError(f"'{folder}': not a dataset converted by bench/datasets.py (no dataset.json)")
    if every < 1:
        raise EvalError(f"--every must be >= 1, got {every}")
    out: dict[str, list[str]] = {}
    for s in SUBSETS:
        p = folder / "splits" / f"{s}.txt"
        if p.is_file():
            ids = sorted(line.strip() for line in p.read_text().splitlines() if line.strip())
            ids = ids[::every]
            out[s] = ids[:limit] if limit else ids
    if "test" not in out:
        raise EvalError(f"'{folder}': no splits/test.txt")
    for s, ids in out.items():
        for i in ids:
            if not list((folder / "images").glob(f"{i}.*")):
                raise EvalError(f"'{folder}': {s} image '{i}' is missing from images/")
            if not (folder / "truth" / f"{i}.geojson").is_file():
                raise EvalError(f"'{folder}': {s} image '{i}' has no truth/{i}.geojson")
    return out


# --------------------------------------------------------------------------------------
# matching and scores


def iou_matrix(dboxes: np.ndarray, tboxes: np.ndarray) -> np.ndarray:
    """IoU of every (detection, truth) pair of half-open ``[row0, col0, row1, col1]`` boxes."""
    d = np.asarray(dboxes, float).reshape(-1, 4)[:, None, :]
    t = np.asarray(tboxes, float).reshape(-1, 4)[None, :, :]
    ih = np.clip(np.minimum(d[..., 2], t[..., 2]) - np.maximum(d[..., 0], t[..., 0]), 0, None)
    iw = np.clip(np.minimum(d[..., 3], t[..., 3]) - np.maximum(d[..., 1], t[..., 1]), 0, None)
    inter = ih * iw
    area = lambda b: np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)  # noqa: E731
    union = area(d) + area(t) - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def match_iou(dboxes, tboxes, thr: float = IOU_HIT) -> list[tuple[int, int]]:
    """One-to-one ``(detection, truth)`` pairs with IoU >= ``thr``, taken by IoU (highest first;
    ties by detection index, then truth index), sorted by detection index."""
    m = iou_matrix(dboxes, tboxes)
    rows, cols = np.nonzero(m >= thr - 1e-9)
    order = sorted(zip(rows.tolist(), cols.tolist()), key=lambda rc: (-m[rc], rc[0], rc[1]))
    used_d: set[int] = set()
    used_t: set[int] = set()
    pairs = []
    for d, t in order:
        if d not in used_d and t not in used_t:
            used_d.add(d)
            used_t.add(t)
            pairs.append((d, t))
    return sorted(pairs)


def iou_counts(dboxes, tboxes, thr: float = IOU_HIT) -> dict:
    """``n_truth``, ``n_detections``, ``n_hit`` under :func:`match_iou`."""
    nd, nt = len(np.asarray(dboxes).reshape(-1, 4)), len(np.asarray(tboxes).reshape(-1, 4))
    return {"n_truth": nt, "n_detections": nd, "n_hit": len(match_iou(dboxes, tboxes, thr))}


def ratios(c: dict) -> dict:
    """Precision, recall, F1 (and false alarms) of summed counts; 0/0 takes the perfect value
    as in ``pipeline/products/scoring.py`` (no ship: recall 1; no detection: precision 1)."""
    h, nd, nt = c["n_hit"], c["n_detections"], c["n_truth"]
    return {
        "precision": h / nd if nd else 1.0,
        "recall": h / nt if nt else 1.0,
        "f1": 2 * h / (nd + nt) if nd + nt else 1.0,
        "n_false": nd - h,
    }


def image_scores(dets: list, truth: list) -> dict:
    """Both matchers' counts for one image (lists of :class:`sarship.pipeline.products.truth.Ship`)."""
    from sarship.pipeline.products.scoring import score

    box = lambda ships: np.array([s.bbox for s in ships], float).reshape(-1, 4)  # noqa: E731
    ours = score(dets, truth)
    return {
        "iou50": iou_counts(box(dets), box(truth)),
        "ours": {k: ours[k] for k in ("n_truth", "n_detections", "n_hit")},
    }


def summarise(per_image: dict[str, dict], ids: list[str]) -> dict:
    """Summed counts and ratios over ``ids`` for each matcher (FoM for ours)."""
    out: dict = {"images": len(ids)}
    for m in ("iou50", "ours"):
        c = {k: int(sum(per_image[i][m][k] for i in ids)) for k in ("n_truth", "n_detections", "n_hit")}
        r = ratios(c)
        if m == "ours":
            den = r["n_false"] + c["n_truth"]
            r["fom"] = c["n_hit"] / den if den else 1.0
        out[m] = {**c, **r}
    return out


# --------------------------------------------------------------------------------------
# running


def _ships(features: list[dict]) -> list:
    from sarship.pipeline.products.truth import Ship

    out = []
    for f in features:
        p = f["properties"]
        b = tuple(float(v) for v in p["bbox_px"])
        c = tuple(float(v) for v in p.get("centroid_px") or ((b[0] + b[2]) / 2, (b[1] + b[3]) / 2))
        out.append(Ship(b, c))
    return out


def run(
    folder: Path, detectors: list[str], subsets: dict[str, list[str]], client, work: Path, threads: int = 2, log=print
) -> dict:
    """Per detector, per image: both matchers' counts (``{det: {id: scores}}``)."""
    from PIL import Image

    from sarship.pipeline.products.truth import load_geojson
    from sarship.pipeline.readers import ingest

    ids = sorted({i for v in subsets.values() for i in v})
    chips: dict[str, rde.Chip] = {}
    truth: dict[str, list] = {}
    for i in ids:
        img = next(iter(sorted((folder / "images").glob(f"{i}.*"))))
        with Image.open(img) as im:
            side = max(im.size)
        sc = ingest([img], work / f"{rde._safe(i)}.zarr", tile=side)
        chips[i] = rde.Chip("split", i, sc.path, sc.shape, sc.looks)
        truth[i] = load_geojson(folder / "truth" / f"{i}.geojson")
    out: dict[str, dict] = {d: {} for d in detectors}

    def one(det: str, i: str):
        _, res = rde.run_mask(client, chips[i], det, {}, work)
        return det, i, image_scores(_ships(res["features"]), truth[i])

    t0 = time.perf_counter()
    with cf.ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        futs = [ex.submit(one, d, i) for d in detectors for i in ids]
        for n, fut in enumerate(cf.as_completed(futs), 1):
            det, i, sc = fut.result()
            out[det][i] = sc
            if n % 50 == 0 or n == len(futs):
                log(f"  {n}/{len(futs)} runs, {time.perf_counter() - t0:.0f} s")
    return out


def report(rows: dict, subsets: dict[str, list[str]]) -> dict:
    """``{det: {subset: summary}}`` from :func:`run`'s rows."""
    return {d: {s: summarise(per, ids) for s, ids in subsets.items()} for d, per in rows.items()}


def markdown(rep: dict, subsets: dict[str, list[str]], every: int = 1) -> str:
    """The REALDATA.md table: per detector and subset, IoU >= 0.5 and the project's matcher."""
    head = (
        "| detector | subset | images / ships | IoU >= 0.5: precision / recall / F1 (false) "
        "| project matcher: precision / recall / F1 (false), FoM |\n|---|---|---|---|---|\n"
    )
    lines = []
    for d, per in rep.items():
        for s in subsets:
            r = per[s]
            a, o = r["iou50"], r["ours"]
            lines.append(
                f"| {d} | {s.replace('test_', '')} | {r['images']} / {a['n_truth']} "
                f"| {a['precision']:.3f} / {a['recall']:.3f} / {a['f1']:.3f} ({a['n_false']}) "
                f"| {o['precision']:.3f} / {o['recall']:.3f} / {o['f1']:.3f} ({o['n_false']}), {o['fom']:.3f} |"
            )
    note = (
        ""
        if every == 1
        else f"\nOne image in {every} of each subset (every {every}-th of the sorted ids), not the whole split.\n"
    )
    return head + "\n".join(lines) + "\n" + note


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a dataset converted by bench/datasets.py")
    ap.add_argument("--detectors", default=",".join(DETECTORS))
    ap.add_argument("--every", type=int, default=1, help="score every K-th image of each subset")
    ap.add_argument("--limit", type=int, help="at most this many images per subset")
    ap.add_argument("--threads", type=int, default=2, help="concurrent run_detection calls")
    ap.add_argument("--scheduler", help="existing Dask scheduler (default: a 2-process LocalCluster)")
    ap.add_argument("--work", type=Path, help="scratch folder (default: a temporary folder)")
    ap.add_argument("--json", type=Path, help="write per-image counts and the summary here")
    ap.add_argument("--md", type=Path, help="write the markdown table here")
    a = ap.parse_args(argv)
    try:
        from sarship.pipeline.detectors import names

        dets = [d for d in a.detectors.split(",") if d]
        unknown = [d for d in dets if d not in names()]
        if not dets or unknown:
            raise EvalError(f"unknown detector(s): {', '.join(unknown) or '(none given)'}")
        subsets = load_subsets(a.data, a.every, a.limit)
    except EvalError as exc:
        print(f"realdata_split_eval.py: {exc}", file=sys.stderr)
        return 2
    from distributed import Client, LocalCluster

    tmp = None
    work = a.work
    if work is None:
        tmp = tempfile.mkdtemp(prefix="sarship-split-")
        work = Path(tmp)
    work.mkdir(parents=True, exist_ok=True)
    cluster = None
    try:
        if a.scheduler:
            client = Client(a.scheduler)
        else:
            cluster = LocalCluster(
                n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.ERROR
            )
            client = Client(cluster)
        try:
            print("images: " + ", ".join(f"{s} {len(v)}" for s, v in subsets.items()), flush=True)
            rows = run(a.data, dets, subsets, client, work, a.threads, log=lambda m: print(m, flush=True))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        rep = report(rows, subsets)
        md = markdown(rep, subsets, a.every)
        print("\n" + md)
        if a.md:
            a.md.write_text(md)
        if a.json:
            a.json.write_text(json.dumps({"subsets": subsets, "every": a.every, "rows": rows, "report": rep}, indent=1))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
