"""Writing a scene tile by tile, and the looks of a written scene that states none
(rank-one test of covariance, MoLC estimate on a bounded sample of tiles).

Looks
-----
``looks`` argument (``looks_source="argument"``); else stated by the file (a ``looks`` /
``enl`` metadata item, the SNAP sidecar, or a Zarr scene's attribute:
``"attribute"``, with ``looks_note`` saying where); else 1 for SLC/quad-pol
(``"single-look complex"``); else estimated after writing with
:func:`sarship.pipeline.stats.looks.estimate_looks` (MoLC) on at most ``LOOKS_SAMPLE_TILES`` tiles spread
over the scene, each cut to at most ``LOOKS_SAMPLE_SIDE`` square (``intensity``, or ``c11``
for covariance): ``"estimated: MoLC ..."``. Covariance scenes are first tested for rank one
on the same sample (median of the largest ``1 - |c_ij|^2 / (c_ii c_jj)`` below
``RANK_ONE_TOL``: single-look ``k k^H`` data, where MoLC on ``c11`` would see the same
1-look speckle) and get ``looks`` = 1, ``"estimated: rank-one covariance ..."``. If that fails (e.g. all-zero data) ``looks`` is
null and ``looks_source`` says why.
"""

from __future__ import annotations

import os
import re
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line
from sarship.pipeline.scene import tile_slices

#: Bounded sample for the looks estimate: at most this many tiles, each cut to this side.
LOOKS_SAMPLE_TILES = 16
LOOKS_SAMPLE_SIDE = 1024

#: Covariance scenes whose sampled principal 2x2 minors ``1 - |c_ij|^2 / (c_ii c_jj)`` have a
#: median below this are rank one (single-look): ``looks`` = 1.
RANK_ONE_TOL = 1e-3


#: Tiles an ingest writes at once (:func:`_write_tiles`): ``SARSHIP_INGEST_WRITERS``, a whole
#: number >= 1, else the machine's cores, at most ``INGEST_WRITERS_MAX``.
INGEST_WRITERS_MAX = 8


def ingest_writers() -> int:
    """The number of tile writes an ingest keeps going at once (see :data:`INGEST_WRITERS_MAX`);
    a value of ``SARSHIP_INGEST_WRITERS`` that is not a whole number >= 1 is an InputError."""
    from sarship.pipeline import settings

    n = settings.read("ingest_writers")
    if n is not None:
        return n
    return max(1, min(os.cpu_count() or 1, INGEST_WRITERS_MAX))


def _write_error(exc: Exception) -> Exception:
    """A fault of the output (a full disk, a quota, a file-size limit), not of the input: an
    OSError with its errno, never an InputError (the service retries it). tensorstore reports the
    system's error code in its message (``[os_error_code='28']``); other errors pass unchanged."""
    if isinstance(exc, OSError):
        return OSError(exc.errno, f"cannot write the scene: {exc.strerror or _one_line(exc)}", exc.filename)
    m = re.search(r"os_error_code='(\d+)'", str(exc))
    if m is None:
        return exc
    code = int(m.group(1))
    return OSError(code, f"cannot write the scene: {os.strerror(code)}")


def _write_tiles(g, shape, tile, variables, read_tile, progress, store: str | os.PathLike | None = None):
    """Write the scene tile by tile: ``read_tile(r0, r1, c0, c1)`` -> {variable: array} in the
    calling thread, in order (the sources need not be thread-safe), each tile's encoding and
    file writes in :func:`ingest_writers` threads at once through tensorstore when ``store`` (the
    group's folder) is given and tensorstore is the reader (:func:`sarship.pipeline.tiling.inputs.reader_backend`),
    else in this thread through zarr-python (``g``). At most that many tiles wait to be written, so
    memory stays bounded; ``progress(done, total)`` in order, as tiles are written."""
    from sarship.pipeline.tiling.inputs import open_array, reader_backend

    grid = list(tile_slices(shape, tile))
    total = len(grid)
    n = ingest_writers() if store is not None and reader_backend() == "tensorstore" else 1
    if n == 1:
        arrays = {name: g[name] for name in variables}
        for done, (_i, _j, r0, r1, c0, c1) in enumerate(grid, 1):
            data = read_tile(r0, r1, c0, c1)
            for name, arr in arrays.items():
                try:
                    arr[r0:r1, c0:c1] = data[name]
                except OSError as exc:
                    raise _write_error(exc) from exc
            if progress is not None:
                progress(done, total)
        return
    outs = {name: open_array(str(Path(store) / name), write=True) for name in variables}

    def put(data: dict, r0: int, r1: int, c0: int, c1: int) -> None:
        for name, arr in outs.items():
            try:
                arr[r0:r1, c0:c1] = data[name]
            except Exception as exc:
                err = _write_error(exc)
                if err is exc:
                    raise
                raise err from exc

    pending: deque = deque()
    done = 0

    def finish_oldest() -> None:
        nonlocal done
        pending.popleft().result()
        done += 1
        if progress is not None:
            progress(done, total)

    with ThreadPoolExecutor(n, thread_name_prefix="sarship-ingest") as ex:
        for _i, _j, r0, r1, c0, c1 in grid:
            # every reader allocates what it returns (a view of a memory map keeps its map alive
            # after the source releases it), so a later read never changes a tile being written
            pending.append(ex.submit(put, read_tile(r0, r1, c0, c1), r0, r1, c0, c1))
            while len(pending) >= n or (pending and pending[0].done()):
                finish_oldest()
        while pending:
            finish_oldest()


