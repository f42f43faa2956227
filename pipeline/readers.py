"""`sarship ingest`: turn SAR images into a scene store (see :mod:`sarship.pipeline.scene`).

:func:`ingest` reads one or more inputs and writes a Zarr v3 scene of square ``tile x tile``
zstd chunks, **tile by tile**, into a temporary sibling that is renamed into place only when
complete (:func:`sarship.pipeline.scene.atomic_store`): a failure leaves nothing behind and an
existing scene at ``out`` untouched.

Inputs (files recognised by their first bytes; PolSARpro folders by their file names)
-------------------------------------------------------------------------------------
- **TIFF / GeoTIFF / BigTIFF** (tifffile): real or complex samples, any number of bands
  (contiguous or planar, or several pages of one series), stripped or tiled, compressed or
  not. Uncompressed contiguous data are memory-mapped; anything else is read through
  tifffile's ``aszarr()`` chunk by chunk. A stripped file whose tile row is small enough
  (<= ``ROW_BAND_BYTES``) is read one tile row at a time so strips are decoded once.
- **PNG / JPEG** (Pillow): grey, or RGB whose three channels are equal (HRSID stores grey
  as RGB). JPEG noise may make grey channels differ slightly, so an RGB image is accepted as
  grey when ``max |R-G|, |R-B|, |G-B| <= GREY_TOLERANCE_DN`` (8 DN) and ingested as the
  mean of the three; any other colour image is refused. Pillow decodes the whole image
  (8-bit, 1-3 bytes per pixel): PNG/JPEG are *not* streamed; use a tiled GeoTIFF for scenes
  larger than memory.
- **.npy** (``np.load(mmap_mode="r")``, read tile by tile):
  2-D real -> intensity (amplitude with ``kind="amplitude"``);
  2-D complex -> one SLC channel (name ``channels[0]``, default ``hh``);
  (H, W, k) real -> k bands (as a multi-band TIFF);
  (H, W, k) complex -> k SLC channels: k=2 dual-pol ``vh, vv`` (Sentinel-1 order; pass
  ``channels`` for others), k=3 quad-pol ``hh, hv, vv``, k=4 ``hh, hv, vh, vv``;
  (H, W, 3, 3) -> covariance C3: ``c11, c22, c33`` float32 (real part of the diagonal) and
  ``c12, c13, c23`` complex64 (upper triangle); (H, W, 2, 2) -> ``c11, c12, c22``. The array
  is stored as given and taken to be in the store's basis (below): a (H, W, 3, 3) array must
  be C3 ``E[k k^H]``, k = [HH, sqrt2 HV, VV]; convert a T3 (Pauli) array first with
  :func:`t3_to_c3`.
- **a PolSARpro folder** (C3, T3 or C2; the path of the folder, of its ``config.txt`` or of
  its ``C11.bin`` / ``T11.bin``): one raw file per matrix element, ``C11.bin``,
  ``C12_real.bin``, ``C12_imag.bin``, ``C13_real.bin``, ``C13_imag.bin``, ``C22.bin``,
  ``C23_real.bin``, ``C23_imag.bin``, ``C33.bin`` (T3: ``T11.bin`` ...; C2: ``C11``,
  ``C12_real``, ``C12_imag``, ``C22``), each with an ENVI header ``C11.bin.hdr`` (or
  ``C11.hdr``): ``samples``, ``lines``, ``bands = 1``, ``data type = 4`` (float32; 5,
  float64, is also read), ``interleave = bsq`` (bil/bip are the same layout for one band),
  ``header offset``, ``byte order`` (0 little-endian, the default; 1 big-endian). File names
  are matched case-insensitively. ``config.txt`` (``Nrow``, ``Ncol``, ``PolarCase``,
  ``PolarType``) is optional; when present its size must agree with the headers, it decides
  C2 (``PolarType`` pp1/pp2/pp3) vs C3 (``full``; without it: C3 when ``C33.bin`` or
  ``C13_real.bin`` exist) and gives the size of element files that have no header (then
  float32 little-endian). Every element file is memory-mapped (``numpy.memmap``) and read
  tile by tile. T3 is converted to C3 per tile (float64 arithmetic, stored float32 /
  complex64), see *Covariance convention*. Missing element files, a file size other than
  ``samples * lines * bytes + header offset``, element files of different sizes, other data
  types, several bands or another interleave raise :class:`InputError` naming the file.
  C4/T4 (bistatic) and T2 folders are refused. A folder cannot be stacked with other inputs.
- **a Zarr scene** (a folder with ``zarr.json``): re-tiled / copied with its attributes
  (``kind``, ``band`` and ``channels`` are then ignored; ``looks`` overrides).

Anything else, and any file that cannot be read, raises :class:`InputError` with one line
naming the file and the problem.

Covariance convention
---------------------
A covariance scene stores ``c_ij = E[k_i k_j^*]`` (upper triangle; ``c_ji = conj(c_ij)``)
with the **lexicographic** scattering vector ``k = [HH, sqrt2 HV, VV]``: PolSARpro's C3
(``c22 = 2 E|HV|^2``), recorded as the attribute ``covariance_basis`` =
``"lexicographic [HH, sqrt2 HV, VV]"``. A coherency matrix ``T = E[k_p k_p^H]`` with the Pauli
vector ``k_p = (1/sqrt2) [HH+VV, HH-VV, 2 HV] = U k`` (``PAULI_U``,
``U = (1/sqrt2) [[1, 0, 1], [1, 0, -1], [0, sqrt2, 0]]``, unitary) is converted with
``C = U^H T U``. C2 (dual-pol) scenes store ``E[k k^H]`` of the two channels as given,
``k = [k1, k2]`` with no sqrt2; ``covariance_basis`` names the channels when the PolSARpro
``PolarType`` does (pp1: [HH, HV], pp2: [VV, VH], pp3: [HH, VV]). Attributes of covariance
scenes: ``format`` (``"npy covariance C3"``, ``"PolSARpro C3"``, ``"PolSARpro C2"`` or
``"PolSARpro T3 -> C3"``), ``covariance_basis``; for PolSARpro also ``source_files``,
``byte_order``, ``polsarpro_config``.

Quantities and the ``auto`` rule for real samples
-------------------------------------------------
Real bands are *detected* data, stored as float32 intensity (amplitude is squared). With
``kind="auto"`` a file's real bands are taken, first rule that applies:

1. as (re, im) pairs of SLC channels when a SNAP metadata sidecar says
   ``SAMPLE_TYPE=COMPLEX`` and there are two bands per polarisation (OpenSARShip SLC chips),
   or when the sampled values include negative numbers and the band count is even
   (negative values cannot be amplitude or intensity; an odd count is refused);
2. as the file says: a tifffile JSON description or GDAL metadata item ``kind`` /
   ``sample_type`` / ``quantity`` / ``unit(s)`` or a band description naming
   ``amplitude``/``magnitude`` or ``intensity``/``power``/``sigma0``/``beta0``/``gamma0``;
3. PNG/JPEG: amplitude (the contract);
4. integer sample types (8/16/32-bit digital numbers): amplitude;
5. floating-point samples that are all whole numbers >= 0 (with some > 1) in a bounded
   sample of the file: amplitude digital numbers exported as float (OpenSARShip ``Patch``
   GRD chips are float32 holding uint16 DN; their ``Patch_Cal`` sigma0 twins are not whole
   and come out as intensity);
6. other floating-point samples: intensity.

``.npy`` 2-D/3-D real arrays are intensity unless ``kind="amplitude"`` (the contract; rules
1 (negative values) and 4-5 are not applied to them). The rule taken is recorded in the
``quantity_rule`` attribute. ``kind="amplitude"`` or ``"intensity"`` forces the choice;
``kind="slc"`` or ``"quadpol"`` pairs real bands as (re, im) (an even count is required).

Several real bands are stored as ``intensity_<name>`` each (names from ``channels``, else
the sidecar/band-description polarisations, else polarisation tokens in the file names when
several files are stacked, else ``b0, b1, ...``) and ``intensity`` = the band chosen by
``band`` (name or index; default band 0).

Several input files are stacked as channels; they must have equal shapes. Complex channel
names come from ``channels``, else polarisation tokens in the file names (``hh``, ``hv``,
``vh``, ``vv``), else by count (1: ``hh``; 2: ``vh, vv``; 3: ``hh, hv, vv``;
4: ``hh, hv, vh, vv``). Complex channels must be named among ``hh, hv, vh, vv``.
``kind`` attribute: ``quadpol`` when ``hh, hv, vv`` are all present, else ``slc``.

Attributes written
------------------
``kind``, ``looks``, ``looks_source``, ``tile``, ``source`` (input file names),
``channels``, ``quantity`` (what the input samples were), ``quantity_rule``,
``sample_dtype``, ``sarship_version``; and when known ``intensity_band``,
``pixel_spacing_m`` ([azimuth, range]; for map-projected GeoTIFFs [row, column] ground
spacing) with ``pixel_spacing_source``, ``crs`` ("EPSG:n") + ``transform`` (GDAL order
``[c, a, b, f, d, e]``, PixelIsPoint shifted to PixelIsArea as GDAL does) or ``gcps``,
``sensor``, ``acquired`` (ISO 8601), ``product``, ``polarisations``.

A ``GDAL_NODATA`` value other than 0 is left out of the ``auto`` sample and stored as 0
(no data) in intensity.

GeoTIFF: ``ModelPixelScale`` + one ``ModelTiepoint``, or ``ModelTransformation``; EPSG from
``ProjectedCSTypeGeoKey`` or ``GeographicTypeGeoKey``. ``pixel_spacing_m`` comes from the
pixel size when the CRS is projected in metres (``ProjLinearUnitsGeoKey``, or a known
metre-based EPSG code when that key is absent); for geographic CRSs (degrees, e.g. EPSG:4326)
it is approximated on the WGS84 ellipsoid at the scene-centre latitude and
``pixel_spacing_source`` says so.

SNAP sidecar: a SNAP/BEAM ``Abstracted_Metadata`` XML named ``<folder>.xml`` in the file's
folder or its parent (the OpenSARShip layout ``<product>/Patch/<chip>.tif`` +
``<product>/<product>.xml``), or ``<stem>.xml`` beside the file, gives ``sensor``
(MISSION + ACQUISITION_MODE), ``acquired`` (first_line_time), ``product``,
``polarisations`` (channel names), ``pixel_spacing_m`` (azimuth_spacing, range_spacing) and
the nominal looks (azimuth_looks x range_looks).

Looks
-----
``looks`` argument (``looks_source="argument"``); else stated by the file (a ``looks`` /
``enl`` metadata item, the SNAP sidecar, or a Zarr scene's attribute:
``"attribute"``, with ``looks_note`` saying where); else 1 for SLC/quad-pol
(``"single-look complex"``); else estimated after writing with
:func:`sarship.pipeline.looks.estimate_looks` (MoLC) on at most ``LOOKS_SAMPLE_TILES`` tiles spread
over the scene, each cut to at most ``LOOKS_SAMPLE_SIDE`` square (``intensity``, or ``c11``
for covariance): ``"estimated: MoLC ..."``. Covariance scenes are first tested for rank one
on the same sample (median of the largest ``1 - |c_ij|^2 / (c_ii c_jj)`` below
``RANK_ONE_TOL``: single-look ``k k^H`` data, where MoLC on ``c11`` would see the same
1-look speckle) and get ``looks`` = 1, ``"estimated: rank-one covariance ..."``. If that fails (e.g. all-zero data) ``looks`` is
null and ``looks_source`` says why.
"""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.scene import (
    COMPLEX_CHANNELS,
    DEFAULT_TILE,
    Scene,
    atomic_store,
    create_scene,
    finalize_scene,
    open_scene,
    tile_slices,
)

