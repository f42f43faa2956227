"""The unit of work sent to Dask workers: one output tile, read-detect-write-label.

Each task reads its tile plus halo straight from the scene's Zarr store (so only tile
metadata travels through the scheduler), runs the detector on it, writes into its own
chunk (shard) of the raw decision (``mask.zarr/detected``) and of the run's scratch store of
its component labels only, and only the inner chunks its detections fall in
(so no two tasks ever write the same chunk or shard), and returns the
tile's component moments and edge labels (small) for the cross-tile merge. Once the client has
decided which detections are kept, :func:`run_tile_keep` writes the tile's part of
``mask.zarr/mask``: the pixels of its components that belong to kept detections.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline import detectors
from sarship.pipeline.targets.components import mask_points, point_labels, points_components
from sarship.pipeline.targets.ship_features import keep_mask, size_prefilter
from sarship.pipeline.tiling.inputs import make_reader, open_array, pixel_power
from sarship.pipeline.tiling.windows import padded_block


def _chunk_box(
    chunks: tuple[int, int], r0: int, c0: int, shape: tuple[int, int], rows: tuple[int, int], cols: tuple[int, int]
) -> tuple[int, int, int, int]:
    """The box ``(a, b, c, d)`` (tile coordinates) of the array's chunks that holds the tile's
    set pixels ``rows = (first, last)``, ``cols = (first, last)``, clipped to the tile."""
    ch, cw = chunks
    h, w = shape
    a = max((r0 + rows[0]) // ch * ch - r0, 0)
    b = min(-(-(r0 + rows[1] + 1) // ch) * ch - r0, h)
    c = max((c0 + cols[0]) // cw * cw - c0, 0)
    d = min(-(-(c0 + cols[1] + 1) // cw) * cw - c0, w)
    return a, b, c, d


def write_sparse(path: str, r0: int, c0: int, core: np.ndarray) -> tuple[int, int, int, int] | None:
    """Write a tile's boolean ``core`` (its ``[0, 0]`` at scene ``(r0, c0)``) into the new,
    all-fill (0) uint8 array at ``path``: only the box of (inner) chunks that holds its set
    pixels, aligned to the array's chunk grid and clipped to the tile, so a tile with one
    small ship encodes one 512 x 512 chunk instead of its whole 2048 x 2048 shard (the rest of
    the tile stays fill value, which is what it holds). Nothing is written when no pixel is
    set. Returns the written box ``(r0, r1, c0, c1)`` in scene pixels, or None."""
    rows = np.flatnonzero(core.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(core.any(axis=0))
    out = open_array(path, write=True)  # chunks equal to the fill value are not stored
    a, b, c, d = _chunk_box(
        out.chunks, r0, c0, core.shape, (int(rows[0]), int(rows[-1])), (int(cols[0]), int(cols[-1]))
    )  # the inner chunks of a sharded array
    out[r0 + a : r0 + b, c0 + c : c0 + d] = core[a:b, c:d].astype(np.uint8)
    return r0 + a, r0 + b, c0 + c, c0 + d


def write_points(
    path: str,
    r0: int,
    c0: int,
    rows: np.ndarray,
    cols: np.ndarray,
    shape: tuple[int, int],
    values: np.ndarray | None = None,
) -> tuple[int, int, int, int] | None:
    """:func:`write_sparse` of the tile (``shape``, its ``[0, 0]`` at scene ``(r0, c0)``) whose
    set pixels are at ``(rows, cols)`` (tile coordinates): the same chunks written with the same
    content, built from the points without scanning the tile. ``values``: what each point holds
    (default 1), in the array's own dtype (e.g. the tile's component labels)."""
    rows = np.asarray(rows, np.int64)
    cols = np.asarray(cols, np.int64)
    if rows.size == 0:
        return None
    out = open_array(path, write=True)
    a, b, c, d = _chunk_box(
        out.chunks, r0, c0, shape, (int(rows.min()), int(rows.max())), (int(cols.min()), int(cols.max()))
    )
    if values is None:
        box = np.zeros((b - a, d - c), np.uint8)
        box[rows - a, cols - c] = 1
    else:
        values = np.asarray(values)
        box = np.zeros((b - a, d - c), values.dtype)
        box[rows - a, cols - c] = values
    out[r0 + a : r0 + b, c0 + c : c0 + d] = box
    return r0 + a, r0 + b, c0 + c, c0 + d


def points_power(values) -> np.ndarray:
    """:func:`~sarship.pipeline.tiling.inputs.pixel_power` of the values of some pixels, ``values[k]``
    being pixel k's (a number, stacked channels or a covariance matrix): a 1-D array."""
    return np.asarray(pixel_power(np.asarray(values)[:, None]))[:, 0]


