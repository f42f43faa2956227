r"""Variational-Bayes PolSAR ship detection (``vb_polsar``), thesis appendix A.

Source: appendix A of Sun Tianyu's Tsinghua thesis (2020), a translated paper (eq A-1..A-27,
Algorithm 6); docs/algorithms/vb_polsar.md, bibliography in docs/references.md.

About 800 lines on purpose: the appendix's updates, their printed typos and what we did
about each sit beside the code that implements them (this docstring and the functions'),
because the maths cannot be checked against the paper without them; the detector's GPU pass
lives in :mod:`sarship.pipeline.gpu.polsar`.

Model (A-3..A-10)
-----------------
Pixel vector ``d`` = real and imaginary parts of the Pauli scattering vector (A-2, A-3):
quad-pol ``w = [HH + VV, HH - VV, 2 HV] / sqrt 2`` (D = 2d = 6 reals); dual-pol (our
extension) the two channels as they are, ``w = [S_1, S_2]`` (D = 4). ``SPAN = |d|^2``.
``D = A * D + C`` (A-5): a binary ship indicator ``a`` per pixel; the clutter vector is
``c = (1 - a) d``. Priors: ``a ~ Bernoulli(e)``, ``e ~ Beta(alpha0, beta0)`` per pixel
(A-6); ``c | z = k ~ N(u_k, M_k^{-1})`` with ``z ~ Cat(pi)`` (A-7), Gauss-Wishart
``(u_k, M_k) ~ N(u_0, (beta2 M_k)^{-1}) W(M_k | W_0, phi_0)`` (A-8), ``pi ~ Dir(eta_0)`` (A-9).

Notation below (Bishop 2006 sec. 10.2): the Gauss-Wishart posterior of component k has
``m_k, beta_k, W_k, nu_k`` and the Dirichlet posterior ``eta_k``; ``Ebar`` = posterior expectation:

    Ebar[(x - u_k)^T M_k (x - u_k)] = D / beta_k + nu_k (x - m_k)^T W_k (x - m_k)
    Ebar[ln |M_k|] = sum_{i=1..D} psi((nu_k + 1 - i) / 2) + D ln 2 + ln |W_k|
    Ebar[ln pi_k]  = psi(eta_k) - psi(sum_k eta_k)
    g_k(x) = Ebar[ln pi_k] + Ebar[ln|M_k|] / 2 - (D/2) ln(2 pi) - Ebar[(x - u_k)^T M_k (x - u_k)] / 2

``g0_k = g_k(d)`` (pixel is clutter, ``c = d``) and ``g1_k = g_k(0)`` (pixel is a ship,
``c = 0``: A-7 taken literally, the ship hypothesis has the clutter density at the origin).

Updates implemented (Ea = E[a], abar = 1 - Ea, rho_k = E[z_k])
-------------------------------------------------------------
* z, pi (A-22, A-23, A-25), with ``coupling="paper"`` (the factorisation A-15):
  ``ln rho_k = abar g0_k + Ea g1_k + const``, normalised over k (A-23 with
  E_a[(d - a d - u)^T M (d - a d - u)] for binary a; its "-3 ln 2 pi" is (D/2) ln 2 pi for
  D = 6). ``eta_k = eta0 + sum_ij rho_ijk (1 - Ea_ij)`` (A-25, see the deviation below).
* a, e (A-16..A-19). A-16/A-17 print a Gaussian q(a) (a relaxed to a real number) with
  precision ``Sigma_a = sum_k rho_k d^T E[M_k] d`` and mean
  ``Sigma_a^{-1} (sum_k rho_k d^T E[M_k](d - E u_k) + psi(alpha*) - psi(beta*))``. We keep a
  binary, as the model says (Bernoulli-Beta): the exact mean-field factor is Bernoulli with
  log-odds ``lambda = sum_k rho_k (g1_k - g0_k) + psi(alpha*) - psi(beta*)``, which is exactly
  ``Sigma_a (E_A17[a] - 1/2)`` (the log-ratio of A-16's Gaussian at a = 1 and a = 0, plus the
  ``D / beta_k`` terms A-17 drops), so ``Ea = sigmoid(lambda)``. A-17 also writes
  ``E(M_k)`` for the product ``E[M_k u_k]``; with the full Gauss-Wishart expectation this is
  ``nu_k W_k m_k``. With ``coupling="joint"`` (the default, see below) q(a, z) is one factor
  (a structured mean field, exact in (a, z) given the other factors):
  ``lambda = logsumexp_k g1_k - logsumexp_k g0_k + psi(alpha*) - psi(beta*)`` and the
  clutter responsibilities are ``q(z = k | a = 0) = softmax_k g0_k``.
  Then (A-18, A-19) ``alpha* = Ea + alpha0``, ``beta* = beta0 + 1 - Ea``. The digammas in
  the next a-update use these alpha*, beta*; the first a-update uses alpha*, beta* of the
  initial A (see the initialisation).
* u, M (A-20, A-21), with the VB-GMM weights ``r_k = rho_k (1 - Ea)``, ``N_k = sum r_k``,
  ``xbar_k``, ``S_k`` the weighted mean and covariance of d:
  ``beta_k = beta2 + N_k``, ``m_k = (beta2 u_0 + N_k xbar_k) / beta_k``,
  ``W_k^{-1} = W_0^{-1} + N_k S_k + beta2 N_k / (beta2 + N_k) (xbar_k - u_0)(xbar_k - u_0)^T``,
  ``nu_k = phi_0 + N_k``.
* Stopping (A-26): ``||E[A^t * D] - E[A^{t-1} * D]||_F / ||E[A^{t-1} * D]||_F < tol`` or
  ``max_iter`` iterations (the appendix: tol 1e-4, or simply 10 iterations, which it used).
* Decision (A-27): ``a_hat = 1`` where ``E[e] = alpha* / (alpha* + beta*) >= 0.5``, i.e.
  ``abar <= alpha0`` (computed so, without cancellation).

Typos and gaps of the appendix, and what we did
-----------------------------------------------
* A-21 as printed counts ship pixels with full weight in ``beta_k`` and ``phi_k`` and with a
  zero vector ``(1 - Ea) d`` in the mean; the Wishart scale update is missing. Counting ship
  pixels as clutter at the origin lets a component collapse on 0 (diverging precision, then
  N(0 | u_k, M_k^{-1}) makes every pixel a ship). We weight every clutter statistic by
  ``rho_k (1 - Ea)`` (the clutter responsibility), the standard VB-GMM update (Bishop 10.58-
  10.63). A-21's ``- beta2 u0k`` is ``+ beta2 u0k``; its ``phi_k = ... + 1`` is read as
  ``phi_0 + N_k`` (Bishop 10.63); ``Sigma_{u_k} = beta_k E(M_k)`` is the precision of u_k.
* A-25 likewise uses the clutter responsibilities ``rho (1 - Ea)``.
* Hyper-parameters (A.4.1): ``phi_0 = 6``, ``beta2 = eta0 = 1e-6``, ``alpha0 = 1e-3``,
  ``beta0 = 1 - alpha0``, K = 5, tol 1e-4 / 10 iterations. ``beta1 = 1e-6`` appears in
  Algorithm 6 but in no printed update: we read it as the Wishart prior scale,
  ``W_0^{-1} = beta1 s I`` with ``s`` the mean per-coordinate variance of the clutter sample
  (scale-free, negligible). ``u_0 = 0`` (circular clutter is zero-mean).
* Initialisation (A.4.1): pixels above the 85 % SPAN quantile start as ships (``Ea = 1``),
  the others as clutter (``Ea = 0``); the mixture is fitted to the initial clutter pixels
  (VB-GMM, K equal-count SPAN bins as the initial responsibilities, at most ``init_iter``
  iterations); z^0 is the A-23 update from A^0 instead of random indicator vectors (a random
  z^0 would make the result depend on a random draw and on the tiling).
* Per-pixel e (A-6) with a small alpha0 has the consequence that a pixel that starts as
  clutter can never become a ship (``psi(alpha0) ~ -1/alpha0``), and a pixel that starts as
  a ship stays one iff, at the fixed point, ``lambda >= L = ln((1 - alpha0)/alpha0)``: the
  decision is a threshold L on the log-odds, set by alpha0 (``alpha0 = expit(-L)``). With the
  appendix' 1e-3, L is ~6.9 nepers, i.e. ``d^T M d > 13.8`` for Gaussian clutter: about
  3 % of the initial ship pixels (0.5 % of the scene) are false alarms on our single-look
  simulated scenes. By default L is therefore set from ``pfa`` (next section);
  ``alpha0=0.001`` gives the appendix.

Decision threshold (``alpha0=None``: from ``pfa``)
--------------------------------------------------
What pass 2 thresholds is, up to ``O(alpha0 + e^-lambda)``, the fixed-point log-odds of a
pixel that starts as a ship (:func:`ship_log_odds`): ``lambda* = logsumexp_k g1_k -
logsumexp_k g0_k`` (joint; "paper": ``sum_k softmax(g1)_k (g1_k - g0_k)``) where SPAN >
t_init, -inf (never a ship) elsewhere; pass 2 detects exactly where ``lambda* >= L`` (tests
check it). ``calibration`` chooses L:

* ``"gaussian"`` (the previous default): ``L = chi2_D.isf(pfa) / 2``, the half Mahalanobis
  energy of Gaussian clutter exceeded with probability pfa. It assumes one Gaussian fitted
  to all the clutter, which is not what the model does: the mixture is fitted to the pixels
  below the 85 % SPAN quantile (the brighter ones start as ships and keep
  ``Ea = sigmoid(lambda*) ~ 1``, out of the clutter statistics), and the ship hypothesis of
  A-7 is the clutter density at the origin. Measured pixel false-alarm rates on pure clutter
  (quad-pol 1024 x 1024, pfa 1e-4): K clutter (texture shape 4, seeds 1-4) 155-205 x pfa,
  Rayleigh (seed 1) 7.6 x pfa; on the seed-5 K scene with ships, 4.5e-3 of the pixels at
  pfa 1e-6.
* ``"tail"`` (default): L from the scene's own clutter. ``reduce`` evaluates lambda* with the
  fitted global factors on a calibration sample (a second global grid, ``row, col %
  calibration_stride == 0``; default 4, i.e. 1/16 of the pixels, 65 536 values for a
  1024 x 1024 scene) and extrapolates its upper tail (:func:`tail_threshold`): the order
  statistics ``s_(k)`` of the n values, ``tail_trim * n < k <= 0.03 n``, are regressed on
  ``z_k = ln(n / (k - 1/2))`` (z = -ln of the survival) by ``s(z) = a + b (z - z0) +
  c (z - z0)^2`` (weights k, ``b, c >= 0``) and ``L = s(ln(1/pfa))``. c = 0 is an
  exponential tail (lambda* of Gaussian clutter is ~ chi2 / 2), c > 0 the stretched
  exponential ``z ~ 2 sqrt(nu x)`` of the quadratic form of compound-Gaussian (K) clutter,
  where lambda* grows like z^2. Ships: the top ``tail_trim`` (0.2 %) of the sample is left out
  of the fit, and the sample values above the fitted ``0.1 / n`` quantile are counted as
  outliers (m) and the fit repeated with clutter ranks ``k - m`` (at most twice); without
  this the ships' rank shift makes L far too high (0.1 % planted ships among 65 536 values of
  a chi2_6 / 2 or K-type tail: FAR 0.08-0.33 x pfa at 1e-4 instead of 0.57-1.44 x). More
  bright ship pixels than ``tail_trim`` in the sample make L conservative (raise
  ``tail_trim``, at most 1 %). ``pfa >= 0.03``: the sample quantile.
  Fewer than 50 points to fit: the Gaussian rule (the run's values record ``calibration``).
  A generalized Pareto fit above a 90-98 % quantile (trimmed at 99.9 %) was tried first: on
  1.6e4-6.5e4 values its shape parameter varies by 0.1-0.3 between sample offsets (FAR at
  pfa 1e-6 from 0 to 40 x pfa on one K scene), and on Rayleigh clutter it fits xi < 0 (the
  polynomial prefactor of chi2_6 / 2), extrapolating 3-220 x too many false alarms; an
  exponential tail (xi = 0) is 5-25 x anti-conservative on K clutter at 1e-6.

Measured accuracy of the tail rule (pixel FAR / pfa on pure quad-pol clutter):
1024 x 1024 scenes, pass 2's mask, pfa 1e-4: K shape 4, seeds 1-8: 0.31-1.97 (seeds 1-4
together 0.86); shape 1, seeds 1-4: 0.52-1.47; shape 10: 0.38-1.14; Rayleigh, seeds 1-3:
0.60-0.66; pfa 1e-5: K shape 4 0.29-4.7, Rayleigh 0.10-0.67. 4096 x 4096 scenes
(calibration sample 1 048 576), against the whole scene's lambda*, at pfa 1e-4 / 1e-5 /
1e-6: K shape 4 1.2 / 1.5 / 1.9, shape 1 1.0-1.2 / 0.9-1.3 / 1.0-1.6, shape 10 1.3 / 1.8 /
3.0, Rayleigh 0.6 / 0.5 / 0.3. So: within ~2 x of pfa where the sample sees the tail
(pfa >~ 10 / n), drifting to 2-5 x too many on K clutter (and too few on Gaussian clutter)
two to three decades beyond it (K 4096 x 4096 with 60 ships at pfa 1e-7: 8 false single
pixels of 16.7 M, ~5 x pfa).

Defaults ``pfa=1e-7, min_area_px=1, merge_px=6`` (previously ``pfa=1e-6, min_area_px=2,
merge_px=2``): on K clutter ships are found by a few bright
pixels (dominant scatterers) separated by dim single-look hull pixels; small ships (3-9 px)
show as one or two of them. With correctly calibrated thresholds (the clutter's own
quantiles, 1024 x 1024, 12 ships, SCR 10 dB, seeds 1-6 pooled) ``min_area_px=2`` caps the FoM
at 0.78 (merge 2) / 0.85 (merge 4) whatever the threshold, while ``min_area_px=1,
merge_px=6`` gives 0.91 at a clutter FAR of 1e-6 and 0.96 at L = 60-65 nepers (~1e-7); on
Rayleigh clutter 0.92 at 1e-6 and 1.0 below. With min_area_px 1 a false alarm is a clutter
pixel, so pfa x pixels is the expected number of false detections.

Measured with the defaults (SimConfig quad-pol 1024 x 1024, 12 ships, SCR 10 +- 2 dB,
end-to-end runs, FoM = hits / (false + ships)):

* K clutter (texture shape 4): quad-pol seeds 1-12 FoM 0.77-1.0 (10 of 12 >= 0.9; seed 5
  1.0), pooled 0.926 (Pd 0.958, 5 false alarms in 12 scenes); dual-pol (hh, hv) seeds 1-6
  0.69-1.0, pooled 0.905. Previous defaults (Gaussian rule, pfa 1e-6, min_area 2, merge 2),
  seed 5: FoM 0.026 (449 false alarms).
* Rayleigh clutter: quad-pol and dual-pol seeds 1-6: FoM 1.0.
* 4096 x 4096, 60 ships, seed 11: Rayleigh FoM 1.0 (60 / 60, no false alarm; previous
  defaults 0.918); K FoM 0.81 (Pd 0.92, the 8 false pixels above), at ``pfa=1e-8`` 0.885
  (Pd 0.90, 1 false). The missed ships have 3-8 px and peaks below the clutter's extremes.
  For large K scenes set a lower pfa.

Why ``coupling="joint"`` by default: with A-15's factorisation, a pixel that starts as a
ship gets z responsibilities evaluated at c = 0, i.e. on the narrowest clutter component, so
bright clutter is measured against the narrowest component. Under the Gaussian rule this
was decisive on K clutter (1024 x 1024, 12 ships, SCR 10 dB, seed 5, pfa 1e-6): "paper"
detected 146 313 px (FoM 0.003, Pd 0.25), "joint" 4 386 px (FoM 0.023, Pd 1.0); Rayleigh,
both FoM 1.0. With the tail calibration each coupling's own statistic is calibrated and
both reach the same pooled FoM on K seeds 1-6 (0.919; Rayleigh 1.0). "joint" stays the
default: it is the exact (a, z) update given the other factors, and its lambda* does not
depend on Ea.

Split between the scene-wide pass and the tiles
-----------------------------------------------
The model couples pixels only through the global factors (u, M, pi): given them, the
pixel factors q(a_ij), q(e_ij), q(z_ij) are independent (no spatial prior), so no halo is
needed (halo 0).

* Pass 1 (``scene_pass``, every tile): the vectors d of the pixels of a global grid
  ``row % sample_stride == 0 and col % sample_stride == 0`` (tiling-independent sample), and
  with the tail calibration the channels of the pixels of the ``calibration_stride`` grid.
* ``reduce`` (client): sort the sample by (row, col) (identical whatever the tiling), take the
  85 % SPAN quantile ``t_init``, fit the initial mixture to the clutter part, then run the
  whole-image VB of Algorithm 6 (A-16..A-25, stopping by A-26, at most ``max_iter``
  iterations) *on the sample*; the VB uses the Gaussian-rule alpha0 (or the given one). The
  factors do not depend on it in practice (pixels that start as ships keep
  ``Ea = sigmoid(lambda*)``; measured on the seed-5 scenes: the same mixture weights and L to
  0.01 nepers for alpha0 = 1e-3, the Gaussian rule's and 1e-26).
  Its global factors (m, beta, W, nu, eta) go into ``prep``, with alpha0 from the threshold
  L (the calibration sample, sorted by (row, col) too, so L is the same for any tiling).
* Pass 2 (``detect``, every tile): with the global factors fixed, per pixel: init from
  ``t_init``, then alternately A-22/23 (z) and A-16..A-19 (a, e) until the pixel's own A-26
  ratio ``|Ea^t - Ea^{t-1}| / Ea^{t-1}`` is below ``tol`` or ``max_iter`` iterations, then A-27.

Approximation relative to the whole-image VB: the global factors are estimated from a
``1 / sample_stride^2`` grid subsample (unbiased estimates of the whole-image sufficient
statistics, not the exact ones), and the A-26 criterion is applied per pixel in pass 2.
Given the same global factors, every pixel's result is a pure function of its own vector,
so tiled and untiled runs give identical masks (tests check it). Memory: a tile, its
outputs, and the samples: ``D + 2`` 8-byte numbers per pixel of the VB sample (16 MiB for
a 4096 x 4096 quad-pol scene with the default stride 8) and the complex channels plus an int32
(row, col) per pixel of the calibration sample (32 B for quad-pol: 2 B per scene pixel at
stride 4, 32 MiB for 4096 x 4096). Measured before the tail calibration (2-core machine,
LocalCluster of 4 single-thread workers, tile 1024, Rayleigh quad-pol 4096 x 4096, 60 ships,
SCR 10 dB, seed 11): whole run 16.1 s (scene pass + reduce 9.7 s, of which the VB on the
262 144-vector sample ~6 s; tiles 5.8 s = 2.9 Mpx/s); the per-pixel kernel alone runs at
~4.4 Mpx/s on one core. Peak RSS of one worker 358 MB, of all processes together 1.66 GB
against a 775 MB idle baseline (the scene as complex64 is 403 MB and is never held by one
process). The calibration adds, on that scene, ~2.8 s CPU in ``reduce`` (lambda* of
1 048 576 vectors, sort, fit) against ~27 s CPU of the VB measured alongside (the machine
was shared with another job then, so whole-run times were not re-measured); worker peak RSS
342-346 MB.

``stat`` = the final log-odds lambda of the pixel (>= the threshold L = ln((1-alpha0)/alpha0)
where detected; ``threshold`` and ``calibration`` are in the run's scene-pass values).

Absent pixels (no data; the appendix assumes a complete image). A pixel whose channels are
not all finite (NaN) or are all exactly 0 (no signal: a zero-filled border, a declared
no-data value of 0) is absent (:mod:`sarship.pipeline.tiling.polsar_absent`). It is left out of both
scene-wide samples (so ``t_init``, the mixture and the calibration tail are those of the
pixels with data: a zero border would otherwise add a cluster of vectors at the origin to the
clutter mixture, and one NaN makes every quantile NaN) and gets decision 0 and stat -inf in
pass 2 (zeroed before the per-pixel kernels, then overwritten). Pixels are independent given
the global factors (halo 0), so no per-pixel count is needed: a pixel with data next to an
absent region is processed exactly as anywhere else.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field
from scipy import special

from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec, with_defaults
from sarship.pipeline.gpu import is_device_array
from sarship.pipeline.tiling.polsar_absent import present, zero_absent

LN2PI = math.log(2.0 * math.pi)


class VBPolSARParams(with_defaults(DetectorParams, "VBPolSARDefaults", pfa=1e-7, min_area_px=1, merge_px=6)):
    """Parameters of ``vb_polsar``. ``target``/``guard``/``background`` are not used.

    Appendix values: K = 5, phi0 = 6, beta1 = beta2 = eta0 = 1e-6, alpha0 = 1e-3 (set
    ``alpha0=0.001``; the default derives it from ``pfa`` by ``calibration``, see the module
    docstring), init_quantile 0.85, tol 1e-4, max_iter 10.
    """

    components: int = Field(5, ge=1, le=16, description="K, Gaussian components of the clutter mixture")
    alpha0: float | None = Field(
        None, gt=0.0, lt=0.5, description="Beta prior alpha0 (beta0 = 1 - alpha0); None: from pfa by `calibration`"
    )
    calibration: Literal["tail", "gaussian"] = Field(
        "tail",
        description="alpha0=None: decision threshold from the sample's log-odds tail (default) "
        "or chi2_D.isf(pfa) / 2 (Gaussian clutter)",
    )
    tail_trim: float = Field(
        2e-3,
        ge=0.0,
        le=0.01,
        description="top fraction of the calibration sample's log-odds left out of the tail fit (ships)",
    )
    calibration_stride: int = Field(
        4, ge=1, le=256, description="tail calibration sample: pixels with row, col % stride == 0"
    )
    phi0: float = Field(6.0, gt=0.0, description="Wishart prior degrees of freedom (must exceed D - 1)")
    beta1: float = Field(1e-6, gt=0.0, description="Wishart prior scale W0^-1 = beta1 * s * I")
    beta2: float = Field(1e-6, gt=0.0, description="Gauss-Wishart prior precision scale of u_k")
    eta0: float = Field(1e-6, gt=0.0, description="Dirichlet prior of the mixture weights")
    init_quantile: float = Field(0.85, gt=0.0, lt=1.0, description="SPAN quantile above which pixels start as ships")
    tol: float = Field(1e-4, ge=0.0, description="A-26 relative-change threshold")
    max_iter: int = Field(10, ge=1, le=1000, description="most iterations of the VB loop")
    init_iter: int = Field(50, ge=1, le=10000, description="most VB-GMM iterations of the initial mixture fit")
    sample_stride: int = Field(8, ge=1, le=256, description="scene-wide sample: pixels with row, col % stride == 0")
    coupling: Literal["paper", "joint"] = Field(
        "joint", description="q(a, z) one factor (default), or q(a) q(z) factorised as A-15"
    )


def halo(p: VBPolSARParams) -> int:
    return 0


def prepare(p: VBPolSARParams) -> dict:
    return {"coupling": p.coupling}


def alpha0_of(p: VBPolSARParams, D: int) -> float:
    """alpha0 (given, or the Gaussian rule: ln((1 - a0) / a0) = chi2_D.isf(pfa) / 2).

    With ``calibration="tail"`` this is the alpha0 of the VB on the sample only; the decision
    threshold is then set by :func:`tail_threshold` in ``reduce``.
    """
    from scipy import stats  # lazy: importing scipy.stats costs every command start-up time

    if p.alpha0 is not None:
        return float(p.alpha0)
    return alpha0_of_threshold(0.5 * float(stats.chi2.isf(p.pfa, D)))


#: log-odds thresholds are kept in [MIN_THRESHOLD, MAX_THRESHOLD] nepers (alpha0 = expit(-L)
#: stays a positive normal double and below 1/2)
MIN_THRESHOLD, MAX_THRESHOLD = 1e-3, 700.0


def alpha0_of_threshold(L: float) -> float:
    """alpha0 whose A-27 decision ``abar <= alpha0`` is ``lambda >= L``: expit(-L)."""
    L = min(max(float(L), MIN_THRESHOLD), MAX_THRESHOLD)
    return float(special.expit(-L))


# --------------------------------------------------------------------------- calibration

#: the tail fit uses the sample's log-odds ranked between tail_trim * n and TAIL_FROM * n
TAIL_FROM = 0.03
#: fewest order statistics a tail fit is made from (else the Gaussian rule, recorded)
TAIL_MIN_POINTS = 50


def ship_log_odds(x: np.ndarray, span: np.ndarray, terms: dict, t_init: float, joint: bool) -> np.ndarray:
    """The log-odds the A-27 decision thresholds, for vectors x (n, D) and the fitted factors.

    A pixel that starts as clutter (SPAN <= t_init) is never a ship: -inf. One that starts as a
    ship keeps Ea ~ 1 while it stays one, so its fixed-point log-odds is the data term at
    Ea = 1 (joint: logsumexp g1 - logsumexp g0; paper: rho = softmax(g1) weighted g1 - g0) up to
    ``psi(1 + a0) - psi(1 - a0 + abar) = O(a0 + e^-lambda)``: pass 2 detects the pixel iff this
    is >= ln((1 - a0) / a0) (to that order).
    """
    g0 = log_terms(x, terms)
    g1 = terms["g1"]
    if joint:
        lam = _lse(g1[None, :])[0] - _lse(g0)
    else:
        w = np.exp(g1 - _lse(g1[None, :])[0])
        lam = ((g1[None, :] - g0) * w[None, :]).sum(1)
    return np.where(span > t_init, lam, -np.inf)


def tail_threshold(s: np.ndarray, pfa: float, trim: float = 2e-3, top: float = TAIL_FROM) -> dict | None:
    """Threshold L with P(s >= L) ~ pfa, from the upper tail of the sample s (None: too few).

    Quantile regression in z = -ln(survival): the order statistics ``s_(k)`` (k-th largest of
    n, ``trim * n < k <= top * n``, finite) against ``z_k = ln(n / (k - 1/2))`` are fitted by
    ``s(z) = a + b (z - z0) + c (z - z0)^2`` (z0 = ln(1/top); least squares weighted by k,
    ~ 1 / Var s_(k); ``b, c >= 0``), and ``L = s(ln(1/pfa))``. c = 0 is an exponential tail
    (the log-odds of Gaussian clutter, ~ chi2 / 2), c > 0 a stretched exponential z ~ sqrt(s),
    the tail of a quadratic form of compound-Gaussian (K) clutter, P(T G > x) ~
    exp(-2 sqrt(nu x)). Outliers (ships): the ``m`` values above the fitted ``0.1 / n``
    quantile (0.1 expected from clutter) shift the clutter's ranks, so the fit is repeated
    with ranks ``k - m`` (``OUTLIER_PASSES`` times at most, until m is stable); the trim keeps
    the brightest values out of the fit. ``pfa >= top``: the sample's own quantile. Returns
    the threshold, the coefficients, ``outliers`` = m and the number of fitted points.
    """
    s = np.asarray(s, float)
    n = s.size
    ss = -np.sort(-s)
    n_fin = int(np.isfinite(ss).sum())
    if n == 0 or n_fin == 0:
        return None
    if pfa >= top:
        k = min(max(math.ceil(pfa * n), 1), n_fin)
        return {"threshold": float(ss[k - 1]), "model": "empirical", "n": int(n)}
    k_hi = min(round(top * n), n_fin)
    k_lo = round(trim * n)
    z0 = math.log(1.0 / top)
    m = 0
    for _ in range(1 + OUTLIER_PASSES):
        lo = max(k_lo, m)
        if k_hi - lo < TAIL_MIN_POINTS:
            return None
        coef = _tail_fit(ss, n - m, lo, k_hi, m, z0)
        if coef is None:
            return None
        # sample points above the model's 1/(10 n) quantile (0.1 expected from clutter) are
        # outliers (ships): they shift the clutter ranks below them, refit with k - m
        m_new = int((ss > _tail_quantile(coef, z0, 0.1 / n)).sum())
        if m_new == m:
            break
        m = m_new
    L = _tail_quantile(coef, z0, pfa)
    return {
        "threshold": L,
        "model": "quadratic" if coef[2] > 0 else "exponential",
        "coef": [float(c) for c in coef],
        "z0": z0,
        "n": int(n),
        "points": int(k_hi - max(k_lo, m)),
        "outliers": int(m),
    }


#: refits of the tail with the outliers' rank shift removed
OUTLIER_PASSES = 2


def _tail_fit(ss: np.ndarray, n: int, lo: int, hi: int, m: int, z0: float) -> np.ndarray | None:
    """Weighted least squares of s_(k) on z = ln(n / (k - m - 1/2)), lo < k <= hi."""
    from scipy import optimize  # lazy: importing scipy.optimize costs every command start-up time

    k = np.arange(lo + 1, hi + 1)
    t = ss[k - 1]
    kc = (k - m).astype(float)
    dz = np.log(n / (kc - 0.5)) - z0
    sw = np.sqrt(kc)
    A = np.stack([np.ones_like(dz), dz, dz * dz], 1) * sw[:, None]
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(t)):
        return None
    # b, c >= 0: the quantile function increases and is convex in z (exponential to K tails)
    coef = optimize.lsq_linear(A, t * sw, bounds=([-np.inf, 0.0, 0.0], [np.inf, np.inf, np.inf]), method="bvls").x
    if not np.all(np.isfinite(coef)) or coef[1] + coef[2] <= 0.0:
        return None
    return coef


def _tail_quantile(coef: np.ndarray, z0: float, p: float) -> float:
    zs = math.log(1.0 / p) - z0
    return float(coef[0] + coef[1] * zs + coef[2] * zs * zs)


# --------------------------------------------------------------------------- vectors


def pauli_vectors(x: np.ndarray) -> np.ndarray:
    """Real 2d-vectors d (A-2, A-3) of complex channels ``(..., p)``, float64 ``(..., 2p)``.

    p = 3 ([hh, hv, vv]): Pauli ``[hh + vv, hh - vv, 2 hv] / sqrt 2``; p = 2: the channels.
    """
    x = np.asarray(x)
    if x.shape[-1] == 3:
        hh = x[..., 0].astype(np.complex128)
        hv = x[..., 1].astype(np.complex128)
        vv = x[..., 2].astype(np.complex128)
        s = 1.0 / math.sqrt(2.0)
        w = np.stack([(hh + vv) * s, (hh - vv) * s, 2.0 * hv * s], -1)
    elif x.shape[-1] == 2:
        w = x.astype(np.complex128)
    else:
        raise ValueError("vb_polsar needs 2 (dual-pol) or 3 (quad-pol [hh, hv, vv]) complex channels")
    out = np.empty(w.shape[:-1] + (2 * w.shape[-1],))
    out[..., 0::2] = w.real
    out[..., 1::2] = w.imag
    return out


# --------------------------------------------------------------------------- mixture


def _digamma_sum(nu: np.ndarray, D: int) -> np.ndarray:
    return sum(special.digamma((nu + 1.0 - i) / 2.0) for i in range(1, D + 1))


def mixture_terms(mix: dict) -> dict:
    """Per-component constants of g_k(x): c_k and the quadratic (nu_k W_k, m_k)."""
    m = np.asarray(mix["m"], float)
    W = np.asarray(mix["W"], float)
    nu = np.asarray(mix["nu"], float)
    beta = np.asarray(mix["beta"], float)
    eta = np.asarray(mix["eta"], float)
    K, D = m.shape
    logdetW = np.array([np.linalg.slogdet(W[k])[1] for k in range(K)])
    elogdet = _digamma_sum(nu, D) + D * math.log(2.0) + logdetW
    elogpi = special.digamma(eta) - special.digamma(eta.sum())
    c = elogpi + 0.5 * elogdet - 0.5 * D * LN2PI - 0.5 * D / beta
    P = nu[:, None, None] * W  # E[M_k]
    g1 = c - 0.5 * np.einsum("ki,kij,kj->k", m, P, m)
    return {"c": c, "P": P, "m": m, "g1": g1, "elogpi": elogpi, "elogdet": elogdet}


def log_terms(x: np.ndarray, terms: dict) -> np.ndarray:
    """g0 = g_k(d) for vectors ``x`` (n, D): (n, K)."""
    K = terms["m"].shape[0]
    out = np.empty((x.shape[0], K))
    for k in range(K):
        diff = x - terms["m"][k]
        out[:, k] = terms["c"][k] - 0.5 * ((diff @ terms["P"][k]) * diff).sum(1)
    return out


def _lse(a: np.ndarray, axis: int = -1) -> np.ndarray:
    mx = a.max(axis=axis, keepdims=True)
    return (mx + np.log(np.exp(a - mx).sum(axis=axis, keepdims=True))).squeeze(axis)


def update_gw(x: np.ndarray, r: np.ndarray, hyper: dict) -> dict:
    """Gauss-Wishart and Dirichlet posteriors (A-21, A-25 as derived) from weights r (n, K)."""
    n, D = x.shape
    Nk = r.sum(0)
    K = r.shape[1]
    u0 = np.zeros(D)
    W0inv = hyper["W0inv"]
    b2 = hyper["beta2"]
    m = np.empty((K, D))
    W = np.empty((K, D, D))
    for k in range(K):
        if Nk[k] > 0:
            xb = (r[:, k] @ x) / Nk[k]
            dx = x - xb
            S = (dx * r[:, k, None]).T @ dx / Nk[k]
        else:
            xb = np.zeros(D)
            S = np.zeros((D, D))
        beta_k = b2 + Nk[k]
        m[k] = (b2 * u0 + Nk[k] * xb) / beta_k
        e = xb - u0
        Winv = W0inv + Nk[k] * S + (b2 * Nk[k] / beta_k) * np.outer(e, e)
        Winv = 0.5 * (Winv + Winv.T)
        W[k] = np.linalg.inv(Winv)
    return {"m": m, "W": W, "nu": hyper["phi0"] + Nk, "beta": b2 + Nk, "eta": hyper["eta0"] + Nk}


def _init_resp(span: np.ndarray, K: int) -> np.ndarray:
    """K equal-count SPAN bins as initial responsibilities (deterministic)."""
    n = span.size
    order = np.argsort(span, kind="stable")
    lab = np.empty(n, np.int64)
    lab[order] = (np.arange(n) * K) // max(n, 1)
    r = np.zeros((n, K))
    r[np.arange(n), lab] = 1.0
    return r


def hyper_of(x_clutter: np.ndarray, p: VBPolSARParams) -> dict:
    D = x_clutter.shape[1]
    s = float(np.mean(x_clutter**2)) if x_clutter.size else 1.0
    s = s if s > 0 else 1.0
    return {"W0inv": p.beta1 * s * np.eye(D), "beta2": p.beta2, "phi0": p.phi0, "eta0": p.eta0}


def fit_vbgmm(
    x: np.ndarray,
    K: int,
    hyper: dict,
    weights: np.ndarray | None = None,
    max_iter: int = 100,
    tol: float = 1e-5,
    resp: np.ndarray | None = None,
) -> dict:
    """Variational Bayes Gaussian mixture (Gauss-Wishart, Dirichlet) of weighted vectors x."""
    w = np.ones(len(x)) if weights is None else np.asarray(weights, float)
    r = _init_resp((x**2).sum(1), K) if resp is None else resp
    mix = update_gw(x, r * w[:, None], hyper)
    prev = None
    for _ in range(max_iter):
        g0 = log_terms(x, mixture_terms(mix))
        r = np.exp(g0 - _lse(g0)[:, None])
        mix = update_gw(x, r * w[:, None], hyper)
        nk = mix["eta"]
        if prev is not None and np.max(np.abs(nk - prev)) <= tol * max(w.sum(), 1.0):
            break
        prev = nk
    return mix


# --------------------------------------------------------------------------- per-pixel updates


def _ea_update(lam0: np.ndarray, ea: np.ndarray, ab: np.ndarray, a0: float, b0: float):
    """A-17..A-19 (Bernoulli form): new Ea, abar and log-odds from the data term lam0."""
    lam = lam0 + special.digamma(ea + a0) - special.digamma(b0 + ab)
    return special.expit(lam), special.expit(-lam), lam


def _data_term(g0: np.ndarray, g1: np.ndarray, ea: np.ndarray, ab: np.ndarray, joint: bool):
    """(lam0, rho): the data part of the a log-odds, and E[z] (A-23)."""
    if joint:
        lg0 = _lse(g0)
        lg1 = _lse(np.broadcast_to(g1, g0.shape))
        rho = np.exp(g0 - lg0[:, None])  # q(z | a = 0): the clutter statistics' weights
        return lg1 - lg0, rho
    s = ab[:, None] * g0 + ea[:, None] * g1[None, :]
    rho = np.exp(s - _lse(s)[:, None])
    return (rho * (g1[None, :] - g0)).sum(1), rho


def vb_sample(x: np.ndarray, span: np.ndarray, p: VBPolSARParams) -> dict:
    """Algorithm 6 on vectors x (n, D): initial mixture, then A-16..A-25 until A-26."""
    n, D = x.shape
    a0 = alpha0_of(p, D)
    b0 = 1.0 - a0
    t_init = float(np.quantile(span, p.init_quantile)) if n else 0.0
    ship0 = span > t_init
    ea = ship0.astype(float)
    ab = 1.0 - ea
    xc = x[~ship0]
    hyper = hyper_of(xc, p)
    mix = fit_vbgmm(xc, p.components, hyper, max_iter=p.init_iter)
    joint = p.coupling == "joint"
    iters, thr = 0, float("nan")
    norms = np.sqrt((x**2).sum(1))
    for it in range(p.max_iter):
        terms = mixture_terms(mix)
        g0 = log_terms(x, terms)
        # z from the current A (A-22/23), then a, e (A-16..A-19)
        _, rho = _data_term(g0, terms["g1"], ea, ab, joint)
        if joint:
            lam0, _ = _data_term(g0, terms["g1"], ea, ab, True)
        else:
            lam0 = (rho * (terms["g1"][None, :] - g0)).sum(1)
        ea_new, ab_new, _ = _ea_update(lam0, ea, ab, a0, b0)
        # u, M, pi with the clutter responsibilities
        g0n = g0
        _, rho = _data_term(g0n, terms["g1"], ea_new, ab_new, joint)
        mix = update_gw(x, rho * ab_new[:, None], hyper)
        den = float(np.sqrt(((ea * norms) ** 2).sum()))
        thr = float(np.sqrt((((ea_new - ea) * norms) ** 2).sum())) / den if den > 0 else 0.0
        ea, ab = ea_new, ab_new
        iters = it + 1
        if thr < p.tol:
            break
    return {
        "mix": mix,
        "t_init": t_init,
        "alpha0": a0,
        "beta0": b0,
        "iterations": iters,
        "a26": thr,
        "n_sample": int(n),
        "sample_ship_fraction": float((ab <= a0).mean()) if n else 0.0,
    }


@njit(nogil=True, cache=True)
def _digamma(x):
    r = 0.0
    while x < 6.0:
        r -= 1.0 / x
        x += 1.0
    f = 1.0 / (x * x)
    return r + math.log(x) - 0.5 / x - f * (1.0 / 12 - f * (1.0 / 120 - f * (1.0 / 252 - f * (1.0 / 240 - f / 132))))


@njit(nogil=True, cache=True)
def _expit(v):
    if v >= 0:
        return 1.0 / (1.0 + math.exp(-v))
    e = math.exp(v)
    return e / (1.0 + e)


@njit(nogil=True, cache=True)
def _pixels(X, c, P, m, g1, t_init, a0, b0, max_iter, tol, joint, mask, stat):
    """Pass 2 per pixel: init from SPAN, then A-22/23 and A-16..A-19 to A-26, then A-27."""
    h, w, p = X.shape
    K, D = m.shape
    d = np.empty(D)
    g0 = np.empty(K)
    rho = np.empty(K)
    s2 = 1.0 / math.sqrt(2.0)
    for i in range(h):
        for j in range(w):
            if p == 3:
                hh = complex(X[i, j, 0])
                hv = complex(X[i, j, 1])
                vv = complex(X[i, j, 2])
                w0 = (hh + vv) * s2
                w1 = (hh - vv) * s2
                w2 = 2.0 * hv * s2
                d[0] = w0.real
                d[1] = w0.imag
                d[2] = w1.real
                d[3] = w1.imag
                d[4] = w2.real
                d[5] = w2.imag
            else:
                for t in range(p):
                    v = complex(X[i, j, t])
                    d[2 * t] = v.real
                    d[2 * t + 1] = v.imag
            span = 0.0
            for t in range(D):
                span += d[t] * d[t]
            for k in range(K):
                q = 0.0
                for a in range(D):
                    da = d[a] - m[k, a]
                    for b in range(D):
                        q += da * P[k, a, b] * (d[b] - m[k, b])
                g0[k] = c[k] - 0.5 * q
            if span > t_init:
                ea, ab = 1.0, 0.0
            else:
                ea, ab = 0.0, 1.0
            lam = 0.0
            lam0 = 0.0
            if joint:
                mx0 = g0[0]
                mx1 = g1[0]
                for k in range(1, K):
                    mx0 = max(mx0, g0[k])
                    mx1 = max(mx1, g1[k])
                s0 = 0.0
                s1 = 0.0
                for k in range(K):
                    s0 += math.exp(g0[k] - mx0)
                    s1 += math.exp(g1[k] - mx1)
                lam0 = (mx1 + math.log(s1)) - (mx0 + math.log(s0))
            for _it in range(max_iter):
                if not joint:
                    mx = -1e300
                    for k in range(K):
                        rho[k] = ab * g0[k] + ea * g1[k]
                        mx = max(mx, rho[k])
                    s = 0.0
                    for k in range(K):
                        rho[k] = math.exp(rho[k] - mx)
                        s += rho[k]
                    lam0 = 0.0
                    for k in range(K):
                        lam0 += rho[k] / s * (g1[k] - g0[k])
                lam = lam0 + _digamma(ea + a0) - _digamma(b0 + ab)
                ea_n = _expit(lam)
                ab_n = _expit(-lam)
                dlt = abs(ea_n - ea)
                conv = dlt == 0.0 or dlt <= tol * ea
                ea, ab = ea_n, ab_n
                if conv:
                    break
            mask[i, j] = ab <= a0
            stat[i, j] = lam


# --------------------------------------------------------------------------- two passes


def _grid(n0: int, n: int, s: int) -> np.ndarray:
    first = (-n0) % s
    return np.arange(first, n, s)


def _grid_values(core, r0: int, c0: int, s: int, ok=None):
    """The grid pixels' channels ``(n, p)`` and global (row, col) ``(n, 2)``; absent pixels
    (``ok`` False) are left out."""
    ri = _grid(r0, core.shape[0], s)
    ci = _grid(c0, core.shape[1], s)
    rr, cc = np.meshgrid(ri + r0, ci + c0, indexing="ij")
    v = core[np.ix_(ri, ci)].reshape(-1, core.shape[2])
    rc = np.stack([rr.ravel(), cc.ravel()], 1)
    if ok is not None:
        keep = ok[np.ix_(ri, ci)].ravel()
        v, rc = v[keep], rc[keep]
    return v, rc


def scene_pass(block, halo_px, origin, p: VBPolSARParams, prep: dict) -> dict:
    """The tile's share of the scene-wide samples (global grids): the VB sample (d, on the
    ``sample_stride`` grid) and the calibration sample (the channels, on the
    ``calibration_stride`` grid; only with the tail calibration). Absent pixels
    (:func:`~sarship.pipeline.tiling.polsar_absent.present`) are in neither sample."""
    x = np.asarray(block)
    if x.ndim != 3 or x.shape[2] not in (2, 3):
        raise ValueError("vb_polsar needs a (rows, cols, 2 or 3) block of complex channels")
    hp = int(halo_px)
    core = x[hp : x.shape[0] - hp, hp : x.shape[1] - hp]
    r0, c0 = origin[0] + hp, origin[1] + hp
    ok = present(core)
    sub, rc = _grid_values(core, r0, c0, p.sample_stride, ok)
    out = {"rc": rc.astype(np.int64), "d": pauli_vectors(sub).reshape(-1, 2 * x.shape[2])}
    if _tail_calibrated(p):
        sub, rc = _grid_values(core, r0, c0, p.calibration_stride, ok)
        out["cal_rc"] = rc.astype(np.int32)
        out["cal"] = np.ascontiguousarray(sub.reshape(-1, x.shape[2]))
    return out


def _tail_calibrated(p: VBPolSARParams) -> bool:
    return p.alpha0 is None and p.calibration == "tail"


def _sorted(parts: list[dict], rc_key: str, key: str) -> np.ndarray:
    """Pool the parts' rows, sorted by global (row, col): the same array whatever the tiling."""
    rc = np.concatenate([q[rc_key] for q in parts])
    v = np.concatenate([q[key] for q in parts])
    return v[np.lexsort((rc[:, 1], rc[:, 0]))]


