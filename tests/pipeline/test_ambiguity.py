"""Azimuth-ambiguity flags (issue 16): pipeline/targets/ambiguity.py, pipeline/readers/safe_geometry.py,
the simulator's ghosts and the ``ambiguity_of`` property of ``sarship detect``.

Checked: the expected displacement against a hand computation from the real Sentinel-1 IW
annotation (values read here with ElementTree, independently of the reader), eq. (3) against
the exact hyperbolic range history, the matcher against a brute-force reference, the simulated
scene end to end through ``sarship detect`` (ghosts flagged with their ship's detection id, the
ships not flagged, no flags without ghosts), and bad or missing geometry (no flags, the reason
in run.json, no crash).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.simulate.geometry import sar_geometry as sim_geometry
from sarship.pipeline.targets import ambiguity as amb
from sarship.pipeline.targets.ambiguity import (
    C_LIGHT,
    GeometryError,
    flag_features,
    geometry_from_attrs,
    match_ambiguities,
    range_shift_m,
)

SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
SLC = next(iter(sorted(SAFE_DIR.glob("S1B_IW_SLC_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
try:
    import xarray_sentinel  # noqa: F401

    HAVE_XS = True
except ImportError:
    HAVE_XS = False
WHY = "the shared SAFE sample or xarray-sentinel is missing"
needs_grd = pytest.mark.skipif(GRD is None or not HAVE_XS, reason=WHY)
needs_slc = pytest.mark.skipif(SLC is None or not HAVE_XS, reason=WHY)


def _seconds(t: str) -> float:
    return float(np.datetime64(t, "ns").astype("int64")) * 1e-9


def _annotation(safe: Path, swath: str, pol: str = "vv") -> ET.Element:
    f = next(p for p in sorted((safe / "annotation").glob("*.xml")) if f"-{swath}-" in p.name and f"-{pol}-" in p.name)
    return ET.parse(f).getroot()


def _product(safe: Path):
    from sarship.pipeline.readers.safe import _Product, safe_layout

    return _Product(safe, safe_layout(safe))


# --------------------------------------------------------------------------------------
# the equations
# --------------------------------------------------------------------------------------


def test_equations_agree_with_each_other_and_with_the_hyperbola():
    lam, R, prf, vs, vr = 0.0555, 850e3, 1700.0, 7590.0, 7180.0
    ka = -2 * vr**2 / (lam * R)
    for k in (-2, -1, 1, 2):
        # eq (1) is k PRF / Ka; eq (2) is Vg times eq (1), Vg = Vr^2 / Vs
        assert amb.azimuth_shift_s(k, lam, R, prf, vr) == pytest.approx(k * prf / ka, rel=1e-12)
        assert amb.azimuth_shift_m(k, lam, R, prf, vs) == pytest.approx(
            amb.azimuth_shift_s(k, lam, R, prf, vr) * vr**2 / vs, rel=1e-12
        )
    # SUMO's |dx| = lambda R PRF / (2 V): 4.7 km for these numbers
    assert abs(amb.azimuth_shift_m(1, lam, R, prf, vs)) == pytest.approx(lam * R * prf / (2 * vs))

    # eq (3) against the exact range history R(t) = sqrt(R^2 + Vr^2 t^2), Doppler f = -2 R'(t) / lambda:
    # energy at Doppler f lies at t = -f lambda R(t) / (2 Vr^2), solved by fixed point
    def exact_excess(f: float) -> float:
        t = -f * lam * R / (2 * vr**2)
        for _ in range(50):
            t = -f * lam * math.hypot(R, vr * t) / (2 * vr**2)
        return math.hypot(R, vr * t) - R

    for fdc in (0.0, 35.0, -120.0):
        for k in (-2, -1, 1, 2):
            want = exact_excess(fdc + k * prf) - exact_excess(fdc)
            assert range_shift_m(k, lam, R, prf, vr, fdc) == pytest.approx(want, rel=2e-3)
    # symmetric without a Doppler centroid, ~18 m for k = +-1 (2-4 ground pixels of 10 m: not negligible)
    assert range_shift_m(1, lam, R, prf, vr) == pytest.approx(range_shift_m(-1, lam, R, prf, vr))
    assert 15 < range_shift_m(1, lam, R, prf, vr) < 22
    # the TOPS half-width: lambda^2 R |k| PRF 2 df / (8 Vr^2) is eq (3) moved by df
    df = 2500.0
    assert amb.range_spread_m(1, lam, R, prf, vr, df) == pytest.approx(
        range_shift_m(1, lam, R, prf, vr, df) - range_shift_m(1, lam, R, prf, vr, 0.0), rel=1e-9
    )


# --------------------------------------------------------------------------------------
# real annotation numbers (Sentinel-1B IW GRDH / SLC)
# --------------------------------------------------------------------------------------


@needs_grd
def test_grd_displacement_matches_a_hand_computation_from_the_annotation():
    from sarship.pipeline.readers.safe_geometry import read_geometry

    root = _annotation(GRD, "iw")
    freq = float(root.findtext("generalAnnotation/productInformation/radarFrequency"))
    lam = C_LIGHT / freq
    assert lam == pytest.approx(0.05547, abs=1e-5)
    prf = {d.findtext("swath"): float(d.findtext("prf")) for d in root.iter("downlinkInformation")}
    assert prf["IW1"] == pytest.approx(1717.13, abs=0.01)
    ati = float(root.findtext("imageAnnotation/imageInformation/azimuthTimeInterval"))
    gp = [p for p in root.iter("geolocationGridPoint") if p.findtext("line") == "0" and p.findtext("pixel") == "0"][0]
    tau = float(gp.findtext("slantRangeTime"))
    R = C_LIGHT * tau / 2
    fm = next(root.iter("azimuthFmRate"))
    c = [float(v) for v in fm.findtext("azimuthFmRatePolynomial").split()]
    dt = tau - float(fm.findtext("t0"))
    ka = c[0] + c[1] * dt + c[2] * dt**2
    assert -2400 < ka < -2250
    # hand: the first ghost lies PRF / |Ka| seconds, i.e. PRF / (|Ka| dt_line) lines, away
    want_rows = prf["IW1"] / abs(ka) / ati
    assert 490 < want_rows < 500
    # eq (2) with the orbit's speed at mid product
    t_mid = 0.5 * (
        _seconds(root.findtext("imageAnnotation/imageInformation/productFirstLineUtcTime"))
        + _seconds(root.findtext("imageAnnotation/imageInformation/productLastLineUtcTime"))
    )
    orb = [
        (_seconds(o.findtext("time")), math.sqrt(sum(float(o.findtext(f"velocity/{a}")) ** 2 for a in "xyz")))
        for o in root.iter("orbit")
    ]
    vs = float(np.interp(t_mid, [t for t, _ in orb], [v for _, v in orb]))
    want_m = lam * R * prf["IW1"] / (2 * vs)
    assert 4900 < want_m < 5100

    g = read_geometry(_product(GRD), "IW", "vv")
    geom = geometry_from_attrs({"sar_geometry": g})
    got = geom.ghosts([8000.0], [0.0], (-1, 1))
    assert got["prf_hz"][0] == prf["IW1"]
    np.testing.assert_allclose(np.abs(got["row"][0] - 8000.0), want_rows, rtol=5e-4)  # median over FM estimates
    np.testing.assert_allclose(np.abs(got["dx_m"][0]), want_m, rtol=1e-5)
    assert got["row"][0, 0] > 8000 > got["row"][0, 1]  # k = -1 later, k = +1 earlier (Ka < 0)
    # the metre and the time routes meet: Vg dt_line is the line spacing on the ground (10.17 m; the
    # annotation's nominal azimuthPixelSpacing says 10 m)
    vr = geom.at(np.array([0.0]), geom.v_eff_m_s)[0]
    nominal = float(root.findtext("imageAnnotation/imageInformation/azimuthPixelSpacing"))
    assert vr**2 / vs * ati == pytest.approx(nominal, rel=0.025)
    # eq (3) by hand, in columns through the grid's slant range (ground range: ~5.3 m slant per column at near range)
    fdc = geom.at(np.array([0.0]), geom.doppler_centroid_hz)[0]
    assert abs(fdc) < prf["IW1"] / 2
    dr = lam**2 * R * ((fdc + prf["IW1"]) ** 2 - fdc**2) / (8 * vr**2)
    gp2 = [p for p in root.iter("geolocationGridPoint") if p.findtext("line") == "0"][1]
    dR_dcol = (C_LIGHT * float(gp2.findtext("slantRangeTime")) / 2 - R) / float(gp2.findtext("pixel"))
    assert got["col"][0, 1] == pytest.approx(dr / dR_dcol, rel=0.02)
    assert 2.5 < got["col"][0, 1] < 4.5


@needs_grd
def test_grd_geometry_values_read_independently_from_the_xml():
    from sarship.pipeline.readers.safe_geometry import read_geometry

    root = _annotation(GRD, "iw")
    g = read_geometry(_product(GRD), "IW", "vv")
    assert g["radar_frequency_hz"] == float(root.findtext("generalAnnotation/productInformation/radarFrequency"))
    assert g["azimuth_time_interval_s"] == float(root.findtext("imageAnnotation/imageInformation/azimuthTimeInterval"))
    prf = {d.findtext("swath"): float(d.findtext("prf")) for d in root.iter("downlinkInformation")}
    merge = {
        m.findtext("swath"): [
            int(m.findtext(f"swathBoundsList/swathBounds/{k}"))
            for k in ("firstAzimuthLine", "lastAzimuthLine", "firstRangeSample", "lastRangeSample")
        ]
        for m in root.iter("swathMerge")
    }
    assert [(s["name"], s["prf_hz"], s["blocks"]) for s in g["swaths"]] == [
        (n, prf[n], [merge[n]]) for n in ("IW1", "IW2", "IW3")
    ]
    pts = {
        int(p.findtext("pixel")): float(p.findtext("slantRangeTime"))
        for p in root.iter("geolocationGridPoint")
        if p.findtext("line") == "0"
    }
    t = g["range_table"]
    assert t["col"] == [float(c) for c in sorted(pts)]
    np.testing.assert_allclose(t["slant_range_m"], [C_LIGHT * pts[c] / 2 for c in sorted(pts)], rtol=1e-9)
    # effective velocity ~ sqrt(Vs Vg): between the ground and the platform speed
    assert all(6700 < v < g["platform_velocity_m_s"] < 7700 for v in t["effective_velocity_m_s"])
    # TOPS: the centroid spans |kt| x burst over a burst (the GRD's fine-DCE window, 2.78 s)
    steer = math.radians(float(root.findtext("generalAnnotation/productInformation/azimuthSteeringRate")))
    ks = 2 * g["platform_velocity_m_s"] * steer / g["wavelength_m"]
    assert 7000 < ks < 8000 and 2.5 < g["burst_duration_s"] < 3.2
    assert 2000 < g["doppler_centroid_spread_hz"] < 3000
    # the column's swath gives its PRF
    geom = geometry_from_attrs({"sar_geometry": g})
    np.testing.assert_array_equal(
        geom.prf_at(np.array([0.0, 100.0, 9000.0, 25000.0]), np.array([5.0, 8681.0, 8682.0, 25787.0])),
        [prf["IW1"], prf["IW1"], prf["IW2"], prf["IW3"]],
    )


@needs_grd
def test_safe_ingest_carries_the_geometry():
    from sarship.pipeline.readers.entry import _open_safe
    from sarship.pipeline.readers.limits import InputLimits
    from sarship.pipeline.readers.safe_geometry import read_geometry

    src = _open_safe(GRD, InputLimits(max_ratio=1e5))  # the constant-pixel sample: ~1900:1
    try:
        got = src.meta["extra_attrs"]["sar_geometry"]
    finally:
        src.close()
    assert got == read_geometry(_product(GRD), "IW", "vv")
    geometry_from_attrs({"sar_geometry": got})  # usable as it is


@needs_slc
def test_slc_geometry_from_the_annotation():
    from sarship.pipeline.readers.safe_geometry import read_geometry

    root = _annotation(SLC, "iw1")
    g = read_geometry(_product(SLC), "IW1", "vv")
    ii = "imageAnnotation/imageInformation/"
    tau0, fs = (
        float(root.findtext(ii + "slantRangeTime")),
        float(root.findtext("generalAnnotation/productInformation/rangeSamplingRate")),
    )
    W = int(root.findtext(ii + "numberOfSamples"))
    assert g["prf_hz"] == float(next(root.iter("downlinkInformation")).findtext("prf"))
    t = g["range_table"]
    assert t["col"][0] == 0 and t["col"][-1] == W - 1
    assert t["slant_range_m"][0] == pytest.approx(C_LIGHT * tau0 / 2, rel=1e-12)
    assert t["slant_range_m"][-1] == pytest.approx(C_LIGHT * (tau0 + (W - 1) / fs) / 2, rel=1e-12)
    assert g["burst_duration_s"] == pytest.approx(
        int(root.findtext("swathTiming/linesPerBurst")) * float(root.findtext(ii + "azimuthTimeInterval"))
    )
    # the SLC's slant-range columns make the range shift ~18 m / 2.33 m ~ 7.7 columns
    geom = geometry_from_attrs({"sar_geometry": g})
    gh = geom.ghosts([5000.0], [0.0], (1,))
    assert gh["col"][0, 0] == pytest.approx(gh["dr_m"][0, 0] / (C_LIGHT / (2 * fs)), rel=1e-6)


@needs_grd
def test_an_annotation_without_prf_gives_a_reason_not_an_error(tmp_path):
    from sarship.pipeline.readers.safe import _Product
    from sarship.pipeline.readers.safe_geometry import sar_geometry

    safe = tmp_path / GRD.name
    (safe / "annotation").mkdir(parents=True)
    shutil.copy(GRD / "manifest.safe", safe / "manifest.safe")
    for f in (GRD / "annotation").glob("*.xml"):
        text = f.read_text()
        (safe / "annotation" / f.name).write_text(text.replace("<prf>", "<notPrf>").replace("</prf>", "</notPrf>"))
    got = sar_geometry(_Product(safe, ("dir", None)), "IW", "vv")
    assert list(got) == ["unavailable"] and "prf" in got["unavailable"]
    with pytest.raises(GeometryError, match="unavailable.*prf"):
        geometry_from_attrs({"sar_geometry": got})


# --------------------------------------------------------------------------------------
# matching
# --------------------------------------------------------------------------------------


def _sim_geom(shape=(4000, 1000), spacing=(10.0, 10.0), **over):
    g = sim_geometry(shape, spacing)
    g.update(over)
    return geometry_from_attrs({"sar_geometry": g})


def _brute(c, p, geom, tol, min_db, orders):
    """The matching rule of match_ambiguities, by exhaustive loops."""
    n = len(c)
    gh = geom.ghosts(c[:, 0], c[:, 1], orders)
    parent, order = [None] * n, [None] * n
    is_ghost = [False] * n
    for j in sorted(range(n), key=lambda j: -p[j]):
        best = None
        for i in range(n):
            if i == j or is_ghost[i] or not p[j] <= p[i] * 10 ** (-min_db / 10):
                continue
            for q, k in enumerate(orders):
                tc = tol + gh["col_spread_px"][i, q]
                dr, dc = abs(c[j, 0] - gh["row"][i, q]) / tol, abs(c[j, 1] - gh["col"][i, q]) / tc
                if dr <= 1 and dc <= 1 and (best is None or math.hypot(dr, dc) < best[0]):
                    best = (math.hypot(dr, dc), i, k)
        if best is not None:
            parent[j], order[j], is_ghost[j] = best[1], best[2], True
    return parent, order


def test_matching_rules():
    geom = _sim_geom()
    ships = np.array([[2000.0, 300.0], [1200.0, 700.0]])
    gh = geom.ghosts(ships[:, 0], ships[:, 1])  # orders -2, -1, 1, 2
    k_idx = {k: q for q, k in enumerate(amb.ORDERS)}
    c = np.array(
        [
            ships[0],
            ships[1],
            [gh["row"][0, k_idx[1]] + 3.0, gh["col"][0, k_idx[1]] - 2.0],  # ghost k=+1 of ship 0
            [gh["row"][0, k_idx[-2]], gh["col"][0, k_idx[-2]]],  # ghost k=-2 of ship 0
            [gh["row"][1, k_idx[-1]] + 9.0, gh["col"][1, k_idx[-1]]],  # 9 rows off: beyond 8 px
            [gh["row"][1, k_idx[1]], gh["col"][1, k_idx[1]]],  # only 7 dB below ship 1
            [300.0, 900.0],
        ]
    )  # an unrelated ship
    p = np.array([1e5, 2e4, 50.0, 5.0, 30.0, 4e3, 60.0])
    parent, order = match_ambiguities(c, p, geom)
    assert parent == [None, None, 0, 0, None, None, None]
    assert order == [None, None, 1, -2, None, None, None]
    # the parameters move the decisions: a wider tolerance takes the 9-row ghost, a smaller ratio the bright one
    assert match_ambiguities(c, p, geom, tol_px=10.0)[0][4] == 1
    assert match_ambiguities(c, p, geom, min_db=5.0)[0][5] == 1
    assert match_ambiguities(c, p, geom, tol_px=1.0)[0][2] is None  # 3 rows off
    # a ghost is no parent: C at B's k=+1 place is B's ghost only while B is not A's ghost
    b = [gh["row"][0, k_idx[1]], gh["col"][0, k_idx[1]]]
    gb = geom.ghosts([b[0]], [b[1]], (1,))
    cc = np.array([ships[0], b, [gb["row"][0, 0], gb["col"][0, 0]]])
    assert match_ambiguities(cc, np.array([1e6, 1e4, 100.0]), geom, orders=(1,))[0] == [None, 0, None]
    assert match_ambiguities(cc[1:], np.array([1e4, 100.0]), geom, orders=(1,))[0] == [None, 0]
    # non-finite values neither match nor crash
    bad = c.copy()
    bad[2, 0] = np.nan
    pb = p.copy()
    pb[3] = np.nan
    assert match_ambiguities(bad, pb, geom)[0] == [None] * 7
    assert match_ambiguities(c[:1], p[:1], geom) == ([None], [None])


def test_tops_spread_widens_the_range_tolerance():
    flat, tops = _sim_geom(), _sim_geom(doppler_centroid_spread_hz=2500.0)
    ship = np.array([[2000.0, 300.0]])
    g = flat.ghosts(ship[:, 0], ship[:, 1], (1,))
    c = np.array([ship[0], [g["row"][0, 0], g["col"][0, 0] + 12.0]])  # 12 columns off (TOPS: up to ~14 here)
    p = np.array([1e5, 10.0])
    assert match_ambiguities(c, p, flat)[0] == [None, None]
    assert tops.ghosts(ship[:, 0], ship[:, 1], (1,))["col_spread_px"][0, 0] > 4.0
    assert match_ambiguities(c, p, tops)[0] == [None, 0]


def test_matching_equals_brute_force_reference():
    rng = np.random.default_rng(16)
    geom = _sim_geom(doppler_centroid_spread_hz=600.0)
    for trial in range(4):
        n = 40
        c = np.column_stack([rng.uniform(0, 4000, n), rng.uniform(0, 1000, n)])
        p = 10 ** rng.uniform(0, 5, n)
        par = rng.choice(n, 12, replace=False)
        g = geom.ghosts(c[par, 0], c[par, 1])
        extra_c, extra_p = [], []
        for q, i in enumerate(par):  # planted ghosts, jittered up to the tolerance, some too bright
            k = rng.integers(0, len(amb.ORDERS))
            extra_c.append([g["row"][q, k] + rng.uniform(-9, 9), g["col"][q, k] + rng.uniform(-9, 9)])
            extra_p.append(p[i] * 10 ** (-rng.uniform(5, 30) / 10))
        cc, pp = np.vstack([c, extra_c]), np.concatenate([p, extra_p])
        got = match_ambiguities(cc, pp, geom)
        assert got == _brute(cc, pp, geom, amb.DEFAULT_TOL_PX, amb.DEFAULT_MIN_DB, amb.ORDERS)
        assert sum(x is not None for x in got[0]) >= 3, trial


# --------------------------------------------------------------------------------------
# geometry attributes: bad or missing -> a reason, never an exception in detection
# --------------------------------------------------------------------------------------


def _feats(centroids, peaks):
    return [
        {"type": "Feature", "geometry": None, "properties": {"centroid_px": list(c), "peak": pk}}
        for c, pk in zip(centroids, peaks)
    ]


@pytest.mark.parametrize(
    "change,needle",
    [
        (None, "no 'sar_geometry'"),
        ("not a dict", "not an object"),
        ({"unavailable": "ValueError: no PRF"}, "unavailable: ValueError: no PRF"),
        ({"radar_frequency_hz": -5.0}, "radar_frequency_hz"),
        ({"radar_frequency_hz": float("nan")}, "radar_frequency_hz"),
        ({"platform_velocity_m_s": "fast"}, "platform_velocity_m_s"),
        ({"prf_hz": 0.0}, "prf_hz"),
        ({"prf_hz": None}, "prf_hz"),
        ({"range_table": None}, "range_table"),
        (
            {"range_table": {"col": [0, 10], "slant_range_m": [8e5, 8e5], "effective_velocity_m_s": [7e3, 7e3]}},
            "monotonic",
        ),
        ({"range_table": {"col": [0], "slant_range_m": [8e5], "effective_velocity_m_s": [7e3]}}, "two columns"),
        (
            {"range_table": {"col": [0, 10], "slant_range_m": [8e5, 9e5], "effective_velocity_m_s": [7e3, 1e9]}},
            "effective_velocity_m_s",
        ),
        (
            {"range_table": {"col": [0, 10], "slant_range_m": [8e5, "x"], "effective_velocity_m_s": [7e3, 7e3]}},
            "range_table",
        ),
        ({"azimuth_time_interval_s": None}, "pixel_spacing_m"),
        ({"doppler_centroid_spread_hz": -1.0}, "doppler_centroid_spread_hz"),
    ],
)
def test_bad_geometry_gives_no_flags_and_a_reason(change, needle):
    g = sim_geometry((1000, 500), (10.0, 10.0))
    if change is None:
        attrs = {}
    elif isinstance(change, str):
        attrs = {"sar_geometry": change}
    else:
        g.update(change)
        if g.get("prf_hz") is None:
            g.pop("prf_hz")
        if g.get("azimuth_time_interval_s") is None:
            g.pop("azimuth_time_interval_s")
        attrs = {"sar_geometry": {k: v for k, v in g.items()}}
    with pytest.raises(GeometryError, match=needle.replace("(", r"\(")):
        geometry_from_attrs(attrs)
    feats, rec = flag_features(_feats([[100.0, 100.0], [600.0, 103.0]], [1e5, 1.0]), attrs)
    assert rec["applied"] is False and needle in rec["reason"]
    assert [f["properties"]["ambiguity_of"] for f in feats] == [None, None]
    assert [f["properties"]["ambiguity_positions_px"] for f in feats] == [None, None]
    assert [f["id"] for f in feats] == [0, 1] and [f["properties"]["id"] for f in feats] == [0, 1]


def test_pixel_spacing_stands_in_for_the_line_time():
    g = sim_geometry((1000, 500), (10.0, 10.0))
    a = geometry_from_attrs({"sar_geometry": g}).ghosts([500.0], [100.0])
    g.pop("azimuth_time_interval_s")
    b = geometry_from_attrs({"sar_geometry": g, "pixel_spacing_m": [10.0, 10.0]}).ghosts([500.0], [100.0])
    np.testing.assert_allclose(a["row"], b["row"], rtol=1e-12)


def test_flag_features_switch_and_ids():
    attrs = {"sar_geometry": sim_geometry((1000, 500), (10.0, 10.0))}
    geom = geometry_from_attrs(attrs)
    g = geom.ghosts([100.0], [100.0], (-1,))
    feats = _feats([[100.0, 100.0], [g["row"][0, 0], g["col"][0, 0]]], [1e5, 1.0])
    feats[0]["id"] = "a"
    out, rec = flag_features([dict(f, properties=dict(f["properties"])) for f in feats], attrs)
    assert rec["applied"] and rec["flagged"] == 1 and rec["reason"] is None
    assert out[1]["properties"]["ambiguity_of"] == "a" and out[1]["properties"]["ambiguity_order"] == -1
    assert out[0]["properties"]["ambiguity_of"] is None and out[1]["id"] == 1
    # each detection's own expected ghosts, in pixels: the ghost sits on its parent's k = -1 place
    pos = {e["order"]: e["centroid_px"] for e in out[0]["properties"]["ambiguity_positions_px"]}
    assert sorted(pos) == sorted(amb.ORDERS)
    np.testing.assert_allclose(pos[-1], out[1]["properties"]["centroid_px"], atol=1e-3)
    out, rec = flag_features(feats, attrs, enabled=False)
    assert not rec["applied"] and "switched off" in rec["reason"]
    assert all(f["properties"]["ambiguity_of"] is None for f in out)


def test_parameters_are_validated_and_defaults_agree():
    from sarship.pipeline.detectors.base import DetectorParams
    from sarship.pipeline.errors import InputError
    from sarship.workers.request import JobRequest

    d = DetectorParams()
    assert (d.ambiguities, d.ambiguity_tol_px, d.ambiguity_min_db) == (True, amb.DEFAULT_TOL_PX, amb.DEFAULT_MIN_DB)
    for k, v in (
        ("ambiguity_tol_px", "-1"),
        ("ambiguity_tol_px", "1e9"),
        ("ambiguity_min_db", "70"),
        ("ambiguity_min_db", "loud"),
        ("ambiguities", "maybe"),
    ):
        with pytest.raises(InputError, match=k):
            JobRequest.from_inputs("ca_cfar", {"scene": "s", k: v})
    p = JobRequest.from_inputs("ca_cfar", {"scene": "s", "ambiguities": "false", "ambiguity_tol_px": "3"})
    assert p.detector_params().ambiguities is False and p.detector_params().ambiguity_tol_px == 3.0


# --------------------------------------------------------------------------------------
# end to end: sarship simulate --ambiguities, sarship detect
# --------------------------------------------------------------------------------------

SIM = ["--shape", "800x512", "--ships", "8", "--seed", "4", "--scr-db", "38", "--spacing", "20", "--looks", "4"]
DETECT = ["--detector", "ca_cfar", "--set", "pfa=1e-6", "--set", "land_mask=none"]


def _cli(*args):
    r = subprocess.run(
        [sys.executable, "-m", "sarship.cli", *map(str, args)], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr
    return r


def _inside(c, box, pad=1.0):
    return box[0] - pad <= c[0] <= box[2] + pad and box[1] - pad <= c[1] <= box[3] + pad


@pytest.fixture(scope="module")
def ghost_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("amb")
    _cli("simulate", d / "s.zarr", *SIM, "--ambiguities")
    _cli("detect", d / "s.zarr", *DETECT, "--out", d / "out")
    return d


def test_simulated_ghosts_flagged_end_to_end(ghost_scene):
    truth = json.loads((ghost_scene / "s.zarr.truth.geojson").read_text())
    dets = json.loads((ghost_scene / "out" / "detections.geojson").read_text())["features"]
    run = json.loads((ghost_scene / "out" / "run.json").read_text())
    ship_det = {}
    for f in dets:
        for t in truth["features"]:
            if _inside(f["properties"]["centroid_px"], t["properties"]["bbox_px"]):
                ship_det.setdefault(t["id"], f)
    checked = 0
    for a in truth["ambiguities"]:
        hits = [f for f in dets if _inside(f["properties"]["centroid_px"], a["bbox_px"])]
        if not hits or a["ambiguity_of"] not in ship_det:
            continue  # a ghost below the sea, or its ship not detected
        for f in hits:
            assert f["properties"]["ambiguity_of"] == ship_det[a["ambiguity_of"]]["id"], (a, f["properties"])
            assert f["properties"]["ambiguity_order"] == a["order"]
            # the parent's expected ghost of that order lies within the default tolerance
            par = dets[f["properties"]["ambiguity_of"]]["properties"]
            want = {e["order"]: e["centroid_px"] for e in par["ambiguity_positions_px"]}[a["order"]]
            assert np.all(np.abs(np.subtract(f["properties"]["centroid_px"], want)) <= amb.DEFAULT_TOL_PX)
            checked += 1
    assert checked >= 4, "the scene should show several detected ghosts of detected ships"
    assert ship_det and all(f["properties"]["ambiguity_of"] is None for f in ship_det.values())
    assert run["ambiguities"]["applied"] and run["ambiguities"]["flagged"] == sum(
        f["properties"]["ambiguity_of"] is not None for f in dets
    )
    # 20 m lines: the first ghosts ~5.0 km = ~251 rows away
    assert 245 < run["ambiguities"]["first_ambiguity_shift"]["rows"][0] < 256
    assert [f["id"] for f in dets] == list(range(len(dets)))


def test_evaluate_ignore_flagged_leaves_out_the_flagged_ghosts(ghost_scene):
    """`sarship evaluate`: by default every detected ghost is a false alarm (the contract's
    rule); with --ignore-flagged the flagged ones that match no ship are left out and counted,
    the hits stay the same."""
    dets = json.loads((ghost_scene / "out" / "detections.geojson").read_text())["features"]
    n_flagged = sum(f["properties"]["ambiguity_of"] is not None for f in dets)
    assert n_flagged >= 4
    args = [
        "evaluate",
        ghost_scene / "out" / "detections.geojson",
        "--truth",
        ghost_scene / "s.zarr.truth.geojson",
        "--json",
    ]
    plain = json.loads(_cli(*args).stdout)
    kept = json.loads(_cli(*args, "--ignore-flagged").stdout)
    assert "n_flagged_ignored" not in plain and kept["n_flagged_ignored"] == n_flagged
    assert kept["n_hit"] == plain["n_hit"] > 0 and kept["n_missed"] == plain["n_missed"]
    assert kept["n_false"] == plain["n_false"] - n_flagged and kept["n_false"] == 0
    assert kept["n_detections"] == plain["n_detections"] - n_flagged
    assert kept["fom"] > plain["fom"]
    text = _cli(*args[:-1], "--ignore-flagged").stdout
    assert f"{n_flagged} flagged ambiguities matching no ship ignored" in text


def test_switched_off_and_bad_geometry(ghost_scene, tmp_path):
    import zarr

    from sarship.workers.jobs import run_detection

    scene = ghost_scene / "s.zarr"
    settings = {"pfa": "1e-6", "land_mask": "none"}
    r = run_detection(scene, "ca_cfar", {**settings, "ambiguities": "false"}, out_dir=tmp_path / "off", progress=False)
    dets = json.loads((tmp_path / "off" / "detections.geojson").read_text())["features"]
    assert r["ambiguities"]["applied"] is False and "switched off" in r["ambiguities"]["reason"]
    assert dets and all(f["properties"]["ambiguity_of"] is None for f in dets)
    # a copy whose geometry is broken: no flags, the reason said, no crash
    bad = tmp_path / "bad.zarr"
    shutil.copytree(scene, bad)
    g = zarr.open_group(str(bad), mode="r+")
    geo = dict(g.attrs["sar_geometry"])
    geo["prf_hz"] = -1.0
    g.attrs["sar_geometry"] = geo
    zarr.consolidate_metadata(str(bad))
    r = run_detection(bad, "ca_cfar", settings, out_dir=tmp_path / "bad", progress=False)
    dets = json.loads((tmp_path / "bad" / "detections.geojson").read_text())["features"]
    assert r["ambiguities"]["applied"] is False and "prf_hz" in r["ambiguities"]["reason"]
    assert dets and all(f["properties"]["ambiguity_of"] is None for f in dets)


def test_no_flags_without_ghosts(tmp_path):
    from sarship.workers.jobs import run_detection

    _cli("simulate", tmp_path / "s.zarr", *SIM)  # the same ships, no --ambiguities
    r = run_detection(
        tmp_path / "s.zarr", "ca_cfar", {"pfa": "1e-6", "land_mask": "none"}, out_dir=tmp_path / "o", progress=False
    )
    dets = json.loads((tmp_path / "o" / "detections.geojson").read_text())["features"]
    assert r["ambiguities"]["applied"] is True and r["ambiguities"]["flagged"] == 0
    assert len(dets) >= 5 and all(f["properties"]["ambiguity_of"] is None for f in dets)
