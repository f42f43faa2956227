"""The warm cluster (``sarship warm``; sarship/warm.py): ``sarship detect`` runs on a local
cluster kept running between commands, with the same outputs, messages and exit codes as on a
cluster of its own; interrupted commands leave nothing; commands it cannot take run on their
own cluster and say why."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from sarship import warm

pytestmark = pytest.mark.skipif(not warm.supported(), reason="the warm cluster needs Linux's Unix socket peer IDs")


def _env(sock: Path) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "SARSHIP_WARM_SOCKET": str(sock)}
    env.pop("SARSHIP_DEBUG", None)
    env.pop("SARSHIP_WARM", None)
    return env


def run(sock, *args, cwd=None, env=None, timeout=240):
    # never the repository's folder: there `python -m sarship` would import the checkout, elsewhere the
    # installed copy, and the warm process refuses commands of another copy than its own
    return subprocess.run(
        [sys.executable, "-m", "sarship", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd or tempfile.gettempdir(),
        env={**_env(sock), **(env or {})},
        timeout=timeout,
    )


#: ``python -m sarship`` with SIGINT handled as in a terminal's foreground command: a test run from a
#: background job (a CI script, ``cmd &``) passes SIGINT ignored to its children, and Python keeps
#: an inherited "ignore", so a Ctrl-C test would send a signal the command never sees
AS_IN_A_TERMINAL = [
    sys.executable,
    "-c",
    "import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "runpy.run_module('sarship', run_name='__main__', alter_sys=True)",
]


@pytest.fixture()
def sockdir():
    d = Path(tempfile.mkdtemp(prefix="sw-"))  # short: a Unix socket path has at most 107 bytes
    os.chmod(d, 0o700)
    yield d
    st = warm.status(d / "warm.sock")
    if st is not None:  # a test left its warm process running: end it (clean-up, not a check)
        try:
            os.kill(st["pid"], signal.SIGTERM)
            for _ in range(100):
                os.kill(st["pid"], 0)
                time.sleep(0.1)
        except ProcessLookupError:
            pass
    import shutil

    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="module")
def warm_cpu():
    """One warm process of 1 CPU worker for the tests of this module that use it (a second worker
    process costs its start-up, a few seconds of the 2-core test machine, and no test needs it)."""
    sockdir = Path(tempfile.mkdtemp(prefix="sw-"))
    os.chmod(sockdir, 0o700)
    sock = sockdir / "warm.sock"
    res = run(
        sock,
        "warm",
        "start",
        "--device",
        "cpu",
        "--workers",
        "1",
        "--idle-timeout",
        "300",
        "--dashboard",
        "127.0.0.1:0",
    )
    assert res.returncode == 0, res.stderr
    assert "warm cluster ready" in res.stdout and "1 worker processes" in res.stdout
    assert "warm-up (ca_cfar, " in (sockdir / "warm.sock.log").read_text()
    yield sock
    res = run(sock, "warm", "stop")
    assert res.returncode == 0 and "stopped" in res.stdout, (res.stdout, res.stderr)
    assert not sock.exists()
    import shutil

    shutil.rmtree(sockdir, ignore_errors=True)


def _scene(tmp_path, shape=(600, 500), tile=256):
    from tests.conftest import write_scene

    rng = np.random.default_rng(3)
    x = rng.gamma(1.0, 1.0, shape).astype(np.float32)
    for r, c in ((100, 120), (300, 50), (450, 400), (250, 260)):
        x[r : r + 5, c : c + 9] += 300.0
    return write_scene(tmp_path / "scene.zarr", {"intensity": x}, tile=tile, looks=1.0)


def _mask(out: Path) -> np.ndarray:
    import zarr

    return np.asarray(zarr.open_array(str(out / "mask.zarr" / "mask"), mode="r")[...])


def test_detect_on_the_warm_cluster_equals_its_own_cluster(warm_cpu, tmp_path):
    _scene(tmp_path)
    before = warm.status(warm_cpu)["commands"]
    a = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "warm", cwd=tmp_path)
    assert a.returncode == 0, a.stderr
    assert "sarship: warm cluster, 1 worker processes" in a.stderr
    assert "local Dask cluster" not in a.stderr
    b = run(
        warm_cpu,
        "detect",
        "scene.zarr",
        "--detector",
        "ca_cfar",
        "--out",
        "own",
        cwd=tmp_path,
        env={"SARSHIP_WARM": "0"},
    )
    assert b.returncode == 0, b.stderr
    assert "local Dask cluster" in b.stderr and "warm cluster" not in b.stderr
    # the same lines on stdout, with the paths of each run's folder (relative paths: the command's folder)
    assert a.stdout.replace("/warm/", "/own/") == b.stdout
    assert str(tmp_path / "warm" / "detections.geojson") in a.stdout
    fa = json.loads((tmp_path / "warm" / "detections.geojson").read_text())["features"]
    fb = json.loads((tmp_path / "own" / "detections.geojson").read_text())["features"]
    assert len(fa) == 4 and [f["properties"]["bbox_px"] for f in fa] == [f["properties"]["bbox_px"] for f in fb]
    np.testing.assert_array_equal(_mask(tmp_path / "warm"), _mask(tmp_path / "own"))
    assert not list(tmp_path.glob("*/.sarship-partial-*"))

    # the command line's refusals, messages and exit codes, from the warm process
    again = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "warm", cwd=tmp_path)
    assert again.returncode == 2 and "pass --overwrite" in again.stderr and "Traceback" not in again.stderr
    assert run(warm_cpu, "detect", "missing.zarr", "--detector", "ca_cfar", cwd=tmp_path).returncode == 2
    bad = run(warm_cpu, "detect", "scene.zarr", "--detector", "nope", cwd=tmp_path)
    assert bad.returncode == 2 and "unknown detector 'nope'" in bad.stderr
    usage = run(warm_cpu, "detect", "scene.zarr", cwd=tmp_path)
    assert usage.returncode == 2 and "--detector" in usage.stderr
    helped = run(warm_cpu, "detect", "--help", env={"COLUMNS": "100"})
    from tests.cli.test_cli import sarship_here

    own_help = sarship_here("detect", "--help", env={"COLUMNS": "100"})  # the command line's own, in this process
    assert helped.returncode == 0 and helped.stdout.startswith("usage: sarship detect")
    assert helped.stdout == own_help.stdout  # the command's terminal width, not the warm process's
    over = run(
        warm_cpu,
        "detect",
        "scene.zarr",
        "--detector",
        "ca_cfar",
        "--out",
        "warm",
        "--overwrite",
        "--set",
        "pfa=1e-3",
        cwd=tmp_path,
    )
    assert over.returncode == 0, over.stderr
    assert json.loads((tmp_path / "warm" / "run.json").read_text())["parameters"]["pfa"] == pytest.approx(1e-3)
    st = run(warm_cpu, "warm", "status")
    assert st.returncode == 0 and f"{before + 7} commands run" in st.stdout, st.stdout


def test_commands_the_warm_cluster_cannot_take_run_on_their_own(warm_cpu, tmp_path, monkeypatch):
    _scene(tmp_path)
    before = warm.status(warm_cpu)["commands"]
    # another setting of the cluster's: said, then run on a cluster of its own, with the command's setting
    res = run(
        warm_cpu,
        "detect",
        "scene.zarr",
        "--detector",
        "ca_cfar",
        "--out",
        "o1",
        "--device",
        "cpu",
        cwd=tmp_path,
        env={"SARSHIP_BLOCK_CACHE_MB": "0"},
    )
    assert res.returncode == 0, res.stderr
    assert "not on the warm cluster: it was started with another SARSHIP_BLOCK_CACHE_MB" in res.stderr
    assert "sarship: local Dask cluster" in res.stderr and "sarship: warm cluster" not in res.stderr
    tiles = json.loads((tmp_path / "o1" / "run.json").read_text())["tiles"]["per_tile"]
    assert tiles and {t["block_from"] for t in tiles} == {"scene"}  # the command's own setting: no read kept
    assert warm.status(warm_cpu)["commands"] == before
    # the warm process's other refusals, by its own rule and state (each run as a command, falling back to
    # a cluster of its own as above: the slow test below): a CPU-only warm cluster and --device gpu; an
    # abbreviation of --scheduler, which passes the client's check and is refused after parsing
    from sarship.cli import build_parser  # the warm process is handed the command line's parser
    from sarship.warm_process import _parse_quietly, _refusal

    state = warm.status(warm_cpu)
    req = {"identity": state["identity"], "env": state["env"]}
    cmd = ["detect", "scene.zarr", "--detector", "ca_cfar"]
    assert _refusal(req, state, _parse_quietly(cmd, build_parser)) == ""
    assert _refusal(req, state, _parse_quietly([*cmd, "--device", "gpu"], build_parser)).startswith(
        "it has no GPU worker"
    )
    assert _refusal(req, state, _parse_quietly([*cmd, "--sched", "local"], build_parser)) == "--scheduler was given"
    # --scheduler (an address or `local`), SARSHIP_SCHEDULER and SARSHIP_WARM=0 never go to it; other commands
    # neither (they run here, as always)
    monkeypatch.delenv("SARSHIP_WARM", raising=False)
    monkeypatch.delenv("SARSHIP_SCHEDULER", raising=False)
    assert warm.eligible(["detect", "s.zarr", "--detector", "ca_cfar"])
    for argv in (
        ["detect", "s.zarr", "--scheduler", "local"],
        ["detect", "s.zarr", "--scheduler=tcp://h:1"],
        ["ingest", "x.npy", "--out", "x.zarr"],
        ["--version"],
        ["warm", "status"],
    ):
        assert not warm.eligible(argv), argv
    monkeypatch.setenv("SARSHIP_SCHEDULER", "tcp://h:8786")
    assert not warm.eligible(["detect", "s.zarr"])
    monkeypatch.delenv("SARSHIP_SCHEDULER")
    monkeypatch.setenv("SARSHIP_WARM", "0")
    assert not warm.eligible(["detect", "s.zarr"])
    monkeypatch.delenv("SARSHIP_WARM")
    assert warm.eligible([*cmd, "--sched", "local"])


@pytest.mark.slow  # two more detections on clusters of their own; the refusals: test_commands_the_warm_...
def test_refused_commands_say_why_and_run_on_their_own(warm_cpu, tmp_path):
    _scene(tmp_path)
    # a CPU-only warm cluster and --device gpu: the command's own cluster decides
    res = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o2", "--device", "gpu", cwd=tmp_path)
    assert "not on the warm cluster: it has no GPU worker" in res.stderr
    # an abbreviation of --scheduler passes the client's check: the warm process refuses it after parsing
    res = run(
        warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o3", "--sched", "local", cwd=tmp_path
    )
    assert res.returncode == 0 and "not on the warm cluster: --scheduler was given" in res.stderr, res.stderr


def test_interrupted_commands_leave_nothing_and_the_cluster_goes_on(warm_cpu, tmp_path):
    # the warm process catches SIGINT (its watcher interrupts a command with it) even when it was
    # started, like this module's from a CI job in the background, with SIGINT ignored
    pid = warm.status(warm_cpu)["pid"]
    caught = next(int(line.split()[1], 16) for line in open(f"/proc/{pid}/status") if line.startswith("SigCgt"))
    assert caught & (1 << (signal.SIGINT - 1)), "the warm process does not catch SIGINT"
    _scene(tmp_path, shape=(3072, 3072), tile=256)
    for sig, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        out = tmp_path / f"out-{code}"
        p = subprocess.Popen(
            [*AS_IN_A_TERMINAL, "detect", "scene.zarr", "--detector", "os_cfar", "--out", out.name],
            cwd=tmp_path,
            env=_env(warm_cpu),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        seen = []
        while True:  # the detection's first progress line: the command is under way on the cluster
            line = p.stderr.readline()
            seen.append(line)
            if not line or line.startswith("detect os_cfar"):
                break
        assert line, "".join(seen)
        p.send_signal(sig)
        rest = p.stderr.read()
        assert p.wait(120) == code, "".join(seen) + rest
        assert "sarship detect: interrupted" in rest
        assert not out.exists(), sorted(str(x) for x in out.rglob("*"))
    small = tmp_path / "small"
    small.mkdir()
    _scene(small)
    res = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "after", cwd=small)
    assert res.returncode == 0 and "warm cluster" in res.stderr, res.stderr
    assert (small / "after" / "detections.geojson").exists()


def test_the_client_imports_no_array_library(warm_cpu, tmp_path):
    code = (
        "import sys; from sarship import warm; "
        "c = warm.run_remote(['detect', 'missing.zarr', '--detector', 'ca_cfar']); "
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('numpy', 'scipy', 'numba', 'dask', 'distributed', 'zarr', 'pydantic', 'tensorstore')); "
        "print(c, heavy)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=_env(warm_cpu), timeout=120
    )
    assert res.stdout.strip() == "2 []", (res.stdout, res.stderr)
    assert "scene 'missing.zarr' does not exist" in res.stderr


def _stale_socket(sock: Path) -> None:
    """A socket left by a warm process that was killed."""
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sock))
    stale.close()


@pytest.mark.slow  # a detection on a cluster of its own; the client's rule: test_start_twice_idle_timeout_...
def test_a_stale_socket_leaves_commands_to_run_on_their_own(sockdir, tmp_path):
    sock = sockdir / "warm.sock"
    _scene(tmp_path)
    _stale_socket(sock)
    res = run(sock, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o1", cwd=tmp_path)
    assert res.returncode == 0 and "warm" not in res.stderr, res.stderr


def test_start_twice_idle_timeout_and_a_stale_socket(sockdir, monkeypatch, capsys):
    sock = sockdir / "warm.sock"
    # a socket left by a warm process that was killed: commands run on their own (the client gives them
    # back to the command line, as for no warm process: the slow test above runs one), silently
    _stale_socket(sock)
    monkeypatch.setenv("SARSHIP_WARM_SOCKET", str(sock))
    monkeypatch.delenv("SARSHIP_WARM", raising=False)
    monkeypatch.delenv("SARSHIP_SCHEDULER", raising=False)
    capsys.readouterr()
    assert warm.run_remote(["detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o1"]) is None
    assert capsys.readouterr() == ("", "")
    assert run(sock, "warm", "status").returncode == 1
    # a second start while one runs is refused (the first one's idle timeout is long: on a loaded
    # machine the second start took longer than a short one, and found it gone)
    res = run(
        sock,
        "warm",
        "start",
        "--device",
        "cpu",
        "--workers",
        "1",
        "--idle-timeout",
        "120",
        "--dashboard",
        "127.0.0.1:0",
        "--warm-up",
        "none",
    )
    assert res.returncode == 0, res.stderr
    again = run(sock, "warm", "start", "--device", "cpu", "--workers", "1", "--dashboard", "127.0.0.1:0")
    assert again.returncode == 2 and "runs already" in again.stderr and len(again.stderr.splitlines()) == 1
    assert run(sock, "warm", "stop").returncode == 0
    # the idle timeout: a warm process without a command for 4 s ends by itself
    res = run(
        sock,
        "warm",
        "start",
        "--device",
        "cpu",
        "--workers",
        "1",
        "--idle-timeout",
        "4",
        "--dashboard",
        "127.0.0.1:0",
        "--warm-up",
        "none",
    )
    assert res.returncode == 0, res.stderr
    for _ in range(300):  # idle for 4 s: it ends by itself
        if warm.status(sock) is None and not sock.exists():
            break
        time.sleep(0.1)
    else:
        pytest.fail("the warm process did not end after its idle timeout")
    assert "idle for 4 s: ending" in (sockdir / "warm.sock.log").read_text()
    assert run(sock, "warm", "stop").stdout.strip() == "no warm cluster was running"


def test_the_folder_must_be_private(tmp_path):
    open_dir = tmp_path / "shared"
    open_dir.mkdir(mode=0o755)
    os.chmod(open_dir, 0o755)
    with pytest.raises(warm.WarmError, match="may be entered by other users"):
        warm.private_folder(open_dir)
    made = warm.private_folder(tmp_path / "new" / "sub")
    assert (made.stat().st_mode & 0o777) == 0o700
    res = run(open_dir / "warm.sock", "warm", "start", "--device", "cpu")
    assert res.returncode == 2 and "must be 0700" in res.stderr and "Traceback" not in res.stderr
    from tests.cli.test_cli import sarship_here  # the arguments' checks, in this process

    env = {"SARSHIP_WARM_SOCKET": str(open_dir / "warm.sock")}
    bad = sarship_here("warm", "start", "--idle-timeout", "-3", env=env)
    assert bad.returncode == 2 and "--idle-timeout" in bad.stderr
    bad = sarship_here("warm", "start", "--warm-up", "ca_cfar,nope", env=env)
    assert bad.returncode == 2 and "unknown detector 'nope'" in bad.stderr


@pytest.mark.gpu
def test_a_warm_cluster_with_gpus_runs_both_devices(sockdir, tmp_path):
    from sarship.pipeline.gpu import available

    if not available():
        pytest.skip("needs CuPy and a CUDA GPU (none here)")
    sock = sockdir / "warm.sock"
    _scene(tmp_path, shape=(1500, 1300), tile=512)
    res = run(sock, "warm", "start", "--workers", "2", "--dashboard", "127.0.0.1:0")
    assert res.returncode == 0, res.stderr
    assert "GPU worker processes and 2 CPU" in res.stdout, res.stdout
    try:
        outs = {}
        for device in ("gpu", "cpu", "auto"):
            r = run(
                sock, "detect", "scene.zarr", "--detector", "ca_cfar", "--device", device, "--out", device, cwd=tmp_path
            )
            assert r.returncode == 0 and "sarship: warm cluster," in r.stderr, r.stderr
            rj = json.loads((tmp_path / device / "run.json").read_text())
            assert rj["device"] == ("cpu" if device == "cpu" else "gpu")
            outs[device] = _mask(tmp_path / device)
        own = run(
            sock,
            "detect",
            "scene.zarr",
            "--detector",
            "ca_cfar",
            "--device",
            "gpu",
            "--out",
            "own",
            cwd=tmp_path,
            env={"SARSHIP_WARM": "0"},
        )
        assert own.returncode == 0 and "local Dask cluster" in own.stderr, own.stderr
        np.testing.assert_array_equal(outs["gpu"], _mask(tmp_path / "own"))
        np.testing.assert_array_equal(outs["auto"], outs["gpu"])
        np.testing.assert_array_equal(outs["cpu"], outs["gpu"])  # the same sums (tests/workers/test_gpu.py)
    finally:
        assert run(sock, "warm", "stop").returncode == 0


def test_code_stamp_is_by_content(tmp_path):
    """The code stamp changes with a module's bytes even when its modification time is kept
    (``rsync -a``, ``cp -p``), and with a module added; not with a timestamp alone."""
    pkg = tmp_path / "sarship"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    mod = pkg / "sub" / "mod.py"
    mod.write_text("X = 1\n")
    before = warm._code_stamp([str(pkg)])
    st = mod.stat()
    os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # touched: the same code
    assert warm._code_stamp([str(pkg)]) == before
    mod.write_text("X = 2\n")
    os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns))  # edited, its old time kept
    assert warm._code_stamp([str(pkg)]) != before
    mod.write_text("X = 1\n")
    assert warm._code_stamp([str(pkg)]) == before
    (pkg / "new.py").write_text("")
    assert warm._code_stamp([str(pkg)]) != before


@contextlib.contextmanager
def _edited_keeping_mtime(sock):
    """sarship.warm, the copy the commands import (installed, or this checkout), edited with its old
    modification time kept (``rsync -a``, ``cp -p``), and restored after."""
    code = "import sarship.warm as w; print(w.__file__)"
    where = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=tempfile.gettempdir(),
        env=_env(sock),
        check=True,
    )
    mod = Path(where.stdout.strip())
    st, text = mod.stat(), mod.read_bytes()
    try:
        mod.write_bytes(text + b"\n# edited\n")
        os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns))
        yield
    finally:
        mod.write_bytes(text)
        os.utime(mod, ns=(st.st_atime_ns, st.st_mtime_ns))


@pytest.mark.slow  # two detections as commands; the rule on the live warm process: test_a_changed_code_is_refused
def test_a_changed_code_makes_commands_run_on_their_own(warm_cpu, tmp_path):
    """A module of sarship modified after the warm process started (a source checkout edited, the
    same version reinstalled), even with its old modification time kept (``rsync -a``,
    ``cp -p``): commands run on their own cluster, with the new code."""
    _scene(tmp_path)
    with _edited_keeping_mtime(warm_cpu):
        res = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "not on the warm cluster: sarship's code was changed since it started" in res.stderr
    assert "local Dask cluster" in res.stderr
    again = run(warm_cpu, "detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o2", cwd=tmp_path)
    assert again.returncode == 0 and "sarship: warm cluster," in again.stderr, again.stderr  # the code restored


def test_a_changed_code_is_refused(warm_cpu):
    """A module of sarship modified after the warm process started (a source checkout edited, the
    same version reinstalled), even with its old modification time kept (``rsync -a``,
    ``cp -p``): a command's identity (what it sends with each command) no longer matches the
    warm process's, which refuses it saying why (the command then runs on its own cluster, as
    every refused one: test_commands_the_warm_cluster_cannot_take_run_on_their_own; as commands,
    with the code restored after: the slow test above)."""
    from sarship.cli import build_parser  # the warm process is handed the command line's parser
    from sarship.warm_process import _parse_quietly, _refusal

    def command():  # a command's request (its identity and settings), made as the command makes it
        code = "import json, sarship.warm as w; print(json.dumps({'identity': w._identity(), 'env': w.relevant_env()}))"
        res = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            cwd=tempfile.gettempdir(),
            env=_env(warm_cpu),
            check=True,
        )  # (the standard library only: tests below)
        return json.loads(res.stdout)

    state = warm.status(warm_cpu)
    ns = _parse_quietly(["detect", "scene.zarr", "--detector", "ca_cfar", "--out", "o"], build_parser)
    assert _refusal(command(), state, ns) == ""
    with _edited_keeping_mtime(warm_cpu):
        edited = command()
    assert _refusal(edited, state, ns) == (
        "sarship's code was changed since it started (sarship warm stop, then sarship warm start, runs the new code)"
    )
    assert _refusal(command(), state, ns) == ""  # the code restored


def test_output_to_a_closed_pipe(warm_cpu, tmp_path):
    """`sarship detect ... | head -1`: the reader leaves after one line; the command still ends
    with its outputs in place and no traceback."""
    _scene(tmp_path)
    p = subprocess.Popen(
        f"{sys.executable} -m sarship detect scene.zarr --detector ca_cfar --out piped | head -1",
        shell=True,
        cwd=tmp_path,
        env=_env(warm_cpu),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = p.communicate(timeout=240)
    assert out.startswith("detections: ") and len(out.splitlines()) == 1, out
    assert "Traceback" not in err and "warm cluster" in err, err
    assert (tmp_path / "piped" / "run.json").exists()
