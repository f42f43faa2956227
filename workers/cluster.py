"""Dask cluster start-up: a local cluster for the run, or an existing scheduler.

The local default is one single-threaded worker *process* per core (the detectors are
Numba/NumPy code that holds the GIL for parts of its work; processes scale, threads
would not), so a run uses every core of the machine.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from typing import Iterator

from pipeline.errors import InputError


def _quiet() -> None:
    for name in ("distributed", "distributed.scheduler", "distributed.worker", "distributed.nanny",
                 "distributed.core", "distributed.http.proxy", "bokeh", "tornado"):
        logging.getLogger(name).setLevel(logging.ERROR)


def dashboard_url(client) -> str | None:
    try:
        return client.dashboard_link
    except Exception:
        return None


@contextlib.contextmanager
def connect(
    scheduler: str | None = None,
    n_workers: int | None = None,
    dashboard_address: str = ":8787",
    echo: bool = True,
) -> Iterator["distributed.Client"]:  # noqa: F821
    """Yield a connected :class:`distributed.Client`.

    ``scheduler``: address of an existing scheduler (``tcp://host:8786``); otherwise a
    :class:`distributed.LocalCluster` with ``n_workers`` processes (default: all cores)
    is started for the duration of the block, and its dashboard address is printed.
    """
    from distributed import Client, LocalCluster

    _quiet()
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except Exception as exc:
            raise InputError(f"cannot reach Dask scheduler at '{scheduler}': {exc}") from None
        if echo:
            n = len(client.scheduler_info().get("workers", {}))
            print(f"sarship: using Dask scheduler {scheduler} ({n} workers), dashboard {dashboard_url(client)}",
                  file=sys.stderr)
        try:
            yield client
        finally:
            client.close()
        return
    n = n_workers or os.cpu_count() or 1
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        dashboard_address=dashboard_address,
        silence_logs=logging.ERROR,
    )
    client = Client(cluster)
    if echo:
        print(f"sarship: local Dask cluster, {n} worker processes, dashboard {dashboard_url(client)}",
              file=sys.stderr)
    try:
        yield client
    finally:
        client.close()
        cluster.close()
