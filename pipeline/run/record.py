"""The record stage: ``run.json`` (docs/interfaces/files.md) from the plan and what each stage returned.

:class:`Outcome` gathers what the stages that ran on the cluster returned (the prepared values
after the scene pass, the land record, the tiles' results, the merge's and the refine stage's
outputs, the placement, the timings); :func:`run_record` lays them out as ``run.json``, a
:class:`RunRecord`. Pure: no I/O.
"""

from __future__ import annotations

import contextlib
import functools
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from sarship.pipeline import __version__
from sarship.pipeline.run.ais import AisOutcome
from sarship.pipeline.run.outputs import AIS_OUTPUT, OPTIONAL_OUTPUTS, OUTPUTS
from sarship.pipeline.run.plan import Plan
from sarship.pipeline.run.refine import Refined

#: The per-tile timings ``run.json`` keeps (seconds, rounded to the microsecond).
TILE_TIMINGS = ("read_s", "land_s", "detect_s", "write_s", "label_s", "h2d_s", "d2h_s")


class RunRecord(TypedDict, total=False):
    """``run.json``: the keys every run writes (docs/interfaces/files.md, "run.json"), in order;
    ``detector_auto`` only for ``--detector auto``, ``ais`` only with AIS files."""

    sarship_version: str
    detector: str
    reference: str
    parameters: dict[str, Any]
    channel: Any
    looks_source: str
    size_rule: str
    prepared: dict[str, Any]
    scene_pass: dict[str, Any] | None
    land: dict[str, Any] | None
    contrast: dict[str, Any]
    ambiguities: dict[str, Any]
    model_fit: dict[str, Any] | None
    detector_auto: dict[str, Any]
    ais: dict[str, Any]
    scene: dict[str, Any]
    tiles: dict[str, Any]
    detections: int
    detected_px: int
    mask_px: int
    discarded: dict[str, int]
    timings: dict[str, Any]
    device: str
    device_requested: str
    placement: dict[str, Any]
    cluster: dict[str, Any]
    versions: dict[str, str]
    warnings: list[str]
    outputs: dict[str, str]


class RunExtras(TypedDict, total=False):
    """The entries a caller adds to ``run.json`` after ``model_fit`` (:attr:`Outcome.extra`):
    ``detector_auto`` for ``--detector auto``."""

    detector_auto: dict[str, Any]


@dataclass
class Outcome:
    """What the stages after the plan returned (module docstring)."""

    prep: dict[str, Any]
    scene_pass: dict[str, Any] | None
    land: dict[str, Any] | None
    results: list[dict[str, Any]]
    refined: Refined
    discarded: dict[str, int]
    model_fit: dict[str, Any] | None
    kept_px: int
    tiles: int
    device: str
    placement_reason: str
    restriction: dict[str, Any]
    dashboard: str | None
    warnings: list[str]
    timings: dict[str, Any]
    extra: RunExtras = field(default_factory=RunExtras)
    ais: AisOutcome | None = None


def versions() -> dict[str, str]:
    """The versions of sarship, Python and the packages that decide a run's numbers (read from
    the installed metadata once per process: the code a process runs does not change with a
    later install, and the read costs 0.1-0.25 s; nothing is imported)."""
    return dict(_versions())


@functools.lru_cache(maxsize=1)
def _versions() -> tuple[tuple[str, str], ...]:
    import importlib.metadata as md

    out = {"sarship": __version__, "python": platform.python_version()}
    for pkg in ("numpy", "scipy", "numba", "dask", "distributed", "zarr", "xarray", "pydantic"):
        with contextlib.suppress(Exception):
            out[pkg] = md.version(pkg)
    return tuple(out.items())


def _scene(plan: Plan) -> dict[str, Any]:
    s = plan.scene
    H, W = plan.shape
    return {
        "path": str(Path(s.path).resolve()),
        "shape": [H, W],
        "kind": s.kind,
        "tile": s.tile,
        "looks": s.looks,
        "pixel_spacing_m": list(s.pixel_spacing_m) if s.pixel_spacing_m else None,
        "ground_spacing_m": list(plan.spacing) if plan.spacing else None,
        "attrs": {k: v for k, v in s.attrs.items() if k not in ("simulation",)},
    }


def _tiles(plan: Plan, o: Outcome) -> dict[str, Any]:
    H, W = plan.shape
    return {
        "size": plan.tile,
        "size_source": plan.tile_source,
        "grid": [math.ceil(H / plan.tile), math.ceil(W / plan.tile)],
        "count": o.tiles,
        "halo_px": plan.halo,
        "merge_radius_px": plan.merge_r,
        "per_tile": [
            {
                "index": list(r["index"]),
                "worker": r["worker"],
                "device": r["device"],
                "detected_px": r["detected_px"],
                "block_from": r.get("block_from", "scene"),
                **{k: round(r[k], 6) for k in TILE_TIMINGS},
            }
            for r in sorted(o.results, key=lambda r: r["index"])
        ],
    }


def run_record(plan: Plan, o: Outcome, tmp: Path) -> RunRecord:
    """``run.json`` (module docstring); ``tmp``: the run's temporary folder, whose optional
    outputs (``land.zarr``) are listed only when written."""
    var = plan.var
    return RunRecord(
        sarship_version=__version__,
        detector=plan.detector,
        reference=plan.spec.reference,
        parameters=plan.params.model_dump(),
        channel=var if isinstance(var, str) else list(var),
        looks_source=plan.looks_source,
        size_rule=plan.size_rule,
        prepared=o.prep,
        scene_pass=o.scene_pass,
        land=o.land,
        contrast=o.refined.contrast,
        ambiguities=o.refined.ambiguities,
        model_fit=o.model_fit,
        **o.extra,
        **({"ais": o.ais.record} if o.ais is not None else {}),
        scene=_scene(plan),
        tiles=_tiles(plan, o),
        detections=len(o.refined.features),
        detected_px=int(sum(r["detected_px"] for r in o.results)),
        mask_px=o.kept_px,
        discarded=o.discarded,
        timings=o.timings,
        device=o.device,
        device_requested=plan.device,
        placement={"reason": o.placement_reason, "restriction": o.restriction},
        cluster={"dashboard": o.dashboard, "workers": sorted({r["worker"] for r in o.results})},
        versions=versions(),
        warnings=o.warnings,
        outputs={
            name: str((plan.out_dir / name).resolve())
            for name in OUTPUTS
            if name not in OPTIONAL_OUTPUTS or (tmp / name).exists() or (name == AIS_OUTPUT and o.ais is not None)
        },
    )
