"""Issue 12, "inputs that exhaust the machine": crafted TIFFs that declare far more than their
size (one huge deflate strip, a sparse 200000 x 200000 image, tiles all pointing at one blob)
are refused from their headers, before any pixel is decoded, with a message naming the limit
to raise; the limits are settings (``sarship ingest --max-pixels/--max-chunk-mb/--max-ratio``).
"""

from __future__ import annotations

import resource
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import tifffile

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import InputLimits, ingest
from sarship.pipeline.simulate.crafted import crafted_tiff


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def test_crafted_files_parse_as_declared(tmp_path):
    """The hand-written TIFFs are what they claim (so the refusals below are of real files)."""
    p = crafted_tiff(tmp_path / "t.tif", 64, 96, tile=32, blob=zlib.compress(np.zeros((32, 32), np.float32).tobytes()))
    with tifffile.TiffFile(p) as t:
        assert t.series[0].shape == (64, 96) and t.pages[0].compression == 8 and len(t.pages[0].dataoffsets) == 6
        assert np.array_equal(t.asarray(), np.zeros((64, 96), np.float32))
    # and small ones of each kind ingest (within limits)
    sc = ingest([p], tmp_path / "ok.zarr")
    assert sc.shape == (64, 96)


def test_one_huge_deflate_strip_is_refused_before_decoding(tmp_path):
    # 40000 x 40000 float32 in one strip: 6.4 GB decoded (the 6 MB file reached 6.4 GB RSS)
    blob = zlib.compress(bytes(2**20))
    p = crafted_tiff(tmp_path / "strip.tif", 40000, 40000, blob=blob)
    before = peak_rss_mb()
    t0 = time.perf_counter()
    with pytest.raises(InputError) as e:
        ingest([p], tmp_path / "o.zarr")
    took = time.perf_counter() - t0
    msg = str(e.value)
    assert "strip/tile decodes to 6104 MiB" in msg and "--max-chunk-mb" in msg and "TILED=YES" in msg, msg
    assert took < 10 and peak_rss_mb() - before < 200, (took, peak_rss_mb() - before)
    assert not (tmp_path / "o.zarr").exists() and sorted(x.name for x in tmp_path.iterdir()) == ["strip.tif"]


def test_sparse_giant_is_refused_by_its_declared_pixels(tmp_path):
    # 200000 x 200000 declared, every tile byte count 0: a 19 KB-class file
    p = crafted_tiff(tmp_path / "sparse.tif", 200000, 200000, tile=2048, counts_zero=True)
    assert p.stat().st_size < 100_000
    with pytest.raises(InputError) as e:
        ingest([p], tmp_path / "o.zarr")
    assert "200000 x 200000 = 4e+10 pixels" in str(e.value) and "--max-pixels" in str(e.value), e.value


def test_tiles_sharing_one_blob_and_sparse_files_are_refused_by_ratio(tmp_path):
    # 40000 x 40000 (within the pixel limit) in 2048-px tiles that all point at one deflate blob
    tile = 2048
    blob = zlib.compress(np.zeros((tile, tile), np.float32).tobytes(), 9)
    p = crafted_tiff(tmp_path / "shared.tif", 40000, 40000, tile=tile, blob=blob)
    with pytest.raises(InputError) as e:
        ingest([p], tmp_path / "o.zarr")
    assert "ratio" in str(e.value) and "--max-ratio" in str(e.value) and "decompression bomb" in str(e.value)
    # a sparse file within the pixel limit: the same rule
    q = crafted_tiff(tmp_path / "sparse.tif", 20000, 20000, tile=512, counts_zero=True)
    with pytest.raises(InputError, match="--max-ratio"):
        ingest([q], tmp_path / "o.zarr")
    # with the ratio limit raised far enough, the shared-blob file is taken (limits are settings)
    ok = crafted_tiff(tmp_path / "small.tif", 512, 512, tile=256, blob=zlib.compress(bytes(256 * 256 * 4), 9))
    with pytest.raises(InputError, match="ratio"):
        ingest([ok], tmp_path / "o.zarr")
    sc = ingest([ok], tmp_path / "o.zarr", limits=InputLimits(max_ratio=1e6))
    assert sc.shape == (512, 512)


def test_real_compressed_files_pass_at_the_defaults(tmp_path):
    """A deflate-tiled and a deflate-striped TIFF of real-looking clutter (ratio near 1) and an
    uncompressed single-strip one (memory-mapped: no chunk limit) ingest unchanged."""
    x = np.random.default_rng(0).gamma(2.0, 0.5, (700, 600)).astype(np.float32)
    tifffile.imwrite(tmp_path / "tiled.tif", x, compression="zlib", tile=(256, 256))
    tifffile.imwrite(tmp_path / "strips.tif", x, compression="zlib", rowsperstrip=64)
    tifffile.imwrite(tmp_path / "raw.tif", x)
    for name in ("tiled", "strips", "raw"):
        sc = ingest([tmp_path / f"{name}.tif"], tmp_path / f"{name}.zarr", kind="intensity")
        assert np.array_equal(np.asarray(sc.array("intensity")[...]), x), name
    # a chunk limit below one strip refuses the compressed one, not the memory-mapped one
    small = InputLimits(max_chunk_mb=0.1)
    with pytest.raises(InputError, match="--max-chunk-mb"):
        ingest([tmp_path / "strips.tif"], tmp_path / "s2.zarr", limits=small)
    ingest([tmp_path / "raw.tif"], tmp_path / "r2.zarr", limits=small)


