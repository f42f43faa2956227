"""PolSARpro C3 / T3 / C2 folders (element files + ENVI headers), the store's covariance
basis ``C3_BASIS`` and the T3 -> C3 conversion (``PAULI_U``, :func:`t3_to_c3`).

**a PolSARpro folder** (C3, T3 or C2; the path of the folder, of its ``config.txt`` or of
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
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line, _Source

#: The unitary change of basis from lexicographic to Pauli scattering vectors:
#: ``k_pauli = PAULI_U @ k_lex`` with ``k_lex = [HH, sqrt2 HV, VV]`` and
#: ``k_pauli = (1/sqrt2) [HH+VV, HH-VV, 2 HV]``; hence ``T = U C U^H`` and ``C = U^H T U``.
PAULI_U = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, -1.0], [0.0, math.sqrt(2.0), 0.0]]) / math.sqrt(2.0)

#: ``covariance_basis`` attribute of C3 scenes (the store's convention, see the module doc).
C3_BASIS = "lexicographic [HH, sqrt2 HV, VV]"


_ENVI_DTYPES = {4: "f4", 5: "f8"}
_ENVI_DTYPE_NAMES = {
    1: "uint8",
    2: "int16",
    3: "int32",
    4: "float32",
    5: "float64",
    6: "complex64",
    9: "complex128",
    12: "uint16",
    13: "uint32",
    14: "int64",
    15: "uint64",
}
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
    n = _matrix_size(d, files, basis, polar_type)
    label = f"{basis}{n}"
    elems = _elements(basis, n)
    stems = [s for _, ss in elems for s in ss]
    missing = [f"{s}.bin" for s in stems if f"{s.lower()}.bin" not in files]
    if missing:
        raise InputError(f"'{d}': PolSARpro {label} folder is missing element file(s) {', '.join(missing)}")
    ncfg = _config_shape(cfg, cfg_path)
    out, shape, orders, headerless = _element_files(files, stems, ncfg, cfg_path)
    src = _PolsarproSource(
        path=d, shape=shape, nbands=n, dtype=out[stems[0]][1].newbyteorder("="), fmt="polsarpro", layout="covariance"
    )
    src.basis, src.files = basis, out
    attrs: dict[str, Any] = {
        "format": f"PolSARpro {label}" if basis == "C" else "PolSARpro T3 -> C3",
        "source_files": [out[s][0].name for s in stems],
        "byte_order": sorted(orders)[0] if len(orders) == 1 else sorted(orders),
        "quantity": f"covariance C{n}",
    }
    attrs.update(_basis_attrs(basis, n, polar_type))
    if cfg:
        attrs["polsarpro_config"] = {k: cfg[k] for k in ("Nrow", "Ncol", "PolarCase", "PolarType") if k in cfg}
    if headerless:
        attrs["polsarpro_note"] = (
            f"no ENVI header for {', '.join(headerless)}: size from config.txt, float32 little-endian"
        )
    src.meta["cov_attrs"] = attrs
    return src


def _matrix_size(d: Path, files: dict[str, Path], basis: str, polar_type: str) -> int:
    """The side of the folder's matrix (``basis`` C: 3, or 2 for dual-pol; T: 3); C4/T4 and T2
    folders are refused."""
    if basis == "C" and ("c44.bin" in files) or basis == "T" and ("t44.bin" in files):
        raise InputError(f"'{d}': a PolSARpro {basis}4 folder (4 x 4, bistatic); only C3, T3 and C2 are supported")
    if basis == "C":
        dual = (
            polar_type in _DUAL_TYPES
            or polar_type.startswith("pp")
            or (polar_type != "full" and "c33.bin" not in files and "c13_real.bin" not in files and "c22.bin" in files)
        )
        return 2 if dual else 3
    if polar_type.startswith("pp") or ("t33.bin" not in files and "t13_real.bin" not in files and "t22.bin" in files):
        raise InputError(
            f"'{d}': a PolSARpro T2 folder; only C3, T3 and C2 are supported (convert it to C2 in PolSARpro)"
        )
    return 3


def _config_shape(cfg: dict[str, str], cfg_path: Path | None) -> tuple[int, int] | None:
    """config.txt's (Nrow, Ncol), None when it gives neither."""
    if "Nrow" in cfg or "Ncol" in cfg:
        try:
            return (int(cfg["Nrow"]), int(cfg["Ncol"]))
        except (KeyError, ValueError):
            raise InputError(
                f"'{cfg_path}': Nrow/Ncol are not whole numbers (Nrow={cfg.get('Nrow')!r}, Ncol={cfg.get('Ncol')!r})"
            ) from None
    return None


