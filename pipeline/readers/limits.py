"""Input limits: what a file may declare before any of its pixels is decoded.

A crafted file can ask for far more than its size suggests: a 6 MB TIFF holding one deflate
strip of 40000 x 40000 float32 decodes to 6.4 GB in one piece; a 19 KB sparse TIFF can declare
200000 x 200000 pixels (every tile byte count 0) and be streamed for hours; a small TIFF whose
tiles all point at one compressed blob decodes that blob thousands of times. These limits are
checked from the headers alone (tifffile reads no strip or tile to answer them), before the
probe or any tile is read:

``max_pixels``
    declared rows x columns of the image (every format; a Zarr scene too).
``max_chunk_mb``
    decoded size of one compressed TIFF strip or tile: the reader decodes a chunk whole, so
    this bounds the memory one read can take. An uncompressed file is memory-mapped and not
    bound by it.
``max_ratio``
    declared decoded bytes / file size on disk, for compressed or sparse TIFFs: deflate cannot
    exceed about 1032:1, so a real image never reaches the default. A Sentinel-1 SAFE product
    (folder or zip) has it applied to each measurement GeoTIFF (the annotation's lines x
    samples x the TIFF's bytes per pixel against the measurement's bytes on disk, or its
    compressed bytes inside a zip), and to every member of a SAFE zip (uncompressed size /
    compressed size: a zip bomb beyond it); see :mod:`.safe`.
``max_xml_mb``
    size of each XML member of a Sentinel-1 SAFE product (manifest, annotation, calibration,
    noise, schema files), MiB, from the zip's directory or the folder's file sizes, before
    any is inflated or parsed; reads of them stop at this many bytes whatever a header says.
    A real IW annotation is about 2 MiB.

The defaults hold every real product the project reads (a Sentinel-1 IW GRD is about
25000 x 17000 = 4.3e8 pixels in uncompressed files; a full-resolution tiled GeoTIFF uses
chunks of a few hundred KB). They are settings of the command line (``sarship ingest
--max-pixels/--max-chunk-mb/--max-ratio/--max-xml-mb``) and of the service (``SARSHIP_MAX_PIXELS``,
``SARSHIP_MAX_CHUNK_MB``, ``SARSHIP_MAX_RATIO``, ``SARSHIP_MAX_XML_MB``); a refusal names the one
to raise.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

#: Default largest image, rows x columns.
DEFAULT_MAX_PIXELS = 2_000_000_000
#: Default largest decoded compressed strip or tile, MiB.
DEFAULT_MAX_CHUNK_MB = 256.0
#: Default largest ratio of declared decoded bytes to file size (compressed or sparse TIFF).
DEFAULT_MAX_RATIO = 1000.0
#: Default largest XML member of a Sentinel-1 SAFE product, MiB.
DEFAULT_MAX_XML_MB = 64.0


@dataclass(frozen=True)
class InputLimits:
    """What an input may declare (see the module docstring); ``option`` names the knobs in
    refusals: ``"cli"`` (``--max-pixels``) or ``"service"`` (``SARSHIP_MAX_PIXELS``)."""

    max_pixels: int = DEFAULT_MAX_PIXELS
    max_chunk_mb: float = DEFAULT_MAX_CHUNK_MB
    max_ratio: float = DEFAULT_MAX_RATIO
    option: str = "cli"
    max_xml_mb: float = DEFAULT_MAX_XML_MB

    def __post_init__(self):
        for name in ("max_pixels", "max_chunk_mb", "max_ratio", "max_xml_mb"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"{self._knob(name)} must be a positive number, got {v!r}")

    def _knob(self, name: str) -> str:
        if self.option == "service":
            return "SARSHIP_" + name.upper()
        return "--" + name.replace("_", "-")

    def check_pixels(self, p: Path | str, H: int, W: int) -> None:
        if int(H) * int(W) > self.max_pixels:
            raise InputError(
                f"'{p}': declares {H} x {W} = {int(H) * int(W):.3g} pixels, above the limit of "
                f"{self.max_pixels:.3g} ({self._knob('max_pixels')})"
            )

    def check_ratio(self, p: Path | str, what: str, declared: float, stored: float) -> None:
        """Refuse ``declared`` decoded bytes held in ``stored`` bytes beyond ``max_ratio``;
        ``what`` names the member or file in the one-line refusal."""
        size = max(float(stored), 1.0)
        if declared / size > self.max_ratio:
            raise InputError(
                f"'{p}': {what} declares {declared / 2**20:.0f} MiB in {size / 2**10:.0f} KiB "
                f"(ratio {declared / size:.0f}:1, above the limit of {self.max_ratio:g}:1, "
                f"{self._knob('max_ratio')}): a decompression bomb or a mostly empty file"
            )

    def check_xml(self, p: Path | str, member: str, size: float) -> None:
        """Refuse an XML member of ``size`` bytes beyond ``max_xml_mb``."""
        if size > self.max_xml_mb * 2**20:
            raise InputError(
                f"'{p}': {member} is {size / 2**20:.0f} MiB, above the limit of {self.max_xml_mb:g} MiB for an "
                f"XML member ({self._knob('max_xml_mb')}; a real annotation is about 2 MiB)"
            )

    def check_tiff(self, p: Path, series: Any, nbands: int, dtype: np.dtype) -> None:
        """The chunk and ratio limits of a TIFF series, from its page headers."""
        H, W = _series_hw(series)
        self.check_pixels(p, H, W)
        compressed = sparse = False
        chunk_bytes = 0
        for page in series.pages:
            if page is None:
                continue
            if not hasattr(page, "compression"):  # a TiffFrame: its tags live on its key frame
                page = getattr(page, "keyframe", None) or page
            comp = int(getattr(page, "compression", 1) or 1)
            counts = getattr(page, "databytecounts", ()) or ()
            sparse = sparse or any(int(c) == 0 for c in counts)
            if comp != 1:
                compressed = True
                chunks = getattr(page, "chunks", None)
                if chunks:
                    chunk_bytes = max(chunk_bytes, int(np.prod(chunks, dtype=np.int64)) * dtype.itemsize)
        if compressed and chunk_bytes > self.max_chunk_mb * 2**20:
            raise InputError(
                f"'{p}': one compressed strip/tile decodes to {chunk_bytes / 2**20:.0f} MiB, above the limit of "
                f"{self.max_chunk_mb:g} MiB ({self._knob('max_chunk_mb')}); rewrite it tiled "
                "(e.g. gdal_translate -co TILED=YES) or raise the limit"
            )
        if compressed or sparse:
            declared = float(H) * W * nbands * dtype.itemsize
            size = max(os.path.getsize(p), 1)
            if declared / size > self.max_ratio:
                raise InputError(
                    f"'{p}': declares {declared / 2**20:.0f} MiB of pixels in a {size / 2**10:.0f} KiB file "
                    f"(ratio {declared / size:.0f}:1, above the limit of {self.max_ratio:g}:1, "
                    f"{self._knob('max_ratio')}): a decompression bomb or a mostly empty sparse file"
                )


def _series_hw(series: Any) -> tuple[int, int]:
    axes, shape = series.axes, tuple(int(v) for v in series.shape)
    return shape[axes.index("Y")], shape[axes.index("X")]
