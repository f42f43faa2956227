"""The scene store (docs/interfaces/files.md): a Zarr v3 group of square-chunked 2-D tiles.

A scene is a Zarr v3 group readable with :func:`xarray.open_zarr`. Each variable is a
2-D array on dims ``(y, x)`` stored in ``tile x tile`` squares (Zarr v3 shards of 512x512
inner chunks when the tile is a multiple of 512, see :func:`chunking`), zstd-compressed:

- ``intensity`` (float32) for detected (GRD-like) scenes,
- complex64 ``hh``, ``hv``, ``vv`` (or ``vh``) for SLC and quad-pol scenes,
- ``c11`` ... ``c33`` for covariance (C3) scenes: real diagonal (float32), complex
  upper triangle (complex64).

Group attributes: ``kind``, ``looks``, ``pixel_spacing_m`` ([azimuth, range]) when known,
``sensor``, ``acquired`` (ISO 8601), ``crs`` + ``transform`` (GDAL order
``[c, a, b, f, d, e]``: x = c + a*col + b*row, y = f + d*col + e*row) when known, and
provenance (``source``, ``looks_source``, ``sarship_version``).

Stores are written to a temporary sibling path and renamed into place only when complete
(:func:`atomic_store`), so a failed or interrupted write never leaves a half-written scene.
A command's output is claimed for the command first (:func:`claim_output`), so that two
commands writing one output never both succeed.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import uuid
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

#: Default tile (chunk) side in pixels.
DEFAULT_TILE = 2048

#: Scene kinds (docs/interfaces/files.md).
KINDS = ("intensity", "slc", "quadpol", "covariance")

#: Complex channel names a scene may hold.
COMPLEX_CHANNELS = ("hh", "hv", "vh", "vv")

#: Covariance element names (upper triangle, row-major), C3 and C2.
COVARIANCE_VARS = ("c11", "c12", "c13", "c22", "c23", "c33")
COVARIANCE2_VARS = ("c11", "c12", "c22")

ZSTD_LEVEL = 3

#: Compressors a scene store's arrays may be written with (``sarship ingest --codec``):
#: ``zstd`` (the default) is zstd level 3, ``lz4`` is Blosc LZ4 level 5 with byte shuffle,
#: ``none`` stores raw bytes. Measured (bench/RESULTS.md, issue 17, session 10): on speckled
#: float32 intensity both store the same bytes and LZ4 reads a tile with its halo 1.7x faster
#: (tensorstore: 13 ms against 22 ms), but end to end that is 0.1 s of an 8192^2 run on two
#: cores and nothing measurable on the GPU host; LZ4's ingest peaks 30 MB higher per 256 MB
#: scene, and on intensities from 8-bit products zstd stores half the bytes (ratio 4.0 / 2.2).
CODECS = ("lz4", "zstd", "none")
DEFAULT_CODEC = "zstd"
#: ``sarship ingest --codec``: the codecs, or ``auto`` (the default): zstd when it stores a sample
#: of the scene's pixels in at most 1 / AUTO_CODEC_MIN_RATIO of their bytes, else none
#: (:func:`sarship.pipeline.readers.writing.choose_codec`). Speckled float32 intensities hardly
#: compress (zstd: ratio 1.07-1.10), and decoding them is most of a tile's read: the 25000 x
#: 16700 band's texture land pass took 0.49-0.52 s on one H100 host stored raw against 0.76-0.86 s
#: with zstd (bench/RESULTS.md, "Session 14"); 8-bit products compress 2-4x and keep zstd.
INGEST_CODECS = ("auto",) + CODECS
DEFAULT_INGEST_CODEC = "auto"
AUTO_CODEC_MIN_RATIO = 1.2


#: Inner chunk side inside a tile when tiles are stored as Zarr v3 shards (measured: reading
#: a 2048 tile plus a 30-px halo takes 0.19 s unsharded, 0.075 s with 256, 0.048 s with 512).
INNER_CHUNK = 512


def chunking(tile: int) -> dict:
    """Zarr layout of a tile: one shard per tile, split into 512x512 inner chunks.

    A detector reads its tile plus a halo that reaches into the eight neighbouring tiles.
    With one chunk per tile it would decompress all nine tiles (9x the data it needs);
    with 512x512 inner chunks inside each tile's shard it decompresses only the strips it
    reads. Writes stay one task per tile (= one shard). Tiles that are not a multiple of
    512 (small test tiles) are plain chunks.
    """
    tile = int(tile)
    if tile > INNER_CHUNK and tile % INNER_CHUNK == 0:
        return {"chunks": (INNER_CHUNK, INNER_CHUNK), "shards": (tile, tile)}
    return {"chunks": (tile, tile)}


def array_tile(arr) -> int:
    """The tile side of a stored array: its shard side, else its chunk side."""
    shards = getattr(arr, "shards", None)
    return int(shards[0] if shards else arr.chunks[0])


def _zstd():
    from zarr.codecs import ZstdCodec

    return ZstdCodec(level=ZSTD_LEVEL)


def scene_compressors(codec: str = DEFAULT_CODEC):
    """The ``compressors`` of a scene array for ``codec`` (:data:`CODECS`); InputError otherwise."""
    if codec == "zstd":
        return _zstd()
    if codec == "lz4":
        from zarr.codecs import BloscCodec

        return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")
    if codec == "none":
        return None
    raise InputError(f"codec must be one of {', '.join(CODECS)}, got '{codec}'")


@dataclass
class Scene:
    """An opened scene store (metadata only; pixels are read on demand)."""

    path: Path
    shape: tuple[int, int]
    tile: int
    variables: dict[str, str]  # name -> dtype string
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        return str(self.attrs.get("kind", "intensity"))

    @property
    def looks(self) -> float | None:
        v = self.attrs.get("looks")
        return None if v is None else float(v)

    @property
    def pixel_spacing_m(self) -> tuple[float, float] | None:
        v = self.attrs.get("pixel_spacing_m")
        if v is None:
            return None
        return (float(v[0]), float(v[1]))

    @property
    def ground_spacing_m(self) -> tuple[float, float] | None:
        """[azimuth, range] metres a pixel on the ground: ``pixel_spacing_m`` with its range
        replaced by ``ground_range_spacing_m`` where the scene states one (a slant-range SLC,
        pipeline/readers/safe_slc.py: slant / sin(incidence) at mid swath), so ship lengths and
        the metre size rules are ground metres."""
        sp = self.pixel_spacing_m
        g = self.attrs.get("ground_range_spacing_m")
        if sp is None or g is None:
            return sp
        return (sp[0], float(g))

    def array(self, name: str):
        """The zarr array ``name`` (opened read-only)."""
        import zarr

        return zarr.open_array(str(self.path / name), mode="r")


def open_scene(path: str | os.PathLike) -> Scene:
    """Open a scene store, raising :class:`InputError` with a clear message if it is not one."""
    import zarr

    p = Path(path)
    if not p.exists():
        raise InputError(f"scene '{p}' does not exist")
    if p.is_file():
        if p.suffix.lower() == ".zarr":
            raise InputError(f"'{p}' is a file, not a Zarr scene store (a folder with zarr.json)")
        raise InputError(
            f"'{p}' is a file, not a scene store: make one with `sarship ingest {p} --out {p.with_suffix('.zarr')}`"
        )
    try:
        g = zarr.open_group(str(p), mode="r")
    except Exception as exc:  # zarr raises several types for non-stores
        raise InputError(f"'{p}' is not a Zarr scene store ({type(exc).__name__}: {exc})") from None
    variables: dict[str, str] = {}
    shape: tuple[int, int] | None = None
    tile = None
    for name, arr in g.arrays():
        if arr.ndim != 2:
            continue
        variables[name] = str(arr.dtype)
        if shape is None:
            shape = (int(arr.shape[0]), int(arr.shape[1]))
            tile = array_tile(arr)
        elif tuple(arr.shape) != shape:
            raise InputError(f"scene '{p}': variable '{name}' has shape {arr.shape}, expected {shape}")
    if shape is None:
        raise InputError(f"scene '{p}' holds no 2-D variable (expected 'intensity', 'hh', ... or 'c11')")
    return Scene(path=p, shape=shape, tile=int(tile), variables=variables, attrs=dict(g.attrs))


def create_scene(
    path: str | os.PathLike,
    shape: tuple[int, int],
    variables: dict[str, Any],
    tile: int = DEFAULT_TILE,
    attrs: dict[str, Any] | None = None,
    codec: str = DEFAULT_CODEC,
):
    """Create an empty scene group at ``path`` (overwriting) and return the zarr group.

    ``variables`` maps names to numpy dtypes. Arrays are chunked ``(tile, tile)`` (:func:`chunking`),
    compressed with ``codec`` (:data:`CODECS`), with dimension names ``("y", "x")`` so that
    xarray opens them.
    """
    import zarr

    if tile < 1:
        raise InputError(f"--tile must be a positive number of pixels, got {tile}")
    compressors = scene_compressors(codec)
    g = zarr.open_group(str(path), mode="w", zarr_format=3)
    for name, dtype in variables.items():
        g.create_array(
            name,
            shape=tuple(int(s) for s in shape),
            **chunking(tile),
            dtype=np.dtype(dtype),
            compressors=compressors,
            dimension_names=("y", "x"),
            fill_value=0,
        )
    if attrs:
        g.attrs.update(_jsonable(attrs))
    return g


def finalize_scene(path: str | os.PathLike, attrs: dict[str, Any] | None = None) -> None:
    """Update attributes and consolidate metadata (for ``xarray.open_zarr``)."""
    import zarr

    g = zarr.open_group(str(path), mode="r+")
    if attrs:
        g.attrs.update(_jsonable(attrs))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(path))


def create_mask_store(
    path: str | os.PathLike,
    shape: tuple[int, int],
    tile: int,
    attrs: dict[str, Any] | None = None,
    arrays: tuple[str, ...] = ("mask",),
    dtype: str = "uint8",
):
    """Create the detection mask store at ``path``: a group with one ``uint8`` array per name in
    ``arrays`` (default ``mask``: 1 = detected), chunked like a scene of tile side ``tile`` (one
    shard per tile, so one tile task writes exactly one chunk or shard), zstd compressed, fill
    value 0. ``dtype``: the arrays' type (e.g. int32 component labels). Returns the first array."""
    import zarr

    g = zarr.open_group(str(path), mode="w", zarr_format=3)
    out = [
        g.create_array(
            name,
            shape=tuple(int(s) for s in shape),
            dtype=dtype,
            **chunking(tile),
            compressors=_zstd(),
            dimension_names=("y", "x"),
            fill_value=0,
        )
        for name in arrays
    ]
    if attrs:
        g.attrs.update(_jsonable(attrs))
    return out[0]


