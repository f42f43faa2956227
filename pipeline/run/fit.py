"""``run.json``'s ``model_fit``: does the detector's clutter model fit the scene (pipeline/stats/model_fit.py)?

From the tiles' exceedance flags on the scene's sample grid (the plan's ``fit`` settings), the
cells of the kept detections left out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sarship.pipeline.run.plan import Plan
from sarship.pipeline.stats import model_fit


def fit_record(plan: Plan, results: list[dict[str, Any]], records: np.ndarray) -> dict[str, Any]:
    """The record (module docstring); ``results``: the tiles' results, ``records``: the kept
    detections' records. Called only for a plan whose fit is measured (``plan.fit`` set)."""
    fit = plan.fit
    assert fit is not None  # the callers (sarship.workers.jobs) check plan.fit first
    stride = int(fit["stride"])
    grid = model_fit.assemble((r["fit"] for r in results), plan.shape, stride)
    boxes = (
        np.stack([records["r0"], records["c0"], records["r1"], records["c1"]], axis=1)
        if len(records)
        else np.empty((0, 4), np.int64)
    )
    excluded = model_fit.exclude_targets(grid, stride, boxes)
    rec = model_fit.record(plan.detector, grid, model_fit.pfas_of(plan.params.pfa), stride, excluded)
    # whose decision the probe PFA's exceedances are: the detector's, or its model's (MODEL_PROBE)
    rec["probe_by"] = fit["probes"][0].get("detector") or plan.detector if fit["probes"] else plan.detector
    return rec