def reduce(parts: list[dict], p: VBPolSARParams, prep: dict) -> dict:
    """Pool the sample (sorted by global position), run Algorithm 6 on it: global factors;
    then the decision threshold (alpha0) from the calibration sample's log-odds tail."""
    d = _sorted(parts, "rc", "d")
    if len(d) < 2 * p.components:
        raise ValueError(f"vb_polsar: {len(d)} sampled pixels (with data) are too few; lower sample_stride")
    span = (d**2).sum(1)
    res = vb_sample(d, span, p)
    mix = res.pop("mix")
    terms = mixture_terms(mix)
    joint = p.coupling == "joint"
    if p.alpha0 is not None:
        rule = "alpha0"
    elif p.calibration == "gaussian":
        rule = "gaussian"
    else:
        xc = pauli_vectors(_sorted(parts, "cal_rc", "cal"))
        s = ship_log_odds(xc, (xc**2).sum(1), terms, res["t_init"], joint)
        cal = tail_threshold(s, p.pfa, p.tail_trim)
        if cal is None:
            rule = "gaussian (calibration sample too small for the tail fit)"
        else:
            rule = "tail"
            a0 = alpha0_of_threshold(cal["threshold"])
            res.update(alpha0=a0, beta0=1.0 - a0, tail=cal)
    L = math.log1p(-res["alpha0"]) - math.log(res["alpha0"])
    # fraction of the VB sample that pass 2 flags (s >= L; ships included)
    s = ship_log_odds(d, span, terms, res["t_init"], joint)
    res.update(calibration=rule, threshold=L, sample_ship_fraction=float((s >= L).mean()))
    return {**res, "mixture": {k: np.asarray(v).tolist() for k, v in mix.items()}}


