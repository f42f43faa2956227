"""``.npy`` input, memory-mapped and read tile by tile.

**.npy** (``np.load(mmap_mode="r")``, read tile by tile):
2-D real -> intensity (amplitude with ``kind="amplitude"``);
2-D complex -> one SLC channel (name ``channels[0]``, default ``hh``);
(H, W, k) real -> k bands (as a multi-band TIFF);
(H, W, k) complex -> k SLC channels: k=2 dual-pol ``vh, vv`` (Sentinel-1 order; pass
``channels`` for others), k=3 quad-pol ``hh, hv, vv``, k=4 ``hh, hv, vh, vv``;
(H, W, 3, 3) -> covariance C3: ``c11, c22, c33`` float32 (real part of the diagonal) and
``c12, c13, c23`` complex64 (upper triangle); (H, W, 2, 2) -> ``c11, c12, c22``. The array
is stored as given and taken to be in the store's basis (*Covariance convention* in
:mod:`sarship.pipeline.readers.polsarpro`): a (H, W, 3, 3) array must be C3 ``E[k k^H]``,
k = [HH, sqrt2 HV, VV]; convert a T3 (Pauli) array first with :func:`t3_to_c3`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _check_dtype, _check_hw, _one_line, _Source


class _NpySource(_Source):
    def _mm(self):
        if getattr(self, "_mmap", None) is None:
            self._mmap = np.load(self.path, mmap_mode="r", allow_pickle=False)
        return self._mmap

    def _read(self, r0, r1, c0, c1):
        a = np.array(self._mm()[r0:r1, c0:c1])
        if self.layout == "covariance":
            return a
        return a.reshape(a.shape[0], a.shape[1], self.nbands)

    def release(self):
        self._mmap = None


def _open_npy(p: Path) -> _Source:
    try:
        a = np.load(p, mmap_mode="r", allow_pickle=False)
    except ValueError as exc:
        raise InputError(f"'{p}': not a readable .npy array (truncated or object array? {_one_line(exc)})") from None
    dt = a.dtype
    if dt.fields is not None:
        raise InputError(f"'{p}': structured arrays are not supported")
    _check_dtype(p, dt)
    shape = tuple(int(s) for s in a.shape)
    del a
    if any(s == 0 for s in shape):
        raise InputError(f"'{p}': empty array of shape {shape}")
    layout, nb = "bands", 1
    if len(shape) == 2:
        nb = 1
    elif len(shape) == 3:
        nb = shape[2]
    elif len(shape) == 4:
        if shape[2] != shape[3] or shape[2] not in (2, 3):
            raise InputError(
                f"'{p}': 4-D array of shape {shape}; a covariance image must be (H, W, 3, 3) or (H, W, 2, 2)"
            )
        layout, nb = "covariance", shape[2]
    else:
        raise InputError(
            f"'{p}': {len(shape)}-D array of shape {shape}; expected (H, W), (H, W, k), (H, W, 3, 3) or (H, W, 2, 2)"
        )
    _check_hw(p, shape[0], shape[1])
    return _NpySource(path=p, shape=(shape[0], shape[1]), nbands=nb, dtype=np.dtype(dt), fmt="npy", layout=layout)
