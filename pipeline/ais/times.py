"""Timestamps of AIS files as POSIX seconds UTC, cheaply: the date part of a timestamp is parsed once
and cached, the time of day by slicing (docs/ais.md, "Reading")."""

from __future__ import annotations

import calendar
import math

NAN = math.nan

#: the plausible POSIX times of AIS (2000-01-01 to 2100-01-01): other numbers are no time
_MIN_SECONDS, _MAX_SECONDS = 946_684_800.0, 4_102_444_800.0
#: a number of at least this many is read as POSIX milliseconds
_MS_FROM = 1e11


def _date_of(key: bytes) -> float:
    """POSIX time of 00:00 UTC of a date written ``YYYY-MM-DD`` or ``DD/MM/YYYY``; NaN if not a date."""
    try:
        if key[4:5] == b"-" and key[7:8] == b"-":
            y, m, d = int(key[0:4]), int(key[5:7]), int(key[8:10])
        elif key[2:3] == b"/" and key[5:6] == b"/":
            d, m, y = int(key[0:2]), int(key[3:5]), int(key[6:10])
        else:
            return NAN
    except ValueError:
        return NAN
    if not (1 <= m <= 12 and 1 <= d <= calendar.monthrange(y, m)[1]) or y < 1970:
        return NAN
    return float(calendar.timegm((y, m, d, 0, 0, 0)))


class DayCache:
    """Dates (the first 10 bytes of a timestamp) -> POSIX time of their 00:00 UTC, parsed once.

    Parameters
    ----------
    max_entries
        Entries kept before the cache is emptied (a file of garbage cannot grow it without bound).
    """

    def __init__(self, max_entries: int = 4096) -> None:
        self._days: dict[bytes, float] = {}
        self._max = max_entries

    def day(self, key: bytes) -> float:
        """The day start of ``key`` (NaN where ``key`` is not a date)."""
        d = self._days.get(key)
        if d is None:
            if len(self._days) >= self._max:
                self._days.clear()
            d = self._days[key] = _date_of(key)
        return d


def _zone_offset(rest: bytes) -> tuple[bytes, float]:
    """Split ``SS[.fff][Z|+HH[:MM]|-HH[:MM]]`` into the seconds and the zone's offset east of UTC (s)."""
    if rest.endswith((b"Z", b"z")):
        return rest[:-1], 0.0
    for sign in (b"+", b"-"):
        k = rest.find(sign)
        if k > 0:
            zone = rest[k + 1 :].replace(b":", b"")
            hours, minutes = int(zone[:2]), int(zone[2:4] or 0)
            off = hours * 3600.0 + minutes * 60.0
            return rest[:k], off if sign == b"+" else -off
    return rest, 0.0


def parse_time(text: bytes, days: DayCache) -> float:
    """POSIX seconds UTC of one timestamp; NaN where it is none.

    Accepted: ISO 8601 ``YYYY-MM-DD[T ]HH:MM:SS[.fff][Z|±HH:MM]`` (no zone: UTC), the Danish
    Maritime Authority's ``DD/MM/YYYY HH:MM:SS`` (UTC), and POSIX seconds or, from 1e11 on,
    milliseconds (a number; only times from 2000 to 2100 are read as such).

    Parameters
    ----------
    text
        The timestamp (bytes; surrounding blanks ignored).
    days
        The cache of parsed dates.

    Returns
    -------
    float
        Seconds since 1970-01-01 00:00 UTC, or NaN.
    """
    text = text.strip()
    if len(text) >= 19 and text[13:14] == b":" and text[16:17] == b":" and text[10:11] in (b"T", b" ", b"t"):
        d = days.day(text[:10])
        try:
            sec, off = _zone_offset(text[17:])
            h, m, s = int(text[11:13]), int(text[14:16]), float(sec)
        except ValueError:
            return NAN
        if h > 23 or m > 59 or not 0.0 <= s < 61.0:
            return NAN
        return d + h * 3600.0 + m * 60.0 + s - off
    try:
        x = float(text)
    except ValueError:
        return NAN
    if x >= _MS_FROM:
        x /= 1000.0
    return x if _MIN_SECONDS <= x < _MAX_SECONDS else NAN


def _clock(seconds: float) -> bytes:
    """``HH:MM:SS`` of a number of seconds into a day (floored to the second)."""
    s = int(seconds)
    return b"%02d:%02d:%02d" % (s // 3600, s // 60 % 60, s % 60)


#: the bounds that let every time of day through, and none
PASS_ALL = (b"", b"\xff")
PASS_NONE = (b"\xff", b"")


class TimeGate:
    """A conservative test of whether a timestamp string can lie in ``[t0, t1]``, without parsing it.

    For a timestamp ``DATE?HH:MM:SS...`` (ISO or DMA), :meth:`bounds` gives, per date, the range of
    ``HH:MM:SS`` (the bytes ``[11:19]``) to compare as strings; floored to whole seconds, so it may
    let through a row up to 1 s after ``t1`` (the exact test follows), never drop one inside.
    Dates it cannot read let every row through (the full parse then counts them).

    Parameters
    ----------
    t0, t1
        The window's times (POSIX seconds).
    days
        The cache of parsed dates.
    max_entries
        Dates remembered before the table is emptied.
    """

    def __init__(self, t0: float, t1: float, days: DayCache, max_entries: int = 4096) -> None:
        self.t0, self.t1 = t0, t1
        self._days = days
        self._bounds: dict[bytes, tuple[bytes, bytes]] = {}
        self._max = max_entries

    def _compute(self, key: bytes) -> tuple[bytes, bytes]:
        d = self._days.day(key)
        if math.isnan(d):
            return PASS_ALL
        lo = self.t0 - d
        hi = self.t1 - d
        if hi < 0.0 or lo >= 86_400.0:
            return PASS_NONE
        return (_clock(lo) if lo > 0.0 else b"", _clock(hi) if hi < 86_400.0 else b"\xff")

    def bounds(self, key: bytes) -> tuple[bytes, bytes]:
        """``(lo, hi)``: a row of date ``key`` can be in the window only if ``lo <= HH:MM:SS <= hi``."""
        b = self._bounds.get(key)
        if b is None:
            if len(self._bounds) >= self._max:
                self._bounds.clear()
            b = self._bounds[key] = self._compute(key)
        return b

    def may_pass(self, ts: bytes) -> bool:
        """Whether the timestamp ``ts`` (any accepted form) can be inside the window."""
        if len(ts) >= 19 and ts[13:14] == b":":
            if len(ts) > 19 and (b"+" in ts[19:] or b"-" in ts[19:]):
                return True  # a zone other than UTC: the exact test decides
            lo, hi = self.bounds(ts[:10])
            return lo <= ts[11:19] <= hi
        try:
            x = float(ts)
        except ValueError:
            return True
        if x >= _MS_FROM:
            x /= 1000.0
        return self.t0 - 1.0 <= x <= self.t1 + 1.0
