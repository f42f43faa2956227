"""GPU twin of ``g0_cfar``, ``k_cfar`` and ``ggd_cfar`` (:mod:`sarship.pipeline.detectors.molc_cfar`).

The per-pixel part runs on the device as CuPy array operations, written once in
:func:`sarship.pipeline.detectors.molc_cfar.decide` for both array modules: the ring's power sums of
ln x come from :func:`sarship.pipeline.gpu.box.centered_box_sum` (the CPU's additions in the
CPU's order, bit-identical for identical inputs), the k-statistics, the table read and the
decision are the same IEEE operations in the same order. CUDA's ``log``/``log1p``/``sqrt``/
``exp`` may differ from the CPU's in the last bit, so statistics agree to ~1e-12 relative
and masks may differ only at pixels whose statistic lies within rounding of 1
(tests/pipeline/test_molc_gpu.py counts them). The tables (:mod:`sarship.pipeline.stats.molc`) are computed
on the host and copied to the device once per process.
"""

from __future__ import annotations

import functools


@functools.lru_cache(maxsize=64)
def _device_table(key: tuple, device_id: int):
    import cupy

    from sarship.pipeline.stats import molc

    tab = {"g0": molc.g0_table, "k": molc.k_table}.get(key[0])
    t = tab(key[1], key[2]) if tab is not None else molc.ggd_table(key[1])
    return cupy.asarray(t.f)


class _DeviceTable:
    """A :class:`sarship.pipeline.stats.molc.Table` whose values live on the current device."""

    def __init__(self, tab, f):
        self.x0, self.x1, self.inv_h, self.n, self.f = tab.x0, tab.x1, tab.inv_h, tab.n, f


def molc_cfar(block, halo: int, origin, b: int, g: int, censor, kind: str, tab, looks: float):
    """CuPy ``(mask, stat)`` of the core of a CuPy ``block`` (arguments as
    :func:`sarship.pipeline.detectors.molc_cfar.decide`)."""
    import cupy

    from sarship.pipeline.detectors.molc_cfar import GPU_STRIP_ROWS, decide
    from sarship.pipeline.gpu.box import centered_box_sum

    dt = _DeviceTable(tab, _device_table(tab.key, cupy.cuda.Device().id))
    return decide(cupy, centered_box_sum, block, halo, origin, b, g, censor, kind, dt, looks, strip_rows=GPU_STRIP_ROWS)
