"""The warm process of :mod:`sarship.warm` (``sarship warm run``, started in the background by
``sarship warm start``): it starts the local cluster, warms it up, then runs the ``sarship
detect`` commands that arrive on its socket, one at a time, in its main thread, until it has
been idle for its timeout, is stopped, or gets SIGTERM. The protocol, the socket's place and
who may use it are described in :mod:`sarship.warm`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from sarship.pipeline import settings
from sarship.temporaries import present, remove_new, temporaries
from sarship.warm import (
    DEFAULT_IDLE_S,
    DEFAULT_WARM_UP,
    WarmError,
    _identity,
    _lock_path,
    _peer_uid,
    _send,
    private_folder,
    relevant_env,
    socket_path,
    supported,
)

_ACTIVE: dict[str, Any] = {}  # during a command: {"client": ..., "what": ...}


def active_client():
    """In the warm process, during a command: the warm cluster's client (else None)."""
    return _ACTIVE.get("client")


def active_description() -> str:
    return _ACTIVE.get("what", "")


class _Stream(io.TextIOBase):
    """A command's stdout or stderr in the warm process: what is written goes to the command."""

    def __init__(self, channel, key: str, tty: bool):
        self._channel, self._key, self._tty = channel, key, tty

    def write(self, text: str) -> int:
        if text:
            self._channel.send({self._key: text})
        return len(text)

    def isatty(self) -> bool:
        return self._tty

    def writable(self) -> bool:
        return True


class _Channel:
    """The command's connection: frames sent from any thread, one at a time; a command that
    left (its connection closed) is not written to again."""

    def __init__(self, sock: socket.socket):
        import threading

        self.sock, self.lock, self.gone = sock, threading.Lock(), False

    def send(self, msg: dict) -> None:
        with self.lock:
            if self.gone:
                return
            try:
                _send(self.sock, msg)
            except OSError:
                self.gone = True


class CommandLine(NamedTuple):
    """The command line the warm process runs (``sarship.cli`` passes its own: this module does not
    import it): ``parser()`` builds its argument parser, ``main(argv)`` runs one command."""

    parser: Callable[[], Any]
    main: Callable[[list[str]], int]


def serve(
    commands: CommandLine,
    device: str = "auto",
    workers: int | None = None,
    idle_timeout: float = DEFAULT_IDLE_S,
    dashboard: str = "127.0.0.1:8787",
    path: Path | None = None,
    warm_up: tuple[str, ...] = DEFAULT_WARM_UP,
) -> int:
    """Run the warm process in the foreground (``sarship warm run``): start the cluster, then
    run the commands that arrive on the socket until ``idle_timeout`` seconds pass without one
    (0: never), ``sarship warm stop``, SIGTERM or Ctrl-C."""
    if not supported():
        raise WarmError("the warm cluster needs Unix sockets with peer credentials (Linux)")
    env = relevant_env()  # as started: Dask sets some (OMP_NUM_THREADS) in this process later
    path = path or socket_path()
    private_folder(path.parent)
    lock_fd = _lock(path)
    _on_signals()
    from sarship.workers.cluster import connect

    gpus, per_gpu, n_cpu = _worker_counts(device, workers)
    with connect(
        None,
        n_workers=n_cpu if not gpus else None,
        gpus=bool(gpus),
        cpu_workers=n_cpu if gpus else 0,
        dashboard_address=dashboard,
        echo=False,
        short_lived=False,
        procs_per_gpu=per_gpu or None,
    ) as client:
        import importlib

        for name in ("sarship.cli", "sarship.workers.jobs"):  # the commands' imports, done once
            importlib.import_module(name)
        _warm_up(client, path.parent, warm_up)
        state = _ready_state(client, path, idle_timeout, env)
        srv = _listen(path)
        from sarship.workers.cluster import DASHBOARD_HINT

        dash = f"dashboard {state['dashboard']}" if state["dashboard"] else f"no dashboard ({DASHBOARD_HINT})"
        print(
            f"sarship: warm cluster ready (pid {os.getpid()}), {state['what']}, {dash}, socket {path}",
            file=sys.stderr,
            flush=True,
        )
        try:
            _accept_commands(srv, client, state, commands, idle_timeout)
        finally:
            srv.close()
            with contextlib.suppress(OSError):
                if path.is_socket():  # ours: the lock keeps every other warm process off this path
                    path.unlink()
            print("sarship: warm cluster closed", file=sys.stderr, flush=True)
    os.close(lock_fd)
    return 0


