"""Sentinel-1 IW SLC products (SAFE folder or ``.zip``): one sub-swath as a complex scene.

What is read (see ``docs/sentinel1.md``, section SLC): the sub-swath chosen with ``swath``
(``--swath IW1|IW2|IW3``; required when the product holds several), each polarisation that
has a measurement GeoTIFF of that sub-swath as a complex64 channel (``vv``, ``vh``, ...),
kind ``slc``, looks 1. Per output tile:

1. **deburst** (:func:`sarship.pipeline.readers.tops.deburst_segments`): the measurement's
   stacked bursts become one continuous azimuth-time grid, each line taken whole from one
   burst, the seams at the midpoints of the burst overlaps (as ESA SNAP's TOPS Deburst);
   samples outside each line's ``firstValidSample .. lastValidSample`` are absent (NaN);
2. **calibration** (ESA, "Radiometric Calibration of S-1 Level-1 Products",
   docs/references.md#s1-calibration): ``z = DN / A``, ``A`` the ``sigmaNought`` LUT
   interpolated bilinearly on its line/pixel grid (in the measurement's own line numbers),
   so that ``|z|^2 = |DN|^2 / A^2`` is sigma0; without calibration annotation ``z = DN``;
3. **deramping and demodulation** (docs/references.md#s1-deramping;
   :mod:`sarship.pipeline.readers.tops`): ``z exp(-j phi)`` per burst, so the azimuth
   spectrum is baseband at every line: the phase relations between neighbouring pixels that
   ``csk``'s per-detection features use (non-circularity, the RFI flag, NPDD) are then those
   of the scene, not of the antenna sweep. Intensity and the polarimetric products
   (``z_p conj(z_q)``: the ramp is common to the polarisations) are unchanged by it.

Thermal noise is not removed (noise power is defined on ``|DN|^2``, not on complex samples).
Attributes as for GRD plus ``swath``, ``bursts`` (each burst's output rows and measurement
lines), ``slc_phase``, ``swath_first_line_time``, ``ground_range_spacing_m``. GCPs: the
swath's geolocation grid, rows mapped to the debursted grid by azimuth time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

import sarship.pipeline.readers.tops as tops
from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line, _Source
from sarship.pipeline.readers.limits import InputLimits

#: Rows processed at once within a tile (bounds the float64 temporaries of the LUT and the
#: deramping phase to a few MiB per column block).
STRIP_ROWS = 256


def _seconds(iso: Any, epoch: np.datetime64) -> float:
    return float((np.datetime64(str(iso), "ns") - epoch) / np.timedelta64(1, "ns")) * 1e-9


def _iso(epoch: np.datetime64, s: float) -> str:
    return str(epoch + np.timedelta64(int(round(s * 1e9)), "ns"))[:26]


class SlcSource(_Source):
    """One debursted, calibrated, deramped sub-swath: ``read`` gives ``(h, w, npol)`` complex64."""

    def __init__(
        self,
        p: Path,
        prod,
        pols: list[str],
        meas: dict[str, str],
        meta: dict[str, Any],
        shape: tuple[int, int],
        segs: list[tops.Segment],
        lpb: int,
        valid: list[tuple[np.ndarray, np.ndarray]],
        ramps: list[tops.BurstRamp] | None,
        luts: dict[str, tuple],
    ):
        super().__init__(path=p, shape=shape, nbands=len(pols), dtype=np.dtype(np.complex64), fmt="safe", meta=meta)
        import rasterio

        from sarship.pipeline.readers.safe import GDAL_CACHE_MB

        self.pols, self.segs, self.lpb, self.valid, self.ramps, self.luts = pols, segs, lpb, valid, ramps, luts
        self._env = rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB)
        with self._env:
            self._ds = [rasterio.open(prod.raster_path(meas[pol])) for pol in pols]

    def _read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        from rasterio.windows import Window

        from sarship.pipeline.readers.safe import bilinear_lut

        out = np.empty((r1 - r0, c1 - c0, len(self.pols)), np.complex64)
        covered = np.zeros(r1 - r0, bool)
        cols = np.arange(c0, c1)
        for sg in self.segs:
            for a in range(max(r0, sg.row0), min(r1, sg.row1), STRIP_ROWS):  # strips bound the temporaries
                b = min(a + STRIP_ROWS, r1, sg.row1)
                covered[a - r0 : b - r0] = True
                l0, l1 = a + sg.offset, b + sg.offset  # lines within the burst
                t0, t1 = sg.burst * self.lpb + l0, sg.burst * self.lpb + l1  # measurement rows
                fv, lv = self.valid[sg.burst]
                fv, lv = fv[l0:l1], lv[l0:l1]
                bad = None
                if fv.max() > c0 or lv.min() < c1 - 1:
                    bad = (cols[None, :] < fv[:, None]) | (cols[None, :] > lv[:, None])
                rot = None
                if self.ramps is not None:
                    rot = tops.rotation(tops.deramp_phase(self.ramps[sg.burst], l0, l1, c0, c1))
                for k, (pol, ds) in enumerate(zip(self.pols, self._ds)):
                    with self._env:
                        z = ds.read(1, window=Window(c0, t0, c1 - c0, t1 - t0), out_dtype=np.complex64)
                    f = rot
                    if pol in self.luts:  # z / A
                        lines, pixels, vals = self.luts[pol]
                        inv = np.reciprocal(bilinear_lut(lines, pixels, vals, t0, t1, c0, c1), dtype=np.float32)
                        f = inv if rot is None else rot * inv
                    dst = out[a - r0 : b - r0, :, k]
                    if f is None:
                        dst[...] = z
                    else:
                        np.multiply(z, f, out=dst)
                    if bad is not None:
                        dst[bad] = np.nan + 1j * np.nan
        if not covered.all():  # rows of a gap between bursts that do not overlap
            out[~covered] = np.nan + 1j * np.nan
        return out

    def close(self) -> None:
        for ds in self._ds:
            ds.close()
        self._ds = []


def _row_of_line(line: int, btimes: list[float], lpb: int, dt: float, t_first: float) -> float:
    """The debursted row (float) at the azimuth time of measurement line ``line``."""
    b = min(line // lpb, len(btimes) - 1)
    return (btimes[b] + (line - b * lpb) * dt - t_first) / dt


def _interp_record(ds, var: str, at_ns: np.datetime64) -> tuple[np.ndarray, float]:
    """Coefficients and t0 of an annotation polynomial list, linear in time at ``at_ns``."""
    times = (ds["azimuth_time"].values - at_ns) / np.timedelta64(1, "ns") * 1e-9
    order = np.argsort(times)
    coeffs = tops.interp_records(times[order], ds[var].values[order], 0.0)
    t0 = float(tops.interp_records(times[order], ds["t0"].values[order], 0.0)[0])
    return coeffs, t0


def open_slc(p: Path, prod, slc: dict[str, dict[str, str]], limits: InputLimits, swath: str | None) -> SlcSource:
    """Open sub-swath ``swath`` of the SLC product ``prod`` (measurements ``slc[swath][pol]``):
    its annotation, bursts and deramping checked and computed before any pixel is read."""
    from sarship.pipeline.readers.safe import POL_ORDER, manifest_attrs

    sw = _choose_swath(p, slc, swath)
    meas = slc[sw]
    pols = sorted(meas, key=lambda q: POL_ORDER[q])
    root = manifest_attrs(p, prod)
    if str(root.get("mode", "IW")).upper() != "IW":
        raise InputError(f"'{p}': a Sentinel-1 {root.get('mode')} SLC product; only IW (TOPS) SLC is read")
    anns = {}
    for pol in pols:
        base = meas[pol].split("/")[-1].rsplit(".", 1)[0]
        ann = f"annotation/{base}.xml"
        if ann not in prod.members:
            raise InputError(f"'{p}': no annotation {ann} for the {sw} {pol.upper()} measurement")
        anns[pol] = (base, ann)
    pol0 = pols[0]
    ann0 = anns[pol0][1]
    info, pinfo, timing, dc, fm, orbit = _annotation(p, prod, ann0)
    b = _bursts(p, prod, sw, ann0, info, timing, meas, pols, limits)
    limits.check_pixels(p, b["H"], b["width"])
    ramps = _ramps(p, sw, ann0, info, pinfo, orbit, fm, dc, b)
    luts, gcps = _calibration_and_gcps(p, prod, sw, pols, anns, b)
    meta = _slc_meta(prod, sw, pols, info, root, gcps, luts, b)
    from sarship.pipeline.readers.safe_geometry import sar_geometry  # azimuth-ambiguity geometry, as for GRD

    geom = sar_geometry(prod, sw, pol0)
    if "shape" in geom:  # the scene's (debursted) rows, not the measurement's stacked lines
        geom["shape"] = [b["H"], b["width"]]
    meta["extra_attrs"]["sar_geometry"] = geom
    return SlcSource(
        p, prod, pols, meas, meta, (b["H"], b["width"]), b["segs"], b["lpb"], b["valid_samples"], ramps, luts
    )


def _choose_swath(p: Path, slc: dict[str, dict[str, str]], swath: str | None) -> str:
    """The sub-swath asked for (``--swath``), or the product's only one; one line otherwise."""
    have = sorted(slc)
    if swath is None:
        if len(have) > 1:
            raise InputError(
                f"'{p}': an IW SLC product with the sub-swaths {', '.join(have)}: choose one with "
                f"--swath {'|'.join(have)} (one scene per sub-swath)"
            )
        swath = have[0]
    sw = str(swath).strip().upper()
    if sw not in slc:
        raise InputError(f"'{p}': --swath {swath}: the product has no such sub-swath (it has {', '.join(have)})")
    return sw


