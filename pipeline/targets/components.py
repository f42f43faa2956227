"""Detections from a tiled mask: connected components across tiles, moments, properties.

Each tile labels its own part of the mask (8-connectivity, on its set pixels only)
and reduces every component to additive moments (pixel count, sums of row, col, row^2,
col^2, row*col, of the input values, bounding box, peak value and peak statistic). Labels
along the four tile edges are kept; connected components of the graph that links
neighbouring tiles' edge labels (:func:`min_labels`) join the parts of components that
straddle tile borders, and their moments add up. The
result equals labelling the whole-scene mask at once, while the client only ever holds a
table of components, never the mask.

``merge_px``: fragments separated by a gap of at most ``merge_px`` pixels are one ship
(single-look ships break up into bright scatterers). Grouping is done on the mask dilated
by a square of half-side ``r = ceil(merge_px / 2)`` (two pixels at Chebyshev distance d are
joined when d <= 2r + 1, i.e. a gap of d - 1 <= merge_px pixels); moments use the
undilated pixels only. Each tile therefore needs its mask on a margin of ``r`` pixels
around its core.

Ship geometry from second moments: the covariance of a component's pixel positions plus
the within-pixel variance (1/12 of a pixel squared along each axis) is that of a uniform
rectangle of length l and width w with variances l^2/12 and w^2/12, so
l = sqrt(12 * lambda_1) and w = sqrt(12 * lambda_2) with lambda the covariance eigenvalues
(in pixels, or in metres with the pixel spacing). Heading is the principal axis, measured
clockwise from image "up" (decreasing row), in [0, 180).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

#: Structured dtype of a component's additive moments.
MOMENT_DTYPE = np.dtype(
    [
        ("n", np.int64),
        ("sr", np.float64),
        ("sc", np.float64),
        ("srr", np.float64),
        ("scc", np.float64),
        ("src", np.float64),
        ("r0", np.int64),
        ("c0", np.int64),
        ("r1", np.int64),
        ("c1", np.int64),
        ("peak", np.float64),
        ("sumv", np.float64),
        ("score", np.float64),
        ("peak_r", np.int64),
        ("peak_c", np.int64),
    ]
)


def merge_radius(merge_px: int) -> int:
    """Half-side of the dilation that joins fragments with gaps of <= merge_px pixels."""
    return int(math.ceil(merge_px / 2.0))


@dataclass
class TileComponents:
    """What one tile contributes: its edge labels and the moments of its components."""

    tile: tuple[int, int]
    shape: tuple[int, int]
    moments: np.ndarray  # MOMENT_DTYPE of edge components, index = edge label - 1
    edges: dict[str, np.ndarray] = field(default_factory=dict)  # top/bottom/left/right label lines
    complete: np.ndarray | None = None  # MOMENT_DTYPE of components inside the tile (final)
    #: the tile's own component ids (:func:`points_components`' labels - 1) of ``moments`` and
    #: ``complete``, row for row: what the tile wrote in its label store, so the kept
    #: detections' pixels can be picked tile by tile (:func:`merge_tiles` ``members``)
    ids: np.ndarray | None = None
    complete_ids: np.ndarray | None = None

    def keep_complete(self, keep: np.ndarray) -> None:
        """Keep only the complete components where ``keep`` (a boolean array) is set."""
        self.complete = self.complete[keep]
        if self.complete_ids is not None:
            self.complete_ids = self.complete_ids[keep]


@njit(nogil=True, cache=True)
def _nonzero(mask):
    """Row-major coordinates of the set pixels (one pass to count, one to fill)."""
    H, W = mask.shape
    n = 0
    for i in range(H):
        for j in range(W):
            if mask[i, j]:
                n += 1
    rr = np.empty(n, np.int64)
    cc = np.empty(n, np.int64)
    k = 0
    for i in range(H):
        for j in range(W):
            if mask[i, j]:
                rr[k] = i
                cc[k] = j
                k += 1
    return rr, cc


def mask_points(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-major (row, col) coordinates (int64) of the set pixels of a 2-D mask."""
    return _nonzero(np.ascontiguousarray(mask))


@njit(nogil=True, cache=True)
def _find(parent, a):
    root = a
    while parent[root] != root:
        root = parent[root]
    while parent[a] != root:
        nxt = parent[a]
        parent[a] = root
        a = nxt
    return root


