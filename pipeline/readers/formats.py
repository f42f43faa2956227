"""The formats :func:`sarship.pipeline.readers.ingest` reads, one :class:`~.protocol.Reader`
each, wrapping its module's code (what each accepts is in that module's docstring):

- :class:`SafeReader`: a Sentinel-1 SAFE product, folder or zip (:mod:`.safe`, GRD;
  :mod:`.safe_slc`, one sub-swath of an IW SLC);
- :class:`ZarrReader`: a Zarr scene (:mod:`.zarr_input`), copied whole;
- :class:`PolsarproReader`: a PolSARpro C3 / T3 / C2 folder (:mod:`.polsarpro`);
- :class:`TiffReader`: TIFF / GeoTIFF / BigTIFF (:mod:`.tiff`);
- :class:`ImageReader`: PNG / JPEG (:mod:`.image`);
- :class:`NpyReader`: a ``.npy`` array (:mod:`.npy`).

Their order, the order of dispatch, is :data:`sarship.pipeline.readers.registry.READERS`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.image import _open_image
from sarship.pipeline.readers.limits import InputLimits
from sarship.pipeline.readers.npy import _open_npy
from sarship.pipeline.readers.polsarpro import _open_polsarpro, _polsarpro_folder
from sarship.pipeline.readers.protocol import BaseReader, Probe, Source
from sarship.pipeline.readers.safe import check_safe_kind, open_grd, product_measurements, safe_layout
from sarship.pipeline.readers.safe_slc import open_slc
from sarship.pipeline.readers.tiff import _open_tiff
from sarship.pipeline.readers.zarr_input import _ingest_zarr
from sarship.pipeline.scene import atomic_store, finalize_scene, open_scene

_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_MAGIC = b"\xff\xd8\xff"
_NPY_MAGIC = b"\x93NUMPY"


def _open_safe(p: Path, limits: InputLimits, swath: str | None = None) -> Source:
    """A Sentinel-1 SAFE product (directory or zip): an SLC's sub-swath or a GRD."""
    prod, meas, swaths, slc = product_measurements(p, limits, safe_layout(p))
    if slc:
        return open_slc(p, prod, slc, limits, swath)
    return open_grd(p, prod, meas, swaths, limits, swath)


def is_zarr_scene(p: Path) -> bool:
    """A folder with ``zarr.json`` (Zarr v3) or ``.zgroup`` (v2)."""
    return p.is_dir() and ((p / "zarr.json").exists() or (p / ".zgroup").exists())


def _checked(p: Path, src: Source, limits: InputLimits) -> Source:
    """``src`` (headers only, pixels memory-mapped) once its size passes ``limits``; closed if not."""
    try:
        limits.check_pixels(p, *src.shape)
    except InputError:
        src.close()
        raise
    return src


class SafeReader(BaseReader):
    """A Sentinel-1 SAFE product: a folder with ``manifest.safe`` or a zip holding one."""

    name = "safe"
    alone = "a Sentinel-1 SAFE product cannot be combined with other inputs (its polarisations are its channels)"
    takes_swath = True

    def detect(self, probe: Probe) -> bool:
        return safe_layout(probe.path) is not None

    def check(self, path: Path, kind: str) -> None:
        check_safe_kind(path, kind)

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        return _open_safe(path, limits, swath)


class ZarrReader(BaseReader):
    """A Zarr scene (a folder with ``zarr.json`` or ``.zgroup``), re-tiled whole by :meth:`ingest`."""

    name = "zarr"
    alone = "a Zarr scene cannot be combined with other inputs"

    def detect(self, probe: Probe) -> bool:
        return probe.is_dir and is_zarr_scene(probe.path)

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        raise InputError(f"'{path}': {self.alone}")  # a scene is copied by ingest, never a source

    def ingest(
        self,
        path: Path,
        out: Path,
        *,
        tile: int,
        progress: Callable[[int, int], None],
        looks: float | None,
        codec: str,
        spacing: list[float] | None,
        limits: InputLimits,
    ) -> None:
        """Copy the scene ``path`` to ``out`` re-tiled; ``spacing`` (when given) overrides its own."""
        limits.check_pixels(path, *open_scene(path).shape)
        if spacing is None:
            _ingest_zarr(path, out, tile, progress, looks, codec)
        else:  # written to a temporary sibling, given the spacing, then renamed
            with atomic_store(out) as tmp:
                _ingest_zarr(path, tmp, tile, progress, looks, codec)
                finalize_scene(tmp, {"pixel_spacing_m": spacing, "pixel_spacing_source": "argument"})


class PolsarproReader(BaseReader):
    """A PolSARpro C3 / T3 / C2 folder, or its ``config.txt`` / ``C11.bin`` / ``T11.bin``
    (a folder that is also a Zarr scene is the Zarr reader's)."""

    name = "polsarpro"
    alone = "a PolSARpro folder cannot be combined with other inputs"

    def detect(self, probe: Probe) -> bool:
        p = probe.path
        if probe.is_dir and is_zarr_scene(p):
            return False
        if _polsarpro_folder(p) is not None:
            return True
        if probe.is_dir:
            return False
        if p.name.lower() == "config.txt":
            raise InputError(f"'{p}': a config.txt, but its folder holds no PolSARpro C11.bin or T11.bin")
        if re.fullmatch(r"[ct]\d\d(_real|_imag)?\.bin", p.name.lower()) and _polsarpro_folder(p.parent):
            raise InputError(
                f"'{p}' is one element of a PolSARpro folder: pass the folder '{p.parent}' (or its config.txt)"
            )
        return False

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        folder = _polsarpro_folder(path)
        if folder is None:  # only when called without detect
            raise InputError(f"'{path}' is not a PolSARpro folder (no C11.bin or T11.bin)")
        return _checked(path, _open_polsarpro(folder), limits)


class TiffReader(BaseReader):
    """TIFF, GeoTIFF or BigTIFF, either byte order (by its magic number)."""

    name = "tiff"

    def detect(self, probe: Probe) -> bool:
        return not probe.is_dir and probe.head[:4] in _TIFF_MAGIC

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        return _open_tiff(path, sidecar_root, limits)


class ImageReader(BaseReader):
    """PNG or JPEG (by its magic number)."""

    name = "image"

    def detect(self, probe: Probe) -> bool:
        return not probe.is_dir and (probe.head[:8] == _PNG_MAGIC or probe.head[:3] == _JPEG_MAGIC)

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        return _open_image(path, limits)


class NpyReader(BaseReader):
    """A NumPy ``.npy`` array (by its magic number), memory-mapped."""

    name = "npy"

    def detect(self, probe: Probe) -> bool:
        return not probe.is_dir and probe.head[:6] == _NPY_MAGIC

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        return _checked(path, _open_npy(path), limits)
