"""Cross-sidelobe suppression on detections (seed 003, section 2 (2); docs/algorithms/sidelobes.md).

A strong point scatterer imaged by an unweighted SAR processor spreads into a cross of
sinc^2 sidelobes along its range line (row) and azimuth line (column) (first sidelobe
-13.26 dB). Where the arms pass the detector's threshold they join the ship's detection and
inflate its length, width and heading error. Seed 003 finds the cross with a modified
Tupin ratio line detector and keeps the ship *core* by region growing from the cross centre;
geometry is then measured on the core.

Here, per detection (its connected component, read from the mask, and its bounding box
plus a margin, read from the scene):

1. **Ratio line detector** (Tupin et al. 1998, section III-A, detector D1, restricted to the
   two sidelobe directions: the modification seed 003 makes, since a cross needs no
   orientation search): for a pixel ``q`` and a line along the row (range), region 1 is the
   pixel, regions 2 and 3 the 3-pixel segments on the rows above and below; with the
   empirical means ``mu_i`` the ratio edge responses are ``r_1j = 1 - min(mu_1/mu_j, mu_j/mu_1)``
   and the line response ``r = min(r_12, r_13)`` (D1), taken only where the centre is the
   brighter (a bright line). Along the column likewise with the columns left and right.
   ``q`` is a line pixel where ``r >= line_ratio`` (``r_min`` of Tupin; default 0.5: the line
   at least twice each side).
2. **Cross**: the scatterers are the component's pixels of at least ``scatterer_ratio``
   times the component's median, brightest first. Walking away from a scatterer of power
   ``P`` along its row (both ways) and column (both ways), up to ``arm_max_px`` and across
   gaps of at most ``gap_px`` pixels outside the component, its half-arms are the
   component's line pixels on that line that are (a) at most ``arm_width_px`` thick across
   the arm and (b) no brighter than ``arm_factor * P * sinc2_envelope(k)`` at offset ``k``:
   the most a sinc^2 sidelobe of that scatterer can put there (a pixel brighter than that is
   the ship's own, not a sidelobe). The *body* is the component without these candidate
   arm pixels, as its moment rectangle (centroid, principal axes, moment length and width)
   widened by ``body_margin_px``. A half-arm *reaches out* when at least ``min_arm_px`` of
   its pixels lie outside the body. The scatterer is a cross centre when at least
   ``min_out_arms`` (2) half-arms reach out and either ``min_half_arms`` (3) of the 4
   half-arms are there (both lines of the cross), or both half-arms of one line reach out
   while the body covers the scatterer's other line (a sidelobe line is symmetric about its
   scatterer; the other line runs inside the hull). A ship's own bright pixels along a row
   or column stay inside its body, or are brighter than its scatterers' sidelobes: they
   make no cross (issue #30: speckled hull pixels had made crosses and cut ships to a tenth).
3. **Core by region growing**: the pixels outside the body of every cross's half-arms are
   removed from the component (arm pixels inside the body are the hull's); the core is the
   region grown from the brightest cross centre through the remaining pixels of the
   detection by the merge rule that made the detection one (pixels within a ``2 merge_r +
   1`` square), so a speckled hull in fragments stays whole (the detector's decision is the
   radiometric similarity criterion: a pixel joins if the detector found it target-like and
   it is not a sidelobe arm pixel). Without a cross the geometry stays the component's.

Length, width and heading of the core are the moment geometry of
:func:`sarship.pipeline.targets.components.shape_from_moments`, as for every detection.

Absent pixels (NaN) are never line pixels and count as absent in the line means.
References (docs/references.md): seed 003, tupin1998.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.tiling.intensity_absent import xp_of as _xp  # NumPy or CuPy, by the array

#: The geometry a core replaces (the component's values are kept as ``<name>_raw``).
GEOMETRY_KEYS = ("centroid_px", "length_px", "width_px", "heading_deg", "length_m", "width_m")


@dataclass(frozen=True)
class SidelobeParams:
    """Parameters of the cross detector and the core (docs/algorithms/sidelobes.md)."""

    line_ratio: float = 0.5  # Tupin D1 threshold r_min
    line_gap: int = 0  # rows (columns) between the line and its side segments
    min_arm_px: int = 2  # a half-arm reaches beyond the body by at least this many pixels
    arm_width_px: int = 1  # an arm pixel: the detection is at most this thick across the arm
    scatterer_ratio: float = 4.0  # a scatterer: local max >= this x the component's median
    min_half_arms: int = 3  # half-arms (of 4) that make a cross
    min_out_arms: int = 2  # of them, half-arms reaching beyond the body (min_arm_px pixels outside it)
    arm_max_px: int = 64  # longest half-arm followed
    gap_px: int = 3  # gaps (outside the component) an arm may jump
    margin_px: int = 3  # window = bounding box + this margin
    max_scatterers: int = 8  # scatterers tried per detection, brightest first
    oversampling: float = 1.2  # resolution / pixel spacing of the sinc^2 impulse response
    arm_factor: float = 4.0  # an arm pixel is at most this x its scatterer's sinc^2 envelope
    body_margin_px: float = 0.5  # the body rectangle is widened by this many pixels each side

    def __post_init__(self) -> None:
        if not (isinstance(self.line_ratio, (int, float)) and 0.0 < float(self.line_ratio) < 1.0):
            raise InputError(f"sidelobes line_ratio: must be a number in (0, 1) (got {self.line_ratio!r})")
        if not (
            isinstance(self.scatterer_ratio, (int, float))
            and math.isfinite(self.scatterer_ratio)
            and float(self.scatterer_ratio) >= 1.0
        ):
            raise InputError(f"sidelobes scatterer_ratio: must be a number >= 1 (got {self.scatterer_ratio!r})")
        for name, lo, hi in (("oversampling", 1.0, 4.0), ("arm_factor", 1.0, 1000.0), ("body_margin_px", 0.0, 16.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= float(v) <= hi:
                raise InputError(f"sidelobes {name}: must be a number in [{lo:g}, {hi:g}] (got {v!r})")
        for name, lo, hi in (
            ("min_half_arms", 1, 4),
            ("min_out_arms", 1, 4),
            ("arm_max_px", 1, 4096),
            ("gap_px", 0, 64),
            ("line_gap", 0, 4),
            ("min_arm_px", 1, 64),
            ("arm_width_px", 1, 16),
            ("margin_px", 2, 64),
            ("max_scatterers", 1, 1024),
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise InputError(f"sidelobes {name}: must be an integer in [{lo}, {hi}] (got {v!r})")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def line_response(power, along: str, gap: int = 0):
    """Tupin's ratio line detector D1 for a 1-pixel line ``along`` ``"row"`` or ``"col"``.

    ``r = min(r_12, r_13)`` with ``r_1j = 1 - mu_j / mu_1`` where the centre pixel (region 1)
    is brighter than both 3-pixel side segments (regions 2, 3: the rows above and below for a
    line along the row, the columns left and right for a line along the column), else 0.
    Border pixels (a side outside the window) and absent pixels respond 0; absent pixels in
    a side segment are left out of its mean. NumPy or CuPy (the same code).
    """
    xp = _xp(power)
    if along not in ("row", "col"):
        raise ValueError(f"along: 'row' or 'col', got {along!r}")
    p = power.astype(xp.float64)
    h, w = p.shape
    ok = xp.isfinite(p)
    v = xp.where(ok, p, 0.0)
    o = ok.astype(xp.float64)
    d = gap + 1
    out = xp.zeros((h, w))
    if along == "row":
        if d >= h:
            return out
        # 3-pixel sums along the row (the side segments' direction), counts of present pixels
        s3, n3 = v.copy(), o.copy()
        s3[:, 1:] += v[:, :-1]
        s3[:, :-1] += v[:, 1:]
        n3[:, 1:] += o[:, :-1]
        n3[:, :-1] += o[:, 1:]
        a, b = s3[: -2 * d], s3[2 * d :]  # the side segments of rows d .. h-d-1
        na, nb = n3[: -2 * d], n3[2 * d :]
        core = (slice(d, h - d), slice(None))
    else:
        if d >= w:
            return out
        s3, n3 = v.copy(), o.copy()
        s3[1:] += v[:-1]
        s3[:-1] += v[1:]
        n3[1:] += o[:-1]
        n3[:-1] += o[1:]
        a, b = s3[:, : -2 * d], s3[:, 2 * d :]
        na, nb = n3[:, : -2 * d], n3[:, 2 * d :]
        core = (slice(None), slice(d, w - d))
    c = p[core]
    with np.errstate(invalid="ignore", divide="ignore"):
        side = xp.maximum(a / na, b / nb)  # NaN where a side has no present pixel
        r = 1.0 - side / c
    good = ok[core] & (na > 0) & (nb > 0) & (c > side) & (c > 0)
    out[core] = xp.where(good, r, 0.0)
    return out


def _thickness(comp: np.ndarray, r: int, c: int, dr: int, dc: int) -> int:
    """Length of the run of detection pixels through ``(r, c)`` along ``(dr, dc)``."""
    h, w = comp.shape
    n = 1
    for s in (1, -1):
        rr, cc = r + s * dr, c + s * dc
        while 0 <= rr < h and 0 <= cc < w and comp[rr, cc]:
            n += 1
            rr, cc = rr + s * dr, cc + s * dc
    return n


def sinc2_envelope(k, oversampling: float = 1.2) -> np.ndarray:
    """Upper bound of a sidelobe's power at ``k`` pixels from a scatterer's peak pixel, relative
    to the peak pixel's power, for a sinc^2 impulse response sampled ``oversampling`` pixels a
    resolution cell.

    The scatterer lies within half a pixel of its peak pixel, so a pixel ``|k| >= 1`` away sees
    it at ``x >= (|k| - 1/2) / os`` resolution cells while the peak pixel sees at least
    ``sinc^2(1/2 / os)``; with ``sinc^2(x) <= 1 / (pi x)^2`` the ratio is at most
    ``(os / (pi (|k| - 1/2)))^2 / sinc^2(1/(2 os))``, capped at 1 (0.12 at 2 px, 0.043 at
    3 px, 0.0048 at 8 px for os = 1.2).
    """
    k = np.abs(np.asarray(k, np.float64))
    x = np.maximum(k - 0.5, 1e-12) / oversampling
    env = 1.0 / (math.pi * x) ** 2 / float(np.sinc(0.5 / oversampling)) ** 2
    return np.minimum(env, 1.0)


def _walk(
    comp: np.ndarray, line: np.ndarray, p: np.ndarray, r: int, c: int, dr: int, dc: int, params: SidelobeParams
) -> list[tuple[int, int]]:
    """The component's arm pixels from ``(r, c)`` outwards along ``(dr, dc)``: line pixels
    where the detection is at most ``arm_width_px`` thick across the arm (a hull is thicker)
    and no brighter than ``arm_factor`` times the scatterer's sinc^2 envelope at their offset
    (a pixel brighter than the scatterer's sidelobe can make it is the ship's own)."""
    h, w = comp.shape
    top = params.arm_factor * float(p[r, c])
    out, gap = [], 0
    for k in range(1, params.arm_max_px + 1):
        rr, cc = r + k * dr, c + k * dc
        if not (0 <= rr < h and 0 <= cc < w):
            break
        if comp[rr, cc]:
            gap = 0
            if (
                line[rr, cc]
                and p[rr, cc] <= top * float(sinc2_envelope(k, params.oversampling))
                and _thickness(comp, rr, cc, dc, dr) <= params.arm_width_px
            ):
                out.append((rr, cc))
        else:
            gap += 1
            if gap > params.gap_px:
                break
    return out


def _outside_body(body: np.ndarray, pts: np.ndarray, margin: float) -> np.ndarray:
    """Which of the points ``pts`` (n x 2, row col) lie outside the body's moment rectangle
    (centred on its centroid, along its principal axes, sides ``sqrt(12 lambda)`` as the moment
    length and width of :func:`sarship.pipeline.targets.components.shape_from_moments`) widened by
    ``margin`` pixels each side. An empty or one-pixel body has no extent: every point is out."""
    rr, cc = np.nonzero(body)
    if rr.size < 2:
        return np.ones(len(pts), bool)
    xy = np.stack([rr, cc], 1).astype(np.float64)
    m = xy.mean(0)
    lam, vec = np.linalg.eigh(np.cov(xy.T, bias=True) + np.eye(2) / 12.0)  # + the pixel's own extent
    half = np.sqrt(3.0 * np.maximum(lam, 0.0)) + margin
    uv = (np.asarray(pts, np.float64).reshape(-1, 2) - m) @ vec
    return (np.abs(uv) > half).any(axis=1)


def refine(
    power: np.ndarray, comp: np.ndarray, params: SidelobeParams = SidelobeParams(), merge_r: int = 1
) -> dict[str, Any]:
    """Cross detection and core of one detection (module doc, steps 1-3).

    ``power``: the window's pixel power (2-D, NaN absent); ``comp``: the detection's pixels in
    the window (bool); ``merge_r``: the merge radius that made the detection one (the core is
    grown by the same rule). Returns ``{"sidelobes": bool, "core": bool array, "centres":
    [(r, c)], "arm_px": int}``; without a cross the core is the component.
    """
    comp = np.asarray(comp, bool)
    p = np.asarray(power, np.float64)
    none = {"sidelobes": False, "core": comp.copy(), "centres": [], "arm_px": 0}
    if not comp.any():
        return none
    vals = p[comp]
    vals = vals[np.isfinite(vals)]
    med = float(np.median(vals)) if vals.size else 0.0
    cand = comp & np.isfinite(p) & (p >= params.scatterer_ratio * med)
    rs, cs = np.nonzero(cand)
    order = np.argsort(-p[rs, cs], kind="stable")[: params.max_scatterers]
    lh = line_response(p, "row", params.line_gap) >= params.line_ratio
    lv = line_response(p, "col", params.line_gap) >= params.line_ratio
    cut = np.zeros_like(comp)
    centres = []
    for i in order:
        r, c = int(rs[i]), int(cs[i])
        half = [
            _walk(comp, lh, p, r, c, 0, -1, params),
            _walk(comp, lh, p, r, c, 0, 1, params),
            _walk(comp, lv, p, r, c, -1, 0, params),
            _walk(comp, lv, p, r, c, 1, 0, params),
        ]
        if sum(1 for a in half if a) < params.min_out_arms:  # too few half-arms to reach out
            continue
        # the body: the detection without this scatterer's candidate arms; an arm of a real
        # cross reaches beyond it, a ship's own thin pixels along a row or column do not
        body = comp.copy()
        for a in half:
            for rr, cc in a:
                body[rr, cc] = False
        outs = [
            np.asarray(a, np.int64)[_outside_body(body, np.asarray(a, np.int64), params.body_margin_px)]
            if a
            else np.zeros((0, 2), np.int64)
            for a in half
        ]
        out = [len(o) >= params.min_arm_px for o in outs]
        h, w = comp.shape

        def covered(dr: int, dc: int) -> bool:  # the hull (body) next to the scatterer along (dr, dc)
            return any(0 <= r + s * dr < h and 0 <= c + s * dc < w and body[r + s * dr, c + s * dc] for s in (1, -1))  # noqa: B023 (called in this iteration)

        # one sidelobe line out on both sides, its other line hidden in the hull
        pair = (out[0] and out[1] and covered(1, 0)) or (out[2] and out[3] and covered(0, 1))
        if sum(out) < params.min_out_arms or not (pair or sum(1 for a in half if a) >= params.min_half_arms):
            continue
        centres.append((r, c))
        for o in outs:
            cut[o[:, 0], o[:, 1]] = True
    if not centres:
        return none
    keep = comp & ~cut
    for r, c in centres:
        keep[r, c] = True
    # region growing from the brightest cross centre, by the merge rule that made the detection
    core = component_in_window(keep, centres[0], merge_r)
    removed = int((comp & ~core).sum())
    if removed == 0:
        return {**none, "centres": centres}
    return {"sidelobes": True, "core": core, "centres": centres, "arm_px": int((cut & ~core).sum())}


def component_in_window(mask: np.ndarray, peak: tuple[int, int], merge_r: int) -> np.ndarray:
    """The detection's pixels in a mask window: the mask pixels joined to the peak pixel by
    the merge rule of :func:`sarship.pipeline.targets.components.tile_components` (pixels within a
    ``2 merge_r + 1`` square of each other are one detection)."""
    from scipy import ndimage as ndi

    m = np.asarray(mask, bool)
    if merge_r > 0:
        joined = ndi.binary_dilation(m, structure=np.ones((2 * merge_r + 1,) * 2, bool))
    else:
        joined = m
    lab, _ = ndi.label(joined, structure=np.ones((3, 3), bool))
    lp = lab[peak]
    return m & (lab == lp) if lp else np.zeros_like(m)


def core_record(rec: np.void, core: np.ndarray, power: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """The moment record of the core (window ``core`` at scene ``origin``), the component's
    ``peak``, ``score`` and peak position kept (the core holds the peak)."""
    rr, cc = np.nonzero(core)
    gr = (rr + origin[0]).astype(np.float64)
    gc = (cc + origin[1]).astype(np.float64)
    out = np.zeros(1, rec.dtype)
    out[0] = rec  # a copy: np.array(void, copy=True) would still share the records' memory
    out["n"] = rr.size
    out["sr"], out["sc"] = gr.sum(), gc.sum()
    out["srr"], out["scc"], out["src"] = (gr * gr).sum(), (gc * gc).sum(), (gr * gc).sum()
    out["r0"], out["c0"] = int(gr.min()), int(gc.min())
    out["r1"], out["c1"] = int(gr.max()) + 1, int(gc.max()) + 1
    v = np.asarray(power, np.float64)[rr, cc]
    out["sumv"] = float(np.nansum(v))
    return out


def refine_features(
    feats: list[dict],
    records: np.ndarray,
    read_power: Callable[[int, int, int, int], np.ndarray],
    read_mask: Callable[[int, int, int, int], np.ndarray],
    shape: tuple[int, int],
    merge_r: int,
    spacing: tuple[float, float] | None,
    geo: dict | None,
    params: SidelobeParams = SidelobeParams(),
) -> list[dict]:
    """Detections with their sidelobes suppressed (the properties of docs/interfaces/files.md).

    For each detection (``feats[i]`` built from ``records[i]``): its window (bounding box +
    ``margin_px``) is read (``read_power(ra, rb, ca, cb)``: what the detector read, made pixel
    power by :func:`sarship.pipeline.tiling.inputs.pixel_power`; ``read_mask``: the detection mask), the cross and the core found (:func:`refine`); with sidelobes the
    core's geometry (``centroid_px``, ``length_px``, ``width_px``, ``heading_deg``,
    ``length_m``, ``width_m`` and the outline) replaces the component's, whose values are
    kept as ``<name>_raw``. Every detection gets ``sidelobes: true|false``. Detections whose
    peak is under ``scatterer_ratio`` times their mean hold no scatterer and are not read.
    """
    from sarship.pipeline.targets.ship_features import features
    from sarship.pipeline.tiling.inputs import pixel_power

    H, W = shape
    m = params.margin_px
    out = []
    for f, rec in zip(feats, records):
        props = f["properties"]
        n = float(rec["n"])
        mean = float(rec["sumv"]) / n if n else 0.0
        if not (n >= 3 and float(rec["peak"]) >= params.scatterer_ratio * mean):
            props["sidelobes"] = False
            out.append(f)
            continue
        ra, rb = max(int(rec["r0"]) - m, 0), min(int(rec["r1"]) + m, H)
        ca, cb = max(int(rec["c0"]) - m, 0), min(int(rec["c1"]) + m, W)
        mask = np.asarray(read_mask(ra, rb, ca, cb)) > 0
        power = np.asarray(pixel_power(np.asarray(read_power(ra, rb, ca, cb))), np.float64)
        peak = (int(rec["peak_r"]) - ra, int(rec["peak_c"]) - ca)
        comp = component_in_window(mask, peak, merge_r)
        # the window may cut another detection's pixels joined through pixels outside it: keep
        # only those inside this detection's bounding box
        bb = np.zeros_like(comp)
        bb[int(rec["r0"]) - ra : int(rec["r1"]) - ra, int(rec["c0"]) - ca : int(rec["c1"]) - ca] = True
        comp &= bb
        res = refine(power, comp, params, merge_r)
        if not res["sidelobes"]:
            props["sidelobes"] = False
            out.append(f)
            continue
        core = core_record(rec, res["core"], power, (ra, ca))
        nf = features(core, spacing, geo)[0]
        np_ = nf["properties"]
        for k in GEOMETRY_KEYS:
            props[f"{k}_raw"] = props[k]
            props[k] = np_[k]
        props["sidelobes"] = True
        props["core_area_px"] = int(core["n"][0])
        out.append({**f, "geometry": nf["geometry"], "properties": props})
    return out
