"""AIS as NMEA 0183 ``!AIVDM``/``!AIVDO`` sentences, decoded by pyais: position reports 1/2/3,
18, 19 and 27, static messages 5, 19 and 24 (parts A and B); multi-sentence messages joined by
their sequence id and channel, in any order and interleaved (docs/ais.md, "Reading").

The time of a message: the ``c:`` field (POSIX seconds, or milliseconds from 1e11 on) of an NMEA
4.0 tag block ``\\c:1700000000*hh\\`` before the sentence; else a logger's timestamp before the
``!`` (ISO 8601 or POSIX seconds); else a POSIX time as the last comma-separated field after the
checksum (the USCG NAIS log form). A message with none is rejected (``no time``).

Speed: a single-sentence position report whose time is outside the window is dropped before its
checksum is computed or its payload decoded.

References (docs/references.md): nmea0183, itu-m1371, gpsd-aivdm, pyais.
"""

from __future__ import annotations

import math
from collections import Counter
from functools import reduce
from operator import xor
from typing import Any

from pyais.exceptions import AISBaseException
from pyais.messages import AISSentence, NMEAMessage

from sarship.pipeline.ais.collect import Collector
from sarship.pipeline.ais.reports import Window
from sarship.pipeline.ais.stream import LineReader
from sarship.pipeline.ais.times import DayCache, parse_time

NAN = math.nan
#: first payload character of the position reports that carry no static fields (types 1, 2, 3,
#: 18 and 27, six-bit ASCII armour): those are dropped unread outside the window's time
POSITION_ONLY = frozenset((b"1", b"2", b"3", b"B", b"K"))
#: separators a logger writes between its timestamp and the sentence
_PREFIX_SEPARATORS = b" \t,;|[]:"
#: message 27's "not available" speed (kn) and course (deg)
SPEED27_NA, COURSE27_NA = 63.0, 511.0


def nmea_checksum_ok(body: bytes, hex_digits: bytes) -> bool:
    """Whether the XOR of the bytes of ``body`` (between ``!`` or ``\\`` and ``*``) equals the
    hexadecimal ``hex_digits`` (the NMEA 0183 checksum, nmea0183)."""
    try:
        return reduce(xor, body, 0) == int(hex_digits, 16)
    except ValueError:
        return False


def tag_block_time(tag: bytes, days: DayCache) -> float | None:
    """The ``c:`` time of a tag block's text (between the backslashes): POSIX seconds (or
    milliseconds from 1e11 on), NaN when it has none; None when its checksum is wrong."""
    star = tag.rfind(b"*")
    if star < 0 or not nmea_checksum_ok(tag[:star], tag[star + 1 :]):
        return None
    for field in tag[:star].split(b","):
        if field.startswith(b"c:"):
            return parse_time(field[2:], days)
    return NAN


def split_line(line: bytes, days: DayCache) -> tuple[float, bytes] | str:
    """A line's time (NaN if it carries none) and its sentence (``!`` to the checksum), or the
    reason it is rejected (``bad line``, ``bad checksum`` of its tag block, ``not AIS``)."""
    i = line.find(b"!")
    if i < 0:
        return "not AIS" if b"$" in line else "bad line"
    t = NAN
    j = line.find(b"\\")
    prefix = line[:i]
    if 0 <= j < i:
        k = line.find(b"\\", j + 1)
        if k < 0 or k > i:
            return "bad line"
        tt = tag_block_time(line[j + 1 : k], days)
        if tt is None:
            return "bad checksum"
        t, prefix = tt, line[:j]
    sentence = line[i:]
    star = sentence.find(b"*")
    if star < 0 or len(sentence) < star + 3:
        return "bad line"
    tail = sentence[star + 3 :]
    sentence = sentence[: star + 3]
    if t != t:
        prefix = prefix.strip(_PREFIX_SEPARATORS)
        if prefix:
            t = parse_time(prefix, days)
        elif tail:
            t = parse_time(tail.rsplit(b",", 1)[-1], days)
    return t, sentence


class _Fragments:
    """Parts of a multi-sentence message seen so far."""

    __slots__ = ("parts", "times")

    def __init__(self, count: int) -> None:
        self.parts: list[bytes | None] = [None] * count
        self.times: list[float] = []


def _position(msg: Any, t: float) -> tuple[float, ...]:
    """The row of a position report (raises TypeError where a field is missing)."""
    mmsi, lon, lat = float(msg.mmsi), float(msg.lon), float(msg.lat)
    if msg.msg_type == 27:
        sog, cog = float(msg.speed), float(msg.course)
        return (mmsi, t, lon, lat, sog if sog < SPEED27_NA else NAN, cog if cog < COURSE27_NA else NAN, NAN)
    return (mmsi, t, lon, lat, float(msg.speed), float(msg.course), float(msg.heading))


def _dims(msg: Any) -> tuple[float, float]:
    return float(msg.to_bow + msg.to_stern), float(msg.to_port + msg.to_starboard)


