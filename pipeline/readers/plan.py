"""Planning an ingest: which scene variables the sources give and how each tile is
computed (covariance, complex channels, detected bands; the ``auto`` quantity rule).

Quantities and the ``auto`` rule for real samples
-------------------------------------------------
Real bands are *detected* data, stored as float32 intensity (amplitude is squared). With
``kind="auto"`` a file's real bands are taken, first rule that applies:

1. as (re, im) pairs of SLC channels when a SNAP metadata sidecar says
   ``SAMPLE_TYPE=COMPLEX`` and there are two bands per polarisation (OpenSARShip SLC chips)
   or the file's metadata says complex, or when the sampled values (NaN and the GDAL no-data
   value left out) include negative numbers and the band count is even (negative values
   cannot be amplitude or intensity; an odd count is refused);
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
1 and 4-5 are not applied to them, but negative sampled values are refused). The rule taken
is recorded in the ``quantity_rule`` attribute. ``kind="amplitude"`` or ``"intensity"``
forces the choice, except where the data contradict it: complex samples, bands the metadata
says are (re, im) pairs (rule 1's sidecar / metadata cases) or negative values in the probe
are refused with one line naming the file, the kind asked and what the data is;
``kind="slc"`` or ``"quadpol"`` pairs real bands as (re, im) (an even count is required).

Detected (amplitude / intensity) data are also checked as each tile is written: a tile with
a negative value (NaN and the no-data value allowed) aborts the ingest with one line, and
the atomic store leaves nothing at ``out`` (a probe can miss a few negative pixels).

Several real bands are stored as ``intensity_<name>`` each (names from ``channels``, else
the sidecar/band-description polarisations (when their count is the band count; for a
single band or complex channel of a product with several, the one polarisation token of the
file name or its two enclosing folders that is among them), else polarisation tokens in
the file names when several files are stacked, else ``b0, b1, ...``) and ``intensity`` =
the band chosen by ``band`` (name or index; default band 0).

A single real band keeps the name ``intensity``; its polarisation, when the metadata gives
it, is the ``channels`` attribute.

Several input files are stacked as channels; they must have equal shapes. Complex channel
names come from ``channels``, else the sidecar polarisations (as for real bands), else
polarisation tokens in the file names (``hh``, ``hv``, ``vh``, ``vv``), else by count
(1: ``hh``; 2: ``vh, vv``; 3: ``hh, hv, vv``; 4: ``hh, hv, vh, vv``), except where the
metadata names other polarisations (one (re, im) pair of an OpenSARShip chip of a VH + VV
product, no ``_vv`` in its name or folders): that is refused in one line asking for
``--channels``, never stored under a polarisation the product does not have. Complex
channels must be named among ``hh, hv, vh, vv``.
``kind`` attribute: ``quadpol`` when ``hh, hv, vv`` are all present, else ``slc``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _POL_RE, _Source
from sarship.pipeline.readers.polsarpro import C3_BASIS
from sarship.pipeline.scene import COMPLEX_CHANNELS

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


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


def _meta_pols(n: int, srcs: list[_Source]) -> list[str] | None:
    """Channel names from the single source's metadata (sidecar / band descriptions): its
    polarisations when there are ``n``; for one channel of a product with several, the one
    polarisation token of the file's name or enclosing folders that is among them."""
    if len(srcs) != 1 or not srcs[0].meta.get("pols"):
        return None
    pols = list(srcs[0].meta["pols"])
    if len(pols) == n:
        return pols
    if n == 1:
        parts = [srcs[0].path.stem, *[d.name for d in list(srcs[0].path.parents)[:2]]]
        toks = {t for part in parts for t in _POL_RE.findall(part.lower().replace("-", "_"))}
        toks &= set(pols)
        if len(toks) == 1:
            return [toks.pop()]
    return None


