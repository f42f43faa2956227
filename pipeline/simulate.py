"""Simulated SAR scenes with ground truth: clutter, ships, land and sensor artefacts.

The simulator writes scenes of the CONTRACT scene store (``intensity``, ``slc`` with ``hh``,
``quadpol`` with ``hh``, ``hv``, ``vv``) and a truth GeoJSON of the same schema as the
detections, for tests, demos and benchmarks of the detectors (up to 65536 px a side).

Tiling independence
-------------------
Every pixel is a pure function of ``(config, row, col)``. All randomness is drawn on a fixed
grid of :data:`BLOCK` x :data:`BLOCK` pixel blocks in global scene coordinates, each block
from its own ``numpy.random.default_rng(SeedSequence([tag, seed, stream, block_i, block_j]))``,
and a block is always rendered whole (then cropped), so :func:`simulate_tile` returns
bit-identical pixels however a scene is cut into requests. Spatially correlated fields
(K texture, land fields) interpolate globally seeded coarse node grids (node blocks keyed
the same way); ships, sidelobes, ghosts, RFI and stripes come from a scene model built once
per configuration (:func:`ship_catalogue`) from their own seeded streams. Each component has
its own stream, so switching an option on (``land``, ``rfi``, ...) does not change the sea
speckle. (Ship positions do change when ``land`` is switched on, since ships avoid land.)

Physics (with sources)
----------------------
Clutter (sea)
    * ``rayleigh``: fully developed single-look speckle, intensity exponential with mean
      ``clutter_mean`` (Goodman 1976; Oliver & Quegan, *Understanding SAR Images*, 1998, ch. 4).
      The scene's ``looks`` is 1 whatever ``cfg.looks`` says.
    * ``gamma``: L-look intensity, Gamma(shape L, mean ``clutter_mean``) (Oliver & Quegan ch. 4);
      ``looks`` may be fractional.
    * ``k``: compound model I = clutter_mean * T * S, with texture T ~ Gamma(shape nu, mean 1)
      spatially correlated and S the L-look gamma speckle, i.e. K-distributed intensity
      (Jakeman & Pusey 1976; Ward 1981). T is a Gaussian copula: a unit-variance Gaussian
      random field, mapped pixel by pixel through the Gamma(nu) quantile function (a 4097-point
      table, linear interpolation), so its marginal is exactly Gamma(nu, 1/nu) and
      E[T] = 1, Var[T] = 1/nu. The Gaussian field is a separable cubic B-spline of i.i.d.
      N(0,1) nodes, renormalised per pixel by sqrt(sum w^2) so that its variance is exactly 1;
      the node spacing is ``texture_corr_px / 1.1847`` so that the field's autocorrelation
      B7(lag/s)/B7(0) (B7: the degree-7 B-spline, the autocorrelation of the cubic) is 1/e at
      lag ``texture_corr_px``. Intensity moments: E[I] = clutter_mean,
      Var[I]/E[I]^2 = (1 + 1/nu)(1 + 1/L) - 1.
    * ``slc``: circular complex Gaussian hh with E|hh|^2 = clutter_mean (times T for ``k``):
      the single-look complex form of the same models; ``looks`` is 1.
    * ``quadpol``: X = [HH, HV, VV] zero-mean circular complex Gaussian (thesis
      000_5bc9398123fbbeaa eq 2-1, 2-2) with the reflection-symmetric covariance of eq 2-3,
      Sigma = sigma_hh [[1, 0, rho sqrt(g)], [0, eps, 0], [conj(rho) sqrt(g), 0, g]], where
      ``rho = E[HH VV*] / sqrt(E|HH|^2 E|VV|^2)`` (eq 2-4 omits the conjugate; the usual
      definition is used). Sea values (typical C/L-band open sea, not fitted to data):
      :data:`SEA_EPS` = 0.03 (HV ~15 dB below HH), :data:`SEA_GAMMA` = 1.5 (VV 1.8 dB above
      HH, Bragg scattering), :data:`SEA_RHO` = 0.7 exp(i 10 deg). sigma_hh = clutter_mean;
      X = sqrt(T) L z with L the Cholesky factor of Sigma and z ~ CN(0, I) for ``k``.
    Speckle is i.i.d. between pixels (an ideal, unweighted single-look processor sampled at
    the resolution): the CFAR calibration tests rely on it.

Land (``land``)
    A coast on one side (drawn from the seed), land depth 15-30 % of the scene plus a fractal
    displacement: a sum of octaves of 1-D cubic-B-spline noise with amplitude ~ scale^H,
    H = 0.7 (fractional-Brownian-like coastline, Mandelbrot 1967; box dimension ~ 1.3).
    Land mean backscatter is +8..12 dB over the sea (a smooth field 10 +- 1 dB clipped to
    [8, 12]), times a strong texture (Gamma(nu = 1), correlation 6 px), with bright urban
    point scatterers (density 1 / 1500 px, +20..35 dB, dihedral/trihedral in quad-pol).
    Quad-pol land covariance: eps = 0.15, gamma = 0.8, rho = 0.35 (vegetation/urban mix).

Ships
    Oriented extended targets: a rectangle of length ~ log-uniform in ``length_m``, width
    length/8..length/6 widened to at least one pixel across, random heading. Rendering: 4x4
    sub-samples per pixel give the area fraction ``cov``; a pixel belongs to the ship where
    cov >= 1/4 (plus the centre pixel). Each ship pixel has a mean RCS
    cov * lognormal (sigma = 0.6 nepers, ~2.6 dB, structure fluctuation) with independent
    speckle (the hull is a distributed target: gamma L-look intensity, circular Gaussian for
    complex data), plus 3-5 dominant point scatterers (bow, stern, superstructure, and a
    few random ones; 4-40 x the hull level) added deterministically (fixed amplitude, random
    phase). The pattern is scaled so that the mean ship power over its pixels is
    ``clutter_mean * 10**(scr_db/10)`` (power = intensity; |hh|^2 for slc; span =
    |HH|^2 + 2|HV|^2 + |VV|^2 for quad-pol, relative to the sea span sigma_hh(1+2 eps+gamma)),
    with per-ship scr_db = cfg.scr_db + U(-2, 2) dB (recorded). The ship is added to the sea
    clutter (coherently for complex data). SCR is relative to the mean sea intensity, not
    to the local texture: a ship's RCS does not depend on the waves around it.
    Quad-pol ship classes (:data:`SHIP_CLASSES`): the hull has its own reflection-symmetric
    covariance, and dominant scatterers are trihedrals [1, 0, 1]/sqrt2 (odd bounce) or
    dihedrals rotated by psi, [cos 2psi, sin 2psi, -cos 2psi]/sqrt2 (even bounce) (Lee &
    Pottier, *Polarimetric Radar Imaging*, 2009, ch. 2/6).
    Ships lie on sea only (>= 8 px from the coast), never overlap (bounding boxes 3 px apart)
    and stay >= 5 px from the scene border.

Artefacts (none is in the truth features)
    * ``sidelobes``: the impulse response of an unweighted processor is sinc^2 in range and
      azimuth (first sidelobe -13.26 dB; Cumming & Wong, *Digital Processing of SAR Data*,
      2005). For every dominant scatterer >= 10 x the sea power a cross of sidelobes is added
      along its row and column: P sinc^2((k - d)/os) / sinc^2(d/os) at offset k != 0 px,
      d the sub-pixel position, os = 1.2 (pixel spacing = resolution / 1.2), out to where the
      envelope is 5 % of the sea power; coherent (sinc amplitude with the scatterer's phase) for
      complex data.
    * ``ambiguities``: azimuth ambiguities (ghosts) of every ship at +- 3000 m in azimuth
      (rows; Delta x = lambda R PRF / (2 V), Curlander & McDonough 1991) at -20 dB, smeared
      over 7 rows (defocus: a quadratic-phase kernel for complex data). Listed under the truth
      member ``ambiguities``.
    * ``stripes``: azimuth stripes (antenna-pattern / beam-seam gain errors): a gain constant
      along azimuth, piecewise constant across range in bands 24-384 px wide, N(0, 0.8) dB
      clipped to +-2.5 dB; multiplies everything (sqrt of it for complex data).
    * ``rfi``: radio interference: 1 + rows // 1024 bands of 1-4 range lines (rows), over
      30-100 % of the columns, +3..12 dB over the sea, sinusoidally modulated (60 %) along
      range, noise-like (exponential intensity / complex Gaussian), added before the stripes.
      Listed under the truth member ``rfi``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import functools
import json
import math
import os
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from sarship.pipeline.errors import InputError

__all__ = [
    "SimConfig", "validate", "ship_catalogue", "simulate_tile", "truth_collection",
    "simulate_array", "simulate", "sea_covariance", "effective_looks", "variables",
]

#: Scene kinds the simulator writes.
KINDS = ("intensity", "slc", "quadpol")
#: Clutter models.
CLUTTERS = ("rayleigh", "gamma", "k")

#: Side of the fixed grid of random blocks (global coordinates). Rendering cost is lowest
#: for requests aligned on it (tile a multiple of 256).
BLOCK = 256
#: Side, in nodes, of the blocks of coarse random-field nodes.
NODE_BLOCK = 64
_NODE_OFF = NODE_BLOCK  # node indices start at -1; shift so block indices are >= 0

#: Quad-pol sea covariance parameters (eq 2-3 of thesis 000): HV/HH, VV/HH, HH-VV correlation.
SEA_EPS = 0.03
SEA_GAMMA = 1.5
SEA_RHO = complex(0.7 * math.cos(math.radians(10.0)), 0.7 * math.sin(math.radians(10.0)))
#: Quad-pol land covariance parameters.
LAND_EPS, LAND_GAMMA, LAND_RHO = 0.15, 0.8, complex(0.35, 0.0)
#: Quad-pol ship classes: hull (eps, gamma, rho) and probability that a dominant scatterer
#: is a dihedral (else a trihedral), dihedral rotation range (deg).
SHIP_CLASSES: dict[str, dict[str, Any]] = {
    "odd": {"eps": 0.08, "gamma": 1.0, "rho": 0.6, "p_dihedral": 0.2, "psi_deg": 15.0},
    "even": {"eps": 0.10, "gamma": 0.9, "rho": -0.6, "p_dihedral": 0.8, "psi_deg": 15.0},
    "volume": {"eps": 0.35, "gamma": 1.0, "rho": 0.15, "p_dihedral": 0.5, "psi_deg": 90.0},
    "mixed": {"eps": 0.30, "gamma": 1.0, "rho": -0.2, "p_dihedral": 0.5, "psi_deg": 30.0},
}

# Geometry / artefact constants (see the module docstring).
BORDER_PX = 5          # ships stay this far from the scene border
GAP_PX = 3             # min gap between ship bounding boxes
LAND_MARGIN_PX = 8     # min distance of ship pixels from the coast
COVERAGE_MIN = 0.25    # min area fraction of a ship pixel
HULL_SIGMA = 0.6       # lognormal sigma of hull RCS structure (nepers)
SIDELOBE_OS = 1.2      # resolution / pixel spacing
SIDELOBE_MIN = 10.0    # scatterer power / sea power for drawing sidelobes
SIDELOBE_FLOOR = 0.05  # sidelobes drawn out to this fraction of the sea power
SIDELOBE_MAX_PX = 1024
AMBIG_OFFSET_M = 3000.0
AMBIG_LEVEL_DB = -20.0
AMBIG_SMEAR = 3        # ghost smear half-length (rows)
URBAN_PX_PER_POINT = 1500.0
LAND_TEXTURE_NU = 1.0
LAND_TEXTURE_CORR_PX = 6.0
LAND_GAIN_CORR_PX = 64.0

# Correlation length (in node spacings) at which the normalised cubic-B-spline field has
# autocorrelation 1/e: root of B7(x)/B7(0) = exp(-1).
_CORR_FACTOR = 1.1846958711967932

_TAG = 0x5A75_1B  # sarship simulator tag in every SeedSequence

# Random streams.
_S_SPECKLE, _S_TEXTURE, _S_CATALOGUE, _S_SHIPDOM, _S_SHIPHULL, _S_SHIPSPK = 1, 2, 3, 4, 5, 6
_S_LAND, _S_COAST, _S_LAND_TEX, _S_LAND_GAIN, _S_URBAN = 7, 8, 9, 10, 11
_S_RFI, _S_RFI_NOISE, _S_STRIPES = 12, 13, 14


@dataclass(frozen=True)
class SimConfig:
    """Simulation parameters (see the module docstring for the physics)."""

    kind: str = "intensity"          # "intensity" | "slc" | "quadpol"
    shape: tuple[int, int] = (2048, 2048)
    ships: int = 10
    seed: int = 0
    looks: float = 1.0               # intensity scenes: L-look gamma speckle; slc/quadpol are single-look
    clutter: str = "gamma"           # "rayleigh" | "gamma" | "k"
    land: bool = False
    sidelobes: bool = False
    ambiguities: bool = False
    stripes: bool = False
    rfi: bool = False
    pixel_spacing_m: tuple[float, float] = (10.0, 10.0)   # [azimuth(row), range(col)]
    scr_db: float = 15.0             # mean ship power / mean sea power
    length_m: tuple[float, float] = (20.0, 400.0)
    texture_shape: float = 4.0       # K clutter: gamma texture shape nu (smaller = spikier)
    texture_corr_px: float = 16.0    # 1/e correlation length of the texture's Gaussian field
    clutter_mean: float = 1.0        # mean sea intensity (HH for quadpol)

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


# --------------------------------------------------------------------------- validation


def _bad(field: str, rng: str, got: Any) -> InputError:
    return InputError(f"simulation {field}: must be {rng} (got {got!r})")


def _num(v: Any, field: str, rng: str) -> float:
    if isinstance(v, bool):
        raise _bad(field, rng, v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise _bad(field, rng, v) from None
    if not math.isfinite(f):
        raise _bad(field, rng, v)
    return f


def _int(v: Any, field: str, rng: str) -> int:
    if isinstance(v, bool):
        raise _bad(field, rng, v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)) and float(v).is_integer():
        return int(v)
    raise _bad(field, rng, v)


def _pair(v: Any, field: str, rng: str) -> tuple[Any, Any]:
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) != 2:
        raise _bad(field, rng, v)
    return v[0], v[1]


def effective_looks(cfg: SimConfig) -> float:
    """The scene's number of looks: cfg.looks for gamma/K intensity, else 1."""
    if cfg.kind != "intensity" or cfg.clutter == "rayleigh":
        return 1.0
    return float(cfg.looks)