@dataclass(frozen=True)
class TileJob:
    scene_path: str
    var: str | tuple[str, ...]  # a tuple: stacked complex channels (polarimetric detectors)
    transform: str
    scene_shape: tuple[int, int]
    index: tuple[int, int]
    bounds: tuple[int, int, int, int]  # r0, r1, c0, c1
    halo: int
    merge_r: int
    detector: str
    params: dict
    prep: dict
    mask_path: str | None
    spacing: tuple[float, float] | None
    device: str = "cpu"  # "gpu": move the block to this worker's GPU once, detect there
    #: sea-land segmentation (workers/land.py): None, {"mode": "texture", "config", "decision"}
    #: or {"mode": "file", "store"}; land pixels become NaN (absent) before the detector sees them
    land: dict | None = None
    land_halo: int = 0  # extra context the texture land mask needs beyond ``halo``
    line_join: bool = False  # lines are joined on the client: the tile keeps elongated components
    land_path: str | None = None  # land.zarr array this tile writes its core into (texture mode)
    #: clutter-model fit (pipeline/stats/model_fit.py): None, or {"stride", "probes": [{"pfa", "prep",
    #: "statistic"}]}: the tile's cells of the scene's sample grid, flagged at the job's PFA and
    #: at each probe PFA (``statistic``: the statistic against the probe's ``prep["threshold"]``;
    #: ``detector``, ``params``: another detector of the same model decides, model_fit.MODEL_PROBE)
    fit: dict | None = None
    #: the raw per-pixel decision (``mask.zarr/detected``) and the scratch store of the tile's
    #: component labels (int32, id + 1) from which :func:`run_tile_keep` writes ``mask``
    detected_path: str | None = None
    label_path: str | None = None


def _worker_name() -> str:
    try:
        from distributed import get_worker

        w = get_worker()
        return str(w.name)
    except Exception:
        return "local"


def _read(job: TileJob, r0: int, r1: int, c0: int, c1: int, timing: dict | None = None, full=None):
    """The job's detector, its parameters, the block ``[r0:r1, c0:c1]`` with its halo (land
    pixels set to NaN when the job has a land mask) and the block's land mask (None without one).
    ``timing``: filled with the seconds of the land mask (``land_s``) when given. ``full``: the
    land pass's read of the tile (:func:`read_land_block`), used instead of reading the scene."""
    spec = detectors.get(job.detector)
    params = spec.params(**job.params)
    block = _land_pass_block(job, (r0, r1, c0, c1), full)
    if timing is not None:
        timing["block_from"] = "scene" if block is None else "land pass"
    if block is None:
        read = make_reader(job.scene_path, job.var, job.transform)
        block = padded_block(read, job.scene_shape, r0, r1, c0, c1, job.halo + job.land_halo)
    land = None
    if job.land is not None:
        t = time.perf_counter()
        block, land = _land_block(job, block, r0, r1, c0, c1)
        if timing is not None:
            timing["land_s"] = time.perf_counter() - t
    return spec, params, block, land


def _land_block(job: TileJob, block, r0: int, r1: int, c0: int, c1: int):
    """The land mask of the padded block (halo ``job.halo``) and the block with land set to NaN:
    computed from the texture (the block was read with ``land_halo`` more context, trimmed
    here) or read from the job's land store (mirror-extended like the scene)."""
    from sarship.pipeline.land import landmask

    h, lh = job.halo, job.land_halo
    if job.land["mode"] == "texture" and not job.land["decision"].get("land") and not job.land.get("coastline"):
        # the scene has no land (the decision): nothing to compute, mark or write
        return (block[lh : block.shape[0] - lh, lh : block.shape[1] - lh] if lh else block), None
    if job.land["mode"] == "texture":
        cfg = landmask.TextureConfig(**job.land["config"])
        land = landmask.classify(block, lh, (r0 - h - lh, c0 - h - lh), cfg, job.land["decision"])
        if lh:
            block = block[lh : block.shape[0] - lh, lh : block.shape[1] - lh]
        if job.land.get("coastline"):  # land_mask=coastline+texture: the union (workers/land.py)
            import zarr

            carr = zarr.open_array(job.land["coastline"], mode="r")
            land = land | (
                padded_block(lambda a, b, c, d: np.asarray(carr[a:b, c:d]), job.scene_shape, r0, r1, c0, c1, h) > 0
            )
    else:
        import zarr

        arr = zarr.open_array(job.land["store"], mode="r")
        land = padded_block(lambda a, b, c, d: np.asarray(arr[a:b, c:d]), job.scene_shape, r0, r1, c0, c1, h) > 0
    return landmask.apply_absent(block, land), land