def _complex_names(n: int, srcs: list[_Source], channels: list[str] | None) -> list[str]:
    if channels is not None:
        names = [str(c).lower() for c in channels]
        if len(names) != n:
            raise InputError(f"--channels names {len(names)} channel(s) but the input has {n} complex channel(s)")
    elif (mp := _meta_pols(n, srcs)) is not None:
        names = mp
    elif len(srcs) > 1 and (pn := _pols_from_names(srcs)) is not None and len(pn) == n:
        names = pn
    else:
        defaults = {1: ["hh"], 2: ["vh", "vv"], 3: ["hh", "hv", "vv"], 4: ["hh", "hv", "vh", "vv"]}
        if n not in defaults:
            raise InputError(f"{n} complex channels: at most 4 (hh, hv, vh, vv) are supported")
        names = defaults[n]
        meta = [str(q) for q in (srcs[0].meta.get("pols") or [])] if len(srcs) == 1 else []
        if meta and not set(names) <= set(meta):  # never a polarisation the product does not have
            side = srcs[0].meta.get("sidecar")
            raise InputError(
                f"'{srcs[0].path}': {n} complex channel(s), but its metadata"
                + (f" ({side})" if side else "")
                + f" names the polarisations {', '.join(meta)} and neither "
                "the file name nor its folders say which: name them with --channels (e.g. --channels "
                f"{','.join(meta[:n])})"
            )
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
    elif (mp := _meta_pols(n, srcs)) is not None:
        names = mp
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


def _pairs_from_metadata(s: _Source) -> str | None:
    """Why the file's metadata says its real bands are (re, im) pairs, or None."""
    side = s.meta.get("sample_type")
    npol = len(s.meta.get("pols") or [])
    if side == "COMPLEX" and npol and s.nbands == 2 * npol:
        return f"SNAP metadata SAMPLE_TYPE=COMPLEX with {s.nbands} bands = (re, im) x {npol} polarisations"
    hint = s.meta.get("kind_hint")
    if hint and hint[0] == "complex" and s.nbands % 2 == 0:
        return hint[1] + f": {s.nbands} real bands = (re, im) pairs"
    return None


def _sample_min(s: _Source, sample: np.ndarray) -> float | None:
    """The smallest sampled value, NaN and the declared no-data value left out (None: none)."""
    if not (np.issubdtype(sample.dtype, np.floating) or np.issubdtype(sample.dtype, np.signedinteger)):
        return None
    if "nodata" in s.meta:
        sample = sample[sample != s.meta["nodata"]]
    fin = sample[np.isfinite(sample)] if np.issubdtype(sample.dtype, np.floating) else sample
    return float(fin.min()) if fin.size else None


def _negative_error(s: _Source, asked: str, vmin: float, where: str) -> InputError:
    pairs = " (re, im) pairs? use --kind slc;" if s.nbands % 2 == 0 else ""
    return InputError(
        f"'{s.path}': {asked}, but the data has negative values (min {vmin:g} in {where}), so it is neither "
        f"amplitude nor intensity:{pairs} dB? convert to linear power first"
    )


def _check_real_kind(s: _Source, kind: str) -> None:
    """Refuse ``--kind amplitude|intensity`` for a file whose data contradict it: (re, im) band
    pairs by its metadata, or negative values in the bounded probe (a damaged file is left
    to fail while writing)."""
    why = _pairs_from_metadata(s)
    if why:
        raise InputError(
            f"'{s.path}': --kind {kind}, but the data is complex (bands re/im: {why}): use --kind slc "
            "or leave --kind auto"
        )
    if s.fmt == "image":
        return
    try:
        sample = s.probe()
    except InputError:
        return  # unreadable pixels: reported with their position by the tile loop
    vmin = _sample_min(s, sample)
    if vmin is not None and vmin < 0:
        raise _negative_error(s, f"--kind {kind}", vmin, "the sample read")


