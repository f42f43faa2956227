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

AIS scores (:func:`ais_counts`; docs/ais.md)
    When the truth carries MMSIs (a ship's ``mmsi``, null for a ship that never reports, and
    ``dark``, by default ``mmsi`` null: the simulator's truth) and the detections carry ``ais``
    (``sarship detect --ais``, ``sarship match``), over the *hits* (detections matched as above
    to a ship that is not difficult): ``ais_precision`` = hits matched to their ship's own MMSI
    / hits matched to an MMSI; ``ais_recall`` = hits on reporting ships matched to their own
    MMSI / hits on reporting ships (not dark, with an MMSI); ``dark_precision`` = hits called
    dark (``dark`` true) on dark ships / hits called dark; ``dark_recall`` = hits on dark ships
    called dark / hits on dark ships. A detection whose ``dark`` is null (the AIS did not cover
    the scene) is not called dark. Unlike the object scores, a 0/0 ratio is ``None`` (JSON null):
    nothing was there to score. The counts behind them are kept for aggregation.
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
#: AIS counts (:func:`ais_counts`), summed by :func:`aggregate` over the images that carry them.
AIS_COUNTS = (
    "n_ais_matched",
    "n_ais_correct",
    "n_ais_reporting",
    "n_ais_found",
    "n_dark_called",
    "n_dark_correct",
    "n_dark_ships",
    "n_dark_found",
)

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


def _ais_ratios(c: dict) -> dict:
    def ratio(num: int, den: int) -> float | None:
        return float(num) / float(den) if den > 0 else None

    return {
        "ais_precision": ratio(c["n_ais_correct"], c["n_ais_matched"]),
        "ais_recall": ratio(c["n_ais_found"], c["n_ais_reporting"]),
        "dark_precision": ratio(c["n_dark_correct"], c["n_dark_called"]),
        "dark_recall": ratio(c["n_dark_found"], c["n_dark_ships"]),
    }


def _mmsi(value: Any, where: str) -> int | None:
    """An MMSI as an int (a whole number or a string of digits), or None for null."""
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str) and value.strip().isdigit():
        return int(value)
    raise InputError(f"{where}: 'mmsi' must be a number or null, got {value!r:.40}")


def _flag(value: Any, where: str, name: str) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    raise InputError(f"{where}: '{name}' must be true, false or null, got {value!r:.40}")


def _truth_ais(ship: Ship, where: str) -> tuple[int | None, bool]:
    """``(mmsi, dark)`` of a truth ship; ``dark`` defaults to ``mmsi`` being null."""
    mmsi = _mmsi(ship.properties.get("mmsi"), where)
    dark = _flag(ship.properties.get("dark"), where, "dark")
    return mmsi, (mmsi is None) if dark is None else dark


def _detection_ais(det: Ship, where: str) -> tuple[int | None, bool]:
    """``(mmsi matched or None, called dark)`` of a detection."""
    rec = det.properties.get("ais")
    if rec is not None and not (isinstance(rec, dict) and rec.get("mmsi") is not None):
        raise InputError(f"{where}: 'ais' must be null or a record with an 'mmsi', got {rec!r:.60}")
    mmsi = None if rec is None else _mmsi(rec["mmsi"], where)
    return mmsi, _flag(det.properties.get("dark"), where, "dark") is True


def has_ais(detections: list[Ship], truth: list[Ship]) -> bool:
    """Whether AIS scores apply.

    Parameters
    ----------
    detections : list of Ship
        The detections (``properties`` as in ``detections.geojson``).
    truth : list of Ship
        The truth ships.

    Returns
    -------
    bool
        True when some truth ship has an ``mmsi`` property (null included) and some detection
        an ``ais`` property (null included).
    """
    return any("mmsi" in s.properties for s in truth) and any("ais" in d.properties for d in detections)


