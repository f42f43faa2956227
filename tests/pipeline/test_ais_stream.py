"""AIS files as lines in bounded memory (pipeline/ais/stream.py): the lines of any chunking equal
those of the whole text, long lines dropped and counted; zstd in several frames, truncated."""

from __future__ import annotations

import io

import numpy as np
import pytest
import zstandard

from sarship.pipeline.ais.stream import LineReader, ZstdReader


def _text(rng: np.random.Generator, n: int) -> tuple[bytes, list[bytes]]:
    lengths = rng.choice([0, 5, 80, 1000, 1500, 3000, 9000], n, p=[0.05, 0.3, 0.4, 0.1, 0.05, 0.05, 0.05])
    lines = [bytes(rng.integers(32, 127, k, dtype=np.uint8)) for k in lengths.tolist()]
    ends = [b"\r\n" if rng.random() < 0.3 else b"\n" for _ in lines]
    text = b"".join(ln + e for ln, e in zip(lines, ends))
    return text, lines


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("final_newline", [True, False])
def test_lines_equal_the_split_text_and_long_ones_are_counted(seed, final_newline):
    rng = np.random.default_rng(seed)
    text, lines = _text(rng, 300)
    if not final_newline:  # the last line ends the text
        text = text[:-2] if text.endswith(b"\r\n") else text[:-1]
        lines = lines if lines[-1] else lines[:-1]
    limit = 2000
    r = LineReader(io.BytesIO(text), max_line_bytes=limit, chunk_bytes=1024 + 17 * seed)
    got = [ln for block in r for ln in block]
    assert got == [ln for ln in lines if len(ln) <= limit]
    assert r.long_lines == sum(len(ln) > limit for ln in lines)
    assert r.lines == len(lines)


def test_zstd_frames_are_read_across_and_a_truncation_is_raised_after_the_data():
    data = bytes(np.random.default_rng(1).integers(48, 58, 300_000, dtype=np.uint8))
    c = zstandard.ZstdCompressor()
    frames = c.compress(data[:100_000]) + c.compress(data[100_000:250_000]) + c.compress(data[250_000:])
    r = ZstdReader(io.BytesIO(frames))
    got = b"".join(iter(lambda: r.read(65_536), b""))
    assert got == data
    r = ZstdReader(io.BytesIO(frames[: len(frames) - 100]))
    got = b""
    with pytest.raises(EOFError):
        while chunk := r.read(65_536):
            got += chunk
    assert 250_000 <= len(got) < len(data) and data.startswith(got)
