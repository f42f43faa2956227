"""``sarship detect``: submit one task per output tile to Dask, merge, write the outputs.

Outputs (docs/interfaces/files.md) in ``DIR``: ``mask.zarr`` (a Zarr v3 group with the uint8 arrays
``mask``, the pixels of the detections kept, and ``detected``, the detector's raw decision, chunked
like the tiles), ``detections.geojson`` and ``run.json``. They are written
under a temporary folder inside ``DIR`` and renamed into place only when the run has
succeeded, so a failed or interrupted run leaves the previous outputs (or nothing) behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import platform
import shutil
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sarship.pipeline import __version__
from sarship.pipeline.ambiguity import flag_features
from sarship.pipeline.components import merge_radius, merge_tiles
from sarship.pipeline.detectors.base import land_mask_parts, resolve_size
from sarship.pipeline.lines import discard_lines, near_land
from sarship.pipeline.ship_features import add_contrast, collection, features, keep_mask, size_prefilter, write_json
from sarship.pipeline.sidelobes import refine_features
from sarship.pipeline.errors import InputError
from sarship.pipeline.inputs import detector_source, make_reader, pixel_power, window_reader
from sarship.pipeline import model_fit
from sarship.pipeline.local_contrast import GAP_PX, MIN_RING_PX, RING_PX, add_local_contrast, keep_contrast
from sarship.pipeline.run.outputs import OPTIONAL_OUTPUTS, OUTPUTS, check_out, check_out_path, prepare_out, publish
from sarship.pipeline.window_cache import CachedWindows
from sarship.pipeline.scene import (Scene, claim_output, create_mask_store, finalize_scene,
                                    open_scene, processing_tile, tile_slices)
from sarship.workers.land import LAND_STORE, check_land_file, finish_land, prepare_land
from sarship.workers.progress import Progress
from sarship.workers.request import AUTO, JobRequest
from sarship.workers.routing import plan
from sarship.workers.tasks import TileJob, read_land_block, run_tile, run_tile_keep, run_tile_stats

#: ``mask.zarr``'s second array: the detector's raw per-pixel decision, before any detection
#: was dropped (``mask`` holds the pixels of the detections kept: docs/interfaces/files.md)
DETECTED_ARRAY = "detected"
#: The run's scratch store of each tile's component labels (int32, id + 1), in its temporary
#: folder only: the kept-detection mask is picked from it tile by tile (tasks.run_tile_keep)
LABEL_STORE = "labels.zarr"


def resolve_looks(spec, params, scene: Scene, var: str, transform: str) -> tuple[Any, str]:
    """Fill ``looks`` from the parameter, else the scene attribute, else an estimate from a
    sample of the scene (:func:`sarship.pipeline.looks.estimate_scene_looks`)."""
    if not spec.needs_looks or params.looks is not None:
        return params, "parameter" if params.looks is not None else "not used"
    if scene.looks is not None:
        return params.model_copy(update={"looks": scene.looks}), "scene attribute"
    from sarship.pipeline.looks import estimate_scene_looks

    L = estimate_scene_looks(make_reader(str(scene.path), var, transform), scene.shape)
    return params.model_copy(update={"looks": L}), "estimated from the scene (MoLC, median over blocks)"


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"sarship": __version__, "python": platform.python_version()}
    for pkg in ("numpy", "scipy", "numba", "dask", "distributed", "zarr", "xarray", "pydantic"):
        with contextlib.suppress(Exception):
            out[pkg] = md.version(pkg)
    return out


def run_detection(
    scene_path: str | os.PathLike,
    detector: str,
    settings: dict[str, Any] | None = None,
    out_dir: str | os.PathLike = "sarship-out",
    tile: int | None = None,
    client=None,
    scheduler: str | None = None,
    device: str = "auto",
    progress: bool = True,
    on_tile: Callable[[int, int], None] | None = None,
    overwrite: bool = False,
    cluster_note: str | None = None,
) -> dict[str, Any]:
    """Run ``detector`` on a scene store; returns the ``run.json`` content.

    ``settings``: the detector's parameters (and optionally ``channel``), validated as a
    :class:`~sarship.workers.request.JobRequest`. ``client``: a connected
    ``distributed.Client`` (else one is made: ``scheduler`` or a local cluster). ``tile``:
    processing/output tile side (default: the scene's chunk). ``out_dir`` must not exist or be
    empty unless ``overwrite`` (then only the three outputs are replaced); it is never allowed
    inside the scene store. ``cluster_note``: a line for stderr once the checks have passed and
    the given ``client``'s cluster is used (as a started cluster's own line). ``out_dir`` is
    claimed for the run (:func:`sarship.pipeline.scene.claim_output`): a second run to the same
    folder meanwhile is refused with :class:`InputError`, and one that starts after it finds its
    outputs (refused too without ``overwrite``).
    """
    request = JobRequest.from_inputs(detector, {**(settings or {}), "scene": str(scene_path), "device": device})
    return run_request(request, out_dir, tile=tile, client=client, scheduler=scheduler, progress=progress,
                       on_tile=on_tile, overwrite=overwrite, cluster_note=cluster_note, claim=True)


def run_request(
    request: JobRequest,
    out_dir: str | os.PathLike = "sarship-out",
    tile: int | None = None,
    client=None,
    scheduler: str | None = None,
    progress: bool = True,
    on_tile: Callable[[int, int], None] | None = None,
    overwrite: bool = False,
    cluster_note: str | None = None,
    claim: bool = False,
    publish_with: Callable[[Path, Path], None] = publish,
    land_source: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run a validated :class:`~sarship.workers.request.JobRequest`; its ``scene`` is the
    path of a scene store. Returns the ``run.json`` content (see :func:`run_detection`).
    ``claim``: hold ``out_dir`` for the run (:func:`sarship.pipeline.scene.claim_output`; the
    output checks run under the claim). The service's runner does not: each attempt writes its
    own temporary folder and the job store fences publication: its ``publish_with`` is called
    with (temporary folder, ``out_dir``) instead of
    :func:`sarship.pipeline.run.outputs.publish` and keeps the folder for the store's
    transaction. ``land_source``: entries added to ``run.json``'s ``land`` record (the
    service's land-mask FILE that the run's raster was made from)."""
    args = (request, out_dir, tile, client, scheduler, progress, on_tile, overwrite, cluster_note)
    run = _run_auto if request.detector == AUTO else _run_request
    kw = {"publish_with": publish_with, "land_source": land_source}
    if not claim:
        return run(*args, **kw)
    check_out_path(Path(out_dir), Path(request.scene))  # first: never a claim inside the scene
    with claim_output(out_dir, "--out", create_parents=True):
        return run(*args, **kw)


