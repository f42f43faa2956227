"""AIS files as streams of lines in bounded memory: plain, gzip, zstd or zip (recognised by their
magic bytes, never the name), read in chunks and cut into lines; a line longer than the limit is
dropped (and counted) without ever being held whole.

References (docs/references.md): rfc8878 (zstd), rfc1952 (gzip).
"""

from __future__ import annotations

import gzip
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import zstandard

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
GZIP_MAGIC = b"\x1f\x8b"
ZIP_MAGIC = b"PK\x03\x04"
#: what a corrupt or truncated compressed stream raises while it is read
READ_ERRORS = (zstandard.ZstdError, EOFError, OSError, zipfile.BadZipFile)


def compression_of(magic: bytes) -> str | None:
    """``"zstd"``, ``"gzip"``, ``"zip"`` or None (plain) from a file's first bytes."""
    if magic.startswith(ZSTD_MAGIC):
        return "zstd"
    if magic.startswith(GZIP_MAGIC):
        return "gzip"
    if magic.startswith(ZIP_MAGIC):
        return "zip"
    return None


class ZstdReader:
    """A zstd stream (one or more frames) decompressed in bounded memory: the compressed bytes are
    fed ``feed`` at a time, so one read returns at most about ``feed`` x 32768 bytes beyond what
    was asked for (a zstd block of 128 KiB takes at least 4 bytes); a stream that ends inside a
    frame (a truncated download) raises ``EOFError`` (``zstandard``'s own stream reader ends
    silently there).

    Parameters
    ----------
    raw
        The compressed bytes.
    feed
        Compressed bytes decompressed at a time.
    """

    def __init__(self, raw: BinaryIO, feed: int = 2048) -> None:
        self._raw = raw
        self._feed = feed
        self._dctx = zstandard.ZstdDecompressor()
        self._obj = self._dctx.decompressobj()
        self._pending = b""
        self._in_frame = False

    def read(self, n: int) -> bytes:
        """At least ``n`` bytes, fewer only at the end of the stream (b"" at its end)."""
        out: list[bytes] = []
        size = 0
        while size < n:
            data = self._pending or self._raw.read(self._feed)
            self._pending = b""
            if not data:
                if self._in_frame and not out:
                    raise EOFError("zstd data ends inside a frame (truncated)")
                break  # (a truncation is raised by the next read, after what was decompressed)
            chunk = self._obj.decompress(data)
            self._in_frame = True
            if self._obj.eof:
                self._pending = self._obj.unused_data
                self._obj = self._dctx.decompressobj()
                self._in_frame = False
            if chunk:
                out.append(chunk)
                size += len(chunk)
        return b"".join(out)


def binary_streams(path: Path) -> Iterator[tuple[str, BinaryIO]]:
    """The decompressed byte streams of a file: one, or one per member of a zip archive.

    Each stream is closed when the iteration moves past it (or is closed).

    Parameters
    ----------
    path
        The file.

    Yields
    ------
    tuple of (str, BinaryIO)
        A label (the path, or ``path!member`` in a zip) and the stream.
    """
    with open(path, "rb") as raw:
        kind = compression_of(raw.read(4))
        raw.seek(0)
        if kind == "zstd":
            yield str(path), ZstdReader(raw)  # type: ignore[misc]
        elif kind == "gzip":
            with gzip.GzipFile(fileobj=raw) as g:
                yield str(path), g  # type: ignore[misc]
        elif kind == "zip":
            with zipfile.ZipFile(raw) as archive:
                for info in archive.infolist():
                    if not info.is_dir():
                        with archive.open(info) as member:
                            yield f"{path}!{info.filename}", member  # type: ignore[misc]
        else:
            yield str(path), raw


class LineReader:
    """The lines of a byte stream, a list per chunk read, in bounded memory.

    Lines are bytes without their end (``\\n`` or ``\\r\\n``). A line longer than
    ``max_line_bytes`` is dropped and counted in :attr:`long_lines`; it is skipped as it is read,
    never held. :attr:`lines` counts the lines read (kept or dropped).

    Parameters
    ----------
    stream
        The decompressed bytes.
    max_line_bytes
        The longest line kept.
    chunk_bytes
        Bytes read at a time (the memory held is about this plus one line).
    """

    def __init__(self, stream: BinaryIO, max_line_bytes: int, chunk_bytes: int = 1 << 20) -> None:
        self._stream = stream
        self._max = max_line_bytes
        self._chunk = max(chunk_bytes, 1024)
        self._head: bytes | None = None
        self.lines = 0
        self.long_lines = 0
        #: why the stream ended early (corrupt compressed data, a read error), else None
        self.error: str | None = None

    def head(self) -> bytes:
        """The first chunk of the stream (read once; the iteration starts with it again)."""
        if self._head is None:
            self._head = self._stream.read(self._chunk)
        return self._head

    def _chunks(self) -> Iterator[bytes]:
        yield self.head()
        while True:
            try:
                data = self._stream.read(self._chunk)
            except READ_ERRORS as e:
                self.error = f"{type(e).__name__}: {e}"
                return
            if not data:
                return
            yield data

    def _cut(self, lines: list[bytes]) -> list[bytes]:
        """Drop the lines longer than the limit (counted)."""
        if lines and max(map(len, lines)) > self._max:
            kept = [ln for ln in lines if len(ln) <= self._max]
            self.long_lines += len(lines) - len(kept)
            return kept
        return lines

    def __iter__(self) -> Iterator[list[bytes]]:
        tail = b""
        skipping = False  # inside a line already over the limit
        for data in self._chunks():
            cut = data.rfind(b"\n")
            if cut < 0:
                if not skipping:
                    tail += data
                    if len(tail) > self._max:
                        tail, skipping = b"", True
                continue
            piece = data[: cut + 1]
            if skipping:  # the long line ends at the first newline
                piece = piece[piece.find(b"\n") + 1 :]
                self.long_lines += 1
                self.lines += 1
                skipping = False
            lines = (tail + piece).replace(b"\r\n", b"\n").split(b"\n")
            lines.pop()  # what follows the last newline
            tail = data[cut + 1 :]
            if len(tail) > self._max:
                tail, skipping = b"", True
            self.lines += len(lines)
            yield self._cut(lines)
        if skipping:
            self.long_lines += 1
            self.lines += 1
        elif tail:
            self.lines += 1
            yield self._cut([tail[:-1] if tail.endswith(b"\r") else tail])
