"""Absent (no-data) pixels of polarimetric blocks, shared by ``apwf``, ``pcdm`` and ``vb_polsar``.

The scene store marks absent pixels as NaN (ingest stores a declared no-data value as NaN
or 0). A polarimetric pixel is *present* when every element of its data (every complex
channel, or every element of its covariance matrix) is finite and it carries some signal
(span > 0: some channel non-zero, or some diagonal element of the covariance non-zero). A
pixel with all channels exactly 0 has no signal (zero-filled border, swath edge, a declared
no-data value of 0) and is absent too.

Absent pixels are never targets (decision 0) and enter no local or scene-wide statistic:
their products are zeroed before the window sums (so a NaN cannot spread through the
van Herk block sums either) and the valid cells are counted with the same tiling-invariant
box sums. The papers (Sun 2020, ch. 2, 4 and appendix A) assume complete data; what each
detector does with the counts is in its module docstring.

Pure array code: NumPy or CuPy (the array's own module), no arithmetic, so CPU and GPU give
the same boolean mask.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sarship.pipeline.gpu import is_device_array


def _xp(a):
    if is_device_array(a):
        import cupy

        return cupy
    return np


def present(block):
    """Boolean ``(rows, cols)``: the pixels of a ``(rows, cols, p)`` channel block or a
    ``(rows, cols, p, p)`` covariance block that are present (finite data, span > 0)."""
    xp = _xp(block)
    x = block
    if xp is np and x.ndim in (3, 4) and np.iscomplexobj(x):  # one pass in Numba (CPU)
        out = np.empty(x.shape[:2], np.bool_)
        (_present3 if x.ndim == 3 else _present4)(x, out)
        return out
    if x.ndim == 3:
        fin = xp.isfinite(x).all(axis=2)
        sig = (x != 0).any(axis=2)
    elif x.ndim == 4:
        fin = xp.isfinite(x).all(axis=(2, 3))
        d = xp.diagonal(x, axis1=2, axis2=3)
        sig = (d.real != 0).any(axis=2)
    else:
        raise ValueError(f"a polarimetric block is (rows, cols, p) or (rows, cols, p, p), got shape {x.shape}")
    return fin & sig


@njit(nogil=True, cache=True)
def _present3(x, out):
    R, C, p = x.shape
    for i in range(R):
        for j in range(C):
            fin = True
            sig = False
            for c in range(p):
                v = x[i, j, c]
                if not (math.isfinite(v.real) and math.isfinite(v.imag)):
                    fin = False
                if v.real != 0 or v.imag != 0:
                    sig = True
            out[i, j] = fin and sig


@njit(nogil=True, cache=True)
def _present4(x, out):
    R, C, p, _ = x.shape
    for i in range(R):
        for j in range(C):
            fin = True
            sig = False
            for a in range(p):
                for b in range(p):
                    v = x[i, j, a, b]
                    if not (math.isfinite(v.real) and math.isfinite(v.imag)):
                        fin = False
                if x[i, j, a, a].real != 0:
                    sig = True
            out[i, j] = fin and sig


def zero_absent(block, ok):
    """``block`` with its absent pixels (``~ok``) set to 0 (a copy; ``block`` itself if all present)."""
    xp = _xp(block)
    if bool(ok.all()):
        return block
    okb = ok.reshape(ok.shape + (1,) * (block.ndim - 2))
    return xp.where(okb, block, xp.zeros((), block.dtype))
