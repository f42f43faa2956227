"""Position reports as they are read: screened in batches (vectorised), those in the window kept in
bounded memory, with each vessel's static information (docs/ais.md, "Reading").

References (docs/references.md): itu-m1371, gpsd-aivdm.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from sarship.pipeline.ais.reports import Reports, VesselInfo, Window
from sarship.pipeline.errors import InputError

#: the columns of a batch row: MMSI, time, lon, lat, SOG (kn), COG (deg), heading (deg)
COLUMNS = ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg")
#: AIS "not available" longitude and latitude (ITU-R M.1371-5, message 1)
LON_NA, LAT_NA = 181.0, 91.0
#: SOG above this is "not available" (102.3 kn, raw 1023; 102.2 means 102.2 kn or more)
SOG_NA_ABOVE = 102.25
#: COG of 360 or more is "not available" (360.0, raw 3600); heading of 360 or more too (511)
ANGLE_NA_FROM = 360.0
MMSI_MIN, MMSI_MAX = 100_000_000, 999_999_999


def screen(rows: np.ndarray, window: Window | None) -> tuple[np.ndarray, np.ndarray, Counter[str]]:
    """Screen a batch of raw reports: rejected ones counted by reason, the rest tested against the
    window, AIS "not available" values set to NaN.

    Reasons, in the order tested: ``bad mmsi`` (not 9 digits; 0 included), ``bad time`` (none
    or unreadable), ``no position`` (longitude 181 or latitude 91, the AIS "not available", or
    empty), ``bad position`` (unreadable, or beyond ±180 / ±90 degrees). SOG above 102.2 kn
    (102.3: not available) or below 0, COG and heading of 360 or more (360 and 511: not
    available) or below 0 become NaN.

    Parameters
    ----------
    rows
        ``(n, 7)`` float64, the columns of :data:`COLUMNS` (NaN where empty, +inf where
        unreadable, MMSI -1 where unreadable).
    window
        What to keep (None: every report that is not rejected).

    Returns
    -------
    keep : ndarray of bool
        The rows to keep.
    cleaned : ndarray
        ``rows`` with the "not available" values of SOG, COG and heading as NaN.
    rejected : Counter
        Rejections by reason.

    References
    ----------
    itu-m1371 and gpsd-aivdm (docs/references.md): the "not available" values of messages 1, 2,
    3, 18, 19 and 27.
    """
    mmsi, t, lon, lat = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3]
    bad_mmsi = ~((mmsi >= MMSI_MIN) & (mmsi <= MMSI_MAX))
    bad_time = ~np.isfinite(t) & ~bad_mmsi
    ok = ~bad_mmsi & ~bad_time
    no_pos = ok & ((lon == LON_NA) | (lat == LAT_NA) | np.isnan(lon) | np.isnan(lat))
    ok &= ~no_pos
    bad_pos = ok & ~((np.abs(lon) <= 180.0) & (np.abs(lat) <= 90.0))
    ok &= ~bad_pos
    rejected: Counter[str] = Counter()
    for reason, mask in (
        ("bad mmsi", bad_mmsi),
        ("bad time", bad_time),
        ("no position", no_pos),
        ("bad position", bad_pos),
    ):
        n = int(np.count_nonzero(mask))
        if n:
            rejected[reason] = n
    keep = ok if window is None else ok & window.contains(t, lon, lat)
    cleaned = rows.copy()
    sog, cog, hdg = cleaned[:, 4], cleaned[:, 5], cleaned[:, 6]
    sog[(sog > SOG_NA_ABOVE) | (sog < 0.0)] = np.nan
    cog[(cog >= ANGLE_NA_FROM) | (cog < 0.0)] = np.nan
    hdg[(hdg >= ANGLE_NA_FROM) | (hdg < 0.0)] = np.nan
    return keep, cleaned, rejected


def _text(value: str | None) -> str | None:
    value = (value or "").strip().rstrip("@").strip()
    return value or None


class Collector:
    """Reports and static information as the readers find them.

    Readers append raw rows (:data:`COLUMNS`, floats) to :attr:`rows` and call :meth:`flush` when
    it is long; :meth:`static` records what a vessel says about itself (the latest value of
    each field wins).

    Parameters
    ----------
    window
        What to keep (None: everything).
    max_reports
        Reports kept before reading is refused (:class:`InputError`).
    max_vessels
        Vessels whose static information is remembered; the information of further vessels is
        dropped and counted under ``vessel limit``.
    batch
        Rows screened at a time.
    """

    def __init__(self, window: Window | None, max_reports: int, max_vessels: int, batch: int = 65_536) -> None:
        self.window = window
        self.max_reports = max_reports
        self.max_vessels = max_vessels
        self.batch = batch
        self.rows: list[tuple[float, float, float, float, float, float, float]] = []
        self.rejected: Counter[str] = Counter()
        self.kept = 0
        self._chunks: list[np.ndarray] = []
        self._info: dict[int, list[object]] = {}

    def flush(self) -> None:
        """Screen the pending :attr:`rows`."""
        if self.rows:
            raw = np.array(self.rows, dtype=np.float64).reshape(-1, len(COLUMNS))
            self.rows.clear()
            self.add(raw)

    def add(self, raw: np.ndarray) -> None:
        """Screen a batch of raw reports (``(n, 7)``, :data:`COLUMNS`) and keep those in the window.

        Raises
        ------
        InputError
            More than ``max_reports`` kept.
        """
        keep, cleaned, rejected = screen(raw, self.window)
        self.rejected.update(rejected)
        n = int(np.count_nonzero(keep))
        if self.kept + n > self.max_reports:
            raise InputError(
                f"AIS: more than max_reports={self.max_reports} reports in the window; "
                "narrow the window or raise max_reports"
            )
        if n:
            self._chunks.append(cleaned[keep])
            self.kept += n

    def static(
        self,
        mmsi: int,
        name: str | None = None,
        ship_type: int | None = None,
        length_m: float | None = None,
        width_m: float | None = None,
    ) -> None:
        """Record what vessel ``mmsi`` says about itself (None: not said); lengths and widths of
        0 or less and ship type 0 are "not available"."""
        values = (
            _text(name),
            ship_type if ship_type else None,
            length_m if length_m and 0 < length_m < math.inf else None,
            width_m if width_m and 0 < width_m < math.inf else None,
        )
        if not MMSI_MIN <= mmsi <= MMSI_MAX or all(v is None for v in values):
            return
        rec = self._info.get(mmsi)
        if rec is None:
            if len(self._info) >= self.max_vessels:
                self.rejected["vessel limit"] += 1
                return
            rec = self._info[mmsi] = [None, None, None, None]
        for i, value in enumerate(values):
            if value is not None:
                rec[i] = value

    def finish(self) -> tuple[Reports, dict[int, VesselInfo], int]:
        """The kept reports sorted by ``(mmsi, t)`` with exact duplicates (same MMSI, time and
        position, e.g. received by two stations) removed, the static information of their
        vessels, and the number of duplicates removed."""
        self.flush()
        if not self._chunks:
            return Reports.empty(), {}, 0
        data = np.concatenate(self._chunks)
        self._chunks.clear()
        order = np.lexsort((data[:, 3], data[:, 2], data[:, 1], data[:, 0]))
        data = data[order]
        same = np.all(data[1:, :4] == data[:-1, :4], axis=1)
        data = data[np.concatenate(([True], ~same))]
        mmsi = data[:, 0].astype(np.int64)
        f32 = np.float32
        reports = Reports(
            mmsi,
            data[:, 1].copy(),
            data[:, 2].copy(),
            data[:, 3].copy(),
            data[:, 4].astype(f32),
            data[:, 5].astype(f32),
            data[:, 6].astype(f32),
        )
        info = {}
        for m in np.unique(mmsi).tolist():
            rec = self._info.get(m)
            if rec is not None:
                name, ship_type, length, width = rec
                info[m] = VesselInfo(m, name, ship_type, length, width)  # type: ignore[arg-type]
        return reports, info, int(np.count_nonzero(same))