def take(msg: Any, t: float, collector: Collector) -> None:
    """Put one decoded message into the collector: its position (types 1, 2, 3, 18, 19, 27) and
    what it says of its vessel (5, 19, 24: name, ship type, length ``A + B`` and width ``C + D``,
    the distances from the reference point to bow, stern, port and starboard; 0 is "not
    available"). Other types are ignored. Nothing is taken from a message with a missing field
    (TypeError). References: itu-m1371, gpsd-aivdm."""
    mt = msg.msg_type
    row = _position(msg, t) if mt in (1, 2, 3, 18, 19, 27) else None
    static: tuple[Any, ...] | None = None
    if mt in (5, 19) or (mt == 24 and msg.partno == 1):
        length, width = _dims(msg)
        static = (msg.mmsi, msg.shipname if mt != 24 else None, int(msg.ship_type), length, width)
    elif mt == 24:
        static = (msg.mmsi, str(msg.shipname), None, None, None)
    if row is not None:
        collector.rows.append(row)  # type: ignore[arg-type]
    if static is not None:
        collector.static(*static)


def _decode(sentences: list[bytes]) -> Any:
    parts = [AISSentence(s) for s in sentences]
    return NMEAMessage.assemble_from_iterable(parts).decode()


class NmeaReader:
    """The state of reading one NMEA stream: the fragments waiting for their message, counts.

    Parameters
    ----------
    collector
        Where the messages go.
    window
        What to keep (None: everything).
    max_pending
        Multi-sentence messages waiting for parts at a time; beyond it the oldest is dropped
        (counted ``incomplete message``).
    """

    def __init__(self, collector: Collector, window: Window | None, max_pending: int = 256) -> None:
        self.collector = collector
        self.window = window
        self.max_pending = max_pending
        self.days = DayCache()
        self.pending: dict[tuple[bytes, ...], _Fragments] = {}
        self.rejected: Counter[str] = Counter()
        self.messages = 0
        self.timed = 0

    def _message(self, sentences: list[bytes], t: float) -> None:
        self.messages += 1
        if t != t:
            self.rejected["no time"] += 1
            return
        self.timed += 1
        try:
            take(_decode(sentences), t, self.collector)
        except (AISBaseException, ValueError, TypeError, KeyError, IndexError, AttributeError):
            # pyais leaves the fields of a short payload None, or raises on a corrupt one
            self.rejected["bad message"] += 1

    def _fragment(self, parts: list[bytes], sentence: bytes, t: float) -> None:
        try:
            count, number = int(parts[1]), int(parts[2])
        except ValueError:
            self.rejected["bad line"] += 1
            return
        if not 1 <= number <= count <= 9:
            self.rejected["bad line"] += 1
            return
        key = (parts[0][1:3], parts[3], parts[4], parts[1])
        frag = self.pending.get(key)
        if frag is None or frag.parts[number - 1] is not None:
            if frag is not None:
                self.rejected["incomplete message"] += 1
            if len(self.pending) >= self.max_pending:
                self.pending.pop(next(iter(self.pending)))
                self.rejected["incomplete message"] += 1
            frag = self.pending[key] = _Fragments(count)
        frag.parts[number - 1] = sentence
        if t == t:
            frag.times.append(t)
        if all(p is not None for p in frag.parts):
            del self.pending[key]
            self._message(frag.parts, frag.times[0] if frag.times else NAN)  # type: ignore[arg-type]

    def line(self, line: bytes) -> None:
        """Read one line."""
        got = split_line(line, self.days)
        if isinstance(got, str):
            self.rejected[got] += 1
            return
        t, sentence = got
        parts = sentence.split(b",")
        if len(parts) != 7 or parts[0][3:6] not in (b"VDM", b"VDO"):
            self.rejected["not AIS" if len(parts[0]) == 6 else "bad line"] += 1
            return
        if parts[1] == b"1":
            w = self.window
            if w is not None and t == t and parts[5][:1] in POSITION_ONLY and not w.t0 <= t <= w.t1:
                self.messages += 1  # outside the window's time: dropped unread
                return
        if not nmea_checksum_ok(sentence[1:-3], sentence[-2:]):
            self.rejected["bad checksum"] += 1
            return
        if parts[1] == b"1":
            self._message([sentence], t)
        else:
            self._fragment(parts, sentence, t)

    def finish(self) -> None:
        """Count the messages still waiting for parts."""
        if self.pending:
            self.rejected["incomplete message"] += len(self.pending)
            self.pending.clear()


def read_nmea(reader: LineReader, collector: Collector, window: Window | None) -> NmeaReader:
    """Stream an NMEA file into ``collector``; returns the reader's state (messages, rejections,
    how many messages had a time).

    Parameters
    ----------
    reader
        The file's lines.
    collector
        Where the messages go.
    window
        What to keep (None: everything).
    """
    nr = NmeaReader(collector, window)
    rows = collector.rows
    for lines in reader:
        for ln in lines:
            if ln.strip():
                nr.line(ln)
            if len(rows) >= collector.batch:
                collector.flush()
    nr.finish()
    return nr
