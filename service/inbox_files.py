"""The file side of the inbox: which files are passes, when a file is complete, its scene key
(streamed SHA-256) and the quarantine move. No database and no threads here, so each part is
testable on its own.

Supported passes are what ``sarship ingest`` reads from one path: TIFF/GeoTIFF (``.tif``,
``.tiff``), PNG/JPEG (``.png``, ``.jpg``, ``.jpeg``), ``.npy``, Sentinel-1 SAFE products zipped
(``.zip``: a GRD, or an SLC with one sub-swath; an SLC zip with several sub-swaths is refused
with the reason, as ``sarship ingest`` without ``--swath`` is) and Zarr scene folders
(``NAME.zarr``, taken as one unit: its key hashes every file of the tree, and it is complete
when its file count, total size and newest mtime are stable, or ``NAME.zarr.done`` exists).
PolSARpro folders are not taken from an inbox (no suffix marks them; ingest them with
``sarship ingest`` or ``POST /scenes``). Hidden files and folders (``.name``), temporary files
(``~``, ``.tmp``, ``.part``, ``.partial``, ``.crdownload``, ``.swp``), ``.done`` markers and
quarantine reason files are ignored; sub-folders are scanned.

The AIS folder (``SARSHIP_INBOX_AIS``, :func:`ais_files`) is listed for each new pass: its AIS
files, newest first, within a count and a total size; the same hidden and temporary names are
passed over, and files whose first MiB is not AIS (as the reader recognises it) are left out.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from sarship.pipeline.errors import InputError

if TYPE_CHECKING:
    from _hashlib import HASH

#: File suffixes of passes (lower case); ``.zarr`` folders besides.
FILE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".npy", ".zip")
#: Suffixes of files that are being written by some tool, never passes.
TEMP_SUFFIXES = (".tmp", ".part", ".partial", ".crdownload", ".swp", ".lock", ".filepart")
#: The marker that says "this file is complete": ``<file>.done``.
MARKER = ".done"
#: Hex digits of the SHA-256 kept as the scene id (the same as ``POST /scenes``).
KEY_HEX = 16
CHUNK = 1 << 20


def scene_key(sha256_hex: str) -> str:
    """The scene id of content whose SHA-256 is ``sha256_hex``: its first 16 hex digits
    (uploads and inbox passes of the same content are the same scene)."""
    return sha256_hex[:KEY_HEX]


class Signature(NamedTuple):
    """What must stay unchanged for a file to count as complete: size and mtime (for a Zarr
    folder: the total size, the newest mtime and the number of files)."""

    size: int
    mtime_ns: int
    files: int = 1


def is_pass(p: Path, is_dir: bool) -> bool:
    """Whether an inbox entry is a pass to take (see the module docstring)."""
    name = p.name
    low = name.lower()
    if name.startswith((".", "~")) or low.endswith("~") or low.endswith(TEMP_SUFFIXES):
        return False
    if is_dir:
        return low.endswith(".zarr")
    return low.endswith(FILE_SUFFIXES)


def list_passes(root: Path, skip: tuple[Path, ...] = ()) -> Iterator[Path]:
    """Every pass under ``root`` (sub-folders included, hidden ones and ``skip`` excluded;
    a ``.zarr`` folder is one pass and is not descended into). Unreadable folders are passed
    over (a vanished sub-folder is not an error)."""
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError:
            continue
        for e in entries:
            p = Path(e.path)
            try:
                is_dir = e.is_dir(follow_symlinks=False)
                is_file = e.is_file(follow_symlinks=False)
            except OSError:
                continue
            if is_dir:
                if e.name.startswith(".") or p in skip:
                    continue
                if is_pass(p, True):
                    yield p
                else:
                    stack.append(p)
            elif is_file and is_pass(p, False):
                yield p


def signature(p: Path) -> Signature | None:
    """The file's (or Zarr folder's) :class:`Signature`; None if it is gone."""
    try:
        if p.is_dir():
            size = n = newest = 0
            for f in _tree(p):
                st = f.stat()
                size += st.st_size
                newest = max(newest, st.st_mtime_ns)
                n += 1
            return Signature(size, max(newest, p.stat().st_mtime_ns), n)
        st = p.stat()
        return Signature(st.st_size, st.st_mtime_ns, 1)
    except OSError:
        return None


def marker(p: Path) -> Path:
    """The ``.done`` marker of a pass."""
    return p.with_name(p.name + MARKER)


def marked_done(p: Path, sig: Signature | None = None) -> bool:
    """Whether ``p``'s ``.done`` marker says it is complete: the marker exists and is not older
    than the file's last modification (``sig.mtime_ns``; for a Zarr folder its newest file). A
    marker older than its file was left by an earlier file of that name (or the file was
    written to after it was marked): it says nothing about this one."""
    try:
        m = marker(p).stat().st_mtime_ns
    except OSError:
        return False
    sig = sig if sig is not None else signature(p)
    return sig is not None and m >= sig.mtime_ns


def settled(stable_since: float, now: float, settle_s: float, has_marker: bool) -> bool:
    """Whether a file whose signature has been the same since ``stable_since`` may be taken:
    at once when its ``.done`` marker exists, else once it has been unchanged for ``settle_s``."""
    return has_marker or now - stable_since >= settle_s


def sha256_of(p: Path, on_chunk: Callable[[], None] | None = None, chunk: int = CHUNK) -> str:
    """SHA-256 (hex) of a file, read in ``chunk``-byte pieces (never the whole file in memory;
    hashlib releases the GIL on large updates, so the API keeps answering), or of a Zarr
    folder: every file in sorted relative-path order, each as ``path NUL size`` then its
    bytes. ``on_chunk`` is called after each piece (the inbox renews its lease there; it may
    raise to abort)."""
    h = hashlib.sha256()
    if p.is_dir():
        for f in sorted(_tree(p), key=lambda f: f.relative_to(p).as_posix()):
            rel = f.relative_to(p).as_posix().encode()
            h.update(rel + b"\0" + str(f.stat().st_size).encode() + b"\0")
            _feed(h, f, on_chunk, chunk)
    else:
        _feed(h, p, on_chunk, chunk)
    return h.hexdigest()


def _feed(h: HASH, f: Path, on_chunk: Callable[[], None] | None, chunk: int) -> None:
    with open(f, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
            if on_chunk is not None:
                on_chunk()


def _tree(d: Path) -> Iterator[Path]:
    for dirpath, dirnames, filenames in os.walk(d):
        dirnames.sort()
        for n in sorted(filenames):
            yield Path(dirpath) / n


def quarantine_target(folder: Path, p: Path, key: str | None) -> Path:
    """Where a bad file goes: ``folder/NAME``, or ``folder/STEM-KEY.SUFFIX`` when a different
    file of that name is already there."""
    dest = folder / p.name
    if dest.exists() or dest.is_symlink():
        dest = folder / f"{p.stem}-{key or uuid.uuid4().hex[:KEY_HEX]}{p.suffix}"
    return dest


def write_reason(dest: Path, fields: dict[str, str]) -> Path:
    """``DEST.reason.txt`` beside a quarantined file: ``key: value`` lines (the reason, the
    original path, the content hash, when), written aside and renamed into place."""
    out = dest.with_name(dest.name + ".reason.txt")
    tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex[:8]}")
    text = "".join(f"{k}: {' '.join(str(v).split())}\n" for k, v in fields.items())
    tmp.write_text(text)
    os.replace(tmp, out)
    return out


def move_into(src: Path, dest: Path) -> None:
    """Move a file or folder to ``dest`` so that ``dest`` is never half there: a rename
    within one file system; across file systems a copy to a hidden sibling of ``dest``, a
    rename into place, then the removal of ``src``."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.exists() or dest.is_symlink():
        raise FileExistsError(f"'{dest}' exists")
    try:
        os.rename(src, dest)
        return
    except OSError as exc:
        import errno

        if exc.errno != errno.EXDEV:
            raise
    tmp = dest.with_name(f".{dest.name}.moving-{uuid.uuid4().hex[:8]}")
    try:
        if src.is_dir():
            shutil.copytree(src, tmp, symlinks=True)
        else:
            shutil.copy2(src, tmp)
        os.rename(tmp, dest)
    except BaseException:
        _remove(tmp)
        raise
    _remove(src)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