#: The default processing tile of a large scene (:func:`processing_tile`): the stored tile is
#: doubled while the doubled tile is at most ``AUTO_TILE_MAX`` px and the scene still has at
#: least ``AUTO_TILE_MIN_COUNT`` tiles of it. Measured (bench/RESULTS.md, "Session 14"): the
#: 25000 x 16700 band stored in 2048 tiles runs in 1.06-1.34 s on a warm one-GPU cluster with
#: 4096 tiles (35 tasks a pass) against 1.64-1.86 s with 2048 tiles (117), and 1.53-1.59 s
#: against 2.19-2.33 s on 16 CPU workers: each task costs the scheduler and the workers a few
#: milliseconds, and a tile's halo is a smaller share of a larger tile's read.
AUTO_TILE_MAX = 4096
AUTO_TILE_MIN_COUNT = 32


def processing_tile(shape: tuple[int, int], stored: int) -> int:
    """The processing tile of ``sarship detect`` when none is given: the scene's stored tile
    ``stored``, doubled while the doubled tile is at most :data:`AUTO_TILE_MAX` and the scene
    has at least :data:`AUTO_TILE_MIN_COUNT` tiles of it (so a large scene keeps enough tiles to
    spread over a cluster, and a small one keeps its tiles). Depends on the scene only, not on
    the cluster, so a scene is tiled alike wherever it runs; a multiple of the stored tile, so a
    processing tile reads whole shards."""
    H, W = (int(s) for s in shape)
    t = int(stored)
    while 2 * t <= AUTO_TILE_MAX and math.ceil(H / (2 * t)) * math.ceil(W / (2 * t)) >= AUTO_TILE_MIN_COUNT:
        t *= 2
    return t


