"""The warm cluster: a background process that keeps a local Dask cluster running between
``sarship detect`` commands, so that a command's time is its work (issue 17).

A ``sarship detect`` that starts its own local cluster pays, every time, for the interpreter's
imports (NumPy, SciPy, Numba, Dask, Zarr, the detectors), the cluster's start (worker
processes, each GPU worker's CUDA context and compiled kernels) and its close: 5-6 s of the
7-8 s the 25000 x 16700 band took as typed on one H100 (bench/RESULTS.md). ``sarship warm
start`` starts one process that holds all of that; while it runs, ``sarship detect`` without
``--scheduler`` hands its command line to it over a Unix socket and only relays what it
prints, so the command itself imports nothing but the standard library.

How a command runs there (:func:`serve`): the warm process runs the very ``sarship detect``
of :mod:`sarship.cli` (the same parser, checks, messages, exit codes, temporary outputs
renamed into place) in the command's working folder and umask, with its standard output and
error sent back to the command's, on the warm cluster instead of a cluster of its own. One
command runs at a time; others wait their turn. Ctrl-C (or SIGTERM) of the command interrupts
it there as it would here: nothing half-written is left.

When a command runs on a cluster of its own instead, it says why on stderr (except when no
warm cluster runs): the warm process runs another sarship (version, installation or Python
environment), was started with other settings (any ``SARSHIP_*``, ``DASK_*``, ``CUDA_*``,
``CUPY_*``, ``NUMBA_*``, ``OMP_*`` or ``MALLOC_*`` environment variable differs), or has no
worker for the ``--device`` asked. ``--scheduler`` (an address, or ``local``: a cluster of the
command's own) and ``SARSHIP_SCHEDULER`` never use it; nor does a command run with
``SARSHIP_WARM=0``.

Only the user who started it can use it: its socket lives in a folder only that user may
enter (``$XDG_RUNTIME_DIR/sarship``, else ``/tmp/sarship-UID``; ``SARSHIP_WARM_SOCKET`` names
another socket path), and both ends check the other's user ID (``SO_PEERCRED``; Linux only:
elsewhere every command starts its own cluster). It ends after ``--idle-timeout`` seconds
without a command (default 900), on ``sarship warm stop`` or on SIGTERM.

The client half of this module (:func:`run_remote`) imports only the standard library; the
server half imports the workers when it starts.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

#: Environment variables that may differ between the warm process and a command (they change
#: nothing the warm process fixed at its start: the error report, the client's exit).
PER_COMMAND_ENV = ("SARSHIP_DEBUG", "SARSHIP_FAST_EXIT", "SARSHIP_WARM", "SARSHIP_WARM_SOCKET")
#: Prefixes of the environment variables that must be equal (they set the cluster's shape, its
#: devices, the readers, the compiled code: what the warm process fixed at its start).
ENV_PREFIXES = ("SARSHIP_", "DASK_", "CUDA_", "CUPY_", "NUMBA_", "OMP_", "MALLOC_")
#: Seconds without a command after which the warm process ends (``--idle-timeout``).
DEFAULT_IDLE_S = 900.0
#: Detectors run once on a small simulated scene when the warm process starts (``--warm-up``).
DEFAULT_WARM_UP = ("ca_cfar",)
#: Seconds ``sarship warm start`` waits for the cluster to be ready.
START_TIMEOUT_S = 300.0

_OFF = ("0", "false", "no", "off")
_ACTIVE: dict[str, Any] = {}  # in the warm process, during a command: {"client": ..., "what": ...}


class WarmError(Exception):
    """A warm-cluster operation that cannot be done (one line, for the command line)."""


# ----------------------------------------------------------------------------- both ends


def socket_path() -> Path:
    """The warm process's socket: ``SARSHIP_WARM_SOCKET``, else ``warm.sock`` in
    ``$XDG_RUNTIME_DIR/sarship`` (when that folder exists), else in ``/tmp/sarship-UID``."""
    raw = os.environ.get("SARSHIP_WARM_SOCKET", "").strip()
    if raw:
        return Path(raw).expanduser()
    run = os.environ.get("XDG_RUNTIME_DIR", "").strip()
    if run and os.path.isdir(run):
        return Path(run) / "sarship" / "warm.sock"
    return Path(tempfile.gettempdir()) / f"sarship-{os.getuid()}" / "warm.sock"


def supported() -> bool:
    """Whether this platform has what the warm cluster needs (Unix sockets with peer IDs)."""
    return hasattr(socket, "AF_UNIX") and hasattr(socket, "SO_PEERCRED")


def _peer_uid(sock: socket.socket) -> int:
    creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", creds)[1]


def _identity() -> dict[str, str]:
    """What must be equal for a command to run in the warm process: the sarship version, the
    installation it was imported from, the Python environment, and the code's newest
    modification (a reinstall of the same version, an edit of a source checkout)."""
    import sarship

    return {"version": sarship.__version__, "package": str(Path(sarship.__file__).resolve().parent),
            "prefix": sys.prefix, "code": str(_code_stamp(sarship.__path__))}


def _code_stamp(paths) -> int:
    """The newest modification time (ns) of the sarship modules under ``paths`` (the package's
    ``__path__``: its folder and, in a source checkout, the checkout with ``pipeline/``,
    ``workers/``, ``service/``); about 2 ms."""
    roots: list[Path] = []
    for i, p in enumerate(paths):
        for sub in (("",) if i == 0 else ()) + ("pipeline", "workers", "service"):
            d = Path(p) / sub
            if d not in roots and (d / "__init__.py").is_file():
                roots.append(d)
    newest = 0
    for root in roots:
        for folder, dirs, files in os.walk(root):
            dirs[:] = [x for x in dirs if x != "__pycache__"]
            for f in files:
                if f.endswith(".py"):
                    with contextlib.suppress(OSError):
                        newest = max(newest, os.stat(os.path.join(folder, f)).st_mtime_ns)
    return newest


def relevant_env(environ: dict[str, str] | None = None) -> dict[str, str]:
    """The environment variables (:data:`ENV_PREFIXES`) a command and the warm process must share."""
    env = os.environ if environ is None else environ
    return {k: v for k, v in env.items() if k.startswith(ENV_PREFIXES) and k not in PER_COMMAND_ENV}


def _send(sock: socket.socket, msg: dict) -> None:
    sock.sendall((json.dumps(msg) + "\n").encode())


def _connect(path: Path, timeout: float = 2.0) -> socket.socket | None:
    """A connection to the warm process at ``path`` (run by this user), or None."""
    if not supported():
        return None
    try:
        if not path.is_socket():
            return None
    except OSError:
        return None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
        if _peer_uid(s) != os.getuid():  # a socket planted by another user: never talk to it
            raise OSError("peer is another user")
    except OSError:
        s.close()
        return None
    return s


def _request(op: str, timeout: float | None = 10.0, path: Path | None = None) -> dict | None:
    """One request/answer exchange (``status``, ``stop``); None when no warm process answers."""
    s = _connect(path or socket_path())
    if s is None:
        return None
    with s:
        try:
            s.settimeout(timeout)
            _send(s, {"op": op})
            line = s.makefile("rb").readline()
        except OSError:
            return None
    return json.loads(line) if line else None


# ----------------------------------------------------------------------------- the command's end


def eligible(argv: list[str]) -> bool:
    """Whether ``sarship ARGV`` may run in the warm process: a ``detect`` without
    ``--scheduler`` or ``SARSHIP_SCHEDULER`` (``local``, there, asks for a cluster of the
    command's own), unless ``SARSHIP_WARM`` is off. (The warm process checks the parsed command
    again.)"""
    if os.environ.get("SARSHIP_WARM", "").strip().lower() in _OFF or not supported():
        return False
    command = next((x for x in argv if not x.startswith("-")), None)
    if command != "detect" or argv[0] != "detect":
        return False
    if any(x == "--scheduler" or x.startswith("--scheduler=") for x in argv):
        return False
    return not os.environ.get("SARSHIP_SCHEDULER", "").strip()


def run_remote(argv: list[str]) -> int | None:
    """Run ``sarship ARGV`` in the warm process; its exit code, or None when the command must
    run here (no warm process, or one that cannot take it: then the reason is on stderr)."""
    if not eligible(argv):
        return None
    try:
        cwd = os.getcwd()
    except OSError:  # the command's folder was removed: the command line reports what it can
        return None
    s = _connect(socket_path())
    if s is None:
        return None
    umask = os.umask(0)
    os.umask(umask)
    request = {"op": "detect", "argv": list(argv), "cwd": cwd, "umask": umask, "env": relevant_env(),
               "identity": _identity(), "debug": os.environ.get("SARSHIP_DEBUG", ""),
               "columns": _columns(),
               "tty": {"stdout": _isatty(sys.stdout), "stderr": _isatty(sys.stderr)}}
    import signal
    import threading

    def on_term(signum, frame):  # as Ctrl-C: the command is interrupted there, then this one ends
        raise _Terminated()

    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGTERM, on_term) if main else None
    try:
        with s:
            try:
                _send(s, request)
            except OSError:
                return None
            except (KeyboardInterrupt, _Terminated) as exc:  # it ends there when it sees this end gone
                print("sarship detect: interrupted", file=sys.stderr)
                return 143 if isinstance(exc, _Terminated) else 130
            return _relay(s)
    finally:
        if main:
            signal.signal(signal.SIGTERM, old)


class _Terminated(Exception):
    """SIGTERM reached the command while it ran in the warm process."""


def _columns() -> int:
    """This command's terminal width (``COLUMNS``, else its terminal's, else 80): the help texts'."""
    import shutil

    return shutil.get_terminal_size().columns


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _relay(s: socket.socket) -> int | None:
    """Print what the warm process sends until its exit code; Ctrl-C (or SIGTERM) interrupts
    the command there (a second one leaves at once)."""
    reader = s.makefile("rb")
    interrupted = terminated = waiting_said = False
    s.settimeout(1.0)
    while True:
        try:
            try:
                line = reader.readline()
            except TimeoutError:
                if not waiting_said:
                    print("sarship: the warm cluster is busy with another command; waiting for it "
                          "(SARSHIP_WARM=0: a cluster of this command's own)", file=sys.stderr, flush=True)
                    waiting_said = True
                reader = s.makefile("rb")  # a timed-out file object cannot be read again
                continue
            except OSError:
                line = b""
            if not line:
                print("sarship detect: error: the warm cluster ended during the command (sarship warm status; "
                      "its log is beside its socket)", file=sys.stderr)
                return 1
            s.settimeout(None)
            msg = json.loads(line)
            if "o" in msg or "e" in msg:
                stream = sys.stdout if "o" in msg else sys.stderr
                try:
                    stream.write(msg["o"] if "o" in msg else msg["e"])
                    stream.flush()
                except BrokenPipeError:  # `sarship detect ... | head`: the reader left; the command goes on
                    with contextlib.suppress(OSError):
                        os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())
            elif "refuse" in msg:
                print(f"sarship: not on the warm cluster: {msg['refuse']}; starting a cluster of this command's "
                      "own", file=sys.stderr, flush=True)
                return None
            elif "exit" in msg:
                return 143 if terminated else int(msg["exit"])
        except (KeyboardInterrupt, _Terminated) as exc:
            terminated = terminated or isinstance(exc, _Terminated)
            if interrupted:
                return 143 if terminated else 130
            interrupted = True
            with contextlib.suppress(OSError):
                _send(s, {"op": "interrupt"})


