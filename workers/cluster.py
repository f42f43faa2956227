"""Dask cluster start-up: a local cluster for the run, or an existing scheduler.

The local default is one single-threaded worker *process* per core (the detectors are
Numba/NumPy code that holds the GIL for parts of its work; processes scale, threads
would not), so a run uses every core of the machine; each advertises the resource
``CPU=1``. A small run (``threads=True``: ``sarship detect`` on a scene of at most
:data:`THREADS_MAX_PX` pixels) gets one in-process worker with a thread per core instead
(resource ``CPU`` = cores): starting worker processes (each imports Dask, NumPy, Numba and
the detectors) costs seconds, more than such a scene's whole detection. With ``gpus=True`` on a machine with GPUs, the local cluster is instead one
process per GPU, pinned by ``CUDA_VISIBLE_DEVICES`` before it starts and advertising
``GPU`` (see :mod:`sarship.workers.gpus`), plus ``cpu_workers`` CPU processes if asked.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import sys
import warnings
from collections.abc import Iterator

from sarship.pipeline import settings
from sarship.pipeline.errors import InputError

#: ``sarship detect`` without ``--scheduler`` runs scenes of at most this many pixels on an
#: in-process threaded worker (see the module doc); ``SARSHIP_THREADS_MAX_PX`` overrides it
#: (0: always worker processes). 64 Mi px: an 8192 x 8192 scene. Measured on the 2-core test
#: machine (issue 17, bench/bench_profile.py, bench/RESULTS.md): worker processes cost ~0.85 s
#: to start, ~0.5 s to close, a second import of the detectors, Numba's cache and zarr in each
#: worker, and results pickled back; the kernels release the GIL, so threads lose nothing:
#: ``ca_cfar`` on 8192 x 8192 takes 4.4 s on threads against 7.7 s on processes, and on 4096 x
#: 4096 ``os_cfar`` 3.2 against 5.7 s, ``two_parameter`` 3.0 against 5.3 s.
THREADS_MAX_PX = settings.VARIABLES["threads_max_px"].default


def threads_max_px() -> int:
    """:data:`THREADS_MAX_PX`, or the ``SARSHIP_THREADS_MAX_PX`` setting (an integer >= 0)."""
    return settings.read("threads_max_px")


#: The interface a local cluster's scheduler, nannies and workers listen on (``SARSHIP_CLUSTER_HOST``
#: overrides it). Loopback: Dask's comms have no authentication, and whoever reaches a
#: scheduler or worker port can run code there (``SARSHIP_TOKENS`` guards the API only).
CLUSTER_HOST = settings.VARIABLES["cluster_host"].default


def cluster_host() -> str:
    """The interface a local cluster listens on: :data:`CLUSTER_HOST`, or the
    ``SARSHIP_CLUSTER_HOST`` setting (an IP address or a host name of this machine; ``0.0.0.0``
    opens the cluster to every network the machine is on). :class:`InputError` for a value
    that is not one."""
    return settings.read("cluster_host")


def _quiet() -> None:
    for name in (
        "distributed",
        "distributed.scheduler",
        "distributed.worker",
        "distributed.nanny",
        "distributed.core",
        "distributed.http.proxy",
        "bokeh",
        "tornado",
    ):
        logging.getLogger(name).setLevel(logging.ERROR)


def _port_in_use(address: str) -> bool:
    """Whether the TCP port of a dashboard address like ':8787' cannot be bound here."""
    host, _, port = address.rpartition(":")
    try:
        port_n = int(port)
    except ValueError:
        return False
    if port_n == 0:
        return False
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host or "", port_n))
        except OSError:
            return True
    return False


def _free_dashboard(address: str) -> tuple[str, str]:
    """The dashboard address to use (``address``, or any free port on the same interface when
    its port is taken) and a note for the start-up line."""
    if address and _port_in_use(address):
        return f"{address.rpartition(':')[0]}:0", f" (port {address.rpartition(':')[2]} is in use)"
    return address, ""


def dashboard_address_on(host: str, port: int = 0) -> str:
    """The dashboard address of a local cluster that listens on the same interface as
    ``host`` (the API's address, ``sarship serve``): the dashboard has no access control, so
    it must not be reachable from where the API is not. ``0.0.0.0``/``::``/empty: every
    interface, as the API; an IPv6 address: ``localhost`` (Dask cannot take an IPv6 literal
    here). Port 0: any free port."""
    import ipaddress

    h = (host or "").strip().strip("[]")
    if h in ("", "0.0.0.0", "::"):
        return f":{port}"
    try:
        ip = ipaddress.ip_address(h)
    except ValueError:
        return f"{h}:{port}"  # a host name
    if ip.version == 6:  # Dask splits the address at ':': no IPv6 literal; loopback is never wider
        return f"localhost:{port}"
    return f"{h}:{port}"


#: How to get the Dask dashboard where a scheduler serves none (it needs bokeh).
DASHBOARD_HINT = "install bokeh where the scheduler runs: pip install 'sarship[dashboard]'"


#: :func:`dashboard_serves`' answers by link, with when they were found: a run's record
#: and each start-up line ask again only after this many seconds.
_DASHBOARD_SEEN: dict[str, tuple[float, bool]] = {}
_DASHBOARD_TTL_S = 30.0


def dashboard_serves(link: str, timeout: float = 3.0) -> bool:
    """Whether the Dask dashboard at ``link`` really serves its plots.

    A scheduler without bokeh still answers its dashboard address (``/status`` is a page
    asking to install bokeh), so the link alone proves nothing: the scheduler's JSON index
    ``individual-plots.json`` lists the dashboard's plots, and is empty without bokeh.

    Parameters
    ----------
    link : str
        The dashboard link, e.g. ``http://127.0.0.1:8787/status``.
    timeout : float
        Seconds to wait for the scheduler's answer.

    Returns
    -------
    bool
        True when the index answers with at least one plot (an answer is kept 30 s).
    """
    import json
    import time
    import urllib.request

    seen = _DASHBOARD_SEEN.get(link)
    if seen is not None and time.monotonic() - seen[0] < _DASHBOARD_TTL_S:
        return seen[1]
    base = link.rsplit("/", 1)[0] if link.rstrip("/").endswith("/status") else link.rstrip("/")
    try:
        with urllib.request.urlopen(f"{base}/individual-plots.json", timeout=timeout) as r:  # noqa: S310
            ok = r.status == 200 and bool(json.loads(r.read(1 << 20) or b"{}"))
    except Exception:  # unreachable, not a Dask scheduler, not JSON: no dashboard to offer
        ok = False
    _DASHBOARD_SEEN[link] = (time.monotonic(), ok)
    return ok


def connect_checked(address: str, timeout_s: float = 10.0):
    """A :class:`distributed.Client` of the scheduler at ``address`` whose workers run this
    sarship version (:func:`check_versions`); one-line :class:`InputError` otherwise."""
    from distributed import Client

    try:
        client = Client(address, timeout=f"{timeout_s:g}s")
    except Exception as exc:
        raise InputError(f"cannot reach Dask scheduler at '{address}': {exc}") from None
    try:
        check_versions(client)
    except BaseException:
        client.close()
        raise
    return client


def dashboard_url(client) -> str | None:
    """The cluster's dashboard link, or None when it serves no dashboard (:func:`dashboard_serves`)."""
    try:
        link = client.dashboard_link
    except Exception:
        return None
    return link if link and dashboard_serves(link) else None


def dashboard_note(client) -> str:
    """The start-up line's words on the dashboard: its link, or why there is none."""
    link = dashboard_url(client)
    return f"dashboard {link}" if link else f"no dashboard ({DASHBOARD_HINT})"


def _sarship_version() -> str:
    """This process's sarship version (run on every worker by :func:`check_versions`)."""
    from sarship.pipeline import __version__

    return __version__


def check_versions(client) -> None:
    """Refuse a cluster whose workers run another sarship than this client.

    Tile tasks travel pickled by module path (``sarship.workers.tasks.run_tile``) and run
    the workers' own copy of the detectors, so a worker with another version (or none)
    would fail or, worse, compute with other maths: every process of a cluster must run the
    same sarship version. :class:`InputError` naming the workers otherwise.
    """
    from sarship.pipeline import __version__

    try:
        got = client.run(_sarship_version)
    except Exception as exc:
        raise InputError(
            f"the cluster's workers cannot run sarship ({type(exc).__name__}: {exc}); "
            f"install sarship {__version__} on every worker"
        ) from None
    other = {w: v for w, v in got.items() if v != __version__}
    if other:
        info = client.scheduler_info(n_workers=-1).get("workers", {})
        names = ", ".join(sorted(f"{info.get(w, {}).get('name', w)} at {w} ({v})" for w, v in other.items()))
        raise InputError(
            f"workers run another sarship version than this client ({__version__}): {names}; "
            f"every process of a cluster must run the same version"
        )


@contextlib.contextmanager
def connect(
    scheduler: str | None = None,
    n_workers: int | None = None,
    dashboard_address: str = "127.0.0.1:8787",
    echo: bool = True,
    gpus: bool | list[str] = False,
    cpu_workers: int = 0,
    gpu_threads: int | None = None,
    threads: bool = False,
    short_lived: bool = False,
    procs_per_gpu: int | None = None,
) -> Iterator[distributed.Client]:  # noqa: F821
    """Yield a connected :class:`distributed.Client`.

    ``scheduler``: address of an existing scheduler (``tcp://host:8786``); otherwise a
    :class:`distributed.LocalCluster` with ``n_workers`` processes (default: all cores)
    is started for the duration of the block, and its dashboard address is printed.
    ``gpus``: start one pinned worker per visible GPU instead (when there are any), or per
    GPU of a list of IDs, plus ``cpu_workers`` CPU workers. ``threads``: without GPU workers,
    one in-process worker with ``n_workers`` threads (default: all cores) instead of processes.
    ``short_lived``: the cluster lives for one command (``sarship detect``), so its worker
    processes may be forked (:func:`worker_start_method`). ``procs_per_gpu``: worker processes
    per GPU (default :func:`gpu_procs`).
    """
    _quiet()
    if scheduler:
        client = connect_checked(scheduler)
        if echo:
            n = len(client.scheduler_info().get("workers", {}))
            print(f"sarship: using Dask scheduler {scheduler} ({n} workers), {dashboard_note(client)}", file=sys.stderr)
        try:
            yield client
        finally:
            client.close()
        return
    from sarship.workers.gpus import visible_gpus

    gpu_ids = list(gpus) if isinstance(gpus, list) else (visible_gpus() if gpus else [])
    dashboard_address, note = _free_dashboard(dashboard_address)
    import dask

    method = worker_start_method(short_lived)
    # Dask's raw "Port 8787 is already in use" and the like; Python's warning that a process
    # with threads forks (the scheduler's loop thread; nothing in it is used by a child)
    with (
        warnings.catch_warnings(),
        dask.config.set(
            {
                "distributed.worker.multiprocessing-method": method,
                "distributed.nanny.pre-spawn-environ": nanny_environ(),
            }
        ),
    ):
        warnings.simplefilter("ignore")
        client, cluster, what = _start_local(
            gpu_ids, n_workers, dashboard_address, cpu_workers, gpu_threads, threads, procs_per_gpu
        )
    if "processes" in what:
        what += f" ({method})"
    if echo:
        print(f"sarship: local Dask cluster, {what}, {dashboard_note(client)}{note}", file=sys.stderr)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def nanny_environ() -> dict:
    """The environment Dask's nannies give a worker process they start
    (``distributed.nanny.pre-spawn-environ``), without ``MALLOC_TRIM_THRESHOLD_``.

    Dask sets that glibc tuning (64 KiB) to return freed memory to the system sooner; setting
    it also switches off glibc's dynamic mmap threshold, so every tile-sized buffer (a 2048 tile
    with its halo is 22 MB) is a fresh mmap whose pages fault in again on each read. Measured
    on the band (one H100, the service's spawned workers): a tile read 76 ms with it, 25 ms
    without (bench/RESULTS.md). A forked worker never had it (glibc reads it at process start).
    A ``MALLOC_TRIM_THRESHOLD_`` in the user's own environment is inherited as before."""
    import dask
    import distributed  # noqa: F401  (its defaults are dask config once imported)

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", None) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    return env


#: Start methods a local cluster's worker processes may use (``SARSHIP_WORKER_START``).
START_METHODS = settings.START_METHODS


def cuda_initialised() -> bool:
    """Whether this process has initialised CUDA, told without touching CUDA: the driver starts
    its own threads at ``cuInit`` (named ``cuda0000...``; ``cuda-EvtHandlr`` with a context),
    and they are listed in ``/proc/self/task``. Importing CuPy does not initialise it (Zarr
    imports CuPy whenever it is installed)."""
    import glob

    for path in glob.glob("/proc/self/task/*/comm"):
        try:
            with open(path) as f:
                if f.read().startswith("cuda"):
                    return True
        except OSError:  # the thread ended meanwhile
            continue
    return False


def worker_start_method(short_lived: bool = True) -> str:
    """How a local cluster starts its worker processes: ``SARSHIP_WORKER_START`` when set,
    else ``fork`` for the short-lived cluster of one command on Linux when this process has not
    initialised CUDA (:func:`cuda_initialised`), else Dask's default, ``spawn``.

    A forked worker inherits the interpreter with NumPy, SciPy, Zarr, Dask and sarship already
    imported, so it is ready at once instead of importing them again (1.2-1.5 s for
    ``distributed`` alone on the H100 host, measured there without compiled bytecode). Measured there on the 25000 x 16700 band, one H100,
    4 worker processes, ``sarship detect`` as typed (bench/RESULTS.md): warm 11.9 s with spawn,
    6.7 s with fork (cluster start 3.4 -> 1.1 s, land pass 4.1 -> 2.0 s, close 0.7 -> 0.3 s);
    cold 28.8 s -> 7.0 s; ``forkserver`` 9.8 s. Fork is not used where it is unsafe: a child of
    a process that has initialised CUDA cannot use CUDA; other platforms (no fork on Windows,
    macOS system frameworks) and the long-lived service, whose cluster restarts workers from a
    process with many threads, keep ``spawn``."""
    method = settings.read("worker_start")
    if method:
        return method
    if short_lived and sys.platform.startswith("linux") and not cuda_initialised():
        return "fork"
    return "spawn"


def gpu_procs(n_gpus: int = 1, long_lived: bool = False) -> int:
    """Worker processes per GPU of a local cluster: ``SARSHIP_GPU_PROCS``, else a quarter of
    the cores per GPU, at most 4 per GPU and at most 4 GPU worker processes in all (one per
    GPU beyond four GPUs). ``long_lived`` (the warm cluster, ``sarship warm``): without the cap
    of 4 in all, whose reason below is the start of a cluster for one command.

    Why several per GPU: a tile's labelling and the Python around its transfers hold one
    interpreter lock per process (its read and write too, with zarr-python); measured on the
    25000 x 16700 band, one H100, 16 cores, ``ca_cfar`` (bench/RESULTS.md): tiles 11.2 s with 1
    process, 5.3 s with 4, 5.3 s with 8 (2 threads each), with zarr-python; with tensorstore
    reading, one in-process worker of 4-16 threads was still slower (7.4-8.8 s as typed
    against 7.3-7.4 s with 4 processes).

    Why not more than 4 in all: every fresh process pays its own CUDA context, CuPy kernels and
    compiled-code loads, and several GPUs' contexts are made at once. On four H200s (64 cores,
    bench/RESULTS.md, issue 18, session 11) the band as typed took 10.7 s with 4 processes per
    GPU (16), 8.4 s with 2 (8) and 7.0 s with 1 (4); on warm ``sarship worker`` processes 4.5,
    4.8 and 4.1 s: more processes bought nothing there either."""
    procs = settings.read("gpu_procs")
    if procs is None:
        n = max(1, n_gpus)
        return max(1, min(4, (os.cpu_count() or 1) // (4 * n), 4 if long_lived else 4 // n))
    return procs


def gpu_cluster_spec(
    gpu_ids: list[str], cpu_workers: int, dashboard_address: str, host: str, gpu_threads: int = 2, per_gpu: int = 1
) -> dict:
    """The keyword arguments of the GPU local cluster's :class:`distributed.SpecCluster`: its
    scheduler and one pinned nanny per GPU process (:func:`sarship.workers.gpus.worker_specs`),
    the scheduler, every nanny and worker (and the worker's HTTP server, which listens where
    its worker does) on ``host`` (:func:`cluster_host`). A pure function of its arguments, so
    the GPU branch's binding is checked without a GPU."""
    from distributed import Scheduler

    from sarship.workers.gpus import worker_specs

    return {
        "workers": worker_specs(
            gpu_ids,
            cpu_workers,
            prefix="local-",
            silence_logs=logging.ERROR,
            gpu_threads=gpu_threads,
            gpu_procs=per_gpu,
            host=host,
        ),
        "scheduler": {"cls": Scheduler, "options": {"host": host, "dashboard_address": dashboard_address}},
        "silence_logs": logging.ERROR,
    }


def _start_local(gpu_ids, n_workers, dashboard_address, cpu_workers, gpu_threads, threads=False, per_gpu=None):
    """Start the local cluster and its client; returns (client, cluster, description). Every
    branch listens on :func:`cluster_host` (loopback unless configured)."""
    from distributed import Client, LocalCluster

    per_gpu = per_gpu or (gpu_procs(len(gpu_ids)) if gpu_ids else 1)
    host = cluster_host()

    if gpu_ids:
        from distributed import SpecCluster

        cluster = SpecCluster(
            **gpu_cluster_spec(
                gpu_ids,
                cpu_workers,
                dashboard_address,
                host,
                per_gpu=per_gpu,
                gpu_threads=gpu_threads or settings.read("gpu_threads"),
            )
        )
        what = f"{len(gpu_ids) * per_gpu} GPU worker processes" + (f" and {cpu_workers} CPU" if cpu_workers else "")
    elif threads:
        n = n_workers or os.cpu_count() or 1
        cluster = LocalCluster(
            n_workers=1,
            threads_per_worker=n,
            processes=False,
            # loopback TCP as the process cluster (inproc:// would name the machine's address in
            # the dashboard link), and the worker's own HTTP server on the cluster's interface
            # (Dask's default for it is every interface)
            protocol="tcp://",
            host=host,
            dashboard_address=dashboard_address,
            worker_dashboard_address=dashboard_address_on(host),
            silence_logs=logging.ERROR,
            resources={"CPU": n},
        )
        what = f"{n} threads in this process"
    else:
        n = n_workers or os.cpu_count() or 1
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host=host,
            dashboard_address=dashboard_address,
            silence_logs=logging.ERROR,
            resources={"CPU": 1},
        )
        what = f"{n} worker processes"
    client = Client(cluster)
    if gpu_ids:
        client.wait_for_workers(len(gpu_ids) * per_gpu + cpu_workers, timeout=120)
    return client, cluster, what
