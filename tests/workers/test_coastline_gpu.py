"""``land_mask=coastline`` and ``coastline+texture`` on GPU tiles: the coastline is rasterised on the
host before the tiles run (workers/land.py), each tile reads its block, sets land to NaN and the NaN
block goes to the device; the GPU run's land and detection masks must equal the CPU run's. Marked
``gpu``; skipped cleanly where CuPy or a CUDA device is missing (CI has none); ``bash
bench/gpu_suite.sh`` runs it on a GPU machine."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from sarship.pipeline.gpu import available
from sarship.pipeline.land import coastline
from sarship.pipeline.simulate import SimConfig, simulate
from sarship.workers.jobs import run_detection

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not available(), reason="needs CuPy and a CUDA GPU (none here)"),
    pytest.mark.skipif(not coastline.available(), reason="needs pip install 'sarship[coastline]'"),
]


def _arr(d, store, name):
    return np.asarray(zarr.open_group(str(d / store), mode="r")[name][...]) > 0


@pytest.mark.parametrize("land_mask", ["coastline", "coastline+texture"])
def test_gpu_run_equals_cpu_run_with_coastline(tmp_path, land_mask):
    cfg = SimConfig(
        shape=(384, 384),
        ships=4,
        seed=3,
        looks=4.0,
        clutter="k",
        land=True,
        scr_db=22.0,
        length_m=(60.0, 150.0),
        geo=(10.6, 59.8),
    )
    scene = simulate(tmp_path / "s.zarr", cfg, tile=128)
    st = {"land_mask": land_mask, "guard": 11, "background": 21}
    for device in ("cpu", "gpu"):
        run_detection(scene, "ca_cfar", st, out_dir=tmp_path / device, tile=128, device=device, progress=False)
    Lc, Lg = _arr(tmp_path / "cpu", "land.zarr", "land"), _arr(tmp_path / "gpu", "land.zarr", "land")
    Mc, Mg = _arr(tmp_path / "cpu", "mask.zarr", "mask"), _arr(tmp_path / "gpu", "mask.zarr", "mask")
    assert Lc.any() and np.array_equal(Lc, Lg)
    assert not (Mg & Lg).any()
    assert np.array_equal(Mc, Mg)  # ca_cfar's GPU twin is bit for bit