def _run_auto(request: JobRequest, out_dir, tile, client, scheduler, progress, on_tile, overwrite,
              cluster_note, **publication) -> dict[str, Any]:
    """``--detector auto``: the clutter-model fit of each candidate (pipeline/model_fit.py,
    ``AUTO_CANDIDATES``) measured on the scene's sample (the candidate run with the request's
    parameters, its own PFA and the probe PFA, its kept detections excluded, no output
    written), then the chosen one (:func:`~sarship.pipeline.model_fit.choose`) run again to
    write the outputs; its ``run.json`` records the choice as ``detector_auto``. (A candidate
    run at the probe PFA itself would merge the clutter's exceedances of a model that does not
    fit into detections, and exclude them from its own sample.)"""
    scene = open_scene(request.scene)
    check_out(Path(out_dir), Path(request.scene), overwrite)
    with contextlib.ExitStack() as stack:
        if client is None:
            from sarship.workers.cluster import connect, threads_max_px

            H, W = scene.shape
            client = stack.enter_context(connect(scheduler, gpus=request.device != "cpu",
                                                 threads=H * W <= threads_max_px(), short_lived=True))
        elif cluster_note:
            print(cluster_note, file=sys.stderr)
        fits = {}
        for name in model_fit.AUTO_CANDIDATES:
            probe = request.model_copy(update={"detector": name})
            fits[name] = _run_request(probe, out_dir, tile, client, None, progress, None, True, None, fit_only=True)
        chosen, why = model_fit.choose(fits)
        record = {
            "candidates": list(model_fit.AUTO_CANDIDATES),
            "probe_pfa": model_fit.PROBE_PFA,
            "tolerance": model_fit.AUTO_TOLERANCE,
            "fits": {n: {k: r[k] for k in ("verdict", "ratio", "rate", "interval", "exceedances", "sample")}
                     for n, r in fits.items()},
            "chosen": chosen,
            "why": why,
        }
        if progress:
            print(f"detector auto: {chosen} ({why})", file=sys.stderr)
        final = request.model_copy(update={"detector": chosen})
        return _run_request(final, out_dir, tile, client, None, progress, on_tile, overwrite, None,
                            extra_run={"detector_auto": record}, **publication)


