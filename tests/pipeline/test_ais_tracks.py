"""AIS tracks at a time (pipeline/ais/tracks.py): interpolation, extrapolation and the gap.

Tracks are made here from their own motion (great-circle-free local metres, constant velocity or
a constant-turn arc) and sampled at AIS-like report times; the code sees only the reports.
Checked: the interpolation is exact on straight tracks at constant speed (position to a
decimetre over kilometres, velocity to mm/s) for many vessels at once, across the antimeridian too; on a
turning ship the Hermite curve is far closer than the straight chord; propagation before the
first and after the last report follows SOG/COG and stops at ``max_extrapolation_s``; ``gap_s``,
``t_before`` / ``t_after`` and ``extrapolated`` are right; unknown SOG/COG fall back to the chord
and a lone report without them is held; :func:`positions_at` agrees with the states at the later
time; unsorted reports are refused in one line.
"""

from __future__ import annotations

import numpy as np
import pytest

from sarship.pipeline.ais.reports import Reports
from sarship.pipeline.ais.tracks import positions_at, vessel_states
from sarship.pipeline.errors import InputError

K = 6_371_008.8 * np.pi / 180.0
KN = 1852.0 / 3600.0


def _lonlat(lon0, lat0, e, n):
    """Local metres about (lon0, lat0) to degrees (the same small-area frame for truth and reports)."""
    lat = lat0 + n / K
    return (lon0 + e / (K * np.cos(np.radians(0.5 * (lat0 + lat)))) + 180.0) % 360.0 - 180.0, lat


def _reports(rows) -> Reports:
    m, t, lon, lat, sog, cog = (np.asarray(c) for c in zip(*rows))
    f = np.float32
    return Reports(m.astype(np.int64), t, lon, lat, sog.astype(f), cog.astype(f), np.full(m.size, np.nan, f)).sorted()


def _straight(rng, n_vessels: int, t_ref: float, lon0: float = 3.0, lat0: float = 54.0):
    """Vessels on straight tracks at constant speed: reports every 2-30 s with a gap of up to
    3 min around t_ref; truth at t_ref."""
    rows, truth = [], {}
    for k in range(n_vessels):
        mmsi = 200_000_000 + k
        speed = rng.uniform(0, 25) * KN
        cog = rng.uniform(0, 360)
        ve, vn = speed * np.sin(np.radians(cog)), speed * np.cos(np.radians(cog))
        e0, n0 = rng.uniform(-5e3, 5e3, 2)
        dt = rng.choice([2.0, 6.0, 10.0, 30.0])
        t = np.arange(t_ref - 400 + rng.uniform(0, dt), t_ref + 400, dt)
        g0 = t_ref - rng.uniform(0, 180)
        t = t[(t < g0) | (t > g0 + rng.uniform(0, 180))]
        lon, lat = _lonlat(lon0, lat0, e0 + ve * (t - t_ref), n0 + vn * (t - t_ref))
        rows += [(mmsi, ti, a, b, speed / KN, cog) for ti, a, b in zip(t, lon, lat)]
        truth[mmsi] = (*_lonlat(lon0, lat0, e0, n0), ve, vn, np.min(np.abs(t - t_ref)))
    return _reports(rows), truth


def _m(lon1, lat1, lon2, lat2):
    dlon = (np.asarray(lon2) - lon1 + 180.0) % 360.0 - 180.0
    return np.hypot(dlon * K * np.cos(np.radians(lat1)), (np.asarray(lat2) - lat1) * K)


@pytest.mark.parametrize("lon0", [3.0, 179.99])
def test_straight_tracks_are_exact(lon0):
    rng = np.random.default_rng(3)
    t_ref = 1.7e9
    rep, truth = _straight(rng, 300, t_ref, lon0=lon0)
    st = vessel_states(rep, t_ref)
    assert len(st) == 300 and not st.extrapolated.any()
    want = np.array([truth[m] for m in st.mmsi.tolist()])
    err = _m(want[:, 0], want[:, 1], st.lon, st.lat)
    assert err.max() < 0.2, err.max()  # the test's frame and the code's differ at second order
    np.testing.assert_allclose(st.v_east_m_s, want[:, 2], atol=2e-3)  # float32 SOG/COG
    np.testing.assert_allclose(st.v_north_m_s, want[:, 3], atol=2e-3)
    np.testing.assert_allclose(st.gap_s, want[:, 4], atol=1e-6)
    np.testing.assert_allclose(np.fmin(t_ref - st.t_before, st.t_after - t_ref), st.gap_s)
    # 12.5 s later (the end of a 25 s scene): propagated = interpolated there
    lon, lat = positions_at(st, t_ref + 12.5)
    later = vessel_states(rep, t_ref + 12.5)
    assert np.array_equal(later.mmsi, st.mmsi)
    assert _m(later.lon, later.lat, lon, lat).max() < 0.2


