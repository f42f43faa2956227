"""The acquisition geometry of a Sentinel-1 SAFE product, as the scene attribute ``sar_geometry``.

What :mod:`sarship.pipeline.targets.ambiguity` needs to place azimuth ambiguities (its eqs. 1-3), read
from the product annotation of one swath/polarisation. The orbit, azimuth FM rate, Doppler
centroid and geolocation grid come from xarray-sentinel's groups (typed, schema-checked); the
plain values it does not expose (the PRF of ``downlinkInformation``, the swath bounds of
``swathMerging``, the TOPS steering rate and burst timing) from one ElementTree parse of the
annotation XML.

=============================== =====================================================================
key                             from the annotation (xarray-sentinel group, else ElementTree)
=============================== =====================================================================
``radar_frequency_hz``          ``generalAnnotation/productInformation/radarFrequency``
``prf_hz`` / ``swaths``         ``downlinkInformation/prf`` per swath; GRD: column/line bounds of
                                each swath from ``swathMerging/swathMergeList`` (IW1/IW2/IW3 have
                                different PRFs in one GRD)
``platform_velocity_m_s``       ``|v|`` of the orbit state vectors (group ``orbit``) at mid product
``azimuth_time_interval_s``     ``imageInformation/azimuthTimeInterval`` (zero-Doppler time per line)
``first_line_time``             ``imageInformation/productFirstLineUtcTime`` (ISO 8601 UTC, ``Z``
                                appended): with the interval, each line's zero-Doppler time
                                (:func:`sarship.pipeline.ais.scene_time.line_times`)
``range_table.slant_range_m``   ``c tau / 2``: GRD: ``slantRangeTime`` of the geolocation grid per
                                grid column (group ``gcp``); SLC: ``tau0 + col / rangeSamplingRate``
``range_table.effective_``      ``sqrt(|Ka| lambda R / 2)`` with ``Ka`` the azimuth FM rate
``velocity_m_s``                polynomial (group ``azimuth_fm_rate``) at the column's ``tau``
                                (median over its azimuth times)
``range_table.doppler_``        the data Doppler centroid polynomials (group ``dc_estimate``) at the
``centroid_hz``                 column's ``tau``, median over azimuth, wrapped into +-PRF/2
``doppler_centroid_spread_hz``  TOPS (``azimuthSteeringRate`` > 0): half the centroid's span over a
                                burst (:func:`~sarship.pipeline.targets.ambiguity.tops_doppler_spread_hz`);
                                burst = ``linesPerBurst x azimuthTimeInterval`` (SLC) or the
                                ``dcEstimate`` fine-DCE window (GRD); 0 for stripmap
=============================== =====================================================================

:func:`sar_geometry` never raises: a product whose annotation lacks a value gives
``{"unavailable": "<why>"}``, and detection then leaves ``ambiguity_of`` null and says why in
``run.json``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any
from xml.etree import ElementTree

import numpy as np

from sarship.pipeline.targets.ambiguity import C_LIGHT, effective_velocity_from_fm_rate, tops_doppler_spread_hz


def _poly(coeffs: np.ndarray, t0: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Annotation polynomials ``sum_d c_d (tau - t0)^d``: (n_az, deg) x (n_az,) at tau -> (n_az, n_tau)."""
    dt = tau[None, :] - t0[:, None]
    return sum(coeffs[:, d, None] * dt**d for d in range(coeffs.shape[1]))


def _seconds(t: Any) -> float:
    return float(np.datetime64(str(t), "ns").astype("int64")) * 1e-9


def _utc_iso(t: str) -> str:
    """An annotation time (UTC, written without a zone) as ISO 8601 with ``Z``."""
    return t if t.endswith("Z") or "+" in t[10:] else t + "Z"