def choose_codec(shape, tile, read_tile, variables) -> tuple[str, dict[str, Any]]:
    """``--codec auto``: the store's codec from a sample of the pixels about to be written: the
    centre (at most 1024 x 1024, :data:`LOOKS_SAMPLE_SIDE`) of up to 4 tiles spread over the
    scene (:func:`_sample_windows`), every variable, compressed with the store's zstd (level
    :data:`~sarship.pipeline.scene.ZSTD_LEVEL`).
    Returns ``"zstd"`` when that stores the sample in at most 1 / ``AUTO_CODEC_MIN_RATIO`` of
    its bytes, else ``"none"``, and the scene attributes that record the choice."""
    from numcodecs import Zstd

    from sarship.pipeline.scene import AUTO_CODEC_MIN_RATIO, ZSTD_LEVEL

    z = Zstd(level=ZSTD_LEVEL)
    wins = _sample_windows(shape, tile)
    raw = packed = 0
    for r0, r1, c0, c1 in wins[:: max(1, len(wins) // 4)][:4]:
        data = read_tile(r0, r1, c0, c1)
        for name in variables:
            b = np.ascontiguousarray(data[name]).tobytes()
            raw += len(b)
            packed += len(z.encode(b))
    ratio = raw / packed if packed else 1.0
    codec = "zstd" if ratio >= AUTO_CODEC_MIN_RATIO else "none"
    return codec, {
        "codec": codec,
        "codec_choice": {
            "rule": "auto",
            "zstd_ratio_of_sample": round(ratio, 4),
            "min_ratio": AUTO_CODEC_MIN_RATIO,
            "sample_bytes": raw,
        },
    }


def _sample_windows(shape, tile):
    """The bounded sample of tiles used for looks: ``(r0, r1, c0, c1)`` windows."""
    grid = list(tile_slices(shape, tile))
    k = min(LOOKS_SAMPLE_TILES, len(grid))
    picks = sorted({int(round(i)) for i in np.linspace(0, len(grid) - 1, k)})
    out = []
    for i in picks:
        _, _, r0, r1, c0, c1 = grid[i]
        h, w = r1 - r0, c1 - c0
        sh, sw = min(h, LOOKS_SAMPLE_SIDE), min(w, LOOKS_SAMPLE_SIDE)
        a0, b0 = r0 + (h - sh) // 2, c0 + (w - sw) // 2
        out.append((a0, a0 + sh, b0, b0 + sw))
    return out


def _rank_one_looks(store: Path, variables: list[str], shape, tile) -> dict[str, Any]:
    """``looks`` = 1 when the covariance is rank one (single-look: C = k k^H), else {}.

    A Hermitian positive semi-definite matrix is rank one iff all its principal 2x2 minors
    vanish; the test is the median, over sampled pixels with positive diagonals, of the
    largest ``1 - |c_ij|^2 / (c_ii c_jj)`` (1 - squared coherence), below ``RANK_ONE_TOL``.
    """
    import zarr

    n = 3 if "c33" in variables else 2
    pairs = [(i, j) for i in range(1, n + 1) for j in range(i + 1, n + 1)]
    arrs = {v: zarr.open_array(str(store / v), mode="r") for v in variables}
    vals = []
    wins = _sample_windows(shape, tile)
    for r0, r1, c0, c1 in wins:
        d = {i: np.asarray(arrs[f"c{i}{i}"][r0:r1, c0:c1], np.float64) for i in range(1, n + 1)}
        worst = np.zeros((r1 - r0, c1 - c0))
        ok = np.ones_like(worst, bool)
        for i, j in pairs:
            p = d[i] * d[j]
            ok &= np.isfinite(p) & (p > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                m = 1.0 - np.abs(np.asarray(arrs[f"c{i}{j}"][r0:r1, c0:c1], np.complex128)) ** 2 / p
            worst = np.maximum(worst, np.where(ok, np.abs(m), 0.0))
        vals.append(worst[ok])
    v = np.concatenate(vals) if vals else np.empty(0)
    if v.size == 0:
        return {}
    med = float(np.median(v))
    if med >= RANK_ONE_TOL:
        return {}
    return {
        "looks": 1.0,
        "looks_source": (
            f"estimated: rank-one covariance (median over sampled pixels of the largest "
            f"1 - |c_ij|^2/(c_ii c_jj) is {med:.1e} < {RANK_ONE_TOL:g}, {len(wins)} tile(s)): "
            "single look"
        ),
    }


def _estimate_scene_looks(store: Path, var: str, shape, tile) -> dict[str, Any]:
    """Looks by MoLC on a bounded sample of tiles re-read from the store."""
    import zarr

    from sarship.pipeline.stats.looks import estimate_looks

    arr = zarr.open_array(str(store / var), mode="r")
    picks = _sample_windows(shape, tile)

    def blocks():
        for a0, a1, b0, b1 in picks:
            yield np.asarray(arr[a0:a1, b0:b1])

    try:
        L = estimate_looks(blocks(), block=32)
    except InputError as exc:
        return {"looks": None, "looks_source": f"unknown: {exc}"}
    return {
        "looks": float(L),
        "looks_source": (
            f"estimated: MoLC (median log-variance of 32x32 windows, trigamma inverted) "
            f"on '{var}', {len(picks)} tile(s)"
        ),
    }