def test_turning_ship_hermite_beats_the_chord():
    # a ship turning at 0.3 deg/s at 15 kn, reporting every 60 s (lost reports)
    speed, omega, psi0 = 15 * KN, np.radians(0.3), np.radians(10.0)
    t = np.arange(0.0, 601.0, 60.0)
    psi = psi0 + omega * t
    e = speed / omega * (np.cos(psi0) - np.cos(psi))
    n = speed / omega * (np.sin(psi) - np.sin(psi0))
    lon, lat = _lonlat(3.0, 54.0, e, n)
    rep = _reports([(1, ti, a, b, speed / KN, np.degrees(p) % 360) for ti, a, b, p in zip(t, lon, lat, psi)])
    t_q = np.arange(5.0, 600.0, 11.0)
    herm, chord = [], []
    for tq in t_q:
        st = vessel_states(rep, float(tq))
        pq = psi0 + omega * tq
        te, tn = _lonlat(
            3.0, 54.0, speed / omega * (np.cos(psi0) - np.cos(pq)), speed / omega * (np.sin(pq) - np.sin(psi0))
        )
        herm.append(_m(te, tn, st.lon[0], st.lat[0]))
        i = np.searchsorted(t, tq) - 1
        s = (tq - t[i]) / 60.0
        chord.append(_m(te, tn, lon[i] + s * (lon[i + 1] - lon[i]), lat[i] + s * (lat[i + 1] - lat[i])))
    herm, chord = np.array(herm), np.array(chord)
    # the chord cuts the arc by up to R (1 - cos(18 deg / 2)) ~ 18 m; the cubic follows it (0.04 m measured)
    assert chord.max() > 10.0
    assert herm.max() < 0.1 * chord.max(), (herm.max(), chord.max())


def test_extrapolation_follows_sog_cog_and_is_bounded():
    t0, t1 = 1000.0, 1100.0
    lon, lat = _lonlat(3.0, 54.0, np.array([0.0, 1000.0]), np.array([0.0, 0.0]))
    rep = _reports([(7, t0, lon[0], lat[0], 10 / KN, 90.0), (7, t1, lon[1], lat[1], 10 / KN, 90.0)])
    for t_ref, e_want in ((t1 + 500, 1000 + 10 * 500), (t0 - 300, -3000.0)):
        st = vessel_states(rep, t_ref, max_extrapolation_s=600)
        assert len(st) == 1 and st.extrapolated[0]
        el, nl = _lonlat(3.0, 54.0, e_want, 0.0)
        assert _m(el, nl, st.lon[0], st.lat[0]) < 0.05
        assert st.gap_s[0] == pytest.approx(abs(t_ref - (t1 if t_ref > t1 else t0)))
    assert len(vessel_states(rep, t1 + 601, max_extrapolation_s=600)) == 0
    assert len(vessel_states(rep, t0 - 200, max_extrapolation_s=100)) == 0
    assert len(vessel_states(rep, t1 + 50, max_extrapolation_s=60)) == 1


def test_unknown_speed_or_course():
    lon, lat = _lonlat(3.0, 54.0, np.array([0.0, 600.0, 0.0]), np.array([0.0, 0.0, 0.0]))
    nan = np.nan
    rep = _reports(
        [
            (1, 0.0, lon[0], lat[0], nan, nan),  # two reports without SOG/COG: the chord
            (1, 60.0, lon[1], lat[1], nan, 90.0),
            (2, 0.0, lon[2], lat[2], nan, nan),  # one report without them: held
            (3, 0.0, lon[0], lat[0], 0.0, nan),  # at rest, no course: velocity zero
        ]
    )
    st = vessel_states(rep, 30.0)
    assert st.mmsi.tolist() == [1, 2, 3]
    el, nl = _lonlat(3.0, 54.0, 300.0, 0.0)
    assert _m(el, nl, st.lon[0], st.lat[0]) < 0.05
    assert st.v_east_m_s[0] == pytest.approx(10.0, abs=1e-6) and not st.extrapolated[0]
    assert _m(lon[2], lat[2], st.lon[1], st.lat[1]) < 1e-6 and np.isnan(st.v_east_m_s[1]) and st.extrapolated[1]
    assert st.v_east_m_s[2] == 0.0 and st.v_north_m_s[2] == 0.0
    # after the last report without SOG/COG: the chord's velocity carries it on
    st = vessel_states(rep, 90.0)
    el, nl = _lonlat(3.0, 54.0, 900.0, 0.0)
    assert _m(el, nl, st.lon[0], st.lat[0]) < 0.05


def test_bad_input_refused_in_one_line():
    rep = _reports([(1, 0.0, 3.0, 54.0, 1.0, 0.0), (1, 10.0, 3.0, 54.001, 1.0, 0.0)])
    unsorted = Reports(
        *(getattr(rep, f)[::-1] for f in ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg"))
    )
    for call in (
        lambda: vessel_states(unsorted, 5.0),
        lambda: vessel_states(rep, float("nan")),
        lambda: vessel_states(rep, 5.0, max_extrapolation_s=-1),
    ):
        with pytest.raises(InputError) as e:
            call()
        assert "\n" not in str(e.value)
    assert len(vessel_states(Reports.empty(), 5.0)) == 0