def detect(block, halo_px, origin, p: VBPolSARParams, prep: dict):
    """Per-pixel VB updates with the scene-wide mixture; A-27 decision.

    A CuPy ``block`` runs the same updates on its GPU (:func:`sarship.pipeline.gpu.polsar.vb_pixels`;
    the scene pass, a grid sample, stays on the host) and returns CuPy arrays. Absent pixels
    (:func:`~sarship.pipeline.tiling.polsar_absent.present`) are zeroed for the kernels and then
    set to mask 0, stat -inf, on both paths.
    """
    if "mixture" not in prep:
        raise ValueError("vb_polsar needs the scene-wide mixture (run its scene pass first)")
    x = block if is_device_array(block) else np.asarray(block)
    if x.ndim != 3 or x.shape[2] not in (2, 3):
        raise ValueError("vb_polsar needs a (rows, cols, 2 or 3) block of complex channels")
    hp = int(halo_px)
    core = x[hp : x.shape[0] - hp, hp : x.shape[1] - hp]
    if not is_device_array(core):
        core = np.ascontiguousarray(core)
    terms = mixture_terms(prep["mixture"])
    if terms["m"].shape[1] != 2 * x.shape[2]:
        raise ValueError("vb_polsar: the mixture's dimension does not match the block's channels")
    ok = present(core)
    complete = bool(ok.all())
    core = zero_absent(core, ok)
    if is_device_array(core):  # CuPy block: the same per-pixel updates on its GPU
        mask, stat = SPEC.twin()(
            core,
            terms["c"],
            terms["P"],
            terms["m"],
            terms["g1"],
            float(prep["t_init"]),
            float(prep["alpha0"]),
            float(prep["beta0"]),
            int(p.max_iter),
            float(p.tol),
            p.coupling == "joint",
        )
    else:
        h, w = core.shape[:2]
        mask = np.zeros((h, w), np.bool_)
        stat = np.zeros((h, w), np.float32)
        _pixels(
            np.ascontiguousarray(core),
            terms["c"],
            np.ascontiguousarray(terms["P"]),
            terms["m"],
            terms["g1"],
            float(prep["t_init"]),
            float(prep["alpha0"]),
            float(prep["beta0"]),
            int(p.max_iter),
            float(p.tol),
            p.coupling == "joint",
            mask,
            stat,
        )
    if not complete:  # absent pixels: never ships (log-odds -inf, as ship_log_odds' never-ships)
        mask &= ok
        stat[~ok] = -np.inf
    return mask, stat


SPEC = DetectorSpec(
    name="vb_polsar",
    summary="Variational-Bayes PolSAR ship detection: D = A*D + C, Beta-Bernoulli ships, VB-GMM clutter",
    reference="Sun 2020 (Tsinghua thesis) appendix A (translated paper), eq A-1..A-27, Algorithm 6; "
    "docs/algorithms/vb_polsar.md",
    params=VBPolSARParams,
    prepare=prepare,
    detect=detect,
    input="polarimetric",
    covariance=False,  # its mixture is over the complex channels of each pixel, not a covariance
    needs_looks=False,
    scene_pass=scene_pass,
    reduce=reduce,
    halo_fn=halo,
    halo_rule="0 (pixels are independent given the scene-wide mixture)",
    gpu="sarship.pipeline.gpu.polsar:vb_pixels",
    scene_pass_gpu=False,
)
