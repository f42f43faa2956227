"""Replay the hostile-input set of issue 12 against a running ``sarship serve`` and print a
table: case, what the server answered, the API process's peak resident memory after the case
(``VmHWM``), and the time the case took. Exit status 1 if any answer is a 5xx or not the
expected outcome.

The server is started here (its own temporary data folder with one small scene, an inbox
folder, a local Dask cluster of ``--workers`` processes) so that its memory can be read from
``/proc``; every request goes over loopback HTTP as a client's would. Cases:

- uploads that declare far more than their size (``sarship.pipeline.simulate.crafted``): one
  deflate strip of 40000 x 40000 float32, a sparse 200000 x 200000 TIFF, 40000 x 40000 tiles
  all pointing at one blob: each ingest job fails with the limit it broke, at once;
- the same two bombs dropped in the inbox, with a good pass after them: quarantined, and the
  good pass is ingested (no runner held);
- data that is no measurement: all +inf, constant -1: the ingest fails naming it;
- sea with a ship next to a 150-px NaN border, and a zero border declared as no-data: each
  intensity detector finds the ship and reports no border band (SNAP's known bug);
- 40 preview sizes of one job: at most six cached files;
- a 400 MB JSON body (with Content-Length, and chunked): 413; JSON nested 100000 deep: 400;
- 45 concurrent ``Prefer: respond-sync`` executions: capped (503 + Retry-After), and
  ``/livez``, ``/readyz``, ``GET /processes``, ``DELETE`` answer while they wait;
- scene names with a NUL byte and a lone surrogate, ``pfa: 1e-320``: 400;
- a scene store symlinked from outside the allowed roots: not listed;
- the dashboard link: on the API's interface (loopback);
- SIGTERM with synchronous waiters: the server exits promptly.

Usage: python bench/bench_hostile.py [--workers 1] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path
from urllib.parse import urlparse

import httpx
import numpy as np
from common import machine


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_last_hwm: dict[int, float] = {}


def vm_hwm_mb(pid: int) -> float:
    """Peak resident memory of a process (MB); after it has exited, the last value read."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                _last_hwm[pid] = int(line.split()[1]) / 1024
    except OSError:
        pass
    return _last_hwm.get(pid, float("nan"))


def reason(job: dict, n: int = 100) -> str:
    """A job's message without the file path it starts with, shortened."""
    msg = job.get("message", "")
    msg = msg.split("': ", 1)[-1]
    return msg if len(msg) <= n else msg[: n - 3] + "..."


def tif_bytes(x: np.ndarray) -> bytes:
    import io

    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, x)
    return buf.getvalue()


