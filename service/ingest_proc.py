"""Ingest in a child process with a memory cap: a hostile or oversized upload can exhaust
that process, never the API process that serves every other request.

The child is started with ``spawn`` (no copy of the server's threads, sockets or Dask client),
caps its address space at ``SARSHIP_INGEST_MEMORY_MB`` (``RLIMIT_AS``) before it imports
anything, and runs :func:`sarship.pipeline.readers.ingest` with the service's input limits
(``SARSHIP_MAX_PIXELS``, ``SARSHIP_MAX_CHUNK_MB``, ``SARSHIP_MAX_RATIO``). It reports
progress and the outcome through a pipe:

- a refused or unreadable file (the reader's :class:`InputError`, or the child running out of
  its memory cap) is :class:`IngestRefused`: the job fails with the reason and the inbox
  quarantines the file;
- a fault of ours, not of the file (:func:`transient_fault`: the data folder full, ``ENOSPC``,
  ``EDQUOT`` or ``EFBIG``, when the scene is written) is :class:`IngestTransient`: the job is
  tried again later and the file is never quarantined for it;
- anything else (the child killed by a signal, an unexpected error) is :class:`IngestCrashed`.

Cancelling (the job dismissed) sends SIGTERM: the child's handler unwinds, so the scene
store's temporary sibling is removed (:func:`sarship.pipeline.scene.atomic_store`); a child
that does not end within 10 s is killed.
"""

from __future__ import annotations

import errno
import multiprocessing as mp
import signal
from pathlib import Path
from typing import Any, Callable, Optional

__all__ = ["IngestCrashed", "IngestRefused", "IngestTransient", "NO_SPACE", "ingest_in_child", "transient_fault"]

#: errno values of a write that failed for want of space (EFBIG: a file-size limit, RLIMIT_FSIZE).
NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def transient_fault(exc: BaseException) -> Optional[OSError]:
    """The ``OSError`` for want of space (:data:`NO_SPACE`) behind ``exc``, if any: ``exc``
    itself or an exception it was raised from or while handling (the readers turn every
    failure into :class:`InputError` but keep the original in ``__cause__``/``__context__``)."""
    seen: set[int] = set()
    todo: list[Optional[BaseException]] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in NO_SPACE:
            return e
        todo += [e.__cause__, e.__context__]
    return None


class IngestRefused(Exception):
    """The file was refused (bad input, limits, out of the memory cap)."""


class IngestTransient(Exception):
    """The ingest failed for a fault of ours (the data folder is full), not the file's: try
    again later."""


class IngestCrashed(Exception):
    """The child ended without an answer (killed, crashed) or failed unexpectedly."""


def _child(conn, src: str, out: str, sidecar_root: Any, limits: dict, memory_mb: Optional[float]) -> None:
    import resource

    if memory_mb:
        cap = int(memory_mb * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    import os

    # one tile writer unless the operator sets SARSHIP_INGEST_WRITERS: the address-space cap counts
    # every thread's stack and malloc arena, and parallel writers bring tensorstore's threads
    os.environ.setdefault("SARSHIP_INGEST_WRITERS", "1")

    def stop(signum, frame):  # unwind: the atomic store removes its temporary sibling
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        from sarship.pipeline.readers import InputLimits, ingest

        def progress(done: int, total: int) -> None:
            conn.send(("progress", done, total))

        ingest([Path(src)], Path(out), progress=progress, sidecar_root=sidecar_root,
               limits=InputLimits(**limits, option="service"))
        conn.send(("ok",))
    except SystemExit:
        raise
    except Exception as exc:
        fault = transient_fault(exc)
        if fault is not None:  # (checked first: the readers report a failed write as an InputError)
            why = str(fault.strerror or fault)
            conn.send(("transient", f"[Errno {fault.errno}] " +
                       (why if why.startswith("cannot write") else f"cannot write the scene: {why}")))
        elif isinstance(exc, MemoryError):
            conn.send(("refused", f"'{src}': ingest needs more memory than its cap of {memory_mb:g} MiB "
                                  "(SARSHIP_INGEST_MEMORY_MB)"))
        elif isinstance(exc, _input_error()):
            msg = str(exc)
            if memory_mb and "ran out of memory" in msg:
                msg += f" [the ingest memory cap is {memory_mb:g} MiB: SARSHIP_INGEST_MEMORY_MB]"
            conn.send(("refused", msg))
        else:  # reported to the parent, which logs it
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
    except BaseException as exc:  # reported to the parent, which logs it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def _input_error() -> type:
    from sarship.pipeline.errors import InputError

    return InputError


def ingest_in_child(src: Path, out: Path, *, sidecar_root: Any, limits: dict, memory_mb: Optional[float],
                    progress: Callable[[int, int], None]) -> None:
    """Run the ingest of ``src`` to ``out`` in a child process (see the module docstring).

    ``progress(done, total)`` is called in this process for every tile the child reports; an
    exception it raises (e.g. the job was dismissed) stops the child and is re-raised."""
    ctx = mp.get_context("spawn")
    parent, child_end = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, name="sarship-ingest", daemon=True,
                       args=(child_end, str(src), str(out), sidecar_root, limits, memory_mb))
    proc.start()
    child_end.close()
    answer = None
    try:
        while answer is None:
            if parent.poll(0.5):
                try:
                    msg = parent.recv()
                except EOFError:  # the child ended without an answer
                    break
                if msg[0] == "progress":
                    progress(msg[1], msg[2])
                else:
                    answer = msg
            elif not proc.is_alive() and not parent.poll(0):
                break
    except BaseException:
        _stop(proc)
        raise
    finally:
        parent.close()
    proc.join(30)
    if answer is None:
        _stop(proc)
        code = proc.exitcode
        how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit status {code}"
        raise IngestCrashed(f"the ingest process ended without an answer ({how})")
    if answer[0] == "refused":
        raise IngestRefused(answer[1])
    if answer[0] == "transient":
        raise IngestTransient(answer[1])
    if answer[0] == "error":
        raise IngestCrashed(answer[1])


def _stop(proc) -> None:
    if proc.is_alive():
        proc.terminate()
        proc.join(10)
    if proc.is_alive():
        proc.kill()
        proc.join(5)
