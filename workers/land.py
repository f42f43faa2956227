"""The land mask of a detection job (``land_mask`` = none | texture | coastline |
coastline+texture | FILE), client side.

``texture``: a land pass over the tiles (:func:`sarship.workers.tasks.run_tile_land_stats`: the
texture on a scene-wide grid, pooled in (row, col) order), the Gaussian mixture fitted and the
sea/land decision made here (:func:`sarship.pipeline.land.landmask.decide`); each detection tile
then computes its land mask from its own block read with ``land_halo`` more context, writes
its core into ``DIR/land.zarr`` and sets land to NaN before the detector runs.

``FILE``: the file is checked (:func:`sarship.pipeline.land.landmask_files.open_land_file`) and
rasterised into ``DIR/land.zarr`` here, strip by strip, before any tile runs; each tile reads
its block of it (mirror-extended like the scene) and sets land to NaN.

``coastline``: the GSHHG shoreline (:mod:`sarship.pipeline.land.coastline`) widened by
``land_buffer_m`` is rasterised into ``DIR/land.zarr`` here, strip by strip, as a FILE is, and
the tiles read it the same way. ``coastline+texture``: the coastline goes to the array
``coastline`` of ``DIR/land.zarr``; each texture tile reads its block of it and writes the union
into ``land``.

Maths in :mod:`sarship.pipeline.land.landmask`; docs/algorithms/landmask.md.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import finalize_scene

if TYPE_CHECKING:  # the service's capped land child imports this module: no detector stack at import
    from sarship.pipeline.run.plan import Plan

LAND_STORE = "land.zarr"


def texture_config(params) -> Any:
    from sarship.pipeline.land.landmask import TextureConfig

    return TextureConfig(
        window=int(params.land_window),
        classes=int(params.land_classes),
        open_px=int(params.land_open_px),
        close_px=int(params.land_close_px),
    )


def create_land_store(path: Path, shape: tuple[int, int], tile: int, attrs: dict):
    """``DIR/land.zarr``: a group with the uint8 array ``land`` (1 = land), chunked like the mask."""
    import zarr

    from sarship.pipeline.scene import _jsonable, _zstd, chunking

    g = zarr.open_group(str(path), mode="w", zarr_format=3)
    arr = g.create_array(
        "land",
        shape=tuple(int(s) for s in shape),
        dtype="uint8",
        **chunking(tile),
        compressors=_zstd(),
        dimension_names=("y", "x"),
        fill_value=0,
    )
    g.attrs.update(_jsonable(attrs))
    return arr


def rasterize_coastline(coast, arr, shape: tuple[int, int], rows: int, progress: bool = False) -> int:
    """Write the buffered coastline mask into ``arr`` strip by strip (``rows`` rows a strip);
    returns the land pixel count. ``progress``: a line per 10 % of the strips on stderr."""
    from sarship.workers.progress import Progress

    H, W = shape
    count = 0
    starts = range(0, H, max(rows, 1))
    bar = Progress(len(starts), "land coastline, strips", progress)
    for r0 in starts:
        r1 = min(r0 + max(rows, 1), H)
        block = coast.read(r0, r1, 0, W)
        arr[r0:r1, :] = block.astype(np.uint8)
        count += int(block.sum())
        bar.step((r1 - r0) * W)
    return count


def coastline_record(coast, count: int, seconds: float) -> dict:
    """``run.json``'s description of the coastline mask."""
    from sarship.pipeline.land.coastline import shoreline_version

    st = coast.stats
    return {
        "source": "coastline",
        "shoreline": f"GSHHG full resolution, level 1 ({shoreline_version()})",
        "buffer_m": coast.buffer_m,
        "spacing_m": list(coast.spacing),
        "spacing_source": coast.spacing_source,
        "halo_px": list(coast.halo),
        "lattice_step_px": coast.step,
        "lattice_points": st["lattice_points"],
        "refined_px": st["refined_px"],
        "evaluated_px": st["pixels"],
        "land_px": count,
        "land": count > 0,
        "seconds": round(seconds, 4),
    }


def prepare_land(plan: Plan, jobs: list, tmp: Path, execute, progress: bool = False) -> tuple[list, dict | None]:
    """Set up the run's land mask (``plan.land``, parsed and checked by the plan): returns the tile
    jobs with their land fields and the record for ``run.json`` (``land``), or ``(jobs, None)``
    without a land mask. ``execute(fn, jobs, stage)`` runs a per-tile function on the cluster and
    returns its results; ``progress``: the coastline's rasterisation reports on stderr."""
    if plan.params.land_mask is None:
        return jobs, None
    land = plan.land
    if "coastline" in land.kinds:
        from sarship.pipeline.land.coastline import Coastline

        if not isinstance(land.source, Coastline):
            raise TypeError("prepare_land: land_mask=coastline needs the plan's checked Coastline")
    t0 = time.perf_counter()
    if land.kinds == {"coastline"}:
        return _coastline_land(plan, jobs, tmp, progress, t0)
    if land.texture:
        return _texture_land(plan, jobs, tmp, execute, progress, t0)
    return _file_land(plan, jobs, tmp, t0)


