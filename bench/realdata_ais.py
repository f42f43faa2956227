"""AIS matching on the OpenSARShip GRD chips (issue 33): distances and the matcher's defaults,
cross-validated on the fixed halves of ``bench/realdata_eval.py``.

Data: the two OpenSARShip Sentinel-1 IW GRDH products under ``../shared/data/real/opensarship``
(Huang et al., IEEE JSTARS 11(1):195, 2018; cite it with these numbers), 38 chips, 37 with their
ship at the centre (``NO_SHIP_AT_CENTRE``, tests/pipeline/test_opensarship_ais.py). Each chip's
``Ship.xml`` entry holds one real AIS report of its ship (``Time`` POSIX s, ``MMSI``,
``Longitude`` / ``Latitude``, ``Sog`` / ``Cog`` in tenths of a knot / degree, ``True_Head``,
``Length``, ``Width``, ``Name``) and the dataset's own AIS position projected to the SAR time
(``Projected_Longitude`` / ``Projected_Latitude``) with its SAR-AIS ``Distance_error``.

What a user's scene would carry, derived from each product's SNAP metadata
(``<product>.xml``, ``Abstracted_Metadata``) as a reader would (:func:`sar_geometry`):

- ``first_line_time``: ``first_line_time`` (SNAP writes ``DD-MON-YYYY hh:mm:ss.ffffff`` UTC; the
  SAFE annotation's ``productFirstLineUtcTime``), as ISO 8601 with ``Z``;
- ``azimuth_time_interval_s``: ``line_time_interval`` (the annotation's ``azimuthTimeInterval``);
- ``platform_velocity_m_s``: ``|v|`` of the ``Orbit_State_Vectors`` interpolated at mid product
  (as the SAFE reader does);
- ``range_table``: ``col`` the tie-point columns (node ``j`` at sample ``j W / (m - 1)``, the
  tie-point convention of the existing test), ``slant_range_m = c tau / 2`` from the
  ``slant_range_time`` tie-point grid (two-way, ns), the median over the grid's rows (it varies
  by < 0.06 % along azimuth: 47 m and 500 m at 960 km in the two products);
- the georeference: the product's tie-point grid as GCPs (:func:`snap_grid` of the existing
  test), in the product's pixel frame; ``acquisition_start`` / ``acquisition_stop`` the first
  and last line times.

Each chip is ingested and run through ``workers.jobs.run_detection`` with ``ca_cfar``'s defaults
on the VH band (as tests/pipeline/test_opensarship_ais.py); its detections (centroid lon/lat,
``length_m``, the centroid's row / column shifted by the chip's offset into the product frame)
are the user's detections. Each product's AIS reports (all its ships: 13 and 25) are written as a
plain AIS CSV (docs/ais.md) and read back with ``read_ais``.

Per chip, for its centre detection (the one nearest the chip centre) and its ship's report:
distance (a) to the raw report, (b) to the report moved to the detection's line time
(``vessel_states``), (c) to that position displaced by the azimuth shift ``R v_los / V``
(``look_geometry``), against the dataset's ``Distance_error``; and whether the report is
self-consistent (:func:`report_check`: the dataset's own projection against its ``Time``).
Matching (:func:`match_chips`) is per product, as a full-scene run would be: the detections of
all its chips (those of overlapping chips counted once, :func:`pool`) against all its vessels
(``vessel_states`` at the mean line time, :func:`sarship.pipeline.ais.match.match`); a chip counts
as matched when its centre detection gets its own ship's MMSI, as wrong when it gets another.

Cross-validation: the matcher's parameters (``GRID``) are chosen on half A and reported on half
B; the swapped fold is shown too. The rule (:func:`choose`): no wrong match on the half; the most
chips matched; then the best calibrated, the smallest Cramer-von Mises distance of the own-ship
scores from uniform (:func:`cvm_uniform`: a true pair's score is uniform, which is what gives
``min_score`` its meaning); then the fewest changes from ``PREVIOUS``. Everything after the
detections takes seconds.

Usage::

    python bench/realdata_ais.py --md out.md --json out.json
    python bench/realdata_ais.py --from-json out.json      # re-report without detecting again
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import itertools
import json
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sarship.pipeline.ais.displacement import LookGeometry, azimuth_shift_m, look_geometry
from sarship.pipeline.ais.formats import read_ais
from sarship.pipeline.ais.match import Detections, MatchParams, match
from sarship.pipeline.ais.reports import KNOT_M_S, Reports, VesselInfo, Window
from sarship.pipeline.ais.scene_time import iso_seconds, line_times
from sarship.pipeline.ais.tracks import M_PER_DEG, move, vessel_states
from sarship.pipeline.targets import georef as G

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # the tests' helpers (tests.pipeline.test_opensarship_ais)
    sys.path.append(str(REPO))


def _bench_module(name: str):
    """A sibling bench module, imported by path (bench/ is not put on ``sys.path``: its
    ``datasets.py`` / ``common.py`` would shadow other packages in a test session)."""
    import importlib.util

    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


rd = _bench_module("realdata_eval")

from tests.pipeline.test_opensarship_ais import NO_SHIP_AT_CENTRE, snap_grid  # noqa: E402

OSS = REPO.parent / "shared" / "data" / "real" / "opensarship"
C_LIGHT = 299_792_458.0
#: Ship.xml fields read per ship (numbers; ``Name`` separately)
FIELDS = (
    "Time",
    "MMSI",
    "Longitude",
    "Latitude",
    "Sog",
    "Cog",
    "True_Head",
    "Length",
    "Width",
    "Center_x",
    "Center_y",
    "Center_longitude",
    "Center_latitude",
    "Projected_Longitude",
    "Projected_Latitude",
    "Distance_error",
)
#: The matcher's parameters swept (the others at their defaults): ``sigma_geo_m`` (the position
#: error), ``sigma_rate_m_s`` (its linear growth with the gap to the report),
#: ``sigma_turn_deg_s`` (a manoeuvre since the report: ``|v| sigma_turn gap^2 / 2``),
#: ``length_sigma_log`` (the length term) and ``max_distance_m``.
GRID = {
    "sigma_geo_m": (50.0, 75.0, 100.0, 150.0, 200.0, 300.0),
    "sigma_rate_m_s": (0.0, 0.25, 0.5, 1.0),
    "sigma_turn_deg_s": (0.0, 0.02, 0.05, 0.1, 0.2),
    "length_sigma_log": (0.3, 0.4, 0.6, 0.8),
    "max_distance_m": (1000.0, 2000.0, 5000.0),
}
#: The matcher's defaults before this study (chosen on all 38 chips' dataset SAR centres).
PREVIOUS = {
    "sigma_geo_m": 100.0,
    "sigma_rate_m_s": 0.5,
    "sigma_turn_deg_s": 0.0,
    "length_sigma_log": 0.4,
    "max_distance_m": 2000.0,
}
#: A ship under way for :func:`report_check` (knots), and the largest disagreement (s) between
#: the time the dataset's own projection moved a report by and the time its ``Time`` gives
#: (measured: at most 43 s on the 18 chips the shipped defaults match under way, 109-425 s on
#: the other 5)
MOVING_KN = 2.0
CONSISTENT_S = 60.0
HALVES = ("A", "B")
#: The fold whose choice is shipped: defaults chosen on half A, reported on half B.
SHIP_FOLD = "A"


# --------------------------------------------------------------------------------------
# the products: SNAP metadata, Ship.xml, the AIS file


def snap_seconds(text: str) -> float:
    """POSIX seconds of a SNAP metadata time (``02-SEP-2015 10:25:05.845140``, UTC)."""
    return dt.datetime.strptime(text.strip(), "%d-%b-%Y %H:%M:%S.%f").replace(tzinfo=dt.UTC).timestamp()


def iso_z(t: float) -> str:
    """ISO 8601 UTC with ``Z`` (as the SAFE reader writes ``first_line_time``)."""
    return dt.datetime.fromtimestamp(t, dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def sar_geometry(product: Path) -> dict:
    """The scene attributes a reader would write from the product's SNAP metadata (module doc):
    ``sar_geometry`` (``first_line_time``, ``azimuth_time_interval_s``,
    ``platform_velocity_m_s``, ``range_table``) and ``acquisition_start`` / ``acquisition_stop``.

    Parameters
    ----------
    product : Path
        An OpenSARShip product folder (``<product>/<product>.xml``).

    Returns
    -------
    dict
        Scene attributes, in the product's pixel frame.
    """
    root = ET.parse(product / f"{product.name}.xml").getroot()
    am = root.find("Abstracted_Metadata")
    a = {x.get("name"): x.get("value") for x in am.findall("attrib")}
    t0, t1 = snap_seconds(a["first_line_time"]), snap_seconds(a["last_line_time"])
    osv = []
    for v in am.find("Orbit_State_Vectors"):
        d = {x.get("name"): x.get("value") for x in v.findall("attrib")}
        osv.append((snap_seconds(d["time"]), float(d["x_vel"]), float(d["y_vel"]), float(d["z_vel"])))
    osv = np.array(osv)
    speed = float(np.interp(0.5 * (t0 + t1), osv[:, 0], np.linalg.norm(osv[:, 1:], axis=1)))
    tpg = root.find("tie-point-grids/slant_range_time")
    tau = np.array([[float(v) for v in r.get("value").split(",")] for r in tpg.findall("row")]) * 1e-9
    width = int(a["num_samples_per_line"])
    cols = np.arange(tau.shape[1]) * width / (tau.shape[1] - 1)
    return {
        "acquisition_start": iso_z(t0),
        "acquisition_stop": iso_z(t1),
        "sar_geometry": {
            "source": f"SNAP Abstracted_Metadata of {product.name}",
            "first_line_time": iso_z(t0),
            "azimuth_time_interval_s": float(a["line_time_interval"]),
            "platform_velocity_m_s": speed,
            "range_table": {"col": cols.tolist(), "slant_range_m": (C_LIGHT * np.median(tau, axis=0) / 2).tolist()},
        },
    }


def ship_records(product: Path) -> list[dict]:
    """Every ``Ship.xml`` entry of a product: the numbers of ``FIELDS`` and ``Name`` (the file
    is not well-formed XML: read with regular expressions, as the existing test does)."""
    text = (product / "Ship.xml").read_text(errors="replace")
    out = []
    for block in text.split("<ship>")[1:]:
        rec: dict = {}
        for tag in FIELDS:
            m = re.search(rf"<{tag}>\s*([-\d.eE+]+)\s*</{tag}>", block)
            rec[tag] = float(m.group(1)) if m else float("nan")
        m = re.search(r"<Name>([^<]*)</Name>", block)
        rec["Name"] = m.group(1).strip() if m else ""
        out.append(rec)
    return out


def write_ais_csv(records: list[dict], path: Path) -> Path:
    """The product's AIS reports as the plain AIS CSV of docs/ais.md (``Sog`` / ``Cog`` from
    tenths to knots / degrees; ``True_Head`` 511 and unknown cells left to the reader)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["mmsi", "time", "lon", "lat", "sog", "cog", "heading", "name", "length_m", "width_m"])
        for r in records:
            w.writerow(
                [
                    int(r["MMSI"]),
                    int(r["Time"]),
                    f"{r['Longitude']:.6f}",
                    f"{r['Latitude']:.6f}",
                    f"{r['Sog'] / 10:.1f}",
                    f"{r['Cog'] / 10:.1f}",
                    f"{r['True_Head']:.0f}",
                    r["Name"],
                    f"{r['Length']:.0f}" if r["Length"] > 0 else "",
                    f"{r['Width']:.0f}" if r["Width"] > 0 else "",
                ]
            )
    return path


