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
2. **Cross**: the scatterers are the component's 3x3 local maxima of at least
   ``scatterer_ratio`` times the component's median. Walking away from a scatterer along its
   row (both ways) and column (both ways), up to ``arm_max_px`` and across gaps of at most
   ``gap_px`` pixels outside the component, the component's line pixels on that line are its
   half-arms. A scatterer with at least ``min_half_arms`` (default 3) of its 4 half-arms is a
   cross centre: a ship alone has at most 2 (its own axis, and only when it lies along a
   row or column), a sidelobe cross has 4, or 3 where the ship's hull covers one.
3. **Core by region growing**: the half-arm pixels of every cross are removed from the
   component, except those whose two neighbours across the arm are both kept (the arm runs
   inside the hull there); the core is the 8-connected region grown from the brightest
   cross centre through the remaining pixels of the detection (the detector's decision is
   the radiometric similarity criterion: a pixel joins if the detector found it
   target-like and it is not a sidelobe line pixel).

Length, width and heading of the core are the moment geometry of
:func:`sarship.pipeline.components.shape_from_moments`, as for every detection.

Absent pixels (NaN) are never line pixels and count as absent in the line means.
References (docs/references.md): seed 003, tupin1998.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.intensity_absent import xp_of as _xp  # NumPy or CuPy, by the array

#: The geometry a core replaces (the component's values are kept as ``<name>_raw``).
GEOMETRY_KEYS = ("centroid_px", "length_px", "width_px", "heading_deg", "length_m", "width_m")


@dataclass(frozen=True)
class SidelobeParams:
    """Parameters of the cross detector and the core (docs/algorithms/sidelobes.md)."""

    line_ratio: float = 0.5          # Tupin D1 threshold r_min
    line_gap: int = 0                # rows (columns) between the line and its side segments
    min_arm_px: int = 2              # a cross needs one half-arm at least this long
    arm_width_px: int = 1            # an arm pixel: the detection is at most this thick across the arm
    scatterer_ratio: float = 4.0     # a scatterer: local max >= this x the component's median
    min_half_arms: int = 3           # half-arms (of 4) that make a cross
    arm_max_px: int = 64             # longest half-arm followed
    gap_px: int = 3                  # gaps (outside the component) an arm may jump
    margin_px: int = 3               # window = bounding box + this margin
    max_scatterers: int = 8          # scatterers tried per detection, brightest first

    def __post_init__(self) -> None:
        if not (isinstance(self.line_ratio, (int, float)) and 0.0 < float(self.line_ratio) < 1.0):
            raise InputError(f"sidelobes line_ratio: must be a number in (0, 1) (got {self.line_ratio!r})")
        if not (isinstance(self.scatterer_ratio, (int, float)) and math.isfinite(self.scatterer_ratio)
                and float(self.scatterer_ratio) >= 1.0):
            raise InputError(f"sidelobes scatterer_ratio: must be a number >= 1 (got {self.scatterer_ratio!r})")
        for name, lo, hi in (("min_half_arms", 1, 4), ("arm_max_px", 1, 4096), ("gap_px", 0, 64),
                             ("line_gap", 0, 4), ("min_arm_px", 1, 64), ("arm_width_px", 1, 16),
                             ("margin_px", 2, 64), ("max_scatterers", 1, 1024)):
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
        a, b = s3[:-2 * d], s3[2 * d:]          # the side segments of rows d .. h-d-1
        na, nb = n3[:-2 * d], n3[2 * d:]
        core = (slice(d, h - d), slice(None))
    else:
        if d >= w:
            return out
        s3, n3 = v.copy(), o.copy()
        s3[1:] += v[:-1]
        s3[:-1] += v[1:]
        n3[1:] += o[:-1]
        n3[:-1] += o[1:]
        a, b = s3[:, :-2 * d], s3[:, 2 * d:]
        na, nb = n3[:, :-2 * d], n3[:, 2 * d:]
        core = (slice(None), slice(d, w - d))
    c = p[core]
    with np.errstate(invalid="ignore", divide="ignore"):
        side = xp.maximum(a / na, b / nb)              # NaN where a side has no present pixel
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


def _walk(comp: np.ndarray, line: np.ndarray, r: int, c: int, dr: int, dc: int, params: SidelobeParams) -> list[tuple[int, int]]:
    """The component's arm pixels from ``(r, c)`` outwards along ``(dr, dc)``: line pixels
    where the detection is at most ``arm_width_px`` thick across the arm (a hull is thicker)."""
    h, w = comp.shape
    out, gap = [], 0
    for k in range(1, params.arm_max_px + 1):
        rr, cc = r + k * dr, c + k * dc
        if not (0 <= rr < h and 0 <= cc < w):
            break
        if comp[rr, cc]:
            gap = 0
            if line[rr, cc] and _thickness(comp, rr, cc, dc, dr) <= params.arm_width_px:
                out.append((rr, cc))
        else:
            gap += 1
            if gap > params.gap_px:
                break
    return out


