"""`sarship ingest`: turn SAR images into a scene store (see :mod:`sarship.pipeline.scene`).

:func:`ingest` reads one or more inputs and writes a Zarr v3 scene of square ``tile x tile``
zstd chunks, **tile by tile**, into a temporary sibling that is renamed into place only when
complete (:func:`sarship.pipeline.scene.atomic_store`): a failure leaves nothing behind and an
existing scene at ``out`` untouched.

Inputs are files recognised by their first bytes, or folders (PolSARpro, SAFE, Zarr) by their
file names: each input is opened by the first reader of the registry
(:data:`sarship.pipeline.readers.registry.READERS`, :mod:`.formats`; adding one:
``docs/adding-a-reader.md``) whose ``detect`` takes it. What each format accepts is in the
docstring of its module:
:mod:`sarship.pipeline.readers.tiff` (TIFF / GeoTIFF / BigTIFF, GeoTIFF georeference, SNAP
sidecar), :mod:`sarship.pipeline.readers.image` (PNG / JPEG), :mod:`sarship.pipeline.readers.npy`,
:mod:`sarship.pipeline.readers.polsarpro` (C3 / T3 / C2 folders; the covariance convention)
:mod:`sarship.pipeline.readers.safe` (Sentinel-1 GRD SAFE folder or zip: calibration,
thermal noise, geolocation grid), :mod:`sarship.pipeline.readers.safe_slc` (one sub-swath of
an IW SLC, ``swath``: debursted, calibrated, deramped) and :mod:`sarship.pipeline.readers.zarr_input` (a Zarr scene). How real samples are taken
(the ``auto`` rule), band and channel names and stacking: :mod:`sarship.pipeline.readers.plan`.
Looks: :mod:`sarship.pipeline.readers.writing`.

Anything else, and any file that cannot be read, raises :class:`InputError` with one line
naming the file and the problem.

Attributes written
------------------
``kind``, ``looks``, ``looks_source``, ``tile``, ``source`` (input file names),
``channels``, ``quantity`` (what the input samples were), ``quantity_rule``,
``sample_dtype``, ``sarship_version``; and when known ``intensity_band``,
``pixel_spacing_m`` ([azimuth, range]; for map-projected GeoTIFFs [row, column] ground
spacing) with ``pixel_spacing_source``, ``crs`` ("EPSG:n") + ``transform`` (GDAL order
``[c, a, b, f, d, e]``, PixelIsPoint shifted to PixelIsArea as GDAL does) or ``gcps``,
``sensor``, ``acquired`` (ISO 8601), ``product``, ``polarisations``.
"""

from __future__ import annotations

import errno
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line, _Source
from sarship.pipeline.readers.formats import _open_safe  # noqa: F401 - where tests and tools find it
from sarship.pipeline.readers.limits import InputLimits
from sarship.pipeline.readers.plan import _plan
from sarship.pipeline.readers.protocol import Reader, SceneReader
from sarship.pipeline.readers.registry import READERS, choose
from sarship.pipeline.readers.writing import (
    _estimate_scene_looks,
    _rank_one_looks,
    _write_tiles,
    choose_codec,
    ingest_writers,
)
from sarship.pipeline.scene import (
    DEFAULT_INGEST_CODEC,
    DEFAULT_TILE,
    INGEST_CODECS,
    Scene,
    atomic_store,
    claim_output,
    create_scene,
    finalize_scene,
    open_scene,
)

#: errno of a full disk, a quota or a file-size limit: an ingest that meets one fails with the
#: OSError itself (a fault of the machine, not of the input: the service retries it).
_STORAGE_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)

#: ``kind`` values accepted by :func:`ingest`.
INGEST_KINDS = ("auto", "amplitude", "intensity", "slc", "quadpol", "covariance")

#: A source that prefers whole tile rows (stripped TIFF) is read a tile row at a time when
#: the row band is at most this many bytes; otherwise tile by tile.
ROW_BAND_BYTES = 256 * 2**20


def _open_source(
    p: Path, sidecar_root: Path | bool | None = None, limits: InputLimits | None = None, swath: str | None = None
) -> _Source:
    """The input ``p`` opened by the reader :func:`~.registry.choose` picks for it (:func:`_open_with`)."""
    return _open_with(choose(p), p, sidecar_root, limits, swath)


