"""The AIS stage: the run's detections matched to the AIS reports given (docs/ais.md).

After the refine stage, when the run was given AIS files: the reports inside the scene's time
(each side widened by ``max_extrapolation_s``) and footprint (widened by :data:`MARGIN_M`) are
read (:func:`~sarship.pipeline.ais.formats.read_ais`), each vessel's state taken at the scene's
middle line time (:func:`~sarship.pipeline.ais.tracks.vessel_states`), the detections described
by their centres, line times, lengths and look geometry, and matched
(:func:`~sarship.pipeline.ais.match.match`). Every feature gets ``ais`` (the matched vessel, or
null) and ``dark``; the vessels that reported inside the footprint and matched nothing become
the Point features of ``ais_unmatched.geojson``; ``run.json`` gets the ``ais`` record.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.ais.coverage import covers_scene, dark_flags, footprint_ring
from sarship.pipeline.ais.displacement import look_geometry
from sarship.pipeline.ais.formats import read_ais
from sarship.pipeline.ais.match import Assignment, Detections, MatchParams, match, vessel_lengths
from sarship.pipeline.ais.reports import VesselInfo, Window
from sarship.pipeline.ais.scene_time import line_times
from sarship.pipeline.ais.tracks import vessel_states
from sarship.pipeline.errors import InputError
from sarship.pipeline.targets.ship_features import Georeference

#: how far (m) beyond the scene's footprint AIS reports are read: a vessel outside it may be
#: imaged inside (its azimuth displacement, up to ~2 km) or reach it before the scene time
MARGIN_M = 5000.0
#: metres per degree of latitude (the window's margin in degrees)
M_PER_DEG = 111_320.0
#: a ship at least this many pixels long (the larger ground spacing) is taken as detectable where
#: the run's own size rule states no minimum length (docs/ais.md, "Unmatched vessels")
DETECTABLE_MIN_PX = 3.0


@dataclass(frozen=True)
class AisOptions:
    """The AIS of a run: its files (absolute, checked to exist) and the matcher's parameters."""

    paths: tuple[Path, ...]
    params: MatchParams = dataclasses.field(default_factory=MatchParams)


@dataclass(frozen=True)
class AisOutcome:
    """What the stage adds: ``unmatched`` (GeoJSON Point features) and ``record`` (``run.json``'s
    ``ais``); the features' ``ais`` and ``dark`` properties are set in place."""

    unmatched: list[dict[str, Any]]
    record: dict[str, Any]


def ais_options(
    paths: Sequence[str | Path] | None, attrs: Mapping[str, Any], geo: Mapping[str, Any]
) -> AisOptions | None:
    """The run's :class:`AisOptions` (None without AIS files), checked before any work: every
    file exists, and the scene is georeferenced and has a time; a one-line InputError otherwise."""
    if not paths:
        return None
    files = []
    for p in paths:
        path = Path(p)
        if not path.is_file():
            raise InputError(f"--ais {p}: no such file")
        files.append(path.absolute())
    if not geo:
        raise InputError("--ais: the scene is not georeferenced (no transform or GCPs), so detections have no lon/lat")
    if line_times(attrs, np.zeros(1)) is None:
        raise InputError(
            "--ais: the scene states no acquisition time (sar_geometry.first_line_time, acquisition_start or acquired)"
        )
    return AisOptions(tuple(files))


def _window(ring: np.ndarray, t0: float, t1: float, params: MatchParams) -> Window:
    """The reports to read: the scene's time widened by ``max_extrapolation_s`` each side, its
    footprint's lon/lat box widened by :data:`MARGIN_M` (across the antimeridian: ``lon_min >
    lon_max``, as :class:`Window` reads it)."""
    lon, lat = ring[:, 0], ring[:, 1]
    if float(np.max(lon)) - float(np.min(lon)) > 180.0:  # the footprint straddles the antimeridian
        lo, hi = float(np.min(lon[lon > 0])), float(np.max(lon[lon < 0]))
    else:
        lo, hi = float(np.min(lon)), float(np.max(lon))
    lat_pad = MARGIN_M / M_PER_DEG
    lon_pad = MARGIN_M / (M_PER_DEG * max(math.cos(math.radians(float(np.max(np.abs(lat))))), 0.01))
    pad = params.max_extrapolation_s
    return Window(
        t0 - pad,
        t1 + pad,
        (lo - lon_pad + 180.0) % 360.0 - 180.0,
        (hi + lon_pad + 180.0) % 360.0 - 180.0,
        max(float(np.min(lat)) - lat_pad, -90.0),
        min(float(np.max(lat)) + lat_pad, 90.0),
    )