def _coastline_land(plan: Plan, jobs: list, tmp: Path, progress: bool, t0: float) -> tuple[list, dict]:
    """``land_mask=coastline``: the buffered shoreline rasterised into ``land.zarr`` strip by strip."""
    store = tmp / LAND_STORE
    arr = create_land_store(store, plan.shape, plan.tile, {"source": "coastline", **plan.geo})
    count = rasterize_coastline(plan.land.source, arr, plan.shape, plan.tile, progress)
    land = {"mode": "file", "store": str(store / "land")}
    jobs = [dataclasses.replace(j, land=land, land_halo=0, land_path=None) for j in jobs]
    return jobs, coastline_record(plan.land.source, count, time.perf_counter() - t0)


def _texture_land(plan: Plan, jobs: list, tmp: Path, execute, progress: bool, t0: float) -> tuple[list, dict]:
    """``land_mask=texture`` (and ``coastline+texture``): the texture sample of every tile, the
    scene-wide decision (:func:`sarship.pipeline.land.landmask.decide`), the tiles' land fields; with
    the coastline, its array beside the texture's, which the tiles add to their block."""
    from sarship.pipeline.land import landmask
    from sarship.workers.tasks import run_tile_land_stats

    store = tmp / LAND_STORE
    H, W = plan.shape
    cfg = texture_config(plan.params)
    stride = landmask.sample_stride((H, W))
    base = {"mode": "texture", "config": dataclasses.asdict(cfg), "stride": stride}
    stats = execute(run_tile_land_stats, [dataclasses.replace(j, land=base) for j in jobs], "land texture")
    t, m = landmask.pool_sample_arrays([s["stats"] for s in sorted(stats, key=lambda s: s["index"])], ("t", "m"))
    decision = landmask.decide(t, cfg)
    decision["stride"] = stride
    decision["sea_mean"] = landmask.sea_mean(t, m, decision)
    create_land_store(store, (H, W), plan.tile, {"source": "+".join(sorted(plan.land.kinds)), **plan.geo})
    land = {"mode": "texture", "config": dataclasses.asdict(cfg), "decision": decision}
    halo = cfg.halo if decision["land"] else 0
    coast_record = None
    if "coastline" in plan.land.kinds:  # the union: the tiles add their block of the coastline array
        import zarr

        from sarship.pipeline.scene import _zstd, chunking

        t1 = time.perf_counter()
        g = zarr.open_group(str(store), mode="r+")
        carr = g.create_array(
            "coastline",
            shape=(H, W),
            dtype="uint8",
            **chunking(plan.tile),
            compressors=_zstd(),
            dimension_names=("y", "x"),
            fill_value=0,
        )
        count = rasterize_coastline(plan.land.source, carr, (H, W), plan.tile, progress)
        coast_record = coastline_record(plan.land.source, count, time.perf_counter() - t1)
        land = {**land, "coastline": str(store / "coastline")}
    jobs = [dataclasses.replace(j, land=land, land_halo=halo, land_path=str(store / "land")) for j in jobs]
    record = {"source": "texture", **decision, "seconds": round(time.perf_counter() - t0, 4)}
    if coast_record is not None:
        record = {
            **record,
            "source": "coastline+texture",
            "texture_land": decision["land"],
            "land": bool(decision["land"] or coast_record["land"]),
            "coastline": coast_record,
        }
    return jobs, record


def _file_land(plan: Plan, jobs: list, tmp: Path, t0: float) -> tuple[list, dict]:
    """``land_mask=FILE``: the file's mask copied into ``land.zarr`` row band by row band."""
    land_file = plan.land.source
    store = tmp / LAND_STORE
    H, W = plan.shape
    arr = create_land_store(store, (H, W), plan.tile, {"source": str(Path(land_file.path).resolve()), **plan.geo})
    rows = max(plan.tile, 1)
    count = 0
    for r0 in range(0, H, rows):
        r1 = min(r0 + rows, H)
        try:
            block = np.asarray(land_file.read(r0, r1, 0, W), bool)
        except InputError as exc:
            raise InputError(f"parameter 'land_mask': {exc}") from None
        arr[r0:r1, :] = block.astype(np.uint8)
        count += int(block.sum())
    land = {"mode": "file", "store": str(store / "land")}
    jobs = [dataclasses.replace(j, land=land, land_halo=0, land_path=None) for j in jobs]
    record = {
        "source": "file",
        "path": str(Path(land_file.path).resolve()),
        "kind": land_file.kind,
        "format": land_file.format,
        **land_file.info,
        "land": count > 0,
        "seconds": round(time.perf_counter() - t0, 4),
    }
    return jobs, record


def finish_land(tmp: Path, record: dict | None, results: list[dict], shape: tuple[int, int]) -> None:
    """Consolidate ``land.zarr`` and add the land pixel count (the tiles' ``land_px``) to the record."""
    if record is None:
        return
    finalize_scene(tmp / LAND_STORE)
    n = int(sum(r.get("land_px", 0) for r in results))
    record["land_px"] = n
    record["land_fraction"] = round(n / max(shape[0] * shape[1], 1), 6)
