"""Discrimination of what is not a ship from the detections' own properties: lines, smear, land edges.

A long straight bright line (a bridge, breakwater, quay, cable, a range or azimuth line) that
the detector marks in pieces gives components each short and thick enough to pass the shape
test (``max_elongation``) on its own. :func:`discard_lines` joins collinear components into one
line object *before* that test and applies it to the object, so the line's pieces are dropped
together:

- each component is a segment from its moments (:func:`segments`): centre, principal axis,
  length ``l = sqrt(12 lambda_1)`` and width ``w = sqrt(12 lambda_2)``, in pixels, as
  :func:`sarship.pipeline.targets.components.shape_from_moments` measures them;
- two components are joined (:func:`collinear_pairs`) when their axes differ by at most
  ``angle_deg`` (a near-round piece, elongation < :data:`ROUND`, takes its partner's axis), the
  one's centre lies on the other's axis line within ``(w_i + w_j) / 2 + 1`` pixels, and the
  gap between their facing ends along the common axis is at most ``gap_px`` pixels (and they
  overlap along it by at most a quarter of the shorter one: pieces side by side, as parallel
  ships in a row or a convoy, are not a line);
- joined components form groups (connected components of the pair graph); a group of two or
  more whose combined moments (its pixels as one object) fail ``max_elongation`` or
  ``max_length_m`` is a line: its members are dropped, reason ``"smear"`` when the line runs
  along azimuth (image rows, within ``angle_deg``: azimuth smear and ambiguity streaks) and
  ``"line"`` otherwise; a member whose peak is at least ``dominant_db`` above the median peak
  of the rest is the bright ship the streak or wake belongs to and is kept (it still meets the
  size and shape rule on its own).

:func:`near_land` marks detections with land within ``gap_px`` pixels of their bounding box
(the ``land_gap_px`` setting; only where a land mask is in use).

Pure functions of moment records (:data:`sarship.pipeline.targets.components.MOMENT_DTYPE`);
docs/algorithms/discrimination.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sarship.pipeline.targets.ship_features import elongations, lengths_m

#: Elongation (length / width) under which a component's axis is not defined well enough to
#: compare: such a piece takes its partner's axis.
ROUND = 1.5


def segments(records: np.ndarray) -> dict[str, np.ndarray]:
    """Each component as a segment, in pixels: ``centre`` (n, 2) (row, col), unit ``axis``
    (n, 2) (row, col) of its principal direction, ``half`` its half-length, ``width`` and
    ``elongation`` (length / width), from the moments (the pixel's own 1/12 variance added)."""
    n = np.maximum(records["n"].astype(np.float64), 1.0)
    mr, mc = records["sr"] / n, records["sc"] / n
    vrr = np.maximum(records["srr"] / n - mr * mr, 0.0) + 1.0 / 12.0
    vcc = np.maximum(records["scc"] / n - mc * mc, 0.0) + 1.0 / 12.0
    vrc = records["src"] / n - mr * mc
    half_tr = (vrr + vcc) / 2.0
    disc = np.sqrt(((vrr - vcc) / 2.0) ** 2 + vrc * vrc)
    l1, l2 = half_tr + disc, np.maximum(half_tr - disc, 1e-12)
    theta = 0.5 * np.arctan2(2.0 * vrc, vrr - vcc)
    return {
        "centre": np.stack([mr + 0.5, mc + 0.5], axis=1),
        "axis": np.stack([np.cos(theta), np.sin(theta)], axis=1),
        "half": np.sqrt(12.0 * l1) / 2.0,
        "width": np.sqrt(12.0 * l2),
        "elongation": np.sqrt(l1 / l2),
    }


def collinear_pairs(seg: dict[str, np.ndarray], gap_px: float, angle_deg: float) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, of collinear segments (:func:`segments`) whose facing ends are
    at most ``gap_px`` apart along their common axis (the rule in the module docstring).
    Candidates are found by a k-d tree on the segments' end points (so the cost grows with the
    number of close ends, not with the square of the number of detections)."""
    from scipy.spatial import cKDTree

    k = len(seg["half"])
    if k < 2:
        return np.zeros((0, 2), np.int64)
    c, u, h, w, el = seg["centre"], seg["axis"], seg["half"], seg["width"], seg["elongation"]
    ends = np.concatenate([c + h[:, None] * u, c - h[:, None] * u])
    # facing ends of a joinable pair are at most gap + lateral offset apart; the offset allowed
    # grows with the widths, capped so that one wide blob (land, a harbour) does not make every
    # end a candidate of every other: pieces more than gap_px + 3 px off each other's axis are
    # not searched (a line's pieces are thin)
    radius = float(gap_px) + min(float(w.max()), float(gap_px) + 2.0) + 1.0
    cand = cKDTree(ends).query_pairs(radius, output_type="ndarray")
    if len(cand) == 0:
        return np.zeros((0, 2), np.int64)
    i, j = cand[:, 0] % k, cand[:, 1] % k
    rnd = el < ROUND
    keep = (i != j) & ~(rnd[i] & rnd[j])  # two near-round pieces are never joined
    i, j = np.minimum(i[keep], j[keep]), np.maximum(i[keep], j[keep])
    if len(i) == 0:
        return np.zeros((0, 2), np.int64)
    key = np.unique(i.astype(np.int64) * k + j)
    i, j = key // k, key % k
    pairs = np.stack([i, j], axis=1)
    ui, uj = u[i], u[j]
    round_i, round_j = rnd[i], rnd[j]
    dot = np.sum(ui * uj, axis=1)
    cross = np.abs(ui[:, 0] * uj[:, 1] - ui[:, 1] * uj[:, 0])
    aligned = cross <= np.sin(np.radians(angle_deg))
    # the common axis: the mean of the two (signs matched); a round piece takes its partner's
    ax = ui + np.sign(np.where(dot == 0, 1.0, dot))[:, None] * uj
    ax = np.where(round_i[:, None], uj, np.where(round_j[:, None], ui, ax))
    ax /= np.maximum(np.linalg.norm(ax, axis=1), 1e-12)[:, None]
    d = c[j] - c[i]
    along = np.abs(np.sum(d * ax, axis=1))
    lateral = np.abs(d[:, 0] * ax[:, 1] - d[:, 1] * ax[:, 0])
    gap = along - h[i] - h[j]
    ok = (
        (aligned | round_i | round_j)
        & (lateral <= (w[i] + w[j]) / 2.0 + 1.0)
        & (gap <= gap_px)
        & (gap >= -0.5 * np.minimum(h[i], h[j]))
    )
    return pairs[ok]


def _groups(k: int, pairs: np.ndarray) -> np.ndarray:
    """Group label of each of ``k`` nodes joined by ``pairs`` (connected components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(k, k))
    return connected_components(g, directed=False)[1]


