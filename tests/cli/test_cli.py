"""The command line as users run it: subprocesses, exit codes, one-line errors, no debris."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import write_scene

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
ENV.pop("SARSHIP_DEBUG", None)


def sarship(*args, cwd=None, timeout=240, env=None):
    return subprocess.run(
        [sys.executable, "-m", "sarship", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={**ENV, **(env or {})},
        timeout=timeout,
    )


def sarship_here(*args, env=None):
    """``sarship ARGS`` run by :func:`sarship.cli.main` in this process, returned as :func:`sarship`
    returns it: without a new interpreter's start-up and imports (seconds a command on the 2-core CI
    machine). For the many arguments and inputs refused before any work; each test of those keeps a
    real ``sarship`` process for one of its commands. Warnings reach stderr as in a process of its
    own (those a process hides by default left out)."""
    import contextlib
    import io
    import warnings

    from sarship.cli import main

    argv = [str(a) for a in args]
    saved = dict(os.environ)
    os.environ.pop("SARSHIP_DEBUG", None)
    os.environ.update(env or {})
    out, err = io.StringIO(), io.StringIO()
    try:
        with (
            warnings.catch_warnings(record=True) as seen,
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
        ):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse's usage errors and --help
                if isinstance(exc.code, str):
                    print(exc.code, file=sys.stderr)
                code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    finally:
        os.environ.clear()
        os.environ.update(saved)
    for w in seen:
        if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)):
            err.write(warnings.formatwarning(w.message, w.category, w.filename, w.lineno))
    return subprocess.CompletedProcess(["sarship", *argv], code, out.getvalue(), err.getvalue())


def assert_clean_error(res, *words):
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.stderr
    for w in words:
        assert w.lower() in lines[0].lower(), (w, lines[0])


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture()
def small_scene(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.gamma(2.0, 0.5, (96, 80)).astype(np.float32)
    x[40:44, 30:36] += 60.0
    return write_scene(tmp_path / "small.zarr", {"intensity": x}, tile=64, looks=2.0)


def test_help_for_every_command():
    res = sarship("--help")  # a real process; each command's help in this one
    assert res.returncode == 0 and "usage" in res.stdout.lower()
    for cmd in ("simulate", "ingest", "detect", "evaluate", "detectors", "demo"):
        res = sarship_here(cmd, "--help")
        assert res.returncode == 0 and "usage" in res.stdout.lower(), cmd


def test_detectors_json_lists_contract_names():
    res = sarship("detectors", "--json")
    assert res.returncode == 0
    info = {d["name"]: d for d in json.loads(res.stdout)}
    assert {"two_parameter", "ca_cfar", "os_cfar"} <= set(info)
    for d in info.values():
        for key in (
            "pfa",
            "target",
            "guard",
            "background",
            "looks",
            "min_area_px",
            "max_area_px",
            "min_length_m",
            "max_length_m",
            "merge_px",
        ):
            assert key in d["parameters"], (d["name"], key)


def test_unknown_detector(small_scene, tmp_path):
    res = sarship("detect", small_scene, "--detector", "nope", "--out", tmp_path / "o")
    assert_clean_error(res, "nope", "ca_cfar")
    assert not (tmp_path / "o").exists() or listing(tmp_path / "o") == []


@pytest.mark.parametrize(
    "setting,word",
    [
        ("pfa=2", "pfa"),
        ("pfa=abc", "pfa"),
        ("guard=40", "guard"),
        ("background=11", "background"),
        ("target=0", "target"),
        ("looks=-1", "looks"),
        ("merge_px=-3", "merge_px"),
        ("colour=red", "colour"),
        ("pfa", "key=value"),
    ],
)
def test_out_of_range_parameters(small_scene, tmp_path, setting, word):
    out = tmp_path / "o"
    # in this process (test_unknown_detector: the same refusal as a real process's one line)
    res = sarship_here("detect", small_scene, "--detector", "ca_cfar", "--set", setting, "--out", out)
    assert_clean_error(res, word)
    assert not out.exists() or listing(out) == []


def test_missing_and_garbage_scene(tmp_path):
    res = sarship("detect", tmp_path / "none.zarr", "--detector", "ca_cfar", "--out", tmp_path / "o")
    assert_clean_error(res, "none.zarr")
    junk = tmp_path / "junk.zarr"
    junk.write_bytes(b"\x00garbage" * 100)
    res = sarship_here("detect", junk, "--detector", "ca_cfar", "--out", tmp_path / "o")
    assert_clean_error(res, "junk.zarr")


def test_ingest_garbage_and_wrong_dimensions(tmp_path):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00" + os.urandom(200))
    res = sarship("ingest", bad, "--out", tmp_path / "bad.zarr")
    assert_clean_error(res, "bad.tif")
    np.save(tmp_path / "cube.npy", np.zeros((4, 5, 6, 7), np.float32))
    res = sarship_here("ingest", tmp_path / "cube.npy", "--out", tmp_path / "cube.zarr")
    assert_clean_error(res, "cube.npy")
    np.save(tmp_path / "line.npy", np.zeros(10, np.float32))
    res = sarship_here("ingest", tmp_path / "line.npy", "--out", tmp_path / "line.zarr")
    assert_clean_error(res, "line.npy")
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    res = sarship_here("ingest", txt, "--out", tmp_path / "notes.zarr")
    assert_clean_error(res, "notes.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.tif", "cube.npy", "line.npy", "notes.txt"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_unwritable_output_nonroot(small_scene, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    res = sarship("detect", small_scene, "--detector", "ca_cfar", "--out", ro / "o")
    assert_clean_error(res, "ro")


def test_unwritable_output(small_scene, tmp_path):
    # a path below a regular file cannot be created, even by root
    f = tmp_path / "file"
    f.write_text("x")
    res = sarship("detect", small_scene, "--detector", "ca_cfar", "--out", f / "o")
    assert_clean_error(res, "file")
    res = sarship_here("simulate", f / "s.zarr", "--shape", "64x64", "--ships", "1")
    assert_clean_error(res)
    res = sarship_here("detect", small_scene, "--detector", "ca_cfar", "--out", f)
    assert_clean_error(res, "file")
    assert f.read_text() == "x"


def test_bad_simulate_arguments(tmp_path):
    res = sarship("simulate", tmp_path / "s.zarr", "--shape", "12by12")
    assert_clean_error(res, "shape")
    res = sarship_here("simulate", tmp_path / "s.zarr", "--shape", "64x64", "--looks", "-2")
    assert_clean_error(res, "looks")
    assert not (tmp_path / "s.zarr").exists()


def test_simulate_detect_evaluate_end_to_end(tmp_path):
    scene = tmp_path / "scene.zarr"
    # simulate and evaluate in this process (as processes: test_output_safety.py's simulate, test_realdata.py's
    # evaluate); the detections as commands
    res = sarship_here(
        "simulate",
        scene,
        "--shape",
        "512x384",
        "--ships",
        "6",
        "--seed",
        "4",
        "--looks",
        "4",
        "--scr-db",
        "18",
        "--tile",
        "256",
    )
    assert res.returncode == 0, res.stderr
    truth = Path(f"{scene}.truth.geojson")
    assert truth.exists()
    out = tmp_path / "run"
    res = sarship(
        "detect",
        scene,
        "--detector",
        "ca_cfar",
        "--out",
        out,
        "--tile",
        "200",
        "--set",
        "pfa=1e-6",
        "--set",
        "min_area_px=2",
        "--set",
        "merge_px=5",
    )
    assert res.returncode == 0, res.stderr
    assert "dashboard" in res.stderr and "tiles" in res.stderr  # cluster address and progress
    assert listing(out) and {"mask.zarr", "detections.geojson", "run.json"} <= set(os.listdir(out))
    assert not [p for p in os.listdir(out) if p.startswith(".")]
    run = json.loads((out / "run.json").read_text())
    assert run["tiles"]["count"] == 6 and run["device"] == "cpu"
    assert all(t["worker"] for t in run["tiles"]["per_tile"])
    assert run["parameters"]["looks"] == 4.0 and run["prepared"]["threshold"] > 1
    res = sarship_here("evaluate", out / "detections.geojson", "--truth", truth, "--json")
    assert res.returncode == 0, res.stderr
    scores = json.loads(res.stdout)
    assert scores["n_truth"] == 6 and scores["fom"] >= 0.8, scores
    # re-running into the same folder is refused without --overwrite, then replaces the outputs atomically
    res = sarship_here("detect", scene, "--detector", "os_cfar", "--out", out, "--tile", "256")
    assert_clean_error(res, "--overwrite")  # (a process's refusal: tests/workers/test_output_safety.py)
    assert json.loads((out / "run.json").read_text())["detector"] == "ca_cfar"
    res = sarship("detect", scene, "--detector", "os_cfar", "--out", out, "--tile", "256", "--overwrite")
    assert res.returncode == 0, res.stderr
    assert json.loads((out / "run.json").read_text())["detector"] == "os_cfar"


def test_demo_main_job(tmp_path):
    """The README's main job (smaller scene): simulate, detect on a local cluster, score."""
    out = tmp_path / "demo"
    res = sarship("demo", "--out", out, "--shape", "1536x1536", "--ships", "8", "--tile", "512")
    assert res.returncode == 0, res.stderr
    for key in ("scene:", "truth:", "detections:", "mask:", "run:", "scores:"):
        assert key in res.stdout, key
    scores = json.loads((out / "scores.json").read_text())
    assert scores["n_truth"] == 8 and scores["fom"] >= 0.8, scores
    assert (out / "detect" / "mask.zarr").is_dir() and (out / "detect" / "run.json").is_file()
