"""TIFF / GeoTIFF / BigTIFF input: the source, the tifffile/GDAL metadata, the GeoTIFF
georeference and the SNAP sidecar of OpenSARShip-style chips.

**TIFF / GeoTIFF / BigTIFF** (tifffile): real or complex samples, any number of bands
(contiguous or planar, or several pages of one series), stripped or tiled, compressed or
not. Uncompressed contiguous data are memory-mapped; anything else is read through
tifffile's ``aszarr()`` chunk by chunk. A stripped file whose tile row is small enough
(<= ``ROW_BAND_BYTES``) is read one tile row at a time so strips are decoded once.

A ``GDAL_NODATA`` value (0 included) is left out of the ``auto`` sample and stored as NaN
(absent: every detector leaves it out of its statistics and never reports it) in intensity.

GeoTIFF: ``ModelPixelScale`` + one ``ModelTiepoint``, or ``ModelTransformation``; EPSG from
``ProjectedCSTypeGeoKey`` or ``GeographicTypeGeoKey``. ``pixel_spacing_m`` comes from the
pixel size when the CRS is projected in metres (``ProjLinearUnitsGeoKey``, or a known
metre-based EPSG code when that key is absent); for geographic CRSs (degrees, e.g. EPSG:4326)
it is approximated on the WGS84 ellipsoid at the scene-centre latitude and
``pixel_spacing_source`` says so.

SNAP sidecar: a SNAP/BEAM ``Abstracted_Metadata`` XML found by :func:`_find_sidecar`: in the
chip's folder ``<stem>.xml``, then in the chip's folder and up to ``SIDECAR_LEVELS`` folders
above it (nearest first, never above ``stop``, the folder the caller's input came from,
when one is given: the inbox folder of a pass) a file named
``Metedata.xml`` (OpenSARShip's own spelling), ``Metadata.xml`` or ``<folder>.xml`` (the
OpenSARShip layout ``<product>/Patch/<chip>.tif`` + ``<product>/Metedata.xml`` or
``<product>/<product>.xml``); files without ``Abstracted_Metadata`` are skipped. It gives
``sensor`` (MISSION + ACQUISITION_MODE), ``acquired`` (first_line_time), ``product``,
``polarisations`` (``mdsN_tx_rx_polar``, else the ``Band_*`` ``polarization`` items, else the
polarisation token of each ``Band_*`` element's name, e.g. ``Band_IW1_VV``; they name the
channels), ``SAMPLE_TYPE`` (COMPLEX: (re, im) band pairs), ``pixel_spacing_m``
(azimuth_spacing, range_spacing) and the nominal looks (azimuth_looks x range_looks).
A caller can turn the sidecar off (``sidecar_root=False``: a service upload is one file, so
nothing beside it belongs to it).
"""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ET
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _POL_RE, _check_dtype, _check_hw, _one_line, _Source
from sarship.pipeline.readers.limits import InputLimits
from sarship.pipeline.scene import COMPLEX_CHANNELS


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


def _open_tiff(p: Path, sidecar_root: Path | bool | None = None, limits: InputLimits | None = None) -> _Source:
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
        (limits or InputLimits()).check_tiff(p, s, nb, dt)  # from the headers, before any decode
        _check_tiff_complete(p, tif, s)
        src = _TiffSource(path=p, shape=(H, W), nbands=nb, dtype=dt.newbyteorder("="), fmt="tiff")
        src.tif, src.series, src.yx = tif, s, (iy, ix)
        src.memmappable = s.dataoffset is not None  # uncompressed and contiguous
        page = s.pages[0] if s.pages else None
        if not hasattr(page, "tags"):  # a TiffFrame: tags live on the first page
            page = tif.pages.first
        src.prefers_rows = (not src.memmappable) and not bool(getattr(page, "is_tiled", False))
        src.meta.update(_tiff_metadata(p, tif, page, nb, (H, W), sidecar_root))
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


