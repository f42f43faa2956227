"""The merge stage's rules on whole detections: after the tiles' components are joined across tiles.

:func:`discriminate` applies, in order, the area rule the tiles applied to their pieces
(:func:`~sarship.pipeline.targets.ship_features.size_prefilter`), the line rule on the pieces before the
shape test (:func:`sarship.pipeline.targets.lines.discard_lines`: collinear pieces of long bright lines
and azimuth smear), the whole size and shape rule
(:func:`~sarship.pipeline.targets.ship_features.keep_mask`), then the detector's own rules on whole
components (``DetectorSpec.discriminate``, e.g. ``gamma_mrf``'s peak rule). It returns the kept
records and what each rule dropped (``run.json`` ``discarded``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sarship.pipeline.detectors.base import DetectorParams
from sarship.pipeline.run.plan import Plan
from sarship.pipeline.targets.lines import discard_lines
from sarship.pipeline.targets.ship_features import keep_mask, size_prefilter


def size_and_lines(
    records: np.ndarray, params: DetectorParams, spacing: tuple[float, float] | None, tile_size_dropped: int
) -> tuple[np.ndarray, dict[str, int]]:
    """The size, shape and line rules (module docstring) on the merged components; returns the
    kept records and the count each rule dropped (``tile_size_dropped``: those the tiles
    dropped already; ``detector``, ``land`` and ``contrast`` start at 0)."""
    pre = size_prefilter(params, params.line_gap_px is not None)
    keep = keep_mask(records, pre, spacing) if pre is not params else np.ones(len(records), bool)
    size = tile_size_dropped + int(len(keep) - keep.sum())
    records = records[keep]
    reason = discard_lines(
        records,
        params.line_gap_px,
        params.line_angle_deg,
        params.line_dominant_db,
        params.max_elongation,
        params.max_length_m,
        spacing,
    )
    counts = {"line": int((reason == "line").sum()), "smear": int((reason == "smear").sum())}
    records = records[reason == ""]
    keep = keep_mask(records, params, spacing)
    counts = {"size": size + int(len(keep) - keep.sum()), **counts, "detector": 0, "land": 0, "contrast": 0}
    return records[keep], counts


def discriminate(
    plan: Plan, prep: dict[str, Any], merged: np.ndarray, tile_size_dropped: int
) -> tuple[np.ndarray, dict[str, int]]:
    """The stage (module docstring): the kept records and ``discarded``. ``prep``: the detector's
    prepared values with the scene pass's."""
    records, discarded = size_and_lines(merged, plan.params, plan.spacing, tile_size_dropped)
    if plan.spec.discriminate is not None:  # the detector's own rules on whole components (e.g. peak)
        n0 = len(records)
        records = records[plan.spec.discriminate(records, plan.params, prep)]
        discarded["detector"] = n0 - len(records)
    return records, discarded
