"""AIS as CSV: MarineCadastre (2015-2023 and 2024+), the Danish Maritime Authority's and a plain
``mmsi,time,lon,lat,...``, recognised by their header and read by column name (docs/ais.md).

Speed: a row is first tested against the window's time from its timestamp's bytes alone (the
date part parsed once per date, the time of day compared as a string: :class:`TimeGate`); only
the rows that may be inside are split and parsed. Rows are split with ``bytes.split`` unless
they hold a quote, then with the ``csv`` module.

References (docs/references.md): marinecadastre-ais, dma-ais, itu-m1371.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass

import numpy as np

from sarship.pipeline.ais.collect import Collector
from sarship.pipeline.ais.reports import Window
from sarship.pipeline.ais.stream import LineReader
from sarship.pipeline.ais.times import DayCache, TimeGate, parse_time

NAN = math.nan
INF = math.inf

#: header names (lower case, letters and digits only) of each column a reader uses
ALIASES: dict[str, tuple[str, ...]] = {
    "mmsi": ("mmsi",),
    "time": ("basedatetime", "timestamp", "time", "datetime"),
    "lon": ("lon", "longitude"),
    "lat": ("lat", "latitude"),
    "sog": ("sog",),
    "cog": ("cog",),
    "heading": ("heading", "trueheading"),
    "name": ("vesselname", "name", "shipname"),
    "ship_type": ("vesseltype", "shiptype"),
    "length": ("length", "lengthm"),
    "width": ("width", "widthm"),
}
REQUIRED = ("mmsi", "time", "lon", "lat")

#: the Danish Maritime Authority's ship type names -> the AIS ship type (itu-m1371, gpsd-aivdm:
#: the first code of each name's group)
DMA_SHIP_TYPES: dict[str, int] = {
    "wig": 20,
    "fishing": 30,
    "towing": 31,
    "towing long/wide": 32,
    "dredging": 33,
    "diving": 34,
    "military": 35,
    "sailing": 36,
    "pleasure": 37,
    "hsc": 40,
    "pilot": 50,
    "sar": 51,
    "tug": 52,
    "port tender": 53,
    "anti-pollution": 54,
    "law enforcement": 55,
    "medical": 58,
    "not party to conflict": 59,
    "passenger": 60,
    "cargo": 70,
    "tanker": 80,
    "other": 90,
}


@dataclass(frozen=True)
class CsvLayout:
    """Where a CSV file holds what: ``kind`` (``dma``, ``marinecadastre``, ``marinecadastre-2024``
    or ``plain``), the ``delimiter``, each used column's index, and the number of fields a row
    needs."""

    kind: str
    delimiter: bytes
    columns: dict[str, int]
    needed: int


def _norm(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def csv_layout(header: bytes) -> CsvLayout | None:
    """The layout of an AIS CSV from its header line; None when it lacks an AIS column
    (MMSI, time, longitude, latitude).

    Parameters
    ----------
    header
        The first line of the file.
    """
    text = header.decode("utf-8", "replace").lstrip("\ufeff")
    delim = max((",", ";", "\t", "|"), key=text.count)
    names = [n.strip().strip('"').strip() for n in text.split(delim)]
    normed = [_norm(n) for n in names]
    columns: dict[str, int] = {}
    for role, aliases in ALIASES.items():
        for alias in aliases:
            if alias in normed:
                columns[role] = normed.index(alias)
                break
    if any(r not in columns for r in REQUIRED):
        return None
    raw_time = names[columns["time"]]
    if raw_time == "BaseDateTime":
        kind = "marinecadastre"
    elif raw_time == "base_date_time":
        kind = "marinecadastre-2024"
    elif "typeofmobile" in normed:
        kind = "dma"
    else:
        kind = "plain"
    return CsvLayout(kind, delim.encode(), columns, max(columns.values()) + 1)


def _num(b: bytes) -> float:
    """A number field: NaN where empty, +inf where unreadable."""
    try:
        return float(b)
    except ValueError:
        return NAN if not b.strip() else INF


def _ship_type(b: bytes) -> int | None:
    """A ship type field: an AIS code, or a DMA name (mapped to the group's first code)."""
    b = b.strip()
    if not b:
        return None
    try:
        return int(float(b))
    except ValueError:
        return DMA_SHIP_TYPES.get(b.decode("utf-8", "replace").strip().lower())


def _quoted(line: bytes, delim: bytes) -> list[bytes]:
    """The fields of a row that holds quotes (the ``csv`` module's rules)."""
    row = next(csv.reader([line.decode("utf-8", "replace")], delimiter=delim.decode()), [])
    return [f.encode() for f in row]


def _gated(lines: list[bytes], col: int, delim: bytes, gate: TimeGate, fixed: bool) -> list[bytes]:
    """The lines whose timestamp (column ``col``) may lie in the gate's time window; ``fixed``:
    the timestamps are ``DATE?HH:MM:SS`` (compared as strings where the column is the first or
    second)."""
    out = []
    bounds = gate.bounds
    if fixed and col == 0:
        for ln in lines:
            lo, hi = bounds(ln[:10])
            if lo <= ln[11:19] <= hi:
                out.append(ln)
    elif fixed and col == 1:
        for ln in lines:
            k = ln.find(delim) + 1
            lo, hi = bounds(ln[k : k + 10])
            if lo <= ln[k + 11 : k + 19] <= hi:
                out.append(ln)
    else:
        may_pass = gate.may_pass
        for ln in lines:
            parts = ln.split(delim, col + 1)
            if len(parts) <= col or may_pass(parts[col]):
                out.append(ln)
    return out


def _fixed_clock(sample: bytes) -> bool:
    """Whether a timestamp is ``DATE?HH:MM:SS`` without a zone other than UTC (string-gateable)."""
    s = sample.strip()
    return len(s) >= 19 and s[13:14] == b":" and s[16:17] == b":" and not (b"+" in s[19:] or b"-" in s[19:])


def _floats(col: list[bytes]) -> list[float]:
    """Number fields: NaN where empty, +inf where unreadable."""
    try:
        return [float(x) if x else NAN for x in col]
    except ValueError:
        return [_num(x) for x in col]


def _mmsis(col: list[bytes]) -> np.ndarray:
    """MMSI fields as int64, -1 where unreadable."""
    try:
        return np.array([int(x) for x in col], dtype=np.int64)
    except (ValueError, OverflowError):
        out = np.full(len(col), -1, dtype=np.int64)
        for i, x in enumerate(col):
            try:
                out[i] = min(max(int(x), -1), 2**62)
            except ValueError:
                pass
        return out


#: byte offsets of the digits of ``HH:MM:SS`` in ``DATE?HH:MM:SS``
_CLOCK_DIGITS = [11, 12, 14, 15, 17, 18]


def clock_times(col: list[bytes], days: DayCache) -> np.ndarray:
    """Timestamps (:func:`~sarship.pipeline.ais.times.parse_time`'s forms) as POSIX seconds, NaN
    where unreadable; the ``DATE?HH:MM:SS`` ones of 19 bytes parsed vectorised (the date once per
    distinct date), the others one by one."""
    a = np.array(col, dtype="S")
    n = a.size
    if n == 0 or a.dtype.itemsize != 19:
        return np.array([parse_time(x, days) for x in col], dtype=np.float64).reshape(n)
    u = a.view(np.uint8).reshape(n, 19)
    d = u[:, _CLOCK_DIGITS].astype(np.int64) - 48
    ok = (u[:, 13] == 58) & (u[:, 16] == 58) & ((u[:, 10] == 32) | (u[:, 10] == 84)) & np.all((d >= 0) & (d <= 9), 1)
    hh, mm, ss = d[:, 0] * 10 + d[:, 1], d[:, 2] * 10 + d[:, 3], d[:, 4] * 10 + d[:, 5]
    ok &= (hh < 24) & (mm < 60) & (ss < 61)
    keys, inverse = np.unique(np.ascontiguousarray(u[:, :10]).view("S10").ravel(), return_inverse=True)
    day = np.array([days.day(k) for k in keys.tolist()], dtype=np.float64)[inverse.ravel()]
    t = day + hh * 3600.0 + mm * 60.0 + ss
    for i in np.flatnonzero(~ok).tolist():
        t[i] = parse_time(col[i], days)
    return t


class _Static:
    """The static columns of a layout (name, ship type, length, width), recorded for each vessel
    when they change (in the order read: the latest non-empty value of each field wins)."""

    def __init__(self, layout: CsvLayout, collector: Collector) -> None:
        c = layout.columns
        self.roles = [r for r in ("name", "ship_type", "length", "width") if r in c]
        self.idx = [c[r] for r in self.roles]
        self.seen: set[tuple[object, ...]] = set()
        self.collector = collector

    def note(self, mmsi: list[int], rows: list[list[bytes]]) -> None:
        """Record the static fields of parsed ``rows`` (of vessels ``mmsi``)."""
        if not self.idx:
            return
        seen = self.seen
        keys = zip(mmsi, *([r[i] for r in rows] for i in self.idx))
        fresh = dict.fromkeys(k for k in keys if k not in seen)
        if len(seen) + len(fresh) > self.collector.max_vessels:
            seen.clear()  # bounded: noting a vessel again changes nothing
        for key in fresh:
            seen.add(key)
            got: dict[str, bytes] = dict(zip(self.roles, key[1:]))  # type: ignore[arg-type]
            name, length, width = got.get("name"), got.get("length"), got.get("width")
            self.collector.static(
                key[0],  # type: ignore[arg-type]
                name.decode("utf-8", "replace") if name else None,
                _ship_type(got.get("ship_type", b"")),
                _num(length) if length else None,
                _num(width) if width else None,
            )


def parse_rows(lines: list[bytes], layout: CsvLayout, days: DayCache) -> tuple[np.ndarray, list[list[bytes]], int]:
    """Parse CSV rows column by column.

    Parameters
    ----------
    lines
        The rows (bytes, without line ends; empty ones skipped).
    layout
        The file's layout.
    days
        The cache of parsed dates.

    Returns
    -------
    raw : ndarray
        ``(n, 7)`` float64, the columns of :data:`~sarship.pipeline.ais.collect.COLUMNS` (NaN
        where empty, +inf where unreadable).
    rows : list
        The fields of each row of ``raw``.
    bad : int
        Rows dropped as malformed (too few fields, or an MMSI that is no number).
    """
    delim, needed, c = layout.delimiter, layout.needed, layout.columns
    # split only as far as the last column used
    split = [ln.split(delim, needed) if b'"' not in ln else _quoted(ln, delim) for ln in lines if ln]
    rows = [r for r in split if len(r) >= needed]
    mmsi = _mmsis([r[c["mmsi"]] for r in rows])
    readable = mmsi >= 0
    bad = len(split) - len(rows) + int(np.count_nonzero(~readable))
    if not readable.all():
        rows = [r for r, ok in zip(rows, readable.tolist()) if ok]
        mmsi = mmsi[readable]
    raw = np.empty((len(rows), 7), dtype=np.float64)
    raw[:, 0] = mmsi
    raw[:, 1] = clock_times([r[c["time"]] for r in rows], days)
    for j, role in enumerate(("lon", "lat", "sog", "cog", "heading"), start=2):
        raw[:, j] = _floats([r[c[role]] for r in rows]) if role in c else NAN
    return raw, rows, bad


def read_csv(reader: LineReader, layout: CsvLayout, collector: Collector, window: Window | None) -> tuple[int, int]:
    """Stream an AIS CSV into ``collector``.

    The header is the first non-empty line. Rows whose timestamp is outside the window's time
    are dropped before they are split (a string test, :class:`TimeGate`); the rest are parsed
    and screened (:func:`~sarship.pipeline.ais.collect.screen`). Static columns (name, ship type,
    length, width) are recorded for the rows inside the window's time.

    Parameters
    ----------
    reader
        The file's lines.
    layout
        Its layout (:func:`csv_layout`).
    collector
        Where the rows go.
    window
        What to keep (None: everything).

    Returns
    -------
    tuple of int
        The data rows read (the messages) and the malformed ones (``bad line``).
    """
    days = DayCache()
    gate = TimeGate(window.t0, window.t1, days) if window is not None else None
    static = _Static(layout, collector)
    it, delim = layout.columns["time"], layout.delimiter
    header_seen = False
    fixed: bool | None = None
    messages = bad = 0
    for lines in reader:
        if not header_seen:
            while lines and not lines[0].strip():
                lines = lines[1:]
            if not lines:
                continue
            lines, header_seen = lines[1:], True
        messages += len(lines) - lines.count(b"")
        if gate is not None and lines:
            if fixed is None:
                sample = next((ln for ln in lines if ln), b"").split(delim, it + 1)
                # the known formats' timestamps are DATE?HH:MM:SS in UTC; a plain CSV's may carry zones
                fixed = layout.kind != "plain" and len(sample) > it and _fixed_clock(sample[it])
            lines = _gated(lines, it, delim, gate, fixed)
        if lines:
            raw, rows, n_bad = parse_rows(lines, layout, days)
            bad += n_bad
            static.note(raw[:, 0].astype(np.int64).tolist(), rows)
            collector.add(raw)
    return messages, bad
