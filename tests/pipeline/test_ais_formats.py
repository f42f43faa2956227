"""Reading AIS files (pipeline/ais/formats.py): every format written by the test from one set of
synthetic vessel tracks (NMEA encoded by pyais's encoder), read back and compared with the truth;
the window; bad lines counted; files that are no AIS refused; the limits; compression."""

from __future__ import annotations

import calendar
import gzip
import math
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zstandard
from pyais.encode import encode_dict
from pyais.messages import TagBlock

from sarship.pipeline.ais.formats import read_ais
from sarship.pipeline.ais.reports import Reports, VesselInfo, Window
from sarship.pipeline.errors import InputError

T_START = calendar.timegm((2023, 2, 27, 23, 0, 0))  # the tracks cross midnight
SPAN_S = 7200
N_REPORTS = 14


@dataclass
class Vessel:
    mmsi: int
    kind: str  # "A" (1/2/3 + 5), "B" (18 + 24), "B19" (19), "LR" (27, no static)
    name: str | None
    ship_type: int | None
    dims: tuple[int, int, int, int]  # to bow, stern, port, starboard
    lon0: float
    lat0: float

    @property
    def length(self) -> float | None:
        return float(self.dims[0] + self.dims[1]) or None

    @property
    def width(self) -> float | None:
        return float(self.dims[2] + self.dims[3]) or None


VESSELS = [
    Vessel(219000001, "A", "AURORA", 70, (100, 20, 10, 8), 11.0, 56.0),
    Vessel(219000002, "A", "BALTIC STAR", 80, (150, 30, 12, 13), 11.5, 56.2),
    Vessel(257000003, "B", "SEA BREEZE", 37, (8, 4, 2, 2), 10.5, 55.8),
    Vessel(265000004, "B19", "FISKER", 30, (15, 5, 3, 3), 12.0, 57.0),
    Vessel(538000005, "LR", None, None, (0, 0, 0, 0), -20.0, -30.0),
    Vessel(244000006, "A", "NO DIMENSIONS", 60, (0, 0, 0, 0), 4.0, 52.0),
    Vessel(412000007, "A", "DATELINE", 70, (200, 40, 20, 20), 179.95, 10.0),
]
DMA_TYPE_NAMES = {70: "Cargo", 80: "Tanker", 37: "Pleasure", 30: "Fishing", 60: "Passenger"}


def _truth() -> Reports:
    """Every vessel's reports: times to the second, positions on the AIS grid (1/10000 minute;
    1/10 minute for message 27), SOG, COG, heading at their resolutions, some not available."""
    rng = np.random.default_rng(33)
    cols: dict[str, list] = {k: [] for k in ("mmsi", "t", "lon", "lat", "sog", "cog", "hdg")}
    for v in VESSELS:
        t = T_START + np.sort(rng.choice(SPAN_S, N_REPORTS, replace=False)).astype(float)
        step = 1 / 600 if v.kind == "LR" else 1 / 600_000
        lon = v.lon0 + 0.0004 * (t - T_START) / 60
        lon = (lon + 180) % 360 - 180
        lat = v.lat0 + rng.normal(0, 0.01, N_REPORTS)
        if v.kind == "LR":
            sog = rng.integers(0, 30, N_REPORTS).astype(float)
            cog = rng.integers(0, 360, N_REPORTS).astype(float)
            hdg = np.full(N_REPORTS, np.nan)
        else:
            sog = np.round(rng.uniform(0, 25, N_REPORTS), 1)
            cog = np.round(rng.uniform(0, 359.9, N_REPORTS), 1)
            hdg = rng.integers(0, 360, N_REPORTS).astype(float)
            hdg[rng.random(N_REPORTS) < 0.3] = np.nan
        sog[rng.random(N_REPORTS) < 0.15] = np.nan
        cog[rng.random(N_REPORTS) < 0.15] = np.nan
        for k, x in zip(
            cols,
            (np.full(N_REPORTS, v.mmsi), t, np.round(lon / step) * step, np.round(lat / step) * step, sog, cog, hdg),
        ):
            cols[k].extend(np.asarray(x).tolist())
    f32 = np.float32
    r = Reports(
        np.array(cols["mmsi"], np.int64),
        np.array(cols["t"]),
        np.array(cols["lon"]),
        np.array(cols["lat"]),
        np.array(cols["sog"], f32),
        np.array(cols["cog"], f32),
        np.array(cols["hdg"], f32),
    )
    return r.sorted()


