"""Upper-tail quantiles (inverse survival functions) of the F, Student-t and normal laws, from
``scipy.special`` alone.

The CFAR thresholds (``ca_cfar``, ``two_parameter``, and their per-pixel tables where rings are
incomplete, :mod:`sarship.pipeline.tiling.intensity_absent`) are these quantiles at the detector's PFA.
They are computed here from the special functions rather than through ``scipy.stats`` for two
reasons:

- accuracy in the far tail: ``F.isf`` as the regularised incomplete beta's complementary inverse
  is exact to a few ulp at every PFA, where ``scipy.stats.f.isf`` drifts (relative error 4e-13
  at PFA 1e-5 and 1.4e-9 at 1e-9 against the closed form of F(2, d2), measured with scipy 1.17);
- start-up: importing ``scipy.stats`` costs about 0.45 s of every ``sarship`` command on a
  2-core machine, ``scipy.special`` a fraction of that (issue 17's start-up budget).

Formulas (Abramowitz and Stegun 1964, 26.6.2 and 26.7.1; docs/references.md#abramowitz1964):

- F(d1, d2): ``P(F > x) = I_{d2/(d2 + d1 x)}(d2/2, d1/2) = 1 - I_z(d1/2, d2/2)`` with
  ``z = d1 x / (d1 x + d2)``, so ``z = betainccinv(d1/2, d2/2, p)`` and
  ``x = d2 z / (d1 (1 - z))`` (``z`` small in the tail: no cancellation);
- Student t with ``df`` degrees of freedom: ``isf(p) = -stdtrit(df, p)`` (symmetry; the
  lower-tail inverse keeps the precision of small ``p``);
- standard normal: ``isf(p) = -ndtri(p)``.
"""

from __future__ import annotations

from scipy import special


def f_isf(p: float, d1: float, d2: float) -> float:
    """``x`` with ``P(F(d1, d2) > x) = p`` (A&S 26.6.2)."""
    z = float(special.betainccinv(0.5 * d1, 0.5 * d2, p))
    return d2 * z / (d1 * (1.0 - z))


def t_isf(p: float, df: float) -> float:
    """``x`` with ``P(T_df > x) = p`` (A&S 26.7.1)."""
    return -float(special.stdtrit(df, p))


def norm_isf(p: float) -> float:
    """``x`` with ``P(N(0, 1) > x) = p``."""
    return -float(special.ndtri(p))