@njit(nogil=True, cache=True)
def _union(parent, a, b):
    """Join the sets of a and b (the smaller root index becomes the root)."""
    ra, rb = _find(parent, a), _find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@njit(nogil=True, cache=True)
def _label_points(rr, cc, n_rows, d):
    """Components of points (row-major sorted) joined at Chebyshev distance <= d.

    Returns component ids numbered 0.. in order of each component's first point.
    """
    n = len(rr)
    parent = np.arange(n)
    row_start = np.zeros(n_rows + 1, np.int64)
    for k in range(n):
        row_start[rr[k] + 1] += 1
    for i in range(n_rows):
        row_start[i + 1] += row_start[i]
    for k in range(n):
        r, c = rr[k], cc[k]
        for q in range(max(r - d, 0), r + 1):
            a, b = row_start[q], row_start[q + 1]
            if q == r:
                b = k
            # first point of row q with col >= c - d (binary search; cols sorted within a row)
            lo, hi = a, b
            while lo < hi:
                mid = (lo + hi) // 2
                if cc[mid] < c - d:
                    lo = mid + 1
                else:
                    hi = mid
            j = lo
            while j < b and cc[j] <= c + d:
                _union(parent, k, j)
                j += 1
    comp = np.empty(n, np.int64)
    ids = -np.ones(n, np.int64)
    m = 0
    for k in range(n):
        root = _find(parent, k)
        if ids[root] < 0:
            ids[root] = m
            m += 1
        comp[k] = ids[root]
    return comp, m


@njit(nogil=True, cache=True)
def _edge_lines(rr, cc, comp, h, w, r):
    """Labels (component id + 1) of the dilated mask along the core's four edges.

    ``rr, cc`` are point coordinates in the extended frame (core starts at ``r``).
    """
    top = np.zeros(w, np.int64)
    bottom = np.zeros(w, np.int64)
    left = np.zeros(h, np.int64)
    right = np.zeros(h, np.int64)
    for k in range(len(rr)):
        pr, pc = rr[k] - r, cc[k] - r  # core coordinates (may be in the margin)
        lab = comp[k] + 1
        c0, c1 = max(pc - r, 0), min(pc + r + 1, w)
        r0, r1 = max(pr - r, 0), min(pr + r + 1, h)
        if c0 < c1 and r0 < r1:
            if r0 == 0:
                for c in range(c0, c1):
                    top[c] = lab
            if r1 == h:
                for c in range(c0, c1):
                    bottom[c] = lab
            if c0 == 0:
                for q in range(r0, r1):
                    left[q] = lab
            if c1 == w:
                for q in range(r0, r1):
                    right[q] = lab
    return top, bottom, left, right


def point_labels(rr: np.ndarray, cc: np.ndarray, core: tuple[int, int], r: int) -> np.ndarray:
    """Component id (0..) of each set pixel of a tile's mask, as :func:`points_components`
    labels them: ``rr``, ``cc`` row-major coordinates in the ``(h + 2r, w + 2r)`` frame, two
    pixels joined at Chebyshev distance ``<= 2r + 1``; ids numbered in order of each
    component's first pixel. The ids of :class:`TileComponents` ``ids`` / ``complete_ids``."""
    comp, _n = _label_points(np.asarray(rr, np.int64), np.asarray(cc, np.int64), core[0] + 2 * r, 2 * r + 1)
    return comp


def tile_components(
    mask_ext: np.ndarray,
    values: np.ndarray,
    stat: np.ndarray,
    r: int,
    origin: tuple[int, int],
    tile: tuple[int, int],
) -> TileComponents:
    """Label one tile's mask and reduce its components to moments.

    Equivalent to labelling (8-connectivity) the mask dilated by a ``(2r+1)`` square,
    restricted to the core, but computed on the set pixels only (O(number of detected
    pixels), not O(tile area)): two set pixels belong together when their Chebyshev
    distance is at most ``2r + 1`` (their dilation squares touch), and a square clipped to
    the core keeps every such contact.

    Parameters
    ----------
    mask_ext : (h + 2r, w + 2r) bool
        The tile's mask with a margin of ``r`` pixels each side (False outside the scene).
    values, stat : (h, w)
        Input values and detector statistic of the core.
    r : merge radius (:func:`merge_radius`).
    origin : global (row, col) of the core's first pixel.
    """
    h, w = values.shape
    rr, cc = mask_points(mask_ext)
    vr, vc = np.clip(rr - r, 0, max(h - 1, 0)), np.clip(cc - r, 0, max(w - 1, 0))  # margin points: unused
    return points_components(rr, cc, values[vr, vc], stat[vr, vc], (h, w), r, origin, tile)