def _detections(features: list[dict[str, Any]], attrs: Mapping[str, Any], georef: Georeference) -> Detections:
    props = [f["properties"] for f in features]
    rows = np.array([p["centroid_px"][0] for p in props], np.float64).reshape(-1)
    cols = np.array([p["centroid_px"][1] for p in props], np.float64).reshape(-1)
    centre = [p.get("centroid_lonlat") or [math.nan, math.nan] for p in props]
    lon = np.array([c[0] for c in centre], np.float64).reshape(-1)
    lat = np.array([c[1] for c in centre], np.float64).reshape(-1)
    length = np.array([p.get("length_m") if p.get("length_m") is not None else math.nan for p in props], np.float64)
    times = line_times(attrs, rows)
    assert times is not None  # ais_options refused a scene without a time
    geometry = look_geometry(attrs, georef, rows, cols) if len(props) else None
    return Detections(lon, lat, times, length.reshape(-1), geometry)


def _record_of(i: int, a: Assignment, info: Mapping[int, VesselInfo], lengths: np.ndarray) -> dict[str, Any] | None:
    j = int(a.vessel[i])
    if j < 0:
        return None
    mmsi = int(a.mmsi[i])
    vi = info.get(mmsi)

    def num(v: float, nd: int) -> float | None:
        return None if not math.isfinite(float(v)) else round(float(v), nd)

    return {
        "mmsi": mmsi,
        "name": vi.name if vi is not None else None,
        "score": num(a.score[i], 4),
        "distance_m": num(a.distance_m[i], 1),
        "dt_s": num(a.dt_s[i], 1),
        "ais_length_m": num(lengths[j], 1),
        "displacement_m": num(a.displacement_m[i], 1),
    }


def _detectable_length_m(min_length_m: float | None, spacing: tuple[float, float] | None) -> float | None:
    """The shortest ship the run counts as detectable: its size rule's ``min_length_m``, else
    :data:`DETECTABLE_MIN_PX` of the larger ground spacing; None where neither is known."""
    if min_length_m is not None:
        return float(min_length_m)
    if spacing is not None:
        return DETECTABLE_MIN_PX * max(spacing)
    return None


def ais_stage(
    opts: AisOptions,
    attrs: Mapping[str, Any],
    geo: Mapping[str, Any],
    shape: tuple[int, int],
    features: list[dict[str, Any]],
    *,
    min_length_m: float | None = None,
    spacing: tuple[float, float] | None = None,
) -> AisOutcome:
    """Match ``features`` (a run's detections) to the AIS of ``opts`` (module doc); sets each
    feature's ``ais`` and ``dark`` properties in place."""
    georef = Georeference(dict(geo))
    H = shape[0]
    t_lines = line_times(attrs, np.array([0.5, H - 0.5]))
    assert t_lines is not None
    t0, t1 = float(np.min(t_lines)), float(np.max(t_lines))
    params = opts.params
    ring = footprint_ring(georef, shape)
    window = _window(ring, t0, t1, params)
    reports, info, stats = read_ais(opts.paths, window)
    states = vessel_states(reports, 0.5 * (t0 + t1), max_extrapolation_s=params.max_extrapolation_s)
    dets = _detections(features, attrs, georef)
    a = match(dets, states, info, params, footprint=ring)
    lengths = vessel_lengths(states, info)
    covered = covers_scene(reports, t0, t1, ring=ring)
    dark = dark_flags(a.vessel, covered)
    for i, f in enumerate(features):
        f["properties"]["ais"] = _record_of(i, a, info, lengths)
        f["properties"]["dark"] = None if dark is None else bool(dark[i])
    shortest = _detectable_length_m(min_length_m, spacing)
    unmatched = [_unmatched_feature(int(j), states, info, lengths, shortest) for j in a.unmatched]
    record = {
        "files": [str(p) for p in opts.paths],
        "read": stats.record(),
        "window": dataclasses.asdict(window),
        "scene_time": [t0, t1],
        "vessels_in_window": int(len(states)),
        "covered": covered,
        "detections": len(features),
        "matched": int(np.sum(a.vessel >= 0)),
        "dark": None if dark is None else int(np.sum(dark)),
        "unmatched_in_footprint": len(unmatched),
        "detectable_length_m": shortest,
        "parameters": dataclasses.asdict(params),
        "pairs": {"scored": a.pairs, "acceptable": a.acceptable, "components": a.components},
    }
    return AisOutcome(unmatched, record)


def _unmatched_feature(
    j: int, states: Any, info: Mapping[int, VesselInfo], lengths: np.ndarray, shortest: float | None
) -> dict[str, Any]:
    mmsi = int(states.mmsi[j])
    vi = info.get(mmsi)
    length = float(lengths[j])
    known = math.isfinite(length)
    detectable = None if (not known or shortest is None) else bool(length >= shortest)
    return {
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": [round(float(states.lon[j]), 7), round(float(states.lat[j]), 7)]},
        "properties": {
            "mmsi": mmsi,
            "name": vi.name if vi is not None else None,
            "length_m": round(length, 1) if known else None,
            "time": float(states.t_ref),
            "gap_s": round(float(states.gap_s[j]), 1),
            "extrapolated": bool(states.extrapolated[j]),
            "detectable": detectable,
        },
    }


__all__ = ["MARGIN_M", "AisOptions", "AisOutcome", "ais_options", "ais_stage"]
