"""Simulated AIS position reports of a scene's vessels, and the plain AIS CSV file (docs/ais.md).

Every reporting vessel of :func:`~sarship.pipeline.simulate.ais_vessels.scene_vessels` (dark
ships never report) sails a straight line at its SOG and COG through its true position at its
zero-Doppler time, and reports over ``[t_c - window_s, t_c + window_s]`` (``t_c`` the zero-Doppler
time of the scene's middle row):

* report intervals (ITU-R M.1371-5, Annex 1, tables 1 and 2; docs/references.md#itu-m1371): class A at anchor
  180 s; under way 10 s up to 14 kn, 6 s up to 23 kn, 2 s above; class B ("CS") 180 s up to
  2 kn, 30 s above. A vessel's first report falls at a random phase of its interval, each report
  +- :data:`JITTER` of the interval;
* reception losses: each report lost with probability ``drop_p``, and with probability ``gap_p``
  a vessel is not received for U(0, ``max_gap_s``) at a random time; no gap between a vessel's
  received reports exceeds ``max_gap_s`` (or its own interval and jitter, where longer): in
  every ``max_gap_s / 2`` of a vessel's reports at least one is kept;
* reported values: the position with Gaussian noise of ``noise_m`` (each of east and north),
  SOG + N(0, :data:`SOG_NOISE_KN`) at 0.1 kn, COG + N(0, :data:`COG_REPORT_NOISE_DEG`) at 0.1 deg,
  the heading (class A only, whole degrees; class B: unknown), the vessel's name, length and
  width (whole metres) from its static data.

Random draws from the stream ``_S_AIS_REPORTS``: the file is the same for the same scene and
options.
"""

from __future__ import annotations

import contextlib
import math
import os
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sarship.pipeline.ais.reports import KNOT_M_S, Reports, VesselInfo
from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.ais_vessels import Vessels, scene_vessels
from sarship.pipeline.simulate.config import SimConfig, validate
from sarship.pipeline.simulate.fields import _S_AIS_REPORTS, _rng
from sarship.pipeline.simulate.land import geo_lonlat
from sarship.pipeline.simulate.motion import zero_doppler_time_s

#: Random offset of each report, as a fraction of the vessel's interval (+-).
JITTER = 0.1
#: Noise of the reported SOG (kn) and COG (deg).
SOG_NOISE_KN = 0.1
COG_REPORT_NOISE_DEG = 1.0
#: Header of the plain AIS CSV (docs/ais.md).
CSV_HEADER = "mmsi,time,lon,lat,sog,cog,heading,name,length_m,width_m"


@dataclass(frozen=True)
class AisOptions:
    """How the AIS reports are drawn (module docstring). Limits: ``window_s`` in (0, 86400],
    ``noise_m`` in [0, 10000], ``drop_p`` in [0, 1), ``gap_p`` in [0, 1], ``max_gap_s`` in [1, 86400]."""

    window_s: float = 600.0  # half-width of the reports' time window around the scene time
    noise_m: float = 10.0  # position noise (standard deviation, east and north)
    drop_p: float = 0.1  # probability that a report is lost
    gap_p: float = 0.5  # probability that a vessel has one reception gap
    max_gap_s: float = 180.0  # the longest gap between a vessel's received reports (at least its interval)

    def validated(self) -> AisOptions:
        """These options, checked (:class:`InputError`, one line naming the option)."""
        limits = {  # (low, high, text): low < v <= high, or low <= v where the text opens with [
            "window_s": (0.0, 86400.0, "(0, 86400]"),
            "noise_m": (0.0, 10000.0, "[0, 10000]"),
            "drop_p": (0.0, 1.0, "[0, 1)"),
            "gap_p": (0.0, 1.0, "[0, 1]"),
            "max_gap_s": (1.0, 86400.0, "[1, 86400]"),
        }
        for name, (lo, hi, text) in limits.items():
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            ok = ok and (lo <= v if text[0] == "[" else lo < v) and (v <= hi if text[-1] == "]" else v < hi)
            if not ok:
                raise InputError(f"AIS option {name}: must be a number in {text} (got {v!r})")
        return self


