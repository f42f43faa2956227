"""Issue 11, data safety and clear errors: no silent replacement of outputs, never a write
inside an input, absolute paths for remote workers, warnings and dashboard notes on stderr
as clean lines, a helpful message for a file given as a scene."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.cli.test_cli import assert_clean_error, listing, sarship, sarship_here
from tests.conftest import dask_processes, fsize_limit, write_scene

# Each test runs one refusal (and each success) as a real ``sarship`` process; its further refusals
# run in this process (tests/cli/test_cli.py ``sarship_here``: no interpreter start-up per command).


@pytest.fixture()
def scene(tmp_path):
    """A small scene without pixel spacing (so length limits cannot be applied)."""
    rng = np.random.default_rng(0)
    x = rng.gamma(2.0, 0.5, (96, 80)).astype(np.float32)
    x[40:44, 30:36] += 60.0
    return write_scene(tmp_path / "small.zarr", {"intensity": x}, tile=64, looks=2.0)


def _tree(p: Path) -> dict[str, bytes]:
    return {str(f.relative_to(p)): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


# ----------------------------------------------------------------------------- simulate


def test_simulate_refuses_existing_store_and_truth(tmp_path):
    out = tmp_path / "s.zarr"
    args = ("simulate", out, "--shape", "64x64", "--ships", "1", "--tile", "64")
    assert sarship(*args).returncode == 0
    truth = Path(f"{out}.truth.geojson")
    before, truth_before = _tree(out), truth.read_bytes()
    res = sarship(*args, "--seed", "7")
    assert_clean_error(res, "s.zarr", "--overwrite")
    assert _tree(out) == before and truth.read_bytes() == truth_before
    # a truth file alone is protected too
    other = tmp_path / "t.geojson"
    other.write_text("keep")
    res = sarship_here("simulate", tmp_path / "new.zarr", "--shape", "64x64", "--ships", "1", "--truth", other)
    assert_clean_error(res, "t.geojson", "--overwrite")
    assert other.read_text() == "keep" and not (tmp_path / "new.zarr").exists()
    res = sarship_here(*args, "--seed", "7", "--overwrite")
    assert res.returncode == 0, res.stderr
    assert truth.read_bytes() != truth_before
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


# ----------------------------------------------------------------------------- ingest


def test_ingest_refuses_existing_and_inside_input(tmp_path):
    src = tmp_path / "x.npy"
    np.save(src, np.random.default_rng(1).gamma(2.0, 0.5, (64, 64)).astype(np.float32))
    out = tmp_path / "x.zarr"
    assert sarship("ingest", src, "--out", out).returncode == 0
    before = _tree(out)
    res = sarship("ingest", src, "--out", out, "--looks", "3")
    assert_clean_error(res, "x.zarr", "--overwrite")
    assert _tree(out) == before
    res = sarship_here("ingest", src, "--out", out, "--looks", "3", "--overwrite")
    assert res.returncode == 0, res.stderr
    # never inside (or equal to) an input, even with --overwrite
    for bad in (out, out / "inner.zarr"):
        res = sarship_here("ingest", out, "--out", bad, "--overwrite")
        assert_clean_error(res, "input")
    res = sarship_here("ingest", src, "--out", src / "y.zarr", "--overwrite")
    assert_clean_error(res, "input")
    assert sorted(os.listdir(out)) == sorted(os.listdir(tmp_path / "x.zarr"))
    assert not (out / "inner.zarr").exists()


def test_ingest_spacing(tmp_path):
    from sarship.pipeline.scene import open_scene

    src = tmp_path / "x.npy"
    np.save(src, np.random.default_rng(1).gamma(2.0, 0.5, (64, 64)).astype(np.float32))
    res = sarship("ingest", src, "--out", tmp_path / "x.zarr", "--spacing", "2.5,10")
    assert res.returncode == 0, res.stderr
    sc = open_scene(tmp_path / "x.zarr")
    assert sc.pixel_spacing_m == (2.5, 10.0) and sc.attrs["pixel_spacing_source"] == "argument"
    # a Zarr input's spacing is overridden as well
    res = sarship_here("ingest", tmp_path / "x.zarr", "--out", tmp_path / "y.zarr", "--spacing", "3,4")
    assert res.returncode == 0, res.stderr
    assert open_scene(tmp_path / "y.zarr").pixel_spacing_m == (3.0, 4.0)
    for bad in ("1", "1,2,3", "0,2", "-1,2", "a,b", "nan,1"):
        run = sarship if bad == "1" else sarship_here
        res = run("ingest", src, "--out", tmp_path / "z.zarr", "--spacing", bad)
        assert_clean_error(res, "spacing")
    assert not (tmp_path / "z.zarr").exists()


# ----------------------------------------------------------------------------- detect, demo


def test_detect_refuses_nonempty_out_and_inside_scene(scene, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = sarship("detect", scene, "--detector", "ca_cfar", "--out", out)
    assert_clean_error(res, "'", "--overwrite")
    assert listing(out) == ["notes.txt"]
    # never inside the scene store, even with --overwrite
    before = _tree(scene)
    for bad in (scene / "run", scene, scene / "intensity"):
        res = sarship_here("detect", scene, "--detector", "ca_cfar", "--out", bad, "--overwrite")
        assert_clean_error(res, "small.zarr", "inside")
    assert _tree(scene) == before and not (scene / "run").exists()
    res = sarship("detect", scene, "--detector", "ca_cfar", "--out", out, "--overwrite")
    assert res.returncode == 0, res.stderr
    assert listing(out)[:1] == ["detections.geojson"] and (out / "notes.txt").read_text() == "mine"
    # land.zarr: ca_cfar's default land_mask=texture writes its (here empty) mask beside the detection mask
    assert {"detections.geojson", "mask.zarr", "land.zarr", "run.json", "notes.txt"} == set(os.listdir(out))


def test_run_detection_api_overwrite(scene, tmp_path):
    from sarship.pipeline.errors import InputError
    from sarship.workers.jobs import run_detection

    out = tmp_path / "o"
    out.mkdir()
    (out / "run.json").write_text("{}")
    with pytest.raises(InputError, match="--overwrite"):  # refused before any cluster is used
        run_detection(scene, "ca_cfar", out_dir=out, client=object(), progress=False)
    with pytest.raises(InputError, match="inside"):
        run_detection(scene, "ca_cfar", out_dir=scene / "o", client=object(), progress=False, overwrite=True)
    assert (out / "run.json").read_text() == "{}"


def test_demo_refuses_nonempty_out(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    res = sarship("demo", "--out", out, "--shape", "256x256", "--ships", "1")
    assert_clean_error(res, "demo", "--overwrite")
    assert listing(out) == ["keep.txt"]


@pytest.mark.parametrize("name,fmt", [("x.npy", "npy"), ("x.jpg", "jpg"), ("x.tif", "tif")])
def test_detect_on_a_file_says_ingest(tmp_path, name, fmt):
    f = tmp_path / name
    if fmt == "npy":
        np.save(f, np.ones((8, 8), np.float32))
    elif fmt == "jpg":
        f.write_bytes(b"\xff\xd8\xff\xe0" + b"\x00" * 64)
    else:
        f.write_bytes(b"II*\x00" + b"\x00" * 64)
    run = sarship if fmt == "npy" else sarship_here  # one real process
    res = run("detect", f, "--detector", "ca_cfar", "--out", tmp_path / "o")
    assert_clean_error(res, name, "sarship ingest", "--out")
    assert "GroupNotFound" not in res.stderr and not (tmp_path / "o").exists()


def test_detect_prints_run_warnings(scene, tmp_path):
    out = tmp_path / "o"
    res = sarship("detect", scene, "--detector", "ca_cfar", "--out", out, "--set", "min_length_m=20")
    assert res.returncode == 0, res.stderr
    warnings = json.loads((out / "run.json").read_text())["warnings"]
    assert warnings
    lines = [ln for ln in res.stderr.splitlines() if "warning" in ln.lower()]
    assert lines == [f"sarship detect: warning: {w}" for w in warnings], res.stderr
    assert "min_length_m" in lines[0]


# ----------------------------------------------------------------------------- cluster


def test_dashboard_port_taken_is_one_clean_line(scene, tmp_path):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.bind(("", 8787))
        sock.listen(1)
    except OSError:
        sock.close()
        pytest.skip("port 8787 is already in use by something else")
    try:
        res = sarship("detect", scene, "--detector", "ca_cfar", "--out", tmp_path / "o")
    finally:
        sock.close()
    assert res.returncode == 0, res.stderr
    assert "UserWarning" not in res.stderr and "site-packages" not in res.stderr, res.stderr
    dash = [ln for ln in res.stderr.splitlines() if "dashboard" in ln]
    assert len(dash) == 1 and "http://" in dash[0] and ":8787/" not in dash[0] and "8787" in dash[0], dash


def test_local_cluster_dashboard_listens_on_loopback_only():
    """The dashboard has no access control: the local cluster of ``sarship detect`` binds it to
    127.0.0.1 (issue 12: it listened on every interface)."""
    psutil = pytest.importorskip("psutil")
    from sarship.workers.cluster import connect

    with connect(None, n_workers=1, echo=False) as client:
        port = int(client.dashboard_link.split(":")[2].split("/")[0])
        me = psutil.Process()
        listening = set()
        for p in [me, *me.children(recursive=True)]:
            try:
                listening |= {
                    c.laddr.ip
                    for c in p.net_connections(kind="inet")
                    if c.status == psutil.CONN_LISTEN and c.laddr.port == port
                }
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
    assert listening == {"127.0.0.1"}, listening


@pytest.fixture()
def remote_cluster(tmp_path):
    """A `dask scheduler` and a `dask worker` whose working folder is another temporary folder."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    yield from dask_processes(tmp_path, {"w": []}, cwd=elsewhere)


