"""The quantity a detector reads from a scene, cut out tile by tile.

Single-channel detectors (``two_parameter``, ``ca_cfar``, ``os_cfar``) read intensity:
the scene's ``intensity`` variable, else |S|^2 of a complex channel (``hh`` first, then
``vv``, ``vh``, ``hv``), else the covariance diagonal ``c11``. The ``channel`` parameter
(any scene variable) overrides the choice.

Polarimetric detectors (``DetectorSpec.input == "polarimetric"``, e.g. ``apwf``) read the
scene's complex channels stacked on a trailing axis, :func:`polarimetric_source`: quad-pol
``[hh, hv, vv]`` (p = 3; ``vh`` is not used when ``hv`` is there, reciprocity), dual-pol
``[hh, hv]``, ``[vh, vv]`` or ``[hh, vv]`` (p = 2), always in the order hh, hv, vh, vv.
The reader (transform ``"stack"``) returns a complex64 ``(rows, cols, p)`` block.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import COVARIANCE2_VARS, COVARIANCE_VARS, Scene

_PREFERENCE = ("intensity", "hh", "vv", "vh", "hv", "c11")


def intensity_source(scene: Scene, channel: str | None = None) -> tuple[str, str]:
    """``(variable, transform)`` giving intensity; transform is ``real`` or ``abs2``."""
    if channel is not None:
        if channel not in scene.variables:
            raise InputError(
                f"parameter 'channel': scene has no variable '{channel}' (has: {', '.join(scene.variables)})"
            )
        var = channel
    else:
        var = next((v for v in _PREFERENCE if v in scene.variables), None)
        if var is None:
            raise InputError(
                f"scene '{scene.path}' has no intensity, complex channel or c11 variable "
                f"(has: {', '.join(scene.variables)})"
            )
    transform = "abs2" if "complex" in scene.variables[var] else "real"
    return var, transform


_POL_ORDER = ("hh", "hv", "vh", "vv")


def complex_source(scene: Scene, channel: str | None = None) -> tuple[str, str]:
    """``(variable, "complex")``: the complex single-look channel a complex-valued detector
    (``DetectorSpec.input == "slc"``, e.g. ``csk``) reads: ``channel`` when given (it must be
    complex), else the first complex one of hh, vv, vh, hv. Amplitude or intensity data carry
    no phase: :class:`InputError` saying so, naming what the scene has."""
    has = ", ".join(f"{k} ({v})" for k, v in scene.variables.items()) or "nothing"
    if channel is not None:
        if channel not in scene.variables:
            raise InputError(f"parameter 'channel': scene has no variable '{channel}' (has: {has})")
        if "complex" not in scene.variables[channel]:
            raise InputError(
                f"parameter 'channel': variable '{channel}' is not complex; this detector reads a "
                f"complex single-look (SLC) channel, amplitude or intensity has no phase (scene has: {has})"
            )
        return channel, "complex"
    var = next((v for v in ("hh", "vv", "vh", "hv") if "complex" in scene.variables.get(v, "")), None)
    if var is None:
        raise InputError(
            f"scene '{scene.path}' has no complex SLC channel (hh, vv, vh or hv complex64): this detector "
            f"needs the phase of single-look complex data, amplitude or intensity is refused "
            f"(scene has: {has}; ingest the SLC product, e.g. sarship ingest --kind slc)"
        )
    return var, "complex"


def polarimetric_source(scene: Scene, channels: str | None = None) -> tuple[tuple[str, ...], str]:
    """``(variables, "stack")``: the scene's complex channels a polarimetric detector reads.

    Order hh, hv, vh, vv; with all of ``hh``, ``hv``, ``vv`` present: ``[hh, hv, vv]``
    (quad-pol, p = 3; ``[hh, vh, vv]`` when the scene has vh instead of hv); otherwise the complex channels among hh/hv/vh/vv (dual-pol, p = 2:
    ``[hh, hv]``, ``[vh, vv]``, ``[hh, vv]``, ...). ``channels`` (comma-separated scene
    variables, e.g. ``"hh,vv"``) overrides the choice; each must be complex. Fewer than two
    complex channels: :class:`InputError` naming what the scene has.
    """

    def is_complex(v: str) -> bool:
        return "complex" in scene.variables.get(v, "")

    has = ", ".join(f"{k} ({v})" for k, v in scene.variables.items()) or "nothing"
    if channels is not None:
        names = [c.strip() for c in str(channels).split(",") if c.strip()]
        for c in names:
            if c not in scene.variables:
                raise InputError(f"parameter 'channel': scene has no variable '{c}' (has: {has})")
            if not is_complex(c):
                raise InputError(
                    f"parameter 'channel': variable '{c}' is not complex "
                    f"(a polarimetric detector needs complex channels; scene has: {has})"
                )
        if len(set(names)) != len(names) or not 2 <= len(names) <= 3:
            raise InputError(f"parameter 'channel': give 2 or 3 distinct complex channels, got '{channels}'")
        return tuple(names), "stack"
    found = [v for v in _POL_ORDER if is_complex(v)]
    if len(found) < 2 and "c11" in scene.variables and "c12" in scene.variables:
        # covariance scene (C3 or C2): the reader assembles (rows, cols, p, p) matrices
        if all(v in scene.variables for v in COVARIANCE_VARS):
            return COVARIANCE_VARS, "covariance"
        if all(v in scene.variables for v in COVARIANCE2_VARS):
            return COVARIANCE2_VARS, "covariance"
    if all(v in found for v in ("hh", "hv", "vv")):
        return ("hh", "hv", "vv"), "stack"
    if len(found) < 2:
        raise InputError(
            f"scene '{scene.path}' has {len(found)} complex polarimetric channel(s) "
            f"({', '.join(found) or 'none'}); a polarimetric detector needs at least two of "
            f"hh, hv, vh, vv (scene has: {has})"
        )
    return tuple(found), "stack"


def detector_source(spec: Any, scene: Scene, channel: str | None = None) -> tuple[Any, str]:
    """``(variable(s), transform)`` that detector ``spec`` reads from ``scene``: the one check
    of a detector against a scene, used by the command line and the job runner
    (:func:`sarship.workers.jobs.run_request`) and by the service when a job is submitted, so
    that a detector that cannot run on a scene is refused before any work (exit 2 / a 400).

    By ``spec.input``: ``polarimetric`` reads :func:`polarimetric_source` (complex channels,
    or a C3/C2 covariance scene only when ``spec.covariance``), ``slc`` reads
    :func:`complex_source`, anything else :func:`intensity_source`. :class:`InputError`, one
    line naming the detector, what it reads and what the scene has, otherwise."""
    if spec.input == "polarimetric":
        var, transform = polarimetric_source(scene, channel)
        if transform == "covariance" and not getattr(spec, "covariance", True):
            raise InputError(
                f"detector '{spec.name}' reads complex polarimetric channels (2 or 3 of hh, hv, vh, vv: a dual- or "
                f"quad-pol SLC), not a covariance matrix; this scene is a {'C3' if len(var) == 6 else 'C2'} "
                f"covariance scene ({', '.join(var)}): use apwf or pcdm, which read covariance scenes"
            )
        return var, transform
    if spec.input == "slc":
        return complex_source(scene, channel)
    return intensity_source(scene, channel)


def reader_backend() -> str:
    """The library that reads scene arrays: ``SARSHIP_READER`` if set, else tensorstore when it
    imports, else zarr-python. Both read the same Zarr v3 stores to the same values;
    tensorstore's C++ path decodes 2-3x faster and in parallel (zarr-python runs every read of a
    process through its one event loop: bench/RESULTS.md, "Issue 17, session 10")."""
    from sarship.pipeline import settings

    want = settings.read("reader")
    if want == "zarr":
        return "zarr"
    try:
        import tensorstore  # noqa: F401
    except ImportError:
        if want == "tensorstore":
            raise InputError(
                "SARSHIP_READER=tensorstore, but tensorstore is not installed (pip install tensorstore)"
            ) from None
        return "zarr"
    return "tensorstore"


_TS_CONTEXT: tuple[int, Any] | None = None


def _ts_context():
    """One tensorstore context per process (its thread pools and concurrency limits shared by
    every array the process opens, instead of a new set for each open); made again in a forked
    child, whose copy of the parent's pools has no threads. No cache pool: reads see the store."""
    global _TS_CONTEXT
    import os

    import tensorstore as ts

    pid = os.getpid()
    if _TS_CONTEXT is None or _TS_CONTEXT[0] != pid:
        _TS_CONTEXT = (pid, ts.Context())
    return _TS_CONTEXT[1]