def _annotation(p: Path, prod, ann0: str):
    """The first polarisation's annotation: image, product and swath-timing information, Doppler
    centroid and azimuth FM-rate estimates, orbit (xarray-sentinel)."""
    from xarray_sentinel import esa_safe, sentinel1

    try:

        def tag(path):
            with prod.open_member(ann0) as f:
                return esa_safe.parse_tag(f, path)

        info, pinfo, timing = tag("//imageInformation"), tag("//productInformation"), tag("//swathTiming")
        with prod.open_member(ann0) as f:
            dc = sentinel1.open_dc_estimate_dataset(f)
        with prod.open_member(ann0) as f:
            fm = sentinel1.open_azimuth_fm_rate_dataset(f)
        with prod.open_member(ann0) as f:
            orbit = sentinel1.open_orbit_dataset(f)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"'{p}': cannot read the annotation {ann0} ({_one_line(exc)})") from None
    return info, pinfo, timing, dc, fm, orbit


def _bursts(
    p: Path, prod, sw: str, ann0: str, info, timing, meas: dict[str, str], pols: list[str], limits: InputLimits
) -> dict[str, Any]:
    """The image size and every measurement's header checked against the annotation, then the
    bursts: lines per burst, azimuth times, valid samples and the debursted segments (tops)."""
    from sarship.pipeline.readers.safe import check_image_size, check_measurement

    try:
        lines_in, width = int(info["numberOfLines"]), int(info["numberOfSamples"])
        check_image_size(p, ann0, (lines_in, width))
        for pol in pols:  # each measurement's header against the annotation, before any pixel or LUT
            check_measurement(p, prod, meas[pol], ann0, (lines_in, width), limits)
        lpb = int(timing["linesPerBurst"])
        bursts = timing["burstList"]["burst"]
        if isinstance(bursts, dict):
            bursts = [bursts]
        if not bursts or lpb * len(bursts) != lines_in:
            raise ValueError(f"{len(bursts or [])} bursts of {lpb} lines for {lines_in} lines")
        dt = float(info["azimuthTimeInterval"])
        epoch = np.datetime64(str(bursts[0]["azimuthTime"]), "ns")
        btimes = [_seconds(b["azimuthTime"], epoch) for b in bursts]
        valid_samples = [
            (
                np.array(str(b["firstValidSample"]["$"]).split(), np.int64),
                np.array(str(b["lastValidSample"]["$"]).split(), np.int64),
            )
            for b in bursts
        ]
        if any(len(f) != lpb or len(lv) != lpb for f, lv in valid_samples):
            raise ValueError("firstValidSample/lastValidSample do not have linesPerBurst values")
        vlines = [tops.valid_lines(f) for f, _ in valid_samples]
        segs, H, t_first = tops.deburst_segments(btimes, vlines, dt)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"'{p}': the {sw} burst annotation of {ann0} is not usable ({_one_line(exc)})") from None
    return {
        "lines_in": lines_in,
        "width": width,
        "lpb": lpb,
        "n": len(bursts),
        "dt": dt,
        "epoch": epoch,
        "btimes": btimes,
        "valid_samples": valid_samples,
        "segs": segs,
        "H": H,
        "t_first": t_first,
    }


