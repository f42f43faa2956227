"""Reading AIS files: the format recognised from the content, each file streamed in bounded memory
with only the window kept (docs/ais.md, "Reading").

Formats: NMEA 0183 (:mod:`~sarship.pipeline.ais.nmea`), and the CSVs of MarineCadastre
(2015-2023 and 2024+), the Danish Maritime Authority and a plain ``mmsi,time,lon,lat,...``
(:mod:`~sarship.pipeline.ais.csv_formats`); each plain, gzip, zstd or zip
(:mod:`~sarship.pipeline.ais.stream`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from contextlib import closing
from pathlib import Path

from sarship.pipeline.ais.collect import Collector
from sarship.pipeline.ais.csv_formats import CsvLayout, csv_layout, read_csv
from sarship.pipeline.ais.nmea import read_nmea
from sarship.pipeline.ais.reports import ReadStats, Reports, VesselInfo, Window
from sarship.pipeline.ais.stream import READ_ERRORS, LineReader, binary_streams, compression_of
from sarship.pipeline.errors import InputError

#: an AIS sentence anywhere in a line (any talker: AI, AB, BS, ...)
_VDM = re.compile(rb"![A-Z]{2}VD[MO],")

DEFAULT_MAX_REPORTS = 4_000_000
DEFAULT_MAX_LINE_BYTES = 16_384
DEFAULT_MAX_VESSELS = 500_000


def detect_format(head: bytes, label: str) -> CsvLayout | None:
    """The format of an AIS stream from its first bytes: a CSV layout, or None for NMEA.

    A CSV is recognised by its header (the first non-empty line: MMSI, time, longitude and
    latitude columns by name); NMEA by an ``!..VDM,`` or ``!..VDO,`` sentence in the first bytes.

    Parameters
    ----------
    head
        The first bytes (decompressed), e.g. 1 MiB.
    label
        The file's name, for the message.

    Raises
    ------
    InputError
        Empty, binary, or text that is neither (one line naming the file).
    """
    if not head.strip():
        raise InputError(f"{label}: empty, no AIS")
    if b"\x00" in head[:65_536] or compression_of(head):
        raise InputError(f"{label}: not AIS (binary content)")
    first = next((ln for ln in head.split(b"\n") if ln.strip()), b"")
    layout = csv_layout(first.rstrip(b"\r"))
    if layout is not None:
        return layout
    if _VDM.search(head):
        return None
    shown = first[:80].decode("utf-8", "replace").strip()
    raise InputError(
        f"{label}: not AIS: no NMEA !AIVDM/!AIVDO sentence and no CSV header with MMSI, time, "
        f"longitude and latitude columns (first line: {shown!r})"
    )


#: Bytes of a file's start that :func:`check_ais_head` reads.
HEAD_BYTES = 1 << 20


def check_ais_head(path: Path, label: str | None = None) -> None:
    """Refuse a file whose first :data:`HEAD_BYTES` are not AIS as :func:`detect_format`
    recognises it (one-line :class:`InputError`; an unreadable file too); a compressed stream
    (gzip, zstd, zip) passes unopened: reading it decompresses and checks it. For a quick check
    of a file before it is kept or given to a job (uploads, the inbox's AIS folder)."""
    label = label or str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError as exc:
        raise InputError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if compression_of(head):
        return
    detect_format(head, label)


def _read_stream(label: str, reader: LineReader, collector: Collector, window: Window | None, stats: ReadStats) -> None:
    try:
        head = reader.head()
    except READ_ERRORS as e:
        raise InputError(f"{label}: unreadable ({type(e).__name__}: {e})") from e
    layout = detect_format(head, label)
    if layout is None:
        nr = read_nmea(reader, collector, window)
        if nr.messages and not nr.timed:
            raise InputError(
                f"{label}: NMEA without times: none of its {nr.messages} messages has a tag block "
                "c: time or a logger's timestamp"
            )
        stats.messages += nr.messages
        stats.rejected.update(nr.rejected)
    else:
        messages, bad = read_csv(reader, layout, collector, window)
        stats.messages += messages
        if bad:
            stats.rejected["bad line"] += bad
    stats.lines += reader.lines
    if reader.long_lines:
        stats.rejected["long line"] += reader.long_lines
    if reader.error:
        stats.rejected["corrupt data"] += 1


def read_ais(
    paths: Sequence[Path | str],
    window: Window | None,
    *,
    max_reports: int = DEFAULT_MAX_REPORTS,
    max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
    max_vessels: int = DEFAULT_MAX_VESSELS,
) -> tuple[Reports, dict[int, VesselInfo], ReadStats]:
    """Read AIS files: the position reports inside ``window``, what their vessels say about
    themselves, and what was read and rejected.

    Each file's format is recognised from its content (:func:`detect_format`), whatever its
    name; compressed files (gzip, zstd, zip) are recognised by their magic bytes. Files are
    streamed in chunks of 1 MiB: reports outside the window are dropped as they are read and no
    file is held. A bad line or message is counted in ``ReadStats.rejected`` under its reason,
    never fatal. Exact duplicates (same MMSI, time and position) are kept once (counted
    ``duplicate``).

    Parameters
    ----------
    paths
        The files (NMEA 0183, MarineCadastre, DMA or plain CSV; plain or compressed).
    window
        Time and box to keep (None: everything).
    max_reports
        Reports kept before reading is refused (about 56 bytes each while reading, twice that
        while sorting at the end: the default, 4 M, bounds that to about 450 MB).
    max_line_bytes
        Longest line read; longer lines are dropped (``long line``).
    max_vessels
        Vessels whose static information (name, type, dimensions) is remembered; the
        information of more is dropped (``vessel limit``).

    Returns
    -------
    reports : Reports
        Sorted by ``(mmsi, t)``.
    info : dict
        MMSI -> :class:`VesselInfo`, for the vessels in ``reports`` that said something about
        themselves (NMEA: static messages at any time in the file; CSV: the rows inside the
        window's time).
    stats : ReadStats
        Files, lines, messages, rejected by reason, kept.

    Raises
    ------
    InputError
        A file missing, empty, not AIS (binary, another CSV, other text), NMEA without any
        time, or more than ``max_reports`` reports in the window (one line).

    References
    ----------
    docs/references.md: itu-m1371 and gpsd-aivdm (the messages, their "not available" values),
    nmea0183 (sentences, checksums, tag blocks), marinecadastre-ais, dma-ais (the CSVs), pyais,
    rfc8878 (zstd), rfc1952 (gzip).
    """
    for name, value in (("max_reports", max_reports), ("max_line_bytes", max_line_bytes), ("max_vessels", max_vessels)):
        if value < 1:
            raise InputError(f"AIS: {name} must be at least 1, got {value}")
    stats = ReadStats()
    collector = Collector(window, max_reports, max_vessels)
    for p in paths:
        path = Path(p)
        if not path.is_file():
            raise InputError(f"AIS file not found: {path}")
        stats.files.append(str(path))
        try:
            with closing(binary_streams(path)) as streams:
                for label, stream in streams:
                    _read_stream(label, LineReader(stream, max_line_bytes), collector, window, stats)
        except READ_ERRORS as e:
            raise InputError(f"{path}: unreadable ({type(e).__name__}: {e})") from e
    reports, info, duplicates = collector.finish()
    stats.rejected.update(collector.rejected)
    if duplicates:
        stats.rejected["duplicate"] += duplicates
    stats.kept = len(reports)
    return reports, info, stats


__all__ = ["detect_format", "read_ais"]