def points_components(
    rr: np.ndarray,
    cc: np.ndarray,
    values: np.ndarray,
    stat: np.ndarray,
    core: tuple[int, int],
    r: int,
    origin: tuple[int, int],
    tile: tuple[int, int],
    comp: np.ndarray | None = None,
) -> TileComponents:
    """:func:`tile_components` from the set pixels of the tile's mask: ``rr``, ``cc`` their
    coordinates in the ``(h + 2r, w + 2r)`` frame of ``mask_ext``, in row-major order, and
    ``values``, ``stat`` the input value and detector statistic at each of them (those of
    points in the margin are not used). A GPU tile hands over only these (a few bytes a
    detection) instead of its whole mask and statistic (workers/tasks.py). ``comp``: the
    points' component ids when already labelled (:func:`point_labels`)."""
    h, w = core
    rr = np.asarray(rr, np.int64)
    cc = np.asarray(cc, np.int64)
    if comp is None:
        comp = point_labels(rr, cc, core, r)
    n = int(comp.max()) + 1 if len(comp) else 0
    top, bottom, left, right = _edge_lines(rr, cc, comp, h, w, r)
    mom = np.zeros(n, MOMENT_DTYPE)
    mom["r0"] = np.iinfo(np.int64).max
    mom["c0"] = np.iinfo(np.int64).max
    mom["r1"] = np.iinfo(np.int64).min
    mom["c1"] = np.iinfo(np.int64).min
    mom["peak"] = -np.inf
    mom["score"] = -np.inf
    incore = (rr >= r) & (rr < r + h) & (cc >= r) & (cc < r + w)
    if n and incore.any():
        lab = comp[incore]
        cr, ccol = rr[incore] - r, cc[incore] - r
        v = np.asarray(values)[incore].astype(np.float64)
        sv = np.asarray(stat)[incore].astype(np.float64)
        grr = cr + origin[0]
        gcc = ccol + origin[1]
        gr = grr.astype(np.float64)
        gc = gcc.astype(np.float64)
        mom["n"] = np.bincount(lab, minlength=n)
        mom["sr"] = np.bincount(lab, gr, n)
        mom["sc"] = np.bincount(lab, gc, n)
        mom["srr"] = np.bincount(lab, gr * gr, n)
        mom["scc"] = np.bincount(lab, gc * gc, n)
        mom["src"] = np.bincount(lab, gr * gc, n)
        mom["sumv"] = np.bincount(lab, v, n)
        np.minimum.at(mom["r0"], lab, grr)
        np.minimum.at(mom["c0"], lab, gcc)
        np.maximum.at(mom["r1"], lab, grr + 1)
        np.maximum.at(mom["c1"], lab, gcc + 1)
        np.maximum.at(mom["score"], lab, sv)
        # peak value and its position (first in raster order among equal peaks)
        order = np.lexsort((-v, lab))
        first = np.ones(len(order), bool)
        first[1:] = lab[order][1:] != lab[order][:-1]
        sel = order[first]
        mom["peak"][lab[sel]] = v[sel]
        mom["peak_r"][lab[sel]] = grr[sel]
        mom["peak_c"][lab[sel]] = gcc[sel]
    edges = {"top": top, "bottom": bottom, "left": left, "right": right}
    touching = np.zeros(n, bool)
    for e in edges.values():
        ids = np.unique(e[e > 0]) - 1
        touching[ids] = True
    # compact: only components touching an edge need merging; relabel the edges 1..k
    remap = np.zeros(n + 1, np.int64)
    tid = np.flatnonzero(touching)
    remap[tid + 1] = np.arange(1, len(tid) + 1)
    edges = {k: remap[v] for k, v in edges.items()}
    inner = np.flatnonzero(~touching)
    inner = inner[mom["n"][inner] > 0]
    return TileComponents(
        tile=tile, shape=(h, w), moments=mom[touching], edges=edges, complete=mom[inner], ids=tid, complete_ids=inner
    )


