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

from sarship.pipeline.errors import InputError


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


def worker_specs(gpu_ids: list[str], cpus: int, prefix: str, memory_limit: str | None = None,
                 gpu_threads: int = 2, gpu_procs: int = 1, **options) -> dict[str, dict]:
    """``distributed.SpecCluster``-style worker specs: one pinned process per GPU, ``cpus``
    single-threaded CPU processes (``options``: more ``Nanny`` keyword arguments).

    ``gpu_threads``: tile tasks a GPU worker runs at once. Default 2: one tile's Zarr read
    and mask write (CPU, GIL released) overlap the other's transfer and kernels; measured on
    the 25000 x 16700 band with ``ca_cfar``, H200: 7.58 s with 1, 6.28 s with 2 (one GPU),
    4.39 / 3.00 s on two GPUs (bench/RESULTS.md). The worker advertises ``GPU=gpu_threads``
    and each tile asks for ``GPU=1``, so the scheduler fills both slots of one device.
    ``gpu_procs``: worker processes per GPU (each with ``gpu_threads`` threads), so that the
    Python parts of a tile (Zarr read and write, labelling) run on as many cores, each process
    with its own interpreter lock, while the kernels share the device.
    """
    from distributed import Nanny

    specs: dict[str, dict] = {}
    for gid in gpu_ids:
        for k in range(max(1, int(gpu_procs))):
            name = f"{prefix}gpu{gid}" + (f"-{k}" if gpu_procs > 1 else "")
            env = {"CUDA_VISIBLE_DEVICES": str(gid), "SARSHIP_DEVICE": "gpu"}
            specs[name] = {"cls": Nanny, "options": {"name": name, "nthreads": gpu_threads,
                                                      "resources": {"GPU": gpu_threads},
                                                      "env": env, **_mem(memory_limit), **options}}
    for k in range(cpus):
        name = f"{prefix}cpu{k}"
        # a CPU worker must not grab a GPU by accident: hide them. An empty value, not "-1":
        # Dask's NVML monitor parses the first entry as a device index and "-1" fails the
        # worker's start (the Nanny applies ``env`` after the child has read Dask's config,
        # so the monitor cannot be switched off from here).
        env = {"CUDA_VISIBLE_DEVICES": "", "SARSHIP_DEVICE": "cpu"} if gpu_ids else {"SARSHIP_DEVICE": "cpu"}
        specs[name] = {"cls": Nanny, "options": {"name": name, "nthreads": 1, "resources": {"CPU": 1},
                                                  "env": env, **_mem(memory_limit), **options}}
    return specs


def _mem(limit: str | None) -> dict:
    return {} if limit is None else {"memory_limit": limit}