def _px_per_m(cfg: SimConfig) -> float:
    """Largest pixels per metre over the two axes (ship length in px, worst heading)."""
    return 1.0 / min(cfg.pixel_spacing_m)


def max_ships(cfg: SimConfig) -> int:
    """A generous upper bound on the number of ships that fit (checked by :func:`validate`)."""
    H, W = cfg.shape
    lgm = math.sqrt(cfg.length_m[0] * cfg.length_m[1]) * _px_per_m(cfg)
    per = 2.0 * (lgm + 2 * GAP_PX + 2) ** 2
    frac = 0.6 if cfg.land else 1.0
    return int(min(1_000_000, frac * (H - 2 * BORDER_PX) * (W - 2 * BORDER_PX) / per))


def validate(cfg: SimConfig) -> SimConfig:
    """Check every field and return a normalised copy (tuples, ints, floats).

    Raises :class:`InputError` with one line naming the bad field and its allowed range.
    """
    if not isinstance(cfg, SimConfig):
        raise InputError(f"simulation config must be a SimConfig, got {type(cfg).__name__}")
    kind = cfg.kind
    if kind not in KINDS:
        raise _bad("kind", "one of " + ", ".join(KINDS), kind)
    clutter = cfg.clutter
    if clutter not in CLUTTERS:
        raise _bad("clutter", "one of " + ", ".join(CLUTTERS), clutter)
    srng = "two integers (rows, cols), each in [16, 65536]"
    a, b = _pair(cfg.shape, "shape", srng)
    shape = (_int(a, "shape", srng), _int(b, "shape", srng))
    if not all(16 <= s <= 65536 for s in shape):
        raise _bad("shape", srng, cfg.shape)
    seed = _int(cfg.seed, "seed", "an integer in [0, 2**63 - 1]")
    if not 0 <= seed < 2**63:
        raise _bad("seed", "an integer in [0, 2**63 - 1]", cfg.seed)
    looks = _num(cfg.looks, "looks", "a number in (0, 1000]")
    if not 0 < looks <= 1000:
        raise _bad("looks", "a number in (0, 1000]", cfg.looks)
    for name in ("land", "sidelobes", "ambiguities", "stripes", "rfi"):
        v = getattr(cfg, name)
        if not isinstance(v, (bool, np.bool_)):
            raise _bad(name, "true or false", v)
    prng = "two numbers (azimuth, range) in [0.01, 10000] m"
    a, b = _pair(cfg.pixel_spacing_m, "pixel_spacing_m", prng)
    spacing = (_num(a, "pixel_spacing_m", prng), _num(b, "pixel_spacing_m", prng))
    if not all(0.01 <= s <= 10000 for s in spacing):
        raise _bad("pixel_spacing_m", prng, cfg.pixel_spacing_m)
    scr = _num(cfg.scr_db, "scr_db", "a number in [-10, 40] dB")
    if not -10 <= scr <= 40:
        raise _bad("scr_db", "a number in [-10, 40] dB", cfg.scr_db)
    lrng = "two numbers (min, max) with 0.1 <= min <= max <= 10000 m"
    a, b = _pair(cfg.length_m, "length_m", lrng)
    length = (_num(a, "length_m", lrng), _num(b, "length_m", lrng))
    if not 0.1 <= length[0] <= length[1] <= 10000:
        raise _bad("length_m", lrng, cfg.length_m)
    nu = _num(cfg.texture_shape, "texture_shape", "a number in [0.05, 100]")
    if not 0.05 <= nu <= 100:
        raise _bad("texture_shape", "a number in [0.05, 100]", cfg.texture_shape)
    corr = _num(cfg.texture_corr_px, "texture_corr_px", "a number in [1, 4096] px")
    if not 1 <= corr <= 4096:
        raise _bad("texture_corr_px", "a number in [1, 4096] px", cfg.texture_corr_px)
    cm = _num(cfg.clutter_mean, "clutter_mean", "a number in [1e-12, 1e12]")
    if not 1e-12 <= cm <= 1e12:
        raise _bad("clutter_mean", "a number in [1e-12, 1e12]", cfg.clutter_mean)
    out = SimConfig(kind=kind, shape=shape, ships=0, seed=seed, looks=looks, clutter=clutter,
                    land=bool(cfg.land), sidelobes=bool(cfg.sidelobes),
                    ambiguities=bool(cfg.ambiguities), stripes=bool(cfg.stripes),
                    rfi=bool(cfg.rfi), pixel_spacing_m=spacing, scr_db=scr, length_m=length,
                    texture_shape=nu, texture_corr_px=corr, clutter_mean=cm)
    ships = _int(cfg.ships, "ships", "an integer >= 0")
    if ships < 0:
        raise _bad("ships", "an integer >= 0", cfg.ships)
    if ships > 0:
        lmax_px = length[1] * _px_per_m(out)
        fit = min(shape) - 2 * (BORDER_PX + 2)
        if lmax_px > fit:
            raise InputError(
                f"simulation length_m: the longest ship ({lmax_px:.0f} px at the pixel spacing) "
                f"must fit the {shape[0]}x{shape[1]} scene: at most {fit} px "
                f"(got length_m={cfg.length_m!r}; lower it, raise pixel_spacing_m or the shape)")
        cap = max_ships(out)
        if ships > cap:
            raise _bad("ships", f"an integer in [0, {cap}] for this shape, length_m and land", ships)
    return dataclasses.replace(out, ships=ships)


