"""Superpixels of SAR intensity by bounded DBSCAN-style growth from a global seed grid (seed 002).

Zhang, Lu, Xiang, Yuan 2023 (docs/references.md, ``zhang2023``), section 3.1 and Table 1; the
page docs/algorithms/superpixel_cfar.md states every choice. Pure array maths (NumPy, Numba).

Pixel dissimilarity (eq 7-8). Each pixel ``i`` carries the mean ``m_i`` and coefficient of
variation ``H(i)`` of the present intensities of the 5x5 patch centred on it. For patch means
``a, b`` (M = 25 pixels each, L looks), eq 8 is the likelihood-ratio statistic
``delta(a, b) = 2 M L ln((a + b) / (2 sqrt(a b)))`` and eq 7 is
``Omega(i, j) = delta(m_i, m_j) + |H(i) - H(j)| delta(m_k, m_j)`` with ``k`` the seed of the
superpixel being grown.

Clustering stage (the fast DBSCAN of the paper's ref. [39]: density-reachable growth). Seeds sit
on a *global* grid, rows and columns ``g * spacing + spacing // 2`` of the scene (by the tile's
``origin``, so every tile that sees a seed has the same one). From each present seed a
breadth-first growth adds a 4-neighbour ``j`` of an accepted pixel ``i`` when ``Omega(i, j) <
eps``, never leaving the square of half-side ``reach`` around the seed (the bounded reach).
Seeds grow independently of each other; a pixel reached by several seeds goes to the nearest
one (Euclidean; ties to the first in global raster order), which gives grid-like superpixels in
homogeneous sea and boundaries on the intensity edges that stop the growth. Present pixels no
seed reached are grouped per grid cell (``row // spacing, col // spacing``) into a *residual*
superpixel of that cell. Every superpixel has an *anchor*, its seed (the cell's grid point for a
residual one), and lies within ``reach`` of it (Chebyshev).

Merging stage (eq 9-10). Superpixel dissimilarity
``Omega(SP_m, SP_n) = 2 min(|SP_m|, |SP_n|) L ln((I_m + I_n) / (2 sqrt(I_m I_n))) + |H_m - H_n|``
(``I``: mean intensity, ``H``: coefficient of variation of the superpixel's intensities). A
superpixel smaller than ``min_size`` merges, in one round, into its least dissimilar 8-adjacent
superpixel of at least ``min_size`` pixels (ties: the smaller global id); it stays alone when it
has none. Absorbers never merge, so there are no chains and the reach stays bounded: a final
superpixel lies within ``3 reach + 1`` of its anchor, and it is fully determined by the pixels
within ``7 reach + 4`` of it (:func:`context_px`).

Ids. A superpixel's global id is ``((gi + OFF) * 2^22 + (gj + OFF)) * 2 + residual`` for its
anchor's grid index ``(gi, gj)``: the same in every tile, sorted like the global raster order of
the anchors. Local label ``l`` of a block indexes the sorted global ids, so every loop over
superpixels or over their pixels (raster order) runs in the same order in any tile and float
sums come out bit-identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from sarship.pipeline.tiling.boxsum import centered_box_sum

#: Side of the patches of eq 8 (and of the homogeneity H of eq 7).
PATCH = 5
#: Offset of the grid indices in a global id (indices may be negative in the mirrored border).
OFF = 1 << 21
SHIFT = 1 << 22


def context_px(reach: int) -> int:
    """Pixels around a final superpixel's anchor that fix its pixels, size, mean and CoV:
    merge members' anchors are within ``2 reach + 1``, their merge choices read neighbours
    within another ``2 reach + 1`` whose extent is ``reach`` and whose labels read ``2 reach + 2``
    (the competing seeds within ``reach`` and their growth's patches)."""
    return 7 * int(reach) + 4


def extent_px(reach: int) -> int:
    """Chebyshev distance from a final superpixel's anchor to any of its pixels (at most)."""
    return 3 * int(reach) + 1


def local_stats(x: np.ndarray, ok: np.ndarray, origin, side: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and coefficient of variation of the present values over ``side x side`` windows,
    for every block pixel at least ``side // 2`` from the block edge (NaN nearer the edge).
    Window sums by :func:`sarship.pipeline.tiling.boxsum.centered_box_sum` (bit-identical for any
    tiling); a window without present pixels has NaN mean."""
    r = side // 2
    H, W = x.shape
    mean = np.full((H, W), np.nan)
    cov = np.full((H, W), np.nan)
    if H <= 2 * r or W <= 2 * r:
        return mean, cov
    xf = np.where(ok, x, 0.0).astype(np.float64)
    org = (int(origin[0]), int(origin[1]))
    s1 = centered_box_sum(xf, side, r, org)
    s2 = centered_box_sum(xf * xf, side, r, org)
    n = centered_box_sum(ok.astype(np.float64), side, r, org)
    _mean_cov(s1, s2, n, mean[r : H - r, r : W - r], cov[r : H - r, r : W - r])
    return mean, cov


@njit(cache=True, nogil=True)
def _mean_cov(s1, s2, n, mean, cov):
    for i in range(s1.shape[0]):
        for j in range(s1.shape[1]):
            k = n[i, j]
            if k > 0:
                m = s1[i, j] / k
                v = s2[i, j] / k - m * m
                mean[i, j] = m
                cov[i, j] = math.sqrt(v) / m if (m > 0.0 and v > 0.0) else 0.0


@njit(cache=True, nogil=True)
def delta(a, b, ml):
    """Eq 8 / eq 10: ``2 ml ln((a + b) / (2 sqrt(a b)))`` (0 for a == b, inf when one is 0)."""
    if a == b:
        return 0.0
    if a <= 0.0 or b <= 0.0:
        return np.inf
    return 2.0 * ml * math.log((a + b) / (2.0 * math.sqrt(a * b)))


@njit(cache=True, nogil=True)
def _grow(m5, h5, ok, sr, sc, reach, eps, ml, best_d, best_s):
    """Clustering stage: every seed's bounded growth; ``best_s`` gets the winning seed per pixel."""
    H, W = m5.shape
    side = 2 * reach + 1
    stamp = np.full((H, W), -1, np.int32)
    qr = np.empty(side * side, np.int32)
    qc = np.empty(side * side, np.int32)
    dr = (-1, 1, 0, 0)
    dc = (0, 0, -1, 1)
    for k in range(sr.size):
        r0 = sr[k]
        c0 = sc[k]
        mk = m5[r0, c0]
        if not ok[r0, c0] or not (mk == mk):
            continue
        head = 0
        tail = 1
        qr[0] = r0
        qc[0] = c0
        stamp[r0, c0] = k
        while head < tail:
            ir = qr[head]
            ic = qc[head]
            head += 1
            d2 = (ir - r0) * (ir - r0) + (ic - c0) * (ic - c0)
            if d2 < best_d[ir, ic]:
                best_d[ir, ic] = d2
                best_s[ir, ic] = k
            mi = m5[ir, ic]
            hi = h5[ir, ic]
            for q in range(4):
                jr = ir + dr[q]
                jc = ic + dc[q]
                if jr < 0 or jr >= H or jc < 0 or jc >= W:
                    continue
                if abs(jr - r0) > reach or abs(jc - c0) > reach:
                    continue
                if stamp[jr, jc] == k or not ok[jr, jc]:
                    continue
                mj = m5[jr, jc]
                if not (mj == mj):
                    continue
                om = delta(mi, mj, ml)
                if om < eps:
                    om += abs(hi - h5[jr, jc]) * delta(mk, mj, ml)
                if om < eps:
                    stamp[jr, jc] = k
                    qr[tail] = jr
                    qc[tail] = jc
                    tail += 1


@njit(cache=True, nogil=True)
def _codes(best_s, ok, valid, sr, sc, r0, c0, spacing, gi0, gj0, ncj):
    """Per pixel ``2 * cell + residual`` (cell: row-major index of the anchor's grid cell among
    the cells from ``(gi0, gj0)``, ``ncj`` per row): the winning seed's, or the residual
    superpixel of the pixel's own cell; -1 absent. Increasing codes are increasing global ids."""
    H, W = best_s.shape
    out = np.full((H, W), -1, np.int64)
    for i in range(H):
        gi = (r0 + i) // spacing - gi0
        for j in range(W):
            if not ok[i, j] or not valid[i, j]:
                continue
            k = best_s[i, j]
            if k >= 0:
                ci = (r0 + sr[k]) // spacing - gi0
                cj = (c0 + sc[k]) // spacing - gj0
                out[i, j] = 2 * (ci * ncj + cj)
            else:
                cj = (c0 + j) // spacing - gj0
                out[i, j] = 2 * (gi * ncj + cj) + 1
    return out


@njit(cache=True, nogil=True)
def _compact(codes, n_codes):
    """Local labels 0..n-1 in increasing code order, and the codes used."""
    used = np.zeros(n_codes, np.int64)
    H, W = codes.shape
    for i in range(H):
        for j in range(W):
            c = codes[i, j]
            if c >= 0:
                used[c] = 1
    remap = np.full(n_codes, -1, np.int64)
    n = 0
    for c in range(n_codes):
        if used[c]:
            remap[c] = n
            n += 1
    which = np.empty(n, np.int64)
    for c in range(n_codes):
        if remap[c] >= 0:
            which[remap[c]] = c
    lab = np.full((H, W), -1, np.int64)
    for i in range(H):
        for j in range(W):
            c = codes[i, j]
            if c >= 0:
                lab[i, j] = remap[c]
    return lab, which


@njit(cache=True, nogil=True)
def pixel_lists(lab, n_lab):
    """Counting sort of the labelled pixels by label (raster order inside a label): CSR
    ``(ptr, flat indices)``."""
    H, W = lab.shape
    ptr = np.zeros(n_lab + 1, np.int64)
    for i in range(H):
        for j in range(W):
            l = lab[i, j]
            if l >= 0:
                ptr[l + 1] += 1
    for l in range(n_lab):
        ptr[l + 1] += ptr[l]
    pos = ptr[:-1].copy()
    out = np.empty(ptr[n_lab], np.int64)
    for i in range(H):
        for j in range(W):
            l = lab[i, j]
            if l >= 0:
                out[pos[l]] = i * W + j
                pos[l] += 1
    return ptr, out


@njit(cache=True, nogil=True)
def region_stats(lab, x, n_lab):
    """Size, mean and coefficient of variation of the intensities of each label (raster order)."""
    n = np.zeros(n_lab, np.int64)
    s1 = np.zeros(n_lab)
    s2 = np.zeros(n_lab)
    H, W = lab.shape
    for i in range(H):
        for j in range(W):
            l = lab[i, j]
            if l >= 0:
                v = x[i, j]
                n[l] += 1
                s1[l] += v
                s2[l] += v * v
    mean = np.zeros(n_lab)
    cov = np.zeros(n_lab)
    for l in range(n_lab):
        if n[l] > 0:
            m = s1[l] / n[l]
            mean[l] = m
            v = s2[l] / n[l] - m * m
            cov[l] = math.sqrt(v) / m if (m > 0.0 and v > 0.0) else 0.0
    return n, mean, cov


@njit(cache=True, nogil=True)
def _pairs(lab):
    """Keys ``a * 2^31 + b`` (a < b) of 8-adjacent labels (each pixel's E, S, SE, SW neighbours)."""
    H, W = lab.shape
    out = np.empty(4 * H * W, np.int64)
    m = 0
    last = np.full(4, -1, np.int64)  # the previous key per direction: runs along a boundary repeat it
    for i in range(H):
        for j in range(W):
            a = lab[i, j]
            if a < 0:
                continue
            for q in range(4):
                if q == 0:
                    ii, jj = i, j + 1
                elif q == 1:
                    ii, jj = i + 1, j
                elif q == 2:
                    ii, jj = i + 1, j + 1
                else:
                    ii, jj = i + 1, j - 1
                if ii >= H or jj < 0 or jj >= W:
                    continue
                b = lab[ii, jj]
                if b < 0 or b == a:
                    continue
                lo = a if a < b else b
                hi = b if a < b else a
                key = lo * 2147483648 + hi
                if key != last[q]:
                    out[m] = key
                    m += 1
                    last[q] = key
    return out[:m]


def adjacency(lab: np.ndarray, n_lab: int) -> tuple[np.ndarray, np.ndarray]:
    """8-adjacency of labels as CSR ``(ptr, idx)``, neighbours of each label sorted."""
    return _csr(np.unique(_pairs(lab)), n_lab)


def merged_adjacency(ptr: np.ndarray, idx: np.ndarray, fmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The adjacency after relabelling by ``fmap``: labels ``a != b`` are adjacent when some of
    their members were (the same as :func:`adjacency` of the relabelled image)."""
    src = np.repeat(np.arange(ptr.size - 1), np.diff(ptr))
    a, b = fmap[src], fmap[idx]
    keep = a < b
    return _csr(np.unique(a[keep] * 2147483648 + b[keep]), ptr.size - 1)


def _csr(keys: np.ndarray, n_lab: int) -> tuple[np.ndarray, np.ndarray]:
    a = keys // 2147483648
    b = keys % 2147483648
    src = np.concatenate([a, b])
    dst = np.concatenate([b, a])
    order = np.lexsort((dst, src))
    src, dst = src[order], dst[order]
    ptr = np.zeros(n_lab + 1, np.int64)
    np.add.at(ptr, src + 1, 1)
    return np.cumsum(ptr), dst.astype(np.int64)


@njit(cache=True, nogil=True)
def sp_dissimilarity(na, ma, ca, nb, mb, cb, looks):
    """Eq 9-10: ``2 min(size) L ln((I_m + I_n) / (2 sqrt(I_m I_n))) + |H_m - H_n|``."""
    return delta(ma, mb, float(min(na, nb)) * looks) + abs(ca - cb)


@njit(cache=True, nogil=True)
def _merge_map(n, mean, cov, ptr, idx, min_size, looks):
    """Each label's final label: small ones (< min_size) go to their least dissimilar big neighbour."""
    L = n.size
    out = np.arange(L)
    for a in range(L):
        if n[a] >= min_size or n[a] == 0:
            continue
        best = -1
        bo = np.inf
        for q in range(ptr[a], ptr[a + 1]):
            b = idx[q]
            if n[b] < min_size:
                continue
            o = sp_dissimilarity(n[a], mean[a], cov[a], n[b], mean[b], cov[b], looks)
            if o < bo:
                bo = o
                best = b
        if best >= 0:
            out[a] = best
    return out


@dataclass
class Superpixels:
    """Superpixels of a block. ``labels`` (block shape, int64): local label, -1 for absent or
    unlabelled pixels; per label ``gid`` (global id, sorted), ``anchor`` (global row, col),
    ``size``, ``mean``, ``cov`` (intensity CoV); ``ptr``/``idx``: 8-adjacency (CSR)."""

    labels: np.ndarray
    gid: np.ndarray
    anchor: np.ndarray
    size: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    ptr: np.ndarray
    idx: np.ndarray


def seeds(shape, origin, spacing: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block positions ``(rows, cols)`` of the global grid seeds, raster order, and their ids."""
    s = int(spacing)
    h = s // 2
    r0, c0 = int(origin[0]), int(origin[1])
    rows = np.arange((h - r0) % s, shape[0], s)
    cols = np.arange((h - c0) % s, shape[1], s)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    gi = (rr + r0) // s
    gj = (cc + c0) // s
    gid = ((gi + OFF) * SHIFT + (gj + OFF)) * 2
    return rr.astype(np.int64), cc.astype(np.int64), gid.astype(np.int64)


def anchors_of(gid: np.ndarray, spacing: int) -> np.ndarray:
    """Global (row, col) of the anchors of global ids."""
    g = gid // 2
    gi = g // SHIFT - OFF
    gj = g % SHIFT - OFF
    s = int(spacing)
    return np.stack([gi * s + s // 2, gj * s + s // 2], 1)


def segment(
    x: np.ndarray, ok: np.ndarray, origin, spacing: int, reach: int, eps: float, looks: float, min_size: int
) -> Superpixels:
    """Clustering and merging stages (module docstring) on a block ``x`` (intensity, ``ok``: present)."""
    x = np.ascontiguousarray(x, np.float64)
    ok = np.ascontiguousarray(ok, np.bool_)
    m5, h5 = local_stats(x, ok, origin, PATCH)
    sr, sc, sgid = seeds(x.shape, origin, spacing)
    best_d = np.full(x.shape, np.iinfo(np.int64).max, np.int64)
    best_s = np.full(x.shape, -1, np.int64)
    ml = float(PATCH * PATCH) * float(looks)
    _grow(m5, h5, ok, sr, sc, int(reach), float(eps), ml, best_d, best_s)
    valid = np.isfinite(m5)
    S = int(spacing)
    r0, c0 = int(origin[0]), int(origin[1])
    gi0, gj0 = r0 // S, c0 // S
    nci = (r0 + x.shape[0] - 1) // S - gi0 + 1
    ncj = (c0 + x.shape[1] - 1) // S - gj0 + 1
    codes = _codes(best_s, ok, valid, sr, sc, r0, c0, S, gi0, gj0, ncj)
    lab, which = _compact(codes, 2 * nci * ncj)
    cell = which // 2
    uniq = ((cell // ncj + gi0 + OFF) * SHIFT + (cell % ncj + gj0 + OFF)) * 2 + which % 2
    nl = uniq.size
    present = lab >= 0
    n, mean, cov = region_stats(lab, x, nl)
    ptr, idx = adjacency(lab, nl)
    fmap = _merge_map(n, mean, cov, ptr, idx, int(min_size), float(looks))
    lab[present] = fmap[lab[present]]
    n, mean, cov = region_stats(lab, x, nl)
    ptr, idx = merged_adjacency(ptr, idx, fmap)
    return Superpixels(
        labels=lab, gid=uniq, anchor=anchors_of(uniq, spacing), size=n, mean=mean, cov=cov, ptr=ptr, idx=idx
    )


@njit(cache=True, nogil=True)
def select_clutter(
    t,
    is_bg,
    is_target,
    n,
    mean,
    cov,
    ptr,
    idx,
    anc_r,
    anc_c,
    radius,
    th_clu,
    tl_clu,
    max_clutter,
    looks,
    out,
    mark,
    queue,
    rings,
):
    """Table 1 for target superpixel ``t``: the background neighbours with ``Omega > th_clu``,
    then, grown breadth-first from them, background neighbours of clutter superpixels with
    ``Omega < tl_clu``, until ``max_clutter``; only superpixels whose anchor lies within
    ``radius`` (Chebyshev) of ``t``'s. When ``t`` has no qualifying background neighbour (a
    superpixel inside a large target), the first step looks at the background neighbours of the
    target superpixels reached from ``t`` through target superpixels, ring by ring (at most
    ``rings`` rings; 0: the paper's adjacent superpixels only), and takes the first ring that
    has any. Writes the clutter labels to ``out`` (sorted) and returns their
    count. ``mark`` (int64, one per label, all -1) is scratch, restored on return."""
    ar = anc_r[t]
    ac = anc_c[t]
    m = 0
    # first step, possibly through rings of target superpixels
    ring_start = 0
    ring_end = 1
    queue[0] = t
    mark[t] = t
    tail = 1
    touched = 1
    depth = 0
    while m == 0 and ring_start < ring_end and depth <= rings:
        depth += 1
        for qi in range(ring_start, ring_end):
            u = queue[qi]
            for q in range(ptr[u], ptr[u + 1]):
                b = idx[q]
                if mark[b] == t:
                    continue
                if abs(anc_r[b] - ar) > radius or abs(anc_c[b] - ac) > radius:
                    continue
                if is_bg[b]:
                    if sp_dissimilarity(n[t], mean[t], cov[t], n[b], mean[b], cov[b], looks) > th_clu:
                        mark[b] = t
                        out[m] = b
                        m += 1
                        if m >= max_clutter:
                            break
                elif is_target[b]:
                    mark[b] = t
                    queue[tail] = b
                    tail += 1
            if m >= max_clutter:
                break
        touched = tail
        ring_start = ring_end
        ring_end = tail
    # growth through similar background neighbours
    head = 0
    while head < m and m < max_clutter:
        c = out[head]
        head += 1
        for q in range(ptr[c], ptr[c + 1]):
            b = idx[q]
            if mark[b] == t or not is_bg[b]:
                continue
            if abs(anc_r[b] - ar) > radius or abs(anc_c[b] - ac) > radius:
                continue
            if sp_dissimilarity(n[c], mean[c], cov[c], n[b], mean[b], cov[b], looks) < tl_clu:
                mark[b] = t
                out[m] = b
                m += 1
                if m >= max_clutter:
                    break
    # restore scratch
    for i in range(touched):
        mark[queue[i]] = -1
    for i in range(m):
        mark[out[i]] = -1
    out[:m].sort()
    return m
