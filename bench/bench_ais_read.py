"""Cost of reading AIS: a Danish Maritime Authority day file streamed for one scene window
(``read_ais``, pipeline/ais/formats.py).

A synthetic DMA day file of ``--rows`` rows (default 11 M, about 2 GB as the real ones: the DMA's
26 columns, sorted by time, ~3000 vessels over Danish waters, class A and B, base stations and
aids to navigation among them) is written in a temporary folder, then read in a fresh process for
a 1-hour, 300 x 300 km window (10:00-11:00 UTC around 11 E, 56 N). Reference, measured in the
same run on the same file: the bare ``csv.reader`` loop over it (no parsing at all).

    python bench/bench_ais_read.py [--rows 11000000] [--keep FOLDER]

Prints the file's size, rows/s, wall time and peak RSS of each run (the child process's own
high-water mark: ``VmHWM``, else ``resource.getrusage``), and the ratio of read_ais's time to the
reference's.
"""

from __future__ import annotations

import argparse
import calendar
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HEADER = (
    "# Timestamp,Type of mobile,MMSI,Latitude,Longitude,Navigational status,ROT,SOG,COG,Heading,IMO,"
    "Callsign,Name,Ship type,Cargo type,Width,Length,Type of position fixing device,Draught,"
    "Destination,ETA,Data source type,A,B,C,D\n"
)
DAY = calendar.timegm((2023, 2, 27, 0, 0, 0))
#: the window: 10:00-11:00 UTC, 300 x 300 km around (11 E, 56 N)
T0, T1 = DAY + 10 * 3600, DAY + 11 * 3600
LON0, LAT0, HALF_KM = 11.0, 56.0, 150.0
STATUS = ["Under way using engine", "At anchor", "Moored", "Engaged in fishing", "Unknown value"]
TYPES = ["Cargo", "Tanker", "Fishing", "Passenger", "Pleasure", "Sailing", "Tug", "Undefined"]