#: ``kind`` values accepted by :func:`ingest`.
INGEST_KINDS = ("auto", "amplitude", "intensity", "slc", "quadpol", "covariance")

#: Largest channel difference (digital numbers) of an RGB image still taken as grey.
GREY_TOLERANCE_DN = 8

#: A source that prefers whole tile rows (stripped TIFF) is read a tile row at a time when
#: the row band is at most this many bytes; otherwise tile by tile.
ROW_BAND_BYTES = 256 * 2**20

#: Bounded sample for the looks estimate: at most this many tiles, each cut to this side.
LOOKS_SAMPLE_TILES = 16
LOOKS_SAMPLE_SIDE = 1024

#: Bounded sample for the ``auto`` rule: windows of this side at the centre and the
#: centres of the four quadrants.
PROBE_SIDE = 256

_POL_RE = re.compile(r"(?<![a-z0-9])(hh|hv|vh|vv)(?![a-z0-9])")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


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
        except InputError:
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
        centres = [(H // 2, W // 2), (H // 4, W // 4), (H // 4, 3 * W // 4),
                   (3 * H // 4, W // 4), (3 * H // 4, 3 * W // 4)]
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


class _TiffSource(_Source):
    tif: Any = None
    series: Any = None
    yx: tuple[int, int] = (0, 1)
    memmappable: bool = False

    def _arr(self):
        if getattr(self, "_array", None) is None:
            if self.memmappable:
                import tifffile

                self._array = tifffile.memmap(str(self.path), series=0, mode="r")
            else:
                import zarr

                self._store = self.series.aszarr(level=0)
                self._array = zarr.open(self._store, mode="r")
        return self._array

    def _read(self, r0, r1, c0, c1):
        arr = self._arr()
        ndim = len(self.series.shape)
        idx = [slice(None)] * ndim
        iy, ix = self.yx
        idx[iy] = slice(r0, r1)
        idx[ix] = slice(c0, c1)
        a = np.asarray(arr[tuple(idx)])
        a = np.moveaxis(a, (iy, ix), (0, 1))
        a = a.reshape(a.shape[0], a.shape[1], -1)
        if a.dtype.byteorder not in ("=", "|"):
            a = a.astype(a.dtype.newbyteorder("="))
        return np.ascontiguousarray(a)

    def release(self):
        if not self.memmappable:
            return  # the zarr view over the open file holds no pixel memory
        self._array = None

    def close(self):
        self._array = None
        st = getattr(self, "_store", None)
        if st is not None:
            try:
                st.close()
            except Exception:
                pass
        if self.tif is not None:
            try:
                self.tif.close()
            except Exception:
                pass


class _ImageSource(_Source):
    data: np.ndarray | None = None

    def _read(self, r0, r1, c0, c1):
        return self.data[r0:r1, c0:c1, None]


# --------------------------------------------------------------------------------------
# opening files
# --------------------------------------------------------------------------------------


def _sniff(p: Path) -> str:
    if p.is_dir():
        if (p / "zarr.json").exists() or (p / ".zgroup").exists():
            return "zarr"
        if _polsarpro_folder(p) is not None:
            return "polsarpro"
        raise InputError(f"'{p}' is a folder but not a Zarr scene (no zarr.json) nor a PolSARpro "
                         "C3/T3/C2 folder (no C11.bin or T11.bin)")
    if _polsarpro_folder(p) is not None:
        return "polsarpro"
    if p.name.lower() == "config.txt":
        raise InputError(f"'{p}': a config.txt, but its folder holds no PolSARpro C11.bin or T11.bin")
    if re.fullmatch(r"[ct]\d\d(_real|_imag)?\.bin", p.name.lower()) and _polsarpro_folder(p.parent):
        raise InputError(f"'{p}' is one element of a PolSARpro folder: pass the folder '{p.parent}' "
                         "(or its config.txt)")
    try:
        with open(p, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise InputError(f"'{p}': cannot open ({_one_line(exc)})") from None
    if not head:
        raise InputError(f"'{p}' is empty")
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        return "image"
    if head[:3] == b"\xff\xd8\xff":
        return "image"
    if head[:6] == b"\x93NUMPY":
        return "npy"
    if head[:4] == b"PK\x03\x04" and p.suffix.lower() == ".npz":
        raise InputError(f"'{p}': .npz archives are not supported; save one array with np.save")
    raise InputError(
        f"'{p}': unrecognised format (expected TIFF/GeoTIFF, PNG, JPEG, .npy or a Zarr scene)"
    )


def _open_source(p: Path) -> _Source:
    fmt = _sniff(p)
    try:
        if fmt == "tiff":
            return _open_tiff(p)
        if fmt == "image":
            return _open_image(p)
        if fmt == "npy":
            return _open_npy(p)
        if fmt == "polsarpro":
            return _open_polsarpro(_polsarpro_folder(p))
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"'{p}': cannot read as {fmt.upper()} ({_one_line(exc)})") from None
    raise InputError(f"'{p}': a Zarr scene cannot be combined with other inputs")


def _check_dtype(p: Path, dt: np.dtype) -> None:
    if not (np.issubdtype(dt, np.integer) or np.issubdtype(dt, np.floating)
            or np.issubdtype(dt, np.complexfloating)) or dt == np.bool_:
        raise InputError(f"'{p}': unsupported sample type {dt} (need integer, float or complex)")


def _check_hw(p: Path, H: int, W: int) -> None:
    if H < 1 or W < 1:
        raise InputError(f"'{p}': empty image ({H} x {W} pixels)")


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
            f"'{p}': {len(shape)}-D array of shape {shape}; expected (H, W), (H, W, k), "
            "(H, W, 3, 3) or (H, W, 2, 2)"
        )
    _check_hw(p, shape[0], shape[1])
    return _NpySource(path=p, shape=(shape[0], shape[1]), nbands=nb, dtype=np.dtype(dt),
                      fmt="npy", layout=layout)


def _open_image(p: Path) -> _Source:
    from PIL import Image

    try:
        with Image.open(p) as im:
            im.load()
            mode = im.mode
            if mode == "1":
                im = im.convert("L")
            elif mode in ("P", "PA"):
                im = im.convert("RGBA")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
            a = np.asarray(im)
    except Image.DecompressionBombError as exc:
        raise InputError(
            f"'{p}': image too large to decode whole ({_one_line(exc)}); convert it to a tiled GeoTIFF"
        ) from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"'{p}': cannot decode image (truncated or damaged? {_one_line(exc)})") from None
    if a.ndim == 3:
        nch = a.shape[2]
        if nch == 2:  # LA: grey + alpha
            a = a[..., 0]
        elif nch >= 3:
            rgb = a[..., :3]
            diff = 0
            for r0 in range(0, rgb.shape[0], 1024):  # bounded temporaries
                blk = rgb[r0:r0 + 1024].astype(np.int16)
                diff = max(diff,
                           int(np.abs(blk[..., 0] - blk[..., 1]).max(initial=0)),
                           int(np.abs(blk[..., 0] - blk[..., 2]).max(initial=0)),
                           int(np.abs(blk[..., 1] - blk[..., 2]).max(initial=0)))
            if diff > GREY_TOLERANCE_DN:
                raise InputError(
                    f"'{p}': colour image (RGB channels differ by up to {diff} DN > "
                    f"{GREY_TOLERANCE_DN}); expected a grey SAR amplitude image"
                )
            if diff == 0:
                a = np.ascontiguousarray(rgb[..., 0])
            else:
                g = np.empty(rgb.shape[:2], np.float32)
                for r0 in range(0, rgb.shape[0], 1024):
                    g[r0:r0 + 1024] = rgb[r0:r0 + 1024].astype(np.float32).mean(axis=2)
                a = g
        else:
            a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"'{p}': unsupported image layout {a.shape}")
    _check_hw(p, a.shape[0], a.shape[1])
    src = _ImageSource(path=p, shape=(a.shape[0], a.shape[1]), nbands=1, dtype=a.dtype, fmt="image")
    src.data = a
    src.meta["kind_hint"] = ("amplitude", "PNG/JPEG images are amplitude")
    src.meta["grey_from"] = mode
    return src


