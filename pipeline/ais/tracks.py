"""Each AIS vessel's position and velocity at a time: its track interpolated between reports,
propagated with SOG/COG beyond them (docs/ais.md, "Physics").

Positions are moved in a local east/north frame about the vessel's report (equirectangular:
``dE = dlon cos(lat) k``, ``dN = dlat k``, ``k = pi R_E / 180``; within 0.1 % over the few
kilometres between two reports), so the maths is in metres and seconds:

- **between two reports** ``(t0, p0, v0)`` and ``(t1, p1, v1)`` (``h = t1 - t0``, ``s = (t -
  t0) / h``), the cubic Hermite curve [deboor2001] when both velocities are known (from SOG/COG,
  ``v = SOG (sin COG, cos COG)``)::

      p(s) = (2s^3 - 3s^2 + 1) p0 + (s^3 - 2s^2 + s) h v0 + (-2s^3 + 3s^2) p1 + (s^3 - s^2) h v1

  which passes through both reports with their velocities and is exact on a straight track at
  constant speed, and the velocity ``(1 - s) v0 + s v1`` (the reported velocities: the curve's
  derivative would carry the reports' position noise, divided by the few seconds between class
  A reports, into the azimuth displacement); else the straight line between them (velocity
  ``(p1 - p0) / h``);
- **before the first or after the last report**, the report's position propagated at its
  velocity for at most ``max_extrapolation_s`` (the velocity of the chord to the neighbouring
  report where SOG/COG are unknown; held, velocity NaN, for a vessel with a single report
  without them).

``gap_s`` is the time to the nearest report: the matcher's position uncertainty grows with it.
A vessel is kept when that nearest report is at most ``max_extrapolation_s`` from ``t_ref``,
interpolated or not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sarship.pipeline.ais.reports import KNOT_M_S, Reports, VesselStates
from sarship.pipeline.errors import InputError

#: mean Earth radius (m), IUGG; the local east/north frame's scale (as ``targets.georef``)
EARTH_RADIUS_M = 6_371_008.8
#: metres per degree of latitude on that sphere
M_PER_DEG = EARTH_RADIUS_M * np.pi / 180.0


@dataclass
class VesselTracks(VesselStates):
    """:class:`~sarship.pipeline.ais.reports.VesselStates` with the times of the reports around
    ``t_ref`` (``t_before``: the last report at or before it, ``t_after``: the first after it;
    NaN where there is none), so that a detection at another time knows its own nearest report
    (the matcher's ``dt_s`` and gap)."""

    t_before: np.ndarray  # float64
    t_after: np.ndarray  # float64


def velocity_m_s(sog_kn: np.ndarray, cog_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """East and north velocity (m/s) from speed over ground (knots) and course (degrees from
    true north); NaN where either is unknown, except ``SOG == 0`` (zero whatever the course).

    Parameters
    ----------
    sog_kn, cog_deg : np.ndarray
        Speed over ground and course over ground, NaN where unknown.

    Returns
    -------
    tuple of np.ndarray
        ``(v_east, v_north)`` in m/s, float64.
    """
    s = np.asarray(sog_kn, np.float64) * KNOT_M_S
    c = np.radians(np.asarray(cog_deg, np.float64))
    ve, vn = s * np.sin(c), s * np.cos(c)
    still = s == 0.0
    return np.where(still, 0.0, ve), np.where(still, 0.0, vn)


def _enu_offset(lon0, lat0, lon1, lat1) -> tuple[np.ndarray, np.ndarray]:
    """East/north metres from (lon0, lat0) to (lon1, lat1), longitude wrapped (equirectangular
    about the mean latitude)."""
    dlon = (np.asarray(lon1) - lon0 + 180.0) % 360.0 - 180.0
    coslat = np.cos(np.radians(0.5 * (np.asarray(lat0) + lat1)))
    return dlon * coslat * M_PER_DEG, (np.asarray(lat1) - lat0) * M_PER_DEG


def move(lon, lat, east_m, north_m) -> tuple[np.ndarray, np.ndarray]:
    """(lon, lat) moved by ``east_m``, ``north_m`` metres (local frame; longitude wrapped to
    [-180, 180)).

    Parameters
    ----------
    lon, lat : array_like
        Start positions, WGS84 degrees.
    east_m, north_m : array_like
        Offsets in metres (broadcast with the positions).

    Returns
    -------
    tuple of np.ndarray
        The moved ``(lon, lat)``.
    """
    lat = np.asarray(lat, np.float64)
    lat1 = lat + np.asarray(north_m) / M_PER_DEG
    coslat = np.maximum(np.cos(np.radians(0.5 * (lat + lat1))), 1e-9)
    lon1 = np.asarray(lon, np.float64) + np.asarray(east_m) / (M_PER_DEG * coslat)
    return (lon1 + 180.0) % 360.0 - 180.0, lat1


def _hermite(s, h, p0, v0, p1, v1) -> np.ndarray:
    """Cubic Hermite position at ``s`` in [0, 1] (one axis, metres; ``h`` the interval, s)."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * v0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * h * v1


def _bracket(reports: Reports, t_ref: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per vessel (runs of equal ``mmsi``): ``(start, count, i_prev, i_next)``: the first row
    and number of rows of the run, and the rows of the last report at or before ``t_ref`` and
    the first after it (-1 where none). Reports are sorted by (mmsi, t)."""
    n = len(reports)
    start = np.flatnonzero(np.r_[True, reports.mmsi[1:] != reports.mmsi[:-1]])
    count = np.diff(np.r_[start, n])
    before = np.add.reduceat((reports.t <= t_ref).astype(np.int64), start)  # a prefix of each run
    i_prev = np.where(before > 0, start + before - 1, -1)
    i_next = np.where(before < count, start + before, -1)
    return start, count, i_prev, i_next


def _check(reports: Reports, t_ref: float, max_extrapolation_s: float) -> None:
    if not np.isfinite(t_ref):
        raise InputError(f"the reference time must be a finite POSIX time, got {t_ref!r}")
    if not (np.isfinite(max_extrapolation_s) and max_extrapolation_s >= 0):
        raise InputError(f"max_extrapolation_s must be a finite number >= 0, got {max_extrapolation_s!r}")
    m, t = reports.mmsi, reports.t
    if len(m) > 1 and np.any((m[1:] < m[:-1]) | ((m[1:] == m[:-1]) & (t[1:] < t[:-1]))):
        raise InputError("AIS reports must be sorted by (mmsi, t): use Reports.sorted()")


def _usable(reports: Reports) -> Reports:
    """The reports with a finite time and position (others carry nothing to interpolate)."""
    ok = np.isfinite(reports.t) & np.isfinite(reports.lon) & np.isfinite(reports.lat)
    if ok.all():
        return reports
    return Reports(*(getattr(reports, f)[ok] for f in ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg")))


def vessel_states(reports: Reports, t_ref: float, *, max_extrapolation_s: float = 600.0) -> VesselTracks:
    """Every vessel's position and velocity at ``t_ref`` (module doc: Hermite or linear between
    the reports around ``t_ref``, SOG/COG propagation before the first or after the last).

    Parameters
    ----------
    reports : Reports
        Position reports sorted by ``(mmsi, t)`` (:meth:`Reports.sorted`); rows without a finite
        time or position are ignored.
    t_ref : float
        The reference time (POSIX seconds), e.g. the scene's middle line time.
    max_extrapolation_s : float, default 600
        A vessel is kept when its nearest report is at most this far from ``t_ref`` (the
        interpolated ones included); this also bounds the propagation beyond the first or last
        report. AIS class A reports every 2-10 s under way and every 3 min at anchor, class B
        every 30 s ([itu-m1371]): 600 s keeps a vessel through a few lost
        reports; the uncertainty the matcher gives its position grows with the gap.

    Returns
    -------
    VesselTracks
        One row per kept vessel, in ``mmsi`` order (:class:`VesselTracks`).

    Raises
    ------
    InputError
        A non-finite ``t_ref``, a negative ``max_extrapolation_s``, or unsorted reports.

    References
    ----------
    [deboor2001] (cubic Hermite interpolation), [itu-m1371] (AIS report intervals).
    """
    _check(reports, float(t_ref), float(max_extrapolation_s))
    r = _usable(reports)
    if len(r) == 0:
        e = np.empty(0)
        return VesselTracks(float(t_ref), np.empty(0, np.int64), e, e, e, e, e, np.empty(0, bool), e, e)
    t_ref = float(t_ref)
    _, _, ip, inx = _bracket(r, t_ref)
    has_p, has_n = ip >= 0, inx >= 0
    tp = np.where(has_p, r.t[np.maximum(ip, 0)], np.nan)
    tn = np.where(has_n, r.t[np.maximum(inx, 0)], np.nan)
    gap = np.fmin(t_ref - tp, tn - t_ref)
    keep = gap <= max_extrapolation_s
    ip, inx, has_p, has_n, tp, tn, gap = (a[keep] for a in (ip, inx, has_p, has_n, tp, tn, gap))
    ve_r, vn_r = velocity_m_s(r.sog_kn, r.cog_deg)
    # the nearer report anchors the state; both exist -> interpolate between them
    both = has_p & has_n
    i0 = np.where(has_p, ip, inx)
    i1 = np.where(has_n, inx, ip)
    lon0, lat0 = r.lon[i0], r.lat[i0]
    e1, n1 = _enu_offset(lon0, lat0, r.lon[i1], r.lat[i1])
    h = np.where(both, tn - tp, 1.0)
    s = np.where(both, (t_ref - tp) / h, 0.0)
    ve0, vn0, ve1, vn1 = ve_r[i0], vn_r[i0], ve_r[i1], vn_r[i1]
    hermite = both & np.isfinite(ve0) & np.isfinite(ve1)
    pe = _hermite(s, h, 0.0, np.nan_to_num(ve0), e1, np.nan_to_num(ve1))
    pn = _hermite(s, h, 0.0, np.nan_to_num(vn0), n1, np.nan_to_num(vn1))
    # the velocity: the reported ones interpolated (the curve's derivative would carry the
    # chord's position noise, amplified 1.5 times at mid-interval, into the displacement)
    ve, vn = (1 - s) * ve0 + s * ve1, (1 - s) * vn0 + s * vn1
    # linear where a velocity is unknown: the chord
    lin = both & ~hermite
    pe, pn = np.where(lin, s * e1, pe), np.where(lin, s * n1, pn)
    ve, vn = np.where(lin, e1 / h, ve), np.where(lin, n1 / h, vn)
    # one side only: propagate from the end report with its velocity (else the chord to the
    # neighbouring report of the same vessel, else held)
    ext = ~both
    ie = np.where(has_p, ip, inx)
    ive, ivn = _end_velocity(r, ie, has_p)
    dt = t_ref - r.t[ie]
    pe, pn = np.where(ext, np.nan_to_num(ive) * dt, pe), np.where(ext, np.nan_to_num(ivn) * dt, pn)
    ve, vn = np.where(ext, ive, ve), np.where(ext, ivn, vn)
    lon, lat = move(lon0, lat0, pe, pn)
    return VesselTracks(t_ref, r.mmsi[i0].astype(np.int64), lon, lat, ve, vn, gap, ext, tp, tn)


def _end_velocity(r: Reports, ie: np.ndarray, after_last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The velocity to propagate from the end report ``ie`` (``after_last``: the last report,
    else the first): its SOG/COG, else the chord from/to the neighbouring report of the same
    vessel, else NaN."""
    ve_r, vn_r = velocity_m_s(r.sog_kn[ie], r.cog_deg[ie])
    nb = np.where(after_last, ie - 1, ie + 1)
    nb_ok = (nb >= 0) & (nb < len(r))
    nb = np.clip(nb, 0, len(r) - 1)
    nb_ok &= (r.mmsi[nb] == r.mmsi[ie]) & (r.t[nb] != r.t[ie])
    e, n = _enu_offset(r.lon[nb], r.lat[nb], r.lon[ie], r.lat[ie])
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = r.t[ie] - r.t[nb]
        ce, cn = np.where(nb_ok, e / dt, np.nan), np.where(nb_ok, n / dt, np.nan)
    unknown = ~np.isfinite(ve_r) | ~np.isfinite(vn_r)
    return np.where(unknown, ce, ve_r), np.where(unknown, cn, vn_r)


def positions_at(
    states: VesselStates, t: float | np.ndarray, vessels: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Vessel positions propagated from ``states.t_ref`` to time(s) ``t`` at their velocity
    (held where the velocity is unknown): linear over the ~25 s a scene spans.

    Parameters
    ----------
    states : VesselStates
        The vessels' states at ``t_ref``.
    t : float or np.ndarray
        Target time(s), POSIX seconds: a scalar, one per vessel, or one per entry of ``vessels``.
    vessels : np.ndarray of int, optional
        Row indices into ``states`` (e.g. the vessel of each candidate pair); all rows when None.

    Returns
    -------
    tuple of np.ndarray
        ``(lon, lat)`` WGS84 degrees, one per vessel (or per entry of ``vessels``).
    """
    idx = slice(None) if vessels is None else np.asarray(vessels, np.intp)
    dt = np.asarray(t, np.float64) - states.t_ref
    ve, vn = np.nan_to_num(states.v_east_m_s[idx]), np.nan_to_num(states.v_north_m_s[idx])
    return move(states.lon[idx], states.lat[idx], ve * dt, vn * dt)


__all__ = ["EARTH_RADIUS_M", "M_PER_DEG", "VesselTracks", "move", "positions_at", "velocity_m_s", "vessel_states"]