def _open_with(
    reader: Reader,
    p: Path,
    sidecar_root: Path | bool | None = None,
    limits: InputLimits | None = None,
    swath: str | None = None,
) -> _Source:
    """``p`` opened by ``reader``.

    Raises :class:`InputError` (one line) when ``swath`` is given to a reader without
    sub-swaths, or the reader fails (a failure other than an InputError named ``cannot read as
    NAME``).
    """
    if swath is not None and not reader.takes_swath:
        raise InputError(f"'{p}': --swath applies to Sentinel-1 SLC products only")
    try:
        return reader.open(p, limits or InputLimits(), sidecar_root=sidecar_root, swath=swath)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"'{p}': cannot read as {reader.name.upper()} ({_one_line(exc)})") from None


def _check_readers(paths: list[Path], readers: list[Reader], kind: str, swath: str | None) -> None:
    """What the chosen readers refuse before anything is opened, in the registry's order: a
    ``kind`` that does not fit, ``--swath`` where no reader takes it, and an input that must
    stand alone combined with others."""
    chosen = [r for r in READERS if r in readers]
    for r in chosen:
        r.check(paths[readers.index(r)], kind)
    if swath is not None and not any(r.takes_swath for r in readers):
        raise InputError(f"'{paths[0]}': --swath applies to Sentinel-1 SLC products only")
    if len(paths) > 1:
        for r in chosen:
            if r.alone is not None:
                raise InputError(f"'{paths[readers.index(r)]}': {r.alone}")


# --------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------


class _CallbackError(Exception):
    """An exception raised by the caller's progress callback: re-raised unchanged by ingest."""

    def __init__(self, exc: Exception):
        super().__init__(str(exc))
        self.exc = exc


def _check_args(inputs, out, kind, tile, looks, channels, overwrite=True):
    if kind not in INGEST_KINDS:
        raise InputError(f"--kind must be one of {', '.join(INGEST_KINDS)}; got '{kind}'")
    try:
        tile_i = int(tile)
    except (TypeError, ValueError):
        raise InputError(f"--tile must be a positive number of pixels, got {tile!r}") from None
    if (isinstance(tile, float) and not tile.is_integer()) or tile_i < 1:
        raise InputError(f"--tile must be a positive number of pixels, got {tile!r}")
    if looks is not None:
        try:
            lv = float(looks)
        except (TypeError, ValueError):
            raise InputError(f"--looks must be a positive number, got {looks!r}") from None
        if not (math.isfinite(lv) and lv > 0):
            raise InputError(f"--looks must be a positive number, got {looks!r}")
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("ingest needs at least one input")
    for p in paths:
        if not p.exists():
            raise InputError(f"input '{p}' does not exist")
    if channels is not None and isinstance(channels, str):
        channels = [c for c in re.split(r"[,\s]+", channels) if c]
    outp = Path(out)
    for p in paths:
        try:
            o, i = outp.resolve(), p.resolve()
        except OSError:
            continue
        if o == i or i in o.parents:
            raise InputError(
                f"--out '{outp}' is "
                + ("also an input" if o == i else f"inside the input '{p}'")
                + ": choose a path outside the inputs (not even --overwrite writes into an input)"
            )
        if o in i.parents:
            raise InputError(f"--out '{outp}' holds the input '{p}': choose another path")
    if outp.exists() and not (outp.is_dir() and ((outp / "zarr.json").exists() or (outp / ".zgroup").exists())):
        raise InputError(f"--out '{outp}' exists and is not a Zarr scene: refusing to overwrite it")
    if outp.exists() and not overwrite:
        raise InputError(f"--out '{outp}' already exists: pass --overwrite to replace it")
    return paths, outp, tile_i, channels


def _check_spacing(spacing) -> list[float] | None:
    """``spacing``: None, (azimuth, range) metres, or the text 'AZ,RG'; two positive numbers."""
    if spacing is None:
        return None
    parts = [x for x in re.split(r"[,\s]+", spacing.strip()) if x] if isinstance(spacing, str) else list(spacing)
    try:
        vals = [float(x) for x in parts]
    except (TypeError, ValueError):
        vals = []
    if len(vals) != 2 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise InputError(f"--spacing expects two positive numbers of metres AZ,RG (azimuth, range), got {spacing!r}")
    return vals


