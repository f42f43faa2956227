"""A detection run's plan: the request parsed and checked ONCE, before any data is read or output written.

:func:`make_plan` turns what a run was asked (detector, its parameters, device, channel, scene,
output folder, tile) into one frozen :class:`Plan`: the detector's parameters with the looks,
the size rule and the settings for the scene resolved; the land options with the mask parsed and
its source checked; the tiling; the clutter-model fit's settings. Every later stage reads the
plan; nothing parses the request again. The order of the steps is part of the contract (``prep``
is computed from the parameters after the looks and before the size rule, as ``run.json``
records them).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, land_mask_parts, resolve_size
from sarship.pipeline.errors import InputError
from sarship.pipeline.run.ais import AisOptions, ais_options
from sarship.pipeline.run.outputs import check_out
from sarship.pipeline.scene import Scene, open_scene, processing_tile
from sarship.pipeline.stats import model_fit
from sarship.pipeline.targets.components import merge_radius
from sarship.pipeline.tiling.inputs import detector_source, make_reader

#: The smallest processing tile side (pixels).
MIN_TILE = 8


@dataclass(frozen=True)
class LandOptions:
    """``land_mask`` parsed once: the masks it combines (``texture``, ``coastline``), the FILE it
    names, and the checked source of the file or coastline (None for none/texture)."""

    kinds: frozenset[str]
    path: str | None
    source: Any = None

    @property
    def texture(self) -> bool:
        return "texture" in self.kinds

    @property
    def any(self) -> bool:
        return bool(self.kinds) or self.path is not None


@dataclass(frozen=True)
class Plan:
    """One run, parsed and checked (:func:`make_plan`)."""

    detector: str
    spec: DetectorSpec
    params: DetectorParams  # the run's parameters (run.json ``parameters``)
    prep: dict[str, Any]  # ``spec.prepare`` on them (run.json ``prepared``)
    device: str  # asked: auto, cpu or gpu
    has_gpu: bool  # GPU code for these parameters
    scene: Scene  # with its absolute path (tile tasks run elsewhere)
    out_dir: Path  # absolute
    var: Any  # what the detector reads (pipeline/tiling/inputs.py)
    transform: str
    tile: int
    tile_source: str
    halo: int
    merge_r: int
    land: LandOptions
    looks_source: str
    size_rule: str
    spacing: tuple[float, float] | None
    geo: dict[str, Any]  # the scene's georeference attributes
    fit: dict[str, Any] | None  # the clutter-model fit's settings, None when not measured
    warnings: tuple[str, ...]
    ais: AisOptions | None = None  # the AIS files matched to the detections (pipeline/run/ais.py)

    @property
    def shape(self) -> tuple[int, int]:
        return self.scene.shape


def check_device(spec: DetectorSpec, detector: str, device: str, params: DetectorParams) -> bool:
    """Whether the run has GPU code (``spec.gpu_for``); a one-line InputError for ``--device gpu``
    without it."""
    if device == "gpu" and not spec.gpu:
        raise InputError(f"--device gpu: detector '{detector}' has no GPU implementation in this version")
    has_gpu = spec.gpu_for(params)
    if device == "gpu" and not has_gpu:
        raise InputError(
            f"--device gpu: detector '{detector}' has no GPU implementation for these parameters "
            f"(docs/algorithms/{detector}.md, 'GPU'); use --device auto or cpu"
        )
    return has_gpu


def choose_tile(scene: Scene, tile: int | None) -> tuple[int, str]:
    """The processing tile side and where it came from (``given``, ``scene``, ``scene tile x N``)."""
    if tile:
        tile, source = int(tile), "given"
    else:
        tile = processing_tile(scene.shape, scene.tile)
        source = "scene" if tile == scene.tile else f"scene tile x {tile // scene.tile}"
    if tile < MIN_TILE:
        raise InputError(f"--tile must be at least {MIN_TILE} pixels, got {tile}")
    return tile, source


def land_options(params: DetectorParams, scene: Scene | None = None) -> LandOptions:
    """``land_mask`` parsed (:func:`~sarship.pipeline.detectors.base.land_mask_parts`) and, with a
    scene, its source checked: the FILE (:class:`~sarship.pipeline.land.landmask_files.LandFile`), the
    coastline (:class:`~sarship.pipeline.land.coastline.Coastline`: package installed, scene
    georeferenced); a one-line InputError otherwise."""
    keys, path = land_mask_parts(params.land_mask)
    kinds = frozenset(keys)
    if scene is None:
        return LandOptions(kinds, path)
    if "coastline" in kinds:
        from sarship.pipeline.land.coastline import open_coastline

        return LandOptions(kinds, path, open_coastline(scene.attrs, scene.shape, float(params.land_buffer_m)))
    if path is None:
        return LandOptions(kinds, path)
    from sarship.pipeline.land.landmask_files import open_land_file

    return LandOptions(kinds, path, open_land_file(path, scene.shape, scene.attrs))


def resolve_looks(
    spec: DetectorSpec, params: DetectorParams, scene: Scene, var: Any, transform: str
) -> tuple[DetectorParams, str]:
    """Fill ``looks`` from the parameter, else the scene attribute, else an estimate from a
    sample of the scene (:func:`sarship.pipeline.stats.looks.estimate_scene_looks`)."""
    if not spec.needs_looks or params.looks is not None:
        return params, "parameter" if params.looks is not None else "not used"
    if scene.looks is not None:
        return params.model_copy(update={"looks": scene.looks}), "scene attribute"
    from sarship.pipeline.stats.looks import estimate_scene_looks

    L = estimate_scene_looks(make_reader(str(scene.path), var, transform), scene.shape)
    return params.model_copy(update={"looks": L}), "estimated from the scene (MoLC, median over blocks)"


def shape_rules(
    params: DetectorParams, scene: Scene, spacing: tuple[float, float] | None
) -> tuple[DetectorParams, list[str]]:
    """The shape filter and length limits for the scene: ``max_elongation`` is the default of
    detected (intensity) products, where it was measured; on a complex scene only when asked
    for, and then in metres (complex pixels are not square: an IW SLC's are ~14 m x 2.3 m slant
    range, so a length / width in pixels is not the ship's). Returns the parameters and warnings."""
    warnings: list[str] = []
    if params.max_elongation is not None and scene.kind != "intensity":
        if "max_elongation" not in params.model_fields_set:
            params = params.model_copy(update={"max_elongation": None})
        elif spacing is None:
            params = params.model_copy(update={"max_elongation": None})
            warnings.append(
                f"max_elongation not applied: the {scene.kind} scene's pixel spacing is unknown (its "
                "pixels need not be square; give it with sarship ingest --spacing AZ,RG)"
            )
    if spacing is None and (params.min_length_m is not None or params.max_length_m is not None):
        warnings.append("min_length_m/max_length_m ignored: the scene's pixel spacing is unknown")
    return params, warnings


def fit_config(
    detector: str, spec: DetectorSpec, params: DetectorParams, shape: tuple[int, int]
) -> dict[str, Any] | None:
    """The tiles' clutter-model-fit settings: the scene's grid step and, for each probe PFA
    beyond the asked one, the detector's ``prepare`` there; None for a detector whose fit is not
    measured (pipeline/stats/model_fit.py, ``FIT_DETECTORS``)."""
    if detector not in model_fit.FIT_DETECTORS:
        return None
    probes = []
    for p in model_fit.pfas_of(params.pfa)[1:]:
        other = model_fit.MODEL_PROBE.get(detector)
        if other is None:
            probes.append(
                {
                    "pfa": p,
                    "prep": spec.prepare(params.model_copy(update={"pfa": p})),
                    "statistic": detector in model_fit.STATISTIC_PROBE,
                }
            )
            continue
        from sarship.pipeline import detectors

        ospec = detectors.get(other)  # the same model, windows, looks and absent pixels
        same = {k: getattr(params, k) for k in ("target", "guard", "background", "looks", "nodata")}
        oparams = ospec.params(pfa=p, land_mask=None, **same)
        probes.append(
            {
                "pfa": p,
                "prep": ospec.prepare(oparams),
                "statistic": False,
                "detector": other,
                "params": oparams.model_dump(),
            }
        )
    return {"stride": model_fit.sample_stride(shape), "probes": probes}


def make_plan(
    spec: DetectorSpec,
    params: DetectorParams,
    *,
    device: str,
    channel: str | None,
    scene_path: str | Path,
    out_dir: str | Path,
    tile: int | None,
    overwrite: bool,
    ais: tuple[str, ...] = (),
) -> Plan:
    """The run's :class:`Plan` from its parsed request; every check that can refuse the run
    (device, output folder, channel, tile, land source, scene size, AIS files) runs here, before
    any output is written. ``params``: the request's parameters, parsed once by the caller."""
    detector = spec.name
    has_gpu = check_device(spec, detector, device, params)
    scene = open_scene(scene_path)  # messages name the paths as given
    check_out(Path(out_dir), Path(scene_path), overwrite)
    # absolute paths: the tile tasks run on workers whose working folder may be another one
    scene = dataclasses.replace(scene, path=Path(scene_path).absolute())
    var, transform = detector_source(spec, scene, channel)
    tile, tile_source = choose_tile(scene, tile)
    # a bad land_mask FILE, or coastline without its package or on a scene without georeference,
    # fails here, before any data is read or output written
    land = land_options(params, scene)
    params, looks_source = resolve_looks(spec, params, scene, var, transform)
    prep = spec.prepare(params)
    spacing = scene.ground_spacing_m  # ground metres (an SLC's slant range converted: pipeline/scene.py)
    params, size_rule = resolve_size(params, spacing)  # metres when the spacing is known; given values win
    params, warnings = shape_rules(params, scene, spacing)
    if spec.for_scene is not None:  # settings for the scene's shape; a scene too small is refused here
        params, notes = spec.for_scene(params, scene.shape, spacing)
        warnings.extend(notes)
    geo: dict[str, Any] = {k: scene.attrs[k] for k in ("crs", "transform", "gcps") if k in scene.attrs}
    return Plan(
        detector=detector,
        spec=spec,
        params=params,
        prep=prep,
        device=device,
        has_gpu=has_gpu,
        scene=scene,
        out_dir=Path(out_dir).absolute(),
        var=var,
        transform=transform,
        tile=tile,
        tile_source=tile_source,
        halo=spec.halo(params),
        merge_r=merge_radius(params.merge_px),
        land=land,
        looks_source=looks_source,
        size_rule=size_rule,
        spacing=spacing,
        geo=geo,
        fit=fit_config(detector, spec, params, scene.shape),
        warnings=tuple(warnings),
        ais=ais_options(ais, scene.attrs, geo),
    )