@dataclass
class Product:
    """One product: its scene attributes, georeference (product frame), Ship.xml records by
    (Center_x, Center_y) and the AIS read back from the CSV."""

    name: str
    path: Path
    attrs: dict
    georef: object
    records: dict
    reports: Reports
    info: dict[int, VesselInfo]
    det: Detections | None = None
    states: object = None


def load_product(product: Path, work: Path) -> Product:
    """Scene attributes, georeference and AIS (written as CSV and read with ``read_ais``)."""
    attrs = sar_geometry(product)
    _, _, gcps = snap_grid(product)
    georef = G.from_gcps(gcps)
    recs = ship_records(product)
    csv_path = write_ais_csv(recs, work / f"{product.name[17:32]}_ais.csv")
    sg = attrs["sar_geometry"]
    lon = [g["x"] for g in gcps]
    lat = [g["y"] for g in gcps]
    t0 = float(iso_seconds(sg["first_line_time"]))
    window = Window(t0 - 900.0, t0 + 1000.0, min(lon) - 0.2, max(lon) + 0.2, min(lat) - 0.2, max(lat) + 0.2)
    reports, info, stats = read_ais([csv_path], window)
    if stats.kept != len(recs) or sum(stats.rejected.values()):
        raise RuntimeError(f"{csv_path}: read back {stats.record()} of {len(recs)} reports")
    by_xy = {(int(r["Center_x"]), int(r["Center_y"])): r for r in recs}
    return Product(product.name, product, attrs, georef, by_xy, reports, info)