def _annotation_root(prod: Any, swath: str, pol: str) -> ElementTree.Element:
    """The root of the annotation XML of ``swath``/``pol`` (the plain values: one ElementTree
    parse of the annotation)."""
    ann = [
        m
        for m in prod.members
        if m.startswith("annotation/") and m.count("/") == 1 and f"-{swath.lower()}-" in m and f"-{pol.lower()}-" in m
    ]
    if not ann:
        raise ValueError(f"no annotation for {swath}/{pol.upper()}")

    with prod.open_member(ann[0]) as f:
        return ElementTree.parse(f).getroot()


def _swaths(root: ElementTree.Element, swath: str) -> list[dict[str, Any]]:
    """``swaths``: each sub-swath's name, PRF (``downlinkInformation/prf``, median) and, in a
    GRD, its bounds in the merged image (``swathMerging``; none for an SLC's one swath)."""
    prfs: dict[str, list[float]] = {}
    for d in root.iterfind("generalAnnotation/downlinkInformationList/downlinkInformation"):
        prfs.setdefault(str(d.findtext("swath", "")).strip().upper(), []).append(float(d.findtext("prf", "nan")))
    if not prfs or not all(math.isfinite(v) and v > 0 for vs_ in prfs.values() for v in vs_):
        raise ValueError("no valid downlinkInformation/prf in the annotation")
    swaths: list[dict[str, Any]] = []
    merge = root.findall("swathMerging/swathMergeList/swathMerge")
    if merge:  # GRD: each sub-swath's bounds in the merged image
        for m in merge:
            name = str(m.findtext("swath", "")).strip().upper()
            if name not in prfs:
                raise ValueError(f"no PRF for sub-swath {name}")
            bl = m.findall("swathBoundsList/swathBounds")
            swaths.append(
                {
                    "name": name,
                    "prf_hz": float(np.median(prfs[name])),
                    "blocks": [
                        [
                            int(b.findtext(k, ""))
                            for k in ("firstAzimuthLine", "lastAzimuthLine", "firstRangeSample", "lastRangeSample")
                        ]
                        for b in bl
                    ],
                }
            )
    else:
        name = swath.upper()
        if name not in prfs:
            raise ValueError(f"no PRF for swath {name}")
        swaths.append({"name": name, "prf_hz": float(np.median(prfs[name])), "blocks": []})
    return swaths


def _tops_burst(
    root: ElementTree.Element, text: Callable[..., str], steer: float, ka: np.ndarray, vs: float, lam: float, ati: float
) -> tuple[float, float]:
    """TOPS (``steer`` > 0): the spread of the centroid over a burst and the burst duration
    (``linesPerBurst x ati``, else the ``dcEstimate`` fine-DCE window); ``ka``: the azimuth FM
    rate per range column."""
    lpb = int(text("swathTiming/linesPerBurst", "0"))
    if lpb > 0:
        burst_s = lpb * ati
    else:
        win = [
            _seconds(e.findtext("fineDceAzimuthStopTime")) - _seconds(e.findtext("fineDceAzimuthStartTime"))
            for e in root.iterfind("dopplerCentroid/dcEstimateList/dcEstimate")
            if e.findtext("fineDceAzimuthStartTime") and e.findtext("fineDceAzimuthStopTime")
        ]
        burst_s = float(np.median(win)) if win else None
    if not burst_s or burst_s <= 0:
        raise ValueError("a TOPS product without burst duration (linesPerBurst or dcEstimate windows)")
    spread = max(tops_doppler_spread_hz(float(k), math.radians(steer), vs, lam, burst_s) for k in ka)
    return spread, burst_s


