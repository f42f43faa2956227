"""The refine stage: from the merged, discriminated detections to the features a run writes.

In order (each step as docs/interfaces/files.md describes its properties): detections within
``land_gap_px`` of the land mask dropped (:func:`sarship.pipeline.targets.lines.near_land`); the
features of each detection (:func:`~sarship.pipeline.targets.ship_features.features`) and its
target-to-clutter ratio against the sea mean; its local contrast and the ``min_contrast_db``
rule (:mod:`sarship.pipeline.targets.local_contrast`); cross-sidelobe suppression
(:mod:`sarship.pipeline.targets.sidelobes`); the detector's own per-detection properties
(``DetectorSpec.detection_properties``); the WGS84 outline and centre
(:func:`~sarship.pipeline.targets.ship_features.geolocate`); the azimuth-ambiguity flags
(:mod:`sarship.pipeline.targets.ambiguity`). The per-detection steps read small windows of the scene
and of the detector's decision through block caches, each chunk once.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.run.plan import Plan
from sarship.pipeline.targets.ambiguity import flag_features
from sarship.pipeline.targets.lines import near_land
from sarship.pipeline.targets.local_contrast import (
    GAP_PX,
    MIN_RING_PX,
    RING_PX,
    Reader,
    add_local_contrast,
    keep_contrast,
)
from sarship.pipeline.targets.ship_features import add_contrast, features, geolocate
from sarship.pipeline.targets.sidelobes import refine_features
from sarship.pipeline.tiling.inputs import make_reader, pixel_power, window_reader
from sarship.pipeline.tiling.window_cache import CachedWindows


@dataclass(frozen=True)
class Refined:
    """The refine stage's output: the detections' features (GeoJSON features), their records,
    the ``run.json`` records of the contrast and ambiguity steps, and what each rule dropped."""

    features: list[dict[str, Any]]
    records: np.ndarray
    contrast: dict[str, Any]
    ambiguities: dict[str, Any]
    dropped_land: int | None  # None when the land-gap rule did not run
    dropped_contrast: int


def contrast_step(
    feats: list[dict[str, Any]],
    records: np.ndarray,
    floor: float | None,
    scene_read: Reader | None,
    mask_read: Reader | None,
    land_path: Path | None,
    shape: tuple[int, int],
    nodata: float | None,
) -> tuple[list[dict[str, Any]], np.ndarray, dict[str, Any]]:
    """The local contrast of every detection and the ``min_contrast_db`` rule
    (pipeline/targets/local_contrast.py): (kept features, their records, the ``run.json`` record).
    Measured only when a floor is set (a window read per detection; -30 dB measures every
    detection and drops practically none); otherwise ``contrast_db`` is null."""
    if floor is None:
        for f in feats:
            f["properties"].update(contrast_db=None, contrast_ring_px=None)
        return feats, records, {"min_contrast_db": None, "measured": False}
    assert scene_read is not None and mask_read is not None  # refine() makes both when a floor is set
    land_read = CachedWindows(window_reader(land_path), shape) if land_path is not None else None
    feats = add_local_contrast(
        feats, lambda *w: pixel_power(np.asarray(scene_read(*w))), mask_read, shape, land_read, nodata
    )
    keep = keep_contrast(feats, floor)
    record = {
        "min_contrast_db": floor,
        "measured": True,
        "gap_px": GAP_PX,
        "ring_px": RING_PX,
        "min_ring_px": MIN_RING_PX,
        "land_excluded": land_path is not None,
        "unmeasured": sum(f["properties"]["contrast_db"] is None for f in feats),
        "dropped": len(keep) - sum(keep),
    }
    return [f for f, k in zip(feats, keep) if k], records[np.asarray(keep, bool)], record


def refine(
    plan: Plan,
    prep: dict[str, Any],
    records: np.ndarray,
    land_record: dict[str, Any] | None,
    land_path: Path | None,
    detected_path: Path,
) -> Refined:
    """The stage (module docstring). ``prep``: the detector's prepared values with the scene
    pass's; ``land_path``: the run's land array (None without a land mask); ``detected_path``:
    the detector's decision (``mask.zarr/detected``)."""
    params, spec, shape, spacing, geo = plan.params, plan.spec, plan.shape, plan.spacing, plan.geo
    dropped_land: int | None = None
    if params.land_gap_px is not None and land_path is not None and len(records):
        near = near_land(records, CachedWindows(window_reader(land_path), shape), shape, params.land_gap_px)
        records, dropped_land = records[~near], int(near.sum())
    feats = features(records, spacing, geo)
    feats = add_contrast(feats, (land_record or {}).get("sea_mean"))
    scene_read: Reader | None = None
    mask_read: Reader | None = None
    if params.sidelobes or spec.detection_properties is not None or params.min_contrast_db is not None:
        # the mask these steps read is the detector's own decision (each detection's component,
        # and the detections left out of the clutter ring)
        scene_read = CachedWindows(make_reader(str(plan.scene.path), plan.var, plan.transform), shape)
        mask_read = CachedWindows(window_reader(detected_path), shape)
    feats, records, contrast = contrast_step(
        feats, records, params.min_contrast_db, scene_read, mask_read, land_path, shape, getattr(params, "nodata", None)
    )
    if params.sidelobes:  # cross-sidelobe suppression on the detections (pipeline/targets/sidelobes.py)
        assert scene_read is not None and mask_read is not None  # made above when params.sidelobes
        feats = refine_features(feats, records, scene_read, mask_read, shape, plan.merge_r, spacing, geo)
    if spec.detection_properties is not None:  # the detector's own per-detection properties (e.g. csk)
        feats = spec.detection_properties(
            feats, records, scene_read, mask_read, shape, plan.merge_r, params, prep, spacing=spacing, geo=geo
        )
    feats = geolocate(feats, geo)  # WGS84 outline + centre of the final geometry
    feats, ambiguities = flag_features(
        feats, plan.scene.attrs, params.ambiguities, params.ambiguity_tol_px, params.ambiguity_min_db
    )
    return Refined(feats, records, contrast, ambiguities, dropped_land, contrast.get("dropped", 0))