def test_relative_scene_with_workers_in_another_folder(scene, tmp_path, remote_cluster):
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "detect",
            scene.name,
            "--detector",
            "ca_cfar",
            "--scheduler",
            remote_cluster,
            "--out",
            "o",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    run = json.loads((tmp_path / "o" / "run.json").read_text())
    assert run["detections"] >= 1 and run["tiles"]["count"] == 4
    assert not (tmp_path / "elsewhere" / "small.zarr").exists() and not (tmp_path / "elsewhere" / "o").exists()


def test_no_space_to_write_is_exit_3_in_one_line_and_leaves_nothing(tmp_path):
    """A full disk is not bad input: `sarship ingest` meeting a real write limit (RLIMIT_FSIZE,
    the kernel's EFBIG, as a full disk's ENOSPC) says so in one line, exit 3, and removes its
    temporary store (issue 12)."""
    x = np.random.default_rng(0).gamma(2.0, 0.5, (1024, 1024)).astype(np.float32)
    np.save(tmp_path / "x.npy", x)
    out = tmp_path / "out"
    out.mkdir()

    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "ingest",
            str(tmp_path / "x.npy"),
            "--out",
            str(out / "x.zarr"),
            "--tile",
            "1024",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=fsize_limit(2**20),
    )  # writes past 1 MiB fail
    assert res.returncode == 3, (res.returncode, res.stderr)
    assert len(res.stderr.strip().splitlines()) == 1 and "no space to write" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and os.listdir(out) == [], os.listdir(out)


