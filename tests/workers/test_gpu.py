"""GPU twins against the CPU references, GPU workers and routing on a real GPU cluster.

Marked ``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none).
``bash bench/gpu_suite.sh`` runs this file and the GPU benchmarks on a GPU machine.

Equality rule: window sums are bit-identical (same van Herk additions in the same order);
masks may differ only at pixels whose statistic lies within float rounding of the
threshold, which we count (``_flips``) and require to be at most a handful; statistics
agree to a relative 1e-6 (float32 output) except where noted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from sarship.pipeline import detectors
from sarship.pipeline.gpu import available

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)")]


@pytest.fixture(scope="module")
def cp():
    import cupy

    return cupy


def _flips(m_cpu, s_cpu, m_gpu, thr, rel=1e-6) -> tuple[int, int]:
    """(differing mask pixels, of which not near the threshold)."""
    d = m_cpu != m_gpu
    near = np.abs(s_cpu.astype(np.float64) - thr) <= rel * max(abs(thr), 1e-30)
    return int(d.sum()), int((d & ~near).sum())


def _run_both(name, block, halo, origin, **kw):
    spec = detectors.get(name)
    p = spec.params(**kw)
    prep = spec.prepare(p)
    import cupy

    mc, sc = spec.detect(block, halo, origin, p, prep)
    mg, sg = spec.detect(cupy.asarray(block), halo, origin, p, prep)
    assert isinstance(mg, cupy.ndarray) and mg.dtype == cupy.bool_ and sg.dtype == cupy.float32
    return mc, sc, mg.get(), sg.get(), prep


@pytest.mark.parametrize("hsum", ["direct", "transpose"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize(
    "m,halo,origin", [(3, 1, (0, 0)), (41, 20, (-20, -20)), (81, 40, (1234, 567)), (61, 45, (-7, 999)), (5, 2, (13, 4))]
)
def test_box_sum_bit_identical(cp, dtype, m, halo, origin, hsum, monkeypatch):
    from sarship.pipeline.gpu import box
    from sarship.pipeline.gpu.box import centered_box_sum as gpu
    from sarship.pipeline.tiling.boxsum import centered_box_sum as cpu

    monkeypatch.setattr(box, "HSUM", hsum)
    rng = np.random.default_rng(m)
    x = rng.gamma(1.0, 1.0, (2 * halo + 173, 2 * halo + 301)).astype(dtype)
    a = cpu(x, m, halo, origin)
    b = gpu(cp.asarray(x), m, halo, origin).get()
    assert a.shape == b.shape
    assert np.array_equal(a, b), f"{int((a != b).sum())} sums differ"


def _gamma_scene(shape, seed=0, looks=1.0):
    rng = np.random.default_rng(seed)
    x = rng.gamma(looks, 1.0 / looks, shape).astype(np.float32)
    # a few bright targets
    for _k in range(12):
        i, j = rng.integers(50, shape[0] - 50), rng.integers(50, shape[1] - 50)
        x[i : i + 4, j : j + 9] *= 60.0
    return x


@pytest.mark.parametrize("kw", [{}, {"target": 3, "guard": 21, "background": 41, "pfa": 1e-3}])
def test_ca_cfar_matches_cpu(cp, kw):
    kw = {"looks": 1.0, **kw}
    p = detectors.get("ca_cfar").params(**kw)
    halo = p.background // 2
    x = _gamma_scene((2 * halo + 700, 2 * halo + 650))
    mc, sc, mg, sg, prep = _run_both("ca_cfar", x, halo, (-halo, -halo), **kw)
    assert mc.sum() > 50
    assert np.array_equal(mc, mg)
    assert np.array_equal(sc, sg)  # same sums, same divisions: bit-identical


@pytest.mark.parametrize("domain", ["intensity", "amplitude", "db"])
def test_two_parameter_matches_cpu(cp, domain):
    kw = {"domain": domain, "pfa": 1e-3}
    p = detectors.get("two_parameter").params(**kw)
    halo = p.background // 2
    x = _gamma_scene((2 * halo + 640, 2 * halo + 610), seed=1, looks=4.0)
    mc, sc, mg, sg, prep = _run_both("two_parameter", x, halo, (100, -halo), **kw)
    assert mc.sum() > 50
    total, far = _flips(mc, sc, mg, prep["threshold"])
    assert far == 0 and total <= 2, (total, far)
    if domain != "db":
        assert np.array_equal(sc, sg)
    else:  # CUDA's log10 vs glibc's: last-bit differences propagate through the sums
        fin = np.isfinite(sc)
        np.testing.assert_allclose(sg[fin], sc[fin], rtol=1e-5, atol=1e-6)


def _quadpol(shape, p=3, seed=2):
    from sarship.pipeline.simulate import SimConfig, simulate_array

    cfg = SimConfig(kind="quadpol", shape=shape, ships=6, seed=seed, clutter="rayleigh", scr_db=10.0)
    arrs, _ = simulate_array(cfg)
    names = ["hh", "hv", "vv"] if p == 3 else ["hh", "vv"]
    return np.stack([arrs[k] for k in names], -1).astype(np.complex64)


@pytest.mark.parametrize("p", [2, 3])
@pytest.mark.parametrize("estimator", ["ring", "window"])
def test_apwf_matches_cpu(cp, p, estimator):
    kw = {"estimator": estimator, "pfa": 1e-4}
    if estimator == "window":
        kw.update(guard=1, background=31)
    prm = detectors.get("apwf").params(**kw)
    halo = prm.background // 2
    X = _quadpol((2 * halo + 300, 2 * halo + 280), p)
    mc, sc, mg, sg, prep = _run_both("apwf", X, halo, (-halo, 7), **kw)
    thr = prep["thresholds"][str(p)]
    assert mc.sum() > 10
    total, far = _flips(mc, sc, mg, thr)
    assert far == 0 and total <= 2, (total, far)
    fin = np.isfinite(sc)
    np.testing.assert_allclose(sg[fin], sc[fin], rtol=1e-6)


def test_apwf_covariance_input_matches_cpu(cp):
    X = _quadpol((2 * 30 + 200, 2 * 30 + 190), 3, seed=5)
    C = (X[..., :, None] * X[..., None, :].conj()).astype(np.complex64)
    mc, sc, mg, sg, prep = _run_both("apwf", C, 30, (-30, -30), pfa=1e-4)
    total, far = _flips(mc, sc, mg, prep["thresholds"]["3"], rel=1e-9)
    assert far == 0 and total <= 2
    fin = np.isfinite(sc) & (sc > 0)
    np.testing.assert_allclose(sg[fin], sc[fin], rtol=1e-5)


@pytest.mark.parametrize("p", [2, 3])
@pytest.mark.parametrize("lw", [1, 3])
def test_pcdm_span_psh_matches_cpu(cp, p, lw):
    from sarship.pipeline.detectors.pcdm import span_psh

    prm = detectors.get("pcdm").params(looks_window=lw)
    halo = 1 + lw // 2
    X = _quadpol((2 * halo + 257, 2 * halo + 263), p, seed=3)
    sc, pc = span_psh(X, halo, (-halo, -halo), prm)
    sg, pg = span_psh(cp.asarray(X), halo, (-halo, -halo), prm)
    assert np.array_equal(sc, sg.get())  # same sums and operations
    np.testing.assert_allclose(pg.get(), pc, rtol=1e-9, atol=1e-12)  # CUDA acos/cos: a few ulp


def test_pcdm_scene_pass_and_detect_match_cpu(cp):
    spec = detectors.get("pcdm")
    prm = spec.params()
    halo = spec.halo(prm)
    X = _quadpol((2 * halo + 400, 2 * halo + 400), 3, seed=4)
    prep = spec.prepare(prm)
    a = spec.scene_pass(X, halo, (-halo, -halo), prm, prep)
    b = spec.scene_pass(cp.asarray(X), halo, (-halo, -halo), prm, prep)
    assert a["min"] == b["min"] and a["max"] == b["max"]
    assert np.abs(a["hist"] - b["hist"]).sum() <= 4  # CUDA log vs glibc log at bin edges
    prep = {**prep, **spec.reduce([a], prm, prep)}
    mc, sc = spec.detect(X, halo, (-halo, -halo), prm, prep)
    mg, sg = spec.detect(cp.asarray(X), halo, (-halo, -halo), prm, prep)
    assert np.array_equal(mc, mg.get()) and np.array_equal(sc, sg.get())


# ------------------------------------------------------------------------ workers, routing


def _scene(tmp_path, name="s.zarr", shape=(1536, 1280), tile=512):
    from sarship.pipeline.simulate import SimConfig, simulate

    cfg = SimConfig(kind="intensity", shape=shape, ships=10, seed=8, clutter="gamma", looks=1)
    simulate(tmp_path / name, cfg, tile=tile, truth_path=tmp_path / f"{name}.truth.geojson")
    return tmp_path / name


def test_local_gpu_cluster_equals_cpu_run(tmp_path):
    from sarship.workers.jobs import run_detection

    scene = _scene(tmp_path)
    g = run_detection(scene, "ca_cfar", out_dir=tmp_path / "g", device="gpu", progress=False)
    c = run_detection(scene, "ca_cfar", out_dir=tmp_path / "c", device="cpu", progress=False)
    assert g["device"] == "gpu" and c["device"] == "cpu"
    assert {t["device"] for t in g["tiles"]["per_tile"]} == {"gpu"}
    assert all("gpu" in t["worker"] for t in g["tiles"]["per_tile"])
    import zarr

    mg = zarr.open_group(str(tmp_path / "g" / "mask.zarr"), mode="r")["mask"][:]
    mc = zarr.open_group(str(tmp_path / "c" / "mask.zarr"), mode="r")["mask"][:]
    assert np.array_equal(mg, mc)
    fg = json.loads((tmp_path / "g" / "detections.geojson").read_text())["features"]
    fc = json.loads((tmp_path / "c" / "detections.geojson").read_text())["features"]
    assert len(fg) == len(fc) > 0


@pytest.mark.parametrize("detector,kind", [("ca_cfar", "intensity"), ("apwf", "quadpol")])
def test_gpu_tiles_send_back_detected_pixels_that_give_the_cpu_detections(tmp_path, detector, kind):
    """A GPU tile sends back only its detected pixels (their coordinates, statistic and input
    value) instead of the whole mask and statistic: the detections, their properties (peak and
    mean of the input: intensity, or the span of stacked channels) and the mask equal the CPU
    run's, with 256 px tiles so that ships cross tile edges."""
    import zarr

    from sarship.pipeline.simulate import SimConfig, simulate
    from sarship.workers.jobs import run_detection

    cfg = SimConfig(
        kind=kind,
        shape=(1024, 1024),
        ships=12,
        seed=21,
        clutter="rayleigh" if kind != "intensity" else "gamma",
        looks=1,
    )
    simulate(tmp_path / "s.zarr", cfg, tile=256)
    runs, feats = {}, {}
    for device in ("gpu", "cpu"):
        runs[device] = run_detection(
            tmp_path / "s.zarr",
            detector,
            {"land_mask": "none"},
            out_dir=tmp_path / device,
            tile=256,
            device=device,
            progress=False,
        )
        feats[device] = sorted(
            (f["properties"] for f in json.loads((tmp_path / device / "detections.geojson").read_text())["features"]),
            key=lambda p: p["bbox_px"],
        )
    assert {t["device"] for t in runs["gpu"]["tiles"]["per_tile"]} == {"gpu"}
    mg = zarr.open_group(str(tmp_path / "gpu" / "mask.zarr"), mode="r")["mask"][:]
    mc = zarr.open_group(str(tmp_path / "cpu" / "mask.zarr"), mode="r")["mask"][:]
    assert np.array_equal(mg, mc) and mg.any()
    assert len(feats["gpu"]) == len(feats["cpu"]) > 0
    for g, c in zip(feats["gpu"], feats["cpu"]):
        for k in ("bbox_px", "area_px", "centroid_px", "peak_px", "peak", "mean"):
            assert g[k] == pytest.approx(c[k], rel=1e-6), (k, g, c)