# ---- TIFF ----------------------------------------------------------------------------


def _open_tiff(p: Path) -> _Source:
    import tifffile

    try:
        tif = tifffile.TiffFile(str(p))
    except Exception as exc:
        raise InputError(f"'{p}': not a readable TIFF ({_one_line(exc)})") from None
    try:
        if not tif.series:
            raise InputError(f"'{p}': TIFF holds no image")
        s = tif.series[0]
        axes = s.axes
        shape = tuple(int(v) for v in s.shape)
        if "Y" not in axes or "X" not in axes:
            raise InputError(f"'{p}': TIFF image has no Y/X axes (axes '{axes}', shape {shape})")
        iy, ix = axes.index("Y"), axes.index("X")
        H, W = shape[iy], shape[ix]
        _check_hw(p, H, W)
        nb = int(np.prod([v for i, v in enumerate(shape) if i not in (iy, ix)], dtype=np.int64))
        if nb < 1:
            raise InputError(f"'{p}': TIFF image with no bands (shape {shape})")
        dt = np.dtype(s.dtype)
        _check_dtype(p, dt)
        _check_tiff_complete(p, tif, s)
        src = _TiffSource(path=p, shape=(H, W), nbands=nb, dtype=dt.newbyteorder("="), fmt="tiff")
        src.tif, src.series, src.yx = tif, s, (iy, ix)
        src.memmappable = s.dataoffset is not None  # uncompressed and contiguous
        page = s.pages[0] if s.pages else None
        if not hasattr(page, "tags"):  # a TiffFrame: tags live on the first page
            page = tif.pages.first
        src.prefers_rows = (not src.memmappable) and not bool(getattr(page, "is_tiled", False))
        src.meta.update(_tiff_metadata(p, tif, page, nb, (H, W)))
        return src
    except BaseException:
        tif.close()
        raise


def _check_tiff_complete(p: Path, tif, series) -> None:
    """Refuse a TIFF whose strips/tiles run past the end of the file (truncated)."""
    size = os.path.getsize(p)
    end = 0
    for page in series.pages:
        if page is None:
            continue
        offs = getattr(page, "dataoffsets", ()) or ()
        cnts = getattr(page, "databytecounts", ()) or ()
        for o, c in zip(offs, cnts):
            if c:
                end = max(end, int(o) + int(c))
    if end > size:
        raise InputError(f"'{p}': truncated TIFF (image data end at byte {end}, file has {size} bytes)")


def _tiff_metadata(p: Path, tif, page, nbands: int, shape: tuple[int, int]) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    items: dict[str, str] = {}
    band_desc: list[str] = []
    # tifffile JSON description (tifffile.imwrite(..., metadata={...}))
    desc = ""
    try:
        desc = page.description or ""
    except Exception:
        pass
    if desc.lstrip().startswith("{"):
        try:
            d = json.loads(desc)
            if isinstance(d, dict):
                for k, v in d.items():
                    if isinstance(v, (str, int, float)):
                        items[str(k).lower()] = str(v)
        except ValueError:
            pass
    elif desc:
        words = set(re.findall(r"\b(amplitude|intensity)\b", desc.lower()))
        if len(words) == 1:
            items.setdefault("description_quantity", words.pop())
    # GDAL_METADATA XML
    tag = page.tags.get(42112)
    if tag is not None and isinstance(tag.value, str):
        try:
            root = ET.fromstring(tag.value)
            for it in root.iter("Item"):
                name = (it.get("name") or "").lower()
                role = (it.get("role") or "").lower()
                text = (it.text or "").strip()
                if role == "description" and it.get("sample") is not None:
                    band_desc.append(text)
                elif name:
                    items.setdefault(name, text)
        except ET.ParseError:
            pass
    # quantity hint
    words = []
    for k in ("kind", "sample_type", "quantity", "unit", "units", "description_quantity"):
        if k in items:
            words.append(items[k].lower())
    words += [b.lower() for b in band_desc]
    hint = _quantity_from_words(words)
    if hint:
        meta["kind_hint"] = (hint, "the file's metadata says " + hint)
    for k in ("looks", "enl", "number_of_looks", "equivalent_number_of_looks"):
        if k in items:
            try:
                v = float(items[k])
                if math.isfinite(v) and v > 0:
                    meta["looks"] = v
                    meta["looks_note"] = f"TIFF metadata item '{k}'"
                    break
            except ValueError:
                pass
    for k in ("sensor", "acquired"):
        if items.get(k):
            meta[k] = items[k]
    pols = [m.group(1) for b in band_desc for m in [_POL_RE.search(b.lower())] if m]
    if band_desc and len(pols) == len(band_desc) == nbands and len(set(pols)) == len(pols):
        meta["pols"] = pols
    meta.update(_geotiff(page, shape))
    nd = page.tags.get(42113)  # GDAL_NODATA (ASCII)
    if nd is not None:
        try:
            v = float(str(nd.value).strip().strip("\x00"))
            if math.isfinite(v) and v != 0:
                meta["nodata"] = v
        except ValueError:
            pass
    side = _snap_sidecar(p)
    # the TIFF's own georeference, looks and band names win over the product-level sidecar
    groups = {"pixel_spacing_m": "pixel_spacing_m", "pixel_spacing_source": "pixel_spacing_m",
              "looks": "looks", "looks_note": "looks", "pols": "pols"}
    have = {g for g in groups.values() if g in meta}
    for k, v in side.items():
        if groups.get(k) in have:
            continue
        meta.setdefault(k, v)
    return meta


def _quantity_from_words(words: list[str]) -> str | None:
    amp = any(re.search(r"amplitude|magnitude", w) for w in words)
    inten = any(re.search(r"intensity|power|sigma0|sigma_0|beta0|beta_0|gamma0|gamma_0", w) for w in words)
    cplx = any(re.search(r"\bcomplex\b|\bslc\b", w) for w in words)
    if amp and not inten and not cplx:
        return "amplitude"
    if inten and not amp and not cplx:
        return "intensity"
    if cplx and not amp and not inten:
        return "complex"
    return None


# EPSG codes of projected CRSs in metres, used when ProjLinearUnitsGeoKey is absent.
_METRE_EPSG_RANGES = (
    (32601, 32660), (32701, 32760), (32201, 32260), (32301, 32360), (26901, 26923),
    (25828, 25838), (28348, 28358), (31466, 31469), (3857, 3857), (3395, 3395),
    (3035, 3035), (3034, 3034), (3031, 3031), (3413, 3413), (3976, 3976), (3995, 3995),
    (2154, 2154), (27700, 27700), (5070, 5070), (6933, 6933), (3577, 3577), (2056, 2056),
    (21781, 21781), (4087, 4087), (32662, 32662), (3578, 3578), (3005, 3005),
)
_LINEAR_UNITS = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0, 9036: 1000.0}


