"""A detection run on a Dask cluster: ``sarship detect``, a service job, ``--detector auto``.

A run is a short sequence of named stages (docs/architecture.md, "A run"); the maths of each is
in :mod:`sarship.pipeline.run`, this module executes them on the cluster::

    plan = make_plan(request)           # pipeline/run/plan.py: parsed and checked once, nothing written yet
    tmp = prepare_out(plan.out_dir)     # pipeline/run/outputs.py: a temporary folder inside the output folder
    jobs = _tile_jobs(plan, tmp)        # the output stores, one TileJob per output tile
    land = prepare_land(plan, jobs)     # workers/land.py: the land mask's pass over the tiles
    prep = _scene_pass(plan, jobs)      # the detector's scene-wide statistics (DetectorSpec.scene_pass)
    results = _execute(jobs)            # the detector on every tile (workers/tasks.py: run_tile)
    merged = merge_tiles(results)       # components joined across tiles (pipeline/targets/components.py)
    records = discriminate(plan, merged)       # pipeline/run/merge.py: size, lines, the detector's rules
    refined = refine(plan, records)            # pipeline/run/refine.py: features, contrast, sidelobes, geolocation, ambiguities
    ais = ais_stage(plan.ais, refined)         # pipeline/run/ais.py: AIS matched, dark, unmatched vessels (with AIS files)
    kept_px = _write_kept(refined.records)     # mask.zarr/mask: the kept detections' pixels, on the workers
    run = run_record(plan, outcome)            # pipeline/run/record.py: run.json
    _write_outputs(...); publish(tmp, plan.out_dir)   # renamed into place only when complete

Outputs (docs/interfaces/files.md) in ``DIR``: ``mask.zarr`` (a Zarr v3 group with the uint8 arrays
``mask``, the pixels of the detections kept, and ``detected``, the detector's raw decision, chunked
like the tiles), ``detections.geojson``, ``run.json`` and, with a land mask, ``land.zarr``; with AIS
files, ``ais_unmatched.geojson``. A failed
or interrupted run leaves the previous outputs (or nothing) behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.run.ais import ais_stage
from sarship.pipeline.run.fit import fit_record
from sarship.pipeline.run.merge import discriminate
from sarship.pipeline.run.outputs import check_out, check_out_path, prepare_out, publish
from sarship.pipeline.run.plan import Plan, make_plan
from sarship.pipeline.run.record import Outcome, run_record
from sarship.pipeline.run.refine import refine
from sarship.pipeline.scene import claim_output, create_mask_store, finalize_scene, open_scene, tile_slices
from sarship.pipeline.stats import model_fit
from sarship.pipeline.targets.components import merge_tiles
from sarship.pipeline.targets.ship_features import collection, write_json
from sarship.workers.land import LAND_STORE, finish_land, prepare_land
from sarship.workers.progress import Progress
from sarship.workers.request import AUTO, JobRequest
from sarship.workers.routing import plan as plan_placement
from sarship.workers.tasks import TileJob, read_land_block, run_tile, run_tile_keep, run_tile_stats

#: ``mask.zarr``'s second array: the detector's raw per-pixel decision, before any detection
#: was dropped (``mask`` holds the pixels of the detections kept: docs/interfaces/files.md)
DETECTED_ARRAY = "detected"
#: The run's scratch store of each tile's component labels (int32, id + 1), in its temporary
#: folder only: the kept-detection mask is picked from it tile by tile (tasks.run_tile_keep)
LABEL_STORE = "labels.zarr"


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
    return run_request(
        request,
        out_dir,
        tile=tile,
        client=client,
        scheduler=scheduler,
        progress=progress,
        on_tile=on_tile,
        overwrite=overwrite,
        cluster_note=cluster_note,
        claim=True,
    )


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


def _run_auto(
    request: JobRequest, out_dir, tile, client, scheduler, progress, on_tile, overwrite, cluster_note, **publication
) -> dict[str, Any]:
    """``--detector auto``: the clutter-model fit of each candidate (pipeline/stats/model_fit.py,
    ``AUTO_CANDIDATES``) measured on the scene's sample (the candidate run with the request's
    parameters, its own PFA and the probe PFA, its kept detections excluded, no output
    written), then the chosen one (:func:`~sarship.pipeline.stats.model_fit.choose`) run again to
    write the outputs; its ``run.json`` records the choice as ``detector_auto``. (A candidate
    run at the probe PFA itself would merge the clutter's exceedances of a model that does not
    fit into detections, and exclude them from its own sample.)"""
    scene = open_scene(request.scene)
    check_out(Path(out_dir), Path(request.scene), overwrite)
    with contextlib.ExitStack() as stack:
        if client is None:
            from sarship.workers.cluster import connect, threads_max_px

            H, W = scene.shape
            client = stack.enter_context(
                connect(scheduler, gpus=request.device != "cpu", threads=H * W <= threads_max_px(), short_lived=True)
            )
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
            "fits": {
                n: {k: r[k] for k in ("verdict", "ratio", "rate", "interval", "exceedances", "sample")}
                for n, r in fits.items()
            },
            "chosen": chosen,
            "why": why,
        }
        if progress:
            print(f"detector auto: {chosen} ({why})", file=sys.stderr)
        final = request.model_copy(update={"detector": chosen})
        return _run_request(
            final,
            out_dir,
            tile,
            client,
            None,
            progress,
            on_tile,
            overwrite,
            None,
            extra_run={"detector_auto": record},
            **publication,
        )


def _run_request(
    request: JobRequest,
    out_dir,
    tile,
    client,
    scheduler,
    progress,
    on_tile,
    overwrite,
    cluster_note,
    fit_only: bool = False,
    extra_run: dict | None = None,
    publish_with: Callable[[Path, Path], None] = publish,
    land_source: dict | None = None,
) -> dict[str, Any]:
    """One detection run (:func:`run_request`), the stages of the module docstring in order.
    ``fit_only``: only the clutter-model fit (``--detector auto``'s candidates): no output is
    written, the ``model_fit`` record is returned. ``extra_run``: entries added to ``run.json``;
    ``publish_with``, ``land_source``: see :func:`run_request`."""
    clock = {"start": time.perf_counter()}
    plan = make_plan(
        request.spec,
        request.detector_params(),
        device=request.device,
        channel=request.channel,
        scene_path=request.scene,
        out_dir=out_dir,
        tile=tile,
        overwrite=overwrite,
        ais=request.ais,
    )
    if fit_only and plan.fit is None:
        raise ValueError(f"fit_only: the fit of '{plan.detector}' is not measured")
    created = not plan.out_dir.exists()
    tmp = prepare_out(plan.out_dir)
    try:
        outcome = _execute_plan(plan, tmp, client, scheduler, cluster_note, progress, on_tile, fit_only, clock)
        if fit_only:  # --detector auto's candidate: the fit of its model, nothing written
            shutil.rmtree(tmp, ignore_errors=True)
            return outcome
        outcome.extra.update(extra_run or {})
        if land_source and outcome.land is not None:  # the service's FILE behind the run's raster
            outcome.land = {**outcome.land, **land_source}
        run = run_record(plan, outcome, tmp)
        _write_outputs(plan, tmp, run, outcome, clock)
        publish_with(tmp, plan.out_dir)
        return run
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if created:  # a failed run leaves no trace, not even the empty folder it made
            with contextlib.suppress(OSError):
                plan.out_dir.rmdir()
        raise


def _execute_plan(
    plan: Plan, tmp: Path, client, scheduler, cluster_note, progress: bool, on_tile, fit_only: bool, clock: dict
) -> Outcome | dict:
    """The stages that run on the cluster (module docstring), on ``client`` or a cluster started
    for the run (``scheduler``, else a local one) and closed at the end. ``fit_only``: the
    ``model_fit`` record, once the detections are merged."""
    jobs = _tile_jobs(plan, tmp, fit_only)
    budget = None
    if plan.land.texture:
        from sarship.workers import blockcache

        budget = blockcache.limit_bytes()  # a bad SARSHIP_BLOCK_CACHE_MB is refused before the cluster starts
    clock["cluster"] = time.perf_counter()
    with contextlib.ExitStack() as stack:
        client, cluster_start = _cluster(plan, stack, client, scheduler, cluster_note)
        workers = client.scheduler_info(n_workers=-1).get("workers", {})
        from sarship.workers.cluster import dashboard_url

        dashboard = dashboard_url(client)  # None when the scheduler serves no dashboard (no bokeh)
        placement = plan_placement(plan.device, plan.detector, plan.has_gpu, workers)
        jobs = [dataclasses.replace(j, device=placement.device) for j in jobs]
        # the texture land pass's reads serve the detection: each tile's read is kept as Dask
        # data on the worker that made it and handed to the tile's texture sample and detection
        # (Dask runs them where it is, within the placement), within the memory budget
        blocks: dict = {}
        stack.callback(blocks.clear)  # the job's kept reads are released however it ends
        keep = kept_blocks(jobs, plan.params, budget * (len(workers) or 1)) if budget is not None else 0
        jobs, land_record = prepare_land(
            plan,
            jobs,
            tmp,
            lambda fn, js, stage: _execute_land(
                client, js, plan.detector, progress, fn, stage, placement.submit, keep, blocks
            ),
            progress=progress,
        )
        jobs, prep, scene_pass, warnings = _scene_pass(plan, client, jobs, placement.submit, progress)
        clock["prep"] = time.perf_counter()
        results = _execute(client, jobs, plan.detector, progress, on_tile, submit=placement.submit, extra=blocks)
        clock["tiles"] = time.perf_counter()
        finish_land(tmp, land_record, results, plan.shape)  # the decision on whole components: on the client
        clock["land_done"] = time.perf_counter()
        merged, members = merge_tiles({r["index"]: r["components"] for r in results}, members=True)
        records, discarded = discriminate(plan, prep, merged, sum(r.get("size_dropped", 0) for r in results))
        if fit_only:
            return fit_record(plan, results, records)
        land_path = tmp / LAND_STORE / "land" if land_record is not None else None
        refined = refine(plan, prep, records, land_record, land_path, tmp / "mask.zarr" / DETECTED_ARRAY)
        if refined.dropped_land is not None:
            discarded["land"] = refined.dropped_land
        discarded["contrast"] = refined.dropped_contrast
        fit = None
        if plan.fit is not None:  # does the detector's clutter model fit the scene? (pipeline/stats/model_fit.py)
            fit = fit_record(plan, results, refined.records)
            line = model_fit.advice(fit)
            if line:
                warnings.append(line)
        clock["merge"] = time.perf_counter()
        # mask.zarr/mask: the pixels of the detections kept, written tile by tile on the workers
        kept_px = _write_kept(client, jobs, merged, members, refined.records, plan.detector, placement.submit)
        clock["mask"] = time.perf_counter()
    clock["closed"] = time.perf_counter()  # a local cluster started here is closed on leaving the block
    ais = None
    if plan.ais is not None:  # pipeline/run/ais.py: on the client, once the cluster is released
        ais = ais_stage(
            plan.ais,
            plan.scene.attrs,
            plan.geo,
            plan.shape,
            refined.features,
            min_length_m=plan.params.min_length_m,
            spacing=plan.spacing,
        )
    clock["ais"] = time.perf_counter()
    H, W = plan.shape
    timings = {
        "prepare_s": round(clock["prep"] - clock["start"], 4),
        "tiles_s": round(clock["tiles"] - clock["prep"], 4),
        "cluster_start_s": None if cluster_start is None else round(cluster_start, 4),
        "cluster_close_s": round(clock["closed"] - clock["mask"], 4),
        "merge_s": round(clock["merge"] - clock["land_done"], 4),
        "mask_s": round(clock["mask"] - clock["merge"], 4),
        "ais_s": round(clock["ais"] - clock["closed"], 4),
        "detect_cpu_s": round(sum(r["detect_s"] for r in results), 4),
        "read_cpu_s": round(sum(r["read_s"] for r in results), 4),
        "mpx_per_s": round(H * W / max(clock["tiles"] - clock["prep"], 1e-9) / 1e6, 3),
    }
    return Outcome(
        prep=prep,
        scene_pass=scene_pass,
        land=land_record,
        results=results,
        refined=refined,
        discarded=discarded,
        model_fit=fit,
        kept_px=kept_px,
        tiles=len(jobs),
        device=placement.device,
        placement_reason=placement.reason,
        restriction={k: v for k, v in placement.submit.items() if k != "allow_other_workers"},
        dashboard=dashboard,
        warnings=warnings,
        timings=timings,
        ais=ais,
    )


def _tile_jobs(plan: Plan, tmp: Path, fit_only: bool) -> list[TileJob]:
    """The run's output stores (``mask.zarr`` with ``mask`` and ``detected``, the scratch label
    store) and one :class:`TileJob` per output tile (``fit_only``: the tiles write nothing)."""
    H, W = plan.shape
    scene = plan.scene
    create_mask_store(
        tmp / "mask.zarr",
        (H, W),
        plan.tile,
        {"detector": plan.detector, "scene": str(scene.path), **plan.geo},
        arrays=("mask", DETECTED_ARRAY),
    )
    create_mask_store(tmp / LABEL_STORE, (H, W), plan.tile, arrays=("labels",), dtype="int32")
    return [
        TileJob(
            scene_path=str(scene.path),
            var=plan.var,
            transform=plan.transform,
            scene_shape=(H, W),
            index=(i, j),
            bounds=(r0, r1, c0, c1),
            halo=plan.halo,
            merge_r=plan.merge_r,
            detector=plan.detector,
            params=plan.params.model_dump(),
            prep=plan.prep,
            mask_path=None if fit_only else str(tmp / "mask.zarr" / "mask"),
            spacing=plan.spacing,
            fit=plan.fit,
            detected_path=None if fit_only else str(tmp / "mask.zarr" / DETECTED_ARRAY),
            label_path=None if fit_only else str(tmp / LABEL_STORE / "labels"),
            line_join=plan.params.line_gap_px is not None,
        )
        for i, j, r0, r1, c0, c1 in tile_slices((H, W), plan.tile)
    ]


def _cluster(plan: Plan, stack: contextlib.ExitStack, client, scheduler, cluster_note) -> tuple[Any, float | None]:
    """The client the run uses, and the seconds it took to start or reach the cluster (None: a
    client was given; ``cluster_note`` is then printed, as a started cluster prints its own line)."""
    if client is not None:
        if cluster_note:
            print(cluster_note, file=sys.stderr)
        return client, None
    from sarship.workers.cluster import connect, threads_max_px

    t0 = time.perf_counter()
    H, W = plan.shape
    client = stack.enter_context(
        connect(
            scheduler, gpus=plan.device != "cpu" and plan.has_gpu, threads=H * W <= threads_max_px(), short_lived=True
        )
    )
    return client, time.perf_counter() - t0


def _scene_pass(
    plan: Plan, client, jobs: list[TileJob], submit: dict, progress: bool
) -> tuple[list[TileJob], dict, dict | None, list[str]]:
    """The detector's scene-wide statistics (``DetectorSpec.scene_pass`` / ``reduce``), pass
    after pass while ``reduce`` asks for another: the jobs with the merged values in their
    ``prep``, that ``prep``, the ``run.json`` ``scene_pass`` record (None without one) and the
    run's warnings (the plan's, then those ``reduce`` returned)."""
    spec, prep, warnings = plan.spec, plan.prep, list(plan.warnings)
    if spec.scene_pass is None:
        return jobs, prep, None, warnings
    t0 = time.perf_counter()
    values_all: dict = {}
    for n_pass in range(1, spec.scene_passes_max + 1):  # noqa: B007 (reported after the loop); reduce may ask for another pass
        stats = _execute(client, jobs, plan.detector, progress, None, run_tile_stats, "scene statistics", submit)
        values = spec.reduce([s["stats"] for s in sorted(stats, key=lambda s: s["index"])], plan.params, prep)
        again = bool(values.pop("another_pass", False))
        warnings.extend(values.pop("warnings", []))  # e.g. gamma_mrf's EM sample made denser
        values_all.update(values)
        prep = {**prep, **values}
        jobs = [dataclasses.replace(j, prep=prep) for j in jobs]
        if not again:
            break
    else:
        raise RuntimeError(f"{plan.detector}: more than {spec.scene_passes_max} scene passes asked for")
    record = {
        "tiles": len(stats),
        "seconds": round(time.perf_counter() - t0, 4),
        "passes": n_pass,
        "values": values_all,
    }
    return jobs, prep, record, warnings


def _write_outputs(plan: Plan, tmp: Path, run: dict, outcome: Outcome, clock: dict) -> None:
    """``mask.zarr``'s consolidated metadata (xarray.open_zarr reads it), ``detections.geojson``,
    with AIS ``ais_unmatched.geojson``, and ``run.json`` (with the time these took) in the run's
    temporary folder."""
    t_fin = time.perf_counter()
    finalize_scene(tmp / "mask.zarr")
    t_cons = time.perf_counter()
    feats = outcome.refined.features
    fc = collection(feats, detector=plan.detector, scene=str(plan.scene.path), parameters=plan.params.model_dump())
    write_json(tmp / "detections.geojson", fc)
    if outcome.ais is not None:
        write_json(tmp / "ais_unmatched.geojson", collection(outcome.ais.unmatched, scene=str(plan.scene.path)))
    t_end = time.perf_counter()
    run["timings"]["consolidate_s"] = round(t_cons - t_fin + clock["land_done"] - clock["tiles"], 4)
    run["timings"]["geojson_s"] = round(t_end - t_cons, 4)
    run["timings"]["total_s"] = round(t_end - clock["start"], 4)
    write_json(tmp / "run.json", run)


def _write_kept(
    client, jobs: list[TileJob], merged: np.ndarray, members: dict, kept: np.ndarray, detector: str, submit: dict | None
) -> int:
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
    futures = [
        client.submit(
            run_tile_keep,
            job,
            ids,
            pure=False,
            key=f"sarship-{detector}-keep-{job.index[0]}-{job.index[1]}-{tag}",
            **(submit or {}),
        )
        for job, ids in todo
    ]
    try:
        return int(sum(r["kept_px"] for r in client.gather(futures)))
    except BaseException:
        client.cancel(futures)
        raise


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


def _execute_land(
    client,
    jobs: list[TileJob],
    detector: str,
    progress: bool,
    fn,
    stage: str,
    submit: dict | None,
    keep: int,
    blocks: dict,
) -> list[dict]:
    """The land pass: the first ``keep`` tiles are read by :func:`read_land_block` into Dask data
    (futures in ``blocks``, by tile index, kept for the detection), their samples taken from
    those reads; the other tiles' samples read the scene themselves."""
    tag = uuid.uuid4().hex[:6]
    for j in jobs[:keep]:
        blocks[j.index] = client.submit(
            read_land_block,
            j,
            pure=False,
            key=f"sarship-{detector}-read-{j.index[0]}-{j.index[1]}-{tag}",
            **(submit or {}),
        )
    return _execute(client, jobs, detector, progress, None, fn, stage, submit, extra=blocks)


def _execute(
    client,
    jobs: list[TileJob],
    detector: str,
    progress: bool,
    on_tile,
    fn=run_tile,
    stage: str = "detect",
    submit: dict | None = None,
    extra: dict | None = None,
) -> list[dict]:
    """One future per tile, each carrying the placement's restriction (``submit``); ``extra``:
    futures of the tiles' land-pass reads (by tile index), passed as each task's second
    argument where there is one (Dask runs the task where the read is); a detection's read is
    released once the tile is done."""
    from distributed import as_completed

    tag = {run_tile_stats: "stats", run_tile: "tile"}.get(fn, "land")
    keys = [f"sarship-{detector}-{tag}-{j.index[0]}-{j.index[1]}-{uuid.uuid4().hex[:6]}" for j in jobs]
    if extra:
        futures = [
            client.submit(fn, j, extra.get(j.index), pure=False, key=k, **(submit or {})) for j, k in zip(jobs, keys)
        ]
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
