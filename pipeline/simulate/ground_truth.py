"""Ground truth of a simulated scene: the ship catalogue and the truth GeoJSON collection.

(Not to be confused with :mod:`sarship.pipeline.products.truth`.)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sarship.pipeline.simulate.ais_vessels import ais_member, ais_properties
from sarship.pipeline.simulate.artefacts import AMBIG_LEVEL_DB
from sarship.pipeline.simulate.clutter import SEA_EPS, SEA_GAMMA, SEA_RHO, _sea_power
from sarship.pipeline.simulate.config import SimConfig, validate
from sarship.pipeline.simulate.fields import BLOCK
from sarship.pipeline.simulate.model import _Model, _model
from sarship.pipeline.simulate.motion import motion_properties
from sarship.pipeline.simulate.render import _ghost_render, _render_block
from sarship.pipeline.simulate.ships import SHIP_CLASSES, _ship_geometry


def _power(data: dict[str, np.ndarray], kind: str) -> np.ndarray:
    """Pixel power: intensity, |hh|^2, or span |hh|^2 + 2|hv|^2 + |vv|^2 (float32)."""
    if kind == "intensity":
        return np.asarray(data["intensity"], dtype=np.float32)

    def p(z):
        return z.real * z.real + z.imag * z.imag

    if kind == "slc":
        return p(data["hh"])
    hv = p(data["hv"])
    return p(data["hh"]) + (hv + hv) + p(data["vv"])


def ship_catalogue(cfg: SimConfig) -> list[dict[str, Any]]:
    """The ships of the scene (deterministic for the config), JSON-serialisable dicts.

    Each: ``id``, the truth geometry (``bbox_px``, ``centroid_px``, ``area_px``, ``length_px``,
    ``width_px``, ``heading_deg`` in [0, 180) clockwise from image up), ``length_m``,
    ``width_m``, ``center_px`` (design centre), ``bow_deg`` (bow direction in [0, 360)),
    ``scr_db``, ``mean_power`` (designed mean power over the ship pixels), ``pol_class`` and
    ``pol_signature`` (quad-pol: hull eps, gamma, rho), ``scatterers`` (dominant point
    scatterers: row, col, power, type); with ``moving`` or ``ais`` also the motion
    (:func:`~sarship.pipeline.simulate.motion.motion_properties`; ``center_px`` is then where
    the ship is imaged).
    """
    cfg = validate(cfg)
    m = _model(cfg)
    out = []
    for s in m.ships:
        d = {
            "id": s.idx,
            **_ship_geometry(cfg, s),
            "center_px": [s.rc, s.cc],
            "bow_deg": s.bow_deg,
            "scr_db": s.scr_db,
            "mean_power": float(_sea_power(cfg) * 10.0 ** (s.scr_db / 10.0)),
            "pol_class": s.pol_class,
        }
        if s.pol_class is not None:
            c = SHIP_CLASSES[s.pol_class]
            d["pol_signature"] = {"eps": c["eps"], "gamma": c["gamma"], "rho": c["rho"]}
        if s.sog_kn is not None:
            d.update(motion_properties(cfg, s))
        dom = s.dom
        d["scatterers"] = [
            {
                "row": int(dom["row"][j]),
                "col": int(dom["col"][j]),
                "power": float(dom["power"][j]),
                "type": ("dihedral" if dom["dihedral"][j] else "trihedral") if cfg.kind == "quadpol" else "point",
            }
            for j in range(dom["row"].size)
        ]
        out.append(d)
    return out


def _new_ship_buffers(m: _Model) -> dict[int, np.ndarray]:
    return {s.idx: np.zeros(s.mask.shape, dtype=np.float32) for s in m.ships}


def _ship_boxes(m: _Model) -> np.ndarray:
    if m.boxes is None:
        m.boxes = np.array([[s.r0, s.r1, s.c0, s.c1] for s in m.ships], dtype=np.int64).reshape(-1, 4)
    return m.boxes


def _collect_tile(m: _Model, bufs: dict[int, np.ndarray], data: dict[str, np.ndarray], r0: int, c0: int) -> None:
    """Copy the power of the ship pixels of a window (origin r0, c0) into the ship buffers."""
    r1 = r0 + next(iter(data.values())).shape[0]
    c1 = c0 + next(iter(data.values())).shape[1]
    b = _ship_boxes(m)
    hit = np.flatnonzero((b[:, 0] < r1) & (b[:, 1] > r0) & (b[:, 2] < c1) & (b[:, 3] > c0))
    for i in hit:
        s = m.ships[int(i)]
        a0, a1, b0, b1 = max(r0, s.r0), min(r1, s.r1), max(c0, s.c0), min(c1, s.c1)
        if a0 < a1 and b0 < b1:
            sub = {k: v[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] for k, v in data.items()}
            bufs[s.idx][a0 - s.r0 : a1 - s.r0, b0 - s.c0 : b1 - s.c0] = _power(sub, m.cfg.kind)


def _ship_buffers_by_blocks(m: _Model) -> dict[int, np.ndarray]:
    bufs = _new_ship_buffers(m)
    need = sorted(
        {
            (bi, bj)
            for s in m.ships
            for bi in range(s.r0 // BLOCK, (s.r1 - 1) // BLOCK + 1)
            for bj in range(s.c0 // BLOCK, (s.c1 - 1) // BLOCK + 1)
        }
    )
    for bi, bj in need:
        blk = _render_block(m, bi, bj)
        _collect_tile(m, bufs, blk, bi * BLOCK, bj * BLOCK)
    return bufs


def _truth(m: _Model, bufs: dict[int, np.ndarray]) -> dict[str, Any]:
    cfg = m.cfg
    feats = []
    for s in m.ships:
        v = bufs[s.idx][s.mask]
        props = {
            "id": s.idx,
            **_ship_geometry(cfg, s),
            "peak": float(v.max()),
            "mean": float(v.astype(np.float64).mean()),
            "score": None,
            "scr_db": round(s.scr_db, 6),
            "difficult": False,
        }
        if s.pol_class is not None:
            props["pol_class"] = s.pol_class
        if s.sog_kn is not None:  # moving / ais (issue 33)
            props.update(motion_properties(cfg, s))
        if cfg.ais:
            props.update(ais_properties(cfg, s.idx))
        feats.append({"type": "Feature", "id": s.idx, "geometry": None, "properties": props})
    H, W = cfg.shape
    p_sea = _sea_power(cfg)
    amb = []
    for k, g in enumerate(m.ghosts):
        s = m.ships[g["ship"]]
        arr = _ghost_render(cfg, k)
        pw = _power(arr, cfg.kind)
        r0, r1 = g["r0"], g["r0"] + pw.shape[0]
        a0, a1 = max(r0, 0), min(r1, H)
        b0, b1 = max(g["c0"], 0), min(g["c0"] + pw.shape[1], W)
        peak = float(pw[a0 - r0 : a1 - r0, b0 - g["c0"] : b1 - g["c0"]].max())
        rr, cc = np.nonzero(s.mask)
        amb.append(
            {
                "source_id": s.idx,
                "ambiguity_of": s.idx,
                "order": g["order"],
                "offset_rows": g["offset"],
                "offset_cols": g["offset_cols"],
                "bbox_px": [a0, b0, a1, b1],
                "centroid_px": [
                    float(s.r0 + rr.mean() + 0.5 + g["offset"]),
                    float(s.c0 + cc.mean() + 0.5 + g["offset_cols"]),
                ],
                "level_db": AMBIG_LEVEL_DB,
                "peak_db_over_clutter": float(10 * math.log10(max(peak, 1e-30) / p_sea)),
            }
        )
    coll: dict[str, Any] = {
        "type": "FeatureCollection",
        "features": feats,
        "simulation": cfg.as_dict(),
        "ambiguities": amb,
        "clutter": {
            "model": cfg.clutter,
            "looks": m.looks,
            "mean": cfg.clutter_mean,
            "power_definition": {"intensity": "intensity", "slc": "|hh|^2", "quadpol": "|hh|^2 + 2|hv|^2 + |vv|^2"}[
                cfg.kind
            ],
            "mean_power": p_sea,
        },
    }
    if cfg.clutter in ("k", "g0"):
        coll["clutter"].update({"texture_shape": cfg.texture_shape, "texture_corr_px": cfg.texture_corr_px})
    if cfg.clutter == "ggd":
        coll["clutter"].update({"ggd_power": cfg.ggd_power, "ggd_shape": cfg.ggd_shape})
    if cfg.kind == "quadpol":
        coll["clutter"]["sea_covariance"] = {"eps": SEA_EPS, "gamma": SEA_GAMMA, "rho": [SEA_RHO.real, SEA_RHO.imag]}
    if m.rfi:
        coll["rfi"] = [{k: ev[k] for k in ("id", "rows", "cols", "level_db")} for ev in m.rfi]
    if m.land is not None and m.land.side == "gshhg":
        coll["land"] = {"side": "gshhg", "source": "GSHHG shoreline (land_mask=coastline, no buffer)"}
    elif m.land is not None:
        coll["land"] = {"side": m.land.side, "mean_depth_px": m.land.depth}
    if m.sources:
        coll["sidelobes"] = [
            {"source_id": sl["ship"], "row": sl["row"], "col": sl["col"], "extent_px": sl["n"]} for sl in m.sources
        ]
    if m.stripes is not None:
        coll["stripes"] = True
    if cfg.ais:
        coll["ais"] = ais_member(cfg)
    return coll


def truth_collection(cfg: SimConfig) -> dict[str, Any]:
    """The truth GeoJSON FeatureCollection (docs/interfaces/files.md) of the scene.

    One Feature per ship (geometry null: the scene is not georeferenced); ``peak`` and
    ``mean`` are statistics of the rendered power (clutter + ship + artefacts) over the
    ship's pixels. Top-level members: ``simulation`` (the config), ``ambiguities`` (azimuth
    ghosts, not ships), ``clutter`` and, where enabled, ``rfi``, ``land``, ``sidelobes``.
    """
    cfg = validate(cfg)
    m = _model(cfg)
    return _truth(m, _ship_buffers_by_blocks(m))
