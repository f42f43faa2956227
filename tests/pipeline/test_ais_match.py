"""AIS matching (pipeline/ais/match.py, score.py, coverage.py) against a synthetic world.

**The world** (made here, not by the code under test: no image simulation). A stripmap-like
scene (descending, right-looking, 170 km x 250 km, slant range 800-950 km, V 7590 m/s, 25 s)
over 1500 AIS ships and 200 dark ones, an anchorage (60 ships at rest, 400-3000 m apart, a tenth
of them dark), a traffic lane (60 ships 1-2 km apart at 12-20 kn, both ways) and 400 AIS vessels
outside the footprint. Ships sail 0-25 kn on constant-turn arcs; AIS reports at the ITU-R
M.1371 intervals (class A 2-10 s by speed, 3 min at anchor; class B 30 s), 10 m GNSS noise, the
antenna anywhere along the hull, SOG/COG noise (0.1 kn, 2 deg), outages of up to 3 min around the
scene for a third of the ships; class B lengths half unknown. Each ship is imaged at its
zero-Doppler time, displaced along the flight by ``R v_los / V`` (v_los the ground-range velocity
times sin(incidence) from the scene's own flat-Earth geometry), with a 30 m georeferencing error
and a log-normal (sigma 0.25) length error; ships under 20 m are missed half the time.

Checked: the issue's targets with a fixed seed (AIS precision >= 0.98, recall >= 0.95 on
detected AIS ships, dark recall >= 0.95, at most 2 % of reporting ships called dark), with and
without the look geometry; the displacement applied matches the world's; the unmatched vessels
are the AIS ships inside the footprint that were not detected; the score is calibrated (true
pairs drawn from the stated error model: the fraction below alpha is alpha); the assignment
equals brute force on small problems (dense and sparse solvers) and beats a greedy one where
they differ; the coverage rule, the footprint test and one-line errors.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pytest

from sarship.pipeline.ais.coverage import covers_scene, dark_flags, footprint_ring, inside
from sarship.pipeline.ais.displacement import LookGeometry
from sarship.pipeline.ais.match import Detections, MatchParams, assign, match
from sarship.pipeline.ais.reports import Reports, VesselInfo, VesselStates
from sarship.pipeline.ais.tracks import vessel_states
from sarship.pipeline.errors import InputError

K = 6_371_008.8 * np.pi / 180.0
KN = 1852.0 / 3600.0

# --------------------------------------------------------------------------------------
# the synthetic world
# --------------------------------------------------------------------------------------


@dataclass
class Scene:
    lon0: float = 3.0
    lat0: float = 54.0
    heading_deg: float = 193.0  # descending; right-looking: range towards heading + 90
    along_m: float = 170_000.0
    across_m: float = 250_000.0
    height_m: float = 693_000.0
    near_ground_m: float = 400_000.0  # the near edge's ground distance from nadir
    V: float = 7590.0
    t_first: float = 1_700_000_000.0
    duration_s: float = 25.0

    def unit(self, deg: float) -> np.ndarray:
        return np.array([np.sin(np.radians(deg)), np.cos(np.radians(deg))])

    @property
    def uf(self) -> np.ndarray:
        return self.unit(self.heading_deg)

    @property
    def ur(self) -> np.ndarray:
        return self.unit(self.heading_deg + 90.0)

    def to_lonlat(self, e, n):
        return self.lon0 + np.asarray(e) / (K * np.cos(np.radians(self.lat0))), self.lat0 + np.asarray(n) / K

    def en(self, a, x):
        """East/north of along/across metres about the scene centre."""
        return a * self.uf[0] + x * self.ur[0], a * self.uf[1] + x * self.ur[1]

    def ax(self, e, n):
        """Along (from the first line) and across (from the near edge) metres."""
        return e * self.uf[0] + n * self.uf[1] + self.along_m / 2, e * self.ur[0] + n * self.ur[1] + self.across_m / 2

    def slant(self, x):
        g = self.near_ground_m + np.asarray(x)
        R = np.hypot(self.height_m, g)
        return R, g / R

    def ring(self) -> np.ndarray:
        a = np.array([0, 1, 1, 0, 0]) * self.along_m - self.along_m / 2
        x = np.array([0, 0, 1, 1, 0]) * self.across_m - self.across_m / 2
        return np.stack(self.to_lonlat(*self.en(a, x)), -1)


def _arc(e0, n0, speed, psi0, omega, tau):
    """Position and heading after ``tau`` s on a constant-turn arc (heading clockwise from north)."""
    om = np.where(np.abs(omega) < 1e-9, 1e-9, omega)
    psi = psi0 + om * tau
    return e0 + speed / om * (np.cos(psi0) - np.cos(psi)), n0 + speed / om * (np.sin(psi) - np.sin(psi0)), psi


def _fleet(rng, sc: Scene, n_ais=1500, n_dark=200, n_outside=400, n_anchorage=60, n_lane=60):
    """Ships at the scene's middle time: (e, n, speed, heading, turn, length, has_ais, class_b)."""
    k_in = n_ais + n_dark
    a = rng.uniform(-sc.along_m / 2, sc.along_m / 2, k_in + n_outside)
    x = rng.uniform(-sc.across_m / 2, sc.across_m / 2, k_in + n_outside)
    side = rng.random(n_outside) < 0.5  # outside: a band 2-30 km around the footprint
    out_a, out_x = a[k_in:], x[k_in:]
    a[k_in:] = np.where(side, np.sign(out_a) * (sc.along_m / 2 + rng.uniform(2e3, 3e4, n_outside)), out_a)
    x[k_in:] = np.where(~side, np.sign(out_x) * (sc.across_m / 2 + rng.uniform(2e3, 3e4, n_outside)), out_x)
    e, n = sc.en(a, x)
    # the anchorage: a spiral of ships 400 m apart; the lane: ships 1-2 km apart along 60 deg
    q = np.arange(n_anchorage)
    ea, na = 20e3 + 400 * np.sqrt(q + 0.5) * np.cos(2.4 * q), -15e3 + 400 * np.sqrt(q + 0.5) * np.sin(2.4 * q)
    s_lane = np.cumsum(rng.uniform(1e3, 2e3, n_lane)) - 45e3
    el, nl = -30e3 + s_lane * np.sin(np.radians(60)), 10e3 + s_lane * np.cos(np.radians(60))
    e, n = np.concatenate([e, ea, el]), np.concatenate([n, na, nl])
    k = e.size
    at_rest = rng.random(k) < 0.2
    at_rest[k_in + n_outside : k - n_lane] = True
    at_rest[k - n_lane :] = False
    speed = np.where(at_rest, rng.uniform(0, 0.3, k), rng.uniform(2, 25, k)) * KN
    heading = rng.uniform(0, 2 * np.pi, k)
    speed[k - n_lane :] = rng.uniform(12, 20, n_lane) * KN
    heading[k - n_lane :] = np.radians(60 + 180 * (rng.random(n_lane) < 0.5))
    turn = np.where(at_rest, 0.0, rng.normal(0, np.radians(0.05), k))
    length = np.exp(rng.uniform(np.log(12), np.log(350), k))
    has_ais = np.ones(k, bool)
    has_ais[n_ais:k_in] = False
    has_ais[k_in + n_outside + rng.choice(n_anchorage, n_anchorage // 10, replace=False)] = False
    class_b = (rng.random(k) < 0.2) & ~at_rest
    return e, n, speed, heading, turn, length, has_ais, class_b


def _ais(rng, sc: Scene, fleet, t_mid: float, span_s: float = 900.0):
    e, n, speed, heading, turn, length, has_ais, class_b = fleet
    mmsi = np.arange(e.size, dtype=np.int64) + 211_000_000
    cols: list[list[np.ndarray]] = [[] for _ in range(6)]
    info: dict[int, VesselInfo] = {}
    for s in np.flatnonzero(has_ais):
        kn = speed[s] / KN
        dt = 180.0 if kn < 0.5 else 30.0 if class_b[s] else 10.0 if kn < 14 else 6.0 if kn < 23 else 2.0
        t = np.arange(t_mid - span_s + rng.uniform(0, dt), t_mid + span_s, dt)
        if rng.random() < 0.35:  # an outage of up to 3 minutes around the scene
            g = rng.uniform(0, 180.0)
            g0 = t_mid - rng.uniform(0, g) + rng.uniform(-15, 15)
            t = t[(t < g0) | (t > g0 + g)]
        pe, pn, psi = _arc(e[s], n[s], speed[s], heading[s], turn[s], t - t_mid)
        off = rng.uniform(-0.5, 0.5) * length[s]  # the antenna somewhere along the hull
        pe = pe + off * np.sin(psi) + rng.normal(0, 10.0, t.size)
        pn = pn + off * np.cos(psi) + rng.normal(0, 10.0, t.size)
        sog, cog = kn + rng.normal(0, 0.1, t.size), np.degrees(psi) + rng.normal(0, 2.0, t.size)
        if kn < 0.5:  # at anchor: SOG a few tenths, COG anything
            sog, cog = np.abs(rng.normal(0.1, 0.1, t.size)), rng.uniform(0, 360, t.size)
        for c, v in zip(cols, (np.full(t.size, mmsi[s]), t, *sc.to_lonlat(pe, pn), np.clip(sog, 0, None), cog % 360)):
            c.append(v)
        known = not (class_b[s] and rng.random() < 0.5)
        info[int(mmsi[s])] = VesselInfo(int(mmsi[s]), length_m=float(round(length[s])) if known else None)
    m, t, lon, lat, sog, cog = (np.concatenate(c) for c in cols)
    f = np.float32
    return Reports(m, t, lon, lat, sog.astype(f), cog.astype(f), np.full(m.size, np.nan, f)).sorted(), info, mmsi


@dataclass
class World:
    scene: Scene
    reports: Reports
    info: dict[int, VesselInfo]
    truth: np.ndarray  # per detection: the ship's MMSI, -1 dark
    detections: Detections
    true_dx: np.ndarray
    missed_in_footprint: set[int]  # MMSIs of AIS ships inside the footprint that were not detected


def make_world(seed: int = 33, **fleet_kw) -> World:
    rng = np.random.default_rng(seed)
    sc = Scene()
    t_mid = sc.t_first + sc.duration_s / 2
    fleet = _fleet(rng, sc, **fleet_kw)
    reports, info, mmsi = _ais(rng, sc, fleet, t_mid)
    e, n, speed, heading, turn, length, has_ais, _ = fleet
    vg = sc.along_m / sc.duration_s
    t = np.full(e.size, t_mid)
    for _ in range(3):  # each ship's zero-Doppler time: when the sensor's line passes it
        pe, pn, psi = _arc(e, n, speed, heading, turn, t - t_mid)
        t = sc.t_first + sc.ax(pe, pn)[0] / vg
    pe, pn, psi = _arc(e, n, speed, heading, turn, t - t_mid)
    a, x = sc.ax(pe, pn)
    in_fp = (a >= 0) & (a <= sc.along_m) & (x >= 0) & (x <= sc.across_m)
    seen = in_fp & ((length >= 20) | (rng.random(e.size) < 0.5))
    idx = np.flatnonzero(seen)
    R, sin_i = sc.slant(x[idx])
    ve, vn = speed[idx] * np.sin(psi[idx]), speed[idx] * np.cos(psi[idx])
    dx = R * (-(ve * sc.ur[0] + vn * sc.ur[1]) * sin_i) / sc.V  # towards the radar: ahead
    de = pe[idx] + dx * sc.uf[0] + rng.normal(0, 30.0, idx.size)
    dn = pn[idx] + dx * sc.uf[1] + rng.normal(0, 30.0, idx.size)
    one = np.ones(idx.size)
    geo = LookGeometry(sc.uf[0] * one, sc.uf[1] * one, sc.ur[0] * one, sc.ur[1] * one, R, sc.V * one, sin_i)
    det = Detections(*sc.to_lonlat(de, dn), t[idx], length[idx] * np.exp(rng.normal(0, 0.25, idx.size)), geo)
    missed = set(mmsi[in_fp & ~seen & has_ais].tolist())
    return World(sc, reports, info, np.where(has_ais[idx], mmsi[idx], -1), det, dx, missed)


def _scores(w: World, a) -> dict[str, float]:
    ais, matched = w.truth >= 0, a.vessel >= 0
    right = matched & (a.mmsi == w.truth)
    return {
        "precision": right.sum() / max(matched.sum(), 1),
        "recall": right[ais].sum() / ais.sum(),
        "dark_recall": (~matched[~ais]).sum() / (~ais).sum(),
        "reporting_called_dark": (~matched[ais]).sum() / ais.sum(),
    }


@pytest.fixture(scope="module")
def world() -> World:
    return make_world()


@pytest.fixture(scope="module")
def states(world):
    return vessel_states(world.reports, world.scene.t_first + world.scene.duration_s / 2)


# --------------------------------------------------------------------------------------
# the targets
# --------------------------------------------------------------------------------------


def test_targets_on_the_synthetic_world(world, states):
    a = match(world.detections, states, world.info, MatchParams(), footprint=world.scene.ring())
    s = _scores(world, a)
    assert (world.truth >= 0).sum() > 1400 and (world.truth < 0).sum() > 150  # the world is as described
    assert s["precision"] >= 0.98 and s["recall"] >= 0.95, s
    assert s["dark_recall"] >= 0.95 and s["reporting_called_dark"] <= 0.02, s
    assert np.all(dark_flags(a.vessel, True) == (a.vessel < 0))
    # the displacement used is the world's, where it matters (fast ships across the line of sight)
    ok = (a.vessel >= 0) & (a.mmsi == world.truth) & (np.abs(world.true_dx) > 300)
    assert ok.sum() > 200
    err = a.displacement_m[ok] - world.true_dx[ok]
    assert np.median(np.abs(err)) < 25.0 and np.abs(err).max() < 250.0, err
    # dt_s: detection time minus the nearest report, within the world's 3 minute outages
    assert np.nanmax(np.abs(a.dt_s)) <= 180.0 + 13.0 and np.isfinite(a.dt_s[a.vessel >= 0]).all()
    # unmatched vessels in the footprint: those the scene missed (none of the detected ones)
    unmatched = set(states.mmsi[a.unmatched].tolist())
    assert len(unmatched & set(world.truth.tolist())) <= 0.02 * (world.truth >= 0).sum()
    assert len(unmatched & world.missed_in_footprint) >= 0.95 * len(world.missed_in_footprint)
    # a vessel matched at most once, and every pair in the candidate set
    assert np.unique(a.vessel[a.vessel >= 0]).size == (a.vessel >= 0).sum()
    assert np.all(a.detection[a.vessel[a.vessel >= 0]] == np.flatnonzero(a.vessel >= 0))


def test_targets_without_look_geometry(world, states):
    det = Detections(world.detections.lon, world.detections.lat, world.detections.time, world.detections.length_m)
    a = match(det, states, world.info)
    s = _scores(world, a)
    assert s["precision"] >= 0.98 and s["recall"] >= 0.95, s
    assert s["dark_recall"] >= 0.95 and s["reporting_called_dark"] <= 0.02, s
    assert np.isnan(a.displacement_m).all()


def test_the_displacement_sign_matters(world, states):
    g = world.detections.geometry
    wrong = LookGeometry(
        -g.flight_east,
        -g.flight_north,
        g.range_east,
        g.range_north,
        g.slant_range_m,
        g.platform_velocity_m_s,
        g.sin_incidence,
    )
    det = Detections(
        world.detections.lon, world.detections.lat, world.detections.time, world.detections.length_m, wrong
    )
    s = _scores(world, match(det, states, world.info))
    assert s["recall"] < 0.9, s  # the undisplaced hypothesis alone cannot rescue fast ships


# --------------------------------------------------------------------------------------
# the score's meaning
# --------------------------------------------------------------------------------------


def _calibration_pairs(rng, n: int, p: MatchParams):
    """``n`` isolated true pairs whose errors are drawn from the score's stated model (score.py
    eq. 1): an isotropic position error, the velocity's SOG error along the course and COG error
    across it (hence the displacement's), the log-length error; displacements of 0.7-1.5 km so
    the undisplaced hypothesis never competes."""
    lat = np.repeat(np.linspace(-60, 60, n // 100 + 1), 100)[:n]
    lon = np.tile(np.linspace(-170, 170, 100), n // 100 + 1)[:n]  # pairs >= 100 km apart
    t_ref, gap = 1.7e9, rng.uniform(0, 120, n)
    az_f = rng.uniform(0, 360, n)
    uf = np.stack([np.sin(np.radians(az_f)), np.cos(np.radians(az_f))])
    ur = np.stack([np.sin(np.radians(az_f + 90)), np.cos(np.radians(az_f + 90))])
    R, V, sin_i = rng.uniform(800e3, 950e3, n), np.full(n, 7590.0), rng.uniform(0.5, 0.7, n)
    course = np.radians(az_f + 90 + np.where(rng.random(n) < 0.5, 180, 0) + rng.uniform(-35, 35, n))
    speed = rng.uniform(11, 13, n)
    vhat, vperp = np.stack([np.sin(course), np.cos(course)]), np.stack([np.cos(course), -np.sin(course)])
    v = speed * vhat
    v_true = (
        v + rng.normal(0, p.sigma_sog_kn * KN, n) * vhat + speed * rng.normal(0, np.radians(p.sigma_cog_deg), n) * vperp
    )
    dx_true = R * (-(v_true * ur).sum(0) * sin_i) / V
    L_ais = np.where(rng.random(n) < 0.5, rng.uniform(20, 300, n), np.nan)
    L_det = L_ais * np.exp(rng.normal(0, p.length_sigma_log, n))
    a = p.sigma_geo_m**2 + (p.sigma_rate_m_s * gap) ** 2 + (np.nan_to_num(L_ais) / np.sqrt(12)) ** 2
    a = a + (0.5 * speed * np.radians(p.sigma_turn_deg_s) * gap**2) ** 2  # a turn since the report
    e = dx_true * uf[0] + rng.normal(0, 1, n) * np.sqrt(a)
    nn = dx_true * uf[1] + rng.normal(0, 1, n) * np.sqrt(a)
    d_lon = lon + e / (K * np.cos(np.radians(lat)))
    d_lat = lat + nn / K
    states = VesselStates(t_ref, np.arange(n) + 1, lon, lat, v[0], v[1], gap, np.zeros(n, bool))
    info = {k + 1: VesselInfo(k + 1, length_m=float(L_ais[k])) for k in np.flatnonzero(np.isfinite(L_ais))}
    geo = LookGeometry(uf[0], uf[1], ur[0], ur[1], R, V, sin_i)
    return Detections(d_lon, d_lat, np.full(n, t_ref), L_det, geo), states, info


@pytest.mark.parametrize(
    "params",
    [
        MatchParams(min_score=1e-9, sigma_geo_m=50.0),  # mostly isotropic (50 m: the displacement stays > 5 sigma)
        MatchParams(min_score=1e-9, sigma_geo_m=10.0, sigma_rate_m_s=0.1, sigma_sog_kn=2.0, sigma_cog_deg=8.0),
        MatchParams(min_score=1e-9, sigma_geo_m=30.0, sigma_rate_m_s=0.0, sigma_turn_deg_s=0.05),  # up to 85 m at 2 min
    ],
    ids=["position-dominated", "displacement-dominated", "manoeuvre-dominated"],
)
def test_true_pair_scores_are_uniform(params):
    n = 6000
    det, states, info = _calibration_pairs(np.random.default_rng(5), n, params)
    a = match(det, states, info, params)
    assert np.all(a.vessel == np.arange(n))  # isolated pairs: each its own
    assert np.all(np.abs(a.displacement_m) > 500)  # the displaced hypothesis, as intended
    for alpha in (0.01, 0.05, 0.2, 0.5, 0.8):
        frac = float(np.mean(a.score < alpha))
        assert abs(frac - alpha) < 4.5 * np.sqrt(alpha * (1 - alpha) / n) + 1e-3, (alpha, frac)
    # the default threshold refuses min_score of true pairs
    known = np.isfinite(det.length_m)
    assert abs(np.mean(a.score[known] < 0.01) - 0.01) < 0.01 and abs(np.mean(a.score[~known] < 0.01) - 0.01) < 0.01


# --------------------------------------------------------------------------------------
# the assignment
# --------------------------------------------------------------------------------------


def _brute_force(i, j, gain) -> float:
    """The best total gain over all matchings (each detection / vessel at most once)."""
    edges = {(a, b): g for a, b, g in zip(i.tolist(), j.tolist(), gain.tolist())}
    dets = sorted(set(i.tolist()))
    best = 0.0

    def walk(k, used, total):
        nonlocal best
        if k == len(dets):
            best = max(best, total)
            return
        walk(k + 1, used, total)
        for (a, b), g in edges.items():
            if a == dets[k] and b not in used:
                walk(k + 1, used | {b}, total + g)

    walk(0, frozenset(), 0.0)
    return best


@pytest.mark.parametrize("max_dense_cells", [4_000_000, 1], ids=["dense", "sparse"])
def test_assignment_equals_brute_force(max_dense_cells):
    rng = np.random.default_rng(11)
    for _ in range(150):
        nd, nv = rng.integers(1, 6, 2)
        pairs = [(a, b) for a, b in itertools.product(range(nd), range(nv)) if rng.random() < 0.5]
        if not pairs:
            continue
        i, j = (np.array(c, np.int64) + off for c, off in zip(zip(*pairs), (100, 7)))
        gain = rng.uniform(0, 5, i.size)
        chosen, _ = assign(i, j, gain, max_dense_cells=max_dense_cells)
        assert np.unique(i[chosen]).size == chosen.size and np.unique(j[chosen]).size == chosen.size
        assert gain[chosen].sum() == pytest.approx(_brute_force(i, j, gain), abs=1e-6)


def test_global_assignment_beats_greedy():
    # along a parallel: detections at 0 and 100 m, vessels at rest at 60 and 160 m. Greedy takes
    # the closest pair (100 <-> 60, 40 m) and leaves 0 <-> 160 (160 m: below min_score); the
    # global assignment pairs 0 <-> 60 and 100 <-> 160 (60 m each: sum ln score higher)
    x_det, x_ves = np.array([0.0, 100.0]), np.array([160.0, 60.0])
    lon = lambda x: 3.0 + x / (K * np.cos(np.radians(54.0)))  # noqa: E731
    det = Detections(lon(x_det), np.full(2, 54.0), np.full(2, 1e9))
    z = np.zeros(2)
    states = VesselStates(1e9, np.array([5, 6]), lon(x_ves), np.full(2, 54.0), z, z, z, np.zeros(2, bool))
    a = match(det, states, {}, MatchParams(sigma_geo_m=50.0, sigma_rate_m_s=0.0))
    assert a.mmsi.tolist() == [6, 5]
    np.testing.assert_allclose(a.distance_m, [60.0, 60.0], atol=0.01)
    np.testing.assert_allclose(a.score, np.exp(-(60.0**2) / (2 * 50.0**2)), rtol=1e-6)


# --------------------------------------------------------------------------------------
# coverage, footprint, errors
# --------------------------------------------------------------------------------------


def test_coverage_rule():
    sc = Scene()
    t0, t1 = sc.t_first, sc.t_first + sc.duration_s
    lon, lat = sc.to_lonlat(0.0, 0.0)
    far_lon, far_lat = sc.to_lonlat(300e3, 0.0)  # outside the footprint

    def reports(ts, where=(lon, lat)):
        k = len(ts)
        f = np.full(k, np.nan, np.float32)
        return Reports(np.arange(k), np.array(ts, float), np.full(k, where[0]), np.full(k, where[1]), f, f, f)

    ring = sc.ring()
    assert covers_scene(reports([t0 - 100, t1 + 100]), t0, t1, ring=ring)
    assert not covers_scene(reports([t0 - 100, t0 - 50]), t0, t1, ring=ring)  # the feed stops before
    assert not covers_scene(reports([t0 - 700, t1 + 100]), t0, t1, ring=ring, max_report_gap_s=600)
    assert not covers_scene(reports([t0 - 100, t1 + 100], (far_lon, far_lat)), t0, t1, ring=ring)
    assert covers_scene(reports([t0 - 100, t1 + 100], (far_lon, far_lat)), t0, t1)  # no footprint: anywhere
    assert dark_flags(np.array([-1, 3]), False) is None
    assert dark_flags(np.array([-1, 3]), True).tolist() == [True, False]


@pytest.mark.parametrize("lon0", [3.0, 179.5])
def test_inside_the_footprint(lon0):
    sc = Scene(lon0=lon0)
    rng = np.random.default_rng(2)
    a, x = rng.uniform(-0.1, 1.1, 4000) * sc.along_m, rng.uniform(-0.1, 1.1, 4000) * sc.across_m
    lon, lat = sc.to_lonlat(*sc.en(a - sc.along_m / 2, x - sc.across_m / 2))
    lon = (lon + 180.0) % 360.0 - 180.0
    truth = (a >= 0) & (a <= sc.along_m) & (x >= 0) & (x <= sc.across_m)
    got = inside(lon, lat, sc.ring())
    near_edge = (np.minimum(np.abs(a), np.abs(a - sc.along_m)) < 50) | (
        np.minimum(np.abs(x), np.abs(x - sc.across_m)) < 50
    )
    assert np.array_equal(got[~near_edge], truth[~near_edge])

    class Affine:  # rows along the flight, columns across, 10 m pixels
        def lonlat(self, rows, cols):
            e, n = sc.en(np.asarray(rows) * 10.0 - sc.along_m / 2, np.asarray(cols) * 10.0 - sc.across_m / 2)
            return sc.to_lonlat(e, n)

    ring = footprint_ring(Affine(), (int(sc.along_m / 10), int(sc.across_m / 10)), points_per_side=4)
    assert ring.shape == (17, 2)
    assert np.array_equal(inside(lon, lat, ring)[~near_edge], truth[~near_edge])


def test_bad_input_refused_in_one_line():
    det = Detections(np.array([3.0]), np.array([54.0]), np.array([np.nan]))
    z = np.zeros(1)
    states = VesselStates(0.0, np.array([1]), z + 3, z + 54, z, z, z, np.zeros(1, bool))
    for call in (
        lambda: match(det, states),
        lambda: match(Detections(np.array([np.nan]), np.array([54.0]), np.array([0.0])), states),
        lambda: match(Detections(np.array([3.0]), np.array([54.0]), np.array([0.0, 1.0])), states),
        lambda: MatchParams(min_score=1.5),
        lambda: MatchParams(sigma_geo_m=0.0),
        lambda: MatchParams(sigma_turn_deg_s=-0.1),
    ):
        with pytest.raises(InputError) as e:
            call()
        assert "\n" not in str(e.value)
    empty = match(Detections(np.zeros(0), np.zeros(0), np.zeros(0)), states)
    assert empty.vessel.size == 0 and empty.unmatched.tolist() == [0]