# ----------------------------------------------------------------------------- commands


def status(path: Path | None = None) -> dict | None:
    """The warm process's state (pid, device, workers, dashboard, ...), or None."""
    return _request("status", path=path)


def stop(path: Path | None = None, timeout: float = 120.0) -> dict | None:
    """Ask the warm process to end (after the command it runs, if any) and wait for it; its
    last state, or None when none runs."""
    path = path or socket_path()
    state = _request("stop", timeout=None, path=path)  # answered once the command it runs has ended
    if state is None:
        return None
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if not _lock_held(_lock_path(path)):
            return state
        time.sleep(0.1)
    raise WarmError(f"the warm cluster (pid {state.get('pid')}) did not end within {timeout:.0f} s")


def start(device: str = "auto", workers: int | None = None, idle_timeout: float = DEFAULT_IDLE_S,
          dashboard: str = "127.0.0.1:8787", path: Path | None = None,
          timeout: float = START_TIMEOUT_S, warm_up: tuple[str, ...] = DEFAULT_WARM_UP) -> dict:
    """Start the warm process in the background (its own session, output in ``warm.log`` beside
    the socket) and wait until it answers; its state. :class:`WarmError` if one runs already or
    it could not start (with the end of its log)."""
    import subprocess

    if not supported():
        raise WarmError("the warm cluster needs Unix sockets with peer credentials (Linux)")
    path = path or socket_path()
    state = status(path)
    if state is not None:
        raise WarmError(f"a warm cluster runs already (pid {state['pid']}, {state['what']}); "
                        "sarship warm stop ends it")
    folder = private_folder(path.parent)
    log = folder / f"{path.name}.log"
    cmd = [sys.executable, "-m", "sarship", "warm", "run", "--device", device, "--idle-timeout", f"{idle_timeout:g}",
           "--dashboard", dashboard, "--warm-up", ",".join(warm_up) or "none"]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    env = {**os.environ, "SARSHIP_WARM_SOCKET": str(path)}
    import sarship

    # started in the folder that holds this process's sarship package: `python -m sarship` there
    # imports this very copy (an installed one, or a source checkout's), whatever folder the
    # command was typed in
    home = Path(sarship.__file__).resolve().parent.parent
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=out, env=env, cwd=home,
                                start_new_session=True, close_fds=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        state = status(path)
        if state is not None and state.get("pid") == proc.pid:
            return state
        if proc.poll() is not None:
            raise WarmError(f"the warm cluster did not start (exit {proc.returncode}): {_tail(log)}")
        time.sleep(0.1)
    proc.terminate()
    raise WarmError(f"the warm cluster did not start within {timeout:.0f} s: {_tail(log)}")


