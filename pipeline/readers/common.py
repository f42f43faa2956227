"""What the format readers share: the input-file base class :class:`_Source` (bounded
probe, read errors as one line), sample-type and size checks, the polarisation-token
pattern."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

#: Bounded sample for the ``auto`` rule: windows of this side at the centre and the
#: centres of the four quadrants.
PROBE_SIDE = 256

_POL_RE = re.compile(r"(?<![a-z0-9])(hh|hv|vh|vv)(?![a-z0-9])")


def _one_line(exc: BaseException) -> str:
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


# --------------------------------------------------------------------------------------
# sources: one input file each
# --------------------------------------------------------------------------------------


@dataclass
class _Source:
    """One input file: ``read`` returns ``(h, w, nbands)`` (or ``(h, w, n, n)``) windows."""

    path: Path
    shape: tuple[int, int]
    nbands: int
    dtype: np.dtype
    fmt: str  # "tiff" | "image" | "npy"
    layout: str = "bands"  # "bands" | "covariance"
    meta: dict[str, Any] = field(default_factory=dict)
    prefers_rows: bool = False

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def is_complex(self) -> bool:
        return np.issubdtype(self.dtype, np.complexfloating)

    def _read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        try:
            return self._read(r0, r1, c0, c1)
        except (InputError, MemoryError):
            raise
        except Exception as exc:
            raise InputError(
                f"'{self.path}': cannot read pixels rows {r0}:{r1}, cols {c0}:{c1} "
                f"(damaged or truncated file? {_one_line(exc)})"
            ) from None

    def release(self) -> None:
        """Drop memory maps (their resident pages count against RSS)."""

    def close(self) -> None:
        self.release()

    def probe(self) -> np.ndarray:
        """A bounded sample of the file: up to five PROBE_SIDE windows, flattened per band."""
        H, W = self.shape
        s = PROBE_SIDE
        centres = [
            (H // 2, W // 2),
            (H // 4, W // 4),
            (H // 4, 3 * W // 4),
            (3 * H // 4, W // 4),
            (3 * H // 4, 3 * W // 4),
        ]
        seen, parts = set(), []
        for cy, cx in centres:
            r0, c0 = max(0, min(cy - s // 2, H - s)), max(0, min(cx - s // 2, W - s))
            r1, c1 = min(H, r0 + s), min(W, c0 + s)
            if (r0, c0) in seen:
                continue
            seen.add((r0, c0))
            a = self.read(r0, r1, c0, c1)
            parts.append(a.reshape(-1, self.nbands))
        self.release()
        return np.concatenate(parts, axis=0)


def _check_dtype(p: Path, dt: np.dtype) -> None:
    if (
        not (np.issubdtype(dt, np.integer) or np.issubdtype(dt, np.floating) or np.issubdtype(dt, np.complexfloating))
        or dt == np.bool_
    ):
        raise InputError(f"'{p}': unsupported sample type {dt} (need integer, float or complex)")


def _check_hw(p: Path, H: int, W: int) -> None:
    if H < 1 or W < 1:
        raise InputError(f"'{p}': empty image ({H} x {W} pixels)")