def test_pixel_limit_applies_to_every_format(tmp_path):
    from PIL import Image

    x = np.random.default_rng(1).gamma(2.0, 0.5, (120, 100)).astype(np.float32)
    np.save(tmp_path / "a.npy", x)
    Image.fromarray((x * 40).clip(0, 255).astype(np.uint8)).save(tmp_path / "a.png")
    tifffile.imwrite(tmp_path / "a.tif", x)
    z = ingest([tmp_path / "a.npy"], tmp_path / "z.zarr")
    lim = InputLimits(max_pixels=10_000)
    for src in ("a.npy", "a.png", "a.tif", "z.zarr"):
        with pytest.raises(InputError, match=r"120 x 100 = 1\.2e\+04 pixels.*--max-pixels"):
            ingest([tmp_path / src], tmp_path / "o.zarr", limits=lim)
        assert not (tmp_path / "o.zarr").exists()
    assert z.shape == (120, 100)
    with pytest.raises(InputError, match="--max-ratio must be a positive number"):
        InputLimits(max_ratio=0)
    with pytest.raises(InputError, match="SARSHIP_MAX_PIXELS"):
        ingest([tmp_path / "a.npy"], tmp_path / "o.zarr", limits=InputLimits(max_pixels=5, option="service"))


def test_cli_refuses_in_one_line_and_takes_the_settings(tmp_path):
    p = crafted_tiff(tmp_path / "strip.tif", 40000, 40000, blob=zlib.compress(bytes(2**16)))
    res = subprocess.run(
        [sys.executable, "-m", "sarship", "ingest", str(p), "--out", str(tmp_path / "o.zarr")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "--max-chunk-mb" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "o.zarr").exists()
    x = np.ones((50, 40), np.float32)
    np.save(tmp_path / "x.npy", x)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "ingest",
            str(tmp_path / "x.npy"),
            "--out",
            str(tmp_path / "x.zarr"),
            "--max-pixels",
            "1000",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2 and "50 x 40 = 2e+03 pixels, above the limit of 1e+03 (--max-pixels)" in res.stderr, (
        res.stderr
    )
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "ingest",
            str(tmp_path / "x.npy"),
            "--out",
            str(tmp_path / "x.zarr"),
            "--max-pixels",
            "2000",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr


def _vm_hwm_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc to read the server's peak memory")
def test_service_ingests_in_a_capped_child_and_moves_on(tmp_path):
    """Through ``POST /scenes``: the ingest runs in a child process, never in the API process.
    With the chunk and ratio limits raised (so the crafted strip is decoded), the child hits its
    memory cap and the job fails naming it; the declared-pixel limit refuses the sparse giant at
    once; the API process's peak memory stays small; the next good upload is ingested."""
    httpx = pytest.importorskip("httpx")
    from svc import Server, data_with_scene, free_port, wait_job

    srv = Server(
        data_with_scene(tmp_path),
        free_port(),
        SARSHIP_MAX_CHUNK_MB="1e6",
        SARSHIP_MAX_RATIO="1e9",
        SARSHIP_INGEST_MEMORY_MB="1024",
    ).start()
    try:
        u = srv.url
        strip = crafted_tiff(tmp_path / "strip.tif", 40000, 40000, blob=zlib.compress(bytes(2**16)))
        sparse = crafted_tiff(tmp_path / "sparse.tif", 200000, 200000, tile=2048, counts_zero=True)
        jobs = {}
        for f in (strip, sparse):
            r = httpx.post(f"{u}/scenes?filename={f.name}", content=f.read_bytes(), timeout=60)
            assert r.status_code == 201, r.text
            jobs[f.name] = r.json()["jobID"]
        st = wait_job(u, jobs["strip.tif"])
        assert st["status"] == "failed" and "memory cap is 1024 MiB" in st["message"], st
        st = wait_job(u, jobs["sparse.tif"])
        assert st["status"] == "failed" and "above the limit of 2e+09 (SARSHIP_MAX_PIXELS)" in st["message"], st
        x = np.random.default_rng(5).gamma(2.0, 0.5, (90, 80)).astype(np.float32)
        good = tmp_path / "good.tif"
        tifffile.imwrite(good, x)
        r = httpx.post(f"{u}/scenes?filename=good.tif", content=good.read_bytes(), timeout=60)
        assert wait_job(u, r.json()["jobID"])["status"] == "successful"
        assert _vm_hwm_mb(srv.proc.pid) < 1024, _vm_hwm_mb(srv.proc.pid)
        assert not list((srv.data / "scenes").glob(".*partial*"))
    finally:
        srv.stop()
