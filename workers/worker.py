"""``sarship worker``: this machine's Dask workers for a scheduler, pinned per GPU.

``--gpu-procs`` worker processes per GPU (``CUDA_VISIBLE_DEVICES`` set before each process
starts, ``--gpu-threads`` task slots each, resource ``GPU`` = one unit per slot; the default
number of processes is the local cluster's, so a deployed worker feeds its GPU as
``sarship detect`` does) and ``--cpus``
single-threaded CPU worker processes (resource ``CPU=1`` each), all under one command that
stops them together on SIGINT/SIGTERM (exit 0). When its scheduler goes away (killed,
restarted, unreachable) Dask's workers close; the command then closes the rest and exits 1
(:data:`EXIT_SCHEDULER_GONE`), so that a service manager restarts it (systemd's
``Restart=on-failure``) and the new command joins the restarted scheduler.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import sys

from sarship.pipeline.errors import InputError
from sarship.workers.gpus import parse_gpus, worker_specs


async def _reachable(address: str, timeout: float = 10.0) -> None:
    from distributed.comm import connect

    try:
        comm = await connect(address, timeout=timeout)
        await comm.close()
    except Exception as exc:
        raise InputError(f"cannot reach Dask scheduler at '{address}': {exc}") from None


#: ``sarship worker``'s exit status when its workers ended without being asked to (the
#: scheduler went away, or closed them): a failure, so that a service manager restarts it
#: (systemd's ``Restart=on-failure``; the restarted command waits for the scheduler to answer).
EXIT_SCHEDULER_GONE = 1


async def _main(address: str, specs: dict[str, dict], echo: bool) -> int:
    """Run the nannies until SIGINT/SIGTERM (0) or until one of them ends on its own
    (:data:`EXIT_SCHEDULER_GONE`, after closing the others, with one line on stderr)."""
    await _reachable(address)
    nannies = [s["cls"](address, **s["options"]) for s in specs.values()]
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    await asyncio.gather(*nannies)
    if echo:
        for name, s in specs.items():
            res = s["options"]["resources"]
            pin = s["options"]["env"].get("CUDA_VISIBLE_DEVICES")
            where = f"GPU {pin}" if "GPU" in res else "CPU"
            print(f"sarship: worker {name} ({where}, resources {res}) -> {address}", file=sys.stderr, flush=True)
    # a nanny ends on its own when its worker lost the scheduler (Dask's workers close then:
    # "worker-handle-scheduler-connection-broken") or the scheduler closed it; it restarts a
    # worker process that crashed by itself
    ended = [asyncio.ensure_future(n.finished()) for n in nannies]
    stopped = asyncio.ensure_future(stop.wait())
    await asyncio.wait([*ended, stopped], return_when=asyncio.FIRST_COMPLETED)
    gone = [name for name, f in zip(specs, ended) if f.done()] if not stop.is_set() else []
    await asyncio.gather(*(n.close(timeout=20) for n in nannies), return_exceptions=True)
    for f in (*ended, stopped):
        f.cancel()
    if gone:
        print(
            f"sarship worker: worker {', '.join(gone)} ended without being asked to: the scheduler at "
            f"'{address}' went away or closed it; exiting {EXIT_SCHEDULER_GONE} so that a service manager "
            "restarts it",
            file=sys.stderr,
            flush=True,
        )
        return EXIT_SCHEDULER_GONE
    return 0


def serve(
    scheduler: str,
    gpus: str = "all",
    cpus: int | None = None,
    name: str | None = None,
    memory_limit: str | None = None,
    echo: bool = True,
    gpu_threads: int = 2,
    gpu_procs: int | None = None,
) -> int:
    """Start the workers and block until they stop: 0 after SIGINT/SIGTERM,
    :data:`EXIT_SCHEDULER_GONE` (1) when they ended on their own (the scheduler went away). ``gpu_procs``: worker
    processes per GPU (default: the local cluster's rule, :func:`sarship.workers.cluster.gpu_procs`:
    ``SARSHIP_GPU_PROCS``, else a quarter of the cores per GPU, at most 4 per GPU and 4 in all)."""
    if not scheduler:
        raise InputError("--scheduler ADDRESS is required (e.g. tcp://10.0.0.1:8786)")
    gpu_ids = parse_gpus(gpus)
    if cpus is None:
        cpus = 0 if gpu_ids else (os.cpu_count() or 1)
    if cpus < 0:
        raise InputError(f"--cpus must be >= 0, got {cpus}")
    if not gpu_ids and cpus == 0:
        raise InputError("nothing to start: no GPU selected (--gpus) and --cpus 0")
    prefix = f"{name or socket.gethostname()}-"
    from sarship.workers.cluster import _quiet
    from sarship.workers.cluster import gpu_procs as default_gpu_procs

    _quiet()
    if gpu_threads < 1:
        raise InputError(f"--gpu-threads must be >= 1, got {gpu_threads}")
    if gpu_procs is None:
        gpu_procs = default_gpu_procs(len(gpu_ids)) if gpu_ids else 1
    if gpu_procs < 1:
        raise InputError(f"--gpu-procs must be >= 1, got {gpu_procs}")
    import dask

    from sarship.workers.cluster import nanny_environ

    with dask.config.set({"distributed.nanny.pre-spawn-environ": nanny_environ()}):  # (reads: see there)
        return asyncio.run(
            _main(
                scheduler,
                worker_specs(gpu_ids, cpus, prefix, memory_limit, gpu_threads=gpu_threads, gpu_procs=gpu_procs),
                echo,
            )
        )
