"""Shared fixtures: a real Dask LocalCluster (processes), scene helpers, shared data paths."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REAL = SHARED / "data" / "real"


@pytest.fixture(scope="session")
def client():
    """A real two-process Dask cluster, shared by the tests that need one."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def write_scene(path, arrays: dict, tile: int = 256, **attrs):
    """Write arrays into a scene store with the project's own store code."""
    from sarship.pipeline.scene import create_scene, finalize_scene

    shape = next(iter(arrays.values())).shape
    g = create_scene(path, shape, {k: v.dtype for k, v in arrays.items()}, tile=tile,
                     attrs={"kind": "intensity", **attrs})
    for k, v in arrays.items():
        g[k][:] = v
    finalize_scene(path)
    return Path(path)


def blobs_scene(shape=(301, 257), looks=2.0, seed=0, n=12, amp=40.0):
    """Gamma clutter with bright rectangular blobs (some across typical tile borders)."""
    rng = np.random.default_rng(seed)
    x = rng.gamma(looks, 1.0 / looks, shape).astype(np.float32)
    for _ in range(n):
        r = int(rng.integers(0, shape[0] - 6))
        c = int(rng.integers(0, shape[1] - 12))
        hh, ww = int(rng.integers(1, 6)), int(rng.integers(1, 12))
        x[r:r + hh, c:c + ww] += amp * rng.random((hh, ww)).astype(np.float32) + amp / 4
    return x