def refine(power: np.ndarray, comp: np.ndarray, params: SidelobeParams = SidelobeParams()) -> dict[str, Any]:
    """Cross detection and core of one detection (module doc, steps 1-3).

    ``power``: the window's pixel power (2-D, NaN absent); ``comp``: the detection's pixels in
    the window (bool). Returns ``{"sidelobes": bool, "core": bool array, "centres": [(r, c)],
    "arm_px": int}``; without a cross the core is the component.
    """
    comp = np.asarray(comp, bool)
    p = np.asarray(power, np.float64)
    if not comp.any():
        return {"sidelobes": False, "core": comp.copy(), "centres": [], "arm_px": 0}
    vals = p[comp]
    vals = vals[np.isfinite(vals)]
    med = float(np.median(vals)) if vals.size else 0.0
    from scipy import ndimage as ndi

    cand = comp & np.isfinite(p) & (p >= params.scatterer_ratio * med)
    rs, cs = np.nonzero(cand)
    order = np.argsort(-p[rs, cs], kind="stable")[:params.max_scatterers]
    lh = line_response(p, "row", params.line_gap) >= params.line_ratio
    lv = line_response(p, "col", params.line_gap) >= params.line_ratio
    arms = np.zeros_like(comp)
    centres = []
    for i in order:
        r, c = int(rs[i]), int(cs[i])
        half = [_walk(comp, lh, r, c, 0, -1, params), _walk(comp, lh, r, c, 0, 1, params),
                _walk(comp, lv, r, c, -1, 0, params), _walk(comp, lv, r, c, 1, 0, params)]
        if sum(1 for a in half if a) >= params.min_half_arms \
                and max(len(a) for a in half) >= params.min_arm_px:
            centres.append((r, c))
            for a in half:
                for rr, cc in a:
                    arms[rr, cc] = True
    if not centres:
        return {"sidelobes": False, "core": comp.copy(), "centres": [], "arm_px": 0}
    keep = comp & ~arms
    # an arm running inside the hull: both neighbours across it are kept -> the pixel is hull
    kp = np.pad(keep, 1)
    across_h = kp[:-2, 1:-1] & kp[2:, 1:-1]         # above and below (row arms)
    across_v = kp[1:-1, :-2] & kp[1:-1, 2:]         # left and right (column arms)
    keep |= arms & comp & (across_h | across_v)
    for r, c in centres:
        keep[r, c] = True
    lab, _ = ndi.label(keep, structure=np.ones((3, 3), bool))
    core = lab == lab[centres[0]]
    removed = int((comp & ~core).sum())
    return {"sidelobes": removed > 0, "core": core if removed > 0 else comp.copy(), "centres": centres,
            "arm_px": int((arms & ~core).sum())}


def component_in_window(mask: np.ndarray, peak: tuple[int, int], merge_r: int) -> np.ndarray:
    """The detection's pixels in a mask window: the mask pixels joined to the peak pixel by
    the merge rule of :func:`sarship.pipeline.components.tile_components` (pixels within a
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


def refine_features(feats: list[dict], records: np.ndarray, read_power: Callable[[int, int, int, int], np.ndarray],
                    read_mask: Callable[[int, int, int, int], np.ndarray], shape: tuple[int, int], merge_r: int,
                    spacing: tuple[float, float] | None, geo: dict | None,
                    params: SidelobeParams = SidelobeParams()) -> list[dict]:
    """Detections with their sidelobes suppressed (the properties of docs/interfaces/files.md).

    For each detection (``feats[i]`` built from ``records[i]``): its window (bounding box +
    ``margin_px``) is read (``read_power(ra, rb, ca, cb)``: what the detector read, made pixel
    power by :func:`sarship.pipeline.inputs.pixel_power`; ``read_mask``: the detection mask), the cross and the core found (:func:`refine`); with sidelobes the
    core's geometry (``centroid_px``, ``length_px``, ``width_px``, ``heading_deg``,
    ``length_m``, ``width_m`` and the outline) replaces the component's, whose values are
    kept as ``<name>_raw``. Every detection gets ``sidelobes: true|false``. Detections whose
    peak is under ``scatterer_ratio`` times their mean hold no scatterer and are not read.
    """
    from sarship.pipeline.inputs import pixel_power
    from sarship.pipeline.ship_features import features

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
        bb[int(rec["r0"]) - ra:int(rec["r1"]) - ra, int(rec["c0"]) - ca:int(rec["c1"]) - ca] = True
        comp &= bb
        res = refine(power, comp, params)
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
