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

A job's ``land_mask`` FILE is parsed and rasterised the same way (:func:`land_in_child`): in
a spawned child under the same cap, which writes the mask as a Zarr raster the job then reads;
a GeoJSON or hostile raster can exhaust that child only.

Cancelling (the job dismissed) sends SIGTERM: the child's handler unwinds, so the scene
store's temporary sibling is removed (:func:`sarship.pipeline.scene.atomic_store`); a child
that does not end within 10 s is killed.
"""

from __future__ import annotations

import errno
import multiprocessing as mp
import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.process import BaseProcess
    from types import FrameType

    from sarship.pipeline.errors import InputError

    #: The child's end of the pipe: it sends ``(kind, ...)`` messages, receives nothing.
    _ChildEnd = Connection[tuple[Any, ...], Any]

__all__ = [
    "IngestCrashed",
    "IngestRefused",
    "IngestTransient",
    "NO_SPACE",
    "ingest_in_child",
    "land_in_child",
    "transient_fault",
]

#: errno values of a write that failed for want of space (EFBIG: a file-size limit, RLIMIT_FSIZE).
NO_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def transient_fault(exc: BaseException) -> OSError | None:
    """The ``OSError`` for want of space (:data:`NO_SPACE`) behind ``exc``, if any: ``exc``
    itself or an exception it was raised from or while handling (the readers turn every
    failure into :class:`InputError` but keep the original in ``__cause__``/``__context__``)."""
    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
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


def _child(
    conn: _ChildEnd,
    src: str,
    out: str,
    sidecar_root: str | Path | bool | None,
    limits: dict[str, Any],
    memory_mb: float | None,
) -> None:
    import resource

    if memory_mb:
        cap = int(memory_mb * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    import os

    # one tile writer unless the operator sets SARSHIP_INGEST_WRITERS: the address-space cap counts
    # every thread's stack and malloc arena, and parallel writers bring tensorstore's threads
    os.environ.setdefault("SARSHIP_INGEST_WRITERS", "1")

    def stop(signum: int, frame: FrameType | None) -> NoReturn:
        raise SystemExit(128 + signum)  # unwind: the atomic store removes its temporary sibling

    signal.signal(signal.SIGTERM, stop)
    try:
        from sarship.pipeline.readers import InputLimits, ingest

        def progress(done: int, total: int) -> None:
            conn.send(("progress", done, total))

        ingest(
            [Path(src)],
            Path(out),
            progress=progress,
            sidecar_root=sidecar_root,
            limits=InputLimits(**limits, option="service"),
        )
        conn.send(("ok",))
    except SystemExit:
        raise
    except Exception as exc:
        fault = transient_fault(exc)
        if fault is not None:  # (checked first: the readers report a failed write as an InputError)
            why = str(fault.strerror or fault)
            conn.send(
                (
                    "transient",
                    f"[Errno {fault.errno}] "
                    + (why if why.startswith("cannot write") else f"cannot write the scene: {why}"),
                )
            )
        elif isinstance(exc, MemoryError):
            conn.send(
                (
                    "refused",
                    f"'{src}': ingest needs more memory than its cap of {memory_mb:g} MiB (SARSHIP_INGEST_MEMORY_MB)",
                )
            )
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


def _input_error() -> type[InputError]:
    from sarship.pipeline.errors import InputError

    return InputError


def ingest_in_child(
    src: Path,
    out: Path,
    *,
    sidecar_root: str | Path | bool | None,
    limits: dict[str, Any],
    memory_mb: float | None,
    progress: Callable[[int, int], None],
) -> None:
    """Run the ingest of ``src`` to ``out`` in a child process (see the module docstring).

    ``progress(done, total)`` is called in this process for every tile the child reports; an
    exception it raises (e.g. the job was dismissed) stops the child and is re-raised."""
    answer = _run_child(_child, (str(src), str(out), sidecar_root, limits, memory_mb), progress, "sarship-ingest")
    if answer[0] == "refused":
        raise IngestRefused(answer[1])
    if answer[0] == "transient":
        raise IngestTransient(answer[1])
    if answer[0] == "error":
        raise IngestCrashed(answer[1])


def _run_child(
    target: Callable[..., None], args: tuple[Any, ...], progress: Callable[[int, int], None], name: str
) -> tuple[Any, ...]:
    """Start ``target(conn, *args)`` in a spawned child and wait for its answer (the first
    message that is not ``("progress", done, total)``, each of which is handed to
    ``progress``); :class:`IngestCrashed` when the child ends without one."""
    ctx = mp.get_context("spawn")
    parent, child_end = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=target, name=name, daemon=True, args=(child_end, *args))
    proc.start()
    child_end.close()
    answer: tuple[Any, ...] | None = None
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
        raise IngestCrashed(f"the {name.removeprefix('sarship-')} process ended without an answer ({how})")
    return answer


def _land_child(
    conn: _ChildEnd,
    src: str,
    out: str,
    shape: tuple[int, int],
    attrs: dict[str, Any],
    tile: int,
    max_bytes: int,
    memory_mb: float | None,
) -> None:
    import resource

    if memory_mb:
        cap = int(memory_mb * 2**20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    def stop(signum: int, frame: FrameType | None) -> NoReturn:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        import numpy as np

        from sarship.pipeline.land.landmask_files import open_land_file
        from sarship.pipeline.scene import finalize_scene
        from sarship.workers.land import create_land_store

        H, W = (int(v) for v in shape)
        land = open_land_file(src, (H, W), attrs, max_bytes=max_bytes)
        arr = create_land_store(Path(out), (H, W), tile, {})
        rows = max(int(tile), 1)
        for r0 in range(0, H, rows):
            r1 = min(r0 + rows, H)
            arr[r0:r1, :] = np.asarray(land.read(r0, r1, 0, W), bool).astype(np.uint8)
            conn.send(("progress", r1, H))
        finalize_scene(out)
        conn.send(("ok", {"kind": land.kind, "format": land.format, "info": land.info}))
    except SystemExit:
        raise
    except MemoryError:
        conn.send(
            (
                "refused",
                f"parameter 'land_mask': '{src}' needs more memory than the cap of {memory_mb:g} MiB "
                "(SARSHIP_INGEST_MEMORY_MB)",
            )
        )
    except Exception as exc:
        if isinstance(exc, _input_error()):
            conn.send(("refused", str(exc)))
        elif (fault := transient_fault(exc)) is not None:
            conn.send(("transient", f"[Errno {fault.errno}] cannot write the land mask: {fault.strerror or fault}"))
        else:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
    except BaseException as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def land_in_child(
    src: Path,
    out: Path,
    *,
    shape: tuple[int, int],
    attrs: dict[str, Any],
    tile: int,
    max_bytes: int,
    memory_mb: float | None,
    progress: Callable[[int, int], None],
) -> dict[str, Any]:
    """Check and rasterise the ``land_mask`` FILE ``src`` onto a scene grid of ``shape`` (its
    georeference ``attrs``) in a child process under the same memory cap as an ingest: the
    file (a GeoJSON of any size up to ``max_bytes``, a hostile TIFF) is parsed there, never in
    the API process. The child writes the mask to the Zarr group ``out`` (array ``land``, 1 =
    land; what the job then reads as its land_mask) and answers the file's ``kind``, ``format``
    and ``info`` (:class:`~sarship.pipeline.land.landmask_files.LandFile`). A bad file (the
    reader's one line, or beyond the memory cap) raises
    :class:`~sarship.pipeline.errors.InputError`; the data folder full,
    :class:`IngestTransient`; anything else, :class:`IngestCrashed`."""
    answer = _run_child(
        _land_child,
        (str(src), str(out), tuple(shape), dict(attrs), int(tile), int(max_bytes), memory_mb),
        progress,
        "sarship-land",
    )
    if answer[0] == "ok":
        found: dict[str, Any] = answer[1]  # the child's {"kind", "format", "info"}
        return found
    if answer[0] == "refused":
        raise _input_error()(answer[1])
    if answer[0] == "transient":
        raise IngestTransient(answer[1])
    raise IngestCrashed(answer[1])


def _stop(proc: BaseProcess) -> None:
    if proc.is_alive():
        proc.terminate()
        proc.join(10)
    if proc.is_alive():
        proc.kill()
        proc.join(5)
