"""Azimuth ambiguities ("ghosts") of bright ships: where they fall, and which detections are one.

A SAR samples the azimuth (Doppler) spectrum at the pulse repetition frequency PRF, so the
energy a bright target returns through the antenna's azimuth sidelobes at Doppler
``f_dc + k PRF`` (k = +-1, +-2, ...) is aliased into the processed band and focused as a
fainter copy of the target: the k-th azimuth ambiguity. Its place follows from the linear
time-frequency relation of the azimuth chirp (Curlander & McDonough 1991, azimuth ambiguity
analysis, and Cumming & Wong 2005: azimuth FM rate ``Ka = -2 Vr^2 / (lambda R)``, ``Vr`` the
effective velocity; docs/references.md#curlander1991, #cumming2005; the section numbers were
not checked against the books, so none are given):

(1) ``dt_k = k PRF / Ka = -k lambda R PRF / (2 Vr^2)``     (zero-Doppler azimuth time shift, s)

(2) ``dx_k = Vg dt_k = -k lambda R PRF / (2 Vs)``          (along-track ground shift, m)

    with ``Vg = Vr^2 / Vs`` (ground velocity of the zero-Doppler point, ``Vs`` the platform
    velocity): the form Greidanus et al. 2017 (docs/references.md#greidanus2017, SUMO)
    use, ``|dx| = lambda R PRF / (2 V)``;

(3) ``dR_k = lambda^2 R ((f_dc + k PRF)^2 - f_dc^2) / (8 Vr^2)``   (slant range shift, m)

    the range migration of the ambiguous energy (true Doppler ``f_dc + k PRF``) that the
    processor's migration correction (for Doppler ``f_dc``) leaves uncorrected: from the
    hyperbolic range history ``R(t) = sqrt(R^2 + Vr^2 t^2)`` and ``f = -2 R'(t) / lambda``,
    the energy at Doppler ``f`` lies ``lambda^2 R f^2 / (8 Vr^2)`` beyond ``R`` (the
    range-Doppler form of the range migration, Cumming & Wong 2005; checked against the
    exact hyperbola in tests/pipeline/test_ambiguity.py). For Sentinel-1 IW (lambda = 5.55 cm,
    R ~ 850 km, PRF ~ 1700 Hz, Vr ~ 7180 m/s, ``f_dc ~ 0``) dR_1 ~ 18 m slant, 2-4
    ground-range pixels of 10 m: not negligible, so it is applied, not bounded.

Pixels: rows are azimuth lines in increasing zero-Doppler time (as Sentinel-1 products and
the simulator write them), ``d_row = dt_k / dt_line`` with ``dt_line`` the annotation's
azimuth time interval, else ``dx_k / d_az`` with ``d_az`` the ground azimuth line spacing.
Columns: ``col(R + dR_k)`` through the scene's slant-range table (slant range sampled at
columns: ground range for GRD, slant range for SLC), so ground/slant range geometry needs no
incidence angle.

TOPS (Sentinel-1 IW/EW): the Doppler centroid of a target changes with its position in the
burst by ``kt = Ka ks / (Ka - ks)`` per second of zero-Doppler time, ``ks = 2 Vs k_psi /
lambda`` the steering's Doppler rate (De Zan & Monti Guarnieri 2006,
docs/references.md#dezan2006; ESA's TOPS deramping note, #s1-deramping), over +-2.5 kHz for
IW. Equation (1) does not depend on ``f_dc``; (3) does, and a GRD product does not say
where in its burst a pixel was, so (3) is taken at the annotation's Doppler centroid and the
range tolerance widened by the spread
``|d col / d R| lambda^2 R |k| PRF 2 df / (8 Vr^2)`` (``df``: half the centroid's span in a
burst, geometry key ``doppler_centroid_spread_hz``).

Matching (as JRC SUMO flags azimuth ambiguities, Greidanus et al. 2017): a detection
is the ghost of order k of a brighter detection when its centroid lies within ``tol_px``
rows and ``tol_px`` (+ the TOPS spread) columns of that detection's predicted k-th ghost
and its peak is at least ``min_db`` dB below the parent's. The azimuth ambiguity-to-signal
ratio of current sensors is -20 to -25 dB (Sentinel-1: <= -22 dB required, Torres et al.
2012, docs/references.md#torres2012), worse at TOPS burst edges; the default ``min_db`` =
10 dB leaves that 10-15 dB for a ghost's peak measured high (speckle, a parent clipped by
saturation) while no ship less than 10x fainter than its neighbour 5 km away is called a
ghost. See docs/algorithms/ambiguity.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Speed of light in vacuum, m/s (SI definition).
C_LIGHT = 299_792_458.0
#: Ambiguity orders searched: the first two on either side (the third is >= 10 dB fainter still).
ORDERS: tuple[int, ...] = (-2, -1, 1, 2)
#: Scene attribute holding the geometry (written by the SAFE reader and the simulator).
ATTR = "sar_geometry"
#: Defaults of the detect-side parameters (docs/algorithms/ambiguity.md "Defaults").
DEFAULT_TOL_PX = 8.0
DEFAULT_MIN_DB = 10.0


# --------------------------------------------------------------------------------------
# equations (1)-(3)
# --------------------------------------------------------------------------------------


def azimuth_shift_s(k: Any, wavelength_m: Any, slant_range_m: Any, prf_hz: Any, v_eff_m_s: Any) -> Any:
    """Eq. (1): zero-Doppler time shift of the k-th ambiguity, ``-k lambda R PRF / (2 Vr^2)``
    (= ``k PRF / Ka``, ``Ka = -2 Vr^2 / (lambda R)``; Curlander & McDonough 1991)."""
    return -np.asarray(k) * wavelength_m * slant_range_m * prf_hz / (2.0 * np.square(v_eff_m_s))


def azimuth_shift_m(k: Any, wavelength_m: Any, slant_range_m: Any, prf_hz: Any, v_platform_m_s: Any) -> Any:
    """Eq. (2): along-track ground shift of the k-th ambiguity, ``-k lambda R PRF / (2 Vs)``
    (Greidanus et al. 2017; = ``Vg`` times eq. (1) with ``Vg = Vr^2 / Vs``)."""
    return -np.asarray(k) * wavelength_m * slant_range_m * prf_hz / (2.0 * v_platform_m_s)


def range_shift_m(
    k: Any, wavelength_m: Any, slant_range_m: Any, prf_hz: Any, v_eff_m_s: Any, doppler_centroid_hz: Any = 0.0
) -> Any:
    """Eq. (3): slant-range shift of the k-th ambiguity, ``lambda^2 R ((f_dc + k PRF)^2 -
    f_dc^2) / (8 Vr^2)``: the range migration left uncorrected for energy aliased by k PRF."""
    k = np.asarray(k)
    f = np.asarray(doppler_centroid_hz, float)
    return (
        np.square(wavelength_m)
        * slant_range_m
        * (np.square(f + k * prf_hz) - np.square(f))
        / (8.0 * np.square(v_eff_m_s))
    )


def range_spread_m(k: Any, wavelength_m: Any, slant_range_m: Any, prf_hz: Any, v_eff_m_s: Any, spread_hz: Any) -> Any:
    """Half-width of eq. (3) when ``f_dc`` is only known to +-``spread_hz`` (TOPS):
    ``lambda^2 R |k| PRF 2 spread / (8 Vr^2)``."""
    return (
        np.square(wavelength_m)
        * slant_range_m
        * np.abs(np.asarray(k))
        * prf_hz
        * 2.0
        * np.asarray(spread_hz, float)
        / (8.0 * np.square(v_eff_m_s))
    )


def effective_velocity_from_fm_rate(fm_rate_hz_s: Any, wavelength_m: Any, slant_range_m: Any) -> Any:
    """``Vr = sqrt(|Ka| lambda R / 2)`` (inverse of ``Ka = -2 Vr^2 / (lambda R)``)."""
    return np.sqrt(np.abs(fm_rate_hz_s) * wavelength_m * slant_range_m / 2.0)


def tops_doppler_spread_hz(
    fm_rate_hz_s: float, steering_rate_rad_s: float, v_platform_m_s: float, wavelength_m: float, burst_s: float
) -> float:
    """Half the span of a TOPS target's Doppler centroid over a burst of ``burst_s`` seconds of
    zero-Doppler time: ``|kt| burst / 2``, ``kt = Ka ks / (Ka - ks)``, ``ks = 2 Vs k_psi /
    lambda`` (De Zan & Monti Guarnieri 2006; ESA's TOPS deramping note)."""
    ks = 2.0 * v_platform_m_s * steering_rate_rad_s / wavelength_m
    ka = -abs(fm_rate_hz_s)
    kt = ka * ks / (ka - ks)
    return abs(kt) * burst_s / 2.0


# --------------------------------------------------------------------------------------
# the scene's geometry
# --------------------------------------------------------------------------------------


class GeometryError(ValueError):
    """The scene's ``sar_geometry`` attribute is missing or unusable (the message says why)."""


@dataclass(frozen=True)
class Geometry:
    """What eqs. (1)-(3) need, per scene: tables over columns, PRF per swath block."""

    wavelength_m: float
    platform_velocity_m_s: float
    cols: np.ndarray  # increasing column positions of the range table
    slant_range_m: np.ndarray  # R at those columns (strictly monotonic)
    v_eff_m_s: np.ndarray  # effective velocity Vr at those columns
    doppler_centroid_hz: np.ndarray  # f_dc at those columns
    prf_blocks: np.ndarray  # (n, 5): first_row, last_row, first_col, last_col (inclusive), prf
    azimuth_time_interval_s: float | None = None
    azimuth_line_spacing_m: float | None = None
    doppler_centroid_spread_hz: float = 0.0
    source: str = ""
    swath_names: tuple[str, ...] = field(default=())

    # -- tables --------------------------------------------------------------------------
    def at(self, cols: np.ndarray, table: np.ndarray) -> np.ndarray:
        """Linear interpolation over columns, extrapolated linearly past the ends."""
        return _interp_extrap(np.asarray(cols, float), self.cols, table)

    def col_of_range(self, r: np.ndarray) -> np.ndarray:
        """The (fractional) column whose slant range is ``r`` (inverse of the range table)."""
        if self.slant_range_m[-1] > self.slant_range_m[0]:
            return _interp_extrap(np.asarray(r, float), self.slant_range_m, self.cols)
        return _interp_extrap(np.asarray(r, float), self.slant_range_m[::-1], self.cols[::-1])

    def prf_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """PRF of the swath block holding each (row, col); outside every block, the block
        nearest in column (then row)."""
        rows, cols = np.asarray(rows, float), np.asarray(cols, float)
        b = self.prf_blocks
        dr = np.maximum(np.maximum(b[None, :, 0] - rows[:, None], rows[:, None] - b[None, :, 1]), 0.0)
        dc = np.maximum(np.maximum(b[None, :, 2] - cols[:, None], cols[:, None] - b[None, :, 3]), 0.0)
        best = np.lexsort((dr.T, dc.T), axis=0)[0] if len(b) > 1 else np.zeros(len(rows), int)
        return b[best, 4]

    # -- eqs (1)-(3) in pixels -----------------------------------------------------------
    def ghosts(
        self, rows: Sequence[float], cols: Sequence[float], orders: Sequence[int] = ORDERS
    ) -> dict[str, np.ndarray]:
        """Expected positions of the ``orders`` ambiguities of targets at (rows, cols).

        Returns arrays of shape (n, len(orders)): ``row``, ``col`` (pixels), ``dx_m`` (eq. 2),
        ``dt_s`` (eq. 1), ``dr_m`` (eq. 3), ``col_spread_px`` (the TOPS half-width in
        columns), and ``prf_hz``, ``slant_range_m`` of shape (n,).
        """
        rows = np.asarray(rows, float).reshape(-1)
        cols = np.asarray(cols, float).reshape(-1)
        k = np.asarray(orders, float)[None, :]
        lam = self.wavelength_m
        R = self.at(cols, self.slant_range_m)[:, None]
        vr = self.at(cols, self.v_eff_m_s)[:, None]
        fdc = self.at(cols, self.doppler_centroid_hz)[:, None]
        prf = self.prf_at(rows, cols)[:, None]
        dt = azimuth_shift_s(k, lam, R, prf, vr)
        dx = azimuth_shift_m(k, lam, R, prf, self.platform_velocity_m_s)
        if self.azimuth_time_interval_s:
            drow = dt / self.azimuth_time_interval_s
        else:
            # dx from eq. (1) times Vg = Vr^2 / Vs: the same line spacing as the time route
            drow = dt * (np.square(vr) / self.platform_velocity_m_s) / float(self.azimuth_line_spacing_m)
        dr = range_shift_m(k, lam, R, prf, vr, fdc)
        gcol = self.col_of_range(R + dr)
        spread = range_spread_m(k, lam, R, prf, vr, self.doppler_centroid_spread_hz)
        dcol_dr = np.abs(self.col_of_range(R + 1.0) - self.col_of_range(R))
        return {
            "row": rows[:, None] + drow,
            "col": gcol,
            "dt_s": dt,
            "dx_m": dx,
            "dr_m": dr,
            "col_spread_px": spread * dcol_dr,
            "prf_hz": prf[:, 0],
            "slant_range_m": R[:, 0],
        }


def _interp_extrap(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    xp, fp = np.asarray(xp, float), np.asarray(fp, float)
    if len(xp) == 1:
        return np.full_like(x, fp[0], dtype=float)
    y = np.interp(x, xp, fp)
    lo, hi = x < xp[0], x > xp[-1]
    y[lo] = fp[0] + (x[lo] - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0])
    y[hi] = fp[-1] + (x[hi] - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
    return y


def _pos(d: Mapping[str, Any], key: str, lo: float = 0.0, hi: float = math.inf) -> float:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo < v < hi:
        raise GeometryError(f"{ATTR}.{key} must be a number in ({lo:g}, {hi:g}), got {v!r}")
    return float(v)


def geometry_from_attrs(attrs: Mapping[str, Any]) -> Geometry:
    """The scene's :class:`Geometry` from its ``sar_geometry`` attribute (schema:
    docs/algorithms/ambiguity.md); :class:`GeometryError` naming the first missing or bad
    value otherwise. ``pixel_spacing_m[0]`` serves as the ground line spacing when the
    geometry has neither ``azimuth_time_interval_s`` nor ``azimuth_line_spacing_m``."""
    g = attrs.get(ATTR)
    if g is None:
        raise GeometryError(f"the scene has no '{ATTR}' attribute (PRF, velocity, wavelength, slant range)")
    if not isinstance(g, Mapping):
        raise GeometryError(f"the scene's '{ATTR}' attribute is not an object")
    if g.get("unavailable"):
        raise GeometryError(f"the scene's geometry is unavailable: {g['unavailable']}")
    f = _pos(g, "radar_frequency_hz", 1e8, 1e12)
    vs = _pos(g, "platform_velocity_m_s", 10.0, 2e4)
    ati = g.get("azimuth_time_interval_s")
    ati = _pos(g, "azimuth_time_interval_s", 0.0, 10.0) if ati is not None else None
    als = g.get("azimuth_line_spacing_m")
    als = _pos(g, "azimuth_line_spacing_m", 0.0, 1e5) if als is not None else None
    if ati is None and als is None:
        sp = attrs.get("pixel_spacing_m")
        try:
            als = float(sp[0])  # type: ignore[index]
        except (TypeError, ValueError, IndexError, KeyError):
            als = None
        if als is None or not math.isfinite(als) or als <= 0:
            raise GeometryError(
                f"{ATTR} has neither azimuth_time_interval_s nor azimuth_line_spacing_m, "
                "and the scene's pixel_spacing_m is unknown"
            )
    spread = g.get("doppler_centroid_spread_hz", 0.0)
    if isinstance(spread, bool) or not isinstance(spread, (int, float)) or not 0 <= spread < 1e5:
        raise GeometryError(f"{ATTR}.doppler_centroid_spread_hz must be a number in [0, 1e5), got {spread!r}")
    t = g.get("range_table")
    if not isinstance(t, Mapping):
        raise GeometryError(f"{ATTR}.range_table (col, slant_range_m, effective_velocity_m_s) is missing")
    try:
        cols = np.asarray(t["col"], float)
        R = np.asarray(t["slant_range_m"], float)
        vr = np.asarray(t["effective_velocity_m_s"], float)
        fdc = np.asarray(t.get("doppler_centroid_hz", np.zeros(len(cols))), float)
    except (KeyError, TypeError, ValueError) as exc:
        raise GeometryError(f"{ATTR}.range_table is not a table of numbers ({exc})") from None
    n = len(cols)
    if n < 1 or cols.ndim != 1 or any(a.shape != (n,) for a in (R, vr, fdc)):
        raise GeometryError(
            f"{ATTR}.range_table: col, slant_range_m, effective_velocity_m_s and "
            "doppler_centroid_hz must be lists of one length (>= 1)"
        )
    if not all(np.all(np.isfinite(a)) for a in (cols, R, vr, fdc)):
        raise GeometryError(f"{ATTR}.range_table holds non-finite values")
    if n > 1 and not np.all(np.diff(cols) > 0):
        raise GeometryError(f"{ATTR}.range_table.col must increase strictly")
    if np.any(R < 1e3) or np.any(R > 1e8) or (n > 1 and not (np.all(np.diff(R) > 0) or np.all(np.diff(R) < 0))):
        raise GeometryError(f"{ATTR}.range_table.slant_range_m must be monotonic, in [1 km, 1e5 km]")
    if n == 1:
        raise GeometryError(f"{ATTR}.range_table needs at least two columns (slant range must vary with column)")
    if np.any(vr < 10.0) or np.any(vr > 2e4):
        raise GeometryError(f"{ATTR}.range_table.effective_velocity_m_s must lie in (10, 2e4) m/s")
    sw = g.get("swaths")
    blocks, names = [], []
    if isinstance(sw, list) and sw:
        for s in sw:
            if not isinstance(s, Mapping):
                raise GeometryError(f"{ATTR}.swaths: each swath must be an object")
            prf = _pos(s, "prf_hz", 1.0, 1e5)
            names.append(str(s.get("name", "")))
            bl = s.get("blocks") or [[-math.inf, math.inf, -math.inf, math.inf]]
            for b in bl:
                try:
                    r0, r1, c0, c1 = (float(v) for v in b)
                except (TypeError, ValueError):
                    raise GeometryError(
                        f"{ATTR}.swaths[].blocks: [first_row, last_row, first_col, last_col], got {b!r}"
                    ) from None
                blocks.append([r0, r1, c0, c1, prf])
    elif "prf_hz" in g:
        blocks.append([-math.inf, math.inf, -math.inf, math.inf, _pos(g, "prf_hz", 1.0, 1e5)])
    else:
        raise GeometryError(f"{ATTR} has neither prf_hz nor swaths[].prf_hz")
    return Geometry(
        wavelength_m=C_LIGHT / f,
        platform_velocity_m_s=vs,
        cols=cols,
        slant_range_m=R,
        v_eff_m_s=vr,
        doppler_centroid_hz=fdc,
        prf_blocks=np.asarray(blocks, float),
        azimuth_time_interval_s=ati,
        azimuth_line_spacing_m=als,
        doppler_centroid_spread_hz=float(spread),
        source=str(g.get("source", "")),
        swath_names=tuple(names),
    )


# --------------------------------------------------------------------------------------
# matching
# --------------------------------------------------------------------------------------


def match_ambiguities(
    centroids: Any,
    peaks: Any,
    geom: Geometry,
    tol_px: float = DEFAULT_TOL_PX,
    min_db: float = DEFAULT_MIN_DB,
    orders: Sequence[int] = ORDERS,
) -> tuple[list[int | None], list[int | None]]:
    """For each detection, the index of the brighter detection it is an azimuth ghost of
    (else None), and the order k of that ghost (else None).

    Detection j is a ghost of order k of detection i when (a) ``peak_j <= peak_i 10^(-min_db
    / 10)``, (b) ``|row_j - row_ik| <= tol_px`` and ``|col_j - col_ik| <= tol_px +
    spread_ik``, (row_ik, col_ik) being i's expected k-th ghost (:meth:`Geometry.ghosts`, eqs.
    1 and 3) and spread_ik the TOPS half-width in columns, and (c) i is not itself a ghost.
    Detections are decided brightest first, so (c) is known when j is decided; among several
    parents the nearest expected position (in tolerance units) wins. Detections with a
    non-finite peak or centroid are neither ghosts nor parents.
    """
    from scipy.spatial import cKDTree

    c = np.asarray(centroids, float).reshape(-1, 2)
    p = np.asarray(peaks, float).reshape(-1)
    n = len(c)
    parent: list[int | None] = [None] * n
    order: list[int | None] = [None] * n
    ok = np.isfinite(p) & np.all(np.isfinite(c), axis=1)
    if n < 2 or ok.sum() < 2:
        return parent, order
    idx = np.flatnonzero(ok)
    g = geom.ghosts(c[idx, 0], c[idx, 1], orders)
    K = len(orders)
    pts = np.stack([g["row"].ravel(), g["col"].ravel()], axis=1)  # (len(idx) * K, 2)
    tol_c = tol_px + g["col_spread_px"].ravel()
    tree = cKDTree(pts)
    ratio = 10.0 ** (-min_db / 10.0)
    ghost = np.zeros(n, bool)
    for j in idx[np.argsort(-p[idx], kind="stable")]:
        cand = tree.query_ball_point(c[j], r=float(np.hypot(tol_px, tol_c.max())))
        best, best_d = None, math.inf
        for q in cand:
            i = int(idx[q // K])
            if i == j or ghost[i] or not p[j] <= p[i] * ratio:
                continue
            dr = abs(c[j, 0] - pts[q, 0]) / tol_px if tol_px > 0 else (0.0 if c[j, 0] == pts[q, 0] else math.inf)
            dc = abs(c[j, 1] - pts[q, 1]) / tol_c[q] if tol_c[q] > 0 else (0.0 if c[j, 1] == pts[q, 1] else math.inf)
            if dr <= 1.0 and dc <= 1.0 and math.hypot(dr, dc) < best_d:
                best, best_d = (i, int(orders[q % K])), math.hypot(dr, dc)
        if best is not None:
            parent[j], order[j] = best
            ghost[j] = True
    return parent, order


def check_params(tol_px: float, min_db: float) -> None:
    """``tol_px`` in [0, 1000] px and ``min_db`` in [0, 60] dB, else ValueError naming them."""
    if not (isinstance(tol_px, (int, float)) and math.isfinite(tol_px) and 0 <= tol_px <= 1000):
        raise ValueError(f"ambiguity_tol_px must be a number in [0, 1000] pixels, got {tol_px!r}")
    if not (isinstance(min_db, (int, float)) and math.isfinite(min_db) and 0 <= min_db <= 60):
        raise ValueError(f"ambiguity_min_db must be a number in [0, 60] dB, got {min_db!r}")


def flag_features(
    feats: list[dict],
    attrs: Mapping[str, Any],
    enabled: bool = True,
    tol_px: float = DEFAULT_TOL_PX,
    min_db: float = DEFAULT_MIN_DB,
    orders: Sequence[int] = ORDERS,
) -> tuple[list[dict], dict[str, Any]]:
    """Give every detection Feature ``properties.ambiguity_of`` (the ``id`` of its parent, or
    None), ``ambiguity_order`` (k, or None) and ``ambiguity_positions_px`` (where its own
    ghosts of ``orders`` are expected: ``[{"order": k, "centroid_px": [row, col]}, ...]``, eqs.
    1 and 3; None without geometry); Features without an ``id`` get their index in
    ``feats`` as ``id`` (Feature member and property). Returns the features and a record for
    ``run.json``: whether flags were computed, and if not why (switched off, no or bad
    geometry), the parameters and the number flagged. Never raises for a bad geometry."""
    for i, f in enumerate(feats):
        f.setdefault("id", i)
        f["properties"].setdefault("id", f["id"])
        f["properties"]["ambiguity_of"] = None
        f["properties"]["ambiguity_order"] = None
        f["properties"]["ambiguity_positions_px"] = None
    rec: dict[str, Any] = {
        "applied": False,
        "reason": None,
        "tol_px": tol_px,
        "min_db": min_db,
        "orders": list(orders),
        "flagged": 0,
    }
    if not enabled:
        rec["reason"] = "switched off (ambiguities=false)"
        return feats, rec
    try:
        geom = geometry_from_attrs(attrs)
    except GeometryError as exc:
        rec["reason"] = f"not computed: {exc}"
        return feats, rec
    rec.update(applied=True, geometry_source=geom.source)
    if not feats:
        return feats, rec
    cent = np.array([f["properties"]["centroid_px"] for f in feats], float)
    peaks = np.array([np.nan if f["properties"].get("peak") is None else f["properties"]["peak"] for f in feats], float)
    parent, order = match_ambiguities(cent, peaks, geom, tol_px, min_db, orders)
    for f, par, k in zip(feats, parent, order):
        if par is not None:
            f["properties"]["ambiguity_of"] = feats[par]["id"]
            f["properties"]["ambiguity_order"] = k
    rec["flagged"] = sum(par is not None for par in parent)
    ok = np.all(np.isfinite(cent), axis=1)
    if ok.any():
        exp = geom.ghosts(cent[ok, 0], cent[ok, 1], orders)
        for q, f in enumerate(f for f, good in zip(feats, ok) if good):
            f["properties"]["ambiguity_positions_px"] = [
                {"order": int(k), "centroid_px": [round(float(exp["row"][q, i]), 3), round(float(exp["col"][q, i]), 3)]}
                for i, k in enumerate(orders)
            ]
        g = geom.ghosts(cent[ok, 0], cent[ok, 1], (1,))
        rec["first_ambiguity_shift"] = {
            "rows": [
                round(float(np.abs(g["row"][:, 0] - cent[ok, 0]).min()), 3),
                round(float(np.abs(g["row"][:, 0] - cent[ok, 0]).max()), 3),
            ],
            "metres": [round(float(np.abs(g["dx_m"]).min()), 3), round(float(np.abs(g["dx_m"]).max()), 3)],
            "range_m": [round(float(g["dr_m"].min()), 3), round(float(g["dr_m"].max()), 3)],
        }
    return feats, rec


__all__ = [
    "ATTR",
    "C_LIGHT",
    "DEFAULT_MIN_DB",
    "DEFAULT_TOL_PX",
    "Geometry",
    "GeometryError",
    "ORDERS",
    "azimuth_shift_m",
    "azimuth_shift_s",
    "check_params",
    "effective_velocity_from_fm_rate",
    "flag_features",
    "geometry_from_attrs",
    "match_ambiguities",
    "range_shift_m",
    "range_spread_m",
    "tops_doppler_spread_hz",
]
