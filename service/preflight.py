"""Start-up checks of ``sarship serve``, run before the server starts.

Anything that can stop the service because of what the operator gave it (a data folder that
cannot be created or written, a job store that is not a SQLite database, a port already in
use or an address that does not resolve, an unreachable Dask scheduler, GPUs that are not
there) is found here and raised as one :class:`~sarship.pipeline.errors.InputError` naming the
setting, so that ``sarship serve`` exits 2 with one line (docs/interfaces/cli.md) instead of a traceback from
inside the ASGI server's start-up. The application's own start-up (``service.app``) then
repeats the same steps, which cannot fail for these reasons any more.
"""

from __future__ import annotations

import os
import socket
import sqlite3
import tempfile
from pathlib import Path

from sarship.pipeline.errors import InputError
from sarship.service.settings import Settings


def check_folder(path: Path, what: str) -> None:
    """Create ``path`` (and its parents) if needed and prove that a file can be written in it."""
    if path.exists() and not path.is_dir():
        raise InputError(f"{what} '{path}' is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".sarship-probe-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{what} '{path}' cannot be used: {exc.strerror or exc}") from None


def check_store(path: Path) -> None:
    """Open (or create) the job store and its tables; a file that is not a SQLite database, or
    one that is locked or read-only, is refused."""
    from sarship.service.store import JobStore

    try:
        JobStore(path)
    except (sqlite3.Error, OSError) as exc:
        raise InputError(f"job store '{path}' cannot be used: {exc}") from None


def check_listen(host: str, port: int) -> None:
    """Bind ``host:port`` as the server will (``SO_REUSEADDR``, as uvicorn sets it), then
    release it. Port 0 (any free port) always passes."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise InputError(f"setting 'host': cannot resolve '{host}': {exc.strerror}") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as exc:
            raise InputError(f"cannot listen on {host}:{port}: {exc.strerror or exc} "
                             "(setting 'host' / 'port')") from None


def check_scheduler(address: str) -> None:
    """Connect to the Dask scheduler once (10 s at most)."""
    from sarship.workers.cluster import connect

    with connect(address, echo=False):
        pass


def preflight(settings: Settings) -> None:
    """Every start-up check, cheapest first; raises :class:`InputError` at the first failure."""
    check_folder(settings.data, "data folder")
    for sub in (settings.scenes_dir, settings.jobs_dir, settings.uploads_dir):
        check_folder(sub, "data folder")
    if settings.inbox:
        check_folder(settings.quarantine_dir, "inbox quarantine folder")
    check_store(settings.db_path)
    check_listen(settings.host, settings.port)
    if settings.scheduler:
        check_scheduler(settings.scheduler)
    else:
        settings.local_workers()  # GPUs asked for must be visible