def _fit_config(detector: str, spec, params, shape: tuple[int, int]) -> dict | None:
    """The tiles' clutter-model-fit settings (:attr:`TileJob.fit`): the scene's grid step and,
    for each probe PFA beyond the asked one, the detector's ``prepare`` there; None for a
    detector whose fit is not measured (pipeline/model_fit.py, ``FIT_DETECTORS``)."""
    if detector not in model_fit.FIT_DETECTORS:
        return None
    probes = []
    for p in model_fit.pfas_of(params.pfa)[1:]:
        other = model_fit.MODEL_PROBE.get(detector)
        if other is None:
            probes.append({"pfa": p, "prep": spec.prepare(params.model_copy(update={"pfa": p})),
                           "statistic": detector in model_fit.STATISTIC_PROBE})
            continue
        from sarship.pipeline import detectors

        ospec = detectors.get(other)  # the same model, windows, looks and absent pixels
        same = {k: getattr(params, k) for k in ("target", "guard", "background", "looks", "nodata")}
        oparams = ospec.params(pfa=p, land_mask=None, **same)
        probes.append({"pfa": p, "prep": ospec.prepare(oparams), "statistic": False, "detector": other,
                       "params": oparams.model_dump()})
    return {"stride": model_fit.sample_stride(shape), "probes": probes}


def _fit_record(detector: str, params, fit: dict, results: list[dict], records, shape) -> dict:
    """``run.json``'s ``model_fit`` from the tiles' flags, the kept detections' cells left out."""
    stride = int(fit["stride"])
    grid = model_fit.assemble((r["fit"] for r in results), shape, stride)
    boxes = np.stack([records["r0"], records["c0"], records["r1"], records["c1"]], axis=1) if len(records) else []
    excluded = model_fit.exclude_targets(grid, stride, boxes)
    rec = model_fit.record(detector, grid, model_fit.pfas_of(params.pfa), stride, excluded)
    # whose decision the probe PFA's exceedances are: the detector's, or its model's (MODEL_PROBE)
    rec["probe_by"] = fit["probes"][0].get("detector") or detector if fit["probes"] else detector
    return rec