def ingest(
    inputs: list[str | Path],
    out: str | Path,
    kind: str = "auto",
    tile: int = DEFAULT_TILE,
    progress: Callable[[int, int], None] | None = None,
    band: str | int | None = None,
    channels: list[str] | None = None,
    looks: float | None = None,
    overwrite: bool = True,
    spacing: tuple[float, float] | str | None = None,
    sidecar_root: str | Path | bool | None = None,
    limits: InputLimits | None = None,
    swath: str | None = None,
    codec: str = DEFAULT_INGEST_CODEC,
) -> Scene:
    """Write the scene store ``out`` from ``inputs`` (see the module docstring); return it opened.

    ``progress(done, total)`` is called after each tile. Raises :class:`InputError` (one
    line naming the file and the problem) on any bad input; nothing is left at ``out`` then.
    ``overwrite=False`` refuses an existing ``out``; ``out`` may never be (inside) an input.
    ``spacing``: (azimuth, range) pixel spacing in metres, overriding what the product says
    (attribute ``pixel_spacing_m``, ``pixel_spacing_source`` "argument").
    ``sidecar_root``: the SNAP sidecar search of a TIFF input never climbs above this folder
    (e.g. the inbox the file was dropped in); ``False``: no sidecar is read; ``None``: up to
    ``SIDECAR_LEVELS`` folders above the file (see :mod:`.tiff`).
    ``limits``: what an input may declare (pixels, decoded chunk size, compression ratio),
    checked from its headers before any pixel is decoded (:class:`.limits.InputLimits`;
    default: its defaults).
    ``swath``: the sub-swath (``IW1``, ``IW2``, ``IW3``) of a Sentinel-1 SLC product, one scene
    per sub-swath (required when the product holds several; see :mod:`.safe_slc`).
    ``out``'s missing parent folders are created (``mkdir -p``) and removed again when the
    ingest fails.
    ``codec``: the store's compressor (:data:`sarship.pipeline.scene.INGEST_CODECS`): ``auto``
    (the default) chooses zstd or none from a sample of the pixels
    (:func:`~sarship.pipeline.readers.writing.choose_codec`; the choice is in the scene's
    attributes ``codec`` and ``codec_choice``).

    ``out`` is claimed for the call once the arguments are checked
    (:func:`sarship.pipeline.scene.claim_output`): a second ingest to it meanwhile is refused
    with :class:`InputError`, one that starts after it finds the scene (refused without
    ``overwrite``); never two that both succeed.
    """
    _check_args(inputs, out, kind, tile, looks, channels, overwrite)  # first: never a claim inside an input
    # the missing folders above out are made for the claim (mkdir -p) and removed again, while
    # empty, when the ingest fails
    with claim_output(out, "--out", create_parents=True):
        # under the claim: the checks again, now authoritative
        paths, outp, tile, channels = _check_args(inputs, out, kind, tile, looks, channels, overwrite)
        if codec not in INGEST_CODECS:  # an unknown codec is refused before any work
            raise InputError(f"codec must be one of {', '.join(INGEST_CODECS)}, got '{codec}'")
        ingest_writers()  # so is a bad SARSHIP_INGEST_WRITERS
        spacing = _check_spacing(spacing)
        return _ingest(
            paths, outp, kind, tile, progress, band, channels, looks, spacing, sidecar_root, limits, swath, codec
        )


def _ingest(
    paths, outp, kind, tile, progress, band, channels, looks, spacing, sidecar_root, limits, swath, codec
) -> Scene:
    user_progress = progress

    def progress(done: int, total: int) -> None:  # noqa: F811 - the caller's, exceptions passed through
        if user_progress is not None:
            try:
                user_progress(done, total)
            except Exception as exc:  # e.g. a job cancelled by the service
                raise _CallbackError(exc) from exc

    try:
        readers = [choose(p) for p in paths]
        _check_readers(paths, readers, kind, swath)
        if isinstance(readers[0], SceneReader):  # alone: the only input
            readers[0].ingest(
                paths[0],
                outp,
                tile=tile,
                progress=progress,
                looks=looks,
                codec=codec,
                spacing=spacing,
                limits=limits or InputLimits(),
            )
            return open_scene(outp)
        srcs: list[_Source] = []
        try:
            root = sidecar_root if isinstance(sidecar_root, bool) or sidecar_root is None else Path(sidecar_root)
            for reader, p in zip(readers, paths):
                srcs.append(_open_with(reader, p, root, limits, swath))
            _ingest_sources(srcs, outp, kind, tile, progress, band, channels, looks, spacing, codec)
        finally:
            for s in srcs:
                s.close()
        return open_scene(outp)
    except InputError:
        raise
    except _CallbackError as exc:
        raise exc.exc from None
    except MemoryError:
        raise InputError(
            f"ingest of {', '.join(str(p) for p in paths)} ran out of memory (a PNG/JPEG, or one "
            "compressed TIFF strip/tile, is decoded whole: convert it to a tiled GeoTIFF)"
        ) from None
    except OSError as exc:
        if exc.errno in _STORAGE_FULL:  # not the input's fault: the caller retries or says so
            raise
        raise InputError(f"ingest of {', '.join(str(p) for p in paths)} failed: {_one_line(exc)}") from None
    except Exception as exc:  # never let a raw traceback escape
        raise InputError(f"ingest of {', '.join(str(p) for p in paths)} failed: {_one_line(exc)}") from None