TRUTH = _truth()
BY_MMSI = {v.mmsi: v for v in VESSELS}


def _rows():
    """The truth's rows in time order (as receivers log them)."""
    for i in np.argsort(TRUTH.t, kind="stable").tolist():
        yield (
            int(TRUTH.mmsi[i]),
            float(TRUTH.t[i]),
            float(TRUTH.lon[i]),
            float(TRUTH.lat[i]),
            float(TRUTH.sog_kn[i]),
            float(TRUTH.cog_deg[i]),
            float(TRUTH.heading_deg[i]),
        )


def _iso(t: float, sep: str = "T") -> str:
    return time.strftime(f"%Y-%m-%d{sep}%H:%M:%S", time.gmtime(t))


def _fmt(x: float, na: str = "", digits: int = 1) -> str:
    return na if math.isnan(x) else f"{x:.{digits}f}"


# ---- NMEA ------------------------------------------------------------------------------------------


def _position_sentences(mmsi, lon, lat, sog, cog, hdg, k) -> list[str]:
    v = BY_MMSI[mmsi]
    na_sog, na_cog = (63, 511) if v.kind == "LR" else (102.3, 360)
    msg = {
        "mmsi": mmsi,
        "lon": lon,
        "lat": lat,
        # pyais's encoder truncates speed x 10 and course x 10: aim at the middle of the step
        "speed": na_sog if math.isnan(sog) else sog + (0 if v.kind == "LR" else 0.04),
        "course": na_cog if math.isnan(cog) else cog + (0 if v.kind == "LR" else 0.04),
    }
    if v.kind != "LR":
        msg["heading"] = 511 if math.isnan(hdg) else int(hdg)
    if v.kind == "A":
        msg["type"] = 1 + k % 3
    elif v.kind == "B":
        msg["type"] = 18
    elif v.kind == "B19":
        msg.update(type=19, shipname=v.name, ship_type=v.ship_type)
        msg.update(zip(("to_bow", "to_stern", "to_port", "to_starboard"), v.dims))
    else:
        msg["type"] = 27
    return encode_dict(msg, talker_id="AI", sentence_type="VDM", radio_channel="AB"[k % 2])


def _static_sentences() -> list[list[str]]:
    """Static messages: type 5 (two sentences, sequence ids 1..) and 24 A and B."""
    out = []
    seq = 0
    for v in VESSELS:
        dims = dict(zip(("to_bow", "to_stern", "to_port", "to_starboard"), v.dims))
        if v.kind == "A":
            seq = seq % 9 + 1
            msg = {"type": 5, "mmsi": v.mmsi, "shipname": v.name, "ship_type": v.ship_type, **dims}
            out.append(encode_dict(msg, talker_id="AI", sentence_type="VDM", seq_id=seq))
        elif v.kind == "B":
            out.append(encode_dict({"type": 24, "mmsi": v.mmsi, "partno": 0, "shipname": v.name}, sentence_type="VDM"))
            msg = {"type": 24, "mmsi": v.mmsi, "partno": 1, "ship_type": v.ship_type, **dims}
            out.append(encode_dict(msg, sentence_type="VDM"))
    return out


def _interleave(groups: list[list[str]]) -> list[list[str]]:
    """Multi-sentence messages taken in pairs, their sentences interleaved (A1 B1 A2 B2)."""
    out = []
    for i in range(0, len(groups), 2):
        pair = groups[i : i + 2]
        mixed = [s for parts in zip(*pair) for s in parts] if len(pair) == 2 and all(len(p) == 2 for p in pair) else []
        out.extend([mixed] if mixed else pair)
    return out


def _tag(t: float, ms: bool) -> str:
    stamp = int(t * 1000) if ms else int(t)
    return "\\" + TagBlock.create_str(source_station="rx1", receiver_timestamp=stamp) + "\\"