def _on_device(job: TileJob, spec) -> bool:
    return job.device == "gpu" and bool(spec.gpu)  # placement already chose: spec.gpu_for(params)


def _to_device(block):
    from sarship.pipeline.gpu import init_device, to_device

    init_device()
    return to_device(block)


def _points_to_host(mask_d, stat_d, block_d, halo: int):
    """The detected pixels of a GPU tile (``mask_d``, the padded ``block_d``'s core, the
    extended window) as what :func:`run_tile` needs on the host: their row-major coordinates in
    the extended window, the statistic at them and the input (``block_d``, its halo ``halo``) at
    them, found on the device; a few bytes a detection come back instead of the whole mask (1
    byte a pixel) and statistic (4)."""
    import cupy as cp

    idx = cp.flatnonzero(mask_d)
    if int(idx.size) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float32), np.zeros((0,) + tuple(block_d.shape[2:]), block_d.dtype)
    we = int(mask_d.shape[1])
    rr_d, cc_d = idx // we, idx % we
    stat = stat_d.reshape(-1)[idx].get()
    vals = block_d[rr_d + halo, cc_d + halo].get()
    rr, cc = rr_d.get(), cc_d.get()
    return rr, cc, stat, vals


def run_tile_stats(job: TileJob) -> dict[str, Any]:
    """First pass of a two-pass detector: the tile's contribution to scene-wide statistics."""
    t0 = time.perf_counter()
    r0, r1, c0, c1 = job.bounds
    spec, params, block, _ = _read(job, r0, r1, c0, c1)
    gpu = _on_device(job, spec) and spec.scene_pass_gpu
    if gpu:
        block = _to_device(block)
    stats = spec.scene_pass(block, job.halo, (r0 - job.halo, c0 - job.halo), params, job.prep)
    return {
        "index": job.index,
        "stats": stats,
        "worker": _worker_name(),
        "pixels": (r1 - r0) * (c1 - c0),
        "device": "gpu" if gpu else "cpu",
        "seconds": time.perf_counter() - t0,
    }


def _extended(job: TileJob) -> tuple[int, int, int, int]:
    """The window :func:`run_tile` reads around its core: the tile plus the merge margin."""
    H, W = job.scene_shape
    r0, r1, c0, c1 = job.bounds
    m = job.merge_r
    return max(r0 - m, 0), min(r1 + m, H), max(c0 - m, 0), min(c1 + m, W)


def _land_pass_block(job: TileJob, window: tuple[int, int, int, int], full):
    """The detection pass's block cut from the land pass's read ``full`` (with the halo
    ``job.halo + job.land_halo``); None when there is none for this job and window."""
    if full is None or job.land is None or job.land.get("mode") != "texture" or window != _extended(job):
        return None
    from sarship.pipeline.land import landmask

    extra = landmask.TextureConfig(**job.land["config"]).halo - job.land_halo  # read with the full land halo
    if extra < 0:
        return None
    return full[extra : full.shape[0] - extra, extra : full.shape[1] - extra] if extra else full


def read_land_block(job: TileJob) -> np.ndarray:
    """The land pass's read of a tile (``land_mask=texture``) with all the context its detection
    will need: the merge margin, the detector's halo and the land mask's halo (the mirror
    extension is defined by position, so any sub-window of it is what a smaller read gives).
    The job keeps the result as Dask data on the worker that read it and hands it to the tile's
    texture sample and to its detection (workers/jobs.py), so the scene is decoded once; Dask
    places both where the block is and moves it only when another worker must run them."""
    from sarship.pipeline.land import landmask

    cfg = landmask.TextureConfig(**job.land["config"])
    er0, er1, ec0, ec1 = _extended(job)
    read = make_reader(job.scene_path, job.var, job.transform)
    return padded_block(read, job.scene_shape, er0, er1, ec0, ec1, job.halo + cfg.halo)