def test_cuda_initialised_is_told_apart_from_an_import():
    """Zarr imports CuPy whenever it is installed; only CUDA's own initialisation keeps the
    command's workers from being forked (workers/cluster.cuda_initialised)."""
    code = (
        "import zarr, cupy\n"
        "from sarship.workers.cluster import cuda_initialised, worker_start_method\n"
        "a, m = cuda_initialised(), worker_start_method()\n"
        "cupy.zeros(1)\n"
        "print(a, m, cuda_initialised(), worker_start_method())\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "SARSHIP_WORKER_START"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "fork", "True", "spawn"]


def test_sarship_detect_forks_its_gpu_workers_and_they_use_the_gpu(tmp_path):
    """`sarship detect --device gpu` as typed: its GPU worker processes are forked from the
    command (which has not initialised CUDA) and every tile runs on the GPU, equal to the CPU run."""
    scene = _scene(tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "SARSHIP_WORKER_START"}
    runs = {}
    for device in ("gpu", "cpu"):
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "sarship",
                "detect",
                str(scene),
                "--detector",
                "ca_cfar",
                "--out",
                str(tmp_path / device),
                "--device",
                device,
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert out.returncode == 0, out.stderr
        if device == "gpu":
            assert "GPU worker processes (fork)" in out.stderr, out.stderr
        runs[device] = json.loads((tmp_path / device / "run.json").read_text())
    assert {t["device"] for t in runs["gpu"]["tiles"]["per_tile"]} == {"gpu"}
    assert runs["gpu"]["detections"] == runs["cpu"]["detections"] > 0


def test_mixed_cluster_routes_each_tile(tmp_path):
    """One GPU worker and one CPU worker on one scheduler: where each tile ran."""
    import logging

    from distributed import Client, Scheduler, SpecCluster

    from sarship.workers.gpus import visible_gpus, worker_specs
    from sarship.workers.jobs import run_detection

    scene = _scene(tmp_path)
    specs = worker_specs(visible_gpus()[:1], 1, prefix="mix-", silence_logs=logging.ERROR)
    with (
        SpecCluster(
            workers=specs,
            scheduler={"cls": Scheduler, "options": {"dashboard_address": ":0"}},
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        client.wait_for_workers(2, timeout=120)
        runs = {
            ("ca_cfar", "gpu"): run_detection(
                scene, "ca_cfar", out_dir=tmp_path / "a", client=client, device="gpu", progress=False
            ),
            ("ca_cfar", "auto"): run_detection(
                scene, "ca_cfar", out_dir=tmp_path / "b", client=client, device="auto", progress=False
            ),
            ("ca_cfar", "cpu"): run_detection(
                scene, "ca_cfar", out_dir=tmp_path / "c", client=client, device="cpu", progress=False
            ),
        }
    for (det, dev), run in runs.items():
        workers = {t["worker"] for t in run["tiles"]["per_tile"]}
        devices = {t["device"] for t in run["tiles"]["per_tile"]}
        if dev in ("gpu", "auto"):
            assert workers == {"mix-gpu" + visible_gpus()[0]} and devices == {"gpu"}, (det, dev, workers)
        else:
            assert workers == {"mix-cpu0"} and devices == {"cpu"}, (det, dev, workers)
    assert runs[("ca_cfar", "gpu")]["detections"] == runs[("ca_cfar", "cpu")]["detections"]


def test_sarship_worker_processes_with_dask_scheduler(tmp_path):
    """`dask scheduler` + `sarship worker --gpus all`: the tiles run on the pinned GPU workers."""
    scene = _scene(tmp_path, shape=(1024, 1024))
    port = 8790 + os.getpid() % 100
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    sched = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--port", str(port), "--dashboard-address", ":0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    work = None
    try:
        time.sleep(3)
        work = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "sarship",
                "worker",
                "--scheduler",
                f"tcp://127.0.0.1:{port}",
                "--gpus",
                "all",
                "--cpus",
                "1",
                "--name",
                "w",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
            text=True,
        )
        from distributed import Client

        with Client(f"tcp://127.0.0.1:{port}", timeout="30s") as client:
            from sarship.workers.cluster import gpu_procs
            from sarship.workers.gpus import visible_gpus

            n_gpu = len(visible_gpus())
            try:  # --gpu-procs defaults to the local cluster's worker processes per GPU
                client.wait_for_workers(n_gpu * gpu_procs(n_gpu) + 1, timeout=90)
            except Exception:
                work.terminate()
                pytest.fail("workers did not arrive; sarship worker said:\n" + work.communicate(timeout=30)[1][-3000:])
            info = client.scheduler_info(n_workers=-1)["workers"]
            res = sorted((w["name"], tuple(sorted(w["resources"].items()))) for w in info.values())
            assert ("w-cpu0", (("CPU", 1.0),)) in res or ("w-cpu0", (("CPU", 1),)) in res
            assert sum(name.startswith("w-gpu") for name, _ in res) == n_gpu * gpu_procs(n_gpu)
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "sarship",
                "detect",
                str(scene),
                "--detector",
                "ca_cfar",
                "--out",
                str(tmp_path / "o"),
                "--scheduler",
                f"tcp://127.0.0.1:{port}",
                "--device",
                "gpu",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert out.returncode == 0, out.stderr
        run = json.loads((tmp_path / "o" / "run.json").read_text())
        assert {t["device"] for t in run["tiles"]["per_tile"]} == {"gpu"}
        assert all(t["worker"].startswith("w-gpu") for t in run["tiles"]["per_tile"])
    finally:
        for p in (work, sched):
            if p is not None:
                p.terminate()
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize(
    "kw", [{"looks": 1.0}, {"looks": 1.0, "target": 3, "guard": 11, "background": 31, "pfa": 1e-4}]
)
def test_os_cfar_matches_cpu(cp, dtype, kw):
    p = detectors.get("os_cfar").params(**kw)
    halo = p.background // 2
    x = _gamma_scene((2 * halo + 500, 2 * halo + 450), seed=6).astype(dtype)
    x[100, 100] = np.nan  # a NaN ranks above every number; a NaN target is never detected
    mc, sc, mg, sg, prep = _run_both("os_cfar", x, halo, (-halo, -halo), **kw)
    assert mc.sum() > 50
    assert np.array_equal(mc, mg)  # exact comparisons only
    assert np.array_equal(sc, sg)


@pytest.mark.parametrize("p", [2, 3])
@pytest.mark.parametrize("coupling", ["joint", "paper"])
def test_vb_polsar_pixels_match_cpu(cp, p, coupling):
    spec = detectors.get("vb_polsar")
    prm = spec.params(coupling=coupling, sample_stride=4)
    X = _quadpol((400, 380), p, seed=9)
    prep = spec.prepare(prm)
    prep = {**prep, **spec.reduce([spec.scene_pass(X, 0, (0, 0), prm, prep)], prm, prep)}
    mc, sc = spec.detect(X, 0, (0, 0), prm, prep)
    mg, sg = spec.detect(cp.asarray(X), 0, (0, 0), prm, prep)
    mg, sg = mg.get(), sg.get()
    assert mc.sum() > 5
    thr = float(np.log1p(-prep["alpha0"]) - np.log(prep["alpha0"]))
    total, far = _flips(mc, sc, mg, thr, rel=1e-5)
    assert far == 0 and total <= 2, (total, far)
    np.testing.assert_allclose(sg, sc, rtol=1e-5, atol=1e-5)


def _lmm_scene(n, seed=12):
    """Two-component lognormal-mixture clutter (a = .7/.3, mu = 0/1, s = .5/.8) with ships."""
    rng = np.random.default_rng(seed)
    comp = rng.random((n, n)) < 0.3
    y = np.where(comp, rng.normal(1.0, 0.8, (n, n)), rng.normal(0.0, 0.5, (n, n)))
    x = np.exp(y).astype(np.float32)
    for _ in range(max(4, n // 25)):
        i, j = rng.integers(8, n - 12, 2)
        x[i : i + 3, j : j + 5] *= 80.0
    x[5, 5] = 0.0  # an unusable sample (ignored in rings, never detected)
    return x


@pytest.mark.parametrize(
    "method,n,kw",
    [
        ("exact", 48, {"guard": 5, "background": 13}),
        ("fast", 96, {"guard": 5, "background": 13}),
        ("fast", 96, {"guard": 5, "background": 13, "select": "fixed", "tail": "plugin"}),
        ("grid", 160, {}),
        ("grid", 120, {"guard": 11, "background": 31, "components": 2}),
    ],
)
def test_lmm_matches_cpu(cp, method, n, kw):
    from sarship.pipeline.tiling.windows import mirror_pad

    spec = detectors.get("lmm")
    # refuse_weight=0: the fits the CUDA code transcribes (the default's contamination refusal
    # runs on the CPU kernels for a CuPy block: tests/pipeline/test_lmm_gpu_censored.py)
    p = spec.params(method=method, pfa=1e-3, refuse_weight=0.0, **kw)
    prep = spec.prepare(p)
    halo = spec.halo(p)
    x = _lmm_scene(n)
    blk = mirror_pad(x, halo)
    origin = (-halo, -halo)
    mc, sc = spec.detect(blk, halo, origin, p, prep)
    mg, sg = spec.detect(cp.asarray(blk), halo, origin, p, prep)
    mg, sg = mg.get(), sg.get()
    assert mc.sum() > 8
    diff = int((mc != mg).sum())
    assert diff <= max(1, int(0.001 * mc.size)), (diff, int(mc.sum()), int(mg.sum()))  # the CPU forms' rule
    both = mc & mg
    np.testing.assert_allclose(sg[both], sc[both], rtol=1e-6)


def test_service_local_cluster_has_gpu_workers(tmp_path):
    """``sarship serve`` alone on a GPU machine: its local cluster has pinned workers on every
    GPU (``gpu_procs`` per GPU) besides the CPU workers; a job's tiles run on the GPU (device auto) or on the CPU
    workers (device cpu), with identical masks."""
    import httpx
    import zarr
    from svc import Server, data_with_scene, free_port, wait_job

    from sarship.workers.gpus import visible_gpus

    data = data_with_scene(tmp_path, shape=(700, 600), tile=256)
    gpus = visible_gpus()  # device nodes: no CUDA or NVML in this process
    srv = Server(data, free_port(), SARSHIP_WORKERS="2", CUDA_VISIBLE_DEVICES=",".join(gpus)).start()
    try:
        from sarship.workers.cluster import gpu_procs

        n_gpu = len(gpus) * gpu_procs(len(gpus))  # worker processes per GPU (same machine, same rule)
        assert httpx.get(srv.url + "/readyz").json()["checks"]["workers"] == n_gpu + 2
        runs = {}
        for device in ("auto", "cpu"):
            r = httpx.post(
                srv.url + "/processes/ca_cfar/execution",
                json={"inputs": {"scene": "s1", "guard": 11, "background": 31, "min_area_px": 1, "device": device}},
            )
            st = wait_job(srv.url, r.json()["jobID"])
            assert st["status"] == "successful", st
            run = httpx.get(f"{srv.url}/jobs/{st['jobID']}/results/metrics").json()
            runs[device] = (run, zarr.open_array(str(data / "jobs" / st["jobID"] / "mask.zarr" / "mask"), mode="r")[:])
        auto, cpu = runs["auto"][0], runs["cpu"][0]
        assert auto["device"] == "gpu" and {t["device"] for t in auto["tiles"]["per_tile"]} == {"gpu"}, auto
        assert cpu["device"] == "cpu" and {t["device"] for t in cpu["tiles"]["per_tile"]} == {"cpu"}, cpu
        np.testing.assert_array_equal(runs["auto"][1], runs["cpu"][1])
        assert auto["detections"] == cpu["detections"] > 5
    finally:
        srv.stop()