# --------------------------------------------------------------------------------------
# the chips and their detections


@dataclass
class Chip:
    """One GRD chip: its product, name (``<product date>/<stem>``), half, offset of its pixel
    (0, 0) in the product (``r0``, ``c0``), side, Ship.xml record and whether it is scored (its
    ship at the centre); after :func:`detect`, its features and (:func:`prepare`) its detections
    as the matcher sees them, its centre detection and (:func:`pool`) that detection's index in
    the product's detections."""

    product: Product
    path: Path
    name: str
    half: str
    r0: int
    c0: int
    side: int
    rec: dict
    scored: bool = True
    features: list = field(default_factory=list)
    det: Detections | None = None
    centre: int = -1
    index: int = -1


def grd_chips(products: list[Product]) -> list[Chip]:
    """All the GRD chips, each with its half (``realdata_eval.split_halves``, as in the detector
    study); the one without a ship at its centre (``NO_SHIP_AT_CENTRE``) is not scored, but its
    detections are part of its product's scene."""
    import tifffile

    every = [
        rd.Chip("grd", f"{p.name[17:32]}/{c.stem}", c, (0, 0), None)
        for p in products
        for c in sorted((p.path / "Patch").glob("*.tif"))
    ]
    rd.split_halves(every)
    half = {c.name: c.half for c in every}
    out = []
    for p in products:
        for path in sorted((p.path / "Patch").glob("*.tif")):
            cx, cy = (int(v) for v in re.search(r"_x(\d+)_y(\d+)$", path.stem).groups())
            with tifffile.TiffFile(path) as t:
                side = max(t.series[0].shape[:2])
            name = f"{p.name[17:32]}/{path.stem}"
            rec = p.records[(cx, cy)]
            scored = path.stem not in NO_SHIP_AT_CENTRE
            out.append(Chip(p, path, name, half[name], cy - side // 2, cx - side // 2, side, rec, scored))
    return out


def detect(client, chips: list[Chip], work: Path, threads: int = 4) -> None:
    """Ingest each chip (VH; the product's tie-point grid shifted to the chip as GCPs, as
    tests/pipeline/test_opensarship_ais.py) and run ``ca_cfar`` with its defaults, 4 chips at a
    time on ``client``; then :func:`prepare` each and :func:`pool` them."""
    import zarr

    from sarship.pipeline.readers import ingest
    from sarship.workers.jobs import run_detection

    grids = {p.name: snap_grid(p.path)[2] for p in {c.product.name: c.product for c in chips}.values()}

    def one(k: int) -> None:
        c = chips[k]
        scene = ingest([c.path], work / f"chip{k:02d}.zarr", tile=c.side, channels=["vh", "vv"], band="vh")
        gcps = [{**g, "row": g["row"] - c.r0, "col": g["col"] - c.c0} for g in grids[c.product.name]]
        zarr.open_group(str(scene.path), mode="r+").attrs.update({"crs": "EPSG:4326", "gcps": gcps})
        out = work / f"chip{k:02d}.out"
        run_detection(scene.path, "ca_cfar", {}, out_dir=out, tile=c.side, client=client, progress=False)
        c.features = json.loads((out / "detections.geojson").read_text())["features"]

    with ThreadPoolExecutor(threads) as ex:
        list(ex.map(one, range(len(chips))))
    for c in chips:
        prepare(c)
    pool(chips)


def _as_detections(attrs: dict, georef, props: list[dict], rows: np.ndarray, cols: np.ndarray) -> Detections:
    """Detections from features' properties and their product-frame rows / columns."""
    lon, lat = (np.array([q["centroid_lonlat"][k] for q in props], np.float64) for k in (0, 1))
    length = np.array([q.get("length_m") or np.nan for q in props], np.float64)
    return Detections(lon, lat, line_times(attrs, rows), length, look_geometry(attrs, georef, rows, cols))


def prepare(c: Chip) -> None:
    """The chip's detections as the matcher sees them (``centroid_lonlat``, ``length_m``, the
    line time and look geometry of the centroid's row / column shifted into the product frame)
    and its centre detection (the one nearest the chip centre: the Ship.xml ship's)."""
    if not c.features:
        raise RuntimeError(f"{c.name}: no detection")
    pr = [f["properties"] for f in c.features]
    rows = np.array([q["centroid_px"][0] for q in pr], np.float64) + c.r0
    cols = np.array([q["centroid_px"][1] for q in pr], np.float64) + c.c0
    c.det = _as_detections(c.product.attrs, c.product.georef, pr, rows, cols)
    h = c.side // 2
    c.centre = int(np.argmin([np.hypot(q["centroid_px"][0] - h, q["centroid_px"][1] - h) for q in pr]))


def pool(chips: list[Chip], same_px: float = 5.0) -> None:
    """Each product's scene as a user would have it: the detections of all its chips, those of
    overlapping chips within ``same_px`` of each other in the product frame counted once (the
    one nearer its own chip's centre, the less cut); the vessels at the mean line time
    (``vessel_states``, ``max_extrapolation_s`` of the defaults); each chip's ``index``."""
    for prod in {id(c.product): c.product for c in chips}.values():
        mine = [c for c in chips if c.product is prod]
        cand = []  # (distance to own chip centre, row, col, props, chip, feature index)
        for c in mine:
            for k, f in enumerate(c.features):
                r, q = f["properties"]["centroid_px"]
                cand.append((np.hypot(r - c.side // 2, q - c.side // 2), r + c.r0, q + c.c0, f["properties"], c, k))
        cand.sort(key=lambda x: x[0])
        kept: list[tuple] = []
        where: dict[tuple[int, int], int] = {}
        for x in cand:
            near = [j for j, y in enumerate(kept) if np.hypot(x[1] - y[1], x[2] - y[2]) <= same_px]
            if not near:
                kept.append(x)
            where[(id(x[4]), x[5])] = near[0] if near else len(kept) - 1
        rows, cols = np.array([x[1] for x in kept]), np.array([x[2] for x in kept])
        prod.det = _as_detections(prod.attrs, prod.georef, [x[3] for x in kept], rows, cols)
        t_ref = float(np.mean(prod.det.time))
        prod.states = vessel_states(prod.reports, t_ref, max_extrapolation_s=MatchParams().max_extrapolation_s)
        for c in mine:
            c.index = where[(id(c), c.centre)]


# --------------------------------------------------------------------------------------
# per chip: distances, the track fit, the match


def own_reports(c: Chip) -> Reports:
    """The chip's ship's report(s) in the product's AIS."""
    r = c.product.reports
    k = r.mmsi == int(c.rec["MMSI"])
    return Reports(*(getattr(r, f)[k] for f in ("mmsi", "t", "lon", "lat", "sog_kn", "cog_deg", "heading_deg")))


def _en(lon0: float, lat0: float, lon: float, lat: float) -> np.ndarray:
    """East/north metres from (lon0, lat0) to (lon, lat) (equirectangular, as ``tracks``)."""
    return np.array([(lon - lon0) * M_PER_DEG * np.cos(np.radians(lat0)), (lat - lat0) * M_PER_DEG])


def distances(c: Chip) -> dict:
    """The centre detection against its ship's AIS report: distance (a) to the raw report, (b)
    to the report moved to the detection's line time (``vessel_states``), (c) to that position
    displaced by ``R v_los / V`` along the flight; the report's age ``dt_s`` (report time minus
    line time), SOG, the displacement, the dataset's ``Distance_error`` and the distance to the
    dataset's SAR centre. For a moving ship (SOG >= 2 kn) also the track fit: the time ``tau``
    along the reported course (displaced) closest to the detection, against the time the report
    says (``-dt_s``) and the time of the dataset's own projection (``Projected_*`` along the
    course), and the detection's offset across the course.

    Parameters
    ----------
    c : Chip
        A scored, prepared chip.

    Returns
    -------
    dict
        ``chip``, ``half``, ``mmsi``, ``name``, ``dt_s``, ``sog_kn``, ``displacement_m``,
        ``raw_m`` (a), ``time_m`` (b), ``time_disp_m`` (c), ``dataset_m``, ``sar_centre_m``,
        ``tau_fit_s``, ``tau_dataset_s``, ``across_m`` (NaN for a ship at rest).
    """
    i, det = c.centre, c.det
    g: LookGeometry = det.geometry.take(np.array([i]))
    own = own_reports(c)
    st = vessel_states(own, float(det.time[i]), max_extrapolation_s=1e6)
    ve, vn = float(np.nan_to_num(st.v_east_m_s[0])), float(np.nan_to_num(st.v_north_m_s[0]))
    dx = float(
        azimuth_shift_m(ve, vn, g.range_east, g.range_north, g.slant_range_m, g.platform_velocity_m_s, g.sin_incidence)[
            0
        ]
    )
    fe, fn = float(g.flight_east[0]), float(g.flight_north[0])
    dlon, dlat = move(st.lon[0], st.lat[0], dx * fe, dx * fn)

    def d(x, y) -> float:
        return float(G.distance_m(det.lon[i], det.lat[i], x, y))

    out = {
        "chip": c.name,
        "half": c.half,
        "mmsi": int(c.rec["MMSI"]),
        "name": c.rec["Name"],
        "dt_s": float(own.t[0] - det.time[i]),
        "sog_kn": float(own.sog_kn[0]),
        "displacement_m": dx,
        "raw_m": d(own.lon[0], own.lat[0]),
        "time_m": d(st.lon[0], st.lat[0]),
        "time_disp_m": d(float(np.ravel(dlon)[0]), float(np.ravel(dlat)[0])),
        "dataset_m": float(c.rec["Distance_error"]),
        "sar_centre_m": d(c.rec["Center_longitude"], c.rec["Center_latitude"]),
        "tau_fit_s": float("nan"),
        "tau_dataset_s": float("nan"),
        "across_m": float("nan"),
    }
    speed = float(np.hypot(ve, vn))
    if own.sog_kn[0] >= 2.0 and len(own) == 1:
        v = np.array([ve, vn]) / speed
        r = _en(own.lon[0], own.lat[0], det.lon[i], det.lat[i]) - dx * np.array([fe, fn])
        proj = _en(own.lon[0], own.lat[0], c.rec["Projected_Longitude"], c.rec["Projected_Latitude"])
        out.update(
            tau_fit_s=float(r @ v / speed),
            across_m=float(abs(r[0] * v[1] - r[1] * v[0])),
            tau_dataset_s=float(proj @ v / speed),
        )
    return out


def report_check(c: Chip) -> dict:
    """Whether the chip's Ship.xml AIS report is self-consistent, from the dataset's fields alone
    (no detection): for a ship under way (SOG >= ``MOVING_KN``) the dataset's own projection
    (``Projected_*`` minus the report, along the reported course, over the speed) moved the
    report by ``tau_dataset_s``; its ``Time`` says the ship's line (``Center_y``) was imaged
    ``age_s`` after the report. Consistent when they agree within ``CONSISTENT_S`` (a ship at
    rest: always).

    Parameters
    ----------
    c : Chip
        A chip (its Ship.xml record and product).

    Returns
    -------
    dict
        ``age_s``, ``tau_dataset_s`` (NaN at rest) and ``consistent``.
    """
    r = c.rec
    t_line = float(line_times(c.product.attrs, np.array([r["Center_y"] + 0.5]))[0])
    age = t_line - r["Time"]
    if r["Sog"] / 10.0 < MOVING_KN:
        return {"age_s": age, "tau_dataset_s": float("nan"), "consistent": True}
    cog = np.radians(r["Cog"] / 10.0)
    proj = _en(r["Longitude"], r["Latitude"], r["Projected_Longitude"], r["Projected_Latitude"])
    tau = float(proj @ np.array([np.sin(cog), np.cos(cog)]) / (r["Sog"] / 10.0 * KNOT_M_S))
    return {"age_s": age, "tau_dataset_s": tau, "consistent": abs(tau - age) <= CONSISTENT_S}


def match_chips(chips: list[Chip], p: MatchParams) -> list[dict]:
    """Each product's detections matched to its vessels (``match`` with ``p``); per scored chip
    the MMSI its centre detection gets (-1 none), ``ok`` (its own ship), ``wrong`` (another),
    the score (0 unless its own) and the distance.

    Parameters
    ----------
    chips : list of Chip
        Prepared and pooled chips (:func:`load`).
    p : MatchParams
        The matcher's parameters.

    Returns
    -------
    list of dict
        Per scored chip: ``chip``, ``half``, ``mmsi``, ``ok``, ``wrong``, ``score``, ``distance_m``.
    """
    out = []
    for prod in {id(c.product): c.product for c in chips}.values():
        a = match(prod.det, prod.states, prod.info, p)
        for c in chips:
            if c.product is not prod or not c.scored:
                continue
            m, own = int(a.mmsi[c.index]), int(c.rec["MMSI"])
            out.append(
                {
                    "chip": c.name,
                    "half": c.half,
                    "mmsi": m,
                    "ok": m == own,
                    "wrong": m not in (-1, own),
                    "score": float(a.score[c.index]) if m == own else 0.0,
                    "distance_m": float(a.distance_m[c.index]),
                }
            )
    return out


# --------------------------------------------------------------------------------------
# the sweep and the choice


def key_str(key: dict) -> str:
    """A setting as ``name=value ...`` (the sweep's keys)."""
    return " ".join(f"{k}={v:g}" for k, v in key.items())


def settings() -> list[dict]:
    """Every ``GRID`` setting (``PREVIOUS`` among them)."""
    return [dict(zip(GRID, v)) for v in itertools.product(*GRID.values())]


def sweep(chips: list[Chip], keys: list[dict]) -> dict[str, list[dict]]:
    """Each setting matched on each chip (:func:`match_chip`), by :func:`key_str`."""
    return {key_str(k): match_chips(chips, MatchParams(**k)) for k in keys}


def cvm_uniform(scores: list[float]) -> float:
    """Cramer-von Mises distance ``W^2 = 1/(12 n) + sum (s_(i) - (2i - 1)/(2n))^2`` of ``scores``
    from the uniform distribution on (0, 1): a calibrated matcher's true-pair scores are uniform
    (docs/ais.md, "Matching"). Every chip counts (the Kolmogorov-Smirnov distance, a maximum,
    is blind to a parameter that moves only some of the scores)."""
    s = np.sort(np.asarray(scores, np.float64))
    n = s.size
    if not n:
        return float("inf")
    return float(1.0 / (12 * n) + np.sum((s - (2 * np.arange(1, n + 1) - 1) / (2 * n)) ** 2))


def summary(rows: list[dict], half: str | None = None, chips: set[str] | None = None) -> dict:
    """Over the scored chips of ``half`` (None: both; ``chips``: only those): matched to their
    own MMSI, wrong (another MMSI), chips, the Cramer-von Mises distance of the own-ship scores
    (0 where not matched) from uniform and their median."""
    r = [x for x in rows if (half is None or x["half"] == half) and (chips is None or x["chip"] in chips)]
    sc = [x["score"] for x in r]
    return {
        "matched": sum(x["ok"] for x in r),
        "wrong": sum(x["wrong"] for x in r),
        "chips": len(r),
        "cvm": cvm_uniform(sc),
        "median_score": float(np.median(sc)) if r else float("nan"),
    }


def changed(key: dict) -> int:
    """How many parameters differ from ``PREVIOUS``."""
    return sum(key[k] != PREVIOUS[k] for k in key)


def choose(results: dict[str, list[dict]], keys: list[dict], half: str) -> dict:
    """The setting chosen on ``half`` (module doc): no wrong match on that half; the most chips
    matched to their own MMSI; then the best calibrated (the smallest Cramer-von Mises distance
    of the own-ship scores from uniform, :func:`cvm_uniform`: a true pair's score is uniform on
    (0, 1), which gives ``min_score`` its meaning); then the fewest changes from ``PREVIOUS``.

    Parameters
    ----------
    results : dict
        :func:`sweep`'s results.
    keys : list of dict
        The settings swept.
    half : str
        ``"A"`` or ``"B"``.

    Returns
    -------
    dict
        The chosen setting (``GRID``'s parameters).
    """
    stats = [(k, summary(results[key_str(k)], half)) for k in keys]
    ok = [x for x in stats if x[1]["wrong"] == 0] or stats
    return min(ok, key=lambda x: (-x[1]["matched"], round(x[1]["cvm"], 9), changed(x[0])))[0]


# --------------------------------------------------------------------------------------
# the study and its report


def study(chips: list[Chip]) -> dict:
    """Distances and report checks per scored chip, the sweep, the choice on each half."""
    import platform

    rows = []
    for c in chips:
        if c.scored:
            rows.append({**distances(c), **report_check(c)})
    keys = settings()
    t0 = time.perf_counter()
    results = sweep(chips, keys)
    return {
        "meta": {
            "date": dt.date.today().isoformat(),
            "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}",
            "sweep_s": round(time.perf_counter() - t0, 1),
            "settings": len(keys),
        },
        "chips": rows,
        "keys": keys,
        "results": results,
        "chosen": {h: choose(results, keys, h) for h in HALVES},
    }


def _mm(v: list[float]) -> str:
    return f"{np.median(v):.0f} / {np.max(v):.0f}" if v else "-"


def distance_table(rows: list[dict]) -> list[str]:
    """Median / max of the distances (a), (b), (c) and the dataset's, per group of chips."""
    groups = [
        ("all chips", rows),
        ("half A", [r for r in rows if r["half"] == "A"]),
        ("half B", [r for r in rows if r["half"] == "B"]),
        (f"under way (SOG >= {MOVING_KN:g} kn)", [r for r in rows if r["sog_kn"] >= MOVING_KN]),
        ("under way, report time consistent", [r for r in rows if r["sog_kn"] >= MOVING_KN and r["consistent"]]),
        ("under way, report time inconsistent", [r for r in rows if not r["consistent"]]),
        (f"at rest (SOG < {MOVING_KN:g} kn)", [r for r in rows if r["sog_kn"] < MOVING_KN]),
    ]
    out = [
        "| chips | n | (a) raw report | (b) moved to the line time | (c) moved and displaced | dataset `Distance_error` |",
        "|---|---|---|---|---|---|",
    ]
    for name, g in groups:
        cells = [_mm([r[k] for r in g]) for k in ("raw_m", "time_m", "time_disp_m", "dataset_m")]
        out.append(f"| {name} | {len(g)} | " + " | ".join(cells) + " |")
    return out


def choice_table(st: dict) -> list[str]:
    """Each fold's choice, and the previous defaults, scored on each half."""
    res = st["results"]
    consistent = {r["chip"] for r in st["chips"] if r["consistent"]}
    lines = [
        "| defaults | scored on | matched / chips | wrong | CvM | median own score |",
        "|---|---|---|---|---|---|",
    ]

    def row(label: str, key: dict, on: str, half: str | None, only: set[str] | None = None) -> None:
        s = summary(res[key_str(key)], half, only)
        lines.append(
            f"| {label} | {on} | {s['matched']} / {s['chips']} ({s['matched'] / max(s['chips'], 1):.1%}) | "
            f"{s['wrong']} | {s['cvm']:.3f} | {s['median_score']:.2f} |"
        )

    a, b = st["chosen"]["A"], st["chosen"]["B"]
    ship = st["chosen"][SHIP_FOLD]
    row(f"chosen on A **(shipped)**: {key_str(a)}", a, "A (tuned on)", "A")
    row("chosen on A **(shipped)**", a, "**B (held out)**", "B")
    row("chosen on A **(shipped)**", a, "B, report time consistent", "B", consistent)
    row(f"chosen on B: {key_str(b)}", b, "B (tuned on)", "B")
    row("chosen on B", b, "**A (held out)**", "A")
    for h in HALVES:
        row(f"previous: {key_str(PREVIOUS)}", PREVIOUS, h, h)
    row("shipped", ship, "all chips", None)
    return lines


def chip_table(st: dict) -> list[str]:
    """Per chip: the report, the distances, the shipped defaults' match."""
    ship = {r["chip"]: r for r in st["results"][key_str(st["chosen"][SHIP_FOLD])]}
    lines = [
        "| half | chip | ship | SOG kn | line - report s | dataset's projection s | consistent | dx m "
        "| (a) m | (b) m | (c) m | dataset m | matched (score) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(st["chips"], key=lambda r: (r["half"], r["chip"])):
        m = ship[r["chip"]]
        got = f"yes ({m['score']:.2f})" if m["ok"] else ("**wrong**" if m["wrong"] else "**no**")
        tau = "" if np.isnan(r["tau_dataset_s"]) else f"{r['tau_dataset_s']:.0f}"
        lines.append(
            f"| {r['half']} | {r['chip']} | {r['name']} | {r['sog_kn']:.1f} | {r['age_s']:.0f} | {tau} | "
            f"{'yes' if r['consistent'] else '**no**'} | {r['displacement_m']:.0f} | {r['raw_m']:.0f} | "
            f"{r['time_m']:.0f} | {r['time_disp_m']:.0f} | {r['dataset_m']:.0f} | {got} |"
        )
    return lines


def misses_table(st: dict) -> list[str]:
    """The chips the shipped defaults leave unmatched: where along its reported track the
    detection lies (``tau_fit``) against the report's age and the dataset's projection."""
    ship = {r["chip"]: r for r in st["results"][key_str(st["chosen"][SHIP_FOLD])]}
    lines = [
        "| chip | ship | SOG kn | line - report (Time) s | track fit s | dataset's projection s | across course m |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in st["chips"]:
        if not ship[r["chip"]]["ok"]:
            lines.append(
                f"| {r['chip']} | {r['name']} | {r['sog_kn']:.1f} | {-r['dt_s']:.0f} | {r['tau_fit_s']:.0f} | "
                f"{r['tau_dataset_s']:.0f} | {r['across_m']:.0f} |"
            )
    return lines


def report(st: dict) -> str:
    """The markdown report of a :func:`study`."""
    m = st["meta"]
    out = [
        f"Measured {m['date']} on {m['machine']}; {m['settings']} matcher settings swept in {m['sweep_s']} s.",
        "",
        "Distances from the centre detection to its ship's AIS (median / max, m):",
        "",
        *distance_table(st["chips"]),
        "",
        "The choice (matched = the chip's centre detection given its own ship's MMSI):",
        "",
        *choice_table(st),
        "",
        "Unmatched with the shipped defaults:",
        "",
        *misses_table(st),
        "",
        "Per chip:",
        "",
        *chip_table(st),
    ]
    return "\n".join(out) + "\n"


def load(client, work: Path) -> list[Chip]:
    """The two products, their chips, detections and pooled scenes: everything the study and the
    test (tests/pipeline/test_opensarship_ais_match.py) need.

    Parameters
    ----------
    client : distributed.Client
        The Dask client the detections run on.
    work : Path
        A scratch folder (AIS CSVs, ingested chips, detection outputs).

    Returns
    -------
    list of Chip
        All 38 GRD chips (``scored`` False for the one without a centre ship), prepared and pooled.
    """
    products = [load_product(p, work) for p in sorted(OSS.glob("S1A_IW_GRDH_*"))]
    chips = grd_chips(products)
    detect(client, chips, work)
    return chips


def main(argv: list[str] | None = None) -> int:
    """The command line (module doc): detect, study, report; or re-report a saved study."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--md", type=Path, help="write the markdown report here (else stdout)")
    ap.add_argument("--json", type=Path, help="save the study (re-report with --from-json)")
    ap.add_argument("--from-json", type=Path, help="re-report a saved study")
    args = ap.parse_args(argv)
    if args.from_json:
        st = json.loads(args.from_json.read_text())
    else:
        import logging

        from distributed import Client, LocalCluster

        if not OSS.is_dir():
            print(f"no OpenSARShip data at {OSS}", file=sys.stderr)
            return 2
        with (
            tempfile.TemporaryDirectory(prefix="realdata-ais-") as work,
            LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0", silence_logs=logging.ERROR) as cl,
            Client(cl) as client,
        ):
            t0 = time.perf_counter()
            chips = load(client, Path(work))
            detect_s = time.perf_counter() - t0
            st = study(chips)
            st["meta"]["detect_s"] = round(detect_s, 1)
        if args.json:
            args.json.write_text(json.dumps(st))
    text = report(st)
    if args.md:
        args.md.write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