def run_tile_land_stats(job: TileJob, full: np.ndarray | None = None) -> dict[str, Any]:
    """The land pass (``land_mask=texture``): the tile's texture sample on the scene-wide grid
    (``job.land["stride"]``), for the mixture fitted on the client (workers/land.py); taken from
    the middle of ``full`` (:func:`read_land_block`) when the job keeps the tile's read, else
    from a read of the tile with the texture window's context."""
    from sarship.pipeline.land import landmask

    t0 = time.perf_counter()
    r0, r1, c0, c1 = job.bounds
    cfg = landmask.TextureConfig(**job.land["config"])
    r = cfg.window // 2
    if full is not None:
        er0, _er1, ec0, _ec1 = _extended(job)
        big = job.halo + cfg.halo
        a, b = (r0 - r) - (er0 - big), (c0 - r) - (ec0 - big)
        block = full[a : a + (r1 - r0) + 2 * r, b : b + (c1 - c0) + 2 * r]
    else:
        read = make_reader(job.scene_path, job.var, job.transform)
        block = padded_block(read, job.scene_shape, r0, r1, c0, c1, r)
    sample = landmask.texture_sample(block, r, (r0 - r, c0 - r), cfg, int(job.land["stride"]))
    return {
        "index": job.index,
        "stats": sample,
        "worker": _worker_name(),
        "pixels": (r1 - r0) * (c1 - c0),
        "device": "cpu",
        "seconds": time.perf_counter() - t0,
    }


def _host(a) -> np.ndarray:
    """A (small) array on the host: a CuPy array copied back, a numpy one as it is."""
    return a.get() if hasattr(a, "get") and not isinstance(a, np.ndarray) else np.asarray(a)


def _fit_flags(job: TileJob, spec, params, host_block, block, origin, mask, stat) -> dict | None:
    """The tile's cells of the scene's clutter-model-fit sample (pipeline/stats/model_fit.py): present
    pixels of the core, whether the detection (``mask``, ``stat`` of the extended window) marks
    them, and whether the decision at each probe PFA does (``block``: the detector's input, on
    the device for a GPU tile; ``host_block``: the same on the host). None without ``job.fit``."""
    if job.fit is None:
        return None
    from sarship.pipeline.stats import model_fit
    from sarship.pipeline.tiling import intensity_absent

    r0, r1, c0, c1 = job.bounds
    er0, _er1, ec0, _ec1 = _extended(job)
    a, b, hb = r0 - er0, c0 - ec0, job.halo
    rs, cs, gi, gj = model_fit.grid_slices(r0, c0, r1 - r0, c1 - c0, int(job.fit["stride"]))
    er = slice(a + rs.start, a + rs.stop, rs.step)
    ec = slice(b + cs.start, b + cs.stop, cs.step)
    core = np.asarray(host_block[hb + er.start : hb + er.stop : er.step, hb + ec.start : hb + ec.stop : ec.step])
    valid = intensity_absent.present(core, getattr(params, "nodata", None))
    exceed = [_host(mask[er, ec])]
    for probe in job.fit["probes"]:
        if probe["statistic"]:
            exceed.append(_host(stat[er, ec]) > float(probe["prep"]["threshold"]))
        elif probe.get("detector"):  # another detector of the same model (model_fit.MODEL_PROBE)
            other = detectors.get(probe["detector"])
            pm, _ = other.detect(block, hb, origin, other.params(**probe["params"]), probe["prep"])
            exceed.append(_host(pm[er, ec]))
        else:
            pm, _ = spec.detect(block, hb, origin, params.model_copy(update={"pfa": probe["pfa"]}), probe["prep"])
            exceed.append(_host(pm[er, ec]))
    return model_fit.pack(valid, exceed, (gi, gj))