def read_geometry(prod: Any, swath: str, pol: str) -> dict[str, Any]:
    """``sar_geometry`` of ``swath``/``pol`` of the product ``prod`` (a
    :class:`sarship.pipeline.readers.safe._Product`: ``url`` for xarray-sentinel, ``members``
    and ``open_member`` for the annotation XML). Raises on a missing or bad value (see
    :func:`sar_geometry` for the form that never raises)."""
    import xarray as xr

    root = _annotation_root(prod, swath, pol)

    def text(path: str, default: str | None = None) -> str:
        v = root.findtext(path)
        if v is None:
            if default is None:
                raise ValueError(f"the annotation has no {path}")
            return default
        return v.strip()

    group = f"{swath}/{pol.upper()}"

    def ds(sub: str):
        return xr.open_dataset(prod.url, engine="sentinel-1", group=f"{group}/{sub}")

    pi, ii = "generalAnnotation/productInformation/", "imageAnnotation/imageInformation/"
    freq = float(text(pi + "radarFrequency"))
    lam = C_LIGHT / freq
    fs = float(text(pi + "rangeSamplingRate"))
    ati = float(text(ii + "azimuthTimeInterval"))
    swaths = _swaths(root, swath)
    # platform velocity at mid product
    orb = ds("orbit")
    t_orb = np.array([_seconds(t) for t in orb["azimuth_time"].values])
    speed = np.linalg.norm(orb["velocity"].values, axis=0)
    t_mid = 0.5 * (_seconds(text(ii + "productFirstLineUtcTime")) + _seconds(text(ii + "productLastLineUtcTime")))
    vs = float(np.interp(t_mid, t_orb, speed))
    # slant range per column
    H, W = int(text(ii + "numberOfLines")), int(text(ii + "numberOfSamples"))
    tau0 = float(text(ii + "slantRangeTime"))
    if text(pi + "projection", "").lower().startswith("ground"):
        g = ds("gcp")
        cols = g["pixel"].values.astype(float)
        tau = g["slant_range_time"].values.astype(float)
    else:
        cols = np.array([0.0, (W - 1) / 2.0, float(W - 1)])
        tau = tau0 + cols / fs
    R = C_LIGHT * tau / 2.0
    # effective velocity from the azimuth FM rate; Doppler centroid
    fm = ds("azimuth_fm_rate")
    ka = np.median(_poly(fm["azimuth_fm_rate_polynomial"].values, fm["t0"].values, tau), axis=0)
    vr = effective_velocity_from_fm_rate(ka, lam, R)
    dc = ds("dc_estimate")
    fdc = np.median(_poly(dc["data_dc_polynomial"].values, dc["t0"].values, tau), axis=0)
    prf0 = swaths[0]["prf_hz"]
    fdc = (fdc + prf0 / 2.0) % prf0 - prf0 / 2.0  # the baseband centroid lies in +-PRF/2
    # TOPS: the spread of the centroid over a burst
    steer = float(text(pi + "azimuthSteeringRate", "0"))
    spread, burst_s = _tops_burst(root, text, steer, ka, vs, lam, ati) if steer > 0 else (0.0, None)
    out: dict[str, Any] = {
        "source": f"Sentinel-1 annotation of {swath}/{pol.upper()} (xarray-sentinel)",
        "radar_frequency_hz": freq,
        "wavelength_m": lam,
        "platform_velocity_m_s": vs,
        "azimuth_time_interval_s": ati,
        "first_line_time": _utc_iso(text(ii + "productFirstLineUtcTime")),
        "range_sampling_rate_hz": fs,
        "slant_range_time_s": tau0,
        "range_table": {
            "col": cols.tolist(),
            "slant_range_m": R.tolist(),
            "effective_velocity_m_s": vr.tolist(),
            "doppler_centroid_hz": fdc.tolist(),
        },
        "swaths": swaths,
        "doppler_centroid_spread_hz": spread,
        "azimuth_steering_rate_deg_s": steer,
        "shape": [H, W],
    }
    if burst_s is not None:
        out["burst_duration_s"] = burst_s
    if len(swaths) == 1:
        out["prf_hz"] = swaths[0]["prf_hz"]
    return out


def sar_geometry(prod: Any, swath: str, pol: str) -> dict[str, Any]:
    """:func:`read_geometry`, or ``{"unavailable": "<one line why>"}`` (never raises: the
    product is read without the ambiguity geometry)."""
    try:
        return read_geometry(prod, swath, pol)
    except Exception as exc:  # any annotation problem: the scene is still usable
        msg = " ".join(str(exc).split())[:300] or type(exc).__name__
        return {"unavailable": f"{type(exc).__name__}: {msg}"}


__all__ = ["read_geometry", "sar_geometry"]
