"""The scene model: ships, land, sidelobe sources, ghosts, RFI and stripes of a configuration.

Built once per configuration (:func:`_model`, cached) from the seeded streams of each
component, with the items bucketed by the :data:`~sarship.pipeline.simulate.fields.BLOCK`
blocks they touch.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.simulate.artefacts import (
    AMBIG_SMEAR,
    SIDELOBE_FLOOR,
    SIDELOBE_MAX_PX,
    SIDELOBE_MIN,
    SIDELOBE_OS,
    _rfi_events,
    _stripes_gain,
)
from sarship.pipeline.simulate.clutter import SEA_EPS, SEA_GAMMA, _sea_power, _span_factor, effective_looks
from sarship.pipeline.simulate.config import SimConfig
from sarship.pipeline.simulate.fields import BLOCK
from sarship.pipeline.simulate.geometry import ghost_offsets
from sarship.pipeline.simulate.land import _Land, _land_model
from sarship.pipeline.simulate.motion import draw_motion
from sarship.pipeline.simulate.ships import _dominants, _hull_pattern, _place_ships, _Ship


@dataclass
class _Model:
    cfg: SimConfig
    looks: float
    ships: list[_Ship]
    land: _Land | None
    stripes: np.ndarray | None
    rfi: list[dict[str, Any]]
    sources: list[dict[str, Any]]
    ghosts: list[dict[str, Any]]
    buckets: dict[tuple[int, int], list[tuple[str, int, int, int, int, int]]]
    boxes: np.ndarray | None = None


def _build_model(cfg: SimConfig) -> _Model:
    H, W = cfg.shape
    land = _land_model(cfg) if cfg.land else None
    ships = _place_ships(cfg, land, draw_motion(cfg))
    p_sea = _sea_power(cfg)
    sf = _span_factor(SEA_EPS, SEA_GAMMA) if cfg.kind == "quadpol" else 1.0
    for s in ships:
        s.dom = _dominants(cfg, s)
        hull = _hull_pattern(cfg, s)
        total = float(hull.sum() + s.dom["rel"].sum())
        target = cfg.clutter_mean * sf * 10.0 ** (s.scr_db / 10.0)
        s.scale = target * int(s.mask.sum()) / total
        s.dom["power"] = s.dom["rel"] * s.scale
    sources: list[dict[str, Any]] = []
    if cfg.sidelobes:
        for s in ships:
            d = s.dom
            for j in range(d["row"].size):
                p = float(d["power"][j])
                if p < SIDELOBE_MIN * p_sea:
                    continue
                n = int(
                    min(SIDELOBE_MAX_PX, math.ceil(SIDELOBE_OS / math.pi * math.sqrt(p / (SIDELOBE_FLOOR * p_sea))))
                )
                sources.append(
                    {
                        "ship": s.idx,
                        "j": j,
                        "row": int(d["row"][j]),
                        "col": int(d["col"][j]),
                        "dr": float(d["dr"][j]),
                        "dc": float(d["dc"][j]),
                        "power": p,
                        "n": n,
                    }
                )
    ghosts: list[dict[str, Any]] = []
    if cfg.ambiguities:  # eqs. 1-3 of pipeline/targets/ambiguity.py with the simulated sensor (simulate/geometry.py)
        for s in ships:
            rr, cc = np.nonzero(s.mask)
            cr, ccol = s.r0 + rr.mean() + 0.5, s.c0 + cc.mean() + 0.5
            for k, drow, dcol in ghost_offsets(cfg.shape, cfg.pixel_spacing_m, cr, ccol):
                g0, g1 = s.r0 + drow - AMBIG_SMEAR, s.r1 + drow + AMBIG_SMEAR
                c0, c1 = s.c0 + dcol, s.c1 + dcol
                if g1 <= 0 or g0 >= H or c1 <= 0 or c0 >= W:
                    continue
                ghosts.append({"ship": s.idx, "order": k, "offset": drow, "offset_cols": dcol, "r0": g0, "c0": c0})
    rfi = _rfi_events(cfg) if cfg.rfi else []
    stripes = _stripes_gain(cfg) if cfg.stripes else None

    buckets: dict[tuple[int, int], list[tuple[str, int, int, int, int, int]]] = {}

    def add(item: str, idx: int, r0: int, r1: int, c0: int, c1: int) -> None:
        r0, r1, c0, c1 = max(r0, 0), min(r1, H), max(c0, 0), min(c1, W)
        if r0 >= r1 or c0 >= c1:
            return
        for bi in range(r0 // BLOCK, (r1 - 1) // BLOCK + 1):
            for bj in range(c0 // BLOCK, (c1 - 1) // BLOCK + 1):
                buckets.setdefault((bi, bj), []).append((item, idx, r0, r1, c0, c1))

    for s in ships:
        add("ship", s.idx, s.r0, s.r1, s.c0, s.c1)
    for k, src in enumerate(sources):
        r, c, n = src["row"], src["col"], src["n"]
        add("slr", k, r, r + 1, c - n, c + n + 1)  # along the row (range sidelobes)
        add("slc", k, r - n, r + n + 1, c, c + 1)  # along the column (azimuth sidelobes)
    for k, g in enumerate(ghosts):
        s = ships[g["ship"]]
        add("ghost", k, g["r0"], g["r0"] + s.mask.shape[0] + 2 * AMBIG_SMEAR, g["c0"], g["c0"] + s.mask.shape[1])
    for k, ev in enumerate(rfi):
        add("rfi", k, ev["rows"][0], ev["rows"][1], ev["cols"][0], ev["cols"][1])
    return _Model(
        cfg=cfg,
        looks=effective_looks(cfg),
        ships=ships,
        land=land,
        stripes=stripes,
        rfi=rfi,
        sources=sources,
        ghosts=ghosts,
        buckets=buckets,
    )


@functools.lru_cache(maxsize=4)
def _model(cfg: SimConfig) -> _Model:
    return _build_model(cfg)