def _tail(log: Path) -> str:
    try:
        lines = [x for x in log.read_text(errors="replace").splitlines() if x.strip()]
    except OSError:
        return "(no log)"
    return lines[-1] if lines else "(empty log)"


def private_folder(folder: Path) -> Path:
    """``folder``, created if missing with mode 0700; refused (:class:`WarmError`) unless it is
    a real folder of this user that nobody else may enter."""
    import stat

    with contextlib.suppress(FileExistsError):
        folder.mkdir(mode=0o700, parents=True)
    st = folder.lstat()
    if not stat.S_ISDIR(st.st_mode):
        raise WarmError(f"{folder} is not a folder")
    if st.st_uid != os.getuid():
        raise WarmError(f"{folder} belongs to another user: set SARSHIP_WARM_SOCKET to a path in a folder of yours")
    if st.st_mode & 0o077:
        raise WarmError(f"{folder} may be entered by other users (mode {stat.S_IMODE(st.st_mode):o}): "
                        "the warm cluster's folder must be 0700")
    return folder


def _lock_path(path: Path) -> Path:
    return path.with_name(f"{path.name}.lock")


def _lock_held(lock: Path) -> bool:
    import fcntl

    try:
        fd = os.open(lock, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


# ----------------------------------------------------------------------------- the warm process


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


def serve(device: str = "auto", workers: int | None = None, idle_timeout: float = DEFAULT_IDLE_S,
          dashboard: str = "127.0.0.1:8787", path: Path | None = None,
          warm_up: tuple[str, ...] = DEFAULT_WARM_UP) -> int:
    """Run the warm process in the foreground (``sarship warm run``): start the cluster, then
    run the commands that arrive on the socket until ``idle_timeout`` seconds pass without one
    (0: never), ``sarship warm stop``, SIGTERM or Ctrl-C."""
    import fcntl
    import signal
    import threading

    if not supported():
        raise WarmError("the warm cluster needs Unix sockets with peer credentials (Linux)")
    env = relevant_env()  # as started: Dask sets some (OMP_NUM_THREADS) in this process later
    path = path or socket_path()
    private_folder(path.parent)
    lock_fd = os.open(_lock_path(path), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(lock_fd)
        raise WarmError(f"a warm cluster runs already on {path} (sarship warm status)") from None
    os.ftruncate(lock_fd, 0)
    os.write(lock_fd, f"{os.getpid()}\n".encode())

    def on_term(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise SystemExit(128 + signum)

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_term)
    from sarship.workers.cluster import connect, gpu_procs
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
    with connect(None, n_workers=n_cpu if not gpus else None, gpus=bool(gpus), cpu_workers=n_cpu if gpus else 0,
                 dashboard_address=dashboard, echo=False, short_lived=False, procs_per_gpu=per_gpu or None) as client:
        import importlib

        for name in ("sarship.cli", "sarship.workers.jobs"):  # the commands' imports, done once
            importlib.import_module(name)
        _warm_up(client, path.parent, warm_up)

        info = client.scheduler_info(n_workers=-1).get("workers", {})
        n_gpu = sum(1 for w in info.values() if float((w.get("resources") or {}).get("GPU", 0)) > 0)
        what = (f"{n_gpu} GPU worker processes" + (f" and {len(info) - n_gpu} CPU" if len(info) > n_gpu else "")
                if n_gpu else f"{len(info)} worker processes")
        from sarship.workers.cluster import dashboard_url

        state = {"pid": os.getpid(), "what": what, "device": "gpu" if n_gpu else "cpu", "gpu_workers": n_gpu,
                 "cpu_workers": len(info) - n_gpu, "dashboard": dashboard_url(client), "socket": str(path),
                 "idle_timeout_s": idle_timeout, "started": time.time(), "commands": 0,
                 "identity": _identity(), "env": env}
        srv = _listen(path)
        print(f"sarship: warm cluster ready (pid {os.getpid()}), {what}, dashboard {state['dashboard']}, "
              f"socket {path}", file=sys.stderr, flush=True)
        last = time.monotonic()
        try:
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
                    end = _handle(conn, client, state)
                if state["commands"] != n:  # a command (not a status) keeps it warm
                    last = time.monotonic()
                if end:
                    break
        finally:
            srv.close()
            with contextlib.suppress(OSError):
                if path.is_socket():  # ours: the lock keeps every other warm process off this path
                    path.unlink()
            print("sarship: warm cluster closed", file=sys.stderr, flush=True)
    os.close(lock_fd)
    return 0


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


def _handle(conn: socket.socket, client, state: dict) -> bool:
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
    reason = _refusal(req, state)
    if reason:
        with contextlib.suppress(OSError):
            _send(conn, {"refuse": reason})
        return False
    conn.settimeout(None)
    state["commands"] += 1
    code = _run_command(conn, req, client, state)
    return code == 143  # SIGTERM reached the warm process during the command: it ends


def _refusal(req: dict, state: dict) -> str:
    """Why a command cannot run here ('' when it can)."""
    if req.get("identity") != state["identity"]:
        got, have = req.get("identity") or {}, state["identity"]
        key = next((k for k in have if got.get(k) != have[k]), "version")
        if key == "code":
            return ("sarship's code was changed since it started (sarship warm stop, then sarship warm start, "
                    "runs the new code)")
        return f"it runs another sarship ({key} {have[key]}, this command's {got.get(key)})"
    env = req.get("env") or {}
    diff = sorted(k for k in set(env) | set(state["env"]) if env.get(k) != state["env"].get(k))
    if diff:
        return (f"it was started with another {diff[0]} ({state['env'].get(diff[0], 'unset')!s}, this command's "
                f"{env.get(diff[0], 'unset')!s})")
    ns = _parse_quietly(req.get("argv") or [])
    if ns is not None:
        if getattr(ns, "scheduler", None):
            return "--scheduler was given"
        if ns.device == "gpu" and not state["gpu_workers"]:
            return "it has no GPU worker (sarship warm start --device gpu)"
        if ns.device == "cpu" and not state["cpu_workers"]:
            return "it has no CPU worker (sarship warm start --workers N)"
    return ""


def _parse_quietly(argv: list[str]):
    """The parsed command line, or None when it does not parse (the command reports that)."""
    from sarship.cli import build_parser

    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null), contextlib.redirect_stderr(null):
        try:
            return build_parser().parse_args(argv)
        except SystemExit:
            return None


def _run_command(conn: socket.socket, req: dict, client, state: dict) -> int:
    """Run the command in this process's main thread (its signal handling is the command line's)
    with the command's folder, umask and streams; returns its exit code."""
    import signal
    import threading

    from sarship import cli

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

    ns = _parse_quietly(list(req["argv"]))
    tty = req.get("tty") or {}
    out, err = _Stream(channel, "o", bool(tty.get("stdout"))), _Stream(channel, "e", bool(tty.get("stderr")))
    cwd, umask = os.getcwd(), os.umask(int(req.get("umask", 0o022)))
    debug, columns = os.environ.get("SARSHIP_DEBUG"), os.environ.get("COLUMNS")
    code = 1
    try:
        os.chdir(req["cwd"])
    except OSError as exc:
        os.umask(umask)
        channel.send({"e": f"sarship detect: error: cannot enter the command's folder ({exc.strerror})\n"})
        channel.send({"exit": 2})
        return 2
    temps = cli._temporaries(ns) if ns is not None else []
    existing = {p for folder, pattern in temps for p in cli._glob(folder, pattern)}
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
                code = cli.main(list(req["argv"]))
            except SystemExit as exc:  # argparse's errors and --help; SIGTERM's unwinding
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                if not isinstance(exc.code, (int, type(None))):
                    print(exc.code, file=sys.stderr)
            except KeyboardInterrupt:
                print("sarship detect: interrupted", file=sys.stderr)
                code = 130
            except Exception as exc:  # what cli.main does not report itself
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
    channel.send({"exit": int(code) if isinstance(code, int) else 1})
    return int(code) if isinstance(code, int) else 1


def _settle(client, temps: list, existing: set, timeout: float = 60.0) -> None:
    """After a command ended early: wait (at most ``timeout``) until the cluster runs none of its
    tasks (a running task cannot be stopped; the ones not started were released with their
    futures), then remove the temporary outputs those tasks may have written again. The
    command's own clean-up ran already; the warm cluster outlives it, which a command's own
    cluster does not."""
    import shutil

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if not any(client.processing().values()):
                break
        except Exception:
            break
        time.sleep(0.05)
    for folder, pattern in temps:
        for p in folder.glob(pattern) if folder.is_dir() else []:
            if p not in existing:
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
    for folder, _ in temps:  # an output folder the command made, which its clean-up had removed
        if folder not in existing:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty


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
        scene = simulate(work / "scene.zarr", SimConfig(shape=(side, side), ships=8, seed=1), tile=128,
                         truth_path=work / "truth.geojson")
        for name in detectors:
            for device in (["gpu"] if gpu else []) + (["cpu"] if cpu else []):
                try:
                    run_detection(scene, name, {}, out_dir=work / f"{name}-{device}", tile=128, client=client,
                                  device=device if device == "cpu" else "auto", progress=False)
                except Exception as exc:  # noqa: BLE001  (the warm-up is a courtesy; the command reports)
                    print(f"sarship: warm-up of {name} on {device} skipped: {type(exc).__name__}: {exc}",
                          file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"sarship: warm-up ({', '.join(detectors)}, {side} x {side} px in 128 px tiles) "
          f"{time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
