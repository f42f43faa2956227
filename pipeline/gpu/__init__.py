"""GPU (CuPy) versions of the detectors' maths, dispatched on the array type.

A detector's public ``detect(block, ...)`` runs on the GPU when ``block`` is a CuPy array
and returns CuPy ``(mask, stat)``; with a NumPy block it runs the CPU code (as dask-image
and xarray-spatial dispatch on the array type). Thresholds and every other scalar come
from the same ``prepare`` on the client, so the maths that sets a result lives in one
place; the per-pixel arithmetic is written in the same order as the CPU kernels, with
floating-point contraction disabled (``--fmad=false``), so that most results are
bit-identical and the rest differ in the last bits (tests count them).

CuPy is optional (the ``gpu`` extra): nothing here imports it at module import time.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

from sarship.pipeline import settings

#: Fraction of the device memory the CuPy pool may hold (``SARSHIP_GPU_POOL_FRACTION``).
DEFAULT_POOL_FRACTION = settings.VARIABLES["gpu_pool_fraction"].default


def cupy_module():
    """The ``cupy`` module, or None when CuPy is not installed."""
    try:
        import cupy
    except Exception:  # ImportError, or a CUDA library error at import
        return None
    return cupy


@functools.cache
def twin(ref: str) -> Any:
    """The GPU twin named by ``ref``: ``"package.module"`` (the module) or ``"package.module:name"``
    (one of its attributes), imported on first use. The one place where a detector's CPU code
    reaches its device code (``DetectorSpec.gpu``, docs/adding-a-detector.md): the twin imports
    the detector's maths, the detector names its twin, so no import goes both ways."""
    module, _, name = ref.partition(":")
    mod = importlib.import_module(module)
    return getattr(mod, name) if name else mod


def is_device_array(a: Any) -> bool:
    """True for a CuPy array (checked without importing CuPy)."""
    return type(a).__module__.startswith("cupy")


@functools.lru_cache(maxsize=1)
def device_count() -> int:
    """Number of CUDA devices visible to this process (0 without CuPy or a driver).

    Creates a CUDA context only in the process that calls it; the cluster code counts GPUs
    with :func:`sarship.workers.gpus.visible_gpus` (device nodes / nvidia-smi) instead, before pinning.
    """
    cp = cupy_module()
    if cp is None:
        return 0
    try:
        return int(cp.cuda.runtime.getDeviceCount())
    except Exception:
        return 0


def available() -> bool:
    """CuPy importable and at least one CUDA device usable."""
    return device_count() > 0


_POOL_SET = False


def init_device() -> None:
    """Idempotent per-process set-up: cap CuPy's memory pool, with headroom.

    The pool may hold ``SARSHIP_GPU_POOL_FRACTION`` (default 0.8) of the device's memory;
    tile buffers are reused from the pool between tiles instead of being re-allocated.
    """
    global _POOL_SET
    if _POOL_SET:
        return
    cp = cupy_module()
    if cp is None:
        raise RuntimeError("CuPy is not installed (pip install 'sarship[gpu]')")
    frac = settings.read("gpu_pool_fraction")
    cp.get_default_memory_pool().set_limit(fraction=min(max(frac, 0.05), 1.0))
    _POOL_SET = True


def to_device(a):
    """Host array to the current device (one transfer)."""
    cp = cupy_module()
    return cp.asarray(a)


def synchronize() -> None:
    """Wait for the current device's work (for honest timings)."""
    cp = cupy_module()
    cp.cuda.get_current_stream().synchronize()


def to_host(a):
    """Device array to a NumPy array (identity for NumPy)."""
    if is_device_array(a):
        return a.get()
    return a
