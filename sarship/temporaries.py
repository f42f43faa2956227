"""The temporary outputs of a writing command, and their removal when it ends early.

A command writes under a temporary name beside its output and publishes it by a rename only when
complete (docs/interfaces/cli.md). When it is interrupted or fails, what it left is removed: the
command line does it for a command of its own, the warm process (``sarship/warm_process.py``)
for a command it ran, after the warm cluster's tasks of that command have ended.
"""

from __future__ import annotations

import shutil
from pathlib import Path


def temporaries(a) -> list[tuple[Path, str]]:
    """Where a writing command's temporary outputs go: (folder, glob pattern) pairs (``a``: its
    parsed command line)."""
    out = Path(a.out) if getattr(a, "out", None) else None
    if out is None:
        return []
    if a.command in ("simulate", "ingest", "enhance"):
        return [(out.parent, f".{out.name}.partial-*")]
    if a.command == "detect":
        return [(out, ".sarship-partial-*")]
    if a.command == "demo":
        return [(out, ".scene.zarr.partial-*"), (out / "detect", ".sarship-partial-*")]
    return []


def present(temps: list[tuple[Path, str]]) -> set[Path]:
    """The temporary outputs of ``temps`` there now (before the command starts: not its own)."""
    return {p for folder, pattern in temps for p in _glob(folder, pattern)}


def remove_new(temps: list[tuple[Path, str]], existing: set[Path]) -> None:
    """Remove the temporary outputs of ``temps`` (:func:`temporaries`) not in ``existing``: what
    a command that ended early left."""
    for folder, pattern in temps:
        for p in _glob(folder, pattern):
            if p not in existing:
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def _glob(folder: Path, pattern: str) -> list[Path]:
    try:
        return list(folder.glob(pattern)) if folder.is_dir() else []
    except OSError:
        return []
