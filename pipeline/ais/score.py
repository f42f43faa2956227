"""The score of a (detection, AIS vessel) pair: how probable a residual at least this large is
for a true pair (docs/ais.md, "Matching").

The residual is 2-D (position, metres) plus 1-D where both lengths are known (the log length
ratio). For a true pair it is a zero-mean Gaussian with covariance::

    Sigma = a I + b u u^T                                                 (1)
    a = sigma_geo^2 + (sigma_rate gap)^2 + (|v| sigma_turn gap^2 / 2)^2 + (f_ref L)^2
        + (|v| sigma_t)^2  [+ (|v| R/V)^2 / 2]
    b = (R / V)^2 sigma_los^2,  sigma_los^2 = sin^2(theta_i) (sigma_sog^2 (v^ . u_r)^2
                                             + |v|^2 sigma_cog^2 (v^_perp . u_r)^2)

(``u`` the flight direction: the displacement's own error lies along it; ``sigma_rate gap``: an
error growing linearly with the gap to the nearest report; ``|v| sigma_turn gap^2 / 2``: a
manoeuvre since that report, an unknown turn at rate ``omega`` (rad/s) moving a ship at speed
``|v|`` sideways by ``|v| omega gap^2 / 2`` (a relative change of speed at the same rate moves it
as far along its course), :func:`manoeuvre_sigma_m`; ``f_ref L``: the AIS antenna's unknown
place along a hull of length ``L``, uniform, ``f_ref = 1/sqrt(12)``; ``|v| sigma_t``: a detection
time known to ``sigma_t``; the bracketed term only where the scene has no look geometry, the
displacement's mean square over an unknown look direction). Its squared
Mahalanobis distance, with ``Sigma^-1 = (I - b/(a+b) u u^T) / a``::

    d2 = (|r|^2 - b/(a+b) (r . u)^2) / a  +  z^2,   z = ln(L_det / L_ais) / sigma_len    (2)

is chi-square with ``k = 2`` degrees of freedom (``k = 3`` with the length term), and the score
is its survival function::

    score = Q(k/2, d2/2)     (k = 2: exp(-d2/2))                                         (3)

([barshalom2001] on chi-square validation gates; ``Q`` the regularised upper incomplete gamma
function). A true pair's score is uniform on (0, 1): ``min_score = 0.01`` refuses 1 % of true
pairs. (The product of the position term's ``exp(-d2_pos/2)`` and the length term's two-sided
p-value ``erfc(|z|/sqrt 2)`` is not uniform: it would refuse ``a (1 - ln a)`` = 5.6 % of true
pairs at ``a = 0.01``; the joint chi-square keeps the stated meaning.)
"""

from __future__ import annotations

import numpy as np
from scipy.special import gammaincc, gammainccinv

#: the AIS antenna's spread along a hull of length L, as a fraction of L: uniform over the hull
REF_POINT_FRACTION = 1.0 / np.sqrt(12.0)


def chi2_sf(d2: np.ndarray, k: np.ndarray | int) -> np.ndarray:
    """Survival function of chi-square with ``k`` degrees of freedom at ``d2`` (eq. 3)."""
    return gammaincc(np.asarray(k, np.float64) / 2.0, np.asarray(d2, np.float64) / 2.0)


def chi2_isf(p: float, k: int) -> float:
    """The ``d2`` whose chi-square(k) survival is ``p`` (the gate of a score threshold)."""
    return float(2.0 * gammainccinv(k / 2.0, p))


def mahalanobis2(
    re: np.ndarray, rn: np.ndarray, a: np.ndarray, b: np.ndarray, ue: np.ndarray, un: np.ndarray
) -> np.ndarray:
    """``r^T Sigma^-1 r`` for ``Sigma = a I + b u u^T`` (eq. 2's first term; ``u`` unit, ``b >= 0``).

    Parameters
    ----------
    re, rn : np.ndarray
        Residual east/north, metres.
    a, b : np.ndarray
        Isotropic and along-``u`` variances, m^2.
    ue, un : np.ndarray
        The unit vector ``u`` (ignored where ``b == 0``).

    Returns
    -------
    np.ndarray
        Squared Mahalanobis distance.
    """
    ru = re * np.nan_to_num(ue) + rn * np.nan_to_num(un)
    return (re * re + rn * rn - b / (a + b) * ru * ru) / a


def los_velocity_variance(
    v_east: np.ndarray,
    v_north: np.ndarray,
    range_east: np.ndarray,
    range_north: np.ndarray,
    sin_incidence: np.ndarray,
    sigma_sog_m_s: float,
    sigma_cog_rad: float,
) -> np.ndarray:
    """Variance of the line-of-sight velocity from SOG and COG errors (eq. 1's ``sigma_los^2``):
    the speed error along the course, the course error across it, both projected on the range
    direction; ``sigma_sog^2 / 2`` (any direction) for a vessel at rest."""
    speed = np.hypot(v_east, v_north)
    moving = speed > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        he, hn = np.where(moving, v_east / speed, 0.0), np.where(moving, v_north / speed, 0.0)
    along = he * range_east + hn * range_north
    across = -hn * range_east + he * range_north
    var = sigma_sog_m_s**2 * along**2 + (speed * sigma_cog_rad) ** 2 * across**2
    var = np.where(moving, var, 0.5 * sigma_sog_m_s**2)
    return np.asarray(sin_incidence) ** 2 * var


def manoeuvre_sigma_m(speed_m_s: np.ndarray, gap_s: np.ndarray, sigma_turn_rad_s: float) -> np.ndarray:
    """The position error (m, per axis) of a manoeuvre since the nearest report (eq. 1): a ship at
    ``speed_m_s`` turning at an unknown rate of standard deviation ``sigma_turn_rad_s`` for
    ``gap_s`` seconds is ``|v| omega gap^2 / 2`` off its straight track (small angles), growing
    with the square of the gap and with the speed (a ship at rest does not manoeuvre away).

    Parameters
    ----------
    speed_m_s : np.ndarray
        Speed over ground, m/s (NaN counts as 0).
    gap_s : np.ndarray
        Time from the nearest report, s.
    sigma_turn_rad_s : float
        Standard deviation of the unknown turn rate, rad/s.

    Returns
    -------
    np.ndarray
        ``|v| sigma_turn gap^2 / 2``, m.
    """
    return 0.5 * np.nan_to_num(np.asarray(speed_m_s, np.float64)) * sigma_turn_rad_s * np.square(gap_s)


def length_z2(det_length_m: np.ndarray, ais_length_m: np.ndarray, sigma_log: float) -> np.ndarray:
    """``z^2`` of eq. 2 where both lengths are known and positive, NaN elsewhere."""
    ld, la = np.asarray(det_length_m, np.float64), np.asarray(ais_length_m, np.float64)
    ok = (ld > 0) & (la > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.log(np.where(ok, ld, 1.0) / np.where(ok, la, 1.0)) / sigma_log
    return np.where(ok, z * z, np.nan)


__all__ = [
    "REF_POINT_FRACTION",
    "chi2_isf",
    "chi2_sf",
    "length_z2",
    "los_velocity_variance",
    "mahalanobis2",
    "manoeuvre_sigma_m",
]