def report_interval_s(class_a: np.ndarray, anchored: np.ndarray, sog_kn: np.ndarray) -> np.ndarray:
    """Nominal AIS position report interval (s) per vessel (ITU-R M.1371-5, tables 1 and 2).

    Parameters
    ----------
    class_a
        True for a class A transponder, False for class B ("CS").
    anchored
        Class A: at anchor or moored (3 min while not faster than 3 kn).
    sog_kn
        Speed over ground (kn).

    Returns
    -------
    numpy.ndarray
        Seconds between reports.

    References
    ----------
    ITU-R M.1371-5 (2014), Annex 1, tables 1 and 2 (docs/references.md#itu-m1371).
    """
    sog = np.asarray(sog_kn, dtype=np.float64)
    a = np.where(
        np.asarray(anchored) & (sog <= 3.0), 180.0, np.where(sog <= 14.0, 10.0, np.where(sog <= 23.0, 6.0, 2.0))
    )
    b = np.where(sog <= 2.0, 180.0, 30.0)
    return np.where(np.asarray(class_a, dtype=bool), a, b)


def _schedule(
    v: Vessels, idx: np.ndarray, t0: float, t1: float, opt: AisOptions, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Received report times of the vessels ``idx``: (vessel index per report, time), by vessel then time."""
    if idx.size == 0:
        return idx, np.empty(0)
    T = report_interval_s(v.class_a[idx], v.anchored[idx], v.sog_kn[idx])
    phase = rng.uniform(0.0, 1.0, idx.size) * T
    count = np.where(phase <= t1 - t0, np.floor((t1 - t0 - phase) / T) + 1, 0).astype(np.int64)
    who = np.repeat(np.arange(idx.size), count)
    k = np.arange(who.size) - np.repeat(np.cumsum(count) - count, count)
    t = t0 + phase[who] + k * T[who] + rng.uniform(-JITTER, JITTER, who.size) * T[who]
    inside = (t >= t0) & (t <= t1)  # a jittered first or last report may fall outside
    who, t = who[inside], t[inside]
    keep = rng.random(who.size) >= opt.drop_p
    has_gap = rng.random(idx.size) < opt.gap_p
    g0 = rng.uniform(t0, t1, idx.size)
    g1 = g0 + rng.uniform(0.0, opt.max_gap_s, idx.size)
    keep &= ~(has_gap[who] & (t > g0[who]) & (t < g1[who]))
    # at least one report kept in each max_gap_s / 2 of a vessel that has reports there
    block = who * (int((t1 - t0) / (opt.max_gap_s / 2.0)) + 2) + ((t - t0) // (opt.max_gap_s / 2.0)).astype(np.int64)
    if who.size == 0:
        return who, t
    first = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])  # blocks are runs (t sorted per vessel)
    kept_any = np.add.reduceat(keep.astype(np.int64), first) > 0
    keep[first[~kept_any]] = True
    return idx[who[keep]], t[keep]


def ais_reports(cfg: SimConfig, options: AisOptions | None = None) -> tuple[Reports, dict[int, VesselInfo]]:
    """The AIS reports of a scene's vessels (module docstring) and their static data.

    Parameters
    ----------
    cfg
        A simulation with ``ais`` (and so ``geo``).
    options
        How the reports are drawn (default :class:`AisOptions`).

    Returns
    -------
    Reports, dict of int to VesselInfo
        The reports sorted by ``(mmsi, t)`` (POSIX seconds, WGS84 degrees, knots, degrees) and each
        reporting vessel's name, length and width (whole metres).
    """
    cfg = validate(cfg)
    opt = (options or AisOptions()).validated()
    v = scene_vessels(cfg)
    rng = _rng(cfg.seed, _S_AIS_REPORTS)
    tc = float(zero_doppler_time_s(cfg, cfg.shape[0] / 2.0))
    j, t = _schedule(v, np.flatnonzero(~v.dark), tc - opt.window_s, tc + opt.window_s, opt, rng)
    dy, dx = cfg.pixel_spacing_m
    c = np.radians(v.cog_deg[j])
    dt = t - v.t_s[j]
    speed = v.sog_kn[j] * KNOT_M_S
    east = speed * np.sin(c) * dt + rng.normal(0.0, opt.noise_m, t.size)
    north = speed * np.cos(c) * dt + rng.normal(0.0, opt.noise_m, t.size)
    lon, lat = geo_lonlat(cfg, v.row[j] - north / dy, v.col[j] + east / dx)  # rows run south, columns east
    sog = np.round(np.maximum(v.sog_kn[j] + rng.normal(0.0, SOG_NOISE_KN, t.size), 0.0), 1)
    cog = np.round((v.cog_deg[j] + rng.normal(0.0, COG_REPORT_NOISE_DEG, t.size)) % 360.0, 1) % 360.0
    heading = np.where(v.class_a[j], np.round(v.heading_deg[j]) % 360.0, np.nan)
    rep = Reports(
        v.mmsi[j].astype(np.int64),
        t,
        lon,
        lat,
        sog.astype(np.float32),
        cog.astype(np.float32),
        heading.astype(np.float32),
    ).sorted()
    info = {
        int(v.mmsi[i]): VesselInfo(
            int(v.mmsi[i]),
            name=str(v.name[i]),
            length_m=float(max(1.0, round(v.length_m[i]))),
            width_m=float(max(1.0, round(v.width_m[i]))),
        )
        for i in np.flatnonzero(~v.dark)
    }
    return rep, info


def csv_text(reports: Reports, info: dict[int, VesselInfo]) -> str:
    """The plain AIS CSV (:data:`CSV_HEADER`; docs/ais.md) of ``reports``, ordered by time then MMSI:
    ISO 8601 UTC times to the millisecond, positions to 1e-7 degrees, empty cells where unknown."""
    order = np.lexsort((reports.mmsi, reports.t))
    mmsi = reports.mmsi[order]
    ms = np.round(reports.t[order] * 1000.0).astype(np.int64).astype("datetime64[ms]")
    times = np.char.add(np.datetime_as_string(ms, unit="ms"), "Z")

    def fmt(a: np.ndarray, spec: str) -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        return np.where(np.isfinite(a), np.char.mod(spec, np.nan_to_num(a)), "")

    known, inv = np.unique(mmsi, return_inverse=True)  # static data per vessel, then per report
    static = [info.get(int(m)) for m in known]
    names = np.array([(i.name or "") if i else "" for i in static], dtype=object)[inv]
    length = np.array([(i.length_m or np.nan) if i else np.nan for i in static], dtype=np.float64)[inv]
    width = np.array([(i.width_m or np.nan) if i else np.nan for i in static], dtype=np.float64)[inv]
    cols = [
        mmsi.astype(str),
        times,
        fmt(reports.lon[order], "%.7f"),
        fmt(reports.lat[order], "%.7f"),
        fmt(reports.sog_kn[order], "%.1f"),
        fmt(reports.cog_deg[order], "%.1f"),
        fmt(reports.heading_deg[order], "%.0f"),
        names.astype(str),
        fmt(length, "%.0f"),
        fmt(width, "%.0f"),
    ]
    rows = cols[0].astype(object)
    for col in cols[1:]:
        rows = rows + "," + col.astype(object)
    return "\n".join([CSV_HEADER, *rows.tolist()]) + "\n"


def write_ais_csv(
    path: str | os.PathLike, cfg: SimConfig, options: AisOptions | None = None, overwrite: bool = False
) -> Path:
    """Write the scene's AIS reports (:func:`ais_reports`) as a plain AIS CSV (:func:`csv_text`).

    The file is written under a temporary name beside ``path`` and renamed into place only when
    complete; an existing ``path`` is refused (:class:`InputError`) unless ``overwrite``.
    """
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise InputError(f"AIS file '{path}' already exists: pass --overwrite to replace it")
    if path.is_dir():
        raise InputError(f"AIS file '{path}' is a folder")
    text = csv_text(*ais_reports(cfg, options))
    tmp = path.parent / f".{path.name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return path


__all__ = ["AisOptions", "CSV_HEADER", "ais_reports", "csv_text", "report_interval_s", "write_ais_csv"]