# --------------------------------------------------------------------------- random helpers


def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([_TAG, seed, *key]))


def _bspline4(t: np.ndarray) -> np.ndarray:
    """Cubic B-spline weights of the 4 nodes k-1..k+2 around a point at fraction t of [k, k+1)."""
    t2 = t * t
    t3 = t2 * t
    w = np.empty((4,) + t.shape)
    w[0] = (1.0 - t) ** 3 / 6.0
    w[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w[3] = t3 / 6.0
    return w


def _axis_weights(coords: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """First node index and unit-energy weights (sum w^2 = 1) at pixel-centre ``coords``."""
    u = coords / spacing
    k = np.floor(u)
    w = _bspline4(u - k)
    w /= np.sqrt((w * w).sum(axis=0))
    return k.astype(np.int64) - 1, w


@functools.lru_cache(maxsize=1024)
def _node_block(seed: int, stream: int, a: int, b: int) -> np.ndarray:
    x = _rng(seed, stream, a, b).standard_normal((NODE_BLOCK, NODE_BLOCK))
    x.flags.writeable = False
    return x


def _nodes(seed: int, stream: int, k0: int, k1: int, l0: int, l1: int) -> np.ndarray:
    """i.i.d. N(0,1) coarse nodes [k0:k1, l0:l1] of a global grid (indices >= -NODE_BLOCK)."""
    out = np.empty((k1 - k0, l1 - l0))
    nb = NODE_BLOCK
    for a in range((k0 + _NODE_OFF) // nb, (k1 - 1 + _NODE_OFF) // nb + 1):
        ra = a * nb - _NODE_OFF
        i0, i1 = max(k0, ra), min(k1, ra + nb)
        for b in range((l0 + _NODE_OFF) // nb, (l1 - 1 + _NODE_OFF) // nb + 1):
            cb = b * nb - _NODE_OFF
            j0, j1 = max(l0, cb), min(l1, cb + nb)
            out[i0 - k0:i1 - k0, j0 - l0:j1 - l0] = _node_block(seed, stream, a, b)[
                i0 - ra:i1 - ra, j0 - cb:j1 - cb]
    return out


def _gauss_field(seed: int, stream: int, corr_px: float, r0: int, r1: int, c0: int, c1: int
                 ) -> np.ndarray:
    """Unit-variance Gaussian random field on pixels [r0:r1, c0:c1] (float32).

    Separable cubic B-spline interpolation of global i.i.d. nodes with spacing
    ``corr_px / 1.1847`` (1/e autocorrelation at ``corr_px``), renormalised to variance 1.
    """
    s = corr_px / _CORR_FACTOR
    kr, wr = _axis_weights(np.arange(r0, r1) + 0.5, s)
    kc, wc = _axis_weights(np.arange(c0, c1) + 0.5, s)
    kr0, kr1 = int(kr[0]), int(kr[-1]) + 4
    kc0, kc1 = int(kc[0]), int(kc[-1]) + 4
    n = _nodes(seed, stream, kr0, kr1, kc0, kc1)
    jc = kc - kc0
    hc = wc[0] * n[:, jc] + wc[1] * n[:, jc + 1] + wc[2] * n[:, jc + 2] + wc[3] * n[:, jc + 3]
    hc = hc.astype(np.float32)
    jr = kr - kr0
    wr = wr.astype(np.float32)
    f = wr[0][:, None] * hc[jr]
    for a in (1, 2, 3):
        f += wr[a][:, None] * hc[jr + a]
    return f


_Q_LO, _Q_HI, _Q_N = -8.5, 8.5, 4097


@functools.lru_cache(maxsize=16)
def _gamma_table(nu: float) -> tuple[np.ndarray, np.ndarray]:
    """Gamma(nu, mean 1) quantiles at Gaussian levels g (copula table) and their differences."""
    from scipy import special

    g = np.linspace(_Q_LO, _Q_HI, _Q_N)
    q = np.where(g < 0, special.gammaincinv(nu, special.ndtr(g)),
                 special.gammainccinv(nu, special.ndtr(-g))) / nu
    q = np.maximum(q, 0.0)
    return q.astype(np.float32), np.diff(q).astype(np.float32)


def _gamma_texture(g: np.ndarray, nu: float) -> np.ndarray:
    """Map a unit Gaussian field to Gamma(nu, mean 1) by the quantile table (float32)."""
    tab, dtab = _gamma_table(float(nu))
    step = (_Q_HI - _Q_LO) / (_Q_N - 1)
    x = (g - np.float32(_Q_LO)) * np.float32(1.0 / step)
    np.clip(x, 0.0, np.float32(_Q_N - 1.0001), out=x)
    i = x.astype(np.int32)
    x -= i
    x *= dtab[i]
    x += tab[i]
    return x


def sea_covariance(cfg: Optional[SimConfig] = None) -> np.ndarray:
    """The quad-pol sea covariance Sigma (eq 2-3), times ``cfg.clutter_mean`` (3x3 complex128)."""
    s = 1.0 if cfg is None else float(cfg.clutter_mean)
    return s * _refl_cov(SEA_EPS, SEA_GAMMA, SEA_RHO)


def _refl_cov(eps: float, gamma: float, rho: complex) -> np.ndarray:
    sg = math.sqrt(gamma)
    return np.array([[1, 0, rho * sg], [0, eps, 0], [np.conj(rho) * sg, 0, gamma]],
                    dtype=np.complex128)


def _span_factor(eps: float, gamma: float) -> float:
    return 1.0 + 2.0 * eps + gamma


def _sea_power(cfg: SimConfig) -> float:
    """Mean sea power in the units ships are scaled in (span for quad-pol)."""
    f = _span_factor(SEA_EPS, SEA_GAMMA) if cfg.kind == "quadpol" else 1.0
    return cfg.clutter_mean * f


def variables(cfg: SimConfig) -> dict[str, np.dtype]:
    """Scene variables and dtypes for ``cfg.kind``."""
    if cfg.kind == "intensity":
        return {"intensity": np.dtype(np.float32)}
    if cfg.kind == "slc":
        return {"hh": np.dtype(np.complex64)}
    return {"hh": np.dtype(np.complex64), "hv": np.dtype(np.complex64),
            "vv": np.dtype(np.complex64)}


def _power(data: dict[str, np.ndarray], kind: str) -> np.ndarray:
    """Pixel power: intensity, |hh|^2, or span |hh|^2 + 2|hv|^2 + |vv|^2 (float32)."""
    if kind == "intensity":
        return np.asarray(data["intensity"], dtype=np.float32)

    def p(z):
        return z.real * z.real + z.imag * z.imag

    if kind == "slc":
        return p(data["hh"])
    hv = p(data["hv"])
    return p(data["hh"]) + (hv + hv) + p(data["vv"])


# --------------------------------------------------------------------------- scene model


@dataclass
class _Ship:
    idx: int
    rc: float
    cc: float
    length_m: float
    width_m: float
    bow_deg: float
    scr_db: float
    pol_class: Optional[str]
    r0: int
    c0: int
    mask: np.ndarray
    cov: np.ndarray
    scale: float = 0.0
    # dominant scatterers: rows, cols (global), sub-pixel offsets, powers, phases, pol vectors
    dom: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def r1(self) -> int:
        return self.r0 + self.mask.shape[0]

    @property
    def c1(self) -> int:
        return self.c0 + self.mask.shape[1]


@dataclass
class _Land:
    side: str            # "top" | "bottom" | "left" | "right"
    depth: float         # mean depth, px
    octaves: list[tuple[float, float, np.ndarray]]


@dataclass
class _Model:
    cfg: SimConfig
    looks: float
    ships: list[_Ship]
    land: Optional[_Land]
    stripes: Optional[np.ndarray]
    rfi: list[dict[str, Any]]
    sources: list[dict[str, Any]]
    ghosts: list[dict[str, Any]]
    buckets: dict[tuple[int, int], list[tuple[str, int, int, int, int, int]]]
    boxes: Optional[np.ndarray] = None


def _unit_vectors(bow_deg: float) -> tuple[float, float, float, float]:
    """Along (bow) and across unit vectors in metres, as (row, col) components."""
    th = math.radians(bow_deg)
    return -math.cos(th), math.sin(th), math.sin(th), math.cos(th)


def _ship_dims(length: float, ratio: float, bow_deg: float, dy: float, dx: float
               ) -> tuple[float, float]:
    """Rendered length and width (m): at least one pixel along and across."""
    ur, uc, vr, vc = _unit_vectors(bow_deg)
    lpx = math.hypot(ur / dy, uc / dx)
    wpx = math.hypot(vr / dy, vc / dx)
    return max(length, 1.0 / lpx), max(length / ratio, 1.0 / wpx)


def _footprint(rc: float, cc: float, length: float, width: float, bow_deg: float,
               dy: float, dx: float) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Ship pixels: (r0, c0, mask, coverage) of the rotated rectangle centred at (rc, cc) px."""
    ur, uc, vr, vc = _unit_vectors(bow_deg)
    hr = (abs(ur) * length / 2 + abs(vr) * width / 2) / dy + 1.0
    hc = (abs(uc) * length / 2 + abs(vc) * width / 2) / dx + 1.0
    r0, r1 = math.floor(rc - hr), math.ceil(rc + hr)
    c0, c1 = math.floor(cc - hc), math.ceil(cc + hc)
    sub = (np.arange(4) + 0.5) / 4.0
    ys = ((np.arange(r0, r1)[:, None] + sub[None, :]).ravel() - rc) * dy
    xs = ((np.arange(c0, c1)[:, None] + sub[None, :]).ravel() - cc) * dx
    a = ys[:, None] * ur + xs[None, :] * uc
    b = ys[:, None] * vr + xs[None, :] * vc
    inside = (np.abs(a) <= length / 2) & (np.abs(b) <= width / 2)
    cov = inside.reshape(r1 - r0, 4, c1 - c0, 4).mean(axis=(1, 3))
    mask = cov >= COVERAGE_MIN
    mask[math.floor(rc) - r0, math.floor(cc) - c0] = True
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    return r0 + int(rows[0]), c0 + int(cols[0]), mask[sl].copy(), cov[sl].astype(np.float32)


def _land_model(cfg: SimConfig) -> _Land:
    H, W = cfg.shape
    rng = _rng(cfg.seed, _S_LAND)
    side = ("top", "bottom", "left", "right")[int(rng.integers(0, 4))]
    along, perp = (W, H) if side in ("top", "bottom") else (H, W)
    depth = float(rng.uniform(0.15, 0.30)) * perp
    a0 = 0.08 * perp
    octaves = []
    s = along / 2.0
    o = 0
    while s >= 3.0 and o < 16:
        n = int(math.ceil(along / s)) + 8
        nodes = _rng(cfg.seed, _S_COAST, o).standard_normal(n)
        octaves.append((s, a0 * 2.0 ** (-0.7 * o), nodes))
        s /= 2.0
        o += 1
    return _Land(side=side, depth=depth, octaves=octaves)


def _coast(land: _Land, along: np.ndarray) -> np.ndarray:
    """Land depth (px from the land side) at pixel-centre coordinates ``along``."""
    d = np.full(along.shape, land.depth)
    for s, amp, nodes in land.octaves:
        k, w = _axis_weights(along, s)
        k = k + 2
        d += amp * (w[0] * nodes[k] + w[1] * nodes[k + 1] + w[2] * nodes[k + 2]
                    + w[3] * nodes[k + 3])
    return d


def _land_mask(cfg: SimConfig, land: _Land, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    H, W = cfg.shape
    rows = np.arange(r0, r1) + 0.5
    cols = np.arange(c0, c1) + 0.5
    if land.side == "top":
        return rows[:, None] < _coast(land, cols)[None, :]
    if land.side == "bottom":
        return (H - rows)[:, None] < _coast(land, cols)[None, :]
    if land.side == "left":
        return cols[None, :] < _coast(land, rows)[:, None]
    return (W - cols)[None, :] < _coast(land, rows)[:, None]


def _land_clearance(cfg: SimConfig, land: _Land, r0: int, r1: int, c0: int, c1: int) -> float:
    """Smallest distance (px, perpendicular to the coast) of box pixels from the land."""
    H, W = cfg.shape
    if land.side in ("top", "bottom"):
        d = _coast(land, np.arange(c0, c1) + 0.5).max()
        p = r0 + 0.5 if land.side == "top" else H - (r1 - 0.5)
    else:
        d = _coast(land, np.arange(r0, r1) + 0.5).max()
        p = c0 + 0.5 if land.side == "left" else W - (c1 - 0.5)
    return float(p - d)


def _place_ships(cfg: SimConfig, land: Optional[_Land]) -> list[_Ship]:
    H, W = cfg.shape
    dy, dx = cfg.pixel_spacing_m
    rng = _rng(cfg.seed, _S_CATALOGUE)
    cell = 64
    grid: dict[tuple[int, int], list[tuple[int, int, int, int]]] = {}
    classes = list(SHIP_CLASSES)
    ships: list[_Ship] = []
    lo, hi = cfg.length_m
    for i in range(cfg.ships):
        length = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else lo
        ratio = float(rng.uniform(6.0, 8.0))
        bow = float(rng.uniform(0.0, 360.0))
        scr = float(cfg.scr_db + rng.uniform(-2.0, 2.0))
        pcls = classes[int(rng.integers(0, len(classes)))]
        length, width = _ship_dims(length, ratio, bow, dy, dx)
        ur, uc, vr, vc = _unit_vectors(bow)
        hr = (abs(ur) * length / 2 + abs(vr) * width / 2) / dy + 1.0
        hc = (abs(uc) * length / 2 + abs(vc) * width / 2) / dx + 1.0
        rlo, rhi = BORDER_PX + hr, H - BORDER_PX - hr
        clo, chi = BORDER_PX + hc, W - BORDER_PX - hc
        placed = None
        if rhi > rlo and chi > clo:
            for _attempt in range(2000):
                rc = float(rng.uniform(rlo, rhi))
                cc = float(rng.uniform(clo, chi))
                r0, c0, mask, cov = _footprint(rc, cc, length, width, bow, dy, dx)
                r1, c1 = r0 + mask.shape[0], c0 + mask.shape[1]
                if r0 < BORDER_PX or c0 < BORDER_PX or r1 > H - BORDER_PX or c1 > W - BORDER_PX:
                    continue
                b = (r0 - GAP_PX, r1 + GAP_PX, c0 - GAP_PX, c1 + GAP_PX)
                cells = [(p, q) for p in range(b[0] // cell, (b[1] - 1) // cell + 1)
                         for q in range(b[2] // cell, (b[3] - 1) // cell + 1)]
                if any(o[0] < b[1] and b[0] < o[1] and o[2] < b[3] and b[2] < o[3]
                       for pq in cells for o in grid.get(pq, ())):
                    continue
                if land is not None and _land_clearance(cfg, land, r0, r1, c0, c1) < LAND_MARGIN_PX:
                    continue
                placed = (rc, cc, r0, c0, mask, cov)
                for p in range(r0 // cell, (r1 - 1) // cell + 1):
                    for q in range(c0 // cell, (c1 - 1) // cell + 1):
                        grid.setdefault((p, q), []).append((r0, r1, c0, c1))
                break
        if placed is None:
            raise InputError(
                f"simulation ships: could not place ship {i + 1} of {cfg.ships} on free sea "
                f"in the {H}x{W} scene (ships must not overlap each other or land); "
                f"use fewer ships, shorter length_m or a larger shape")
        rc, cc, r0, c0, mask, cov = placed
        ships.append(_Ship(idx=i, rc=rc, cc=cc, length_m=length, width_m=width, bow_deg=bow,
                           scr_db=scr, pol_class=pcls if cfg.kind == "quadpol" else None,
                           r0=r0, c0=c0, mask=mask, cov=cov))
    return ships


def _hull_pattern(cfg: SimConfig, s: _Ship) -> np.ndarray:
    """Relative mean hull RCS per ship pixel (cov x unit-mean lognormal; 0 off the ship)."""
    rng = _rng(cfg.seed, _S_SHIPHULL, s.idx)
    g = rng.standard_normal(s.mask.shape)
    lg = np.exp(HULL_SIGMA * g - 0.5 * HULL_SIGMA**2)
    return np.where(s.mask, s.cov * lg, 0.0)


def _dominants(cfg: SimConfig, s: _Ship) -> dict[str, np.ndarray]:
    """Dominant point scatterers (bow, stern, superstructure, extras) of ship ``s``."""
    dy, dx = cfg.pixel_spacing_m
    rng = _rng(cfg.seed, _S_SHIPDOM, s.idx)
    n_extra = int(rng.integers(0, 3))
    L, Wd = s.length_m, s.width_m
    along = np.concatenate([[0.42 * L, -0.42 * L, rng.uniform(-0.3, 0.15) * L],
                            rng.uniform(-0.4, 0.4, n_extra) * L])
    across = rng.uniform(-0.25, 0.25, along.size) * Wd
    rel = np.concatenate([rng.uniform(4.0, 12.0, 2), rng.uniform(12.0, 40.0, 1),
                          rng.uniform(3.0, 10.0, n_extra)])
    phase = rng.uniform(0.0, 2 * math.pi, along.size)
    ur, uc, vr, vc = _unit_vectors(s.bow_deg)
    rp = s.rc + (along * ur + across * vr) / dy
    cp = s.cc + (along * uc + across * vc) / dx
    rows = np.floor(rp).astype(np.int64)
    cols = np.floor(cp).astype(np.int64)
    dr = rp - rows - 0.5
    dc = cp - cols - 0.5
    mr, mc = np.nonzero(s.mask)
    for j in range(rows.size):  # snap to the nearest ship pixel
        lr, lc = rows[j] - s.r0, cols[j] - s.c0
        if not (0 <= lr < s.mask.shape[0] and 0 <= lc < s.mask.shape[1] and s.mask[lr, lc]):
            k = int(np.argmin((mr - lr) ** 2 + (mc - lc) ** 2))
            rows[j], cols[j] = s.r0 + mr[k], s.c0 + mc[k]
    # polarimetric vectors (unit span) for quad-pol
    info = SHIP_CLASSES[s.pol_class or "mixed"]
    is_di = rng.random(along.size) < info["p_dihedral"]
    psi = np.radians(rng.uniform(-info["psi_deg"], info["psi_deg"], along.size))
    vec = np.where(is_di[:, None],
                   np.stack([np.cos(2 * psi), np.sin(2 * psi), -np.cos(2 * psi)], axis=1),
                   np.array([[1.0, 0.0, 1.0]])) / math.sqrt(2.0)
    return {"row": rows, "col": cols, "dr": dr, "dc": dc, "rel": rel, "phase": phase,
            "vec": vec, "dihedral": is_di}


def _stripes_gain(cfg: SimConfig) -> np.ndarray:
    W = cfg.shape[1]
    rng = _rng(cfg.seed, _S_STRIPES)
    g = np.empty(W, dtype=np.float64)
    c = 0
    while c < W:
        w = int(rng.integers(24, 385))
        db = float(np.clip(rng.normal(0.0, 0.8), -2.5, 2.5))
        g[c:c + w] = 10.0 ** (db / 10.0)
        c += w
    return g.astype(np.float32)


def _rfi_events(cfg: SimConfig) -> list[dict[str, Any]]:
    H, W = cfg.shape
    rng = _rng(cfg.seed, _S_RFI)
    out = []
    for e in range(min(64, 1 + H // 1024)):
        thick = int(rng.integers(1, 5))
        r0 = int(rng.integers(0, H - thick + 1))
        n = max(1, int(round(rng.uniform(0.3, 1.0) * W)))
        c0 = int(rng.integers(0, W - n + 1))
        out.append({"id": e, "rows": [r0, r0 + thick], "cols": [c0, c0 + n],
                    "level_db": float(rng.uniform(3.0, 12.0)),
                    "period_px": float(rng.uniform(40.0, 400.0)),
                    "phase": float(rng.uniform(0.0, 2 * math.pi)), "modulation": 0.6})
    return out


def _build_model(cfg: SimConfig) -> _Model:
    H, W = cfg.shape
    land = _land_model(cfg) if cfg.land else None
    ships = _place_ships(cfg, land)
    p_sea = _sea_power(cfg)
    sf = _span_factor(SEA_EPS, SEA_GAMMA) if cfg.kind == "quadpol" else 1.0
    for s in ships:
        s.dom = _dominants(cfg, s)
        hull = _hull_pattern(cfg, s)
        total = float(hull.sum() + s.dom["rel"].sum())
        target = cfg.clutter_mean * sf * 10.0 ** (s.scr_db / 10.0)
        s.scale = target * int(s.mask.sum()) / total
        s.dom["power"] = s.dom["rel"] * s.scale
    sources: list[dict[str, Any]] = []
    if cfg.sidelobes:
        for s in ships:
            d = s.dom
            for j in range(d["row"].size):
                p = float(d["power"][j])
                if p < SIDELOBE_MIN * p_sea:
                    continue
                n = int(min(SIDELOBE_MAX_PX,
                            math.ceil(SIDELOBE_OS / math.pi * math.sqrt(p / (SIDELOBE_FLOOR * p_sea)))))
                sources.append({"ship": s.idx, "j": j, "row": int(d["row"][j]),
                                "col": int(d["col"][j]), "dr": float(d["dr"][j]),
                                "dc": float(d["dc"][j]), "power": p, "n": n})
    ghosts: list[dict[str, Any]] = []
    if cfg.ambiguities:
        off = int(round(AMBIG_OFFSET_M / cfg.pixel_spacing_m[0]))
        for s in ships:
            for sign in (-1, 1):
                g0, g1 = s.r0 + sign * off - AMBIG_SMEAR, s.r1 + sign * off + AMBIG_SMEAR
                if g1 <= 0 or g0 >= H:
                    continue
                ghosts.append({"ship": s.idx, "offset": sign * off, "r0": g0, "c0": s.c0})
    rfi = _rfi_events(cfg) if cfg.rfi else []
    stripes = _stripes_gain(cfg) if cfg.stripes else None

    buckets: dict[tuple[int, int], list[tuple[str, int, int, int, int, int]]] = {}

    def add(item: str, idx: int, r0: int, r1: int, c0: int, c1: int) -> None:
        r0, r1, c0, c1 = max(r0, 0), min(r1, H), max(c0, 0), min(c1, W)
        if r0 >= r1 or c0 >= c1:
            return
        for bi in range(r0 // BLOCK, (r1 - 1) // BLOCK + 1):
            for bj in range(c0 // BLOCK, (c1 - 1) // BLOCK + 1):
                buckets.setdefault((bi, bj), []).append((item, idx, r0, r1, c0, c1))

    for s in ships:
        add("ship", s.idx, s.r0, s.r1, s.c0, s.c1)
    for k, src in enumerate(sources):
        r, c, n = src["row"], src["col"], src["n"]
        add("slr", k, r, r + 1, c - n, c + n + 1)   # along the row (range sidelobes)
        add("slc", k, r - n, r + n + 1, c, c + 1)   # along the column (azimuth sidelobes)
    for k, g in enumerate(ghosts):
        s = ships[g["ship"]]
        add("ghost", k, g["r0"], g["r0"] + s.mask.shape[0] + 2 * AMBIG_SMEAR, s.c0, s.c1)
    for k, ev in enumerate(rfi):
        add("rfi", k, ev["rows"][0], ev["rows"][1], ev["cols"][0], ev["cols"][1])
    return _Model(cfg=cfg, looks=effective_looks(cfg), ships=ships, land=land, stripes=stripes,
                  rfi=rfi, sources=sources, ghosts=ghosts, buckets=buckets)


@functools.lru_cache(maxsize=4)
def _model(cfg: SimConfig) -> _Model:
    return _build_model(cfg)


# --------------------------------------------------------------------------- rendering


def _cn(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """n1 + i n2 with n1, n2 i.i.d. N(0,1) (E|z|^2 = 2), complex64."""
    return rng.standard_normal(shape + (2,), dtype=np.float32).view(np.complex64)[..., 0]


def _speckle(rng: np.random.Generator, looks: float, shape: tuple[int, ...]) -> np.ndarray:
    """Unit-mean L-look gamma intensity speckle (float32)."""
    if looks == 1.0:
        return rng.standard_exponential(shape, dtype=np.float32)
    g = rng.standard_gamma(looks, shape, dtype=np.float32)
    g *= np.float32(1.0 / looks)
    return g


def _chol(eps: float, gamma: float, rho: complex) -> np.ndarray:
    return np.linalg.cholesky(_refl_cov(eps, gamma, rho))


def _polmix(lc: np.ndarray, z: np.ndarray, amp: Any) -> list[np.ndarray]:
    """X = amp * L z for the lower-triangular L (skipping zeros); z (3, ...) complex64."""
    out = []
    for i in range(3):
        acc = None
        for j in range(i + 1):
            v = complex(lc[i, j])
            if v == 0:
                continue
            if v == 1:
                t = z[j]
            elif v.imag == 0:
                t = z[j] * np.float32(v.real)
            else:
                t = z[j] * np.complex64(v)
            acc = t if acc is None else acc + t
        out.append(acc * amp)
    return out


@functools.lru_cache(maxsize=2048)
def _ship_render(cfg: SimConfig, idx: int) -> dict[str, np.ndarray]:
    """Additive contribution of ship ``idx`` on its box (no clutter): {var: array}."""
    m = _model(cfg)
    s = m.ships[idx]
    hull = (_hull_pattern(cfg, s) * s.scale).astype(np.float32)
    d = s.dom
    lr, lc = d["row"] - s.r0, d["col"] - s.c0
    rng = _rng(cfg.seed, _S_SHIPSPK, idx)
    out: dict[str, np.ndarray] = {}
    if cfg.kind == "intensity":
        x = hull * _speckle(rng, m.looks, hull.shape)
        np.add.at(x, (lr, lc), d["power"].astype(np.float32))
        out["intensity"] = x
    else:
        amp = np.sqrt(d["power"]) * np.exp(1j * d["phase"])
        if cfg.kind == "slc":
            x = _cn(rng, hull.shape) * np.sqrt(hull * np.float32(0.5))
            np.add.at(x, (lr, lc), amp.astype(np.complex64))
            out["hh"] = x
        else:
            c = SHIP_CLASSES[s.pol_class]
            L = _chol(c["eps"], c["gamma"], c["rho"]) / math.sqrt(_span_factor(c["eps"], c["gamma"]))
            z = _cn(rng, (3,) + hull.shape)
            xs = _polmix(L, z, np.sqrt(hull * np.float32(0.5)))
            for k, name in enumerate(("hh", "hv", "vv")):
                np.add.at(xs[k], (lr, lc), (amp * d["vec"][:, k]).astype(np.complex64))
                out[name] = xs[k]
    for v in out.values():
        v.flags.writeable = False
    return out


@functools.lru_cache(maxsize=1024)
def _ghost_render(cfg: SimConfig, k: int) -> dict[str, np.ndarray]:
    """Azimuth ghost k: the ship contribution at -20 dB, smeared over 2*AMBIG_SMEAR+1 rows."""
    g = _model(cfg).ghosts[k]
    src = _ship_render(cfg, g["ship"])
    n = 2 * AMBIG_SMEAR + 1
    out = {}
    for name, a in src.items():
        h, w = a.shape
        acc = np.zeros((h + n - 1, w), dtype=a.dtype)
        if a.dtype == np.float32:
            f = np.float32(10.0 ** (AMBIG_LEVEL_DB / 10.0) / n)
            for j in range(n):
                acc[j:j + h] += a * f
        else:
            amp = 10.0 ** (AMBIG_LEVEL_DB / 20.0) / math.sqrt(n)
            for j in range(n):
                t = j - AMBIG_SMEAR
                acc[j:j + h] += a * np.complex64(amp * np.exp(1j * math.pi * t * t / n))
        acc.flags.writeable = False
        out[name] = acc
    return out


def _sidelobe_ratio(k: np.ndarray, d: float) -> np.ndarray:
    """Amplitude of the sinc IRF at integer offsets k from the peak pixel (sub-pixel offset d)."""
    return np.sinc((k - d) / SIDELOBE_OS) / np.sinc(-d / SIDELOBE_OS)


def _render_block(m: _Model, bi: int, bj: int) -> dict[str, np.ndarray]:
    """All pixels of block (bi, bj) of the fixed global grid (clipped at the scene edge)."""
    cfg = m.cfg
    H, W = cfg.shape
    r0, c0 = bi * BLOCK, bj * BLOCK
    r1, c1 = min(r0 + BLOCK, H), min(c0 + BLOCK, W)
    shape = (r1 - r0, c1 - c0)
    seed = cfg.seed
    cm = np.float32(cfg.clutter_mean)

    # mean sea power field (texture) and land
    mu: Any = cm
    if cfg.clutter == "k":
        t = _gamma_texture(_gauss_field(seed, _S_TEXTURE, cfg.texture_corr_px, r0, r1, c0, c1),
                           cfg.texture_shape)
        t *= cm
        mu = t
    land = None
    mu_land = None
    if m.land is not None:
        land = _land_mask(cfg, m.land, r0, r1, c0, c1)
        if land.any():
            gdb = _gauss_field(seed, _S_LAND_GAIN, LAND_GAIN_CORR_PX, r0, r1, c0, c1)
            gdb = np.clip(gdb + np.float32(10.0), 8.0, 12.0)
            tl = _gamma_texture(_gauss_field(seed, _S_LAND_TEX, LAND_TEXTURE_CORR_PX,
                                             r0, r1, c0, c1), LAND_TEXTURE_NU)
            mu_land = (np.power(np.float32(10.0), gdb * np.float32(0.1)) * tl * cm
                       ).astype(np.float32)
        else:
            land = None

    rng = _rng(seed, _S_SPECKLE, bi, bj)
    out: dict[str, np.ndarray] = {}
    if cfg.kind == "intensity":
        sp = _speckle(rng, m.looks, shape)
        if land is not None:
            mu = np.where(land, mu_land, mu)
        sp *= mu
        out["intensity"] = sp
    elif cfg.kind == "slc":
        z = _cn(rng, shape)
        if land is not None:
            mu = np.where(land, mu_land, mu)
        z *= np.sqrt(np.float32(0.5) * np.asarray(mu, dtype=np.float32))
        out["hh"] = z
    else:
        z = _cn(rng, (3,) + shape)
        amp = np.sqrt(np.float32(0.5) * np.asarray(mu, dtype=np.float32))
        xs = _polmix(_chol(SEA_EPS, SEA_GAMMA, SEA_RHO), z, amp)
        if land is not None:
            xl = _polmix(_chol(LAND_EPS, LAND_GAMMA, LAND_RHO), z,
                         np.sqrt(np.float32(0.5) * mu_land))
            xs = [np.where(land, a, b) for a, b in zip(xl, xs)]
        for name, x in zip(("hh", "hv", "vv"), xs):
            out[name] = np.ascontiguousarray(x, dtype=np.complex64)

    if land is not None:  # bright urban point scatterers
        ru = _rng(seed, _S_URBAN, bi, bj)
        n = int(ru.poisson(shape[0] * shape[1] / URBAN_PX_PER_POINT))
        rr = ru.integers(0, shape[0], n)
        cc = ru.integers(0, shape[1], n)
        pw = cfg.clutter_mean * 10.0 ** (ru.uniform(20.0, 35.0, n) / 10.0)
        ph = ru.uniform(0.0, 2 * math.pi, n)
        di = ru.random(n) < 0.5
        psi = ru.uniform(0.0, math.pi, n)
        keep = land[rr, cc]
        rr, cc, pw, ph, di, psi = rr[keep], cc[keep], pw[keep], ph[keep], di[keep], psi[keep]
        if cfg.kind == "intensity":
            np.add.at(out["intensity"], (rr, cc), pw.astype(np.float32))
        else:
            a = np.sqrt(pw) * np.exp(1j * ph)
            if cfg.kind == "slc":
                np.add.at(out["hh"], (rr, cc), a.astype(np.complex64))
            else:
                vec = np.where(di[:, None], np.stack([np.cos(2 * psi), np.sin(2 * psi),
                                                      -np.cos(2 * psi)], axis=1),
                               np.array([[1.0, 0.0, 1.0]])) / math.sqrt(2.0)
                for k, name in enumerate(("hh", "hv", "vv")):
                    np.add.at(out[name], (rr, cc), (a * vec[:, k]).astype(np.complex64))

    for item, idx, ir0, ir1, ic0, ic1 in m.buckets.get((bi, bj), ()):
        a0, a1, b0, b1 = max(ir0, r0), min(ir1, r1), max(ic0, c0), min(ic1, c1)
        if a0 >= a1 or b0 >= b1:
            continue
        dst = (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))
        if item == "ship" or item == "ghost":
            if item == "ship":
                s = m.ships[idx]
                arrs, or0, oc0 = _ship_render(cfg, idx), s.r0, s.c0
            else:
                g = m.ghosts[idx]
                arrs, or0, oc0 = _ghost_render(cfg, idx), g["r0"], g["c0"]
            src = (slice(a0 - or0, a1 - or0), slice(b0 - oc0, b1 - oc0))
            for name, a in arrs.items():
                out[name][dst] += a[src]
        elif item in ("slr", "slc"):
            sl = m.sources[idx]
            if item == "slr":
                k = np.arange(b0, b1) - sl["col"]
                ratio = _sidelobe_ratio(k, sl["dc"])
            else:
                k = np.arange(a0, a1) - sl["row"]
                ratio = _sidelobe_ratio(k, sl["dr"])
            ratio[k == 0] = 0.0
            if item == "slr":
                ratio = ratio[None, :]
            else:
                ratio = ratio[:, None]
            if cfg.kind == "intensity":
                out["intensity"][dst] += (sl["power"] * ratio * ratio).astype(np.float32)
            else:
                d = m.ships[sl["ship"]].dom
                j = sl["j"]
                amp = math.sqrt(sl["power"]) * np.exp(1j * d["phase"][j])
                if cfg.kind == "slc":
                    out["hh"][dst] += (amp * ratio).astype(np.complex64)
                else:
                    for k2, name in enumerate(("hh", "hv", "vv")):
                        out[name][dst] += (amp * d["vec"][j, k2] * ratio).astype(np.complex64)
        elif item == "rfi":
            ev = m.rfi[idx]
            cols = np.arange(b0, b1) + 0.5
            p = (cfg.clutter_mean * 10.0 ** (ev["level_db"] / 10.0)
                 * (1.0 + ev["modulation"] * np.sin(2 * math.pi * cols / ev["period_px"]
                                                     + ev["phase"])))
            rn = _rng(seed, _S_RFI_NOISE, idx, bi, bj)
            sh = (a1 - a0, b1 - b0)
            if cfg.kind == "intensity":
                out["intensity"][dst] += rn.standard_exponential(sh, dtype=np.float32) * \
                    p.astype(np.float32)[None, :]
            else:
                a = np.sqrt(0.5 * p).astype(np.float32)[None, :]
                names = ("hh",) if cfg.kind == "slc" else ("hh", "hv", "vv")
                for name in names:
                    out[name][dst] += _cn(rn, sh) * a

    if m.stripes is not None:
        g = m.stripes[c0:c1][None, :]
        if cfg.kind == "intensity":
            out["intensity"] *= g
        else:
            sg = np.sqrt(g)
            for name in out:
                out[name] *= sg
    return out


def _check_window(cfg: SimConfig, r0: int, r1: int, c0: int, c1: int) -> tuple[int, int, int, int]:
    H, W = cfg.shape
    try:
        r0, r1, c0, c1 = (int(v) for v in (r0, r1, c0, c1))
    except (TypeError, ValueError):
        raise InputError(f"tile window must be integers, got {(r0, r1, c0, c1)!r}") from None
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise InputError(f"tile window rows [{r0}, {r1}) cols [{c0}, {c1}) must be a non-empty "
                         f"part of the {H}x{W} scene")
    return r0, r1, c0, c1


def simulate_tile(cfg: SimConfig, r0: int, r1: int, c0: int, c1: int) -> dict[str, np.ndarray]:
    """Pixels ``[r0:r1, c0:c1]`` of the scene: ``{"intensity": float32}`` or complex64 channels.

    Bit-identical for any way of cutting the scene into requests (see the module docstring).
    Cheapest for windows aligned on the :data:`BLOCK` grid.
    """
    cfg = validate(cfg)
    r0, r1, c0, c1 = _check_window(cfg, r0, r1, c0, c1)
    m = _model(cfg)
    out = {name: np.empty((r1 - r0, c1 - c0), dtype=dt) for name, dt in variables(cfg).items()}
    for bi in range(r0 // BLOCK, (r1 - 1) // BLOCK + 1):
        br0 = bi * BLOCK
        a0, a1 = max(r0, br0), min(r1, br0 + BLOCK)
        for bj in range(c0 // BLOCK, (c1 - 1) // BLOCK + 1):
            bc0 = bj * BLOCK
            b0, b1 = max(c0, bc0), min(c1, bc0 + BLOCK)
            blk = _render_block(m, bi, bj)
            for name in out:
                out[name][a0 - r0:a1 - r0, b0 - c0:b1 - c0] = \
                    blk[name][a0 - br0:a1 - br0, b0 - bc0:b1 - bc0]
    return out


# --------------------------------------------------------------------------- catalogue & truth


def _ship_geometry(cfg: SimConfig, s: _Ship) -> dict[str, Any]:
    dy, dx = cfg.pixel_spacing_m
    ur, uc, vr, vc = _unit_vectors(s.bow_deg)
    heading = math.degrees(math.atan2(uc / dx, -ur / dy)) % 180.0
    rr, cc = np.nonzero(s.mask)
    return {
        "bbox_px": [s.r0, s.c0, s.r1, s.c1],
        "centroid_px": [float(s.r0 + rr.mean() + 0.5), float(s.c0 + cc.mean() + 0.5)],
        "area_px": int(rr.size),
        "length_px": float(s.length_m * math.hypot(ur / dy, uc / dx)),
        "width_px": float(s.width_m * math.hypot(vr / dy, vc / dx)),
        "heading_deg": float(heading),
        "length_m": float(s.length_m),
        "width_m": float(s.width_m),
    }


def ship_catalogue(cfg: SimConfig) -> list[dict[str, Any]]:
    """The ships of the scene (deterministic for the config), JSON-serialisable dicts.

    Each: ``id``, the truth geometry (``bbox_px``, ``centroid_px``, ``area_px``, ``length_px``,
    ``width_px``, ``heading_deg`` in [0, 180) clockwise from image up), ``length_m``,
    ``width_m``, ``center_px`` (design centre), ``bow_deg`` (bow direction in [0, 360)),
    ``scr_db``, ``mean_power`` (designed mean power over the ship pixels), ``pol_class`` and
    ``pol_signature`` (quad-pol: hull eps, gamma, rho), ``scatterers`` (dominant point
    scatterers: row, col, power, type).
    """
    cfg = validate(cfg)
    m = _model(cfg)
    out = []
    for s in m.ships:
        d = {"id": s.idx, **_ship_geometry(cfg, s), "center_px": [s.rc, s.cc],
             "bow_deg": s.bow_deg, "scr_db": s.scr_db,
             "mean_power": float(_sea_power(cfg) * 10.0 ** (s.scr_db / 10.0)),
             "pol_class": s.pol_class}
        if s.pol_class is not None:
            c = SHIP_CLASSES[s.pol_class]
            d["pol_signature"] = {"eps": c["eps"], "gamma": c["gamma"], "rho": c["rho"]}
        dom = s.dom
        d["scatterers"] = [
            {"row": int(dom["row"][j]), "col": int(dom["col"][j]),
             "power": float(dom["power"][j]),
             "type": ("dihedral" if dom["dihedral"][j] else "trihedral")
             if cfg.kind == "quadpol" else "point"}
            for j in range(dom["row"].size)]
        out.append(d)
    return out


def _new_ship_buffers(m: _Model) -> dict[int, np.ndarray]:
    return {s.idx: np.zeros(s.mask.shape, dtype=np.float32) for s in m.ships}


def _ship_boxes(m: _Model) -> np.ndarray:
    if m.boxes is None:
        m.boxes = np.array([[s.r0, s.r1, s.c0, s.c1] for s in m.ships],
                           dtype=np.int64).reshape(-1, 4)
    return m.boxes


def _collect_tile(m: _Model, bufs: dict[int, np.ndarray], data: dict[str, np.ndarray],
                  r0: int, c0: int) -> None:
    """Copy the power of the ship pixels of a window (origin r0, c0) into the ship buffers."""
    r1 = r0 + next(iter(data.values())).shape[0]
    c1 = c0 + next(iter(data.values())).shape[1]
    b = _ship_boxes(m)
    hit = np.flatnonzero((b[:, 0] < r1) & (b[:, 1] > r0) & (b[:, 2] < c1) & (b[:, 3] > c0))
    for i in hit:
        s = m.ships[int(i)]
        a0, a1, b0, b1 = max(r0, s.r0), min(r1, s.r1), max(c0, s.c0), min(c1, s.c1)
        if a0 < a1 and b0 < b1:
            sub = {k: v[a0 - r0:a1 - r0, b0 - c0:b1 - c0] for k, v in data.items()}
            bufs[s.idx][a0 - s.r0:a1 - s.r0, b0 - s.c0:b1 - s.c0] = _power(sub, m.cfg.kind)


def _ship_buffers_by_blocks(m: _Model) -> dict[int, np.ndarray]:
    bufs = _new_ship_buffers(m)
    need = sorted({(bi, bj) for s in m.ships
                   for bi in range(s.r0 // BLOCK, (s.r1 - 1) // BLOCK + 1)
                   for bj in range(s.c0 // BLOCK, (s.c1 - 1) // BLOCK + 1)})
    for bi, bj in need:
        blk = _render_block(m, bi, bj)
        _collect_tile(m, bufs, blk, bi * BLOCK, bj * BLOCK)
    return bufs


def _truth(m: _Model, bufs: dict[int, np.ndarray]) -> dict[str, Any]:
    cfg = m.cfg
    feats = []
    for s in m.ships:
        v = bufs[s.idx][s.mask]
        props = {"id": s.idx, **_ship_geometry(cfg, s),
                 "peak": float(v.max()), "mean": float(v.astype(np.float64).mean()),
                 "score": None, "scr_db": round(s.scr_db, 6), "difficult": False}
        if s.pol_class is not None:
            props["pol_class"] = s.pol_class
        feats.append({"type": "Feature", "id": s.idx, "geometry": None, "properties": props})
    H, W = cfg.shape
    p_sea = _sea_power(cfg)
    amb = []
    for k, g in enumerate(m.ghosts):
        s = m.ships[g["ship"]]
        arr = _ghost_render(cfg, k)
        pw = _power(arr, cfg.kind)
        r0, r1 = g["r0"], g["r0"] + pw.shape[0]
        a0, a1 = max(r0, 0), min(r1, H)
        peak = float(pw[a0 - r0:a1 - r0].max())
        rr, cc = np.nonzero(s.mask)
        amb.append({"source_id": s.idx, "offset_rows": g["offset"],
                    "bbox_px": [a0, s.c0, a1, s.c1],
                    "centroid_px": [float(s.r0 + rr.mean() + 0.5 + g["offset"]),
                                    float(s.c0 + cc.mean() + 0.5)],
                    "level_db": AMBIG_LEVEL_DB,
                    "peak_db_over_clutter": float(10 * math.log10(max(peak, 1e-30) / p_sea))})
    coll: dict[str, Any] = {
        "type": "FeatureCollection",
        "features": feats,
        "simulation": cfg.as_dict(),
        "ambiguities": amb,
        "clutter": {
            "model": cfg.clutter, "looks": m.looks, "mean": cfg.clutter_mean,
            "power_definition": {"intensity": "intensity", "slc": "|hh|^2",
                                 "quadpol": "|hh|^2 + 2|hv|^2 + |vv|^2"}[cfg.kind],
            "mean_power": p_sea,
        },
    }
    if cfg.clutter == "k":
        coll["clutter"].update({"texture_shape": cfg.texture_shape,
                                "texture_corr_px": cfg.texture_corr_px})
    if cfg.kind == "quadpol":
        coll["clutter"]["sea_covariance"] = {"eps": SEA_EPS, "gamma": SEA_GAMMA,
                                             "rho": [SEA_RHO.real, SEA_RHO.imag]}
    if m.rfi:
        coll["rfi"] = [{k: ev[k] for k in ("id", "rows", "cols", "level_db")} for ev in m.rfi]
    if m.land is not None:
        coll["land"] = {"side": m.land.side, "mean_depth_px": m.land.depth}
    if m.sources:
        coll["sidelobes"] = [{"source_id": sl["ship"], "row": sl["row"], "col": sl["col"],
                              "extent_px": sl["n"]} for sl in m.sources]
    if m.stripes is not None:
        coll["stripes"] = True
    return coll


def truth_collection(cfg: SimConfig) -> dict[str, Any]:
    """The truth GeoJSON FeatureCollection (CONTRACT schema) of the scene.

    One Feature per ship (geometry null: the scene is not georeferenced); ``peak`` and
    ``mean`` are statistics of the rendered power (clutter + ship + artefacts) over the
    ship's pixels. Top-level members: ``simulation`` (the config), ``ambiguities`` (azimuth
    ghosts, not ships), ``clutter`` and, where enabled, ``rfi``, ``land``, ``sidelobes``.
    """
    cfg = validate(cfg)
    m = _model(cfg)
    return _truth(m, _ship_buffers_by_blocks(m))


def simulate_array(cfg: SimConfig) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The whole scene in memory and its truth (small scenes, tests)."""
    cfg = validate(cfg)
    H, W = cfg.shape
    data = simulate_tile(cfg, 0, H, 0, W)
    m = _model(cfg)
    bufs = _new_ship_buffers(m)
    _collect_tile(m, bufs, data, 0, 0)
    return data, _truth(m, bufs)


# --------------------------------------------------------------------------- writing


def acquired_time(cfg: SimConfig) -> str:
    """A fixed ISO 8601 acquisition time derived from the seed."""
    t0 = _dt.datetime(2020, 1, 1, tzinfo=_dt.timezone.utc)
    t = t0 + _dt.timedelta(seconds=int(cfg.seed) % (5 * 365 * 86400))
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _writable_dir(p: Path, what: str) -> None:
    if not p.is_dir():
        raise InputError(f"{what} folder '{p}' does not exist or is not a folder")
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{what} folder '{p}' is not writable")


def simulate(out: str | os.PathLike, cfg: SimConfig, tile: int = 2048,
             truth_path: str | os.PathLike | None = None,
             progress: Optional[Callable[[int, int], None]] = None) -> Path:
    """Write the scene store ``out`` tile by tile (bounded memory) and its truth GeoJSON.

    The truth goes to ``truth_path`` (default ``f"{out}.truth.geojson"``). ``progress(done,
    total)`` is called after each tile. On any failure nothing is left behind (the store is
    written to a temporary sibling and renamed; the truth likewise). Returns the store path.
    """
    from sarship.pipeline import __version__
    from sarship.pipeline.scene import atomic_store, create_scene, finalize_scene, tile_slices

    cfg = validate(cfg)
    if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or not 16 <= tile <= 65536:
        raise InputError(f"tile: must be an integer in [16, 65536] (got {tile!r})")
    tile = int(tile)
    out = Path(out)
    truth = Path(truth_path) if truth_path is not None else Path(f"{out}.truth.geojson")
    _writable_dir(out.parent if str(out.parent) else Path("."), "output")
    _writable_dir(truth.parent if str(truth.parent) else Path("."), "truth")
    if truth.resolve() == out.resolve():
        raise InputError(f"truth path '{truth}' must differ from the scene path")
    m = _model(cfg)  # ship placement errors before anything is written
    H, W = cfg.shape
    attrs = {
        "kind": cfg.kind,
        "looks": m.looks,
        "pixel_spacing_m": list(cfg.pixel_spacing_m),
        "sensor": "sarship-simulator",
        "acquired": acquired_time(cfg),
        "source": "simulated",
        "looks_source": "simulator",
        "sarship_version": __version__,
        "simulation": cfg.as_dict(),
        "truth": truth.name,
    }
    if cfg.kind == "quadpol":
        attrs["polarizations"] = ["hh", "hv", "vv"]
    tmp_truth = truth.parent / f".{truth.name}.partial-{uuid.uuid4().hex[:8]}"
    slices = list(tile_slices((H, W), tile))
    moved = False
    try:
        with atomic_store(out) as tmp:
            g = create_scene(tmp, (H, W), variables(cfg), tile=tile, attrs=attrs)
            arrays = {name: g[name] for name in variables(cfg)}
            bufs = _new_ship_buffers(m)
            for done, (_i, _j, r0, r1, c0, c1) in enumerate(slices, 1):
                data = simulate_tile(cfg, r0, r1, c0, c1)
                for name, a in arrays.items():
                    a[r0:r1, c0:c1] = data[name]
                _collect_tile(m, bufs, data, r0, c0)
                del data
                if progress is not None:
                    progress(done, len(slices))
            finalize_scene(tmp, attrs)
            with open(tmp_truth, "w", encoding="utf-8") as fh:
                json.dump(_truth(m, bufs), fh, indent=1)
                fh.write("\n")
            os.replace(tmp_truth, truth)
            moved = True
    except BaseException:
        with contextlib.suppress(OSError):
            tmp_truth.unlink()
        if moved and not out.exists():
            with contextlib.suppress(OSError):
                truth.unlink()
        raise
    return out
