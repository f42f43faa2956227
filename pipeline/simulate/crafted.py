"""Crafted hostile inputs, for tests and ``bench/bench_hostile.py``: TIFFs that declare far
more than their size, written by hand so that nothing of the declared size is ever produced.

A real reader must refuse them from their headers (:mod:`sarship.pipeline.readers.limits`).
"""

from __future__ import annotations

import struct
from pathlib import Path

__all__ = ["crafted_tiff"]


def crafted_tiff(
    path: str | Path,
    height: int,
    width: int,
    *,
    tile: int | None = None,
    rows_per_strip: int | None = None,
    blob: bytes = b"",
    counts_zero: bool = False,
) -> Path:
    """A little-endian classic TIFF of float32 samples (one band), deflate-compressed, whose
    every strip or tile points at the same ``blob`` (e.g. ``zlib.compress(bytes(n))``), or
    declares byte count 0 with ``counts_zero`` (a sparse file). With ``tile``: square tiles of
    that side; else strips of ``rows_per_strip`` rows (default: one strip for the image).

    Examples of the issue's bombs: ``crafted_tiff(p, 40000, 40000, blob=zlib.compress(bytes(2**20)))``
    (one strip decoding to 6.4 GB); ``crafted_tiff(p, 200000, 200000, tile=2048, counts_zero=True)``
    (19 KB declaring 4e10 pixels); ``crafted_tiff(p, 40000, 40000, tile=2048, blob=...)`` (every
    tile the same blob)."""
    path = Path(path)
    if tile:
        n = -(-height // tile) * -(-width // tile)
    else:
        rows_per_strip = rows_per_strip or height
        n = -(-height // rows_per_strip)
    n_tags = 12 if tile else 11  # 7 common tags, 4 tile or 3 strip tags, PlanarConfiguration
    ifd_size = 2 + 12 * n_tags + 4
    offs_at = 8 + ifd_size
    counts_at = offs_at + 4 * n
    blob_at = counts_at + 4 * n
    count = 0 if counts_zero else len(blob)
    # (tag, type 3 SHORT / 4 LONG, count, value or offset of the values)
    tags = [
        (256, 4, 1, width),
        (257, 4, 1, height),
        (258, 3, 1, 32),
        (259, 3, 1, 8),
        (262, 3, 1, 1),
        (277, 3, 1, 1),
        (284, 3, 1, 1),
        (339, 3, 1, 3),
    ]
    if tile:
        tags += [
            (322, 4, 1, tile),
            (323, 4, 1, tile),
            (324, 4, n, offs_at if n > 1 else blob_at),
            (325, 4, n, counts_at if n > 1 else count),
        ]
    else:
        tags += [
            (273, 4, n, offs_at if n > 1 else blob_at),
            (278, 4, 1, rows_per_strip),
            (279, 4, n, counts_at if n > 1 else count),
        ]
    tags.sort()
    assert len(tags) == n_tags
    out = bytearray(b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", n_tags))
    for tag, typ, cnt, value in tags:
        v = struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value)
        out += struct.pack("<HHI", tag, typ, cnt) + v
    out += struct.pack("<I", 0)
    out += struct.pack(f"<{n}I", *([blob_at] * n))
    out += struct.pack(f"<{n}I", *([count] * n))
    out += blob
    path.write_bytes(bytes(out))
    return path