def _lock(path: Path) -> int:
    """Take the lock of the socket ``path`` (its file holds this process's id); returns its
    descriptor. WarmError when another warm process holds it."""
    import fcntl

    lock_fd = os.open(_lock_path(path), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(lock_fd)
        raise WarmError(f"a warm cluster runs already on {path} (sarship warm status)") from None
    os.ftruncate(lock_fd, 0)
    os.write(lock_fd, f"{os.getpid()}\n".encode())
    return lock_fd


def _on_signals() -> None:
    """In the main thread: SIGTERM ends the process (SystemExit 128 + 15) and SIGINT raises
    KeyboardInterrupt."""
    import signal
    import threading

    def on_term(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise SystemExit(128 + signum)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_term)
        # a command is interrupted by the SIGINT this process sends its own main thread
        # (_run_command's watcher): a warm process started from a background job or a service
        # manager inherits SIGINT ignored, which would make every interrupt a no-op
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _worker_counts(device: str, workers: int | None) -> tuple[list[Any], int, int]:
    """The GPUs the cluster uses, its worker processes per GPU and its CPU workers (``workers``,
    else the cores the GPU processes leave)."""
    from sarship.workers.cluster import gpu_procs
    from sarship.workers.gpus import visible_gpus

    gpus = visible_gpus() if device != "cpu" else []
    if device == "gpu" and not gpus:
        raise WarmError("--device gpu: no GPU is visible here")
    cores = os.cpu_count() or 1
    per_gpu = gpu_procs(len(gpus), long_lived=True) if gpus else 0  # started once: no cap on the count
    n_gpu_procs = len(gpus) * per_gpu
    n_cpu = workers if workers is not None else (max(0, cores - n_gpu_procs) if gpus else cores)
    if not gpus and n_cpu < 1:
        raise WarmError("--workers must be at least 1 without GPUs")
    return gpus, per_gpu, n_cpu


def _ready_state(client, path: Path, idle_timeout: float, env: dict[str, str]) -> dict[str, Any]:
    """The warm process's state, once its cluster is up (what ``sarship warm status`` shows)."""
    from sarship.workers.cluster import dashboard_url

    info = client.scheduler_info(n_workers=-1).get("workers", {})
    n_gpu = sum(1 for w in info.values() if float((w.get("resources") or {}).get("GPU", 0)) > 0)
    what = (
        f"{n_gpu} GPU worker processes" + (f" and {len(info) - n_gpu} CPU" if len(info) > n_gpu else "")
        if n_gpu
        else f"{len(info)} worker processes"
    )
    return {
        "pid": os.getpid(),
        "what": what,
        "device": "gpu" if n_gpu else "cpu",
        "gpu_workers": n_gpu,
        "cpu_workers": len(info) - n_gpu,
        "dashboard": dashboard_url(client),
        "socket": str(path),
        "idle_timeout_s": idle_timeout,
        "started": time.time(),
        "commands": 0,
        "identity": _identity(),
        "env": env,
    }


def _accept_commands(srv: socket.socket, client, state: dict, commands: CommandLine, idle_timeout: float) -> None:
    """Take the connections on ``srv``, one at a time, until the process has been idle for
    ``idle_timeout`` seconds (0: never), its scheduler is gone or a command ends it."""
    last = time.monotonic()
    while True:
        if idle_timeout and time.monotonic() - last > idle_timeout:
            print(f"sarship: warm cluster idle for {idle_timeout:g} s: ending", file=sys.stderr, flush=True)
            break
        if client.status not in ("running", "connecting"):
            print("sarship: the warm cluster's scheduler is gone: ending", file=sys.stderr, flush=True)
            break
        srv.settimeout(min(5.0, idle_timeout) if idle_timeout else 5.0)
        try:
            conn, _ = srv.accept()
        except TimeoutError:
            continue
        n = state["commands"]
        with conn:
            end = _handle(conn, client, state, commands)
        if state["commands"] != n:  # a command (not a status) keeps it warm
            last = time.monotonic()
        if end:
            break


def _listen(path: Path) -> socket.socket:
    """Bind the socket under a temporary name (mode 0600) and rename it into place: a command
    never finds a socket that does not answer yet."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)
    try:
        srv.bind(str(tmp))
    finally:
        os.umask(old)
    srv.listen(16)
    os.replace(tmp, path)  # a stale socket of a warm process that was killed is replaced
    return srv


def _handle(conn: socket.socket, client, state: dict, commands: CommandLine) -> bool:
    """Serve one connection; True when the warm process should end."""
    conn.settimeout(10.0)
    try:
        if _peer_uid(conn) != os.getuid():
            return False
        line = conn.makefile("rb").readline()
    except OSError:
        return False
    try:
        req = json.loads(line)
    except ValueError:
        return False
    op = req.get("op")
    if op == "status":
        with contextlib.suppress(OSError):
            _send(conn, state)
        return False
    if op == "stop":
        with contextlib.suppress(OSError):
            _send(conn, state)
        return True
    if op != "detect":
        return False
    ns = _parse_quietly(req.get("argv") or [], commands.parser)
    reason = _refusal(req, state, ns)
    if reason:
        with contextlib.suppress(OSError):
            _send(conn, {"refuse": reason})
        return False
    conn.settimeout(None)
    state["commands"] += 1
    code = _run_command(conn, req, client, state, ns, commands.main)
    return code == 143  # SIGTERM reached the warm process during the command: it ends


def _refusal(req: dict, state: dict, ns) -> str:
    """Why a command cannot run here ('' when it can); ``ns``: its parsed command line, or None
    when it does not parse (then the command itself reports that)."""
    if req.get("identity") != state["identity"]:
        got, have = req.get("identity") or {}, state["identity"]
        key = next((k for k in have if got.get(k) != have[k]), "version")
        if key == "code":
            return (
                "sarship's code was changed since it started (sarship warm stop, then sarship warm start, "
                "runs the new code)"
            )
        return f"it runs another sarship ({key} {have[key]}, this command's {got.get(key)})"
    env = req.get("env") or {}
    diff = sorted(k for k in set(env) | set(state["env"]) if env.get(k) != state["env"].get(k))
    if diff:
        return (
            f"it was started with another {diff[0]} ({state['env'].get(diff[0], 'unset')!s}, this command's "
            f"{env.get(diff[0], 'unset')!s})"
        )
    if ns is not None:
        if getattr(ns, "scheduler", None):
            return "--scheduler was given"
        if ns.device == "gpu" and not state["gpu_workers"]:
            return "it has no GPU worker (sarship warm start --device gpu)"
        if ns.device == "cpu" and not state["cpu_workers"]:
            return "it has no CPU worker (sarship warm start --workers N)"
    return ""


def _parse_quietly(argv: list[str], build_parser: Callable[[], Any]):
    """The parsed command line, or None when it does not parse (the command reports that)."""
    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null), contextlib.redirect_stderr(null):
        try:
            return build_parser().parse_args(argv)
        except SystemExit:
            return None


def _run_command(conn: socket.socket, req: dict, client, state: dict, ns, main: Callable[[list[str]], int]) -> int:
    """Run the command (``ns``: its parsed command line, or None) in this process's main thread
    (its signal handling is the command line's) with the command's folder, umask and streams;
    returns its exit code."""
    import signal
    import threading

    channel = _Channel(conn)
    done = threading.Event()
    guard = threading.Lock()
    main_id = threading.main_thread().ident

    def watch() -> None:  # the command's Ctrl-C (or its end): interrupt the command here
        reader = conn.makefile("rb")
        while True:
            try:
                line = reader.readline()
            except (OSError, ValueError):
                line = b""
            if line and b"interrupt" not in line:
                continue
            with guard:
                if not done.is_set():
                    signal.pthread_kill(main_id, signal.SIGINT)
            if not line:
                channel.gone = True
            return

    tty = req.get("tty") or {}
    out, err = _Stream(channel, "o", bool(tty.get("stdout"))), _Stream(channel, "e", bool(tty.get("stderr")))
    cwd, umask = os.getcwd(), os.umask(int(req.get("umask", 0o022)))
    debug, columns = settings.raw("debug"), os.environ.get("COLUMNS")
    code = 1
    try:
        os.chdir(req["cwd"])
    except OSError as exc:
        os.umask(umask)
        channel.send({"e": f"sarship detect: error: cannot enter the command's folder ({exc.strerror})\n"})
        channel.send({"exit": 2})
        return 2
    temps = temporaries(ns) if ns is not None else []
    existing = present(temps)
    existing |= {folder for folder, _ in temps if folder.exists()}
    channel.send({"started": True})
    _ACTIVE.update(client=client, what=state["what"])
    try:
        if req.get("debug"):
            os.environ["SARSHIP_DEBUG"] = req["debug"]
        else:
            os.environ.pop("SARSHIP_DEBUG", None)
        os.environ["COLUMNS"] = str(int(req.get("columns") or 80))  # argparse's help width
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:  # the watcher starts here: its interrupt lands in this block
                threading.Thread(target=watch, name="sarship-warm-watch", daemon=True).start()
                code = main(list(req["argv"]))
            except SystemExit as exc:  # argparse's errors and --help; SIGTERM's unwinding
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                if not isinstance(exc.code, (int, type(None))):
                    print(exc.code, file=sys.stderr)
            except KeyboardInterrupt:
                print("sarship detect: interrupted", file=sys.stderr)
                code = 130
            except Exception as exc:  # what the command line's main does not report itself
                print(f"sarship detect: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
                code = 1
    finally:
        try:
            with guard:
                done.set()
            time.sleep(0.01)  # an interrupt sent just before the command ended arrives here
        except KeyboardInterrupt:
            pass
        _ACTIVE.clear()
        if code not in (0, 2):  # interrupted or failed: tiles still running may write again
            _settle(client, temps, existing)
        for key, value in (("SARSHIP_DEBUG", debug), ("COLUMNS", columns)):
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        os.umask(umask)
        with contextlib.suppress(OSError):
            os.chdir(cwd)
    code = code if isinstance(code, int) else 1
    channel.send({"exit": code})
    return code


def _settle(client, temps: list, existing: set, timeout: float = 60.0) -> None:
    """After a command ended early: wait (at most ``timeout``) until the cluster runs none of its
    tasks (a running task cannot be stopped; the ones not started were released with their
    futures), then remove the temporary outputs those tasks may have written again. The
    command's own clean-up ran already; the warm cluster outlives it, which a command's own
    cluster does not."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:  # a cancelled task leaves the scheduler's view at once but runs on in its worker's thread
            if not any(client.processing().values()) and not _executing(client):
                break
        except Exception:
            break
        time.sleep(0.05)
    remove_new(temps, existing)
    for folder, _ in temps:  # an output folder the command made, which its clean-up had removed
        if folder not in existing:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty


def _executing(client) -> int:
    """The number of tasks the cluster's workers are executing now, cancelled ones included."""
    counts = client.run(lambda dask_worker: int(dask_worker.state.executing_count))
    return int(sum(counts.values()))


def _warm_up(client, folder: Path, detectors: tuple[str, ...]) -> None:
    """Run each detector of ``detectors`` (defaults, texture land mask) on a small simulated scene
    cut into 128 px tiles, at least four tiles a worker, once on the GPU workers (if any) and once
    on the CPU workers (if any), outputs discarded: every worker then has its compiled kernels
    loaded (Numba's cache, CuPy's kernels, the CUDA context) and the first command does not pay
    for them (on a fresh H200 host the first command on a cold cluster took 20 s, the next 1.8 s;
    bench/RESULTS.md). A detector that fails here (e.g. one that needs another kind of scene) is
    reported in the log and skipped."""
    import shutil

    if not detectors:
        return
    from sarship.pipeline.simulate import SimConfig, simulate
    from sarship.workers.jobs import run_detection

    info = client.scheduler_info(n_workers=-1).get("workers", {})
    gpu = any(float((w.get("resources") or {}).get("GPU", 0)) > 0 for w in info.values())
    cpu = any(float((w.get("resources") or {}).get("GPU", 0)) <= 0 for w in info.values())
    import math

    side = 128 * max(4, math.ceil(math.sqrt(4 * max(1, len(info)))))
    work = Path(tempfile.mkdtemp(prefix=".warm-up-", dir=folder))
    t0 = time.perf_counter()
    try:
        scene = simulate(
            work / "scene.zarr",
            SimConfig(shape=(side, side), ships=8, seed=1),
            tile=128,
            truth_path=work / "truth.geojson",
        )
        for name in detectors:
            for device in (["gpu"] if gpu else []) + (["cpu"] if cpu else []):
                try:
                    run_detection(
                        scene,
                        name,
                        {},
                        out_dir=work / f"{name}-{device}",
                        tile=128,
                        client=client,
                        device=device if device == "cpu" else "auto",
                        progress=False,
                    )
                except Exception as exc:  # noqa: BLE001  (the warm-up is a courtesy; the command reports)
                    print(
                        f"sarship: warm-up of {name} on {device} skipped: {type(exc).__name__}: {exc}",
                        file=sys.stderr,
                        flush=True,
                    )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(
        f"sarship: warm-up ({', '.join(detectors)}, {side} x {side} px in 128 px tiles) "
        f"{time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
        flush=True,
    )