def write_nmea_tagged(path: Path) -> None:
    """NMEA 4.0 tag blocks (``c:`` in seconds, every third in milliseconds); static messages
    before the tracks (their time outside any window), multi-sentence ones interleaved, only the
    first sentence of each tagged."""
    lines = []
    for group in _interleave(_static_sentences()):
        for s in group:
            first = s.split(",")[2] == "1"  # the first sentence of its message
            lines.append((_tag(T_START - 600, False) if first else "") + s)
    for k, (mmsi, t, lon, lat, sog, cog, hdg) in enumerate(_rows()):
        for s in _position_sentences(mmsi, lon, lat, sog, cog, hdg, k):
            lines.append(_tag(t, k % 3 == 0) + s)
    path.write_text("\n".join(lines) + "\n")


def write_nmea_logged(path: Path) -> None:
    """A logger's timestamps before the sentences (ISO 8601 and POSIX seconds), or after the
    checksum (USCG NAIS form); Windows line ends."""
    lines = []
    for group in _static_sentences():
        lines.extend(f"{_iso(T_START - 600)}Z {s}" for s in group)
    for k, (mmsi, t, lon, lat, sog, cog, hdg) in enumerate(_rows()):
        for s in _position_sentences(mmsi, lon, lat, sog, cog, hdg, k):
            form = k % 3
            lines.append(
                f"{_iso(t)}.000Z,{s}" if form == 0 else f"{t:.3f} {s}" if form == 1 else f"{s},b003669710,{int(t)}"
            )
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())


# ---- CSV -------------------------------------------------------------------------------------------


def _static_cols(mmsi: int) -> tuple[str, str, str, str]:
    v = BY_MMSI[mmsi]
    return (
        v.name or "",
        "" if v.ship_type is None else str(v.ship_type),
        str(v.dims[0] + v.dims[1]),
        str(v.dims[2] + v.dims[3]),
    )


def write_marinecadastre(path: Path) -> None:
    """2015-2023: LAT before LON, ``T`` in the time, the AIS "not available" values; sorted by
    vessel, as some of those files are."""
    head = "MMSI,BaseDateTime,LAT,LON,SOG,COG,Heading,VesselName,IMO,CallSign,VesselType,Status,Length,Width,Draft,Cargo,TransceiverClass"
    out = [head]
    for mmsi, t, lon, lat, sog, cog, hdg in sorted(_rows()):
        name, typ, length, width = _static_cols(mmsi)
        out.append(
            f"{mmsi},{_iso(t)},{lat:.6f},{lon:.6f},{_fmt(sog, '102.3')},{_fmt(cog, '360.0')},{_fmt(hdg, '511.0')},"
            f"{name},IMO9627980,VRME7,{typ},0,{length},{width},3.5,70,A"
        )
    path.write_text("\n".join(out) + "\n")


def write_marinecadastre_2024(path: Path) -> None:
    """2024+: snake_case, longitude before latitude, a space in the time, "not available" as
    empty fields, in a zstd stream of two frames."""
    head = (
        "mmsi,base_date_time,longitude,latitude,sog,cog,heading,vessel_name,imo,call_sign,vessel_type,status,"
        "length,width,draft,cargo,transceiver"
    )
    out = [head]
    for mmsi, t, lon, lat, sog, cog, hdg in _rows():
        name, typ, length, width = _static_cols(mmsi)
        out.append(
            f"{mmsi},{_iso(t, ' ')},{lon:.6f},{lat:.6f},{_fmt(sog)},{_fmt(cog)},{_fmt(hdg, digits=0)},"
            f'"{name}",,,{typ},0,{length},{width},,,A'
        )
    text = ("\n".join(out) + "\n").encode()
    half = len(text) // 2
    c = zstandard.ZstdCompressor()
    path.write_bytes(c.compress(text[:half]) + c.compress(text[half:]))


DMA_HEAD = (
    "# Timestamp,Type of mobile,MMSI,Latitude,Longitude,Navigational status,ROT,SOG,COG,Heading,IMO,Callsign,"
    "Name,Ship type,Cargo type,Width,Length,Type of position fixing device,Draught,Destination,ETA,"
    "Data source type,A,B,C,D"
)