def _geotiff(page, shape: tuple[int, int]) -> dict[str, Any]:
    """crs / transform / gcps / pixel spacing from GeoTIFF tags (empty dict when none)."""
    tags = page.tags
    out: dict[str, Any] = {}

    def val(code):
        t = tags.get(code)
        return None if t is None else t.value

    scale, tie, mtx, gkd = val(33550), val(33922), val(34264), val(34735)
    if scale is None and tie is None and mtx is None:
        return out
    keys: dict[int, int] = {}
    if gkd is not None:
        try:
            g = [int(v) for v in gkd]
            n = g[3]
            for k in range(n):
                kid, loc, cnt, v = g[4 + 4 * k: 8 + 4 * k]
                if loc == 0:
                    keys[kid] = v
        except (IndexError, TypeError, ValueError):
            keys = {}
    model = keys.get(1024)
    projected = keys.get(3072)
    geographic = keys.get(2048)
    epsg = None
    if projected and 1 <= projected < 32767:
        epsg, is_geo = projected, False
    elif geographic and 1 <= geographic < 32767 and model != 1:
        epsg, is_geo = geographic, True
    else:
        is_geo = model == 2
    if epsg:
        out["crs"] = f"EPSG:{epsg}"
    transform = None
    try:
        if mtx is not None and len(mtx) >= 16:
            m = [float(v) for v in mtx]
            transform = [m[3], m[0], m[1], m[7], m[4], m[5]]
        elif scale is not None and tie is not None and len(tie) >= 6:
            sx, sy = float(scale[0]), float(scale[1])
            I, J, X, Y = float(tie[0]), float(tie[1]), float(tie[3]), float(tie[4])
            transform = [X - I * sx, sx, 0.0, Y + J * sy, 0.0, -sy]
        elif tie is not None and len(tie) >= 12:
            t = [float(v) for v in tie]
            out["gcps"] = [
                {"row": t[i + 1], "col": t[i], "x": t[i + 3], "y": t[i + 4], "z": t[i + 5]}
                for i in range(0, len(t) - 5, 6)
            ]
    except (TypeError, ValueError, IndexError):
        transform = None
    if transform is not None:
        if keys.get(1025) == 2:  # PixelIsPoint: GDAL moves the origin by half a pixel
            c, a, b, f, d, e = transform
            transform = [c - 0.5 * a - 0.5 * b, a, b, f - 0.5 * d - 0.5 * e, d, e]
        out["transform"] = transform
        c, a, b, f, d, e = transform
        col_sz, row_sz = math.hypot(a, d), math.hypot(b, e)
        if not is_geo and (projected or model == 1):
            unit = _LINEAR_UNITS.get(keys.get(3076)) if 3076 in keys else None
            if unit is None and 3076 not in keys and epsg and any(lo <= epsg <= hi for lo, hi in _METRE_EPSG_RANGES):
                unit = 1.0
            if unit is not None and col_sz > 0 and row_sz > 0:
                out["pixel_spacing_m"] = [row_sz * unit, col_sz * unit]
                out["pixel_spacing_source"] = (
                    f"GeoTIFF pixel size in projected {out.get('crs', 'CRS')} "
                    "([row, column] ground spacing of the map grid)"
                )
        elif is_geo and keys.get(2054, 9102) == 9102:
            H, W = shape
            lat = f + d * W / 2.0 + e * H / 2.0
            if -90.0 <= lat <= 90.0:
                phi = math.radians(lat)
                m_lat = 111132.954 - 559.822 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi)
                m_lon = 111412.84 * math.cos(phi) - 93.5 * math.cos(3 * phi) + 0.118 * math.cos(5 * phi)
                col_m = math.hypot(a * m_lon, d * m_lat)
                row_m = math.hypot(b * m_lon, e * m_lat)
                if col_m > 0 and row_m > 0:
                    out["pixel_spacing_m"] = [row_m, col_m]
                    out["pixel_spacing_source"] = (
                        f"approximate: pixel size in degrees ({out.get('crs', 'geographic CRS')}) "
                        f"converted on the WGS84 ellipsoid at the scene-centre latitude {lat:.4f}"
                    )
    return out


def _snap_sidecar(p: Path) -> dict[str, Any]:
    """SNAP ``Abstracted_Metadata`` next to an OpenSARShip-style chip (see module doc)."""
    cands = [p.with_suffix(".xml"), p.parent / (p.parent.name + ".xml"),
             p.parent.parent / (p.parent.parent.name + ".xml")]
    for c in cands:
        try:
            if not c.is_file() or c.stat().st_size > 16 * 2**20:
                continue
            root = ET.parse(c).getroot()
        except (OSError, ET.ParseError):
            continue
        am = root if root.tag == "Abstracted_Metadata" else root.find(".//Abstracted_Metadata")
        if am is None:
            continue
        a = {e.get("name"): e.get("value") for e in am.findall("attrib")}
        out: dict[str, Any] = {"sidecar": c.name}
        mission, mode = a.get("MISSION"), a.get("ACQUISITION_MODE")
        if mission:
            out["sensor"] = f"{mission} {mode}".strip() if mode else mission
        if a.get("PRODUCT"):
            out["product"] = a["PRODUCT"]
        t = a.get("first_line_time")
        if t:
            for fmt in ("%d-%b-%Y %H:%M:%S.%f", "%d-%b-%Y %H:%M:%S"):
                try:
                    out["acquired"] = datetime.strptime(t.title(), fmt).isoformat() + "Z"
                    break
                except ValueError:
                    pass
        pols = [a.get(f"mds{i}_tx_rx_polar", "") for i in range(1, 5)]
        pols = [v.lower() for v in pols if v and v.strip() and v.strip() != "-"]
        if pols and all(v in COMPLEX_CHANNELS for v in pols) and len(set(pols)) == len(pols):
            out["pols"] = pols
        st = (a.get("SAMPLE_TYPE") or "").upper()
        if st:
            out["sample_type"] = st
        try:
            az, rg = float(a["azimuth_spacing"]), float(a["range_spacing"])
            if az > 0 and rg > 0:
                out["pixel_spacing_m"] = [az, rg]
                out["pixel_spacing_source"] = f"SNAP metadata {c.name}: azimuth_spacing, range_spacing"
        except (KeyError, TypeError, ValueError):
            pass
        try:
            la, lr = float(a["azimuth_looks"]), float(a["range_looks"])
            if la > 0 and lr > 0:
                out["looks"] = la * lr
                out["looks_note"] = (
                    f"SNAP metadata {c.name}: azimuth_looks {la:g} x range_looks {lr:g} (nominal)"
                )
        except (KeyError, TypeError, ValueError):
            pass
        return out
    return {}


# ---- PolSARpro folders (C3 / T3 / C2 element files + ENVI headers) ---------------------

#: The unitary change of basis from lexicographic to Pauli scattering vectors:
#: ``k_pauli = PAULI_U @ k_lex`` with ``k_lex = [HH, sqrt2 HV, VV]`` and
#: ``k_pauli = (1/sqrt2) [HH+VV, HH-VV, 2 HV]``; hence ``T = U C U^H`` and ``C = U^H T U``.
PAULI_U = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, -1.0], [0.0, math.sqrt(2.0), 0.0]]) / math.sqrt(2.0)

#: ``covariance_basis`` attribute of C3 scenes (the store's convention, see the module doc).
C3_BASIS = "lexicographic [HH, sqrt2 HV, VV]"

#: Covariance scenes whose sampled principal 2x2 minors ``1 - |c_ij|^2 / (c_ii c_jj)`` have a
#: median below this are rank one (single-look): ``looks`` = 1.
RANK_ONE_TOL = 1e-3

_ENVI_DTYPES = {4: "f4", 5: "f8"}
_ENVI_DTYPE_NAMES = {1: "uint8", 2: "int16", 3: "int32", 4: "float32", 5: "float64", 6: "complex64",
                     9: "complex128", 12: "uint16", 13: "uint32", 14: "int64", 15: "uint64"}
#: PolSARpro dual-pol PolarType -> the channels of the C2 scattering vector.
_DUAL_TYPES = {"pp1": ["hh", "hv"], "pp2": ["vv", "vh"], "pp3": ["hh", "vv"]}


def _elements(prefix: str, n: int) -> list[tuple[str, list[str]]]:
    """(store name, [file stems]) of an n x n PolSARpro matrix, upper triangle row-major."""
    out = []
    for i in range(1, n + 1):
        for j in range(i, n + 1):
            e = f"{prefix}{i}{j}"
            out.append((f"c{i}{j}", [e] if i == j else [f"{e}_real", f"{e}_imag"]))
    return out


