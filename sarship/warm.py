"""The warm cluster: a background process that keeps a local Dask cluster running between
``sarship detect`` commands, so that a command's time is its work (issue 17).

A ``sarship detect`` that starts its own local cluster pays, every time, for the interpreter's
imports (NumPy, SciPy, Numba, Dask, Zarr, the detectors), the cluster's start (worker
processes, each GPU worker's CUDA context and compiled kernels) and its close: 5-6 s of the
7-8 s the 25000 x 16700 band took as typed on one H100 (bench/RESULTS.md). ``sarship warm
start`` starts one process that holds all of that; while it runs, ``sarship detect`` without
``--scheduler`` hands its command line to it over a Unix socket and only relays what it
prints, so the command itself imports nothing but the standard library.

How a command runs there (:func:`sarship.warm_process.serve`): the warm process runs the very ``sarship detect``
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

This module (the command's end, :func:`run_remote`, and ``sarship warm start|status|stop``)
imports only the standard library; the warm process itself is :mod:`sarship.warm_process`.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path

from sarship.pipeline import settings

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


class WarmError(Exception):
    """A warm-cluster operation that cannot be done (one line, for the command line)."""


# ----------------------------------------------------------------------------- both ends


def socket_path() -> Path:
    """The warm process's socket: ``SARSHIP_WARM_SOCKET``, else ``warm.sock`` in
    ``$XDG_RUNTIME_DIR/sarship`` (when that folder exists), else in ``/tmp/sarship-UID``."""
    given = settings.read("warm_socket")
    if given is not None:
        return given.expanduser()
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
    installation it was imported from, the Python environment, and the code's content (a
    reinstall of the same version, an edit of a source checkout, also one that kept the file's
    old modification time: ``rsync -a``, ``cp -p``)."""
    import sarship

    return {
        "version": sarship.__version__,
        "package": str(Path(sarship.__file__).resolve().parent),
        "prefix": sys.prefix,
        "code": _code_stamp(sarship.__path__),
    }


def _code_stamp(paths) -> str:
    """A hash (BLAKE2b, hex) of the sarship modules under ``paths`` (the package's ``__path__``:
    its folder and, in a source checkout, the checkout with ``pipeline/``, ``workers/``,
    ``service/``): each ``.py`` file's path relative to its root and its bytes, in sorted order.
    By content, not modification times: a copy that keeps the old times (``rsync -a``,
    ``cp -p``, a checkout of an older commit) changes it too. About 1.5 MB of source: a few
    ms, once per command."""
    import hashlib

    roots: list[Path] = []
    for i, p in enumerate(paths):
        for sub in (("",) if i == 0 else ()) + ("pipeline", "workers", "service"):
            d = Path(p) / sub
            if d not in roots and (d / "__init__.py").is_file():
                roots.append(d)
    files: list[tuple[str, str]] = []
    for k, root in enumerate(roots):
        for folder, dirs, names in os.walk(root):
            dirs[:] = [x for x in dirs if x != "__pycache__"]
            files += [
                (f"{k}:{os.path.relpath(os.path.join(folder, f), root)}", os.path.join(folder, f))
                for f in names
                if f.endswith(".py")
            ]
    h = hashlib.blake2b(digest_size=16)
    for rel, path in sorted(files):
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError:  # removed meanwhile: its absence is the content
            data = b"\0missing"
        h.update(rel.encode() + b"\0" + len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


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
    if not settings.read("warm") or not supported():
        return False
    if not argv or argv[0] != "detect":
        return False
    if any(x == "--scheduler" or x.startswith("--scheduler=") for x in argv):
        return False
    return not settings.read("scheduler")


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
    request = {
        "op": "detect",
        "argv": list(argv),
        "cwd": cwd,
        "umask": umask,
        "env": relevant_env(),
        "identity": _identity(),
        "debug": settings.raw("debug") or "",
        "columns": _columns(),
        "tty": {"stdout": _isatty(sys.stdout), "stderr": _isatty(sys.stderr)},
    }
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
                    print(
                        "sarship: the warm cluster is busy with another command; waiting for it "
                        "(SARSHIP_WARM=0: a cluster of this command's own)",
                        file=sys.stderr,
                        flush=True,
                    )
                    waiting_said = True
                reader = s.makefile("rb")  # a timed-out file object cannot be read again
                continue
            except OSError:
                line = b""
            if not line:
                print(
                    "sarship detect: error: the warm cluster ended during the command (sarship warm status; "
                    "its log is beside its socket)",
                    file=sys.stderr,
                )
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
                print(
                    f"sarship: not on the warm cluster: {msg['refuse']}; starting a cluster of this command's own",
                    file=sys.stderr,
                    flush=True,
                )
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


def start(
    device: str = "auto",
    workers: int | None = None,
    idle_timeout: float = DEFAULT_IDLE_S,
    dashboard: str = "127.0.0.1:8787",
    path: Path | None = None,
    timeout: float = START_TIMEOUT_S,
    warm_up: tuple[str, ...] = DEFAULT_WARM_UP,
) -> dict:
    """Start the warm process in the background (its own session, output in ``warm.log`` beside
    the socket) and wait until it answers; its state. :class:`WarmError` if one runs already or
    it could not start (with the end of its log)."""
    import subprocess

    if not supported():
        raise WarmError("the warm cluster needs Unix sockets with peer credentials (Linux)")
    path = path or socket_path()
    state = status(path)
    if state is not None:
        raise WarmError(f"a warm cluster runs already (pid {state['pid']}, {state['what']}); sarship warm stop ends it")
    folder = private_folder(path.parent)
    log = folder / f"{path.name}.log"
    cmd = [
        sys.executable,
        "-m",
        "sarship",
        "warm",
        "run",
        "--device",
        device,
        "--idle-timeout",
        f"{idle_timeout:g}",
        "--dashboard",
        dashboard,
        "--warm-up",
        ",".join(warm_up) or "none",
    ]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    env = {**os.environ, "SARSHIP_WARM_SOCKET": str(path)}
    import sarship

    # started in the folder that holds this process's sarship package: `python -m sarship` there
    # imports this very copy (an installed one, or a source checkout's), whatever folder the
    # command was typed in
    home = Path(sarship.__file__).resolve().parent.parent
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=out,
            env=env,
            cwd=home,
            start_new_session=True,
            close_fds=True,
        )
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
        raise WarmError(
            f"{folder} may be entered by other users (mode {stat.S_IMODE(st.st_mode):o}): "
            "the warm cluster's folder must be 0700"
        )
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
