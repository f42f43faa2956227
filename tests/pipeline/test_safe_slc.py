"""Sentinel-1 IW SLC SAFE ingest (pipeline/readers/safe_slc.py, pipeline/readers/tops.py) on the
real product layout of ../shared/data/real/sentinel1-safe (real annotation, constant pixel
values: VV 2, VH 1 in IW1, VH 1j in IW2; see its README).

Checked: the debursting and deramping maths on hand examples; the full-size IW1 sub-swath
(13509 x 21632 measurement lines, both polarisations) ingested from a zip in a subprocess
whose own peak RSS (VmHWM) stays well below the swath as complex64; its shape, channels,
spacing, times, burst seams and GCPs against the annotation read here with ElementTree; each
sample equal to DN / A exp(-j phi) with A and phi computed here from the XML (calibration
LUT, orbit, Doppler centroid, azimuth FM rate, steering rate); samples outside each burst
line's valid range absent; the folder gives the same samples and attributes as the zip; bad
products and arguments fail with one line, exit 2, nothing left behind.
"""

from __future__ import annotations

import functools
import math
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import tops
from sarship.pipeline.readers.limits import InputLimits

SAFE_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "sentinel1-safe"
SLC = next(iter(sorted(SAFE_DIR.glob("S1B_IW_SLC_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
GRD = next(iter(sorted(SAFE_DIR.glob("S1B_IW_GRDH_*.SAFE"))), None) if SAFE_DIR.is_dir() else None
needs_slc = pytest.mark.skipif(SLC is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
C = 299792458.0


# --------------------------------------------------------------------------------------
# pure maths: no product needed
# --------------------------------------------------------------------------------------


def test_deburst_segments_hand_examples():
    dt = 1.0
    # 20-line bursts 12 lines apart, valid lines 2..17: valid overlap from time 14 (burst 1 line 2)
    # to 17 (burst 0 line 17), seam at 15.5: rows 0-13 (times 2-15) from burst 0, 14-27 from burst 1
    segs, rows, t0 = tops.deburst_segments([0.0, 12.0], [(2, 17), (2, 17)], dt)
    assert t0 == 2.0 and rows == 28
    assert segs == [tops.Segment(0, 0, 14, 2), tops.Segment(1, 14, 28, -10)]
    assert 13 + segs[0].offset == 15 and 14 + segs[1].offset == 4  # times 15 (burst 0) and 16 (12 + 4)
    # bursts 20 lines apart do not overlap: the valid gap (times 18..21) is no burst's
    segs, rows, _ = tops.deburst_segments([0.0, 20.0], [(2, 17), (2, 17)], dt)
    assert segs == [tops.Segment(0, 0, 16, 2), tops.Segment(1, 20, 36, -18)] and rows == 36
    # burst times off the line grid by 0.3 line: the nearest line
    segs, _, _ = tops.deburst_segments([0.0, 12.3], [(2, 17), (2, 17)], dt)
    assert segs[1].offset == -10  # row 14 (time 16) is burst 1's line 3.7 -> 4
    with pytest.raises(ValueError, match="increase"):
        tops.deburst_segments([5.0, 1.0], [(0, 3), (0, 3)], dt)
    with pytest.raises(ValueError, match="valid"):
        tops.valid_lines([-1, -1, -1])
    assert tops.valid_lines([-1, -1, 40, 38, -1]) == (2, 3)


def test_burst_ramp_and_deramp_phase():
    tau = 5.3e-3 + np.arange(5) * 1e-6
    v, fc, psi = 7600.0, 5.405e9, 1.59
    fm, fm_t0 = [-2320.0, 4.5e5, -7.9e7], 5.34e-3
    dc, dc_t0 = [-1.8, 3565.0, -3.3e6], 5.35e-3
    r = tops.burst_ramp(tau, v, fc, psi, fm, fm_t0, dc, dc_t0, first_valid_col=1, lines_per_burst=1500, dt=2e-3)
    ks = 2 * v / (C / fc) * math.radians(psi)
    x = tau - fm_t0
    ka = fm[0] + fm[1] * x + fm[2] * x**2
    np.testing.assert_allclose(r.kt, ka * ks / (ka - ks), rtol=1e-12)
    assert 1000 < r.kt[0] < 3000  # the Doppler centroid rate of IW bursts: ~1.5-2 kHz/s
    y = tau - dc_t0
    fdc = dc[0] + dc[1] * y + dc[2] * y**2
    np.testing.assert_allclose(r.fdc, fdc, rtol=1e-12)
    eta_c = -fdc / ka
    np.testing.assert_allclose(r.eta_ref, eta_c - eta_c[1], rtol=1e-9, atol=1e-15)
    assert r.eta_ref[1] == 0.0
    # the phase's azimuth frequency d(phi)/d(eta) / 2 pi = fdc + kt (eta - eta_ref): the Doppler
    # centroid of the focused burst at that line, which exp(-j phi) removes
    ph = tops.deramp_phase(r, 0, 1500, 0, 5)
    eta = (np.arange(1500) - 750) * 2e-3
    f_inst = np.diff(ph, axis=0) / (2 * np.pi * 2e-3)
    mid = (eta[1:] + eta[:-1]) / 2
    np.testing.assert_allclose(f_inst, fdc + r.kt * (mid[:, None] - r.eta_ref), rtol=1e-9, atol=1e-6)
    rot = tops.rotation(ph)
    assert rot.dtype == np.complex64
    np.testing.assert_allclose(rot, np.exp(-1j * ph), atol=2e-6)


def test_deramping_is_what_npdd_needs():
    """Why the SLC ingest deramps. Sea speckle of an IW burst, oversampled as S-1's is (azimuth
    band 327 of 486 Hz, range 56.5 of 64.3 MHz), at baseband: NPDD's circular variance (the
    feature of every csk detection, eq 19-21, 5) is ~0.7 wherever the window is. The same
    speckle as the product delivers it (times exp(j phi), the IW1 burst's ramp) reads ~0.9-1,
    varying along the burst: the sweep, not the sea. Deramping gives the baseband values back;
    intensity is unchanged throughout."""
    from sarship.pipeline.stats import circular

    tau = 5.343e-3 + np.arange(64) / 6.4345e7
    r = tops.burst_ramp(
        tau,
        7600.0,
        5.405e9,
        1.590368784,
        [-2320.27, 4.5014e5, -7.9186e7],
        5.343e-3,
        [-1.7936, 3565.0, -3.326e6],
        5.351e-3,
        first_valid_col=0,
        lines_per_burst=1501,
        dt=2.0555563e-3,
    )
    rng = np.random.default_rng(2)
    w = rng.standard_normal((1501, 64)) + 1j * rng.standard_normal((1501, 64))
    F = np.fft.fft(w, axis=0)
    F[np.abs(np.fft.fftfreq(1501)) > 0.5 * 327 / 486] = 0
    G = np.fft.fft(np.fft.ifft(F, axis=0), axis=1)
    G[:, np.abs(np.fft.fftfreq(64)) > 0.5 * 56.5 / 64.3] = 0
    sea = np.fft.ifft(G, axis=1)
    ph = tops.deramp_phase(r, 0, 1501, 0, 64)
    delivered = sea * np.exp(1j * ph)
    deramped = delivered * tops.rotation(ph)
    np.testing.assert_allclose(np.abs(delivered), np.abs(sea), rtol=1e-12)

    def spread(z, l0):
        return circular.npdd_spread(circular.npdd(z[l0 : l0 + 100], 3, 1)[2:-2, 2:-2])[0]

    for l0 in range(50, 1450, 200):
        base, ramped, back = spread(sea, l0), spread(delivered, l0), spread(deramped, l0)
        assert 0.6 < base < 0.8 and ramped > base + 0.12, (l0, base, ramped)
        assert back == pytest.approx(base, abs=1e-4)


# --------------------------------------------------------------------------------------
# the annotation, read here with ElementTree (independently of the reader)
# --------------------------------------------------------------------------------------


def _t(s: str) -> np.datetime64:
    return np.datetime64(s.strip(), "ns")


def _sec(a: np.datetime64, b: np.datetime64) -> float:
    return float((a - b) / np.timedelta64(1, "ns")) * 1e-9


@functools.cache
def _annotation(safe: Path, swath: str, pol: str) -> dict:
    path = next((safe / "annotation").glob(f"s1?-{swath}-slc-{pol}-*.xml"))
    r = ET.parse(path).getroot()
    info = r.find(".//imageAnnotation/imageInformation")
    pinfo = r.find(".//generalAnnotation/productInformation")
    st = r.find(".//swathTiming")
    bursts = [
        (
            _t(b.findtext("azimuthTime")),
            np.array(b.findtext("firstValidSample").split(), int),
            np.array(b.findtext("lastValidSample").split(), int),
        )
        for b in st.iter("burst")
    ]

    def records(tag, poly):
        return [
            (_t(e.findtext("azimuthTime")), float(e.findtext("t0")), np.array(e.findtext(poly).split(), float))
            for e in r.iter(tag)
        ]

    cal = next((safe / "annotation" / "calibration").glob(f"calibration-{path.name}"), None)
    return {
        "path": path,
        "root": r,
        "lines": int(info.findtext("numberOfLines")),
        "samples": int(info.findtext("numberOfSamples")),
        "az": float(info.findtext("azimuthPixelSpacing")),
        "rg": float(info.findtext("rangePixelSpacing")),
        "dt": float(info.findtext("azimuthTimeInterval")),
        "tau0": float(info.findtext("slantRangeTime")),
        "fs": float(pinfo.findtext("rangeSamplingRate")),
        "fc": float(pinfo.findtext("radarFrequency")),
        "psi": float(pinfo.findtext("azimuthSteeringRate")),
        "lpb": int(st.findtext("linesPerBurst")),
        "bursts": bursts,
        "dc": records("dcEstimate", "dataDcPolynomial"),
        "fm": records("azimuthFmRate", "azimuthFmRatePolynomial"),
        "orbit": [
            (_t(o.findtext("time")), np.array([float(o.findtext(f"velocity/{a}")) for a in "xyz"]))
            for o in r.iter("orbit")
        ],
        "cal": cal,
    }


def _valid_lines(fv):
    v = np.flatnonzero(fv >= 0)
    return v[0], v[-1]


def _row_source(a: dict, row: int) -> tuple[int, int]:
    """(burst, line) of a debursted row by the midpoint rule, one row at a time."""
    dt, bs = a["dt"], a["bursts"]
    t_first = bs[0][0]
    f0, _ = _valid_lines(bs[0][1])
    T = _sec(t_first, bs[0][0]) + (f0 + row) * dt  # seconds after burst 0's first line
    starts = [_sec(b[0], bs[0][0]) for b in bs]
    cands = []
    for k, (_tb, fv, _) in enumerate(bs):
        f, l = _valid_lines(fv)
        if starts[k] + f * dt - dt / 2 <= T <= starts[k] + l * dt + dt / 2:
            cands.append(k)
    k = cands[0]
    if len(cands) > 1:
        _, l0 = _valid_lines(bs[k][1])
        f1, _ = _valid_lines(bs[k + 1][1])
        cut = (starts[k] + l0 * dt + starts[k + 1] + f1 * dt) / 2
        k = k if T < cut - 1e-9 else k + 1
    return k, int(round((T - starts[k]) / dt))


def _rows(a: dict) -> int:
    bs, dt = a["bursts"], a["dt"]
    f0, _ = _valid_lines(bs[0][1])
    _, ln = _valid_lines(bs[-1][1])
    return int(round(_sec(bs[-1][0], bs[0][0]) / dt + ln - f0)) + 1


@functools.cache
def _lut(path: Path):
    root = ET.parse(path).getroot()
    vecs = list(root.iter("calibrationVector"))
    lines = np.array([int(v.findtext("line")) for v in vecs], float)
    pix = np.array(vecs[0].findtext("pixel").split(), float)
    vals = np.array([np.array(v.findtext("sigmaNought").split(), float) for v in vecs])
    return lines, pix, vals


def _bil(L, P, V, r, c):
    i = int(np.clip(np.searchsorted(L, r, side="right") - 1, 0, len(L) - 2))
    j = int(np.clip(np.searchsorted(P, c, side="right") - 1, 0, len(P) - 2))
    t = min(max((r - L[i]) / (L[i + 1] - L[i]), 0.0), 1.0)
    u = min(max((c - P[j]) / (P[j + 1] - P[j]), 0.0), 1.0)
    return (1 - t) * (1 - u) * V[i, j] + (1 - t) * u * V[i, j + 1] + t * (1 - u) * V[i + 1, j] + t * u * V[i + 1, j + 1]


def _expected(a: dict, dn: complex, row: int, col: int) -> complex:
    """DN / A exp(-j phi) at a debursted pixel, from the XML alone."""
    b, line = _row_source(a, row)
    tb, fv, _ = a["bursts"][b]
    dt, lpb = a["dt"], a["lpb"]
    centre = tb + np.timedelta64(int(round(lpb / 2 * dt * 1e9)), "ns")

    def at_centre(recs):  # coefficients and t0, linear in time between records
        x = np.array([_sec(t, centre) for t, _, _ in recs])
        o = np.argsort(x)
        t0 = np.interp(0.0, x[o], np.array([r[1] for r in recs])[o])
        co = [np.interp(0.0, x[o], np.array([r[2][k] for r in recs])[o]) for k in range(len(recs[0][2]))]
        return t0, co

    ot = np.array([_sec(t, centre) for t, _ in a["orbit"]])
    v = np.linalg.norm([np.interp(0.0, ot, [o[1][k] for o in a["orbit"]]) for k in range(3)])
    fm_t0, fm = at_centre(a["fm"])
    dc_t0, dc = at_centre(a["dc"])

    def tau(c):
        return a["tau0"] + c / a["fs"]

    def ka(c):
        return np.polyval(fm[::-1], tau(c) - fm_t0)

    def fdc(c):
        return np.polyval(dc[::-1], tau(c) - dc_t0)

    ks = 2 * v * a["fc"] / C * math.radians(a["psi"])
    kt = ka(col) * ks / (ka(col) - ks)
    c0 = int(np.median(fv[fv >= 0]))
    eta_ref = -fdc(col) / ka(col) + fdc(c0) / ka(c0)
    d = (line - lpb / 2) * dt - eta_ref
    phi = math.pi * kt * d * d + 2 * math.pi * fdc(col) * d
    A = _bil(*_lut(a["cal"]), b * lpb + line, col) if a["cal"] is not None else 1.0
    return dn / A * np.exp(-1j * phi)


def _check_burst_seams(bursts: list[dict]) -> None:
    """The scene's bursts join at the overlap midpoints the annotation gives (rows of IW1)."""
    a = _annotation(SLC, "iw1", "vv")
    assert [b["burst"] for b in bursts] == list(range(9))
    assert bursts[0]["rows"][0] == 0 and bursts[-1]["rows"][1] == _rows(a)
    for prev, b in zip(bursts, bursts[1:]):
        r = b["rows"][0]
        assert prev["rows"][1] == r
        assert _row_source(a, r - 1)[0] == b["burst"] - 1 and _row_source(a, r)[0] == b["burst"]
        assert b["measurement_lines"][0] == b["burst"] * a["lpb"] + _row_source(a, r)[1]


def _check_samples(read) -> None:
    """Each sample = DN / A exp(-j phi) (see test_samples_are_dn_over_a_deramped); ``read(pol,
    r, c0, c1)`` gives row ``r``, columns ``c0:c1`` of polarisation ``pol``."""
    import tifffile

    for pol in ("vv", "vh"):
        a = _annotation(SLC, "iw1", pol)
        with tifffile.TiffFile(next((SLC / "measurement").glob(f"*-iw1-slc-{pol}-*.tiff"))) as t:
            page = t.pages[0]  # the sample's constant, from the first strip (not the 2.3 GB band)
            t.filehandle.seek(page.dataoffsets[0])
            dn = complex(page.decode(t.filehandle.read(page.databytecounts[0]), 0)[0].ravel()[0])
        assert dn == {"vv": 2, "vh": 1}[pol]
        for r, c in [(0, 600), (700, 10000), (1402, 20900), (1403, 3000), (6000, 15000), (12198, 20000), (12198, 600)]:
            want = _expected(a, dn, r, c)
            got = complex(read(pol, r, c, c + 1)[0])
            assert abs(got - want) <= 2e-5 * abs(want), (pol, r, c, got, want)


def _check_invalid_edges(read_row) -> None:
    """Outside a burst line's valid samples the scene has no data (NaN), inside it has."""
    a = _annotation(SLC, "iw1", "vv")
    for r in (0, 1402, 1403, 5000, 12198):
        b, line = _row_source(a, r)
        fv, lv = a["bursts"][b][1][line], a["bursts"][b][2][line]
        assert fv >= 0
        row = read_row(r)
        assert np.isnan(row[:fv]).all() and np.isnan(row[lv + 1 :]).all()
        assert np.isfinite(row[fv : lv + 1]).all()


@needs_slc
def test_iw1_source_seams_samples_and_edges():
    """The default run's check of the SLC reader on the real product without the full-size
    ingest (TestIW1, slow: 3.4 GB written): the IW1 source read from the zip has the
    annotation's shape, channels and spacing, its bursts join at the overlap midpoints, its
    samples are DN / A exp(-j phi) and its invalid burst edges are absent. TestIW1 checks that
    the ingested store holds exactly what this source reads."""
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    from sarship.pipeline.readers.entry import _open_source

    a = _annotation(SLC, "iw1", "vv")
    src = _open_source(SLC, swath="IW1", limits=InputLimits(max_ratio=1e5))
    try:
        pols = src.meta["pols"]
        assert pols == ["vv", "vh"] and src.shape == (_rows(a), a["samples"]) == (12199, 21632)
        assert src.meta["pixel_spacing_m"] == [a["az"], a["rg"]]
        _check_burst_seams(src.meta["extra_attrs"]["bursts"])
        _check_samples(lambda pol, r, c0, c1: src.read(r, r + 1, c0, c1)[0, :, pols.index(pol)])
        _check_invalid_edges(lambda r: src.read(r, r + 1, 0, src.shape[1])[0, :, 0])
    finally:
        src.close()


# --------------------------------------------------------------------------------------
# the full-size IW1 sub-swath, ingested once from a zip in a fresh process
# --------------------------------------------------------------------------------------


def _zip(safe: Path, out: Path) -> Path:
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:  # ~1 MB: the TIFFs are compressed
        for f in sorted(safe.rglob("*")):
            if f.is_file():
                zf.write(f, f"{safe.name}/{f.relative_to(safe)}")
    return out


@pytest.fixture(scope="module")
def iw1(tmp_path_factory):
    """IW1 of the SLC sample, ingested from its zip: (store path, peak RSS bytes, zip path)."""
    if SLC is None:
        pytest.skip(f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
    if not Path("/proc/self/status").is_file():
        pytest.skip("peak RSS is read from /proc/self/status (Linux)")
    pytest.importorskip("xarray_sentinel", reason="xarray-sentinel not installed (pip install 'sarship[safe]')")
    d = tmp_path_factory.mktemp("slc")
    z = _zip(SLC, d / (SLC.stem + ".zip"))
    out = d / "iw1.zarr"
    # VmHWM: this process's own high-water mark (ru_maxrss would carry the pytest worker's over)
    code = (
        "import sys; from sarship.pipeline.readers import ingest; "
        "from sarship.pipeline.readers import InputLimits; "
        "ingest([sys.argv[1]], sys.argv[2], swath='iw1', limits=InputLimits(max_ratio=1e5)); "
        "print(next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmHWM')))"
    )
    r = subprocess.run([sys.executable, "-c", code, str(z), str(out)], capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr
    yield out, int(r.stdout.split()[-1]), z
    shutil.rmtree(out, ignore_errors=True)  # 3.4 GB: the constant samples, deramped, do not compress


@needs_slc
@pytest.mark.slow  # the full-size ingest writes 3.4 GB: test_iw1_source_seams_samples_and_edges is its sibling
class TestIW1:
    def test_shape_channels_spacing_times(self, iw1):
        from sarship.pipeline.scene import open_scene

        sc = open_scene(iw1[0])
        a = _annotation(SLC, "iw1", "vv")
        assert a["lines"] == 13509 and a["samples"] == 21632 and len(a["bursts"]) == 9
        assert sc.shape == (_rows(a), a["samples"]) == (12199, 21632)
        assert sc.kind == "slc" and set(sc.variables) == {"vv", "vh"}
        at = sc.attrs
        assert at["channels"] == ["vv", "vh"] and at["polarisations"] == ["vv", "vh"]
        assert all(np.dtype(sc.array(v).dtype) == np.complex64 for v in ("vv", "vh"))
        assert at["pixel_spacing_m"] == [a["az"], a["rg"]]
        assert at["looks"] == 1.0 and at["swath"] == "IW1" and at["mode"] == "IW" and at["product_type"] == "SLC"
        man = (SLC / "manifest.safe").read_text()
        start = man.split("<safe:startTime>")[1].split("<")[0]
        stop = man.split("<safe:stopTime>")[1].split("<")[0]
        assert at["acquisition_start"] == at["acquired"] == start and at["acquisition_stop"] == stop
        f0, _ = _valid_lines(a["bursts"][0][1])
        first = a["bursts"][0][0] + np.timedelta64(int(round(f0 * a["dt"] * 1e9)), "ns")
        assert abs(_sec(np.datetime64(at["swath_first_line_time"], "ns"), first)) < 1e-6
        span = np.timedelta64(int(round((sc.shape[0] - 1) * a["dt"] * 1e9)), "ns")
        last = np.datetime64(at["swath_first_line_time"], "ns") + span
        assert abs(_sec(np.datetime64(at["swath_last_line_time"], "ns"), last)) < 1e-6
        assert at["calibration"].startswith("sigma0") and "deramped" in at["slc_phase"]
        assert at["product"] == SLC.name and at["sensor"] == "SENTINEL-1B"
        prf = float(a["root"].findtext(".//downlinkInformation/prf"))
        g = at["sar_geometry"]  # the azimuth-ambiguity geometry (pipeline/readers/safe_geometry.py)
        assert g["prf_hz"] == pytest.approx(prf) and g["shape"] == list(sc.shape), g

    def test_burst_seams_at_the_overlap_midpoints(self, iw1):
        from sarship.pipeline.scene import open_scene

        _check_burst_seams(open_scene(iw1[0]).attrs["bursts"])

    def test_gcps_match_the_geolocation_grid(self, iw1):
        from sarship.pipeline.scene import open_scene

        sc = open_scene(iw1[0])
        a = _annotation(SLC, "iw1", "vv")
        t_first = np.datetime64(sc.attrs["swath_first_line_time"], "ns")
        pts = [
            (
                _t(p.findtext("azimuthTime")),
                int(p.findtext("line")),
                int(p.findtext("pixel")),
                float(p.findtext("latitude")),
                float(p.findtext("longitude")),
                float(p.findtext("incidenceAngle")),
            )
            for p in a["root"].iter("geolocationGridPoint")
        ]
        gcps = sc.attrs["gcps"]
        assert len(gcps) == len(pts) == 210
        lpb, bs = a["lpb"], a["bursts"]
        for g, (t, line, pix, lat, lon, inc) in zip(gcps, pts):
            # the row at the azimuth time of the point's measurement line (burst start + line
            # interval), so each grid line stays one row; the point's own azimuth time agrees
            # to a fraction of a line (it varies by up to 0.25 ms along range)
            b = min(line // lpb, len(bs) - 1)
            line_time = _sec(bs[b][0], t_first) + (line - b * lpb) * a["dt"]
            # (+ 1/2: the centre of the indexed pixel, pixel-is-area coordinates)
            assert g["row"] == pytest.approx(line_time / a["dt"] + 0.5, abs=1e-3)  # (times kept to 1 us)
            assert g["row"] == pytest.approx(_sec(t, t_first) / a["dt"] + 0.5, abs=0.2)
            assert g["col"] == pix + 0.5 and (g["y"], g["x"]) == pytest.approx((lat, lon), abs=1e-9)
            assert g["incidence"] == pytest.approx(inc, abs=1e-9)

    def test_samples_are_dn_over_a_deramped(self, iw1):
        """Each sample = DN / A exp(-j phi): A bilinear from the calibration XML at the
        measurement line, phi the TOPS deramping function from the annotation's orbit,
        Doppler centroid, FM rate and steering rate, all computed here."""
        from sarship.pipeline.scene import open_scene

        sc = open_scene(iw1[0])
        _check_samples(lambda pol, r, c0, c1: np.asarray(sc.array(pol)[r, c0:c1]))

    def test_invalid_burst_edges_are_absent(self, iw1):
        from sarship.pipeline.scene import open_scene

        v = open_scene(iw1[0]).array("vv")
        _check_invalid_edges(lambda r: np.asarray(v[r, :]))

    def test_peak_memory_bounded(self, iw1):
        from sarship.pipeline.scene import open_scene

        h, w = open_scene(iw1[0]).shape
        full = h * w * 8  # one polarisation of the swath as complex64 (2.1 GB; the scene holds two)
        print(f"IW1 ingest from the zip: peak RSS {iw1[1] / 2**20:.0f} MiB; one polarisation {full / 2**20:.0f} MiB")
        assert iw1[1] < 0.4 * full, f"peak RSS {iw1[1] / 2**20:.0f} MiB vs swath {full / 2**20:.0f} MiB"

    def test_folder_gives_what_the_zip_gave(self, iw1):
        """The folder's source against the zip's store: the same attributes (bar ``source``)
        and bit-identical samples on windows across a burst seam and the corners (a second
        full-size ingest would double this file's time)."""
        from sarship.pipeline.readers.entry import _open_source
        from sarship.pipeline.readers.plan import _plan
        from sarship.pipeline.scene import open_scene

        sc = open_scene(iw1[0])
        src = _open_source(SLC, swath="IW1", limits=InputLimits(max_ratio=1e5))
        try:
            assert src.shape == sc.shape
            plan = _plan([src], "auto", None, None)
            assert plan.kind == "slc" and set(plan.variables) == {"vv", "vh"}
            for k, want in src.meta["extra_attrs"].items():
                assert sc.attrs[k] == want, k
            for k in ("pixel_spacing_m", "gcps", "acquired", "product", "sensor", "looks"):
                assert sc.attrs[k] == src.meta[k], k
            H, W = sc.shape
            for r0, c0 in [(1300, 500), (0, 0), (H - 200, W - 300), (6000, 10000)]:
                r1, c1 = min(r0 + 200, H), min(c0 + 300, W)
                got = src.read(r0, r1, c0, c1)
                for k, pol in enumerate(src.meta["pols"]):
                    np.testing.assert_array_equal(got[:, :, k], sc.array(pol)[r0:r1, c0:c1])
        finally:
            src.close()


# --------------------------------------------------------------------------------------
# another sub-swath; errors: one line, exit 2, nothing left behind
# --------------------------------------------------------------------------------------


@needs_slc
def test_iw2_is_its_own_scene():
    """IW2 has only VH (1j): one complex channel of its own size, |z| = 1 / A."""
    pytest.importorskip("xarray_sentinel")
    from sarship.pipeline.readers.entry import _open_source

    a = _annotation(SLC, "iw2", "vh")
    src = _open_source(SLC, swath="iw2", limits=InputLimits(max_ratio=1e5))
    try:
        assert src.meta["pols"] == ["vh"] and src.shape == (_rows(a), a["samples"])
        assert src.meta["extra_attrs"]["swath"] == "IW2" and src.meta["pixel_spacing_m"] == [a["az"], a["rg"]]
        for r, c in [(10, 5000), (3000, 20000)]:
            got = complex(src.read(r, r + 1, c, c + 1)[0, 0, 0])
            want = _expected(a, 1j, r, c)
            assert abs(got - want) <= 2e-5 * abs(want)
    finally:
        src.close()


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "sarship.cli", *map(str, args)], capture_output=True, text=True, timeout=120
    )


@needs_slc
def test_swath_missing_or_unknown_fails_one_line(tmp_path):
    pytest.importorskip("xarray_sentinel")
    from sarship.pipeline.readers import ingest

    r = _cli("ingest", SLC, "--out", tmp_path / "o.zarr")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "IW1, IW2" in r.stderr and "--swath" in r.stderr
    with pytest.raises(InputError, match=r"--swath IW3: the product has no such sub-swath \(it has IW1, IW2\)"):
        ingest([SLC], tmp_path / "o.zarr", swath="IW3")
    with pytest.raises(InputError, match="--kind intensity does not apply"):
        ingest([SLC], tmp_path / "o.zarr", swath="IW1", kind="intensity")
    if GRD is not None:
        with pytest.raises(InputError, match="--swath applies to Sentinel-1 SLC products; this is a GRD"):
            ingest([GRD], tmp_path / "o.zarr", swath="IW1")
    npy = tmp_path / "x.npy"
    np.save(npy, np.ones((8, 8), np.complex64))
    with pytest.raises(InputError, match="--swath applies to Sentinel-1 SLC products only"):
        ingest([npy], tmp_path / "o.zarr", swath="IW1")
    assert not (tmp_path / "o.zarr").exists()


def _copy(src: Path, dst: Path, ignore=None) -> None:
    """A writable copy of a (read-only) sample product."""
    shutil.copytree(src, dst, ignore=ignore, copy_function=shutil.copyfile)
    for d in [dst, *[q for q in dst.rglob("*") if q.is_dir()]]:
        d.chmod(0o755)


@needs_slc
def test_missing_annotation_and_truncated_zip_fail_one_line(tmp_path):
    pytest.importorskip("xarray_sentinel")
    from sarship.pipeline.readers import ingest

    bad = tmp_path / SLC.name
    _copy(SLC, bad)
    ann = next((bad / "annotation").glob("s1?-iw1-slc-vh-*.xml"))
    ann.unlink()
    with pytest.raises(InputError, match=f"no annotation annotation/{ann.name} for the IW1 VH measurement") as e:
        ingest([bad], tmp_path / "o.zarr", swath="IW1")
    assert "\n" not in str(e.value)
    ew = tmp_path / "ew" / SLC.name  # the same layout declared as an EW product: not TOPS IW
    _copy(SLC, ew, ignore=shutil.ignore_patterns("*.tiff"))
    (ew / "measurement" / "s1b-iw1-slc-vv-x.tiff").write_bytes(b"II*\x00")
    man = ew / "manifest.safe"
    man.write_text(man.read_text().replace("<s1sarl1:mode>IW</s1sarl1:mode>", "<s1sarl1:mode>EW</s1sarl1:mode>"))
    with pytest.raises(InputError, match="a Sentinel-1 EW SLC product; only IW"):
        ingest([ew], tmp_path / "o.zarr", swath="IW1")
    z = _zip(SLC, tmp_path / "full.zip")
    cut = tmp_path / (SLC.stem + ".zip")
    cut.write_bytes(z.read_bytes()[: z.stat().st_size // 2])  # a download cut half-way
    r = _cli("ingest", cut, "--swath", "IW1", "--out", tmp_path / "o.zarr")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "zip" in r.stderr, r.stderr
    assert not (tmp_path / "o.zarr").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".o.zarr")]  # no temporary sibling either


# --------------------------------------------------------------------------------------
# the service inbox takes a SAFE .zip as sarship ingest does
# --------------------------------------------------------------------------------------


def test_a_safe_zip_is_an_inbox_pass(tmp_path):
    from sarship.service.inbox_files import list_passes

    for name in ("S1B_IW_GRDH_X.zip", "S1B.ZIP", "half.zip.part", ".hidden.zip"):
        (tmp_path / name).write_bytes(b"x")
    assert {p.name for p in list_passes(tmp_path)} == {"S1B_IW_GRDH_X.zip", "S1B.ZIP"}


def _inbox_server(tmp_path):
    import json

    from svc import Server, free_port

    data, inbox = tmp_path / "data", tmp_path / "inbox"
    data.mkdir()
    inbox.mkdir()
    srv = Server(
        data,
        free_port(),
        SARSHIP_INBOX=json.dumps([str(inbox)]),
        SARSHIP_INBOX_INTERVAL_S="0.2",
        SARSHIP_INBOX_SETTLE_S="0.2",  # the zips arrive by rename: complete at once
        SARSHIP_MAX_RATIO="1e5",
    ).start()  # the constant-pixel samples: ~53000:1 zipped
    return srv, data, inbox


@needs_slc
def test_inbox_quarantines_a_multi_swath_slc_zip(tmp_path):
    """A real ``sarship serve`` with an inbox (no detectors): the SLC zip, whose sub-swath the
    inbox cannot choose, is quarantined with the one-line reason (the GRD zip ingested in full
    beside it: test_inbox_ingests_a_grd_zip_and_quarantines_a_multi_swath_slc_zip, slow)."""
    pytest.importorskip("xarray_sentinel")
    from svc import wait_pass

    slc = _zip(SLC, tmp_path / (SLC.stem + ".zip"))
    srv, data, inbox = _inbox_server(tmp_path)
    try:
        slc.rename(inbox / slc.name)
        q = wait_pass(srv.url, slc.name, ("quarantined", "failed", "ingested", "submitted"), timeout=120)
        assert q["status"] == "quarantined" and "IW1, IW2" in q["reason"] and "--swath" in q["reason"], q
        assert (data / "quarantine" / slc.name).is_file() and not (inbox / slc.name).exists()
    finally:
        srv.stop()


@pytest.mark.slow  # the full-size GRD (16685 x 25788) through the service's capped child
@pytest.mark.skipif(SLC is None or GRD is None, reason=f"Sentinel-1 SAFE samples not found at {SAFE_DIR}")
def test_inbox_ingests_a_grd_zip_and_quarantines_a_multi_swath_slc_zip(tmp_path):
    """A real ``sarship serve`` with an inbox (no detectors): the GRD zip becomes the scene
    ``sarship ingest`` makes of it (full size, in the service's capped child process); the SLC
    zip, whose sub-swath the inbox cannot choose, is quarantined with the one-line reason."""
    pytest.importorskip("xarray_sentinel")
    httpx = pytest.importorskip("httpx")

    from svc import wait_job, wait_pass

    from sarship.pipeline.scene import open_scene

    grd = _zip(GRD, tmp_path / (GRD.stem + ".zip"))
    slc = _zip(SLC, tmp_path / (SLC.stem + ".zip"))
    srv, data, inbox = _inbox_server(tmp_path)
    try:
        grd.rename(inbox / grd.name)
        slc.rename(inbox / slc.name)
        p = wait_pass(srv.url, grd.name, ("ingested", "submitted", "quarantined", "failed"), timeout=240)
        assert p["status"] in ("ingested", "submitted"), p
        assert wait_job(srv.url, p["ingestJob"])["status"] == "successful"
        sc = open_scene(data / "scenes" / f"{p['sceneID']}.zarr")
        assert sc.shape == (16685, 25788) and sc.kind == "intensity" and sc.attrs["product"] == GRD.name
        assert sc.attrs["mode"] == "IW" and len(sc.attrs["gcps"]) == 210
        assert httpx.get(f"{srv.url}/scenes/{p['sceneID']}").json()["status"] == "ready"
        q = wait_pass(srv.url, slc.name, ("quarantined", "failed", "ingested", "submitted"), timeout=120)
        assert q["status"] == "quarantined" and "IW1, IW2" in q["reason"] and "--swath" in q["reason"], q
        assert (data / "quarantine" / slc.name).is_file() and not (inbox / slc.name).exists()
    finally:
        srv.stop()