# ----------------------------------------------------------------------------- output claims


def test_claim_output_is_exclusive_and_a_dead_holder_blocks_nothing(tmp_path):
    """:func:`claim_output`: a second claim of one output is refused naming the holder; a claim
    file left by a process that died (its lock went with it) is taken over; the claim file goes
    at release, and parents it made are removed again when still empty."""
    from sarship.pipeline.errors import InputError
    from sarship.pipeline.scene import claim_output, claim_path

    out = tmp_path / "a" / "b" / "out"
    with claim_output(out, create_parents=True):
        assert claim_path(out).read_text().startswith(f"pid {os.getpid()} on ")
        with pytest.raises(InputError, match=f"being written by another sarship command \\(pid {os.getpid()} "):
            with claim_output(out, create_parents=True):
                pass
    assert not (tmp_path / "a").exists()  # the claim file and the parents it made
    (tmp_path / ".x.sarship-claim").write_text("pid 999999 on elsewhere\n")  # a crashed holder's file
    with claim_output(tmp_path / "x"):
        assert claim_path(tmp_path / "x").read_text().startswith(f"pid {os.getpid()} ")
    assert not (tmp_path / ".x.sarship-claim").exists()
    with claim_output(tmp_path / "missing" / "y"):  # no parent, no claim: the writer's own check says so
        assert not (tmp_path / "missing").exists()


def test_a_held_output_refuses_another_command(tmp_path):
    """While another command holds ``--out`` (here: this process), ``sarship ingest`` to it exits 2
    with one line naming the holder, and writes nothing."""
    from sarship.pipeline.scene import claim_output

    src = tmp_path / "x.npy"
    np.save(src, np.random.default_rng(1).gamma(2.0, 0.5, (64, 64)).astype(np.float32))
    with claim_output(tmp_path / "x.zarr"):
        res = sarship("ingest", src, "--out", tmp_path / "x.zarr")
    assert_clean_error(res, "x.zarr", "being written by another sarship command", f"pid {os.getpid()}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.npy"]


@pytest.mark.parametrize("command", ["ingest", "detect"])
def test_two_commands_to_one_new_out_never_both_succeed(command, scene, tmp_path):
    """Two ``sarship detect`` (or ``ingest``) started together to the same new ``--out`` without
    ``--overwrite``: exactly one succeeds; the other exits 2 with one line (refused while the
    first holds the output, or finding its outputs), and the winner's outputs are intact."""
    out = tmp_path / ("both.zarr" if command == "ingest" else "both")
    args = (
        ["ingest", scene, "--out", out]
        if command == "ingest"
        else ["detect", scene, "--detector", "ca_cfar", "--out", out]
    )
    from tests.cli.test_cli import ENV

    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "sarship", *map(str, args)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        for _ in range(2)
    ]
    results = [(p.wait(timeout=240), *p.communicate()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    loser = next(r for r in results if r[0] == 2)
    lines = [ln for ln in loser[2].splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in loser[2], loser
    assert "being written by another sarship command" in lines[0] or "--overwrite" in lines[0], lines
    assert not list(tmp_path.glob("*.sarship-claim")) and not list(tmp_path.glob(".*partial*"))
    if command == "detect":
        assert json.loads((out / "run.json").read_text())["detections"] >= 1
    else:
        from sarship.pipeline.scene import open_scene

        assert open_scene(out).shape == (96, 80)