def run_tile(job: TileJob, full: np.ndarray | None = None) -> dict[str, Any]:
    """Process one tile; returns its components and timings. ``full``: the land pass's read of
    the tile (:func:`read_land_block`), when the job kept it."""
    t0 = time.perf_counter()
    r0, r1, c0, c1 = job.bounds
    m = job.merge_r
    er0, er1, ec0, ec1 = _extended(job)
    timing = {"land_s": 0.0}
    spec, params, block, land = _read(job, er0, er1, ec0, ec1, timing, full)
    t1 = time.perf_counter()
    gpu = _on_device(job, spec)
    origin = (er0 - job.halo, ec0 - job.halo)
    h2d = d2h = 0.0
    if gpu:  # one transfer in, the whole detector on the device, the detected pixels back
        from sarship.pipeline.gpu import synchronize

        dblock = _to_device(block)
        synchronize()
        ta = time.perf_counter()
        mask_d, stat_d = spec.detect(dblock, job.halo, origin, params, job.prep)
        synchronize()  # kernel time is detect_s - h2d_s - d2h_s
        tb = time.perf_counter()
        pr, pc, stat_p, vals = _points_to_host(mask_d, stat_d, dblock, job.halo)
        val_p = points_power(vals)
        h2d, d2h = ta - t1, time.perf_counter() - tb
        fit = _fit_flags(job, spec, params, block, dblock, origin, mask_d, stat_d)
        del dblock, mask_d, stat_d
    else:
        mask_e, stat_e = spec.detect(block, job.halo, origin, params, job.prep)
        pr, pc = mask_points(mask_e)
        stat_p = np.asarray(stat_e)[pr, pc]
        val_p = points_power(block[pr + job.halo, pc + job.halo])
        fit = _fit_flags(job, spec, params, block, block, origin, mask_e, stat_e)
    t2 = time.perf_counter()
    a, b = r0 - er0, c0 - ec0
    h, w = r1 - r0, c1 - c0
    incore = (pr >= a) & (pr < a + h) & (pc >= b) & (pc < b + w)
    # points in the (h + 2m, w + 2m) frame of the tile's mask with its merge margin
    rr, cc = pr + (m - a), pc + (m - b)
    comp = point_labels(rr, cc, (h, w), m)
    # the stores are new and all fill value (0): a tile writes only the chunks its marks fall in;
    # mask.zarr/mask is written once the detections are decided (run_tile_keep)
    if job.detected_path is not None:
        write_points(job.detected_path, r0, c0, pr[incore] - a, pc[incore] - b, (h, w))
    if job.label_path is not None:
        write_points(
            job.label_path, r0, c0, pr[incore] - a, pc[incore] - b, (h, w), (comp[incore] + 1).astype(np.int32)
        )
    hb = job.halo
    if job.land_path is not None and land is not None:
        write_sparse(job.land_path, r0, c0, land[hb + a : hb + a + h, hb + b : hb + b + w])
    t3 = time.perf_counter()
    comps = points_components(rr, cc, val_p, stat_p, (h, w), m, (r0, c0), job.index, comp)
    pre = size_prefilter(params, job.line_join)
    size_dropped = 0
    if pre is not None:
        keep = keep_mask(comps.complete, pre, job.spacing)
        size_dropped = int(len(keep) - keep.sum())
        comps.keep_complete(keep)
    t4 = time.perf_counter()
    return {
        "index": job.index,
        "components": comps,
        "worker": _worker_name(),
        "device": "gpu" if gpu else "cpu",
        "detected_px": int(incore.sum()),
        "size_dropped": size_dropped,  # complete components the size rule dropped here
        "land_px": 0
        if land is None
        else int(land[job.halo + a : job.halo + a + h, job.halo + b : job.halo + b + w].sum()),
        "pixels": h * w,
        "block_from": timing["block_from"],  # "land pass": the land pass's read, kept as Dask data
        "read_s": t1 - t0 - timing["land_s"],
        "land_s": timing["land_s"],
        "detect_s": t2 - t1,
        "write_s": t3 - t2,
        "label_s": t4 - t3,
        "h2d_s": h2d,
        "d2h_s": d2h,
        "fit": fit,
    }


def run_tile_keep(job: TileJob, ids: np.ndarray) -> dict[str, Any]:
    """Write the tile's part of ``mask.zarr/mask``: the pixels of its components ``ids`` (the
    tile's own component ids, :func:`sarship.pipeline.targets.components.merge_tiles` ``members``,
    of the detections kept), read from the tile's label store; nothing else. Returns the tile's
    index and its count of kept pixels."""
    r0, r1, c0, c1 = job.bounds
    labels = np.asarray(open_array(job.label_path)[r0:r1, c0:c1])
    rows, cols = np.nonzero(labels)
    sel = np.isin(labels[rows, cols] - 1, np.asarray(ids, np.int64))
    write_points(job.mask_path, r0, c0, rows[sel], cols[sel], (r1 - r0, c1 - c0))
    return {"index": job.index, "kept_px": int(sel.sum()), "pixels": (r1 - r0) * (c1 - c0), "worker": _worker_name()}