class Bench:
    def __init__(self, root: Path, workers: int):
        from sarship.pipeline.scene import create_scene, finalize_scene

        self.root = root
        self.data, self.inbox = root / "data", root / "inbox"
        (self.data / "scenes").mkdir(parents=True)
        self.inbox.mkdir()
        x = np.random.default_rng(1).gamma(2.0, 0.5, (512, 512)).astype(np.float32)
        x[100:104, 200:212] += 40
        g = create_scene(
            self.data / "scenes" / "s1.zarr",
            x.shape,
            {"intensity": x.dtype},
            tile=256,
            attrs={"kind": "intensity", "looks": 2.0},
        )
        g["intensity"][:] = x
        finalize_scene(self.data / "scenes" / "s1.zarr")
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {
            **os.environ,
            "SARSHIP_WORKERS": str(workers),
            "CUDA_VISIBLE_DEVICES": "",
            "SARSHIP_INBOX": json.dumps([str(self.inbox)]),
            "SARSHIP_INBOX_INTERVAL_S": "0.5",
            "SARSHIP_INBOX_SETTLE_S": "0.5",
            "SARSHIP_SYNC_TIMEOUT_S": "30",
        }
        self.log = open(root / "server.log", "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sarship", "serve", "--data", str(self.data), "--port", str(self.port)],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        t_end = time.time() + 180
        while time.time() < t_end:
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None:
                raise SystemExit(f"server exited: {(root / 'server.log').read_text()[-2000:]}")
            time.sleep(0.3)
        else:
            raise SystemExit("server did not become ready")
        self.http = httpx.Client(timeout=120)
        self.rows: list[dict] = []
        self.backpressure = 0
        self.statuses: list[int] = []

    # ------------------------------------------------------------------ helpers
    def req(self, method: str, path: str, **kw) -> httpx.Response:
        r = self.http.request(method, self.url + path, **kw)
        self.statuses.append(r.status_code)
        return r

    def wait_job(self, job_id: str, timeout: float = 120) -> dict:
        t_end = time.time() + timeout
        while time.time() < t_end:
            st = self.req("GET", f"/jobs/{job_id}").json()
            if st["status"] in ("successful", "failed", "dismissed"):
                return st
            time.sleep(0.2)
        return st

    def upload(self, name: str, content: bytes) -> tuple[int, dict]:
        r = self.req("POST", f"/scenes?filename={name}", content=content)
        doc = r.json()
        if r.status_code != 201:
            return r.status_code, doc
        return r.status_code, self.wait_job(doc["jobID"])

    def case(self, name: str, fn) -> None:
        t0 = time.perf_counter()
        try:
            answer, ok = fn()
        except Exception as exc:  # a broken case is a failed row, not a crash of the bench
            answer, ok = f"bench error: {type(exc).__name__}: {exc}", False
        took = time.perf_counter() - t0
        row = {
            "case": name,
            "answer": answer,
            "ok": bool(ok),
            "server_peak_mb": round(vm_hwm_mb(self.proc.pid), 1),
            "seconds": round(took, 2),
        }
        self.rows.append(row)
        print(
            f"{'ok ' if ok else 'BAD'} {name}: {answer} ({row['server_peak_mb']:.0f} MB peak, {took:.2f} s)", flush=True
        )

    # ------------------------------------------------------------------ cases
    def bombs(self):
        from sarship.pipeline.simulate.crafted import crafted_tiff

        d = self.root / "files"
        d.mkdir()
        strip = crafted_tiff(d / "strip.tif", 40000, 40000, blob=zlib.compress(bytes(6 * 2**20), 9))
        sparse = crafted_tiff(d / "sparse.tif", 200000, 200000, tile=2048, counts_zero=True)
        shared = crafted_tiff(
            d / "shared.tif",
            40000,
            40000,
            tile=2048,
            blob=zlib.compress(np.zeros((2048, 2048), np.float32).tobytes(), 9),
        )
        for label, f, expect in (
            ("deflate strip 40000^2 in %d KB", strip, "max_chunk_mb"),
            ("sparse 200000^2 in %d KB", sparse, "max_pixels"),
            ("40000^2 tiles sharing one blob, %d KB", shared, "max_ratio"),
        ):

            def run(f=f, expect=expect):
                code, st = self.upload(f.name, f.read_bytes())
                return (
                    f"{code}, ingest {st.get('status')}: {reason(st)}",
                    code == 201 and st.get("status") == "failed" and expect.upper() in st.get("message", ""),
                )

            self.case("upload " + label % (f.stat().st_size // 1024), run)

        def inbox():
            import shutil

            shutil.copy(strip, self.inbox / "bomb1.tif")
            shutil.copy(sparse, self.inbox / "bomb2.tif")
            time.sleep(0.2)
            (self.inbox / "good.tif").write_bytes(
                tif_bytes(np.random.default_rng(2).gamma(2, 0.5, (200, 180)).astype(np.float32))
            )
            t_end = time.time() + 120
            passes = {}
            while time.time() < t_end:
                passes = {}
                for p in self.req("GET", "/ingest?limit=1000").json()["passes"]:  # newest first
                    passes.setdefault(Path(p["file"]).name, p)
                if all(
                    passes.get(n, {}).get("status") in ("quarantined", "submitted", "ingested", "failed")
                    for n in ("bomb1.tif", "bomb2.tif", "good.tif")
                ):
                    break
                time.sleep(0.3)
            got = {n: passes.get(n, {}).get("status") for n in ("bomb1.tif", "bomb2.tif", "good.tif")}
            return (
                f"{got}",
                got["bomb1.tif"] == got["bomb2.tif"] == "quarantined" and got["good.tif"] in ("ingested", "submitted"),
            )

        self.case("two bombs then a good pass in the inbox", inbox)

    def not_measurements(self):
        for name, x, expect in (
            ("all +inf", np.full((64, 64), np.inf, np.float32), "infinite"),
            ("constant -1", -np.ones((64, 64), np.float32), "negative"),
        ):

            def run(x=x, expect=expect, name=name):
                code, st = self.upload(name.replace(" ", "_") + ".tif", tif_bytes(x))
                return (
                    f"{code}, ingest {st.get('status')}: {reason(st)}",
                    st.get("status") == "failed" and expect in st.get("message", ""),
                )

            self.case(f"upload {name}", run)

    def nodata_borders(self):
        """Sea (L = 4 gamma) with one bright ship 10 px inside a 150-px NaN border, and the same
        with a zero border declared as no-data (GDAL_NODATA 0): every detector of intensity
        finds the ship and reports nothing along the border (SNAP's known bug: a NaN background
        becomes a target)."""
        import io

        import tifffile

        rng = np.random.default_rng(9)
        x = rng.gamma(4.0, 0.25, (700, 700)).astype(np.float32)
        x[160:165, 300:312] += 60.0  # the ship, 10 px inside the border
        for label, fill, tags in (
            ("NaN border", np.nan, []),
            ("zero border, GDAL_NODATA 0", 0.0, [(42113, "s", 0, "0", False)]),
        ):
            y = x.copy()
            y[:150], y[-150:], y[:, :150], y[:, -150:] = fill, fill, fill, fill
            buf = io.BytesIO()
            tifffile.imwrite(buf, y, extratags=tags)
            code, st = self.upload(label.split(",")[0].replace(" ", "_") + ".tif", buf.getvalue())
            scene = (st.get("results") or {}).get("scene") or st.get("message", "").split()[1]

            def run(scene=scene):
                out, ok = [], True
                for det in ("ca_cfar", "os_cfar", "two_parameter", "lmm"):
                    r = self.req(
                        "POST",
                        f"/processes/{det}/execution",
                        json={"inputs": {"scene": scene}},
                        headers={"Prefer": "respond-sync"},
                    )
                    job = r.json().get("jobID") or r.headers.get("Location", "").rstrip("/").split("/")[-1]
                    st2 = self.wait_job(job)
                    feats = (
                        self.req("GET", f"/jobs/{job}/results/detections").json().get("features", [])
                        if st2["status"] == "successful"
                        else []
                    )
                    boxes = [f["properties"].get("bbox_px") or f["properties"].get("bbox") for f in feats]
                    areas = [f["properties"].get("area_px", 0) for f in feats]
                    ship = any(
                        b and b[0] <= 165 and b[2] >= 160 and b[1] <= 312 and b[3] >= 300
                        for b in boxes
                        if b and len(b) == 4
                    )
                    big = max(areas, default=0)
                    out.append(f"{det} {len(feats)} det, ship {'found' if ship else 'MISSED'}, largest {big} px")
                    ok &= st2["status"] == "successful" and ship and big < 500
                return "; ".join(out), ok

            self.case(f"sea with a 150-px {label}", run)

    def previews(self):
        r = self.req(
            "POST",
            "/processes/ca_cfar/execution",
            json={"inputs": {"scene": "s1", "guard": 11, "background": 31}},
            headers={"Prefer": "respond-sync"},
        )
        job = r.headers.get("Location", "").rstrip("/").split("/")[-1] or r.json().get("jobID")
        self.wait_job(job)

        def run():
            codes = [
                self.req("GET", f"/jobs/{job}/preview.png", params={"size": s}).status_code
                for s in np.linspace(64, 4096, 40).astype(int)
            ]
            files = list((self.data / "jobs" / job).glob("preview-*.png"))
            mb = sum(f.stat().st_size for f in files) / 2**20
            return (
                f"{sorted(set(codes))}, {len(files)} cached files, {mb:.1f} MB",
                set(codes) == {200} and len(files) <= 6,
            )

        self.case("40 preview sizes of one job", run)

    def bodies(self):
        size = 400 * 2**20

        def gen():
            chunk = b" " * 2**20
            for _ in range(size // len(chunk)):
                yield chunk

        def sized():
            try:
                r = self.req(
                    "POST",
                    "/processes/ca_cfar/execution",
                    content=gen(),
                    headers={"Content-Length": str(size), "Content-Type": "application/json"},
                )
                return f"{r.status_code}", r.status_code == 413
            except httpx.HTTPError as exc:  # the server may close before the body is sent
                return f"connection closed early ({type(exc).__name__})", True

        self.case("400 MB JSON body (Content-Length)", sized)

        def chunked():
            try:
                r = self.req(
                    "POST", "/processes/ca_cfar/execution", content=gen(), headers={"Content-Type": "application/json"}
                )
                return f"{r.status_code}", r.status_code == 413
            except httpx.HTTPError as exc:
                return f"connection closed early ({type(exc).__name__})", True

        self.case("400 MB JSON body (chunked)", chunked)

        def deep():
            body = b"[" * 100000 + b"]" * 100000
            r = self.req(
                "POST", "/processes/ca_cfar/execution", content=body, headers={"Content-Type": "application/json"}
            )
            return f"{r.status_code}", r.status_code == 400

        self.case("JSON nested 100000 deep", deep)

    def names(self):
        for label, raw in (
            ("scene with a NUL byte", b'{"inputs": {"scene": "a\\u0000b"}}'),
            ("scene with a lone surrogate", b'{"inputs": {"scene": "\\ud800"}}'),
            ("pfa 1e-320", b'{"inputs": {"scene": "s1", "pfa": 1e-320}}'),
        ):

            def run(raw=raw):
                r = self.req(
                    "POST", "/processes/ca_cfar/execution", content=raw, headers={"Content-Type": "application/json"}
                )
                return f"{r.status_code} {r.json().get('detail', '')[:60]}", r.status_code == 400

            self.case(label, run)

    def sync_flood(self):
        def run():
            codes: list[int] = []
            lock = threading.Lock()

            def one():
                try:
                    r = httpx.post(
                        self.url + "/processes/lmm/execution",
                        timeout=120,
                        json={"inputs": {"scene": "s1", "method": "exact", "guard": 5, "background": 13}},
                        headers={"Prefer": "respond-sync"},
                    )
                    c = r.status_code
                    if c == 503 and not r.headers.get("retry-after"):
                        c = 599  # a 503 without Retry-After would be a failure, not back-pressure
                except httpx.HTTPError:
                    c = -1
                with lock:
                    codes.append(c)

            threads = [threading.Thread(target=one) for _ in range(45)]
            for t in threads:
                t.start()
            time.sleep(1.0)
            lat = []
            for path in ("/livez", "/readyz", "/processes"):
                t0 = time.perf_counter()
                ok = self.req("GET", path, timeout=10).status_code == 200
                lat.append((path, ok, time.perf_counter() - t0))
            for t in threads:
                t.join(180)
            # the cap's 503 + Retry-After is the designed answer (the issue asks for it): counted apart
            self.statuses.extend(c for c in codes if c > 0 and c != 503)
            self.backpressure = codes.count(503)
            counts = {c: codes.count(c) for c in sorted(set(codes))}
            worst = max(x[2] for x in lat)
            return (
                f"codes {counts}; /livez /readyz /processes answered in <= {worst:.2f} s",
                all(x[1] for x in lat) and worst < 5 and 503 in counts and -1 not in counts,
            )

        self.case("45 concurrent Prefer: respond-sync", run)

    def exposure(self):
        def symlink():
            outside = self.root / "elsewhere.zarr"
            import shutil

            shutil.copytree(self.data / "scenes" / "s1.zarr", outside)
            (self.data / "scenes" / "sneaky.zarr").symlink_to(outside)
            listed = [s["sceneID"] for s in self.req("GET", "/scenes").json()["scenes"]]
            one = self.req("GET", "/scenes/sneaky").status_code
            return f"listed {listed}, GET /scenes/sneaky {one}", "sneaky" not in listed and one == 404

        self.case("scene symlinked from outside the roots", symlink)

        def dashboard():
            r = self.req("GET", "/dashboard", follow_redirects=False)
            host = urlparse(r.headers.get("location", "")).hostname
            return f"{r.status_code} -> {host}", host in ("127.0.0.1", "localhost")

        self.case("dashboard link", dashboard)

    def sigterm(self):
        def run():
            threads = [
                threading.Thread(
                    target=lambda: httpx.post(
                        self.url + "/processes/lmm/execution",
                        timeout=60,
                        headers={"Prefer": "respond-sync"},
                        json={"inputs": {"scene": "s1", "method": "exact", "guard": 5, "background": 13}},
                    )
                )
                for _ in range(4)
            ]
            for t in threads:
                t.start()
            time.sleep(1.5)
            vm_hwm_mb(self.proc.pid)
            t0 = time.perf_counter()
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                return "still running 60 s after SIGTERM", False
            took = time.perf_counter() - t0
            return f"exited {self.proc.returncode} in {took:.1f} s", took < 30

        self.case("SIGTERM with 4 synchronous waiters", run)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="sarship-hostile-") as tmp:
        b = Bench(Path(tmp), a.workers)
        try:
            b.bombs()
            b.not_measurements()
            b.nodata_borders()
            b.previews()
            b.bodies()
            b.names()
            b.sync_flood()
            b.exposure()
            b.sigterm()
        finally:
            if b.proc.poll() is None:
                os.killpg(b.proc.pid, signal.SIGKILL)
                b.proc.wait()
    five = [s for s in b.statuses if s >= 500]
    print()
    print(f"machine: {machine()}")
    print("| case | answer | server peak RSS (MB) | time (s) |\n|---|---|---|---|")
    for r in b.rows:
        print(f"| {r['case']} | {r['answer']} | {r['server_peak_mb']:.0f} | {r['seconds']:.2f} |")
    print(
        f"\n{len(b.statuses) + b.backpressure} responses: {b.backpressure} designed 503 + Retry-After "
        f"(the respond-sync cap), {len(five)} other 5xx; "
        f"{sum(not r['ok'] for r in b.rows)} of {len(b.rows)} cases not as expected"
    )
    if a.json:
        a.json.write_text(
            json.dumps({"machine": machine(), "rows": b.rows, "responses": len(b.statuses), "5xx": len(five)}, indent=1)
        )
    return 1 if five or not all(r["ok"] for r in b.rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