def _vessels(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    mobile = rng.choice(4, n, p=[0.70, 0.24, 0.03, 0.03])  # class A, class B, base station, AtoN
    mmsi = rng.integers(211_000_000, 277_999_999, n)
    mmsi[mobile == 2] = rng.integers(2_190_000, 2_199_999, int(np.sum(mobile == 2)))  # 00MIDxxxx
    mmsi[mobile == 3] = rng.integers(992_190_000, 992_199_999, int(np.sum(mobile == 3)))
    return {
        "mobile": mobile,
        "mmsi": mmsi,
        "lon": rng.uniform(3.0, 17.0, n),
        "lat": rng.uniform(53.5, 59.0, n),
        "sog": np.where(mobile < 2, rng.gamma(2.0, 5.0, n).clip(0, 30), 0.0),
        "cog": rng.uniform(0, 360, n),
        "length": rng.integers(8, 300, n),
        "type": rng.integers(0, len(TYPES), n),
        "status": rng.integers(0, len(STATUS), n),
    }


def _rows(v: dict[str, np.ndarray], idx: np.ndarray, t: np.ndarray, clock: list[str], rng) -> str:
    """``len(idx)`` rows of vessels ``idx`` at times ``t`` (s into the day), as DMA CSV text."""
    km = v["sog"][idx] * 1.852 * t / 3600.0  # dead reckoning from the day's start (wraps the box)
    c = np.radians(v["cog"][idx])
    lat = 53.5 + (v["lat"][idx] - 53.5 + km * np.cos(c) / 111.32) % 5.5
    lon = 3.0 + (v["lon"][idx] - 3.0 + km * np.sin(c) / (111.32 * np.cos(np.radians(lat)))) % 14.0
    sog = np.round(v["sog"][idx] + rng.normal(0, 0.2, idx.size).clip(-0.5, 0.5), 1).clip(0)
    cog = np.round((v["cog"][idx] + rng.normal(0, 2, idx.size)) % 360, 1)
    mobile = ["Class A", "Class B", "Base Station", "AtoN"]
    out = []
    for k, i in enumerate(idx.tolist()):
        m = int(v["mobile"][i])
        if m >= 2:
            out.append(
                f"{clock[int(t[k])]},{mobile[m]},{v['mmsi'][i]:07d},{lat[k]:.6f},{lon[k]:.6f},Unknown value,,,,,"
                "Unknown,Unknown,,Undefined,,,,GPS,,Unknown,,AIS,,,,\n"
            )
            continue
        ln = int(v["length"][i])
        out.append(
            f"{clock[int(t[k])]},{mobile[m]},{v['mmsi'][i]},{lat[k]:.6f},{lon[k]:.6f},"
            f"{STATUS[int(v['status'][i])]},0.0,{sog[k]},{cog[k]},{int(cog[k]) if m == 0 else ''},"
            f"IMO{9000000 + i},OX{i:04d},VESSEL {i},{TYPES[int(v['type'][i])]},,{max(ln // 6, 2)},{ln},GPS,"
            f"{ln / 40:.1f},AARHUS,27/02/2023 18:00:00,AIS,{ln // 2},{ln - ln // 2},{ln // 12},{ln // 6 - ln // 12}\n"
        )
    return "".join(out)


def write_dma_day(path: Path, n_rows: int, seed: int = 0, chunk: int = 200_000) -> None:
    """A synthetic DMA day file of ``n_rows`` rows sorted by time."""
    rng = np.random.default_rng(seed)
    v = _vessels(max(50, n_rows // 3700), rng)
    clock = [time.strftime("%d/%m/%Y %H:%M:%S", time.gmtime(DAY + s)) for s in range(86_400)]
    with open(path, "w", newline="") as f:
        f.write(HEADER)
        for start in range(0, n_rows, chunk):
            m = min(chunk, n_rows - start)
            t = np.linspace(86_400 * start / n_rows, 86_400 * (start + m) / n_rows, m, endpoint=False)
            f.write(_rows(v, rng.integers(0, v["mmsi"].size, m), t, clock, rng))


#: the child's own peak: VmHWM (a process's high-water RSS, reset by exec) where Linux gives it;
#: ``ru_maxrss`` otherwise (which on Linux carries the parent's peak over the exec)
PEAK = """
def peak_rss():
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
"""

CHILD_READ = """
import json, resource, sys, time
from sarship.pipeline.ais.formats import read_ais
from sarship.pipeline.ais.reports import Window
w = Window(*json.loads(sys.argv[2]))
t = time.perf_counter()
reports, info, stats = read_ais([sys.argv[1]], w)
wall = time.perf_counter() - t
rss = peak_rss()
print(json.dumps({"wall_s": wall, "peak_rss": rss, "kept": len(reports), "vessels": len(info), "stats": stats.record()}))
"""

CHILD_CSV = """
import csv, json, resource, sys, time
t = time.perf_counter()
n = 0
with open(sys.argv[1], newline="") as f:
    for row in csv.reader(f):
        n += 1
wall = time.perf_counter() - t
rss = peak_rss()
print(json.dumps({"wall_s": wall, "peak_rss": rss, "rows": n}))
"""


def _child(code: str, *args: str) -> dict:
    code = code.replace("import json, resource, sys, time", "import json, resource, sys, time\n" + PEAK, 1)
    code = code.replace("import csv, json, resource, sys, time", "import csv, json, resource, sys, time\n" + PEAK, 1)
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=11_000_000)
    ap.add_argument("--keep", type=Path, default=None, help="write the file here and keep it")
    a = ap.parse_args()
    dlat = HALF_KM / 111.32
    dlon = HALF_KM / (111.32 * math.cos(math.radians(LAT0)))
    window = [T0, T1, LON0 - dlon, LON0 + dlon, LAT0 - dlat, LAT0 + dlat]
    with tempfile.TemporaryDirectory() as tmp:
        path = (a.keep or Path(tmp)) / f"aisdk-synthetic-{a.rows}.csv"
        t = time.perf_counter()
        write_dma_day(path, a.rows)
        size = os.path.getsize(path)
        print(
            f"wrote {a.rows} rows, {size / 1e6:.0f} MB ({size / a.rows:.0f} B/row) in {time.perf_counter() - t:.1f} s"
        )
        ref = _child(CHILD_CSV, str(path))
        got = _child(CHILD_READ, str(path), json.dumps(window))
    for name, r in (("csv.reader loop (reference)", ref), ("read_ais, 1 h x 300 km window", got)):
        print(
            f"{name:32s} {a.rows / r['wall_s'] / 1e6:6.2f} M rows/s  {r['wall_s']:7.2f} s  "
            f"peak RSS {r['peak_rss'] / 2**20:6.0f} MiB"
        )
    print(f"read_ais time / reference time: {got['wall_s'] / ref['wall_s']:.2f}")
    print(f"kept {got['kept']} reports of {got['vessels']} vessels with static info; stats {json.dumps(got['stats'])}")
    print(f"extrapolated to 11 M rows: {got['wall_s'] * 11e6 / a.rows:.1f} s")


if __name__ == "__main__":
    main()