def _dma_row(mmsi, t, lon, lat, sog, cog, hdg, mobile="Class A") -> str:
    v = BY_MMSI.get(mmsi)
    name = (v.name or "") if v else ""
    typ = DMA_TYPE_NAMES.get(v.ship_type, "Undefined") if v and v.ship_type else "Undefined"
    width, length = (str(v.dims[2] + v.dims[3]), str(v.dims[0] + v.dims[1])) if v else ("", "")
    stamp = time.strftime("%d/%m/%Y %H:%M:%S", time.gmtime(t))
    return (
        f"{stamp},{mobile},{mmsi},{lat:.6f},{lon:.6f},Under way using engine,0.0,{_fmt(sog)},{_fmt(cog)},"
        f"{_fmt(hdg, digits=0)},Unknown,OX1234,{name},{typ},,{width},{length},GPS,,AARHUS,,AIS,,,,"
    )


def write_dma(path: Path, extra: list[str] = ()) -> None:
    """The Danish Maritime Authority's CSV: ``DD/MM/YYYY`` times, ship types as names."""
    out = [DMA_HEAD] + [_dma_row(*r) for r in _rows()] + list(extra)
    path.write_text("\n".join(out) + "\n")


def write_dma_zip(path: Path) -> None:
    """The DMA's CSV as the DMA distributes it: in a zip archive."""
    write_dma(path.with_suffix(".csv"))
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.write(path.with_suffix(".csv"), "aisdk-2023-02-27.csv")
    path.with_suffix(".csv").unlink()


def write_plain(path: Path) -> None:
    """The plain CSV with every column, POSIX seconds, gzip-compressed."""
    out = ["mmsi,time,lon,lat,sog,cog,heading,name,length_m,width_m"]
    for mmsi, t, lon, lat, sog, cog, hdg in _rows():
        name, _, length, width = _static_cols(mmsi)
        out.append(
            f"{mmsi},{int(t)},{lon:.6f},{lat:.6f},{_fmt(sog)},{_fmt(cog)},{_fmt(hdg, digits=0)},{name},{length},{width}"
        )
    path.write_bytes(gzip.compress(("\n".join(out) + "\n").encode()))


def write_plain_short(path: Path) -> None:
    """The plain CSV's six required columns, ISO 8601 times with a zone."""
    out = ["mmsi,time,lon,lat,sog,cog"]
    for mmsi, t, lon, lat, sog, cog, _ in _rows():
        out.append(f"{mmsi},{_iso(t)}+00:00,{lon:.6f},{lat:.6f},{_fmt(sog)},{_fmt(cog)}")
    path.write_text("\n".join(out) + "\n")


WRITERS = {  # (writer, has headings, static fields: all, all but the ship type, none)
    "nmea_tagged.nmea": (write_nmea_tagged, True, "all"),
    "nmea_logged.txt": (write_nmea_logged, True, "all"),
    "marinecadastre.csv": (write_marinecadastre, True, "all"),
    "marinecadastre_2024.csv.zst": (write_marinecadastre_2024, True, "all"),
    "dma.csv": (write_dma, True, "all"),
    "dma_zipped.zip": (write_dma_zip, True, "all"),
    "plain.csv.gz": (write_plain, True, "no type"),
    "plain_short.csv": (write_plain_short, False, "none"),
}


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ais")
    out = {}
    for name, (writer, _, _) in WRITERS.items():
        writer(d / name)
        out[name] = d / name
    return out


def _expect(reports: Reports, truth: Reports, heading: bool = True) -> None:
    np.testing.assert_array_equal(reports.mmsi, truth.mmsi)
    np.testing.assert_array_equal(reports.t, truth.t)
    np.testing.assert_allclose(reports.lon, truth.lon, rtol=0, atol=1e-6)
    np.testing.assert_allclose(reports.lat, truth.lat, rtol=0, atol=1e-6)
    np.testing.assert_allclose(reports.sog_kn, truth.sog_kn, rtol=0, atol=1e-4)
    np.testing.assert_allclose(reports.cog_deg, truth.cog_deg, rtol=0, atol=1e-4)
    hdg = truth.heading_deg if heading else np.full(len(truth), np.nan, np.float32)
    np.testing.assert_array_equal(reports.heading_deg, hdg)