def _folder_files(d: Path) -> dict[str, Path]:
    """Files of a folder by lower-case name (PolSARpro names are upper case, tolerate others)."""
    try:
        return {q.name.lower(): q for q in d.iterdir() if q.is_file()}
    except OSError:
        return {}


def _polsarpro_folder(p: Path) -> Path | None:
    """The PolSARpro folder ``p`` names (the folder, its config.txt, C11.bin/T11.bin or their
    headers), or None."""
    name = p.name.lower()
    if p.is_dir():
        d = p
    elif name == "config.txt" or re.fullmatch(r"[ct]11(\.bin(\.hdr)?|\.hdr)", name):
        d = p.parent
    else:
        return None
    files = _folder_files(d)
    return d if ("c11.bin" in files or "t11.bin" in files) else None


def _parse_envi_header(h: Path) -> dict[str, str]:
    try:
        text = h.read_text(encoding="latin-1")
    except OSError as exc:
        raise InputError(f"'{h}': cannot read ENVI header ({_one_line(exc)})") from None
    lines = text.splitlines()
    if not lines or lines[0].strip().upper() != "ENVI":
        raise InputError(f"'{h}': not an ENVI header (the first line is not 'ENVI')")
    out: dict[str, str] = {}
    key, buf = None, ""
    for ln in lines[1:]:
        if key is not None:  # inside { ... } spanning lines
            buf += " " + ln.strip()
            if "}" in ln:
                out[key] = buf.strip()
                key = None
            continue
        if "=" not in ln:
            continue
        k, v = ln.split("=", 1)
        k, v = " ".join(k.lower().split()), v.strip()
        if v.startswith("{") and "}" not in v:
            key, buf = k, v
        else:
            out[k] = v
    return out


def _parse_config(cfg: Path) -> dict[str, str]:
    """PolSARpro config.txt: ``Key`` / value line pairs separated by ``---------``."""
    try:
        lines = [ln.strip() for ln in cfg.read_text(encoding="latin-1").splitlines()]
    except OSError as exc:
        raise InputError(f"'{cfg}': cannot read ({_one_line(exc)})") from None
    lines = [ln for ln in lines if ln and not set(ln) <= {"-"}]
    return {lines[i]: lines[i + 1] for i in range(0, len(lines) - 1, 2)}


def _header_int(h: Path, hdr: dict[str, str], key: str, default: int | None = None) -> int:
    v = hdr.get(key)
    if v is None:
        if default is not None:
            return default
        raise InputError(f"'{h}': ENVI header has no '{key}'")
    try:
        return int(v.strip().strip("{}").strip())
    except ValueError:
        raise InputError(f"'{h}': ENVI header '{key} = {v}' is not a whole number") from None


class _PolsarproSource(_Source):
    """A PolSARpro folder; ``read`` returns a dict of store variables (already in C)."""

    basis: str = "C"  # "C" (covariance) or "T" (coherency, converted to C3)
    files: dict[str, tuple[Path, np.dtype, int]] | None = None  # stem -> (path, dtype, offset)

    def _el(self, stem: str, r0, r1, c0, c1, dtype) -> np.ndarray:
        maps = self.__dict__.setdefault("_maps", {})
        if stem not in maps:
            path, dt, off = self.files[stem]
            maps[stem] = np.memmap(path, dtype=dt, mode="r", offset=off, shape=self.shape)
        return np.asarray(maps[stem][r0:r1, c0:c1]).astype(dtype)

    def _read(self, r0, r1, c0, c1):
        try:
            return self._read_tile(r0, r1, c0, c1)
        finally:
            self.release()  # unmap after every tile: mapped pages count against RSS

    def _read_tile(self, r0, r1, c0, c1):
        n = self.nbands
        if self.basis == "C":
            out = {}
            for name, stems in _elements("C", n):
                if len(stems) == 1:
                    out[name] = self._el(stems[0], r0, r1, c0, c1, np.float32)
                else:
                    z = np.empty((r1 - r0, c1 - c0), np.complex64)
                    z.real = self._el(stems[0], r0, r1, c0, c1, np.float32)
                    z.imag = self._el(stems[1], r0, r1, c0, c1, np.float32)
                    out[name] = z
            return out
        return _t3_to_c3(lambda stem: self._el(stem, r0, r1, c0, c1, np.float64), (r1 - r0, c1 - c0))

    def release(self):
        self.__dict__["_maps"] = {}


def _t3_to_c3(el: Callable[[str], np.ndarray], shape) -> dict[str, np.ndarray]:
    """C = U^H T U (``PAULI_U``) element by element, in float64, from T3 element reader ``el``.

    With U real:  c11 = (t11 + t22)/2 + Re t12,  c33 = (t11 + t22)/2 - Re t12,  c22 = t33,
    c12 = (t13 + t23)/sqrt2,  c13 = (t11 - t22)/2 - i Im t12,  c23 = conj(t13 - t23)/sqrt2.
    """
    r2 = math.sqrt(2.0)
    t11, t22, t12r = el("T11"), el("T22"), el("T12_real")
    half = 0.5 * (t11 + t22)
    out = {"c11": (half + t12r).astype(np.float32), "c33": (half - t12r).astype(np.float32)}
    c13 = np.empty(shape, np.complex64)
    c13.real = 0.5 * (t11 - t22)
    del t11, t22, half, t12r
    c13.imag = -el("T12_imag")
    out["c13"] = c13
    out["c22"] = el("T33").astype(np.float32)
    t13r, t23r = el("T13_real"), el("T23_real")
    c12, c23 = np.empty(shape, np.complex64), np.empty(shape, np.complex64)
    c12.real, c23.real = (t13r + t23r) / r2, (t13r - t23r) / r2
    del t13r, t23r
    t13i, t23i = el("T13_imag"), el("T23_imag")
    c12.imag, c23.imag = (t13i + t23i) / r2, (t23i - t13i) / r2
    out["c12"], out["c23"] = c12, c23
    return out


def t3_to_c3(T: np.ndarray) -> np.ndarray:
    """Coherency (Pauli basis) matrices ``(..., 3, 3)`` -> covariance C3 ``U^H T U`` in the
    store's lexicographic basis [HH, sqrt2 HV, VV] (use it before saving a T3 as .npy)."""
    U = PAULI_U
    return np.einsum("ai,...ab,bj->...ij", U.conj(), np.asarray(T), U)