def _run_request(request: JobRequest, out_dir, tile, client, scheduler, progress, on_tile, overwrite,
                 cluster_note, fit_only: bool = False, extra_run: dict | None = None,
                 publish_with: Callable[[Path, Path], None] = publish,
                 land_source: dict | None = None) -> dict[str, Any]:
    """One detection run (:func:`run_request`). ``fit_only``: only the clutter-model fit
    (``--detector auto``'s candidates): no output is written, the ``model_fit`` record is
    returned. ``extra_run``: entries added to ``run.json``; ``publish_with``, ``land_source``:
    see :func:`run_request`."""
    t_start = time.perf_counter()
    spec, detector, device, channel = request.spec, request.detector, request.device, request.channel
    params = request.detector_params()
    if device == "gpu" and not spec.gpu:
        raise InputError(f"--device gpu: detector '{detector}' has no GPU implementation in this version")
    has_gpu = spec.gpu_for(params)
    if device == "gpu" and not has_gpu:
        raise InputError(f"--device gpu: detector '{detector}' has no GPU implementation for these parameters "
                         f"(docs/algorithms/{detector}.md, 'GPU'); use --device auto or cpu")
    # absolute paths: the tile tasks run on workers whose working folder may be another one
    scene = open_scene(request.scene)  # messages name the paths as given
    check_out(Path(out_dir), Path(request.scene), overwrite)
    scene = dataclasses.replace(scene, path=Path(request.scene).absolute())
    out_dir = Path(out_dir).absolute()
    var, transform = detector_source(spec, scene, channel)  # (the service checks the same at submission)
    if tile:
        tile, tile_source = int(tile), "given"
    else:
        tile = processing_tile(scene.shape, scene.tile)
        tile_source = "scene" if tile == scene.tile else f"scene tile x {tile // scene.tile}"
    if tile < 8:
        raise InputError(f"--tile must be at least 8 pixels, got {tile}")
    # a bad land_mask FILE, or coastline without its package or on a scene without georeference,
    # fails here, before any data is read or output written
    land_file = check_land_file(params, scene)
    params, looks_source = resolve_looks(spec, params, scene, var, transform)
    prep = spec.prepare(params)
    warnings: list[str] = []
    spacing = scene.ground_spacing_m  # ground metres (an SLC's slant range converted: pipeline/scene.py)
    # the size rule: metres when the spacing is known, pixels otherwise; given values win
    params, size_rule = resolve_size(params, spacing)
    if params.max_elongation is not None and scene.kind != "intensity":
        # the default shape filter is for detected (intensity) products, where it was measured; on a
        # complex scene only when asked for, and then in metres: complex pixels are not square (an
        # IW SLC's are ~14 m x 2.3 m slant range), so a length / width in pixels is not the ship's
        if "max_elongation" not in params.model_fields_set:
            params = params.model_copy(update={"max_elongation": None})
        elif spacing is None:
            params = params.model_copy(update={"max_elongation": None})
            warnings.append(f"max_elongation not applied: the {scene.kind} scene's pixel spacing is unknown (its "
                            "pixels need not be square; give it with sarship ingest --spacing AZ,RG)")
    if spacing is None and (params.min_length_m is not None or params.max_length_m is not None):
        warnings.append("min_length_m/max_length_m ignored: the scene's pixel spacing is unknown")
    if spec.for_scene is not None:  # settings for the scene's shape; a scene too small is refused here
        params, notes = spec.for_scene(params, scene.shape, spacing)
        warnings.extend(notes)
    halo = spec.halo(params)
    mr = merge_radius(params.merge_px)
    H, W = scene.shape
    fit = _fit_config(detector, spec, params, (H, W))
    if fit_only and fit is None:
        raise ValueError(f"fit_only: the fit of '{detector}' is not measured")
    created = not out_dir.exists()
    tmp = prepare_out(out_dir)
    try:
        geo = {k: scene.attrs[k] for k in ("crs", "transform", "gcps") if k in scene.attrs}
        create_mask_store(tmp / "mask.zarr", (H, W), tile, {"detector": detector, "scene": str(scene.path), **geo},
                          arrays=("mask", DETECTED_ARRAY))
        create_mask_store(tmp / LABEL_STORE, (H, W), tile, arrays=("labels",), dtype="int32")
        jobs = [
            TileJob(
                scene_path=str(scene.path), var=var, transform=transform, scene_shape=(H, W),
                index=(i, j), bounds=(r0, r1, c0, c1), halo=halo, merge_r=mr, detector=detector,
                params=params.model_dump(), prep=prep,
                mask_path=None if fit_only else str(tmp / "mask.zarr" / "mask"), spacing=spacing, fit=fit,
                detected_path=None if fit_only else str(tmp / "mask.zarr" / DETECTED_ARRAY),
                label_path=None if fit_only else str(tmp / LABEL_STORE / "labels"),
                line_join=params.line_gap_px is not None,
            )
            for i, j, r0, r1, c0, c1 in tile_slices((H, W), tile)
        ]
        scene_pass = None
        land_record = None
        texture = "texture" in land_mask_parts(params.land_mask)[0]
        if texture:
            from sarship.workers import blockcache

            budget = blockcache.limit_bytes()  # a bad SARSHIP_BLOCK_CACHE_MB is refused before the cluster starts
        t_cluster = time.perf_counter()
        cluster_start = None  # seconds to start (or reach) the cluster; None: a client was given
        with contextlib.ExitStack() as stack:
            if client is None:
                from sarship.workers.cluster import connect, threads_max_px

                client = stack.enter_context(connect(scheduler, gpus=device != "cpu" and has_gpu,
                                                     threads=H * W <= threads_max_px(), short_lived=True))
                cluster_start = time.perf_counter() - t_cluster
            elif cluster_note:
                print(cluster_note, file=sys.stderr)
            cluster_workers = client.scheduler_info(n_workers=-1).get("workers", {})
            from sarship.workers.cluster import dashboard_url

            dashboard = dashboard_url(client)  # None when the scheduler serves no dashboard (no bokeh)
            placement = plan(device, detector, has_gpu, cluster_workers)
            jobs = [dataclasses.replace(j, device=placement.device) for j in jobs]
            # the texture land pass's reads serve the detection: each tile's read is kept as Dask
            # data on the worker that made it and handed to the tile's texture sample and detection
            # (Dask runs them where it is, within the placement), within the memory budget
            blocks: dict = {}
            stack.callback(blocks.clear)  # the job's kept reads are released however it ends
            keep = kept_blocks(jobs, params, budget * (len(cluster_workers) or 1)) if texture else 0
            jobs, land_record = prepare_land(
                params, scene, land_file, jobs, tmp, tile,
                lambda fn, js, stage: _execute_land(client, js, detector, progress, fn, stage, placement.submit,
                                                    keep, blocks),
                progress=progress)
            if spec.scene_pass is not None:
                t_pass = time.perf_counter()
                scene_values: dict = {}
                for n_pass in range(1, spec.scene_passes_max + 1):  # reduce may ask for another pass
                    stats = _execute(client, jobs, detector, progress, None, run_tile_stats, "scene statistics",
                                     placement.submit)
                    values = spec.reduce([s["stats"] for s in sorted(stats, key=lambda s: s["index"])],
                                         params, prep)
                    again = bool(values.pop("another_pass", False))
                    warnings.extend(values.pop("warnings", []))  # e.g. gamma_mrf's EM sample made denser
                    scene_values.update(values)
                    prep = {**prep, **values}
                    jobs = [dataclasses.replace(j, prep=prep) for j in jobs]
                    if not again:
                        break
                else:
                    raise RuntimeError(f"{detector}: more than {spec.scene_passes_max} scene passes asked for")
                scene_pass = {"tiles": len(stats), "seconds": round(time.perf_counter() - t_pass, 4),
                              "passes": n_pass, "values": scene_values}
            t_prep = time.perf_counter()
            results = _execute(client, jobs, detector, progress, on_tile, submit=placement.submit, extra=blocks)
            t_tiles = time.perf_counter()
            # the decision on whole components: on the client, from the tiles' moment tables
            finish_land(tmp, land_record, results, (H, W))
            t_land_done = time.perf_counter()
            comps = {r["index"]: r["components"] for r in results}
            merged, members = merge_tiles(comps, members=True)
            records, discarded = _discriminate(merged, params, spacing, sum(r.get("size_dropped", 0) for r in results))
            if spec.discriminate is not None:  # the detector's own rules on whole components (e.g. peak)
                n0 = len(records)
                records = records[spec.discriminate(records, params, prep)]
                discarded["detector"] = n0 - len(records)
            if fit_only:  # --detector auto's candidate: the fit of its model, nothing written
                shutil.rmtree(tmp, ignore_errors=True)
                return _fit_record(detector, params, fit, results, records, (H, W))
            land_path = tmp / LAND_STORE / "land" if land_record is not None else None
            if params.land_gap_px is not None and land_path is not None and len(records):
                near = near_land(records, CachedWindows(window_reader(land_path), (H, W)), (H, W), params.land_gap_px)
                records, discarded["land"] = records[~near], int(near.sum())
            feats = features(records, spacing, geo)
            feats = add_contrast(feats, (land_record or {}).get("sea_mean"))
            scene_read = mask_read = None
            if params.sidelobes or spec.detection_properties is not None or params.min_contrast_db is not None:
                # the per-detection steps read small windows: through block caches, each chunk once; the
                # mask they read is the detector's own decision (each detection's component, and the
                # detections left out of the clutter ring)
                scene_read = CachedWindows(make_reader(str(scene.path), var, transform), (H, W))
                mask_read = CachedWindows(window_reader(tmp / "mask.zarr" / DETECTED_ARRAY), (H, W))
            feats, records, contrast_record = _contrast_step(
                feats, records, params.min_contrast_db, scene_read, mask_read, land_path, (H, W),
                getattr(params, "nodata", None))
            discarded["contrast"] = contrast_record.get("dropped", 0)
            if params.sidelobes:  # cross-sidelobe suppression on the detections (pipeline/sidelobes.py)
                feats = refine_features(feats, records, scene_read, mask_read, (H, W), mr, spacing, geo)
            if spec.detection_properties is not None:  # the detector's own per-detection properties (e.g. csk)
                feats = spec.detection_properties(feats, records, scene_read, mask_read, (H, W), mr, params, prep,
                                                  spacing=spacing, geo=geo)
            from sarship.pipeline.ship_features import geolocate  # WGS84 outline + centre of the final geometry

            feats = geolocate(feats, geo)
            # azimuth-ambiguity flags: ambiguity_of on every detection (pipeline/ambiguity.py)
            feats, ambiguity_record = flag_features(feats, scene.attrs, params.ambiguities, params.ambiguity_tol_px,
                                                    params.ambiguity_min_db)
            fit_record = None
            if fit is not None:  # does the detector's clutter model fit the scene? (pipeline/model_fit.py)
                fit_record = _fit_record(detector, params, fit, results, records, (H, W))
                line = model_fit.advice(fit_record)
                if line:
                    warnings.append(line)
            t_merge = time.perf_counter()
            # mask.zarr/mask: the pixels of the detections kept, written tile by tile on the workers
            kept_px = _write_kept(client, jobs, merged, members, records, detector, placement.submit)
            t_mask = time.perf_counter()
        t_closed = time.perf_counter()  # a local cluster started here is closed on leaving the block
        run = {
            "sarship_version": __version__,
            "detector": detector,
            "reference": spec.reference,
            "parameters": params.model_dump(),
            "channel": var if isinstance(var, str) else list(var),
            "looks_source": looks_source,
            "size_rule": size_rule,
            "prepared": prep,
            "scene_pass": scene_pass,
            "land": {**land_record, **land_source} if land_source and land_record is not None else land_record,
            "contrast": contrast_record,
            "ambiguities": ambiguity_record,
            "model_fit": fit_record,
            **(extra_run or {}),
            "scene": {
                "path": str(Path(scene.path).resolve()),
                "shape": [H, W],
                "kind": scene.kind,
                "tile": scene.tile,
                "looks": scene.looks,
                "pixel_spacing_m": list(scene.pixel_spacing_m) if scene.pixel_spacing_m else None,
                "ground_spacing_m": list(spacing) if spacing else None,
                "attrs": {k: v for k, v in scene.attrs.items() if k not in ("simulation",)},
            },
            "tiles": {
                "size": tile,
                "size_source": tile_source,
                "grid": [math.ceil(H / tile), math.ceil(W / tile)],
                "count": len(jobs),
                "halo_px": halo,
                "merge_radius_px": mr,
                "per_tile": [
                    {"index": list(r["index"]), "worker": r["worker"], "device": r["device"],
                     "detected_px": r["detected_px"], "block_from": r.get("block_from", "scene"),
                     **{k: round(r[k], 6) for k in ("read_s", "land_s", "detect_s", "write_s", "label_s", "h2d_s",
                                                    "d2h_s")}}
                    for r in sorted(results, key=lambda r: r["index"])
                ],
            },
            "detections": len(feats),
            "detected_px": int(sum(r["detected_px"] for r in results)),
            "mask_px": kept_px,
            "discarded": discarded,
            "timings": {
                "prepare_s": round(t_prep - t_start, 4),
                "tiles_s": round(t_tiles - t_prep, 4),
                "cluster_start_s": None if cluster_start is None else round(cluster_start, 4),
                "cluster_close_s": round(t_closed - t_mask, 4),
                "merge_s": round(t_merge - t_land_done, 4),
                "mask_s": round(t_mask - t_merge, 4),
                "detect_cpu_s": round(sum(r["detect_s"] for r in results), 4),
                "read_cpu_s": round(sum(r["read_s"] for r in results), 4),
                "mpx_per_s": round(H * W / max(t_tiles - t_prep, 1e-9) / 1e6, 3),
            },
            "device": placement.device,
            "device_requested": device,
            "placement": {"reason": placement.reason,
                          "restriction": {k: v for k, v in placement.submit.items() if k != "allow_other_workers"}},
            "cluster": {"dashboard": dashboard, "workers": sorted({r["worker"] for r in results})},
            "versions": _versions(),
            "warnings": warnings,
            "outputs": {name: str((out_dir / name).resolve()) for name in OUTPUTS
                        if name not in OPTIONAL_OUTPUTS or (tmp / name).exists()},
        }
        t_fin = time.perf_counter()
        finalize_scene(tmp / "mask.zarr")  # consolidated metadata: xarray.open_zarr reads it
        t_cons = time.perf_counter()
        fc = collection(feats, detector=detector, scene=str(scene.path), parameters=params.model_dump())
        write_json(tmp / "detections.geojson", fc)
        t_end = time.perf_counter()
        run["timings"]["consolidate_s"] = round(t_cons - t_fin + t_land_done - t_tiles, 4)
        run["timings"]["geojson_s"] = round(t_end - t_cons, 4)
        run["timings"]["total_s"] = round(t_end - t_start, 4)
        write_json(tmp / "run.json", run)
        publish_with(tmp, out_dir)
        return run
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if created:  # a failed run leaves no trace, not even the empty folder it made
            with contextlib.suppress(OSError):
                out_dir.rmdir()
        raise