class AisChoice(NamedTuple):
    """The AIS files a pass's jobs are given (absolute resolved paths, newest first) and what
    was left out, in one line each (empty when nothing was)."""

    paths: tuple[str, ...]
    left_out: tuple[str, ...]


def _is_ais(p: Path) -> bool:
    """Whether ``p``'s first MiB is AIS as the reader recognises it (a compressed stream passes:
    the run decompresses it and counts what it cannot read)."""
    from sarship.pipeline.ais.formats import check_ais_head

    try:
        check_ais_head(p, p.name)
    except InputError:
        return False
    return True


def ais_files(folder: Path, max_files: int, max_bytes: int) -> AisChoice:
    """The AIS files of ``folder`` (sub-folders included; hidden, temporary and ``.done`` names
    passed over) a pass's jobs read: newest modification time first, at most ``max_files``,
    adding files while their total stays within ``max_bytes`` (a file that would pass it is
    skipped, a smaller older one may still fit); files that are not AIS are left out. The run
    keeps only the reports inside the scene's time and footprint, so every file may be given."""
    found: list[tuple[int, str, int]] = []  # (-mtime_ns, path, size)
    not_ais = 0
    stack = [folder]
    while stack:
        d = stack.pop()
        try:
            entries = list(os.scandir(d))
        except OSError:
            continue
        for e in entries:
            name, low = e.name, e.name.lower()
            if name.startswith((".", "~")) or low.endswith(("~", MARKER, *TEMP_SUFFIXES)):
                continue
            try:
                if e.is_dir(follow_symlinks=False):
                    stack.append(Path(e.path))
                    continue
                if not e.is_file(follow_symlinks=True):
                    continue
                st = e.stat(follow_symlinks=True)
            except OSError:
                continue
            found.append((-st.st_mtime_ns, str(Path(e.path).resolve()), st.st_size))
    found.sort()
    paths: list[str] = []
    total = over_count = over_size = 0
    for _neg, path, size in found:
        if len(paths) >= max_files:
            over_count += 1
            continue
        if total + size > max_bytes:
            over_size += 1
            continue
        if not _is_ais(Path(path)):
            not_ais += 1
            continue
        paths.append(path)
        total += size
    left: list[str] = []
    if over_count:
        left.append(f"{over_count} older AIS file(s) beyond inbox_ais_max_files ({max_files}) left out")
    if over_size:
        left.append(f"{over_size} AIS file(s) beyond inbox_ais_max_mb ({max_bytes / 2**20:g} MiB in all) left out")
    if not_ais:
        left.append(f"{not_ais} file(s) of the AIS folder that are not AIS left out")
    return AisChoice(tuple(paths), tuple(left))