def _element_files(
    files: dict[str, Path], stems: list[str], ncfg: tuple[int, int] | None, cfg_path: Path | None
) -> tuple[dict[str, tuple[Path, np.dtype, int]], tuple[int, int], set[str], list[str]]:
    """The element files of ``stems``, each checked: (stem -> (path, dtype, offset), the scene's
    shape, the byte orders, the names of the files read without a header)."""
    out: dict[str, tuple[Path, np.dtype, int]] = {}
    shape = None
    orders: set[str] = set()
    headerless: list[str] = []
    for s in stems:
        b = files[f"{s.lower()}.bin"]
        h = files.get(f"{s.lower()}.bin.hdr") or files.get(f"{s.lower()}.hdr")
        H, W, off, order, dt, what = _element_layout(b, h, ncfg)
        if h is None:
            headerless.append(b.name)
        size = os.path.getsize(b)
        want = H * W * dt.itemsize + off
        if size != want:
            raise InputError(f"'{b}': header/size mismatch: the file has {size} bytes but {what} = {want}")
        if shape is None:
            shape = (H, W)
        elif (H, W) != shape:
            first = stems[0]
            raise InputError(
                f"'{b}': {H} lines x {W} samples but {first}.bin is "
                f"{shape[0]} x {shape[1]}: element files must have equal sizes"
            )
        if ncfg is not None and ncfg != (H, W):
            raise InputError(f"'{b}': {H} lines x {W} samples but '{cfg_path}' says Nrow {ncfg[0]} x Ncol {ncfg[1]}")
        orders.add("big-endian" if order == 1 else "little-endian")
        out[s] = (b, dt, off)
    assert shape is not None
    return out, shape, orders, headerless


def _element_layout(b: Path, h: Path | None, ncfg: tuple[int, int] | None) -> tuple[int, int, int, int, np.dtype, str]:
    """An element file's (lines, samples, header offset, byte order, dtype) from its ENVI header
    ``h`` (checked) or, without one, from config.txt's size (float32 little-endian), and the
    sentence that says where they came from."""
    if h is None:
        if ncfg is None:
            raise InputError(f"'{b}': no ENVI header ('{b.name}.hdr') and no config.txt Nrow/Ncol to give its size")
        H, W = ncfg
        return H, W, 0, 0, np.dtype("<f4"), f"config.txt says Nrow {H} x Ncol {W} x 4 bytes (float32, no header)"
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
            "PolSARpro element files are data type 4 (float32) or 5 (float64)"
        )
    if nb != 1:
        raise InputError(f"'{h}': {nb} bands; a PolSARpro element file holds one band")
    if inter not in ("bsq", "bil", "bip"):
        raise InputError(f"'{h}': unsupported interleave '{inter}' (expected bsq)")
    if order not in (0, 1):
        raise InputError(f"'{h}': byte order must be 0 (little-endian) or 1 (big-endian), got {order}")
    if H < 1 or W < 1 or off < 0:
        raise InputError(f"'{h}': bad size ({W} samples x {H} lines, header offset {off})")
    dt = np.dtype(("<" if order == 0 else ">") + _ENVI_DTYPES[code])
    return (
        H,
        W,
        off,
        order,
        dt,
        f"its header '{h.name}' says {W} samples x {H} lines x {dt.itemsize} bytes + offset {off}",
    )


def _basis_attrs(basis: str, n: int, polar_type: str) -> dict[str, Any]:
    """The scene attributes ``covariance_basis``, ``quantity_rule`` and, for a C2 folder whose
    PolarType names them, ``polarisations``."""
    attrs: dict[str, Any] = {}
    if n == 3:
        attrs["covariance_basis"] = C3_BASIS
        attrs["quantity_rule"] = (
            "PolSARpro C3 folder: element files stored as they are"
            if basis == "C"
            else "PolSARpro T3 folder (coherency, Pauli basis k_p = (1/sqrt2)[HH+VV, HH-VV, 2HV]) converted "
            "to C3 = U^H T U, U = (1/sqrt2)[[1,0,1],[1,0,-1],[0,sqrt2,0]]"
        )
    else:
        ch = _DUAL_TYPES.get(polar_type)
        attrs["covariance_basis"] = (
            f"dual-pol [{ch[0].upper()}, {ch[1].upper()}] (PolarType {polar_type})"
            if ch
            else "dual-pol [k1, k2] as given (channels unknown)"
        )
        if ch:
            attrs["polarisations"] = ch
        attrs["quantity_rule"] = "PolSARpro C2 folder: element files stored as they are"
    return attrs