def _open_polsarpro(d: Path) -> _PolsarproSource:
    files = _folder_files(d)
    basis = "C" if "c11.bin" in files else "T"
    cfg_path = files.get("config.txt")
    cfg = _parse_config(cfg_path) if cfg_path is not None else {}
    polar_type = cfg.get("PolarType", "").strip().lower()
    if basis == "C" and ("c44.bin" in files) or basis == "T" and ("t44.bin" in files):
        raise InputError(f"'{d}': a PolSARpro {basis}4 folder (4 x 4, bistatic); only C3, T3 and C2 are supported")
    if basis == "C":
        dual = polar_type in _DUAL_TYPES or polar_type.startswith("pp") or (
            polar_type != "full" and "c33.bin" not in files and "c13_real.bin" not in files
            and "c22.bin" in files)
        n = 2 if dual else 3
    else:
        if polar_type.startswith("pp") or ("t33.bin" not in files and "t13_real.bin" not in files
                                           and "t22.bin" in files):
            raise InputError(f"'{d}': a PolSARpro T2 folder; only C3, T3 and C2 are supported "
                             "(convert it to C2 in PolSARpro)")
        n = 3
    label = f"{basis}{n}"
    elems = _elements(basis, n)
    stems = [s for _, ss in elems for s in ss]
    missing = [f"{s}.bin" for s in stems if f"{s.lower()}.bin" not in files]
    if missing:
        raise InputError(f"'{d}': PolSARpro {label} folder is missing element file(s) {', '.join(missing)}")
    ncfg = None
    if "Nrow" in cfg or "Ncol" in cfg:
        try:
            ncfg = (int(cfg["Nrow"]), int(cfg["Ncol"]))
        except (KeyError, ValueError):
            raise InputError(f"'{cfg_path}': Nrow/Ncol are not whole numbers "
                             f"(Nrow={cfg.get('Nrow')!r}, Ncol={cfg.get('Ncol')!r})") from None
    out: dict[str, tuple[Path, np.dtype, int]] = {}
    shape = None
    orders, headerless = set(), []
    for s in stems:
        b = files[f"{s.lower()}.bin"]
        h = files.get(f"{s.lower()}.bin.hdr") or files.get(f"{s.lower()}.hdr")
        if h is not None:
            hdr = _parse_envi_header(h)
            W, H = _header_int(h, hdr, "samples"), _header_int(h, hdr, "lines")
            nb = _header_int(h, hdr, "bands", 1)
            off = _header_int(h, hdr, "header offset", 0)
            code = _header_int(h, hdr, "data type")
            order = _header_int(h, hdr, "byte order", 0)
            inter = hdr.get("interleave", "bsq").strip().lower()
            if code not in _ENVI_DTYPES:
                raise InputError(
                    f"'{h}': unsupported ENVI data type {code} ({_ENVI_DTYPE_NAMES.get(code, 'unknown')}); "
                    "PolSARpro element files are data type 4 (float32) or 5 (float64)")
            if nb != 1:
                raise InputError(f"'{h}': {nb} bands; a PolSARpro element file holds one band")
            if inter not in ("bsq", "bil", "bip"):
                raise InputError(f"'{h}': unsupported interleave '{inter}' (expected bsq)")
            if order not in (0, 1):
                raise InputError(f"'{h}': byte order must be 0 (little-endian) or 1 (big-endian), got {order}")
            if H < 1 or W < 1 or off < 0:
                raise InputError(f"'{h}': bad size ({W} samples x {H} lines, header offset {off})")
            dt = np.dtype(("<" if order == 0 else ">") + _ENVI_DTYPES[code])
            what = f"its header '{h.name}' says {W} samples x {H} lines x {dt.itemsize} bytes + offset {off}"
        else:
            if ncfg is None:
                raise InputError(f"'{b}': no ENVI header ('{b.name}.hdr') and no config.txt Nrow/Ncol "
                                 "to give its size")
            (H, W), off, order, dt = ncfg, 0, 0, np.dtype("<f4")
            headerless.append(b.name)
            what = f"config.txt says Nrow {H} x Ncol {W} x 4 bytes (float32, no header)"
        size = os.path.getsize(b)
        want = H * W * dt.itemsize + off
        if size != want:
            raise InputError(f"'{b}': header/size mismatch: the file has {size} bytes but {what} = {want}")
        if shape is None:
            shape = (H, W)
        elif (H, W) != shape:
            first = stems[0]
            raise InputError(f"'{b}': {H} lines x {W} samples but {first}.bin is "
                             f"{shape[0]} x {shape[1]}: element files must have equal sizes")
        if ncfg is not None and ncfg != (H, W):
            raise InputError(f"'{b}': {H} lines x {W} samples but '{cfg_path}' says "
                             f"Nrow {ncfg[0]} x Ncol {ncfg[1]}")
        orders.add("big-endian" if order == 1 else "little-endian")
        out[s] = (b, dt, off)
    assert shape is not None
    src = _PolsarproSource(path=d, shape=shape, nbands=n, dtype=out[stems[0]][1].newbyteorder("="), fmt="polsarpro",
                           layout="covariance")
    src.basis, src.files = basis, out
    fmt_name = f"PolSARpro {label}" if basis == "C" else "PolSARpro T3 -> C3"
    attrs: dict[str, Any] = {
        "format": fmt_name,
        "source_files": [out[s][0].name for s in stems],
        "byte_order": sorted(orders)[0] if len(orders) == 1 else sorted(orders),
        "quantity": f"covariance C{n}",
    }
    if n == 3:
        attrs["covariance_basis"] = C3_BASIS
        attrs["quantity_rule"] = (
            "PolSARpro C3 folder: element files stored as they are" if basis == "C" else
            "PolSARpro T3 folder (coherency, Pauli basis k_p = (1/sqrt2)[HH+VV, HH-VV, 2HV]) converted "
            "to C3 = U^H T U, U = (1/sqrt2)[[1,0,1],[1,0,-1],[0,sqrt2,0]]")
    else:
        ch = _DUAL_TYPES.get(polar_type)
        attrs["covariance_basis"] = (f"dual-pol [{ch[0].upper()}, {ch[1].upper()}] (PolarType {polar_type})"
                                     if ch else "dual-pol [k1, k2] as given (channels unknown)")
        if ch:
            attrs["polarisations"] = ch
        attrs["quantity_rule"] = "PolSARpro C2 folder: element files stored as they are"
    if cfg:
        attrs["polsarpro_config"] = {k: cfg[k] for k in ("Nrow", "Ncol", "PolarCase", "PolarType") if k in cfg}
    if headerless:
        attrs["polsarpro_note"] = f"no ENVI header for {', '.join(headerless)}: size from config.txt, float32 little-endian"
    src.meta["cov_attrs"] = attrs
    return src


# --------------------------------------------------------------------------------------
# planning: which variables, and how each tile is computed
# --------------------------------------------------------------------------------------


@dataclass
class _Plan:
    kind: str
    variables: dict[str, Any]
    compute: Callable[[list[np.ndarray]], dict[str, np.ndarray]]
    attrs: dict[str, Any]
    looks_var: str | None  # variable to estimate looks from (None: complex)


def _pols_from_names(srcs: list[_Source]) -> list[str] | None:
    pols = []
    for s in srcs:
        m = _POL_RE.findall(s.path.stem.lower().replace("-", "_"))
        if len(set(m)) != 1:
            return None
        pols.append(m[0])
    return pols if len(set(pols)) == len(pols) else None


def _complex_names(n: int, srcs: list[_Source], channels: list[str] | None) -> list[str]:
    if channels is not None:
        names = [str(c).lower() for c in channels]
        if len(names) != n:
            raise InputError(f"--channels names {len(names)} channel(s) but the input has {n} complex channel(s)")
    elif len(srcs) == 1 and srcs[0].meta.get("pols") and len(srcs[0].meta["pols"]) == n:
        names = list(srcs[0].meta["pols"])
    elif len(srcs) > 1 and (pn := _pols_from_names(srcs)) is not None and len(pn) == n:
        names = pn
    else:
        defaults = {1: ["hh"], 2: ["vh", "vv"], 3: ["hh", "hv", "vv"], 4: ["hh", "hv", "vh", "vv"]}
        if n not in defaults:
            raise InputError(f"{n} complex channels: at most 4 (hh, hv, vh, vv) are supported")
        names = defaults[n]
    bad = [c for c in names if c not in COMPLEX_CHANNELS]
    if bad:
        raise InputError(f"complex channel names must be among {', '.join(COMPLEX_CHANNELS)}; got {', '.join(bad)}")
    if len(set(names)) != len(names):
        raise InputError(f"channel names must be distinct, got {', '.join(names)}")
    return names


def _real_names(n: int, srcs: list[_Source], channels: list[str] | None) -> list[str]:
    if channels is not None:
        names = [str(c) for c in channels]
        if len(names) != n:
            raise InputError(f"--channels names {len(names)} band(s) but the input has {n} band(s)")
    elif len(srcs) == 1 and srcs[0].meta.get("pols") and len(srcs[0].meta["pols"]) == n:
        names = list(srcs[0].meta["pols"])
    elif len(srcs) > 1 and (pn := _pols_from_names(srcs)) is not None and len(pn) == n:
        names = pn
    else:
        names = [f"b{i}" for i in range(n)]
    for c in names:
        if not _NAME_RE.match(c):
            raise InputError(f"band name '{c}' must be letters, digits, '_', '.' or '-'")
    if len(set(names)) != len(names):
        raise InputError(f"band names must be distinct, got {', '.join(names)}")
    return names


def _auto_quantity(s: _Source) -> tuple[str, str]:
    """("amplitude" | "intensity" | "pairs", rule) for a real source under kind auto."""
    if s.fmt == "npy":
        return "intensity", ".npy real arrays are intensity (the contract)"
    sample = None
    side = s.meta.get("sample_type")
    npol = len(s.meta.get("pols") or [])
    if side == "COMPLEX" and npol and s.nbands == 2 * npol:
        return "pairs", f"SNAP metadata SAMPLE_TYPE=COMPLEX with {s.nbands} bands = (re, im) x {npol} polarisations"
    hint = s.meta.get("kind_hint")
    if hint and hint[0] == "complex":
        if s.nbands % 2 == 0:
            return "pairs", hint[1] + f": {s.nbands} real bands = (re, im) pairs"
        raise InputError(f"'{s.path}': metadata says complex but it has an odd number ({s.nbands}) of real bands")
    if s.fmt != "image":
        sample = s.probe()
        if "nodata" in s.meta:
            sample = sample[sample != s.meta["nodata"]]
        fin = sample[np.isfinite(sample)] if np.issubdtype(sample.dtype, np.floating) else sample
        if fin.size and fin.min() < 0:
            if s.nbands % 2 == 0:
                return "pairs", (f"negative samples cannot be amplitude or intensity: {s.nbands} "
                                 "real bands taken as (re, im) pairs")
            raise InputError(
                f"'{s.path}': real samples include negative values, so they are neither amplitude nor "
                f"intensity (dB? convert to linear), and {s.nbands} band(s) cannot be (re, im) pairs; "
                "pass --kind intensity to store them as they are"
            )
    if hint:
        return hint[0], hint[1]
    if np.issubdtype(s.dtype, np.integer):
        return "amplitude", f"integer samples ({s.dtype}) are amplitude digital numbers"
    fin = sample[np.isfinite(sample)]
    if fin.size and fin.max() > 1 and np.all(fin == np.floor(fin)):
        return "amplitude", (f"{s.dtype} samples are all whole numbers (digital numbers stored as float): "
                             "amplitude")
    return "intensity", f"{s.dtype} samples are intensity"


