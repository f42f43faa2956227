"""``sarship match RUN_DIR --ais FILE ...``: a finished run's detections matched to AIS again,
without detecting again (docs/ais.md).

Everything the AIS stage needs is in the run's own files: the detections (``centroid_px``,
``centroid_lonlat``, ``length_m``) in ``detections.geojson``, and the scene's attributes (its
georeference, ``sar_geometry`` with the line times), shape, spacing and the run's size rule in
``run.json``, so the scene store need not be there any more. The stage
(:func:`~sarship.pipeline.run.ais.ais_stage`) then rewrites ``detections.geojson`` (each
feature's ``ais`` and ``dark``), ``ais_unmatched.geojson`` and ``run.json``'s ``ais`` record, each
written whole to a temporary file and renamed into place, ``run.json`` last.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sarship.pipeline.errors import InputError
from sarship.pipeline.run.ais import ais_options, ais_stage
from sarship.pipeline.targets.ship_features import collection, write_json

#: the files of a run that ``sarship match`` reads
RUN_FILES = ("detections.geojson", "run.json")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (not a run folder of sarship detect?)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable as JSON ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: not a JSON object")
    return data


def rematch(run_dir: str | Path, ais: Sequence[str | Path], *, overwrite: bool = False) -> dict[str, Any]:
    """Match the detections of the run in ``run_dir`` to the AIS files ``ais`` (module doc);
    returns ``run.json``'s new ``ais`` record. A run that already has one is refused unless
    ``overwrite``; every check runs before anything is written."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder")
    dets, run = (_read_json(run_dir / name) for name in RUN_FILES)
    scene = run.get("scene")
    features = dets.get("features")
    if not isinstance(scene, dict) or not isinstance(scene.get("attrs"), dict) or not isinstance(features, list):
        raise InputError(f"{run_dir}: run.json has no scene record or detections.geojson no features")
    if "ais" in run and not overwrite:
        raise InputError(
            f"{run_dir}: the run was already matched to AIS (run.json 'ais'): add --overwrite to match again"
        )
    attrs = scene["attrs"]
    geo = {k: attrs[k] for k in ("crs", "transform", "gcps") if k in attrs}
    opts = ais_options(list(ais), attrs, geo)
    if opts is None:
        raise InputError("sarship match needs at least one --ais FILE")
    spacing = scene.get("ground_spacing_m")
    out = ais_stage(
        opts,
        attrs,
        geo,
        (int(scene["shape"][0]), int(scene["shape"][1])),
        features,
        min_length_m=(run.get("parameters") or {}).get("min_length_m"),
        spacing=(float(spacing[0]), float(spacing[1])) if spacing else None,
    )
    write_json(run_dir / "ais_unmatched.geojson", collection(out.unmatched, scene=scene.get("path")))
    write_json(run_dir / "detections.geojson", dets)
    run["ais"] = out.record
    outputs = run.get("outputs")
    if isinstance(outputs, dict):
        outputs["ais_unmatched.geojson"] = str((run_dir / "ais_unmatched.geojson").resolve())
    write_json(run_dir / "run.json", run)
    return out.record


__all__ = ["rematch"]
