"""The detection mask as a Cloud-Optimized GeoTIFF, written tile by tile from ``mask.zarr``.

Layout (COG spec, https://github.com/cogeotiff/cog-spec/blob/master/spec.md, and GDAL's COG
driver, https://gdal.org/drivers/raster/cog.html, whose ``validate_cloud_optimized_geotiff.py``
checks exactly these points)::

    TIFF header | GDAL ghost header | IFD 0 (full resolution) | IFD 1 (1/2) | ... | IFD K
    | tiles of level K | ... | tiles of level 1 | tiles of level 0

- every level is tiled (:data:`TILE` = 256 px), deflate-compressed uint8, one sample;
- the IFDs of all levels come first, main image first then overviews by decreasing size
  (``NewSubfileType`` = 1 for the overviews), so one ranged read of the file's head gives a
  client the whole index;
- tile data follow, smallest overview first and the full resolution last, each level's tiles
  in row-major order with increasing offsets;
- the ghost header (``GDAL_STRUCTURAL_METADATA``) declares ``LAYOUT=IFDS_BEFORE_DATA``,
  ``BLOCK_ORDER=ROW_MAJOR``, ``BLOCK_LEADER=SIZE_AS_UINT4`` (each tile preceded by its byte count)
  and ``BLOCK_TRAILER=LAST_4_BYTES_REPEATED``, as GDAL writes them;
- overviews halve the size until the smallest fits one tile (GDAL's default), so level k has
  ``ceil(H / 2^k) x ceil(W / 2^k)`` pixels and the levels line up with the XYZ zoom levels
  of :mod:`sarship.service.tiles` (XYZ tile (z, x, y) is COG tile (y, x) of level Z - z);
- overviews are **max-pooled** (2 x 2 maximum, cascaded): a ship of a few pixels would vanish
  from a nearest-neighbour or averaged overview, while the maximum keeps every detected pixel
  visible at every zoom (a mask overview pixel is set iff any full-resolution pixel under it is);
- georeference on the main IFD (GeoTIFF 1.1, OGC 19-008r4): ``ModelPixelScale`` +
  ``ModelTiepoint`` for a north-up transform, else ``ModelTransformation``; a
  ``GeoKeyDirectory`` with the EPSG code (projected or geographic, from pyproj) when the mask's
  ``crs`` attribute is one.

The TIFF structure is written here rather than with ``tifffile.imwrite``: tifffile writes each
page's IFD next to its data (or overviews as SubIFDs), which is not the COG order, and it wants
each page's data at once or in page order. Here one pass over the mask in strips of tile rows
(memory: a strip of tiles per level) compresses every level into a spool file; the final file
is the header and IFDs (whose tile offsets are then known) followed by the spools, copied.
The file is classic TIFF, or BigTIFF when it would pass 4 GiB. Reading uses tifffile.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, cast

import numpy as np
import numpy.typing as npt

from sarship.pipeline import __version__
from sarship.service.cache import build_once

if TYPE_CHECKING:
    import zarr

#: Tile side of every level (and of the XYZ tiles, so that the two pyramids coincide).
TILE = 256
#: zlib level of the tiles: masks are mostly zeros, level 6 costs little over 1 and is smaller.
DEFLATE_LEVEL = 6
COG_MEDIA_TYPE = "image/tiff; application=geotiff; profile=cloud-optimized"

_GHOST_BODY = (
    "LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n"
    "BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n"
)
GHOST = (f"GDAL_STRUCTURAL_METADATA_SIZE={len(_GHOST_BODY):06d} bytes\n" + _GHOST_BODY).encode("ascii")

# TIFF field types
_ASCII, _SHORT, _LONG, _DOUBLE, _LONG8 = 2, 3, 4, 12, 16
_FMT = {_ASCII: "s", _SHORT: "H", _LONG: "I", _DOUBLE: "d", _LONG8: "Q"}
_SIZE = {_ASCII: 1, _SHORT: 2, _LONG: 4, _DOUBLE: 8, _LONG8: 8}
#: A TIFF tag: ``(code, field type, values)``, the values a str for an ASCII tag.
_Tag = tuple[int, int, list[Any] | str]


def maxpool(a: np.ndarray, f: int) -> np.ndarray:
    """Maximum over ``f x f`` blocks of a 2-D array (``ceil(H/f) x ceil(W/f)``); the partial
    blocks at the bottom and right edges take the maximum of the pixels they have."""
    if f == 1:
        return a
    H, W = a.shape
    h, w = -(-H // f), -(-W // f)
    if H != h * f or W != w * f:
        fill = np.iinfo(a.dtype).min if np.issubdtype(a.dtype, np.integer) else (False if a.dtype == bool else -np.inf)
        p = np.full((h * f, w * f), fill, a.dtype)
        p[:H, :W] = a
        a = p
    pooled: np.ndarray
    if f == 2:  # the pyramid's step: four strided views, ~10x faster than a 4-D reduction
        pooled = np.maximum(np.maximum(a[0::2, 0::2], a[0::2, 1::2]), np.maximum(a[1::2, 0::2], a[1::2, 1::2]))
    else:
        pooled = a.reshape(h, f, w * f).max(axis=1).reshape(h, w, f).max(axis=2)
    return pooled


def level_shapes(shape: tuple[int, int], tile: int = TILE) -> list[tuple[int, int]]:
    """Sizes of the full resolution and its overviews: halving (rounded up) until the level
    fits one tile (GDAL's rule), ``ceil(H / 2^k) x ceil(W / 2^k)`` for k = 0..K."""
    H, W = int(shape[0]), int(shape[1])
    out = [(H, W)]
    k = 0
    while max(H, W) > tile << k:
        k += 1
        out.append((-(-H // (1 << k)), -(-W // (1 << k))))
    return out


# --------------------------------------------------------------------------- georeference


def geotiff_tags(attrs: dict[str, Any]) -> list[_Tag]:
    """GeoTIFF tags ``(code, type, values)`` for the ``crs`` / ``transform`` attributes the
    pipeline stores (``transform`` in GDAL order ``[c, a, b, f, d, e]``: x = c + a*col + b*row,
    y = f + d*col + e*row, PixelIsArea; ``crs`` as ``"EPSG:n"``). Empty without a transform."""
    tr = attrs.get("transform")
    tags: list[_Tag] = []
    if not tr or len(tr) < 6:
        return tags
    c, a, b, f, d, e = (float(v) for v in tr[:6])
    if b == 0 and d == 0 and a > 0 and e < 0:  # north-up: pixel scale + one tie point
        tags.append((33550, _DOUBLE, [a, -e, 0.0]))
        tags.append((33922, _DOUBLE, [0.0, 0.0, 0.0, c, f, 0.0]))
    else:
        tags.append((34264, _DOUBLE, [a, b, 0.0, c, d, e, 0.0, f, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    keys = geokeys(attrs.get("crs"))
    if keys:
        tags.append((34735, _SHORT, keys))
    return tags


def geokeys(crs: Any) -> list[int] | None:
    """GeoKeyDirectory (GeoTIFF 1.0 key revision 1.0) for an EPSG CRS: model type (projected or
    geographic), PixelIsArea, and the ProjectedCSType or GeographicType key; None when the crs
    is not an EPSG code pyproj knows (the transform tags are then written alone)."""
    if not crs:
        return None
    try:
        from pyproj import CRS

        c = CRS.from_user_input(str(crs))
        epsg = c.to_epsg()
    except Exception:
        return None
    if not epsg or not 1 <= epsg <= 65535:
        return None
    if c.is_projected:
        entries = [(1024, 1), (1025, 1), (3072, epsg)]
    elif c.is_geographic:
        entries = [(1024, 2), (1025, 1), (2048, epsg)]
    else:
        return None
    out = [1, 1, 0, len(entries)]
    for key, v in entries:
        out += [key, 0, 1, v]
    return out


# --------------------------------------------------------------------------- writing


@dataclass
class _Level:
    shape: tuple[int, int]
    spool: BinaryIO
    pending: list[np.ndarray] = field(default_factory=list)
    npending: int = 0
    rows_done: int = 0
    carry: np.ndarray | None = None
    counts: list[int] = field(default_factory=list)
    nbytes: int = 0


class _Pyramid:
    """Levels fed with rows of full resolution; each level compresses its tile rows into its
    spool as they fill, and passes its rows, max-pooled 2 x 2, to the next level."""

    def __init__(self, shape: tuple[int, int], spool_dir: Path, tile: int):
        self.tile = tile
        self.levels = [
            _Level(s, open(spool_dir / f"level-{k}", "w+b")) for k, s in enumerate(level_shapes(shape, tile))
        ]

    def feed(self, k: int, rows: np.ndarray, final: bool) -> None:
        lv = self.levels[k]
        if rows.shape[0]:
            lv.pending.append(rows)
            lv.npending += rows.shape[0]
        while lv.npending >= self.tile or (final and lv.npending):
            buf = np.concatenate(lv.pending) if len(lv.pending) > 1 else lv.pending[0]
            n = min(self.tile, buf.shape[0])
            self._write_row(lv, buf[:n])
            rest = buf[n:]
            lv.pending, lv.npending = ([rest] if rest.shape[0] else []), rest.shape[0]
        if k + 1 < len(self.levels):
            if lv.carry is not None:
                rows = np.concatenate([lv.carry, rows])
                lv.carry = None
            if rows.shape[0] % 2 and not final:
                lv.carry, rows = rows[-1:], rows[:-1]
            nxt = maxpool(rows, 2) if rows.shape[0] else np.zeros((0, self.levels[k + 1].shape[1]), rows.dtype)
            self.feed(k + 1, nxt, final)

    def _write_row(self, lv: _Level, rows: np.ndarray) -> None:
        t = self.tile
        h, w = lv.shape
        nx = -(-w // t)
        block = np.zeros((t, nx * t), np.uint8)
        block[: rows.shape[0], :w] = rows
        for j in range(nx):
            data = zlib.compress(np.ascontiguousarray(block[:, j * t : (j + 1) * t]).tobytes(), DEFLATE_LEVEL)
            n = len(data)
            lv.spool.write(struct.pack("<I", n) + data + data[-4:])  # leader, tile, trailer
            lv.counts.append(n)
            lv.nbytes += n + 8
        lv.rows_done += rows.shape[0]


def _ifd(entries: list[_Tag], at: int, bigtiff: bool, next_ifd: int = 0) -> bytes:
    """One IFD at file offset ``at``, pointing to the IFD at ``next_ifd`` (0: the last), followed
    by its out-of-line values. Entries must be sorted by tag."""
    n = len(entries)
    cnt_fmt, ent_size, inline, off_fmt = ("<Q", 20, 8, "<Q") if bigtiff else ("<H", 12, 4, "<I")
    head = struct.calcsize(cnt_fmt) + n * ent_size + struct.calcsize(off_fmt)
    body, extra = [struct.pack(cnt_fmt, n)], []
    pos = at + head
    for tag, typ, values in entries:
        if typ == _ASCII:
            raw = values.encode("ascii") + b"\0" if isinstance(values, str) else bytes(values)
            count = len(raw)
        else:
            count = len(values)
            raw = struct.pack(f"<{count}{_FMT[typ]}", *values)
        if len(raw) <= inline:
            val = raw.ljust(inline, b"\0")
        else:
            val = struct.pack(off_fmt, pos)
            raw += b"\0" * (len(raw) % 2)  # word boundary
            extra.append(raw)
            pos += len(raw)
        body.append(struct.pack("<HHQ" if bigtiff else "<HHI", tag, typ, count) + val)
    body.append(struct.pack(off_fmt, next_ifd))
    return b"".join(body + extra)


def _ifd_size(entries: list[_Tag], bigtiff: bool) -> int:
    return len(_ifd(entries, 0, bigtiff))


def _entries(k: int, lv: _Level, offsets: list[int], tile: int, bigtiff: bool, geotags: list[_Tag]) -> list[_Tag]:
    h, w = lv.shape
    off_t = _LONG8 if bigtiff else _LONG
    e: list[_Tag] = [
        (254, _LONG, [0 if k == 0 else 1]),
        (256, _LONG, [w]),
        (257, _LONG, [h]),
        (258, _SHORT, [8]),
        (259, _SHORT, [8]),
        (262, _SHORT, [1]),
        (277, _SHORT, [1]),
        (284, _SHORT, [1]),
        (322, _SHORT, [tile]),
        (323, _SHORT, [tile]),
        (324, off_t, offsets),
        (325, off_t, lv.counts),
        (339, _SHORT, [1]),
    ]
    if k == 0:
        e.append((305, _ASCII, f"sarship {__version__}"))
        e += geotags
    return sorted(e, key=lambda x: x[0])


def write_cog(
    read_rows: Callable[[int, int], npt.ArrayLike],
    shape: tuple[int, ...],
    out: Path,
    attrs: dict[str, Any] | None = None,
    tile: int = TILE,
    strip: int = TILE,
    bigtiff: bool | None = None,
) -> Path:
    """Write a uint8 2-D raster as a COG at ``out`` (see the module doc for the layout).

    ``read_rows(r0, r1)`` returns rows ``r0:r1`` (all columns) as uint8; it is called for
    consecutive strips of ``strip`` rows (a multiple of ``tile``), so memory stays at a strip
    plus one tile row per level. ``attrs``: ``crs`` / ``transform`` for the GeoTIFF tags.
    ``bigtiff``: None = BigTIFF only when a classic TIFF's 32-bit offsets would not reach.
    """
    if strip % tile:
        raise ValueError(f"strip ({strip}) must be a multiple of the tile ({tile})")
    H, W = int(shape[0]), int(shape[1])
    geotags = geotiff_tags(attrs or {})
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".cog-spool-") as sd:
        pyr = _Pyramid((H, W), Path(sd), tile)
        try:
            for r0 in range(0, H, strip):
                r1 = min(r0 + strip, H)
                rows = np.asarray(read_rows(r0, r1), dtype=np.uint8)
                if rows.shape != (r1 - r0, W):
                    raise ValueError(f"read_rows({r0}, {r1}) gave shape {rows.shape}, expected {(r1 - r0, W)}")
                pyr.feed(0, rows, final=r1 == H)
            for lv in pyr.levels:
                assert lv.rows_done == lv.shape[0] and not lv.npending, (lv.shape, lv.rows_done)
            data_total = sum(lv.nbytes for lv in pyr.levels)
            for big in (False, True) if bigtiff is None else (bool(bigtiff),):
                head = 16 if big else 8
                first_ifd = head + len(GHOST)
                first_ifd += first_ifd % 2
                dummy = [[0] * len(lv.counts) for lv in pyr.levels]
                sizes = [
                    _ifd_size(_entries(k, lv, dummy[k], tile, big, geotags), big) for k, lv in enumerate(pyr.levels)
                ]
                data_start = first_ifd + sum(sizes)
                if big or data_start + data_total < 2**32:
                    break
            bigtiff = big
            # tile offsets: data of the smallest level first, full resolution last
            offsets: list[list[int]] = [[] for _ in pyr.levels]
            pos = data_start
            for k in range(len(pyr.levels) - 1, -1, -1):
                for n in pyr.levels[k].counts:
                    offsets[k].append(pos + 4)  # after the 4-byte leader
                    pos += n + 8
            with open(out, "wb") as fh:
                if bigtiff:
                    fh.write(b"II" + struct.pack("<HHHQ", 43, 8, 0, first_ifd))
                else:
                    fh.write(b"II" + struct.pack("<HI", 42, first_ifd))
                fh.write(GHOST)
                fh.write(b"\0" * (first_ifd - fh.tell()))
                at = first_ifd
                for k, lv in enumerate(pyr.levels):
                    nxt = at + sizes[k] if k + 1 < len(pyr.levels) else 0
                    raw = _ifd(_entries(k, lv, offsets[k], tile, bigtiff, geotags), at, bigtiff, nxt)
                    assert len(raw) == sizes[k]
                    fh.write(raw)
                    at += sizes[k]
                assert fh.tell() == data_start
                for k in range(len(pyr.levels) - 1, -1, -1):
                    sp = pyr.levels[k].spool
                    sp.seek(0)
                    shutil.copyfileobj(sp, fh, 1 << 20)
                fh.flush()
                os.fsync(fh.fileno())
        finally:
            for lv in pyr.levels:
                lv.spool.close()
    return out


def mask_cog(job_dir: Path) -> Path:
    """The job's mask as a COG (``JOB/mask.tif``), made once from ``JOB/mask.zarr`` and cached.

    Read in strips of whole tile rows aligned on the mask's chunks (each chunk decompressed
    once), so a 25000 x 16700 mask is never in memory: a strip plus a tile row per level.
    """

    def build(tmp: Path) -> None:
        import zarr

        g = zarr.open_group(str(job_dir / "mask.zarr"), mode="r")
        arr = cast("zarr.Array[Any]", g["mask"])  # the job wrote "mask" as an array, never a group
        ch = int(arr.chunks[0])
        strip = TILE * max(1, -(-ch // TILE))
        write_cog(lambda r0, r1: arr[r0:r1, :], arr.shape, tmp, attrs=dict(g.attrs), strip=strip)

    return build_once(job_dir / "mask.tif", build)


# --------------------------------------------------------------------------- reading


_index_lock = threading.Lock()
#: Per level of a COG: its shape, tile offsets and tile byte counts.
_LevelIndex = tuple[tuple[int, int], np.ndarray, np.ndarray]
_index: OrderedDict[tuple[str, int, int], list[_LevelIndex]] = OrderedDict()


def _levels_index(path: Path) -> list[_LevelIndex]:
    """Per level (IFD chain order): shape, tile offsets, tile byte counts, parsed by tifffile;
    cached per file (a few small arrays per job)."""
    st = path.stat()
    key = (str(path), st.st_mtime_ns, st.st_size)
    with _index_lock:
        if key in _index:
            _index.move_to_end(key)
            return _index[key]
    import tifffile

    out: list[_LevelIndex] = []
    with tifffile.TiffFile(path) as tif:
        for item in tif.pages:
            page = cast(tifffile.TiffPage, item)  # TiffPages yields frames only with useframes (never set here)
            out.append(
                (
                    (int(page.imagelength), int(page.imagewidth)),
                    np.asarray(page.dataoffsets, np.int64),
                    np.asarray(page.databytecounts, np.int64),
                )
            )
    with _index_lock:
        _index[key] = out
        while len(_index) > 64:
            _index.popitem(last=False)
    return out


def cog_tile(path: Path, level: int, row: int, col: int, tile: int = TILE) -> np.ndarray:
    """Tile ``(row, col)`` of ``level`` (0 = full resolution) of a COG written by
    :func:`write_cog`: a ``tile x tile`` uint8 array (zero beyond the level's edge)."""
    levels = _levels_index(path)
    (h, w), offs, counts = levels[level]
    nx = -(-w // tile)
    i = row * nx + col
    with open(path, "rb") as fh:
        fh.seek(int(offs[i]))
        data = fh.read(int(counts[i]))
    return np.frombuffer(zlib.decompress(data), np.uint8).reshape(tile, tile)


def mask_zarr_zip(job_dir: Path) -> Path:
    """The job's ``mask.zarr`` packaged as a zip (``JOB/mask.zarr.zip``, made once): the store's
    files at the zip's root, stored uncompressed (the chunks are zstd already), so that
    ``zarr.open_group(zarr.storage.ZipStore(path, mode="r"))`` or ``unzip`` + ``zarr.open``
    reads it."""
    src = job_dir / "mask.zarr"

    def build(tmp: Path) -> None:
        import zipfile

        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for dirpath, dirnames, filenames in os.walk(src):
                dirnames.sort()
                for name in sorted(filenames):
                    p = Path(dirpath) / name
                    zf.write(p, p.relative_to(src).as_posix())

    return build_once(job_dir / "mask.zarr.zip", build)