def _to_f32_intensity(a: np.ndarray, amplitude: bool, nodata: float | None = None) -> np.ndarray:
    x = a.astype(np.float32, copy=False)
    if amplitude:
        x = np.square(x, dtype=np.float32)
    if nodata is not None:
        x = np.where(a == nodata, np.float32(0), x).astype(np.float32, copy=False)
    return x


def _plan(srcs: list[_Source], kind: str, band, channels, ) -> _Plan:
    H, W = srcs[0].shape
    for s in srcs[1:]:
        if s.shape != (H, W):
            raise InputError(
                f"'{srcs[0].path}' is {H} x {W} pixels but '{s.path}' is {s.shape[0]} x {s.shape[1]}: "
                "stacked inputs must have equal shapes"
            )
    attrs: dict[str, Any] = {}
    # covariance -------------------------------------------------------------------
    cov = [s for s in srcs if s.layout == "covariance"]
    if cov:
        if len(srcs) > 1:
            raise InputError(f"'{cov[0].path}': a covariance image cannot be stacked with other inputs")
        if kind not in ("auto", "covariance"):
            raise InputError(f"'{cov[0].path}' is a covariance (C{cov[0].nbands}) image; --kind {kind} does not apply")
        n = cov[0].nbands
        names = [(i, j) for i in range(n) for j in range(i, n)]
        variables = {f"c{i + 1}{j + 1}": (np.float32 if i == j else np.complex64) for i, j in names}

        def compute(arrs):
            a = arrs[0]
            if isinstance(a, dict):  # PolSARpro: the source already gives the store variables
                return a
            out = {}
            for i, j in names:
                v = a[:, :, i, j]
                out[f"c{i + 1}{j + 1}"] = (np.real(v).astype(np.float32) if i == j
                                           else v.astype(np.complex64))
            return out

        attrs["quantity"] = f"covariance C{n}"
        attrs["quantity_rule"] = f"(H, W, {n}, {n}) array: covariance matrix per pixel"
        attrs["format"] = f"npy covariance C{n}"
        attrs["covariance_basis"] = (C3_BASIS if n == 3 else "dual-pol [k1, k2] as given (channels unknown)")
        attrs.update(cov[0].meta.get("cov_attrs", {}))
        attrs["channels"] = list(variables)
        return _Plan("covariance", variables, compute, attrs, "c11")
    if kind == "covariance":
        raise InputError(f"'{srcs[0].path}' is not a covariance image ((H, W, 3, 3) or (H, W, 2, 2) .npy)")
    # complex or real ----------------------------------------------------------------
    cplx = [s.is_complex for s in srcs]
    if any(cplx) and not all(cplx):
        a = srcs[cplx.index(True)]
        b = srcs[cplx.index(False)]
        raise InputError(f"'{a.path}' is complex but '{b.path}' is real: cannot stack them")
    if all(cplx):
        if kind in ("amplitude", "intensity"):
            raise InputError(
                f"'{srcs[0].path}' holds complex samples; --kind {kind} does not apply "
                "(use auto, slc or quadpol; detectors derive intensity themselves)"
            )
        parts = [(k, b, None) for k, s in enumerate(srcs) for b in range(s.nbands)]  # (src, band, im)
        rule = "complex samples: SLC channels"
    else:
        if kind in ("slc", "quadpol"):
            quants = []
            for s in srcs:
                if s.nbands % 2:
                    raise InputError(
                        f"'{s.path}': --kind {kind} with real samples needs (re, im) band pairs, "
                        f"but it has {s.nbands} band(s)"
                    )
                quants.append(("pairs", f"--kind {kind}: real bands are (re, im) pairs"))
        elif kind in ("amplitude", "intensity"):
            quants = [(kind, f"--kind {kind}") for s in srcs]
        else:
            quants = [_auto_quantity(s) for s in srcs]
        qs = {q for q, _ in quants}
        if len(qs) > 1:
            i = [q for q, _ in quants].index(quants[0][0])
            j = next(k for k, (q, _) in enumerate(quants) if q != quants[i][0])
            raise InputError(
                f"'{srcs[i].path}' reads as {quants[i][0]} ({quants[i][1]}) but '{srcs[j].path}' as "
                f"{quants[j][0]} ({quants[j][1]}); pass --kind to say which"
            )
        q, rule = quants[0]
        if q == "pairs":
            parts = [(k, b, b + 1) for k, s in enumerate(srcs) for b in range(0, s.nbands, 2)]
        else:
            return _plan_detected(srcs, q == "amplitude", rule, band, channels)
    # complex channels ------------------------------------------------------------------
    names = _complex_names(len(parts), srcs, channels)
    is_quad = {"hh", "hv", "vv"} <= set(names)
    if kind == "quadpol" and not is_quad:
        raise InputError(f"--kind quadpol needs complex hh, hv and vv channels; got {', '.join(names)}")
    variables = {n: np.complex64 for n in names}

    def compute(arrs):
        out = {}
        for name, (k, b, im) in zip(names, parts):
            a = arrs[k]
            if im is None:
                out[name] = a[:, :, b].astype(np.complex64)
            else:
                z = np.empty(a.shape[:2], np.complex64)
                z.real = a[:, :, b]
                z.imag = a[:, :, im]
                out[name] = z
        return out

    attrs["quantity"] = "complex (single-look complex samples)" if all(cplx) else "complex from (re, im) band pairs"
    attrs["quantity_rule"] = rule
    attrs["channels"] = names
    return _Plan("quadpol" if is_quad else "slc", variables, compute, attrs, None)


def _plan_detected(srcs, amplitude: bool, rule: str, band, channels) -> _Plan:
    bands = [(k, b) for k, s in enumerate(srcs) for b in range(s.nbands)]
    n = len(bands)
    attrs: dict[str, Any] = {
        "quantity": "amplitude (squared to intensity)" if amplitude else "intensity",
        "quantity_rule": rule,
    }
    if n == 1:
        if channels is not None and len(channels) != 1:
            raise InputError(f"--channels names {len(channels)} band(s) but the input has 1 band")
        if band is not None and str(band) not in ("0", *(channels or [])):
            raise InputError(f"--band {band}: the input has a single band")
        if channels:
            attrs["channels"] = [str(channels[0])]

        def compute(arrs):
            return {"intensity": _to_f32_intensity(arrs[0][:, :, 0], amplitude, srcs[0].meta.get("nodata"))}

        return _Plan("intensity", {"intensity": np.float32}, compute, attrs, "intensity")
    names = _real_names(n, srcs, channels)
    if band is None:
        sel = 0
    elif isinstance(band, (int, np.integer)) and not isinstance(band, bool):
        sel = int(band)
    elif str(band) in names:
        sel = names.index(str(band))
    elif str(band).lstrip("-").isdigit():
        sel = int(str(band))
    else:
        raise InputError(f"--band {band}: no such band (bands: {', '.join(names)})")
    if not 0 <= sel < n:
        raise InputError(f"--band {band}: index out of range 0..{n - 1} (bands: {', '.join(names)})")
    variables = {f"intensity_{nm}": np.float32 for nm in names}
    variables["intensity"] = np.float32
    attrs["channels"] = names
    attrs["intensity_band"] = names[sel]

    def compute(arrs):
        out = {}
        for nm, (k, b) in zip(names, bands):
            out[f"intensity_{nm}"] = _to_f32_intensity(arrs[k][:, :, b], amplitude, srcs[k].meta.get("nodata"))
        out["intensity"] = out[f"intensity_{names[sel]}"]
        return out

    return _Plan("intensity", variables, compute, attrs, "intensity")


# --------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------


class _CallbackError(Exception):
    """An exception raised by the caller's progress callback: re-raised unchanged by ingest."""

    def __init__(self, exc: Exception):
        super().__init__(str(exc))
        self.exc = exc


def _check_args(inputs, out, kind, tile, looks, channels):
    if kind not in INGEST_KINDS:
        raise InputError(f"--kind must be one of {', '.join(INGEST_KINDS)}; got '{kind}'")
    try:
        tile_i = int(tile)
    except (TypeError, ValueError):
        raise InputError(f"--tile must be a positive number of pixels, got {tile!r}") from None
    if (isinstance(tile, float) and not tile.is_integer()) or tile_i < 1:
        raise InputError(f"--tile must be a positive number of pixels, got {tile!r}")
    if looks is not None:
        try:
            lv = float(looks)
        except (TypeError, ValueError):
            raise InputError(f"--looks must be a positive number, got {looks!r}") from None
        if not (math.isfinite(lv) and lv > 0):
            raise InputError(f"--looks must be a positive number, got {looks!r}")
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("ingest needs at least one input")
    for p in paths:
        if not p.exists():
            raise InputError(f"input '{p}' does not exist")
    if channels is not None and isinstance(channels, str):
        channels = [c for c in re.split(r"[,\s]+", channels) if c]
    outp = Path(out)
    for p in paths:
        try:
            if outp.exists() and p.resolve() == outp.resolve():
                raise InputError(f"--out '{outp}' is also an input")
        except OSError:
            pass
    if outp.exists() and not (outp.is_dir() and ((outp / "zarr.json").exists() or (outp / ".zgroup").exists())):
        raise InputError(f"--out '{outp}' exists and is not a Zarr scene: refusing to overwrite it")
    return paths, outp, tile_i, channels


