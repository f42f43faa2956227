"""The records AIS reading, tracking and matching share (docs/ais.md)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

#: metres per second in one knot
KNOT_M_S = 1852.0 / 3600.0


@dataclass(frozen=True)
class Window:
    """What to keep of an AIS file: reports with ``t0 <= t <= t1`` inside the box (WGS84 degrees;
    ``lon_min > lon_max`` means a box across the antimeridian). A reader keeps nothing else."""

    t0: float
    t1: float
    lon_min: float
    lon_max: float
    lat_min: float
    lat_max: float

    def contains(self, t: np.ndarray, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Boolean mask of the reports inside the window."""
        in_lon = (
            (lon >= self.lon_min) & (lon <= self.lon_max)
            if self.lon_min <= self.lon_max
            else (lon >= self.lon_min) | (lon <= self.lon_max)
        )
        return (t >= self.t0) & (t <= self.t1) & in_lon & (lat >= self.lat_min) & (lat <= self.lat_max)


@dataclass
class Reports:
    """Position reports, one row each, sorted by ``(mmsi, t)``; NaN where a field is unknown."""

    mmsi: np.ndarray  # int64
    t: np.ndarray  # float64, POSIX seconds
    lon: np.ndarray  # float64
    lat: np.ndarray  # float64
    sog_kn: np.ndarray  # float32
    cog_deg: np.ndarray  # float32
    heading_deg: np.ndarray  # float32

    def __len__(self) -> int:
        return int(self.mmsi.size)

    @classmethod
    def empty(cls) -> Reports:
        f32 = np.empty(0, np.float32)
        return cls(np.empty(0, np.int64), np.empty(0), np.empty(0), np.empty(0), f32, f32.copy(), f32.copy())

    def sorted(self) -> Reports:
        """The same reports sorted by ``(mmsi, t)`` (stable)."""
        order = np.lexsort((self.t, self.mmsi))
        return Reports(*(getattr(self, f)[order] for f in _FIELDS))


_FIELDS = ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg")


@dataclass(frozen=True)
class VesselInfo:
    """What a vessel says about itself (AIS static messages 5 and 24, or a CSV's columns)."""

    mmsi: int
    name: str | None = None
    ship_type: int | None = None
    length_m: float | None = None
    width_m: float | None = None


@dataclass
class ReadStats:
    """What reading AIS files found: the ``files``, lines and messages read, those rejected (by
    reason: never fatal), and those kept in the window."""

    files: list[str] = field(default_factory=list)
    lines: int = 0
    messages: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    kept: int = 0

    def record(self) -> dict[str, object]:
        """The JSON form (``run.json``'s ``ais.read``)."""
        return {
            "files": list(self.files),
            "lines": self.lines,
            "messages": self.messages,
            "rejected": sum(self.rejected.values()),
            "rejected_by_reason": dict(sorted(self.rejected.items())),
            "kept": self.kept,
        }


@dataclass
class VesselStates:
    """Each vessel's state at a reference time ``t_ref``: position, velocity and how far it is from
    a report (``gap_s``: the time to the nearest report; ``extrapolated``: before the first or
    after the last report, propagated with SOG/COG). One row per vessel."""

    t_ref: float
    mmsi: np.ndarray  # int64
    lon: np.ndarray  # float64
    lat: np.ndarray  # float64
    v_east_m_s: np.ndarray  # float64 (NaN: speed or course unknown)
    v_north_m_s: np.ndarray  # float64
    gap_s: np.ndarray  # float64
    extrapolated: np.ndarray  # bool

    def __len__(self) -> int:
        return int(self.mmsi.size)


__all__ = ["KNOT_M_S", "ReadStats", "Reports", "VesselInfo", "VesselStates", "Window"]