def _auto_quantity(s: _Source) -> tuple[str, str]:
    """("amplitude" | "intensity" | "pairs", rule) for a real source under kind auto."""
    sample = None
    if s.fmt != "npy":
        why = _pairs_from_metadata(s)
        if why:
            return "pairs", why
    hint = s.meta.get("kind_hint")
    if hint and hint[0] == "complex":
        raise InputError(f"'{s.path}': metadata says complex but it has an odd number ({s.nbands}) of real bands")
    if s.fmt != "image":
        sample = s.probe()
        vmin = _sample_min(s, sample)
        if vmin is not None and vmin < 0:
            if s.fmt == "npy":
                raise _negative_error(s, ".npy real arrays are intensity", vmin, "the sample read")
            if s.nbands % 2 == 0:
                return "pairs", (
                    f"negative samples cannot be amplitude or intensity: {s.nbands} real bands taken as (re, im) pairs"
                )
            raise InputError(
                f"'{s.path}': real samples include negative values (sampled min {vmin:g}), so they are "
                f"neither amplitude nor intensity (dB? convert to linear power first), and {s.nbands} "
                "band(s) cannot be (re, im) pairs"
            )
    if s.fmt == "npy":
        return "intensity", ".npy real arrays are intensity (the contract)"
    if hint:
        return hint[0], hint[1]
    if np.issubdtype(s.dtype, np.integer):
        return "amplitude", f"integer samples ({s.dtype}) are amplitude digital numbers"
    if "nodata" in s.meta:
        sample = sample[sample != s.meta["nodata"]]
    fin = sample[np.isfinite(sample)]
    if fin.size and fin.max() > 1 and np.all(fin == np.floor(fin)):
        return "amplitude", (f"{s.dtype} samples are all whole numbers (digital numbers stored as float): amplitude")
    return "intensity", f"{s.dtype} samples are intensity"


def _check_tile(s: _Source, a: np.ndarray, asked: str) -> None:
    """Abort on a tile of detected data with negative or infinite values (NaN and no-data
    allowed: they are absent pixels; an infinite one is not a measurement of anything)."""
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.signedinteger)):
        return
    if np.issubdtype(a.dtype, np.floating):
        inf = np.isposinf(a)
        if inf.any() and not ("nodata" in s.meta and np.isposinf(s.meta["nodata"])):
            raise InputError(
                f"'{s.path}': {asked}, but the data has infinite values ({int(inf.sum())} pixels in "
                "a tile being written): a damaged or unscaled product? Mark absent pixels as NaN "
                "or with a declared no-data value"
            )
    neg = a < 0
    if not neg.any():
        return
    if "nodata" in s.meta:
        neg &= a != s.meta["nodata"]
        if not neg.any():
            return
    raise _negative_error(s, asked, float(a[neg].min()), "a tile being written")


def _to_f32_intensity(a: np.ndarray, amplitude: bool, nodata: float | None = None) -> np.ndarray:
    x = a.astype(np.float32, copy=False)
    if amplitude:
        x = np.square(x, dtype=np.float32)
    if nodata is not None:  # declared no-data: absent (NaN), which every detector leaves out
        x = np.where(a == nodata, np.float32(np.nan), x).astype(np.float32, copy=False)
    return x


def _plan(
    srcs: list[_Source],
    kind: str,
    band,
    channels,
) -> _Plan:
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
                out[f"c{i + 1}{j + 1}"] = np.real(v).astype(np.float32) if i == j else v.astype(np.complex64)
            return out

        attrs["quantity"] = f"covariance C{n}"
        attrs["quantity_rule"] = f"(H, W, {n}, {n}) array: covariance matrix per pixel"
        attrs["format"] = f"npy covariance C{n}"
        attrs["covariance_basis"] = C3_BASIS if n == 3 else "dual-pol [k1, k2] as given (channels unknown)"
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
                f"'{srcs[0].path}': --kind {kind}, but the data is complex ({srcs[0].dtype} samples): "
                "use --kind slc (or quadpol) or leave --kind auto; detectors derive intensity themselves"
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
            for s in srcs:
                _check_real_kind(s, kind)
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
            asked = f"--kind {kind}" if kind in ("amplitude", "intensity") else f"read as {q} ({rule})"
            return _plan_detected(srcs, q == "amplitude", rule, band, channels, asked)
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


def _plan_detected(srcs, amplitude: bool, rule: str, band, channels, asked: str = "detected data") -> _Plan:
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
        elif (mp := _meta_pols(1, srcs)) is not None:
            attrs["channels"] = mp

        def compute(arrs):
            _check_tile(srcs[0], arrs[0], asked)
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
        for k, a in enumerate(arrs):
            _check_tile(srcs[k], a, asked)
        out = {}
        for nm, (k, b) in zip(names, bands):
            out[f"intensity_{nm}"] = _to_f32_intensity(arrs[k][:, :, b], amplitude, srcs[k].meta.get("nodata"))
        out["intensity"] = out[f"intensity_{names[sel]}"]
        return out

    return _Plan("intensity", variables, compute, attrs, "intensity")