def _ingest_sources(srcs, outp, kind, tile, progress, band, channels, looks, spacing=None, codec=DEFAULT_INGEST_CODEC):
    plan = _plan(srcs, kind, band, channels)
    H, W = srcs[0].shape
    attrs = dict(plan.attrs)
    attrs["kind"] = plan.kind
    attrs["source"] = [s.name for s in srcs]
    attrs["tile"] = tile
    attrs["sample_dtype"] = str(srcs[0].dtype)
    from sarship.pipeline import __version__

    attrs["sarship_version"] = __version__
    meta: dict[str, Any] = {}
    for s in srcs:  # first file that knows wins
        for k, v in s.meta.items():
            meta.setdefault(k, v)
    for k in ("crs", "transform", "gcps", "pixel_spacing_m", "pixel_spacing_source", "sensor", "acquired", "product"):
        if k in meta:
            attrs[k] = meta[k]
    if spacing is not None:
        attrs["pixel_spacing_m"], attrs["pixel_spacing_source"] = list(spacing), "argument"
    if meta.get("pols"):
        attrs["polarisations"] = meta["pols"]
    if meta.get("sidecar"):
        attrs["metadata_sidecar"] = meta["sidecar"]
    attrs.update(meta.get("extra_attrs", {}))  # e.g. a SAFE product's mode, times, calibration
    # looks that need no pixels
    if looks is not None:
        attrs["looks"], attrs["looks_source"] = float(looks), "argument"
    elif meta.get("looks") is not None:
        attrs["looks"], attrs["looks_source"] = float(meta["looks"]), "attribute"
        attrs["looks_note"] = meta.get("looks_note", "")
    elif plan.kind in ("slc", "quadpol"):
        attrs["looks"], attrs["looks_source"] = 1.0, "single-look complex"

    row_band: dict[int, tuple[int, int, np.ndarray]] = {}

    def read_src(k: int, s: _Source, r0, r1, c0, c1):
        if s.prefers_rows:
            nbytes = (r1 - r0) * W * max(1, s.nbands) * s.dtype.itemsize
            if nbytes <= ROW_BAND_BYTES:
                cached = row_band.get(k)
                if cached is None or cached[0] != r0:
                    row_band[k] = (r0, r1, s.read(r0, r1, 0, W))
                return row_band[k][2][:, c0:c1]
        return s.read(r0, r1, c0, c1)

    last_row = [-1]

    def read_tile(r0, r1, c0, c1):
        if r0 != last_row[0]:  # new tile row: drop the previous row's maps and bands
            for s in srcs:
                s.release()
            row_band.clear()
            last_row[0] = r0
        arrs = [read_src(k, s, r0, r1, c0, c1) for k, s in enumerate(srcs)]
        return plan.compute(arrs)

    if codec == "auto":
        codec, chosen = choose_codec((H, W), tile, read_tile, plan.variables)
        attrs.update(chosen)
    else:
        attrs["codec"] = codec
    with atomic_store(outp) as tmp:
        g = create_scene(tmp, (H, W), plan.variables, tile=tile, attrs=attrs, codec=codec)
        _write_tiles(g, (H, W), tile, plan.variables, read_tile, progress, store=tmp)
        row_band.clear()
        for s in srcs:
            s.release()
        if "looks" not in attrs and plan.kind == "covariance":
            attrs.update(_rank_one_looks(tmp, list(plan.variables), (H, W), tile))
        if "looks" not in attrs:
            attrs.update(_estimate_scene_looks(tmp, plan.looks_var, (H, W), tile))
        finalize_scene(tmp, attrs)