def _ramps(p: Path, sw: str, ann0: str, info, pinfo, orbit, fm, dc, b: dict[str, Any]) -> list:
    """The deramping function of each burst (tops module docstring)."""
    dt, epoch, btimes, lpb = b["dt"], b["epoch"], b["btimes"], b["lpb"]
    try:
        tau = float(info["slantRangeTime"]) + np.arange(b["width"]) / float(pinfo["rangeSamplingRate"])
        ramps = []
        ot = (orbit["azimuth_time"].values - epoch) / np.timedelta64(1, "ns") * 1e-9
        vel = orbit["velocity"].values  # (3, n)
        for k in range(b["n"]):
            centre = btimes[k] + lpb / 2.0 * dt
            v = np.array([np.interp(centre, ot, vel[i]) for i in range(3)])
            at = epoch + np.timedelta64(int(round(centre * 1e9)), "ns")
            fmc, fmt0 = _interp_record(fm, "azimuth_fm_rate_polynomial", at)
            dcc, dct0 = _interp_record(dc, "data_dc_polynomial", at)
            fv, _ = b["valid_samples"][k]
            first_col = int(np.median(fv[fv >= 0]))
            ramps.append(
                tops.burst_ramp(
                    tau,
                    float(np.linalg.norm(v)),
                    float(pinfo["radarFrequency"]),
                    float(pinfo["azimuthSteeringRate"]),
                    fmc,
                    fmt0,
                    dcc,
                    dct0,
                    first_col,
                    lpb,
                    dt,
                )
            )
    except Exception as exc:
        raise InputError(f"'{p}': cannot compute the {sw} deramping function from {ann0} ({_one_line(exc)})") from None
    return ramps