class _TensorStoreArray:
    """A 2-D Zarr v3 array through tensorstore: ``a[ra:rb, ca:cb]`` -> NumPy, with NumPy's
    clipping of slices at the array's edges (as zarr-python does); ``write``: also
    ``a[ra:rb, ca:cb] = values`` (chunks equal to the fill value are not stored, as zarr-python's
    ``write_empty_chunks=False``). ``chunks``: the inner (read) chunk shape."""

    def __init__(self, path: str, write: bool = False):
        import tensorstore as ts

        self._t = ts.open(
            {"driver": "zarr3", "kvstore": {"driver": "file", "path": path}},
            read=True,
            write=write,
            open=True,
            context=_ts_context(),
        ).result()
        self.shape = tuple(int(s) for s in self._t.shape)
        self.chunks = tuple(int(s) for s in self._t.chunk_layout.read_chunk.shape)

    def __setitem__(self, key, values) -> None:
        rs, cs = key
        self._t[rs, cs].write(np.ascontiguousarray(values)).result()

    def __getitem__(self, key) -> np.ndarray:
        rs, cs = key
        r = range(*rs.indices(self.shape[0]))
        c = range(*cs.indices(self.shape[1]))
        if r.step < 1 or c.step < 1:
            raise ValueError("only slices with step >= 1 are supported")
        if len(r) == 0 or len(c) == 0:
            return np.empty((len(r), len(c)), self._t.dtype.numpy_dtype)
        a = self._t[r[0] : r[-1] + 1, c[0] : c[-1] + 1].read().result()
        return a if r.step == 1 and c.step == 1 else a[:: r.step, :: c.step]