def _expect_info(info: dict[int, VesselInfo], mmsis, static: str = "all") -> None:
    want = {}
    for m in sorted(set(np.asarray(mmsis).tolist())):
        v = BY_MMSI[m]
        if static != "none" and (v.name or v.ship_type or v.length):
            want[m] = VesselInfo(m, v.name, v.ship_type if static == "all" else None, v.length, v.width)
    assert info == want


@pytest.mark.parametrize("name", list(WRITERS))
def test_every_format_reads_back_the_truth(files, name):
    _, heading, static = WRITERS[name]
    reports, info, stats = read_ais([files[name]], None)
    _expect(reports, TRUTH, heading)
    _expect_info(info, TRUTH.mmsi, static)
    assert stats.kept == len(TRUTH) and sum(stats.rejected.values()) == 0, stats.record()
    assert stats.files == [str(files[name])]
    n_static = 2 * sum(v.kind in ("A", "B") for v in VESSELS) - sum(v.kind == "A" for v in VESSELS)
    assert stats.messages == len(TRUTH) + (n_static if name.startswith("nmea") else 0)


WINDOWS = {
    # across midnight, a box around the Danish vessels
    "midnight": Window(T_START + 2400, T_START + 4800, 10.0, 12.5, 55.5, 57.5),
    # across the antimeridian
    "antimeridian": Window(T_START, T_START + SPAN_S, 179.97, -179.9, 9.0, 11.0),
    # the whole span, a box that holds no vessel
    "empty": Window(T_START, T_START + SPAN_S, 100.0, 101.0, 0.0, 1.0),
}