def group_moments(records: np.ndarray, labels: np.ndarray, n_groups: int) -> np.ndarray:
    """The additive moments of each group of records (its pixels as one object): ``n`` and the
    position sums; the other fields are zero."""
    out = np.zeros(n_groups, records.dtype)
    for f in ("n", "sr", "sc", "srr", "scc", "src", "sumv"):
        out[f] = np.bincount(labels, records[f].astype(np.float64), n_groups).astype(out.dtype[f])
    return out


def discard_lines(
    records: np.ndarray,
    gap_px: int | None,
    angle_deg: float,
    dominant_db: float | None,
    max_elongation: float | None,
    max_length_m: float | None,
    spacing: tuple[float, float] | None,
) -> np.ndarray:
    """Why each record is not a ship by the line rule: ``""`` (kept), ``"line"`` or ``"smear"``
    (the rule in the module docstring). ``gap_px`` None, or neither ``max_elongation`` nor
    (with ``spacing``) ``max_length_m`` set: nothing is dropped.

    Parameters
    ----------
    records : MOMENT_DTYPE array
        Whole components (after the cross-tile merge).
    gap_px, angle_deg, dominant_db
        The ``line_gap_px``, ``line_angle_deg`` and ``line_dominant_db`` settings.
    max_elongation, max_length_m, spacing
        The shape and length test applied to each joined object (as
        :func:`sarship.pipeline.targets.ship_features.keep_mask` applies it to one component).

    Returns
    -------
    numpy.ndarray
        One reason string per record (dtype ``<U5``).
    """
    k = len(records)
    reason = np.full(k, "", "<U5")
    use_len = spacing is not None and max_length_m is not None
    if gap_px is None or k < 2 or (max_elongation is None and not use_len):
        return reason
    seg = segments(records)
    pairs = collinear_pairs(seg, gap_px, angle_deg)
    if len(pairs) == 0:
        return reason
    lab = _groups(k, pairs)
    ng = int(lab.max()) + 1
    size = np.bincount(lab, minlength=ng)
    gm = group_moments(records, lab, ng)
    line = size >= 2
    bad = np.zeros(ng, bool)
    if max_elongation is not None:
        bad |= elongations(gm, spacing) > max_elongation
    if use_len:
        bad |= lengths_m(gm, spacing) > max_length_m
    line &= bad
    gseg = segments(gm)
    along_azimuth = np.abs(gseg["axis"][:, 0]) >= np.cos(np.radians(angle_deg))
    peak_db = 10.0 * np.log10(np.maximum(records["peak"].astype(np.float64), 1e-30))
    in_line = line[lab]
    reason[in_line & along_azimuth[lab]] = "smear"
    reason[in_line & ~along_azimuth[lab]] = "line"
    if dominant_db is not None:  # the bright ship of its streak or wake stays
        idx = np.flatnonzero(in_line)
        idx = idx[np.argsort(lab[idx], kind="stable")]
        starts = np.flatnonzero(np.r_[True, lab[idx][1:] != lab[idx][:-1]])
        for members in np.split(idx, starts[1:]):
            p = peak_db[members]
            for t in range(len(members)):
                if p[t] >= np.median(np.delete(p, t)) + dominant_db:
                    reason[members[t]] = ""
    return reason


def near_land(
    records: np.ndarray, read_land: Callable[[int, int, int, int], np.ndarray], shape: tuple[int, int], gap_px: int
) -> np.ndarray:
    """Which records have a land pixel within ``gap_px`` pixels of their bounding box (0: in or
    touching it; Chebyshev distance), ``read_land(ra, rb, ca, cb)`` reading the land mask."""
    H, W = shape
    out = np.zeros(len(records), bool)
    d = int(gap_px) + 1
    for k, rec in enumerate(records):
        ra, rb = max(int(rec["r0"]) - d, 0), min(int(rec["r1"]) + d, H)
        ca, cb = max(int(rec["c0"]) - d, 0), min(int(rec["c1"]) + d, W)
        out[k] = bool(np.any(np.asarray(read_land(ra, rb, ca, cb))))
    return out


__all__ = ["ROUND", "segments", "collinear_pairs", "group_moments", "discard_lines", "near_land"]
