"""GPU twin of ``csk`` (:mod:`sarship.pipeline.detectors.csk`): the same window sums
(:func:`sarship.pipeline.gpu.box.centered_box_sum`, bit-identical to the CPU's) and the same
per-pixel IEEE operations, one CuPy element-wise kernel each, so masks equal the CPU's bit
for bit. CuPy is imported here only (lazily, through ``detect``'s dispatch)."""

from __future__ import annotations

from sarship.pipeline.detectors.csk import csk_window, decide


def csk_detect(block, halo: int, origin, p, prep: dict):
    """(mask, stat) of the core of a CuPy complex block; CuPy arrays."""
    import cupy as cp

    from sarship.pipeline.gpu.box import centered_box_sum

    if block.ndim != 2 or not cp.iscomplexobj(block):
        raise ValueError(f"csk needs a 2-D complex (SLC) block, got {block.dtype} {block.shape}")
    k, tested, pw, s11 = csk_window(block, halo, origin, int(p.window), p.nodata, centered_box_sum, cp)
    return decide(k, tested, pw, s11, int(prep["n_window"]), float(prep["threshold"]), p.cells, cp)