def _tiff_metadata(
    p: Path, tif, page, nbands: int, shape: tuple[int, int], sidecar_root: Path | bool | None = None
) -> dict[str, Any]:
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
            if math.isfinite(v):
                meta["nodata"] = v
        except ValueError:
            pass
    side = (
        {} if sidecar_root is False else _snap_sidecar(p, stop=sidecar_root if isinstance(sidecar_root, Path) else None)
    )
    # the TIFF's own georeference, looks and band names win over the product-level sidecar
    groups = {
        "pixel_spacing_m": "pixel_spacing_m",
        "pixel_spacing_source": "pixel_spacing_m",
        "looks": "looks",
        "looks_note": "looks",
        "pols": "pols",
    }
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
    (32601, 32660),
    (32701, 32760),
    (32201, 32260),
    (32301, 32360),
    (26901, 26923),
    (25828, 25838),
    (28348, 28358),
    (31466, 31469),
    (3857, 3857),
    (3395, 3395),
    (3035, 3035),
    (3034, 3034),
    (3031, 3031),
    (3413, 3413),
    (3976, 3976),
    (3995, 3995),
    (2154, 2154),
    (27700, 27700),
    (5070, 5070),
    (6933, 6933),
    (3577, 3577),
    (2056, 2056),
    (21781, 21781),
    (4087, 4087),
    (32662, 32662),
    (3578, 3578),
    (3005, 3005),
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
                kid, loc, cnt, v = g[4 + 4 * k : 8 + 4 * k]
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


#: How many folders above the chip's own folder :func:`_find_sidecar` looks in.
SIDECAR_LEVELS = 3

#: Sidecar names looked for in each folder (besides ``<stem>.xml`` and ``<folder>.xml``).
SIDECAR_NAMES = ("Metedata.xml", "metedata.xml", "Metadata.xml", "metadata.xml")


def _sidecar_candidates(p: Path, levels: int = SIDECAR_LEVELS, stop: Path | None = None) -> list[Path]:
    """Candidate sidecar files for the chip ``p``, nearest first (see the module docstring).

    The search climbs at most ``levels`` folders above the chip's folder, and never above
    ``stop`` (the folder the user gave) when that is one of the chip's folders.
    """
    here = Path(os.path.abspath(p)).parent  # the folders as given (symbolic links not followed)
    stop_r = None if stop is None else Path(os.path.abspath(stop))
    if stop_r is not None and stop_r != here and stop_r not in here.parents:
        stop_r = None  # not an enclosing folder: no extra bound
    cands = [p.with_suffix(".xml")]
    d = here
    for _ in range(levels + 1):
        names = list(SIDECAR_NAMES)
        if d.name:
            names.append(d.name + ".xml")
        for n in names:
            c = d / n
            if c not in cands:
                cands.append(c)
        if d == stop_r or d.parent == d:
            break
        d = d.parent
    return cands


def _snap_sidecar(p: Path, stop: Path | None = None) -> dict[str, Any]:
    """SNAP ``Abstracted_Metadata`` of an OpenSARShip-style chip (see module doc); {} if none."""
    cands = _sidecar_candidates(p, stop=stop)
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
        try:
            rel = os.path.relpath(c, p.parent)
        except ValueError:
            rel = str(c)
        out: dict[str, Any] = {"sidecar": rel}
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
        pols = [v.strip().lower() for v in pols if v and v.strip() and v.strip() != "-"]
        if not pols:  # no mdsN_tx_rx_polar: the polarisations of the Band_* elements, in order
            for b in am:
                if b.tag.startswith("Band_"):
                    v = next((e.get("value") for e in b.findall("attrib") if e.get("name") == "polarization"), None)
                    if not v:  # no polarization item: the one token of the element's name (Band_IW1_VV)
                        toks = set(_POL_RE.findall(b.tag.lower()))
                        v = toks.pop() if len(toks) == 1 else None
                    if v and v.strip().lower() not in pols:
                        pols.append(v.strip().lower())
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
                out["looks_note"] = f"SNAP metadata {c.name}: azimuth_looks {la:g} x range_looks {lr:g} (nominal)"
        except (KeyError, TypeError, ValueError):
            pass
        return out
    return {}