def ais_counts(detections: list[Ship], truth: list[Ship], pairs: list[tuple[int, int]]) -> dict:
    """The AIS counts of :data:`AIS_COUNTS` over the hits (module docstring, "AIS scores").

    Parameters
    ----------
    detections : list of Ship
        Detections with ``ais`` (null or ``{mmsi, ...}``) and ``dark`` (true, false or null)
        properties; a detection without them is unmatched and not called dark.
    truth : list of Ship
        Truth ships with ``mmsi`` (a number or null) and optionally ``dark`` (default:
        ``mmsi`` null).
    pairs : list of (int, int)
        ``(detection index, truth index)`` from :func:`match`; pairs on difficult ships are
        left out (they are not hits).

    Returns
    -------
    dict
        ``n_ais_matched`` (hits matched to an MMSI), ``n_ais_correct`` (of those, to their
        ship's own), ``n_ais_reporting`` (hits on reporting ships), ``n_ais_found`` (of those,
        matched to their own MMSI), ``n_dark_called`` (hits called dark), ``n_dark_correct``
        (of those, on dark ships), ``n_dark_ships`` (hits on dark ships), ``n_dark_found`` (of
        those, called dark).

    Raises
    ------
    InputError
        An ``mmsi`` that is no number, an ``ais`` that is no record with an ``mmsi``, a
        ``dark`` that is not a boolean or null (one line naming the ship or detection).
    """
    ships = [_truth_ais(s, f"truth ship {k + 1}") for k, s in enumerate(truth)]
    dets = [_detection_ais(d, f"detection {k + 1}") for k, d in enumerate(detections)]
    c = dict.fromkeys(AIS_COUNTS, 0)
    for d, t in pairs:
        if truth[t].difficult:
            continue
        (t_mmsi, t_dark), (d_mmsi, d_dark) = ships[t], dets[d]
        own = d_mmsi is not None and d_mmsi == t_mmsi
        if d_mmsi is not None:
            c["n_ais_matched"] += 1
            c["n_ais_correct"] += own
        if not t_dark and t_mmsi is not None:
            c["n_ais_reporting"] += 1
            c["n_ais_found"] += own
        if d_dark:
            c["n_dark_called"] += 1
            c["n_dark_correct"] += t_dark
        if t_dark:
            c["n_dark_ships"] += 1
            c["n_dark_found"] += d_dark
    return c


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
    ship stays a hit (the flag was wrong, the ship was found). AIS scores and their counts
    when :func:`has_ais` (:func:`ais_counts`)."""
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
    if has_ais(detections, truth):
        ais = ais_counts(detections, truth, pairs)
        out.update(ais)
        out.update(_ais_ratios(ais))
    if det_mask is not None and truth_mask is not None:
        px = pixel_counts(det_mask, truth_mask)
        out.update(px)
        out.update(_pixel_ratios(px))
    return out


def aggregate(per_image: Iterable[dict]) -> dict:
    """Micro-average: sum the counts over images and recompute the ratios.

    Pixel scores are aggregated over the images that carry pixel counts
    (``n_images_pixel`` says how many) and appear only when at least one does; AIS scores
    likewise (``n_images_ais``).
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
    ais_imgs = [s for s in per_image if all(k in s for k in AIS_COUNTS)]
    if ais_imgs:
        ais = {k: int(sum(int(s[k]) for s in ais_imgs)) for k in AIS_COUNTS}
        out["n_images_ais"] = len(ais_imgs)
        out.update(ais)
        out.update(_ais_ratios(ais))
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
    ``ignore_flagged``: see :func:`score`. AIS scores: when the truth carries MMSIs and the
    detections ``ais`` (:func:`has_ais`).
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


def _fmt(v: float | None) -> str:
    if v is None:
        return "n/a"
    return f"{v:.4f}" if v >= 1e-3 or v == 0 else f"{v:.3e}"


def _ais_lines(s: dict) -> list[str]:
    return [
        f"ais: precision {_fmt(s['ais_precision'])} ({s['n_ais_correct']} of {s['n_ais_matched']} matched hits: "
        f"own MMSI)   recall {_fmt(s['ais_recall'])} ({s['n_ais_found']} of {s['n_ais_reporting']} detected "
        "reporting ships: own MMSI)",
        f"dark: precision {_fmt(s['dark_precision'])} ({s['n_dark_correct']} of {s['n_dark_called']} hits called "
        f"dark: dark ships)   recall {_fmt(s['dark_recall'])} ({s['n_dark_found']} of {s['n_dark_ships']} "
        "detected dark ships: called dark)",
    ]


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
    if "ais_precision" in s:
        lines += _ais_lines(s)
    return "\n".join(lines)
