"""Start-up checks of ``sarship serve``, run before the server starts.

Anything that can stop the service because of what the operator gave it (a data folder that
cannot be created or written, a job store that is not a SQLite database, a port already in
use or an address that does not resolve, an address other machines reach without tokens, an
unreachable Dask scheduler, GPUs that are not there) is found here and raised as one :class:`~sarship.pipeline.errors.InputError` naming the
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
            raise InputError(
                f"cannot listen on {host}:{port}: {exc.strerror or exc} (setting 'host' / 'port')"
            ) from None


def is_loopback(host: str) -> bool | None:
    """Whether every address ``host`` resolves to is a loopback address (127.0.0.0/8, ``::1``);
    ``0.0.0.0``, ``::`` and an empty host are every interface: False. None when ``host`` does
    not resolve (:func:`check_listen` names it)."""
    import ipaddress

    h = (host or "").strip().strip("[]")
    if not h:
        return False
    try:
        infos = socket.getaddrinfo(h, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        return None
    # (i[4][0]: the host of an IPv4 or IPv6 socket address, a str; typed str | int for other families)
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split("%")[0]).is_loopback for i in infos)


def check_exposure(settings: Settings) -> None:
    """Refuse to serve without tokens on an address other machines can reach, unless the
    operator says so (``allow_unauthenticated``): anyone who reaches such an API could run
    and dismiss jobs and upload scenes."""
    if settings.tokens or settings.allow_unauthenticated or is_loopback(settings.host) is not False:
        return  # (a host that does not resolve: check_listen says so)
    raise InputError(
        f"refusing to serve on '{settings.host}' (reachable from other machines) without tokens: "
        "set SARSHIP_TOKENS, listen on 127.0.0.1, or pass --allow-unauthenticated "
        "(SARSHIP_ALLOW_UNAUTHENTICATED=1) to serve without them"
    )


def check_scheduler(address: str) -> None:
    """Connect to the Dask scheduler once (10 s at most)."""
    from sarship.workers.cluster import connect

    with connect(address, echo=False):
        pass


def preflight(settings: Settings) -> None:
    """Every start-up check, cheapest first; raises :class:`InputError` at the first failure."""
    check_exposure(settings)  # before anything is created
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