@pytest.mark.parametrize("window", list(WINDOWS))
@pytest.mark.parametrize(
    "name",
    [
        "nmea_tagged.nmea",
        "marinecadastre.csv",
        "marinecadastre_2024.csv.zst",
        "dma_zipped.zip",
        "plain.csv.gz",
        "plain_short.csv",
    ],
)
def test_the_window_keeps_exactly_the_reports_inside(files, name, window):
    w = WINDOWS[window]
    inside = w.contains(TRUTH.t, TRUTH.lon, TRUTH.lat)
    assert window == "empty" or 0 < inside.sum() < len(TRUTH)
    want = Reports(
        *(getattr(TRUTH, f)[inside] for f in ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg"))
    )
    _, heading, static = WRITERS[name]
    reports, info, stats = read_ais([files[name]], w)
    _expect(reports, want, heading)
    assert stats.kept == int(inside.sum())
    _expect_info(info, want.mmsi, static)


def test_several_files_add_up_and_duplicates_are_kept_once(files):
    reports, _, stats = read_ais([files["dma.csv"], files["nmea_tagged.nmea"]], None)
    _expect(reports, TRUTH)
    assert stats.rejected == {"duplicate": len(TRUTH)}
    assert len(stats.files) == 2


def test_bad_csv_rows_are_counted_and_the_rest_read(tmp_path):
    t = T_START + 100
    bad = {
        "bad line": ["garbage", "27/02/2023 23:01:40,Class A", "", "x,y,notanumber" + ",1" * 24],
        "bad mmsi": [_dma_row(2190068, t, 11, 56, 0, 0, 0, "Base Station"), _dma_row(0, t, 11, 56, 0, 0, 0)],
        "bad time": [_dma_row(219000999, t, 11, 56, 0, 0, 0).replace("27/02/2023", "31/02/2023")],
        "no position": [_dma_row(219000999, t, 181.0, 91.0, 0, 0, 0)],
        "bad position": [_dma_row(219000999, t, 11, 95, 0, 0, 0), _dma_row(219000999, t, 200, 56, 0, 0, 0)],
        "duplicate": [_dma_row(*next(_rows()))],
    }
    path = tmp_path / "dma_bad.csv"
    write_dma(path, [ln for lines in bad.values() for ln in lines])
    reports, _, stats = read_ais([path], None)
    _expect(reports, TRUTH)
    want = {k: len(v) for k, v in bad.items()}
    want["bad line"] -= 1  # the empty line is no row
    assert dict(stats.rejected) == want
    assert stats.messages == len(TRUTH) + sum(want.values()) - want["duplicate"] + 1


def test_bad_nmea_lines_are_counted_and_the_rest_read(files, tmp_path):
    good = files["nmea_tagged.nmea"].read_text().splitlines()
    sentence = encode_dict({"type": 1, "mmsi": 219000999, "lon": 11, "lat": 56}, sentence_type="VDM")[0]
    t5 = encode_dict({"type": 5, "mmsi": 219000998, "shipname": "LOST"}, sentence_type="VDM", seq_id=7)
    bad = {
        "bad checksum": [_tag(T_START, False) + sentence[:-2] + "00", "\\c:1677539000*00\\" + sentence],
        "no time": [sentence],
        "incomplete message": [_tag(T_START, False) + t5[1]],
        "not AIS": ["$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"],
        "bad line": ["hello", _tag(T_START, False) + "!AIVDM,1,1,,A,13u"],
    }
    path = tmp_path / "bad.nmea"
    path.write_text("\n".join(good[:3] + [ln for v in bad.values() for ln in v] + good[3:]) + "\n")
    reports, info, stats = read_ais([path], None)
    _expect(reports, TRUTH)
    _expect_info(info, TRUTH.mmsi)
    assert dict(stats.rejected) == {k: len(v) for k, v in bad.items()}


@pytest.mark.parametrize(
    "content, why",
    [
        (b"II*\x00" + bytes(range(256)) * 40, "binary"),
        (b"id,value,label\n1,2.5,a\n2,3.5,b\n", "not AIS"),
        (b"Lorem ipsum dolor sit amet,\nconsectetur adipiscing elit\n" * 20, "not AIS"),
        (b"", "empty"),
        (zstandard.ZstdCompressor().compress(gzip.compress(b"mmsi,time,lon,lat\n")), "binary"),
    ],
)
def test_files_that_hold_no_ais_are_refused_in_one_line(tmp_path, content, why):
    path = tmp_path / "input.csv"
    path.write_bytes(content)
    with pytest.raises(InputError) as e:
        read_ais([path], None)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg and why in msg


def test_missing_file_and_nmea_without_any_time_are_refused(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_ais([tmp_path / "nope.nmea"], None)
    path = tmp_path / "untimed.nmea"
    path.write_text(
        "\n".join(encode_dict({"type": 1, "mmsi": 219000001 + k, "lon": 11, "lat": 56})[0] for k in range(5))
    )
    with pytest.raises(InputError, match="without times") as e:
        read_ais([path], None)
    assert "\n" not in str(e.value)


def test_max_reports_refuses_in_one_line_naming_the_setting(files):
    reports, _, _ = read_ais([files["dma.csv"]], None, max_reports=len(TRUTH))
    assert len(reports) == len(TRUTH)
    with pytest.raises(InputError, match="max_reports") as e:
        read_ais([files["dma.csv"]], None, max_reports=len(TRUTH) - 1)
    assert "\n" not in str(e.value)


def test_a_line_over_max_line_bytes_is_dropped_and_counted(tmp_path, files):
    lines = gzip.decompress(files["plain.csv.gz"].read_bytes()).split(b"\n")
    path = tmp_path / "long.csv"
    path.write_bytes(b"\n".join(lines[:5] + [b"9" * 300_000] + lines[5:]))
    reports, _, stats = read_ais([path], None, max_line_bytes=4096)
    _expect(reports, TRUTH)
    assert dict(stats.rejected) == {"long line": 1}


def test_a_truncated_zstd_stream_keeps_what_was_read(tmp_path, files):
    data = files["marinecadastre_2024.csv.zst"].read_bytes()
    path = tmp_path / "cut.csv.zst"
    path.write_bytes(data[: len(data) // 3 * 2])
    reports, _, stats = read_ais([path], None)
    assert stats.rejected["corrupt data"] == 1
    assert 0 < len(reports) < len(TRUTH)


def test_max_vessels_bounds_the_static_information_kept(files):
    reports, info, stats = read_ais([files["nmea_tagged.nmea"]], None, max_vessels=2)
    _expect(reports, TRUTH)
    with_static = [v for v in VESSELS if v.name or v.ship_type]
    assert len(info) == 2 and all(
        info[m] == full for m, full in read_ais([files["nmea_tagged.nmea"]], None)[1].items() if m in info
    )
    assert stats.rejected["vessel limit"] >= len(with_static) - 2
