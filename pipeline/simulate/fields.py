"""Seeded random streams and spatially correlated random fields.

All randomness is drawn on a fixed grid of :data:`BLOCK` x :data:`BLOCK` pixel blocks in global
scene coordinates, each block from its own generator :func:`_rng` keyed by
``[tag, seed, stream, block_i, block_j]``; every component has its own stream (``_S_*``).
Spatially correlated fields (K texture, land fields) interpolate globally seeded coarse node
grids, the node blocks keyed the same way (:func:`_gauss_field`); :func:`_gamma_texture` maps
such a unit Gaussian field to a Gamma(nu, mean 1) texture (Gaussian copula; see the clutter
module docstring).
"""

from __future__ import annotations

import functools

import numpy as np

#: Side of the fixed grid of random blocks (global coordinates). Rendering cost is lowest
#: for requests aligned on it (tile a multiple of 256).
BLOCK = 256
#: Side, in nodes, of the blocks of coarse random-field nodes.
NODE_BLOCK = 64
_NODE_OFF = NODE_BLOCK  # node indices start at -1; shift so block indices are >= 0

# Correlation length (in node spacings) at which the normalised cubic-B-spline field has
# autocorrelation 1/e: root of B7(x)/B7(0) = exp(-1).
_CORR_FACTOR = 1.1846958711967932

_TAG = 0x5A75_1B  # sarship simulator tag in every SeedSequence

# Random streams.
_S_SPECKLE, _S_TEXTURE, _S_CATALOGUE, _S_SHIPDOM, _S_SHIPHULL, _S_SHIPSPK = 1, 2, 3, 4, 5, 6
_S_LAND, _S_COAST, _S_LAND_TEX, _S_LAND_GAIN, _S_URBAN = 7, 8, 9, 10, 11
_S_RFI, _S_RFI_NOISE, _S_STRIPES = 12, 13, 14
_S_MOTION, _S_AIS, _S_AIS_EXTRA, _S_AIS_REPORTS = 15, 16, 17, 18  # moving ships and AIS (issue 33)


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
            out[i0 - k0 : i1 - k0, j0 - l0 : j1 - l0] = _node_block(seed, stream, a, b)[
                i0 - ra : i1 - ra, j0 - cb : j1 - cb
            ]
    return out


def _gauss_field(seed: int, stream: int, corr_px: float, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
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
    q = np.where(g < 0, special.gammaincinv(nu, special.ndtr(g)), special.gammainccinv(nu, special.ndtr(-g))) / nu
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