def ingest(
    inputs: list[str | Path],
    out: str | Path,
    kind: str = "auto",
    tile: int = DEFAULT_TILE,
    progress: Callable[[int, int], None] | None = None,
    band: str | int | None = None,
    channels: list[str] | None = None,
    looks: float | None = None,
) -> Scene:
    """Write the scene store ``out`` from ``inputs`` (see the module docstring); return it opened.

    ``progress(done, total)`` is called after each tile. Raises :class:`InputError` (one
    line naming the file and the problem) on any bad input; nothing is left at ``out`` then.
    """
    paths, outp, tile, channels = _check_args(inputs, out, kind, tile, looks, channels)
    user_progress = progress

    def progress(done: int, total: int) -> None:  # noqa: F811 - the caller's, exceptions passed through
        if user_progress is not None:
            try:
                user_progress(done, total)
            except Exception as exc:  # e.g. a job cancelled by the service
                raise _CallbackError(exc) from exc

    try:
        fmts = [_sniff(p) for p in paths]
        if "polsarpro" in fmts and len(paths) > 1:
            raise InputError(f"'{paths[fmts.index('polsarpro')]}': a PolSARpro folder cannot be combined "
                             "with other inputs")
        if "zarr" in fmts:
            if len(paths) > 1:
                raise InputError(f"'{paths[fmts.index('zarr')]}': a Zarr scene cannot be combined with other inputs")
            _ingest_zarr(paths[0], outp, tile, progress, looks)
            return open_scene(outp)
        srcs: list[_Source] = []
        try:
            for p in paths:
                srcs.append(_open_source(p))
            _ingest_sources(srcs, outp, kind, tile, progress, band, channels, looks)
        finally:
            for s in srcs:
                s.close()
        return open_scene(outp)
    except InputError:
        raise
    except _CallbackError as exc:
        raise exc.exc from None
    except MemoryError:
        raise InputError("ingest ran out of memory (a PNG/JPEG is decoded whole: convert it to a tiled GeoTIFF)") from None
    except Exception as exc:  # never let a raw traceback escape
        raise InputError(f"ingest of {', '.join(str(p) for p in paths)} failed: {_one_line(exc)}") from None


def _write_tiles(g, shape, tile, variables, read_tile, progress):
    arrays = {name: g[name] for name in variables}
    grid = list(tile_slices(shape, tile))
    total = len(grid)
    for done, (_i, _j, r0, r1, c0, c1) in enumerate(grid, 1):
        data = read_tile(r0, r1, c0, c1)
        for name, arr in arrays.items():
            try:
                arr[r0:r1, c0:c1] = data[name]
            except OSError as exc:
                raise InputError(f"cannot write the scene: {_one_line(exc)}") from None
        if progress is not None:
            progress(done, total)


def _ingest_sources(srcs, outp, kind, tile, progress, band, channels, looks):
    plan = _plan(srcs, kind, band, channels)
    H, W = srcs[0].shape
    attrs = dict(plan.attrs)
    attrs["kind"] = plan.kind
    attrs["source"] = [s.name for s in srcs]
    attrs["tile"] = tile
    attrs["sample_dtype"] = str(srcs[0].dtype)
    from sarship.pipeline import __version__

    attrs["sarship_version"] = __version__
    meta: dict[str, Any] = {}
    for s in srcs:  # first file that knows wins
        for k, v in s.meta.items():
            meta.setdefault(k, v)
    for k in ("crs", "transform", "gcps", "pixel_spacing_m", "pixel_spacing_source", "sensor",
              "acquired", "product"):
        if k in meta:
            attrs[k] = meta[k]
    if meta.get("pols"):
        attrs["polarisations"] = meta["pols"]
    if meta.get("sidecar"):
        attrs["metadata_sidecar"] = meta["sidecar"]
    # looks that need no pixels
    if looks is not None:
        attrs["looks"], attrs["looks_source"] = float(looks), "argument"
    elif meta.get("looks") is not None:
        attrs["looks"], attrs["looks_source"] = float(meta["looks"]), "attribute"
        attrs["looks_note"] = meta.get("looks_note", "")
    elif plan.kind in ("slc", "quadpol"):
        attrs["looks"], attrs["looks_source"] = 1.0, "single-look complex"

    row_band: dict[int, tuple[int, int, np.ndarray]] = {}

    def read_src(k: int, s: _Source, r0, r1, c0, c1):
        if s.prefers_rows:
            nbytes = (r1 - r0) * W * max(1, s.nbands) * s.dtype.itemsize
            if nbytes <= ROW_BAND_BYTES:
                cached = row_band.get(k)
                if cached is None or cached[0] != r0:
                    row_band[k] = (r0, r1, s.read(r0, r1, 0, W))
                return row_band[k][2][:, c0:c1]
        return s.read(r0, r1, c0, c1)

    last_row = [-1]

    def read_tile(r0, r1, c0, c1):
        if r0 != last_row[0]:  # new tile row: drop the previous row's maps and bands
            for s in srcs:
                s.release()
            row_band.clear()
            last_row[0] = r0
        arrs = [read_src(k, s, r0, r1, c0, c1) for k, s in enumerate(srcs)]
        return plan.compute(arrs)

    with atomic_store(outp) as tmp:
        g = create_scene(tmp, (H, W), plan.variables, tile=tile, attrs=attrs)
        _write_tiles(g, (H, W), tile, plan.variables, read_tile, progress)
        row_band.clear()
        for s in srcs:
            s.release()
        if "looks" not in attrs and plan.kind == "covariance":
            attrs.update(_rank_one_looks(tmp, list(plan.variables), (H, W), tile))
        if "looks" not in attrs:
            attrs.update(_estimate_scene_looks(tmp, plan.looks_var, (H, W), tile))
        finalize_scene(tmp, attrs)


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
    return {"looks": 1.0,
            "looks_source": (f"estimated: rank-one covariance (median over sampled pixels of the largest "
                             f"1 - |c_ij|^2/(c_ii c_jj) is {med:.1e} < {RANK_ONE_TOL:g}, {len(wins)} tile(s)): "
                             "single look")}


def _estimate_scene_looks(store: Path, var: str, shape, tile) -> dict[str, Any]:
    """Looks by MoLC on a bounded sample of tiles re-read from the store."""
    import zarr

    from sarship.pipeline.looks import estimate_looks

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
        "looks_source": (f"estimated: MoLC (median log-variance of 32x32 windows, trigamma inverted) "
                         f"on '{var}', {len(picks)} tile(s)"),
    }


def _ingest_zarr(src: Path, outp: Path, tile: int, progress, looks) -> None:
    sc = open_scene(src)
    attrs = dict(sc.attrs)
    arrays = {name: sc.array(name) for name in sc.variables}
    variables = {name: np.dtype(dt) for name, dt in sc.variables.items()}
    attrs["tile"] = tile
    attrs.setdefault("source", [src.name])
    attrs.setdefault("kind", "intensity")
    if looks is not None:
        attrs["looks"], attrs["looks_source"] = float(looks), "argument"
        attrs.pop("looks_note", None)

    def read_tile(r0, r1, c0, c1):
        out = {}
        for name, a in arrays.items():
            try:
                out[name] = np.asarray(a[r0:r1, c0:c1])
            except Exception as exc:
                raise InputError(f"'{src}': cannot read '{name}' rows {r0}:{r1}, cols {c0}:{c1} "
                                 f"({_one_line(exc)})") from None
        return out

    with atomic_store(outp) as tmp:
        g = create_scene(tmp, sc.shape, variables, tile=tile, attrs=attrs)
        _write_tiles(g, sc.shape, tile, variables, read_tile, progress)
        if attrs.get("looks") is None:
            if attrs["kind"] in ("slc", "quadpol"):
                attrs["looks"], attrs["looks_source"] = 1.0, "single-look complex"
            else:
                var = "intensity" if "intensity" in variables else ("c11" if "c11" in variables else None)
                if attrs["kind"] == "covariance" and "c12" in variables:
                    attrs.update(_rank_one_looks(tmp, list(variables), sc.shape, tile))
                if var is not None and attrs.get("looks") is None:
                    attrs.update(_estimate_scene_looks(tmp, var, sc.shape, tile))
        finalize_scene(tmp, attrs)
