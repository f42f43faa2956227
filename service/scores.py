"""Scores of a finished job against the scene's ground truth, when the scene has one.

The truth convention is ``sarship simulate``'s: a GeoJSON beside the store named
``<scene path>.truth.geojson`` (the simulator also records that file's name in the scene's
``truth`` attribute, which is honoured when it names a file beside the store). The scores are
:func:`sarship.pipeline.products.scoring.evaluate`'s, exactly what ``sarship evaluate DETECTIONS --truth TRUTH``
prints with ``--json`` (n_truth, n_hit, pd, precision, fom, f1, ...), computed once and cached in
the job folder (``scores.json``, written atomically).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from sarship.service.cache import build_once

log = logging.getLogger("sarship.service")


def truth_path(run: dict[str, Any]) -> Path | None:
    """The scene's truth file, or None (see the module doc)."""
    scene = Path(run["scene"]["path"])
    cands = [Path(f"{scene}.truth.geojson")]
    name = (run["scene"].get("attrs") or {}).get("truth")
    if isinstance(name, str) and name and Path(name).name == name and name not in (".", ".."):
        cands.append(scene.parent / name)  # a file name only: never a path out of the scene's folder
    return next((p for p in cands if p.is_file()), None)


def job_scores(job_dir: Path, run: dict[str, Any]) -> dict[str, Any] | None:
    """The job's scores (cached in ``JOB/scores.json``), or None when the scene has no truth.

    A truth file that cannot be read is reported as ``{"error": ...}`` rather than failing the
    metrics request (the detections are fine; the truth beside the scene is not)."""
    truth = truth_path(run)
    if truth is None:
        return None

    def build(tmp: Path) -> None:
        from sarship.pipeline.errors import InputError
        from sarship.pipeline.products.scoring import evaluate

        try:
            scores = evaluate(job_dir / "detections.geojson", truth, mask_path=job_dir / "mask.zarr")
        except InputError as exc:
            log.warning("scores of %s: %s", job_dir.name, exc)
            scores = {"error": str(exc), "truth": str(truth)}
        tmp.write_text(json.dumps(scores, indent=1, allow_nan=False))

    doc: dict[str, Any] = json.loads(build_once(job_dir / "scores.json", build).read_text())
    return doc