def _discriminate(records: np.ndarray, params, spacing: tuple[float, float] | None,
                  tile_size_dropped: int) -> tuple[np.ndarray, dict[str, int]]:
    """The size, shape and line rules on the merged components: the area rule the tiles applied
    (:func:`sarship.pipeline.ship_features.size_prefilter`), the line rule
    (:func:`sarship.pipeline.lines.discard_lines`, on the pieces before the shape test), then the
    whole size and shape rule (:func:`keep_mask`). Returns the kept records and the count of
    components dropped by each rule (``tile_size_dropped``: those the tiles dropped already)."""
    pre = size_prefilter(params, params.line_gap_px is not None)
    keep = keep_mask(records, pre, spacing) if pre is not params else np.ones(len(records), bool)
    size = tile_size_dropped + int(len(keep) - keep.sum())
    records = records[keep]
    reason = discard_lines(records, params.line_gap_px, params.line_angle_deg, params.line_dominant_db,
                           params.max_elongation, params.max_length_m, spacing)
    counts = {"line": int((reason == "line").sum()), "smear": int((reason == "smear").sum())}
    records = records[reason == ""]
    keep = keep_mask(records, params, spacing)
    counts = {"size": size + int(len(keep) - keep.sum()), **counts, "detector": 0, "land": 0, "contrast": 0}
    return records[keep], counts


