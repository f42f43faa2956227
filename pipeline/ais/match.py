"""Detections matched to AIS vessels: pair scores inside a gate, one global assignment
(docs/ais.md, "Matching").

1. **Candidates.** A KD-tree over the detections (3-D points on the Earth sphere, so distances
   are chords, no projection, no antimeridian) is queried with each vessel's position at
   ``t_ref`` and a radius that bounds every pair the score can accept: ``min(max_distance_m,
   sqrt(d2_gate var_max)) + |v| (dt_max + max R/V)`` (the gate of ``min_score`` for 3 degrees of
   freedom over the vessel's largest variance, plus how far the vessel moves over the scene's
   times and how far it can be displaced). Nothing dense is built: pairs are as many as vessels
   have detections within that radius.
2. **Score** (:mod:`sarship.pipeline.ais.score`, eqs. 1-3) of each candidate pair, against the
   AIS position at the detection's time both **displaced** by ``dx = R v_los / V`` along the
   flight direction (:mod:`sarship.pipeline.ais.displacement`) and **undisplaced**; the better
   hypothesis counts (``displacement_m`` records the one used: 0 for the undisplaced one, NaN
   where the detection has no look geometry: then only the undisplaced position, its variance
   grown by the unknown displacement's). A pair is acceptable when ``score >= min_score`` and its
   distance is at most ``max_distance_m``.
3. **Assignment.** One global assignment over the acceptable pairs, maximising ``sum (ln score
   - ln min_score)`` (leaving a detection or vessel unmatched costs nothing, an acceptable pair
   gains a non-negative amount), solved per connected component of the pair graph: a component
   with one detection or one vessel takes its best pair; others by
   ``scipy.optimize.linear_sum_assignment`` [crouse2016] [kuhn1955] on the component's dense
   matrix (absent pairs at zero gain), or, over ``max_dense_cells`` cells, by the sparse
   ``scipy.sparse.csgraph.min_weight_full_bipartite_matching`` [jonker1987] with an "unmatched" dummy for
   every detection and vessel (the same optimum, memory in the pairs).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from sarship.pipeline.ais import score as S
from sarship.pipeline.ais.coverage import inside
from sarship.pipeline.ais.displacement import LookGeometry, azimuth_shift_m
from sarship.pipeline.ais.reports import KNOT_M_S, VesselInfo, VesselStates
from sarship.pipeline.ais.tracks import EARTH_RADIUS_M, M_PER_DEG, VesselTracks, positions_at
from sarship.pipeline.errors import InputError


@dataclass(frozen=True)
class MatchParams:
    """The matcher's parameters (docs/ais.md, "Matching"); every limit has a safe default.

    ``sigma_geo_m``, ``sigma_rate_m_s``, ``sigma_turn_deg_s``, ``length_sigma_log`` and
    ``max_distance_m`` were chosen on half A of the OpenSARShip GRD chips of ../shared and
    reported on half B (bench/realdata_ais.py, bench/REALDATA.md "AIS matching on OpenSARShip"):
    every chip of A matched, then the best calibrated (own-ship scores closest to uniform).

    - ``sigma_geo_m`` (100): the detection's position error, 1-sigma per axis: the scene's
      georeferencing, the detection's centroid and the AIS GNSS fix (ships at rest on the
      OpenSARShip chips: 51-281 m from their AIS report, a product's bias up to ~250 m);
      Sentinel-1's own absolute geolocation is ~10 m;
    - ``sigma_rate_m_s`` (0.25): growth of the AIS position error per second from the nearest
      report (0.25 m/s is 45 m after 3 minutes);
    - ``sigma_turn_deg_s`` (0): an unknown turn rate since the nearest report (deg/s): the error
      ``|v| sigma_turn gap^2 / 2`` grows with the square of the gap and with the speed (eq. 1 of
      :mod:`~sarship.pipeline.ais.score`). Off: the ships of half A under way 166-222 s from their
      report lie 41-93 m from it, moved and displaced, and any turn term made their scores less
      calibrated; set it for sparse (satellite) AIS in manoeuvring waters;
    - ``sigma_sog_kn`` (0.5), ``sigma_cog_deg`` (3): SOG and COG errors, the displacement's own
      uncertainty (eq. 1 of :mod:`~sarship.pipeline.ais.score`);
    - ``length_sigma_log`` (0.6): sigma of ``ln(L_det / L_ais)`` (SAR length estimates of ships
      are off by tens of percent, and a 10 m detection of a 70-100 m ship can be 2.6 times too
      long: a ratio of 1.8 is one sigma);
    - ``min_score`` (0.01): a pair is matched when its score is at least this: the fraction of
      true pairs refused;
    - ``max_distance_m`` (2000): no pair farther apart (after the displacement) whatever the
      uncertainty;
    - ``max_extrapolation_s`` (600): for :func:`~sarship.pipeline.ais.tracks.vessel_states`;
    - ``unknown_range_over_velocity_s`` (115): ``R/V`` for the displacement's variance where a
      detection has no look geometry (Sentinel-1 IW: 800-950 km / 7.6 km/s);
    - ``max_dense_cells`` (4 000 000): the largest component solved on a dense matrix (32 MB);
      larger ones by the sparse solver.
    """

    sigma_geo_m: float = 100.0
    sigma_rate_m_s: float = 0.25
    sigma_turn_deg_s: float = 0.0
    sigma_sog_kn: float = 0.5
    sigma_cog_deg: float = 3.0
    length_sigma_log: float = 0.6
    min_score: float = 0.01
    max_distance_m: float = 2000.0
    max_extrapolation_s: float = 600.0
    unknown_range_over_velocity_s: float = 115.0
    max_dense_cells: int = 4_000_000

    def __post_init__(self) -> None:
        for name in (
            "sigma_geo_m",
            "length_sigma_log",
            "max_distance_m",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"MatchParams.{name} must be a finite number > 0, got {v!r}")
        for name in ("sigma_rate_m_s", "sigma_turn_deg_s", "sigma_sog_kn", "sigma_cog_deg", "max_extrapolation_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"MatchParams.{name} must be a finite number >= 0, got {v!r}")
        if not (0.0 < self.min_score < 1.0):
            raise InputError(f"MatchParams.min_score must lie in (0, 1), got {self.min_score!r}")
        if not (np.isfinite(self.unknown_range_over_velocity_s) and self.unknown_range_over_velocity_s >= 0):
            raise InputError(
                f"MatchParams.unknown_range_over_velocity_s must be >= 0, got {self.unknown_range_over_velocity_s!r}"
            )
        if int(self.max_dense_cells) < 1:
            raise InputError(f"MatchParams.max_dense_cells must be >= 1, got {self.max_dense_cells!r}")


@dataclass
class Detections:
    """What the matcher needs of the detections: ``lon``, ``lat`` (WGS84 degrees), ``time``
    (POSIX s, :func:`~sarship.pipeline.ais.scene_time.line_times`), ``length_m`` (NaN unknown),
    the :class:`~sarship.pipeline.ais.displacement.LookGeometry` (None where the scene has none;
    NaN rows: none for that detection) and ``time_sigma_s`` (how well the time is known; None:
    exactly, as line times are)."""

    lon: np.ndarray
    lat: np.ndarray
    time: np.ndarray
    length_m: np.ndarray | None = None
    geometry: LookGeometry | None = None
    time_sigma_s: np.ndarray | None = None

    def __len__(self) -> int:
        return int(np.asarray(self.lon).size)


@dataclass
class Assignment:
    """The matcher's result. Per detection: ``vessel`` (row of the vessel states, -1 none),
    ``mmsi`` (-1 none), ``score``, ``distance_m`` (to the AIS position used), ``dt_s`` (detection
    time minus the nearest report of the two around ``t_ref``), ``displacement_m`` (the azimuth
    displacement applied: 0 undisplaced, NaN without look geometry), NaN where unmatched. Per
    vessel: ``detection`` (-1 none). ``unmatched``: rows of vessels matched to nothing whose
    position at ``t_ref`` lies inside the footprint (all unmatched rows without one).
    ``pairs``: candidate pairs scored; ``acceptable``: pairs at or above ``min_score``;
    ``components``: connected components of the acceptable pairs."""

    vessel: np.ndarray
    mmsi: np.ndarray
    score: np.ndarray
    distance_m: np.ndarray
    dt_s: np.ndarray
    displacement_m: np.ndarray
    detection: np.ndarray
    unmatched: np.ndarray
    pairs: int
    acceptable: int
    components: int


def vessel_lengths(states: VesselStates, info: Mapping[int, VesselInfo]) -> np.ndarray:
    """Each vessel's length (m) from its :class:`VesselInfo`, NaN where unknown."""
    out = np.full(len(states), np.nan)
    if info:
        for k, m in enumerate(states.mmsi.tolist()):  # a dict look-up per vessel: no numpy form
            vi = info.get(m)
            if vi is not None and vi.length_m is not None and vi.length_m > 0:
                out[k] = float(vi.length_m)
    return out


