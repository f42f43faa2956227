"""``sarship enhance``: scene -> scene image-quality enhancement on the Dask cluster.

Destriping (docs/algorithms/destripe.md) runs as detection does, one task per tile:

1. scene pass: each tile task reads its tile (no halo) straight from the store and returns
   its exact segment sums of ``ln P`` (:func:`sarship.pipeline.image.destripe.segment_sums`);
2. the client assembles them (integer sums: the same for every tiling), finds the stripe
   bins (Otsu + Hough) and the stripe profile (:func:`sarship.pipeline.image.destripe.estimate`);
3. each tile task reads every variable of its tile, multiplies it by the stripe gain of its
   columns (rows) and writes exactly its chunk of the output store.

The output store is a new scene (same variables, tiling and attributes, plus an
``enhance`` record) written to a temporary sibling and renamed into place at the end; an
existing ``OUT`` is refused unless ``overwrite``, and ``OUT`` may never be (or be inside)
the input.
"""

from __future__ import annotations

import contextlib
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline import __version__
from sarship.pipeline.errors import InputError
from sarship.pipeline.image.destripe import DestripeParams, apply_gain, assemble, estimate, segment_sums
from sarship.pipeline.scene import atomic_store, create_scene, finalize_scene, open_scene, tile_slices
from sarship.pipeline.tiling.inputs import intensity_source, make_reader


@dataclass(frozen=True)
class EnhanceTile:
    scene_path: str
    var: str
    transform: str
    index: tuple[int, int]
    bounds: tuple[int, int, int, int]  # r0, r1, c0, c1


def tile_stats(job: EnhanceTile, params: DestripeParams) -> dict[str, Any]:
    """Scene pass of one tile: its exact segment sums of ``ln P``."""
    r0, r1, c0, c1 = job.bounds
    block = make_reader(job.scene_path, job.var, job.transform)(r0, r1, c0, c1)
    part = segment_sums(block, r0, c0, params)
    return {"index": job.index, "part": part, "pixels": (r1 - r0) * (c1 - c0)}


def tile_apply(
    job: EnhanceTile,
    out_path: str,
    variables: dict[str, str],
    amplitude: dict[str, bool],
    profile_part: np.ndarray,
    params: DestripeParams,
) -> dict[str, Any]:
    """Filter one tile of every variable and write it into the output store."""
    import zarr

    r0, r1, c0, c1 = job.bounds
    for name in variables:
        src = zarr.open_array(f"{job.scene_path}/{name}", mode="r")
        dst = zarr.open_array(f"{out_path}/{name}", mode="r+")
        dst[r0:r1, c0:c1] = apply_gain(
            np.asarray(src[r0:r1, c0:c1]), profile_part, params, complex_amplitude=amplitude[name]
        )
    return {"index": job.index, "pixels": (r1 - r0) * (c1 - c0)}


def check_enhance_out(out: Path, scene_path: Path, overwrite: bool) -> None:
    """Refuse ``out`` equal to, inside or containing the input, and an existing ``out``
    without ``overwrite``."""
    o, s = out.resolve(), scene_path.resolve()
    if o == s or s in o.parents or o in s.parents:
        raise InputError(
            f"--out '{out}' is the input scene '{scene_path}', inside it or around it: "
            "choose another path (not even --overwrite writes into an input)"
        )
    if out.exists() and not overwrite:
        raise InputError(f"output '{out}' already exists: pass --overwrite to replace it")
    if out.exists() and not (out / "zarr.json").is_file():
        raise InputError(f"output '{out}' exists and is not a scene store: not replacing it")


def _amplitude(scene_kind: str, dtype: str) -> bool:
    """Complex channels of SLC/quad-pol scenes are amplitudes (gain exp(-s/2)); covariance
    elements and intensity are powers (gain exp(-s))."""
    return "complex" in dtype and scene_kind != "covariance"