def open_array(path: str, write: bool = False):
    """A 2-D Zarr v3 array for reading rectangles (``a[ra:rb, ca:cb]``; ``write``: and writing
    them, without storing chunks equal to the fill value), through :func:`reader_backend`."""
    if reader_backend() == "tensorstore":
        try:
            return _TensorStoreArray(path, write)
        except ValueError as exc:  # e.g. a store tensorstore cannot read: zarr-python reads it
            import warnings

            warnings.warn(f"tensorstore cannot open '{path}' ({exc}); using zarr-python", stacklevel=2)
    import zarr

    if write:
        return zarr.open_array(path, mode="r+", config={"write_empty_chunks": False})
    return zarr.open_array(path, mode="r")


def window_reader(path) -> Callable[[int, int, int, int], np.ndarray]:
    """``read(ra, rb, ca, cb)`` of the 2-D Zarr array at ``path`` as it is stored (e.g. the uint8
    detection and land masks), through :func:`open_array` (tensorstore when it imports)."""
    arr = open_array(str(path))

    def read(ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
        return np.asarray(arr[ra:rb, ca:cb])

    return read


def make_reader(path: str, var: str | tuple[str, ...], transform: str) -> Callable[[int, int, int, int], np.ndarray]:
    """``read(ra, rb, ca, cb)`` -> float32 intensity of the scene rectangle (transform
    ``"complex"``: the complex64 channel itself).

    With a tuple of variables and transform ``"stack"``: the complex64 channels of the
    rectangle stacked on a trailing axis, shape ``(rb - ra, cb - ca, p)``. With transform
    ``"covariance"`` (variables :data:`COVARIANCE_VARS` or :data:`COVARIANCE2_VARS`): the Hermitian
    matrices, shape ``(rb - ra, cb - ca, p, p)``. Arrays are read through :func:`open_array`.
    """
    if not isinstance(var, str) and transform == "covariance":
        p = 3 if len(var) == 6 else 2
        arrs = {v: open_array(f"{path}/{v}") for v in var}

        def read_cov(ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
            out = np.empty((rb - ra, cb - ca, p, p), np.complex64)
            for i in range(p):
                for j in range(i, p):
                    a = np.asarray(arrs[f"c{i + 1}{j + 1}"][ra:rb, ca:cb])
                    out[:, :, i, j] = a
                    if j != i:
                        out[:, :, j, i] = np.conj(a)
            return out

        return read_cov
    if not isinstance(var, str):
        if transform != "stack":
            raise ValueError(f"several variables need transform 'stack', got '{transform}'")
        arrs = [open_array(f"{path}/{v}") for v in var]

        def read_stack(ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
            out = np.empty((rb - ra, cb - ca, len(arrs)), np.complex64)
            for k, a in enumerate(arrs):
                out[:, :, k] = a[ra:rb, ca:cb]
            return out

        return read_stack

    arr = open_array(f"{path}/{var}")

    def read(ra: int, rb: int, ca: int, cb: int) -> np.ndarray:
        a = arr[ra:rb, ca:cb]
        if transform == "complex":  # a complex channel as it is (complex-valued detectors: input "slc")
            return np.asarray(a, dtype=np.complex64)
        if transform == "abs2":
            return (a.real.astype(np.float32) ** 2 + a.imag.astype(np.float32) ** 2).astype(np.float32)
        return np.asarray(a, dtype=np.float32)

    return read


def span(x: np.ndarray) -> np.ndarray:
    """Sum over the trailing axis of |x|^2 (float32): the span of stacked channels.

    Plain sum of the channels' powers (|hh|^2 + |hv|^2 + |vv|^2 for quad-pol), not the
    lexicographic |hh|^2 + 2|hv|^2 + |vv|^2 of the simulator's SCR definition.
    """
    xr = x.real.astype(np.float32)
    xi = x.imag.astype(np.float32)
    return (xr * xr + xi * xi).sum(axis=-1, dtype=np.float32)


def pixel_power(values: np.ndarray) -> np.ndarray:
    """The power of each pixel of what a detector read, for the detections' ``peak`` and
    ``mean``: intensity as it is (2-D), the :func:`span` of stacked complex channels
    (``(rows, cols, p)``), the trace of covariance matrices (``(rows, cols, p, p)``)."""
    if values.ndim == 3:
        return span(values)
    if values.ndim == 4:
        return np.trace(values, axis1=2, axis2=3).real.astype(np.float32)
    if np.iscomplexobj(values):  # one complex channel (input "slc"): |z|^2
        return (values.real.astype(np.float32) ** 2 + values.imag.astype(np.float32) ** 2).astype(np.float32)
    return values