def _pairs_line(a: np.ndarray, b: np.ndarray) -> set[tuple[int, int]]:
    """Label pairs of 8-adjacent pixels across a straight border (a and b face each other)."""
    out: set[tuple[int, int]] = set()
    n = len(a)
    for d in (-1, 0, 1):
        lo, hi = max(0, -d), min(n, n - d)
        if lo >= hi:
            continue
        aa = a[lo:hi]
        bb = b[lo + d : hi + d]
        ok = (aa > 0) & (bb > 0)
        if ok.any():
            out.update(zip(aa[ok].tolist(), bb[ok].tolist()))
    return out


def combine(moments: list[np.ndarray]) -> np.ndarray:
    """Add moment records of parts of one component."""
    m = np.concatenate(moments)
    out = np.zeros(1, MOMENT_DTYPE)
    for k in ("n", "sr", "sc", "srr", "scc", "src", "sumv"):
        out[k] = m[k].sum()
    valid = m["n"] > 0
    mv = m[valid]
    out["r0"], out["c0"] = mv["r0"].min(), mv["c0"].min()
    out["r1"], out["c1"] = mv["r1"].max(), mv["c1"].max()
    out["score"] = mv["score"].max()
    i = int(np.lexsort((mv["peak_c"], mv["peak_r"], -mv["peak"]))[0])
    out["peak"], out["peak_r"], out["peak_c"] = mv["peak"][i], mv["peak_r"][i], mv["peak_c"][i]
    return out


def _order(res: np.ndarray) -> np.ndarray:
    """Deterministic output order: top-left of the box, then the rest of the record."""
    return np.lexsort((res["peak_c"], res["peak_r"], res["n"], res["c1"], res["r1"], res["c0"], res["r0"]))