def _write_kept(client, jobs: list[TileJob], merged: np.ndarray, members: dict, kept: np.ndarray, detector: str,
                submit: dict | None) -> int:
    """Write ``mask.zarr/mask``: each tile with a part of a kept detection (``kept``: the final
    records, a subset of ``merged``, matched by their peak pixel, which belongs to one component)
    writes its pixels of them from its label store (:func:`run_tile_keep`), on the workers.
    Returns the number of pixels written."""
    if not len(kept):
        return 0
    index = {(int(r), int(c)): k for k, (r, c) in enumerate(zip(merged["peak_r"], merged["peak_c"]))}
    chosen = np.zeros(len(merged), bool)
    chosen[[index[(int(r), int(c))] for r, c in zip(kept["peak_r"], kept["peak_c"])]] = True
    todo = []
    for job in jobs:
        ids, recs = members.get(job.index, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
        sel = ids[chosen[recs]]
        if len(sel):
            todo.append((job, sel))
    tag = uuid.uuid4().hex[:6]
    futures = [client.submit(run_tile_keep, job, ids, pure=False,
                             key=f"sarship-{detector}-keep-{job.index[0]}-{job.index[1]}-{tag}", **(submit or {}))
               for job, ids in todo]
    try:
        return int(sum(r["kept_px"] for r in client.gather(futures)))
    except BaseException:
        client.cancel(futures)
        raise


def _contrast_step(feats: list[dict], records, floor: float | None, scene_read, mask_read, land_path: Path | None,
                   shape: tuple[int, int], nodata: float | None):
    """The local contrast of every detection and the ``min_contrast_db`` rule
    (pipeline/local_contrast.py): (kept features, their records, the ``run.json`` record).
    Measured only when a floor is set (a window read per detection; -30 dB measures every
    detection and drops practically none); otherwise ``contrast_db`` is null."""
    if floor is None:
        for f in feats:
            f["properties"].update(contrast_db=None, contrast_ring_px=None)
        return feats, records, {"min_contrast_db": None, "measured": False}
    land_read = CachedWindows(window_reader(land_path), shape) if land_path is not None else None
    feats = add_local_contrast(feats, lambda *w: pixel_power(np.asarray(scene_read(*w))), mask_read, shape,
                               land_read, nodata)
    keep = keep_contrast(feats, floor)
    record = {"min_contrast_db": floor, "measured": True, "gap_px": GAP_PX, "ring_px": RING_PX,
              "min_ring_px": MIN_RING_PX, "land_excluded": land_path is not None,
              "unmeasured": sum(f["properties"]["contrast_db"] is None for f in feats),
              "dropped": len(keep) - sum(keep)}
    return [f for f, k in zip(feats, keep) if k], records[np.asarray(keep, bool)], record


def kept_blocks(jobs: list[TileJob], params, budget: int) -> int:
    """How many tiles' land-pass reads a job keeps for its detection: as many as fit in
    ``budget`` bytes (the cluster's: ``blockcache.limit_bytes()`` per worker), counting each
    read (:func:`sarship.workers.tasks.read_land_block`: the tile, its merge margin, the
    detector's and the land mask's halos) at 8 bytes a pixel and channel (the largest sample
    type read); the first tiles in row order. The others' detections read the scene again."""
    from sarship.workers.land import texture_config

    if not jobs:
        return 0
    j = jobs[0]
    r0, r1, c0, c1 = j.bounds
    pad = 2 * (j.merge_r + j.halo + texture_config(params).halo)
    per = (r1 - r0 + pad) * (c1 - c0 + pad) * 8 * (len(j.var) if isinstance(j.var, tuple) else 1)
    return int(min(len(jobs), budget // per))


def _execute_land(client, jobs: list[TileJob], detector: str, progress: bool, fn, stage: str,
                  submit: dict | None, keep: int, blocks: dict) -> list[dict]:
    """The land pass: the first ``keep`` tiles are read by :func:`read_land_block` into Dask data
    (futures in ``blocks``, by tile index, kept for the detection), their samples taken from
    those reads; the other tiles' samples read the scene themselves."""
    tag = uuid.uuid4().hex[:6]
    for j in jobs[:keep]:
        blocks[j.index] = client.submit(read_land_block, j, pure=False,
                                        key=f"sarship-{detector}-read-{j.index[0]}-{j.index[1]}-{tag}", **(submit or {}))
    return _execute(client, jobs, detector, progress, None, fn, stage, submit, extra=blocks)


def _execute(client, jobs: list[TileJob], detector: str, progress: bool, on_tile, fn=run_tile,
             stage: str = "detect", submit: dict | None = None, extra: dict | None = None) -> list[dict]:
    """One future per tile, each carrying the placement's restriction (``submit``); ``extra``:
    futures of the tiles' land-pass reads (by tile index), passed as each task's second
    argument where there is one (Dask runs the task where the read is); a detection's read is
    released once the tile is done."""
    from distributed import as_completed

    tag = {run_tile_stats: "stats", run_tile: "tile"}.get(fn, "land")
    keys = [f"sarship-{detector}-{tag}-{j.index[0]}-{j.index[1]}-{uuid.uuid4().hex[:6]}" for j in jobs]
    if extra:
        futures = [client.submit(fn, j, extra.get(j.index), pure=False, key=k, **(submit or {}))
                   for j, k in zip(jobs, keys)]
    else:
        futures = client.map(fn, jobs, pure=False, key=keys, **(submit or {}))
    prog = Progress(len(jobs), f"{stage} {detector}", progress)
    results = []
    try:
        # results fetched by the client's event loop as tasks finish, handed over in batches
        # (not one blocking round trip per future from this thread; a failed task raises here)
        for batch in as_completed(futures, with_results=True).batches():
            for _fut, res in batch:
                results.append(res)
                if fn is run_tile and extra:
                    extra.pop(res["index"], None)
                prog.step(res["pixels"])
                if on_tile is not None:
                    on_tile(len(results), len(jobs))
    except BaseException:
        client.cancel(futures)
        raise
    return results
