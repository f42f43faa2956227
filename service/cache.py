"""Job products made once and cached in the job folder, never half-written.

A finished job's outputs never change, so every product derived from them (the mask COG, the
Zarr zip, the quicklook stretch, the scores) is built on first request and kept. The build
writes a temporary sibling and renames it into place (``os.replace`` is atomic on POSIX), so a
reader sees either no file or the whole file. Concurrent first requests do the work once: a
per-path thread lock serialises the API's threads, and an ``fcntl`` lock file serialises API
processes sharing the data folder (two ``sarship serve`` on one store); whoever gets the lock
second finds the product already there.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import threading
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path

_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _thread_lock(key: str) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(key, threading.Lock())


def build_once(out: Path, build: Callable[[Path], object]) -> Path:
    """``out``, built by ``build(tmp)`` into a temporary sibling and renamed, unless it exists.

    ``build`` must write the whole product at ``tmp`` (a file or a folder; what it returns is
    ignored); on any exception the temporary path is removed and nothing is left at ``out``.
    """
    if out.exists():
        return out
    with _thread_lock(str(out)):
        if out.exists():
            return out
        lock_path = out.parent / f".{out.name}.lock"
        with open(lock_path, "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                if out.exists():
                    return out
                tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
                try:
                    build(tmp)
                    os.replace(tmp, out)
                finally:
                    _remove(tmp)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
    return out


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        import shutil

        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


_trim_lock = threading.Lock()


def trim_oldest(files: Iterable[Path], limit_bytes: int) -> int:
    """Remove the oldest (by modification time: products are written once) of ``files`` until
    those left take at most ``limit_bytes``; the bytes removed. Files that vanish meanwhile (a
    concurrent trim, a dismissed job) are skipped."""
    with _trim_lock:
        sized = []
        for p in files:
            try:
                st = p.stat()
            except OSError:
                continue
            sized.append((st.st_mtime, st.st_size, p))
        total = sum(s for _, s, _ in sized)
        removed = 0
        for _, size, p in sorted(sized, key=lambda t: t[0]):
            if total <= limit_bytes:
                break
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
            total -= size
            removed += size
        return removed
