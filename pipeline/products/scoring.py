"""Object-level and pixel-level scores of detections against truth (docs/interfaces/files.md, "Scores").

Matching (:func:`match`)
    A detection *can* match a truth ship when its centroid lies in the truth box
    (half-open: ``row0 <= r < row1`` and ``col0 <= c < col1``) **or** the two boxes overlap
    with IoU >= 0.1 (compared with a 1e-9 tolerance, so an IoU of exactly 0.1 matches
    despite float rounding). Matching is one-to-one and greedy: candidate pairs are taken
    in order, a pair is kept when neither its detection nor its truth is taken yet.
    Order: first the pairs with IoU >= 0.1, highest IoU first, ties broken by centroid
    distance (detection centroid to truth centroid); then the centroid-only pairs
    (IoU < 0.1), nearest centroid first, ties by higher IoU; last ties by detection index,
    then truth index -- fully deterministic.

    Difficult truth ships are matched in a second pass, after the other ships: a detection
    that could be a hit on an ordinary ship is never spent on a difficult one.

Object scores (:func:`score`)
    - ``n_truth``: truth ships that are not difficult; ``n_difficult``: the difficult ones.
    - ``n_ignored``: detections matched to a difficult ship. They are neither hits nor false
      alarms and are **not counted in** ``n_detections`` (so precision is not diluted by
      them). Only the one detection matched (one-to-one) to a difficult ship is ignored: a
      second detection on the same difficult ship is a false alarm, as on any ship.
    - ``n_detections`` = all detections - ``n_ignored``; ``n_hit``: detections matched to a
      non-difficult ship; ``n_false`` = ``n_detections - n_hit``; ``n_missed`` =
      ``n_truth - n_hit`` (difficult ships are never missed).
    - ``pd`` (= recall) = n_hit / n_truth; ``precision`` = n_hit / n_detections;
      ``fom`` = n_hit / (n_false + n_truth); ``f1`` = 2 n_hit / (n_detections + n_truth)
      (= the harmonic mean of precision and pd whenever both are defined).

    0/0 cases: a ratio whose denominator is zero has nothing that could have gone wrong,
    so it takes its *perfect* value: ``pd`` = 1.0 when n_truth = 0 (nothing to miss),
    ``precision`` = 1.0 when n_detections = 0 (no false alarm), ``fom`` and ``f1`` = 1.0
    when there is neither truth nor detection. So an empty scene with no detections
    scores 1.0 everywhere, an empty scene with detections has pd 1.0 but precision, fom
    and f1 0.0, and detections-free output on a scene with ships has precision 1.0 but
    pd, fom, f1 0.0. Values are always finite (never NaN in JSON); :func:`aggregate`
    recomputes them from the summed counts.

Pixel scores (when both a detection mask and a truth mask are given)
    ``tpr`` = detected ship pixels / ship pixels, ``fpr`` = detected clutter pixels /
    clutter pixels; with the same 0/0 rule (``tpr`` = 1.0 with no ship pixel, ``fpr`` = 0.0
    with no clutter pixel). The counts ``px_truth``, ``px_clutter``, ``px_tp``, ``px_fp``
    are kept for aggregation. Difficult flags do not apply to pixels.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.products.truth import (
    Ship,
    detections_scene,
    load_detections,
    load_ships,
    read_mask,
    truth_kind,
)

#: Minimum IoU for a box-overlap match (docs/interfaces/files.md).
IOU_MIN = 0.1
#: Float tolerance on the IoU comparison.
IOU_TOL = 1e-9

#: Integer counts summed by :func:`aggregate`.
OBJECT_COUNTS = ("n_truth", "n_detections", "n_hit", "n_false", "n_missed", "n_difficult", "n_ignored")
PIXEL_COUNTS = ("px_truth", "px_clutter", "px_tp", "px_fp")

_CHUNK = 512  # truth ships per vectorised block of the pairwise tables


def _arrays(ships: list[Ship]) -> tuple[np.ndarray, np.ndarray]:
    if not ships:
        return np.zeros((0, 4)), np.zeros((0, 2))
    boxes = np.array([s.bbox for s in ships], dtype=np.float64).reshape(-1, 4)
    cents = np.array([s.centroid for s in ships], dtype=np.float64).reshape(-1, 2)
    return boxes, cents


def _candidates(
    dboxes: np.ndarray, dcents: np.ndarray, tboxes: np.ndarray, tcents: np.ndarray, tindex: np.ndarray
) -> list[tuple[tuple, int, int]]:
    """Candidate pairs as (sort key, det index, truth index); truth rows restricted to ``tindex``."""
    out: list[tuple[tuple, int, int]] = []
    if len(dboxes) == 0 or len(tindex) == 0:
        return out
    darea = np.clip(dboxes[:, 2] - dboxes[:, 0], 0, None) * np.clip(dboxes[:, 3] - dboxes[:, 1], 0, None)
    for start in range(0, len(tindex), _CHUNK):
        ti = tindex[start : start + _CHUNK]
        tb = tboxes[ti][:, None, :]  # (T, 1, 4)
        tc = tcents[ti][:, None, :]
        db = dboxes[None, :, :]  # (1, D, 4)
        dc = dcents[None, :, :]
        ih = np.clip(np.minimum(tb[..., 2], db[..., 2]) - np.maximum(tb[..., 0], db[..., 0]), 0, None)
        iw = np.clip(np.minimum(tb[..., 3], db[..., 3]) - np.maximum(tb[..., 1], db[..., 1]), 0, None)
        inter = ih * iw
        tarea = np.clip(tb[..., 2] - tb[..., 0], 0, None) * np.clip(tb[..., 3] - tb[..., 1], 0, None)
        union = tarea + darea[None, :] - inter
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
        inside = (
            (dc[..., 0] >= tb[..., 0])
            & (dc[..., 0] < tb[..., 2])
            & (dc[..., 1] >= tb[..., 1])
            & (dc[..., 1] < tb[..., 3])
        )
        by_iou = iou >= IOU_MIN - IOU_TOL
        ok = by_iou | inside
        if not ok.any():
            continue
        dist = np.hypot(dc[..., 0] - tc[..., 0], dc[..., 1] - tc[..., 1])
        rows, cols = np.nonzero(ok)
        for r, d in zip(rows.tolist(), cols.tolist()):
            t = int(ti[r])
            v, dd = float(iou[r, d]), float(dist[r, d])
            key = (0, -v, dd, d, t) if by_iou[r, d] else (1, dd, -v, d, t)
            out.append((key, d, t))
    return out


def match(detections: list[Ship], truth: list[Ship], difficult_last: bool = True) -> list[tuple[int, int]]:
    """One-to-one greedy matches ``(detection index, truth index)``, sorted by detection index.

    See the module docstring for the rule and the order. With ``difficult_last`` (default)
    difficult truth ships are matched only after all the others, from the detections left.
    """
    dboxes, dcents = _arrays(list(detections))
    tboxes, tcents = _arrays(list(truth))
    diff = np.array([bool(s.difficult) for s in truth], dtype=bool)
    if difficult_last:
        passes = [np.flatnonzero(~diff), np.flatnonzero(diff)]
    else:
        passes = [np.arange(len(truth))]
    used_d: set[int] = set()
    used_t: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for tindex in passes:
        cands = _candidates(dboxes, dcents, tboxes, tcents, tindex)
        cands.sort(key=lambda c: c[0])
        for _, d, t in cands:
            if d in used_d or t in used_t:
                continue
            used_d.add(d)
            used_t.add(t)
            pairs.append((d, t))
    pairs.sort()
    return pairs


def _ratio(num: float, den: float, empty: float) -> float:
    """num / den, or ``empty`` when den == 0 (the documented 0/0 convention)."""
    return float(num) / float(den) if den > 0 else float(empty)


def _object_ratios(c: dict) -> dict:
    return {
        "pd": _ratio(c["n_hit"], c["n_truth"], 1.0),
        "precision": _ratio(c["n_hit"], c["n_detections"], 1.0),
        "fom": _ratio(c["n_hit"], c["n_false"] + c["n_truth"], 1.0),
        "f1": _ratio(2 * c["n_hit"], c["n_detections"] + c["n_truth"], 1.0),
    }


def _pixel_ratios(c: dict) -> dict:
    return {
        "tpr": _ratio(c["px_tp"], c["px_truth"], 1.0),
        "fpr": _ratio(c["px_fp"], c["px_clutter"], 0.0),
    }


def pixel_counts(det_mask: Any, truth_mask: Any) -> dict:
    """``px_truth``, ``px_clutter``, ``px_tp``, ``px_fp`` of two same-shape 2-D masks."""
    d = np.asarray(det_mask) != 0
    t = np.asarray(truth_mask) != 0
    if d.ndim != 2 or t.ndim != 2 or d.shape != t.shape:
        raise InputError(f"detection mask shape {d.shape} differs from truth mask shape {t.shape}")
    n_t = int(t.sum())
    return {
        "px_truth": n_t,
        "px_clutter": int(t.size - n_t),
        "px_tp": int(np.count_nonzero(d & t)),
        "px_fp": int(np.count_nonzero(d & ~t)),
    }


def flagged(ship: Ship) -> bool:
    """Whether a detection is flagged as an azimuth ambiguity (``ambiguity_of`` set:
    docs/algorithms/ambiguity.md)."""
    return ship.properties.get("ambiguity_of") is not None


def score(
    detections: list[Ship],
    truth: list[Ship],
    det_mask: Any = None,
    truth_mask: Any = None,
    ignore_flagged: bool = False,
) -> dict:
    """Object scores (and pixel ``tpr``/``fpr`` when both masks are given); see module docstring.

    ``ignore_flagged``: a detection flagged as an azimuth ambiguity that matches no truth ship
    is left out like one on a difficult ship (neither a hit nor a false alarm, not in
    ``n_detections``), counted in ``n_flagged_ignored``; a flagged detection that matches a
    ship stays a hit (the flag was wrong, the ship was found)."""
    detections, truth = list(detections), list(truth)
    pairs = match(detections, truth)
    n_ignored = sum(1 for _, t in pairs if truth[t].difficult)
    n_hit = len(pairs) - n_ignored
    n_difficult = sum(1 for s in truth if s.difficult)
    n_truth = len(truth) - n_difficult
    n_flagged = 0
    if ignore_flagged:
        matched = {d for d, _ in pairs}
        n_flagged = sum(1 for i, d in enumerate(detections) if i not in matched and flagged(d))
    n_det = len(detections) - n_ignored - n_flagged
    counts = {
        "n_truth": n_truth,
        "n_detections": n_det,
        "n_hit": n_hit,
        "n_false": n_det - n_hit,
        "n_missed": n_truth - n_hit,
        "n_difficult": n_difficult,
        "n_ignored": n_ignored,
    }
    if ignore_flagged:
        counts["n_flagged_ignored"] = n_flagged
    out: dict[str, Any] = dict(counts)
    out.update(_object_ratios(counts))
    if det_mask is not None and truth_mask is not None:
        px = pixel_counts(det_mask, truth_mask)
        out.update(px)
        out.update(_pixel_ratios(px))
    return out


def aggregate(per_image: Iterable[dict]) -> dict:
    """Micro-average: sum the counts over images and recompute the ratios.

    Pixel scores are aggregated over the images that carry pixel counts
    (``n_images_pixel`` says how many) and appear only when at least one does.
    """
    per_image = list(per_image)
    tot: dict[str, Any] = {k: int(sum(int(s.get(k, 0)) for s in per_image)) for k in OBJECT_COUNTS}
    if any("n_flagged_ignored" in s for s in per_image):
        tot["n_flagged_ignored"] = int(sum(int(s.get("n_flagged_ignored", 0)) for s in per_image))
    out: dict[str, Any] = {"n_images": len(per_image)}
    out.update(tot)
    out.update(_object_ratios(tot))
    px_imgs = [s for s in per_image if all(k in s for k in PIXEL_COUNTS)]
    if px_imgs:
        px = {k: int(sum(int(s[k]) for s in px_imgs)) for k in PIXEL_COUNTS}
        out["n_images_pixel"] = len(px_imgs)
        out.update(px)
        out.update(_pixel_ratios(px))
    return out


def evaluate(
    detections_path: str | os.PathLike,
    truth_path: str | os.PathLike,
    mask_path: str | os.PathLike | None = None,
    ignore_flagged: bool = False,
) -> dict:
    """Back-end of ``sarship evaluate DETECTIONS.geojson --truth TRUTH``.

    ``TRUTH``: a truth GeoJSON (docs/interfaces/files.md), a VOC xml file, a folder of VOC xml, or a mask image.
    For a folder, the xml whose stem is the detections' scene name is used (the scene is
    read from the detections file's ``scene`` member or the ``run.json`` beside it, see
    :func:`sarship.pipeline.products.truth.detections_scene`); when the detections name no scene the folder
    must hold exactly one xml. Otherwise: :class:`InputError`.

    Pixel scores: only for a mask truth, with the detection mask ``mask_path``, by default
    the ``mask.zarr`` beside the detections when it exists (a Zarr array, or a group with a
    2-D ``mask`` array; non-zero = detected). Its shape must equal the truth mask's.
    A ``mask_path`` given with a non-mask truth is not used (there is no truth mask).
    ``ignore_flagged``: see :func:`score`.
    """
    dpath, tpath = Path(detections_path), Path(truth_path)
    dets = load_detections(dpath)
    kind = truth_kind(tpath)
    scene = detections_scene(dpath) if kind == "voc-folder" else None
    ships, tmask = load_ships(tpath, scene=scene)
    dmask = None
    if tmask is not None:
        mp = Path(mask_path) if mask_path is not None else dpath.parent / "mask.zarr"
        if mask_path is not None or mp.exists():
            dmask = read_mask(mp)
            if dmask.shape != tmask.shape:
                raise InputError(
                    f"'{mp}': detection mask shape {dmask.shape} differs from truth mask '{tpath}' shape {tmask.shape}"
                )
    out = score(dets, ships, det_mask=dmask, truth_mask=tmask, ignore_flagged=ignore_flagged)
    out["detections"] = str(dpath)
    out["truth"] = str(tpath)
    out["truth_format"] = "voc" if kind == "voc-folder" else kind
    if scene is not None:
        out["scene"] = scene
    if dmask is not None:
        out["mask"] = str(mp)
    return out


def _fmt(v: float) -> str:
    return f"{v:.4f}" if v >= 1e-3 or v == 0 else f"{v:.3e}"


def format_scores(scores: dict) -> str:
    """A human-readable block of text for the CLI."""
    s = scores
    lines = []
    head = []
    if "n_images" in s:
        head.append(f"{s['n_images']} images")
    if s.get("scene"):
        head.append(f"scene {s['scene']}")
    if s.get("truth"):
        head.append(f"truth {s['truth']} ({s.get('truth_format', '?')})")
    if head:
        lines.append("; ".join(head))
    lines.append(
        f"objects: {s['n_truth']} truth ships, {s['n_detections']} detections"
        + (
            f" ({s['n_difficult']} difficult ships, {s['n_ignored']} detections on them ignored)"
            if s.get("n_difficult")
            else ""
        )
        + (
            f" ({s['n_flagged_ignored']} flagged ambiguities matching no ship ignored)"
            if "n_flagged_ignored" in s
            else ""
        )
    )
    lines.append(f"  hits {s['n_hit']}   false alarms {s['n_false']}   missed {s['n_missed']}")
    lines.append(
        f"  Pd (recall) {_fmt(s['pd'])}   precision {_fmt(s['precision'])}   FoM {_fmt(s['fom'])}   F1 {_fmt(s['f1'])}"
    )
    if "tpr" in s:
        lines.append(
            f"pixels: TPR {_fmt(s['tpr'])}   FPR {_fmt(s['fpr'])}   "
            f"({s['px_tp']} of {s['px_truth']} ship px detected, {s['px_fp']} of {s['px_clutter']} clutter px)"
        )
    return "\n".join(lines)