def _xyz(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    lo, la = np.radians(lon), np.radians(lat)
    c = np.cos(la)
    return EARTH_RADIUS_M * np.stack([c * np.cos(lo), c * np.sin(lo), np.sin(la)], -1)


def _check_detections(det: Detections) -> int:
    n = len(det)
    for name in ("lat", "time"):
        if np.asarray(getattr(det, name)).size != n:
            raise InputError(f"detections: {name} has {np.asarray(getattr(det, name)).size} values for {n} detections")
    bad = ~(np.isfinite(det.lon) & np.isfinite(det.lat))
    if bad.any():
        raise InputError(
            f"{int(bad.sum())} of {n} detections have no position (lon/lat): match georeferenced detections only"
        )
    if not np.all(np.isfinite(det.time)):
        raise InputError("detections without a time: the scene has no acquisition or line time, AIS cannot be matched")
    if det.geometry is not None and len(det.geometry) != n:
        raise InputError(f"detections: the look geometry has {len(det.geometry)} rows for {n} detections")
    return n


def _candidates(
    det: Detections, states: VesselStates, L_ais: np.ndarray, p: MatchParams
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs ``(i, j)``: a superset of every pair the score can accept (module doc, 1)."""
    from scipy.spatial import cKDTree

    t = np.asarray(det.time, np.float64)
    dt_max = float(np.max(np.abs(t - states.t_ref)))
    geo_ok = det.geometry.valid() if det.geometry is not None else np.zeros(len(det), bool)
    rv = (
        np.asarray(det.geometry.slant_range_m)[geo_ok] / np.asarray(det.geometry.platform_velocity_m_s)[geo_ok]
        if geo_ok.any()
        else np.zeros(0)
    )
    rv_max = max(float(rv.max()) if rv.size else 0.0, p.unknown_range_over_velocity_s if not geo_ok.all() else 0.0)
    speed = np.nan_to_num(np.hypot(states.v_east_m_s, states.v_north_m_s))
    L_det = np.asarray(det.length_m, np.float64) if det.length_m is not None else np.zeros(0)
    L_det_max = float(np.nanmax(L_det)) if L_det.size and np.isfinite(L_det).any() else 0.0
    L_max = np.fmax(np.nan_to_num(L_ais), L_det_max)
    sig_t = float(np.max(det.time_sigma_s)) if det.time_sigma_s is not None and len(det) else 0.0
    var = (
        p.sigma_geo_m**2
        + (p.sigma_rate_m_s * (states.gap_s + dt_max)) ** 2
        + S.manoeuvre_sigma_m(speed, states.gap_s + dt_max, np.radians(p.sigma_turn_deg_s)) ** 2
        + (S.REF_POINT_FRACTION * L_max) ** 2
        + speed**2 * (sig_t**2 + 0.5 * p.unknown_range_over_velocity_s**2 * (not geo_ok.all()))
        + rv_max**2 * ((p.sigma_sog_kn * KNOT_M_S) ** 2 + (speed * np.radians(p.sigma_cog_deg)) ** 2)
    )
    gate = np.minimum(p.max_distance_m, np.sqrt(S.chi2_isf(p.min_score, 3) * var))
    radius = gate + speed * (dt_max + rv_max) + 1.0
    tree = cKDTree(_xyz(det.lon, det.lat))
    hits = tree.query_ball_point(_xyz(states.lon, states.lat), radius, workers=2, return_sorted=False)
    counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
    j = np.repeat(np.arange(len(states)), counts)
    i = np.concatenate([np.asarray(h, np.int64) for h in hits]) if counts.sum() else np.zeros(0, np.int64)
    return i, j


def _nearest_report(states: VesselStates, j: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dt_s, gap_s)`` per pair: detection time minus the nearest of the reports around
    ``t_ref`` (:class:`VesselTracks`); for plain states, dt unknown (NaN) and the gap bounded by
    ``gap_s + |t - t_ref|``."""
    if isinstance(states, VesselTracks):
        db, da = t - states.t_before[j], t - states.t_after[j]
        dt = np.where(np.isnan(da) | (np.abs(db) <= np.abs(da)), db, da)
        return dt, np.abs(dt)
    return np.full(t.shape, np.nan), states.gap_s[j] + np.abs(t - states.t_ref)


def _score_pairs(
    det: Detections, states: VesselStates, L_ais: np.ndarray, i: np.ndarray, j: np.ndarray, p: MatchParams
) -> dict[str, np.ndarray]:
    """Score, distance and displacement of each pair under its better hypothesis (module doc, 2)."""
    t = np.asarray(det.time, np.float64)[i]
    lon, lat = positions_at(states, t, j)
    dlat, dlon = np.asarray(det.lat)[i], np.asarray(det.lon)[i]
    coslat = np.cos(np.radians(dlat))
    re = ((lon - dlon + 180.0) % 360.0 - 180.0) * coslat * M_PER_DEG  # detection -> AIS, metres
    rn = (lat - dlat) * M_PER_DEG
    ve, vn = np.nan_to_num(states.v_east_m_s[j]), np.nan_to_num(states.v_north_m_s[j])
    speed = np.hypot(ve, vn)
    dt, gap = _nearest_report(states, j, t)
    L_det = np.asarray(det.length_m, np.float64)[i] if det.length_m is not None else np.full(i.shape, np.nan)
    L = np.where(np.isfinite(L_ais[j]), L_ais[j], L_det)
    a = (
        p.sigma_geo_m**2
        + (p.sigma_rate_m_s * gap) ** 2
        + S.manoeuvre_sigma_m(speed, gap, np.radians(p.sigma_turn_deg_s)) ** 2
        + (S.REF_POINT_FRACTION * np.nan_to_num(L)) ** 2
    )
    if det.time_sigma_s is not None:
        a = a + (speed * np.asarray(det.time_sigma_s, np.float64)[i]) ** 2
    z2 = S.length_z2(L_det, L_ais[j], p.length_sigma_log)
    k = np.where(np.isnan(z2), 2, 3)
    z2 = np.nan_to_num(z2)
    if det.geometry is not None:
        g = det.geometry.take(i)
        ok = g.valid()
    else:
        ok = np.zeros(i.shape, bool)
    a = np.where(ok, a, a + 0.5 * (speed * p.unknown_range_over_velocity_s) ** 2)
    zero = np.zeros(i.shape)
    d2_u = S.mahalanobis2(re, rn, a, zero, zero, zero) + z2
    score_u = np.where(np.hypot(re, rn) <= p.max_distance_m, S.chi2_sf(d2_u, k), 0.0)
    out = {"score": score_u, "distance_m": np.hypot(re, rn), "displacement_m": np.where(ok, 0.0, np.nan), "dt_s": dt}
    if ok.any():
        dx = np.where(
            ok,
            azimuth_shift_m(
                ve, vn, g.range_east, g.range_north, g.slant_range_m, g.platform_velocity_m_s, g.sin_incidence
            ),
            0.0,
        )
        fe, fn = np.nan_to_num(g.flight_east), np.nan_to_num(g.flight_north)
        de, dn = re + dx * fe, rn + dx * fn
        rv = np.where(ok, g.slant_range_m / g.platform_velocity_m_s, 0.0)
        var_los = S.los_velocity_variance(
            ve, vn, np.nan_to_num(g.range_east), np.nan_to_num(g.range_north), np.nan_to_num(g.sin_incidence),
            p.sigma_sog_kn * KNOT_M_S, np.radians(p.sigma_cog_deg),
        )  # fmt: skip
        b = rv**2 * var_los
        dist_d = np.hypot(de, dn)
        score_d = np.where(
            ok & (dist_d <= p.max_distance_m), S.chi2_sf(S.mahalanobis2(de, dn, a, b, fe, fn) + z2, k), 0.0
        )
        better = score_d >= score_u
        out["score"] = np.where(better, score_d, score_u)
        out["distance_m"] = np.where(better, dist_d, out["distance_m"])
        out["displacement_m"] = np.where(better & ok, dx, out["displacement_m"])
    return out


def _best_per_component(label: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Index of the highest-gain pair of each component present in ``label``."""
    order = np.lexsort((-gain, label))
    first = np.ones(order.size, bool)
    first[1:] = label[order][1:] != label[order][:-1]
    return order[first]


def _solve_dense(di: np.ndarray, vj: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Pairs (indices into the arrays) chosen by ``linear_sum_assignment`` on the component's
    dense matrix (absent pairs at zero gain, dropped after)."""
    from scipy.optimize import linear_sum_assignment

    ur, ri = np.unique(di, return_inverse=True)
    uc, ci = np.unique(vj, return_inverse=True)
    cost = np.zeros((ur.size, uc.size))
    pair = np.full((ur.size, uc.size), -1, np.int64)
    cost[ri, ci] = -gain
    pair[ri, ci] = np.arange(gain.size)
    rr, cc = linear_sum_assignment(cost)
    chosen = pair[rr, cc]
    return chosen[chosen >= 0]


def _solve_sparse(di: np.ndarray, vj: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """The same optimum as :func:`_solve_dense` from the pairs alone: a full matching over the
    detections plus one "unmatched" dummy per vessel, and the vessels plus one dummy per
    detection (``min_weight_full_bipartite_matching``; every edge weighs ``G - gain`` or ``G``,
    ``G > max gain``, so the weights are positive and a full matching's weight is ``(n + m) G -
    sum gain``)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import min_weight_full_bipartite_matching

    ur, ri = np.unique(di, return_inverse=True)
    uc, ci = np.unique(vj, return_inverse=True)
    n, m, e = ur.size, uc.size, gain.size
    G = float(gain.max()) + 1.0
    rows = np.concatenate([ri, np.arange(n), n + np.arange(m), n + ci])
    cols = np.concatenate([ci, m + np.arange(n), np.arange(m), m + ri])
    w = np.concatenate([G - gain, np.full(n + m + e, G)])
    graph = csr_matrix((w, (rows, cols)), shape=(n + m, m + n))
    r, c = min_weight_full_bipartite_matching(graph)
    real = (r < n) & (c < m)
    index = csr_matrix((np.arange(1, e + 1, dtype=np.float64), (ri, ci)), shape=(n, m))
    return np.asarray(index[r[real], c[real]]).ravel().astype(np.int64) - 1


def assign(
    i: np.ndarray, j: np.ndarray, gain: np.ndarray, *, max_dense_cells: int = 4_000_000
) -> tuple[np.ndarray, int]:
    """The matching of maximum total ``gain`` (all ``>= 0``) over the pairs ``(i[k], j[k])``,
    each detection and vessel at most once (module doc, 3).

    Parameters
    ----------
    i, j : np.ndarray
        Detection and vessel indices of the acceptable pairs (each pair at most once).
    gain : np.ndarray
        ``ln(score / min_score) >= 0`` per pair.
    max_dense_cells : int, default 4 000 000
        Components with more detection x vessel cells use the sparse solver.

    Returns
    -------
    tuple
        ``(chosen, components)``: indices into the pairs, and the number of connected components.

    References
    ----------
    [kuhn1955], [crouse2016], [jonker1987].
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if gain.size == 0:
        return np.zeros(0, np.int64), 0
    gain = np.asarray(gain, np.float64) + 1e-12  # a pair at exactly min_score still beats none
    ui, ii = np.unique(i, return_inverse=True)
    uj, jj = np.unique(j, return_inverse=True)
    nd, nv = ui.size, uj.size
    graph = coo_matrix((np.ones(gain.size), (ii, nd + jj)), shape=(nd + nv, nd + nv))
    ncomp, node_label = connected_components(graph, directed=False)
    label = node_label[ii]
    n_det = np.bincount(node_label[:nd], minlength=ncomp)
    n_ves = np.bincount(node_label[nd:], minlength=ncomp)
    star = (n_det == 1) | (n_ves == 1)
    in_star = star[label]
    chosen = [_best_per_component(label[in_star], gain[in_star])]
    chosen[0] = np.flatnonzero(in_star)[chosen[0]]
    rest = np.flatnonzero(~in_star)
    if rest.size:
        rest = rest[np.argsort(label[rest], kind="stable")]
        bounds = np.flatnonzero(np.diff(label[rest])) + 1
        for grp in np.split(rest, bounds):
            c = label[grp[0]]
            solve = _solve_dense if n_det[c] * n_ves[c] <= max_dense_cells else _solve_sparse
            chosen.append(grp[solve(i[grp], j[grp], gain[grp])])
    return np.concatenate(chosen), int(ncomp)


def match(
    detections: Detections,
    vessels: VesselStates,
    info: Mapping[int, VesselInfo] | None = None,
    params: MatchParams | None = None,
    *,
    footprint: np.ndarray | None = None,
) -> Assignment:
    """Match detections to AIS vessels (module doc): candidates, scores, one global assignment.

    Parameters
    ----------
    detections : Detections
        Positions, times, lengths and look geometry of the detections.
    vessels : VesselStates
        The vessels at ``t_ref`` (:func:`~sarship.pipeline.ais.tracks.vessel_states`; a
        :class:`~sarship.pipeline.ais.tracks.VesselTracks` also gives ``dt_s``).
    info : mapping of MMSI to VesselInfo, optional
        Static data: the lengths for the length term.
    params : MatchParams, optional
        Defaults when None.
    footprint : np.ndarray, optional
        The scene's outline (:func:`~sarship.pipeline.ais.coverage.footprint_ring`): the
        unmatched vessels reported are those inside it.

    Returns
    -------
    Assignment

    Raises
    ------
    InputError
        Detections without a position or a time, or inconsistent array lengths.

    References
    ----------
    [raney1971], [barshalom2001], [kuhn1955], [crouse2016].
    """
    p = params or MatchParams()
    nd, nv = _check_detections(detections), len(vessels)
    L_ais = vessel_lengths(vessels, info or {})
    i, j = _candidates(detections, vessels, L_ais, p) if nd and nv else (np.zeros(0, np.int64),) * 2
    fields = ("score", "distance_m", "dt_s", "displacement_m")
    sc = _score_pairs(detections, vessels, L_ais, i, j, p) if i.size else {f: np.zeros(0) for f in fields}
    ok = sc["score"] >= p.min_score
    gain = np.log(sc["score"][ok] / p.min_score)
    chosen, ncomp = assign(i[ok], j[ok], gain, max_dense_cells=p.max_dense_cells)
    k = np.flatnonzero(ok)[chosen]
    vessel, detection = np.full(nd, -1, np.int64), np.full(nv, -1, np.int64)
    vessel[i[k]], detection[j[k]] = j[k], i[k]
    out = {f: np.full(nd, np.nan) for f in fields}
    for f, arr in out.items():
        arr[i[k]] = sc[f][k]
    mmsi = np.where(vessel >= 0, vessels.mmsi[np.maximum(vessel, 0)] if nv else -1, -1)
    free = np.flatnonzero(detection < 0)
    if footprint is not None and free.size:
        free = free[inside(vessels.lon[free], vessels.lat[free], footprint)]
    return Assignment(
        vessel,
        mmsi,
        detection=detection,
        unmatched=free,
        pairs=int(i.size),
        acceptable=int(ok.sum()),
        components=ncomp,
        **out,
    )


__all__ = ["Assignment", "Detections", "MatchParams", "assign", "match", "vessel_lengths"]