def tile_slices(shape: tuple[int, int], tile: int) -> Iterator[tuple[int, int, int, int, int, int]]:
    """Yield ``(i, j, r0, r1, c0, c1)`` for each tile of a grid over ``shape`` (row-major)."""
    H, W = shape
    for i, r0 in enumerate(range(0, H, tile)):
        for j, c0 in enumerate(range(0, W, tile)):
            yield i, j, r0, min(r0 + tile, H), c0, min(c0 + tile, W)


@contextlib.contextmanager
def atomic_store(final: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary sibling path; rename it to ``final`` only if the block succeeds.

    On any exception the temporary path is removed and ``final`` is left as it was.
    """
    final = Path(final)
    parent = final.parent if str(final.parent) else Path(".")
    if not parent.exists():
        raise InputError(f"output folder '{parent}' does not exist")
    if not os.access(parent, os.W_OK):
        raise InputError(f"output folder '{parent}' is not writable")
    if final.exists() and not overwrite:
        raise InputError(f"output '{final}' already exists")
    tmp = parent / f".{final.name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        yield tmp
        if final.exists():
            old = parent / f".{final.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(final, old)
            os.replace(tmp, final)
            _rm(old)
        else:
            os.replace(tmp, final)
    except BaseException:
        _rm(tmp)
        raise


#: The name of an output's claim (:func:`claim_output`): a lock file beside the output
#: (``.NAME.sarship-claim``), or inside it (``.sarship-claim``) when its folder is not writable.
CLAIM_SUFFIX = ".sarship-claim"


def claim_path(final: str | os.PathLike) -> Path:
    """Where the claim of the output ``final`` lives: ``PARENT/.NAME.sarship-claim``, or
    ``final/.sarship-claim`` when the parent exists but is not writable and ``final`` is a
    folder that is (e.g. ``--overwrite`` into a user's folder of a root-owned one)."""
    final = Path(final)
    parent = final.parent if str(final.parent) else Path(".")
    if parent.is_dir() and not os.access(parent, os.W_OK) and final.is_dir() and os.access(final, os.W_OK):
        return final / CLAIM_SUFFIX
    return parent / f".{final.name}{CLAIM_SUFFIX}"


def _lock_or_none(lock: Path) -> int | None:
    """An open descriptor of ``lock`` holding its exclusive ``flock``; None when another open
    file holds it. Retries when the file was removed (and maybe made again) by the holder that
    just released it, so two claimers never hold two different files of one name."""
    import fcntl

    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        except BaseException:
            os.close(fd)
            raise
        try:
            if os.path.samestat(os.fstat(fd), os.stat(lock)):
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _holder(lock: Path) -> str:
    with contextlib.suppress(OSError):
        text = lock.read_text(errors="replace").strip()
        if text:
            return text.splitlines()[0][:200]
    return "another process"


@contextlib.contextmanager
def claim_output(final: str | os.PathLike, what: str = "--out", create_parents: bool = False) -> Iterator[None]:
    """Hold the output ``final`` for this process for the block: an exclusive ``flock`` on
    :func:`claim_path` (made if missing, recording ``pid N on HOST``), taken without waiting.

    Two commands writing the same output: the second is refused at once with
    :class:`InputError` naming the holder, so it can never replace the first one's output
    without ``--overwrite`` (checked by the writer *after* the claim: the first one's
    published output is found then). A crashed holder blocks nothing: the kernel releases its
    lock when the process ends, and the next claimer takes the file over (a leftover file is
    empty of meaning; the holder removes it when it releases the claim). ``create_parents``:
    make missing parent folders (removed again if still empty at the end); otherwise a missing
    parent takes no claim and is left to the writer's own check. The lock works across the
    processes of one machine and, where the file system supports ``flock`` (NFSv4, CephFS,
    Lustre with ``flock``), across machines.
    """
    import socket

    final = Path(final)
    parent = final.parent if str(final.parent) else Path(".")
    made: list[Path] = []
    if create_parents:
        missing = [d for d in (parent, *parent.parents) if not d.exists()]
        above = missing[-1].parent if missing else parent
        if above.exists() and not above.is_dir():
            raise InputError(f"{what} '{final}': '{above}' is a file, not a folder")
        for d in reversed(missing):
            try:
                d.mkdir()
            except FileExistsError:
                continue
            except OSError as exc:
                _rm_empty(made)
                raise InputError(f"cannot create output folder '{d}': {exc.strerror}") from None
            made.append(d)
    elif not parent.is_dir():
        yield
        return
    lock = claim_path(final)
    try:
        fd = _lock_or_none(lock)
    except OSError as exc:
        _rm_empty(made)
        raise InputError(
            f"cannot claim {what} '{final}': cannot write '{lock.name}' in '{lock.parent}' ({exc.strerror})"
        ) from None
    if fd is None:
        _rm_empty(made)
        raise InputError(
            f"{what} '{final}' is being written by another sarship command ({_holder(lock)}): "
            "wait for it to finish, or choose another output"
        )
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # still holding it: a waiter that opened this file retries on a new one
        os.close(fd)
        _rm_empty(made)


def _rm_empty(folders: list[Path]) -> None:
    """Remove the folders :func:`claim_output` made, innermost first, where they are empty."""
    for d in reversed(folders):
        with contextlib.suppress(OSError):
            d.rmdir()


def _rm(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        with contextlib.suppress(OSError):
            p.unlink()


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, np.generic):
            v = v.item()
        elif isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, tuple):
            v = list(v)
        out[k] = v
    return out
