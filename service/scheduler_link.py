"""The API's Dask client of an external scheduler (``SARSHIP_SCHEDULER``), reconnected when the
scheduler goes away and comes back.

Dask's own client retries a lost scheduler for its connect timeout (10 s here) and then
closes for good: every job after that failed to reach the scheduler and was retried, and
``/readyz`` answered 503, until the API was restarted. :class:`SchedulerLink` stands where the
client stood (the runner and the routes call it as they called the client) and watches it: once
the client has closed, a new one is made with an exponential back-off between tries
(``SARSHIP_RECONNECT_S``, doubled after each failed try up to ``SARSHIP_RECONNECT_MAX_S``), and
the new cluster's workers are checked for this sarship version as at start-up. While no client
is connected (:attr:`SchedulerLink.connected` false), the runners claim no job (jobs wait in
the store instead of being retried again and again), and every use raises
:class:`ConnectionError` naming the scheduler, which the runner counts as a fault of the service
for a job in flight (retried after its back-off, never failed for it) and ``/readyz`` reports as
not ready.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from distributed import Client

log = logging.getLogger("sarship.service")

#: Client states after which Dask's client never reconnects by itself.
_GONE = ("closing", "closed", "failed")


def backoff(first_s: float, max_s: float, failures: int) -> float:
    """Seconds before the next try after ``failures`` failed tries in a row: ``first_s``
    doubled per failure, at most ``max_s``."""
    factor: int = 2 ** min(max(failures, 0), 30)
    return min(first_s * factor, max_s)


class SchedulerLink:
    """A :class:`distributed.Client` of ``address`` that is made again when it has closed.

    ``connect``: makes a connected, checked client (default :func:`_client`); the first call
    runs here, so an unreachable scheduler at start-up fails the start as before
    (:class:`InputError`). ``first_s``/``max_s``: the back-off (:func:`backoff`). ``watch_s``:
    how often the client's state is looked at.
    """

    def __init__(
        self,
        address: str,
        first_s: float = 1.0,
        max_s: float = 30.0,
        connect: Callable[[], Client] | None = None,
        watch_s: float = 0.25,
    ):
        self.address = address
        self.first_s, self.max_s = float(first_s), float(max_s)
        self._connect = connect or (lambda: _client(address))
        self._client = self._connect()
        self._lock = threading.Lock()
        self._failures = 0
        self._next_try = 0.0
        self.reconnects = 0
        self.last_error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, args=(watch_s,), name="sarship-scheduler-link", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the client's place

    @property
    def status(self) -> str:
        """The current client's state (``running`` when connected)."""
        return getattr(self._client, "status", "closed")

    @property
    def connected(self) -> bool:
        return self.status == "running"

    def current(self) -> Client:
        """The connected client; :class:`ConnectionError` naming the scheduler when there is none."""
        c = self._client
        if getattr(c, "status", "closed") != "running":
            wait = max(self._next_try - time.monotonic(), 0.0)
            why = f": {self.last_error}" if self.last_error else ""
            raise ConnectionError(
                f"the Dask scheduler at '{self.address}' is unreachable (reconnecting, next try in {wait:.0f} s{why})"
            )
        return c

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.current(), name)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        c = self._client
        if c is not None:
            try:
                c.close()  # type: ignore[no-untyped-call]  # distributed's Client.close is unannotated
            except Exception:  # noqa: BLE001 - closing a client of a scheduler that is gone
                pass

    # ------------------------------------------------------------------ reconnection

    def _watch(self, every: float) -> None:
        while not self._stop.wait(every):
            if self.status in _GONE and time.monotonic() >= self._next_try:
                self.reconnect()

    def reconnect(self) -> bool:
        """One try at a new client (when the current one has closed); whether one is connected."""
        with self._lock:
            if self.status not in _GONE:
                return self.connected
            try:
                new = self._connect()
            except Exception as exc:  # noqa: BLE001 - unreachable, refused, another version: tried again
                self._failures += 1
                delay = backoff(self.first_s, self.max_s, self._failures - 1)
                self._next_try = time.monotonic() + delay
                self.last_error = " ".join(str(exc).split())[:300]
                log.warning(
                    "Dask scheduler %s: reconnection failed (%s); next try in %g s",
                    self.address,
                    self.last_error,
                    delay,
                )
                return False
            old, self._client = self._client, new
            self._failures, self._next_try, self.last_error = 0, 0.0, None
            self.reconnects += 1
        try:
            old.close()  # type: ignore[no-untyped-call]  # distributed's Client.close is unannotated
        except Exception:  # noqa: BLE001
            pass
        n = len(new.scheduler_info().get("workers", {}))
        log.warning("Dask scheduler %s: reconnected (%d workers)", self.address, n)
        return True


def _client(address: str, timeout_s: float = 10.0) -> Client:
    """A client of ``address`` whose workers run this sarship version
    (:func:`sarship.workers.cluster.connect_checked`); :class:`InputError` otherwise."""
    from sarship.workers.cluster import connect_checked

    client: Client = connect_checked(address, timeout_s)
    return client


def open_link(address: str, first_s: float = 1.0, max_s: float = 30.0, echo: bool = True) -> SchedulerLink:
    """The service's :class:`SchedulerLink` to ``address`` (its start-up line on stderr, as
    :func:`sarship.workers.cluster.connect` prints it)."""
    import sys

    from sarship.workers.cluster import _quiet, dashboard_note

    _quiet()
    link = SchedulerLink(address, first_s, max_s)
    if echo:
        c = link.current()
        print(
            f"sarship: using Dask scheduler {address} ({len(c.scheduler_info().get('workers', {}))} workers), "
            f"{dashboard_note(c)}, reconnected with a back-off of {first_s:g}-{max_s:g} s when it goes "
            "away",
            file=sys.stderr,
        )
    return link
