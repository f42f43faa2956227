"""GPU discovery and pinning, without creating a CUDA context in the calling process.

One Dask worker process per GPU, pinned by ``CUDA_VISIBLE_DEVICES`` set in the worker's
environment before it starts (dask-cuda's discipline), advertising the resource ``GPU``
(one unit per task slot: 2 slots by default, see :func:`worker_specs`); CPU workers
advertise ``CPU=1`` per thread. dask-cuda itself is not a
dependency: it pins exact dask releases (through rapids-dask-dependency) and what we need
from it is this module; ``sarship worker`` runs the same ``distributed.Nanny`` processes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time

from distributed.diagnostics.plugin import WorkerPlugin

from sarship.pipeline import settings
from sarship.pipeline.errors import InputError


class CudaWarmup(WorkerPlugin):
    """Create a GPU worker's CUDA context in the background once the worker has registered.

    Without it the context (and CuPy's memory pool) is made by the worker's first tile. The
    thread waits until the worker runs (registered with the scheduler), so the context is made
    while the client prepares and the land pass runs. ``SARSHIP_CUDA_WARMUP=0`` turns it off.

    Measured on the 25000 x 16700 band, ``sarship detect`` as typed, one H100, 4 fresh GPU
    worker processes, 7 interleaved pairs of commands (bench/RESULTS.md, issue 17, session 11):

    - the tiles' host-to-device seconds, summed: 3.1-3.4 s -> 0.7-0.8 s;
    - the tile stage: 1.35-2.19 s -> 0.73-1.02 s;
    - cluster start and land pass together: +0.5 s on average;
    - wall: mean 7.13 -> 6.81 s; 5 pairs faster, 1 equal, 1 slower.

    Started before registration instead, the contexts delayed the cluster's start (2.6-3.6 s
    on four H200s) and nothing was gained. A failure is left to the first tile, which reports
    it. Does nothing in a worker without ``SARSHIP_DEVICE=gpu`` or without CuPy."""

    name = "sarship-cuda-warmup"

    def setup(self, worker) -> None:
        if settings.read("device") != "gpu" or not settings.read("cuda_warmup"):
            return
        threading.Thread(target=_warm_cuda, args=(worker,), name="sarship-cuda-warmup", daemon=True).start()


def _warm_cuda(worker) -> None:
    try:
        t_end = time.monotonic() + 60
        while getattr(worker.status, "name", "") != "running" and time.monotonic() < t_end:
            time.sleep(0.01)
        from sarship.pipeline.gpu import cupy_module, init_device

        cp = cupy_module()
        if cp is None:
            return
        init_device()  # the memory pool's cap: creates the device's primary context
        cp.empty(1, dtype=cp.float32)
        cp.cuda.get_current_stream().synchronize()
    except Exception:  # noqa: BLE001 - the first tile meets the same error and reports it
        pass


def visible_gpus() -> list[str]:
    """IDs of the GPUs this process may use (as ``CUDA_VISIBLE_DEVICES`` entries).

    ``CUDA_VISIBLE_DEVICES`` if set; else the NVIDIA device nodes ``/dev/nvidia0``,
    ``/dev/nvidia1``, ... (what a container was given); else ``nvidia-smi -L``; [] when none
    answers. None of these touches CUDA or NVML in this process: a process that has called
    either carries the driver's ``cuda...`` thread, and ``sarship detect`` forks its workers
    only from a process without one (:func:`sarship.workers.cluster.cuda_initialised`).
    """
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        ids = [s.strip() for s in env.split(",") if s.strip()]
        return [] if not ids or ids[0] in ("-1", "NoDevFiles") else ids  # "" and "-1" hide all
    try:
        nodes = [n for n in os.listdir("/dev") if n.startswith("nvidia") and n[6:].isdigit()]
    except OSError:
        nodes = []
    if nodes:
        return [str(i) for i in range(len(nodes))]
    exe = shutil.which("nvidia-smi")
    if exe:
        try:
            out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=20).stdout
            return [str(i) for i, line in enumerate(l for l in out.splitlines() if l.startswith("GPU "))]
        except Exception:
            return []
    return []


def parse_gpus(text: str) -> list[str]:
    """``--gpus``: ``all`` (every visible GPU), ``none``, or a comma list of IDs."""
    t = (text or "").strip().lower()
    if t == "none":
        return []
    vis = visible_gpus()
    if t in ("all", ""):
        return vis
    ids = [s.strip() for s in t.split(",") if s.strip()]
    bad = [i for i in ids if vis and i not in vis]
    if bad:
        raise InputError(f"--gpus: GPU {', '.join(bad)} not visible (visible: {', '.join(vis) or 'none'})")
    if not vis:
        raise InputError(f"--gpus {text}: no GPU is visible on this machine")
    return ids


def worker_specs(
    gpu_ids: list[str],
    cpus: int,
    prefix: str,
    memory_limit: str | None = None,
    gpu_threads: int = 2,
    gpu_procs: int = 1,
    **options,
) -> dict[str, dict]:
    """``distributed.SpecCluster``-style worker specs: one pinned process per GPU, ``cpus``
    single-threaded CPU processes (``options``: more ``Nanny`` keyword arguments).

    ``gpu_threads``: tile tasks a GPU worker runs at once. Default 2: one tile's Zarr read
    and mask write (CPU, GIL released) overlap the other's transfer and kernels; measured on
    the 25000 x 16700 band with ``ca_cfar``, H200: 7.58 s with 1, 6.28 s with 2 (one GPU),
    4.39 / 3.00 s on two GPUs (bench/RESULTS.md). The worker advertises ``GPU=gpu_threads``
    and each tile asks for ``GPU=1``, so the scheduler fills both slots of one device.
    ``gpu_procs``: worker processes per GPU (each with ``gpu_threads`` threads), so that the
    Python parts of a tile (Zarr read and write, labelling) run on as many cores, each process
    with its own interpreter lock, while the kernels share the device. Each GPU worker
    creates its CUDA context once it has registered (:class:`CudaWarmup`).
    """
    from distributed import Nanny

    specs: dict[str, dict] = {}
    for gid in gpu_ids:
        for k in range(max(1, int(gpu_procs))):
            name = f"{prefix}gpu{gid}" + (f"-{k}" if gpu_procs > 1 else "")
            env = {"CUDA_VISIBLE_DEVICES": str(gid), "SARSHIP_DEVICE": "gpu"}
            specs[name] = {
                "cls": Nanny,
                "options": {
                    "name": name,
                    "nthreads": gpu_threads,
                    "resources": {"GPU": gpu_threads},
                    "plugins": {CudaWarmup()},
                    "env": env,
                    **_mem(memory_limit),
                    **options,
                },
            }
    for k in range(cpus):
        name = f"{prefix}cpu{k}"
        # a CPU worker must not grab a GPU by accident: hide them. An empty value, not "-1":
        # Dask's NVML monitor parses the first entry as a device index and "-1" fails the
        # worker's start (the Nanny applies ``env`` after the child has read Dask's config,
        # so the monitor cannot be switched off from here).
        env = {"CUDA_VISIBLE_DEVICES": "", "SARSHIP_DEVICE": "cpu"} if gpu_ids else {"SARSHIP_DEVICE": "cpu"}
        specs[name] = {
            "cls": Nanny,
            "options": {
                "name": name,
                "nthreads": 1,
                "resources": {"CPU": 1},
                "env": env,
                **_mem(memory_limit),
                **options,
            },
        }
    return specs


def _mem(limit: str | None) -> dict:
    return {} if limit is None else {"memory_limit": limit}