def _calibration_and_gcps(
    p: Path, prod, sw: str, pols: list[str], anns: dict, b: dict[str, Any]
) -> tuple[dict[str, tuple], list | None]:
    """Each polarisation's size checked, its sigmaNought LUT (where the product has one) and the
    swath's GCPs on the debursted rows."""
    import xarray as xr
    from xarray_sentinel import esa_safe

    from sarship.pipeline.readers.safe import check_lut

    lines_in, width = b["lines_in"], b["width"]
    luts: dict[str, tuple] = {}
    gcps = None
    for pol in pols:
        base, ann = anns[pol]
        group = f"{sw}/{pol.upper()}"
        try:
            if pol != pols[0]:
                with prod.open_member(ann) as f:
                    other = esa_safe.parse_tag(f, "//imageInformation")
                if (int(other["numberOfLines"]), int(other["numberOfSamples"])) != (lines_in, width):
                    raise InputError(
                        f"'{p}': the {sw} {pol.upper()} measurement is {other['numberOfLines']} x "
                        f"{other['numberOfSamples']}, not {lines_in} x {width}"
                    )
            if gcps is None:
                g = xr.open_dataset(prod.url, engine="sentinel-1", group=f"{group}/gcp")
                gl, gp = g["line"].values, g["pixel"].values
                lat, lon, h, inc = (g[v].values for v in ("latitude", "longitude", "height", "incidenceAngle"))
                # measurement line -> debursted row, by the line's azimuth time
                rows = [_row_of_line(int(L), b["btimes"], b["lpb"], b["dt"], b["t_first"]) for L in gl]
                # + 1/2: the centre of the indexed pixel in pixel-is-area coordinates (safe.py)
                gcps = [
                    {
                        "row": float(rows[i]) + 0.5,
                        "col": float(gp[j]) + 0.5,
                        "x": float(lon[i, j]),
                        "y": float(lat[i, j]),
                        "z": float(h[i, j]),
                        "incidence": float(inc[i, j]),
                    }
                    for i in range(len(gl))
                    for j in range(len(gp))
                ]
            if f"annotation/calibration/calibration-{base}.xml" in prod.members:
                c = xr.open_dataset(prod.url, engine="sentinel-1", group=f"{group}/calibration")
                luts[pol] = (c["line"].values, c["pixel"].values, c["sigmaNought"].values)
                check_lut(p, f"sigmaNought calibration LUT of {sw} {pol.upper()} (calibration-{base}.xml)", *luts[pol])
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"'{p}': cannot read the {group} annotation ({_one_line(exc)})") from None
    return luts, gcps