def run_enhance(
    scene_path: str | Path,
    out: str | Path,
    destripe: DestripeParams | None = None,
    client=None,
    scheduler: str | None = None,
    progress: bool = True,
    overwrite: bool = False,
    channel: str | None = None,
) -> dict[str, Any]:
    """Destripe ``scene_path`` into the new scene store ``out``; returns the ``enhance`` record."""
    from sarship.workers.progress import Progress

    t0 = time.perf_counter()
    params = destripe or DestripeParams()
    scene = open_scene(scene_path)
    out = Path(out)
    check_enhance_out(out, Path(scene_path), overwrite)
    src = Path(scene_path).absolute()
    var, transform = intensity_source(scene, channel)
    if transform not in ("real", "abs2"):
        raise InputError(
            f"sarship enhance: scene '{scene_path}' of kind '{scene.kind}': destriping reads "
            f"intensity or a complex channel, got '{var}' ({transform})"
        )
    H, W = scene.shape
    jobs = [
        EnhanceTile(str(src), var, transform, (i, j), (r0, r1, c0, c1))
        for i, j, r0, r1, c0, c1 in tile_slices((H, W), scene.tile)
    ]
    with contextlib.ExitStack() as stack:
        if client is None:
            from sarship.workers.cluster import connect

            client = stack.enter_context(connect(scheduler, short_lived=True))
        tag = uuid.uuid4().hex[:6]
        stats = _run(
            client,
            tile_stats,
            jobs,
            [f"sarship-destripe-stats-{j.index[0]}-{j.index[1]}-{tag}" for j in jobs],
            Progress(len(jobs), "enhance: stripe spectrum", progress),
            params=params,
        )
        t_pass = time.perf_counter()
        sums, counts = assemble([s["part"] for s in sorted(stats, key=lambda s: s["index"])], (H, W), params)
        est = estimate(sums, counts, params)
        t_est = time.perf_counter()
        record = {"destripe": {**est.record(), "estimated_on": var}}
        amp = {name: _amplitude(scene.kind, dt) for name, dt in scene.variables.items()}
        with atomic_store(out, overwrite=overwrite) as tmp:
            attrs = {k: v for k, v in scene.attrs.items()}
            prior = attrs.get("enhance")
            create_scene(
                tmp, (H, W), {k: np.dtype(v) for k, v in scene.variables.items()}, tile=scene.tile, attrs=attrs
            )
            prof = est.profile
            futures_args = []
            for j in jobs:
                r0, r1, c0, c1 = j.bounds
                part = prof[c0:c1] if params.stripes_along == "azimuth" else prof[r0:r1]
                futures_args.append((j, part))
            keys = [f"sarship-destripe-apply-{j.index[0]}-{j.index[1]}-{tag}" for j in jobs]
            bar = Progress(len(jobs), "enhance: destripe", progress)
            futures = [
                client.submit(tile_apply, j, str(tmp.absolute()), scene.variables, amp, part, params, key=k, pure=False)
                for (j, part), k in zip(futures_args, keys)
            ]
            _gather(client, futures, bar)
            t_apply = time.perf_counter()
            record["destripe"]["timings"] = {
                "spectrum_s": round(t_pass - t0, 4),
                "estimate_s": round(t_est - t_pass, 4),
                "filter_s": round(t_apply - t_est, 4),
            }
            record["input"] = str(src)
            record["sarship_version"] = __version__
            history = (prior if isinstance(prior, list) else [prior] if prior else []) + [record]
            finalize_scene(tmp, {"enhance": history})
    return record


def _run(client, fn, jobs, keys, bar, **kw) -> list[dict[str, Any]]:
    futures = [client.submit(fn, j, key=k, pure=False, **kw) for j, k in zip(jobs, keys)]
    return _gather(client, futures, bar)


def _gather(client, futures, bar) -> list[dict[str, Any]]:
    from distributed import as_completed

    out = []
    try:
        for fut in as_completed(futures):
            res = fut.result()
            out.append(res)
            bar.step(res["pixels"])
    except BaseException:
        client.cancel(futures)
        raise
    return out