def min_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the graph on nodes ``0..n-1`` with edges ``(a[k], b[k])``:
    each node's label is the smallest node of its component.

    Vectorised label propagation with pointer jumping (hook every edge's larger label onto
    its smaller one, then shorten label chains until every label is a root; repeat until no
    edge joins two labels), so the client's merge needs NumPy only: no JIT compiler is
    loaded in the process that runs ``sarship detect`` (loading the union-find's compiled
    code cost 0.3 s of each command). Rounds: at most a few per doubling of a component's
    diameter."""
    lab = np.arange(n, dtype=np.int64)
    a = np.asarray(a, np.int64)
    b = np.asarray(b, np.int64)
    while a.size:
        la, lb = lab[a], lab[b]
        differ = la != lb
        if not differ.any():
            break
        la, lb = la[differ], lb[differ]
        a, b = a[differ], b[differ]
        lo, hi = np.minimum(la, lb), np.maximum(la, lb)
        np.minimum.at(lab, hi, lo)
        while True:
            nxt = lab[lab]
            if np.array_equal(nxt, lab):
                break
            lab = nxt
    return lab


def merge_tiles(tiles: dict[tuple[int, int], TileComponents], members: bool = False):
    """Join components across tile borders; returns one moment record per component.

    ``tiles`` maps grid index (i, j) to the tile's :class:`TileComponents`. Components
    inside a tile (``complete``) pass through; edge components are joined by :func:`min_labels`.

    ``members``: also return, for each tile, ``(ids, record)``: the tile's component ids
    (:class:`TileComponents` ``ids`` / ``complete_ids``) with a part in the scene and the index
    of the returned record each belongs to, so that the pixels of chosen records can be picked
    tile by tile from the tiles' label stores (workers/tasks.py ``run_tile_keep``).
    """
    keys = sorted(tiles)
    offset: dict[tuple[int, int], int] = {}
    total = 0
    for k in keys:
        offset[k] = total
        total += len(tiles[k].moments)
    ends_a: list[np.ndarray] = []
    ends_b: list[np.ndarray] = []

    def link(ka, kb, pairs):
        if pairs:
            ab = np.array(sorted(pairs), dtype=np.int64)
            ends_a.append(ab[:, 0] + offset[ka] - 1)
            ends_b.append(ab[:, 1] + offset[kb] - 1)

    for i, j in keys:
        t = tiles[(i, j)]
        right = tiles.get((i, j + 1))
        if right is not None:
            link((i, j), (i, j + 1), _pairs_line(t.edges["right"], right.edges["left"]))
        below = tiles.get((i + 1, j))
        if below is not None:
            link((i, j), (i + 1, j), _pairs_line(t.edges["bottom"], below.edges["top"]))
        diag = tiles.get((i + 1, j + 1))
        if diag is not None:
            a, b = t.edges["bottom"][-1], diag.edges["top"][0]
            if a > 0 and b > 0:
                link((i, j), (i + 1, j + 1), [(a, b)])
        anti = tiles.get((i + 1, j - 1))
        if anti is not None:
            a, b = t.edges["bottom"][0], anti.edges["top"][-1]
            if a > 0 and b > 0:
                link((i, j), (i + 1, j - 1), [(a, b)])
    complete = [tiles[k].complete for k in keys if tiles[k].complete is not None]
    out: list[np.ndarray] = []
    owner = np.full(total, -1, np.int64)  # record (before ordering) of each edge part
    if total:
        allm = np.concatenate([tiles[k].moments for k in keys])
        roots = min_labels(
            total,
            np.concatenate(ends_a) if ends_a else np.zeros(0, np.int64),
            np.concatenate(ends_b) if ends_b else np.zeros(0, np.int64),
        )
        order = np.argsort(roots, kind="stable")
        rs = roots[order]
        starts = np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])
        ends = np.r_[starts[1:], len(rs)]
        for s, e in zip(starts, ends):
            idx = order[s:e]
            rec = allm[idx] if e - s == 1 else combine([allm[idx]])
            if rec["n"][0] > 0:
                owner[idx] = len(out)
                out.append(rec)
    n_edge = len(out)
    parts = out + complete
    res = np.concatenate(parts) if parts else np.zeros(0, MOMENT_DTYPE)
    perm = _order(res)
    res = res[perm]
    if not members:
        return res
    rank = np.empty(len(perm), np.int64)
    rank[perm] = np.arange(len(perm))  # position of each record after ordering
    member: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    base = n_edge
    for k in keys:
        t = tiles[k]
        ids, recs = [], []
        if len(t.moments):
            own = owner[offset[k] : offset[k] + len(t.moments)]
            sel = (own >= 0) & (t.moments["n"] > 0)  # parts with pixels in this tile's core
            ids.append(np.asarray(t.ids, np.int64)[sel])
            recs.append(rank[own[sel]])
        if t.complete is not None and len(t.complete):
            ids.append(np.asarray(t.complete_ids, np.int64))
            recs.append(rank[base + np.arange(len(t.complete))])
            base += len(t.complete)
        if ids:
            member[k] = (np.concatenate(ids), np.concatenate(recs))
    return res, member


def shape_from_moments(rec: np.void | np.ndarray, spacing: tuple[float, float] | None) -> dict:
    """Centroid, bounding box, length/width/heading (pixels and metres) of one component."""
    n = float(rec["n"])
    mr, mc = float(rec["sr"]) / n, float(rec["sc"]) / n
    vrr = max(float(rec["srr"]) / n - mr * mr, 0.0) + 1.0 / 12.0
    vcc = max(float(rec["scc"]) / n - mc * mc, 0.0) + 1.0 / 12.0
    vrc = float(rec["src"]) / n - mr * mc

    def eig(a, b, c):
        tr, det = a + c, a * c - b * b
        disc = math.sqrt(max(tr * tr / 4.0 - det, 0.0))
        l1, l2 = tr / 2.0 + disc, max(tr / 2.0 - disc, 0.0)
        # principal direction (dr, dc)
        if abs(b) > 1e-12 * max(abs(a), abs(c), 1e-300):
            dr, dc = l1 - c, b
        elif a >= c:
            dr, dc = 1.0, 0.0
        else:
            dr, dc = 0.0, 1.0
        return l1, l2, dr, dc

    l1, l2, dr, dc = eig(vrr, vrc, vcc)
    out = {
        "bbox_px": [int(rec["r0"]), int(rec["c0"]), int(rec["r1"]), int(rec["c1"])],
        "centroid_px": [mr + 0.5, mc + 0.5],
        "area_px": int(n),
        "length_px": math.sqrt(12.0 * l1),
        "width_px": math.sqrt(12.0 * l2),
        "length_m": None,
        "width_m": None,
    }
    if spacing is not None:
        az, rg = spacing
        l1m, l2m, dr, dc = eig(vrr * az * az, vrc * az * rg, vcc * rg * rg)
        out["length_m"] = math.sqrt(12.0 * l1m)
        out["width_m"] = math.sqrt(12.0 * l2m)
    heading = math.degrees(math.atan2(dc, -dr)) % 180.0
    out["heading_deg"] = 0.0 if abs(heading - 180.0) < 1e-9 else heading
    return out