def _slc_meta(prod, sw: str, pols: list[str], info, root: dict, gcps, luts: dict, b: dict[str, Any]) -> dict[str, Any]:
    """The source's metadata and the scene attributes it records (docs/interfaces/files.md)."""
    dt, epoch, t_first, H, lpb = b["dt"], b["epoch"], b["t_first"], b["H"], b["lpb"]
    spacing = [float(info["azimuthPixelSpacing"]), float(info["rangePixelSpacing"])]
    inc = float(info.get("incidenceAngleMidSwath", "nan"))
    if len(luts) == len(pols):
        cal = "sigma0: z = DN / A (sigmaNought LUT, bilinear), |z|^2 = sigma0"
    elif luts:
        cal = f"sigma0 for {', '.join(sorted(luts))} only (z = DN / A); DN for the others (no calibration annotation)"
    else:
        cal = "none (no calibration annotation in the product)"
    meta: dict[str, Any] = {
        "pols": pols,
        "kind_hint": ("complex", "Sentinel-1 IW SLC sub-swath"),
        "pixel_spacing_m": spacing,
        "pixel_spacing_source": "SAFE annotation imageInformation azimuthPixelSpacing, rangePixelSpacing (slant range)",
        "sensor": f"{root.get('family_name', 'SENTINEL-1')}{root.get('number', '')}",
        "acquired": str(root.get("start_time")),
        "product": prod.name.removesuffix(".zip"),
        "gcps": gcps,
        "looks": 1.0,
        "looks_note": "single-look complex (SLC)",
    }
    meta["extra_attrs"] = {
        "mode": str(root.get("mode", "IW")),
        "product_type": "SLC",
        "swath": sw,
        "acquisition_start": str(root.get("start_time")),
        "acquisition_stop": str(root.get("stop_time")),
        "swath_first_line_time": _iso(epoch, t_first),
        "swath_last_line_time": _iso(epoch, t_first + (H - 1) * dt),
        "azimuth_time_interval_s": dt,
        "orbit_pass": str(root.get("pass", "")),
        "calibration": cal,
        "thermal_noise_removal": "none (SLC: noise power applies to |DN|^2, not to complex samples)",
        "slc_phase": (
            "debursted (seams at the burst-overlap midpoints), deramped and demodulated to baseband per "
            "burst (ESA TOPS SLC deramping function)"
        ),
        "bursts": [
            {
                "burst": sg.burst,
                "rows": [sg.row0, sg.row1],
                "measurement_lines": [sg.burst * lpb + sg.row0 + sg.offset, sg.burst * lpb + sg.row1 + sg.offset],
                "azimuth_time": _iso(epoch, t_first + sg.row0 * dt),
            }
            for sg in b["segs"]
        ],
        "incidence_angle_mid_swath_deg": inc,
        "ground_range_spacing_m": spacing[1] / float(np.sin(np.radians(inc))) if np.isfinite(inc) and inc > 0 else None,
    }
    return meta
