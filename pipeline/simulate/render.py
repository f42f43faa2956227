"""Rendering: the pixels of a block of the fixed grid, and :func:`simulate_tile`.

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
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.artefacts import AMBIG_LEVEL_DB, AMBIG_SMEAR, _sidelobe_ratio
from sarship.pipeline.simulate.clutter import (
    SEA_EPS,
    SEA_GAMMA,
    SEA_RHO,
    _chol,
    _cn,
    _polmix,
    _span_factor,
    _speckle,
    ggd_speckle,
    sea_texture,
)
from sarship.pipeline.simulate.config import SimConfig, validate, variables
from sarship.pipeline.simulate.fields import (
    _S_LAND_GAIN,
    _S_LAND_TEX,
    _S_RFI_NOISE,
    _S_SHIPSPK,
    _S_SPECKLE,
    _S_TEXTURE,
    _S_URBAN,
    BLOCK,
    _gamma_texture,
    _gauss_field,
    _rng,
)
from sarship.pipeline.simulate.land import (
    LAND_EPS,
    LAND_GAIN_CORR_PX,
    LAND_GAMMA,
    LAND_RHO,
    LAND_TEXTURE_CORR_PX,
    LAND_TEXTURE_NU,
    URBAN_PX_PER_POINT,
    _land_mask,
)
from sarship.pipeline.simulate.model import _Model, _model
from sarship.pipeline.simulate.ships import SHIP_CLASSES, _hull_pattern


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
                acc[j : j + h] += a * f
        else:
            amp = 10.0 ** (AMBIG_LEVEL_DB / 20.0) / math.sqrt(n)
            for j in range(n):
                t = j - AMBIG_SMEAR
                acc[j : j + h] += a * np.complex64(amp * np.exp(1j * math.pi * t * t / n))
        acc.flags.writeable = False
        out[name] = acc
    return out


def _render_block(m: _Model, bi: int, bj: int) -> dict[str, np.ndarray]:
    """All pixels of block (bi, bj) of the fixed global grid (clipped at the scene edge): the
    clutter (sea, land), the urban points, the ships and what they bring (ghosts, sidelobes),
    RFI, then the stripe gain."""
    cfg = m.cfg
    H, W = cfg.shape
    r0, c0 = bi * BLOCK, bj * BLOCK
    r1, c1 = min(r0 + BLOCK, H), min(c0 + BLOCK, W)
    mu, land, mu_land = _power_fields(m, r0, r1, c0, c1)
    out = _clutter(m, bi, bj, (r1 - r0, c1 - c0), mu, land, mu_land)
    if land is not None:  # bright urban point scatterers
        _urban_points(m, bi, bj, land, out)
    for item, idx, ir0, ir1, ic0, ic1 in m.buckets.get((bi, bj), ()):
        a0, a1, b0, b1 = max(ir0, r0), min(ir1, r1), max(ic0, c0), min(ic1, c1)
        if a0 >= a1 or b0 >= b1:
            continue
        dst = (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0))
        if item == "ship" or item == "ghost":
            _add_target(m, item, idx, (a0, a1, b0, b1), dst, out)
        elif item in ("slr", "slc"):
            _add_sidelobe(m, item, idx, (a0, a1, b0, b1), dst, out)
        elif item == "rfi":
            _add_rfi(m, idx, bi, bj, (a0, a1, b0, b1), dst, out)
    if m.stripes is not None:
        g = m.stripes[c0:c1][None, :]
        if cfg.kind == "intensity":
            out["intensity"] *= g
        else:
            sg = np.sqrt(g)
            for name in out:
                out[name] *= sg
    return out


def _power_fields(m: _Model, r0: int, r1: int, c0: int, c1: int) -> tuple[Any, Any, Any]:
    """The block's mean sea power (a field with texture for ``k`` / ``g0``), its land mask and the
    land's mean power (None, None where the block has no land)."""
    cfg = m.cfg
    seed = cfg.seed
    cm = np.float32(cfg.clutter_mean)
    mu: Any = cm
    if cfg.clutter in ("k", "g0"):
        t = sea_texture(cfg, _gauss_field(seed, _S_TEXTURE, cfg.texture_corr_px, r0, r1, c0, c1))
        t *= cm
        mu = t
    land = None
    mu_land = None
    if m.land is not None:
        land = _land_mask(cfg, m.land, r0, r1, c0, c1)
        if land.any():
            gdb = _gauss_field(seed, _S_LAND_GAIN, LAND_GAIN_CORR_PX, r0, r1, c0, c1)
            gdb = np.clip(gdb + np.float32(10.0), 8.0, 12.0)
            tl = _gamma_texture(_gauss_field(seed, _S_LAND_TEX, LAND_TEXTURE_CORR_PX, r0, r1, c0, c1), LAND_TEXTURE_NU)
            mu_land = (np.power(np.float32(10.0), gdb * np.float32(0.1)) * tl * cm).astype(np.float32)
        else:
            land = None
    return mu, land, mu_land


def _clutter(m: _Model, bi: int, bj: int, shape: tuple[int, int], mu, land, mu_land) -> dict[str, np.ndarray]:
    """The block's speckled clutter of the scene's kind (intensity, SLC ``hh``, quad-pol)."""
    cfg = m.cfg
    rng = _rng(cfg.seed, _S_SPECKLE, bi, bj)
    out: dict[str, np.ndarray] = {}
    if cfg.kind == "intensity":
        sp = ggd_speckle(rng, cfg, shape) if cfg.clutter == "ggd" else _speckle(rng, m.looks, shape)
        if land is not None:
            mu = np.where(land, mu_land, mu)
        sp *= mu
        out["intensity"] = sp
    elif cfg.kind == "slc":
        if (
            cfg.clutter == "cggd"
        ):  # circular CGGD of unit variance (pipeline/stats/cggd.py, seed 004 eq 27-31), as _cn's E|z|^2 = 2
            from sarship.pipeline.stats.cggd import sample as cggd_sample

            z = cggd_sample(cfg.shape_beta, None, shape, rng, np.complex64) * np.float32(math.sqrt(2.0))
        else:
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
            xl = _polmix(_chol(LAND_EPS, LAND_GAMMA, LAND_RHO), z, np.sqrt(np.float32(0.5) * mu_land))
            xs = [np.where(land, a, b) for a, b in zip(xl, xs)]
        for name, x in zip(("hh", "hv", "vv"), xs):
            out[name] = np.ascontiguousarray(x, dtype=np.complex64)
    return out


def _urban_points(m: _Model, bi: int, bj: int, land: np.ndarray, out: dict[str, np.ndarray]) -> None:
    """Bright point scatterers on the block's land (20-35 dB over the clutter; single or double
    bounce in quad-pol), added in place."""
    cfg = m.cfg
    shape = land.shape
    ru = _rng(cfg.seed, _S_URBAN, bi, bj)
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
        return
    a = np.sqrt(pw) * np.exp(1j * ph)
    if cfg.kind == "slc":
        np.add.at(out["hh"], (rr, cc), a.astype(np.complex64))
        return
    vec = np.where(
        di[:, None], np.stack([np.cos(2 * psi), np.sin(2 * psi), -np.cos(2 * psi)], axis=1), np.array([[1.0, 0.0, 1.0]])
    ) / math.sqrt(2.0)
    for k, name in enumerate(("hh", "hv", "vv")):
        np.add.at(out[name], (rr, cc), (a * vec[:, k]).astype(np.complex64))


def _add_target(m: _Model, item: str, idx: int, win: tuple[int, int, int, int], dst, out: dict) -> None:
    """A ship's (or its azimuth ghost's) rendered pixels in the window ``win`` = (a0, a1, b0, b1)."""
    a0, a1, b0, b1 = win
    if item == "ship":
        s = m.ships[idx]
        arrs, or0, oc0 = _ship_render(m.cfg, idx), s.r0, s.c0
    else:
        g = m.ghosts[idx]
        arrs, or0, oc0 = _ghost_render(m.cfg, idx), g["r0"], g["c0"]
    src = (slice(a0 - or0, a1 - or0), slice(b0 - oc0, b1 - oc0))
    for name, a in arrs.items():
        out[name][dst] += a[src]


def _add_sidelobe(m: _Model, item: str, idx: int, win: tuple[int, int, int, int], dst, out: dict) -> None:
    """A dominant scatterer's range (``slr``) or azimuth (``slc``) sidelobe line in the window."""
    cfg = m.cfg
    a0, a1, b0, b1 = win
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
        return
    d = m.ships[sl["ship"]].dom
    j = sl["j"]
    amp = math.sqrt(sl["power"]) * np.exp(1j * d["phase"][j])
    if cfg.kind == "slc":
        out["hh"][dst] += (amp * ratio).astype(np.complex64)
    else:
        for k2, name in enumerate(("hh", "hv", "vv")):
            out[name][dst] += (amp * d["vec"][j, k2] * ratio).astype(np.complex64)


def _add_rfi(m: _Model, idx: int, bi: int, bj: int, win: tuple[int, int, int, int], dst, out: dict) -> None:
    """An RFI event's power in the window: noise-like on intensity, narrow-band tones on complex data."""
    cfg = m.cfg
    seed = cfg.seed
    a0, a1, b0, b1 = win
    ev = m.rfi[idx]
    cols = np.arange(b0, b1) + 0.5
    p = (
        cfg.clutter_mean
        * 10.0 ** (ev["level_db"] / 10.0)
        * (1.0 + ev["modulation"] * np.sin(2 * math.pi * cols / ev["period_px"] + ev["phase"]))
    )
    rn = _rng(seed, _S_RFI_NOISE, idx, bi, bj)
    sh = (a1 - a0, b1 - b0)
    if cfg.kind == "intensity":
        out["intensity"][dst] += rn.standard_exponential(sh, dtype=np.float32) * p.astype(np.float32)[None, :]
        return
    # narrow-band interference: 1-2 tones along range, drawn once per event (any tiling)
    re = _rng(seed, _S_RFI_NOISE, idx, 1 << 20, 0)
    nt = 1 + int(re.integers(0, 2))
    freq = re.uniform(0.02, 0.48, nt)  # cycles per pixel along range
    psi = re.uniform(0.0, 2 * math.pi, (nt, ev["rows"][1] - ev["rows"][0]))  # per row
    rows = np.arange(a0, a1) - ev["rows"][0]
    tone = np.zeros(sh, np.complex128)
    for k in range(nt):
        tone += np.exp(1j * (2 * math.pi * freq[k] * cols[None, :] + psi[k][rows][:, None]))
    z = (tone * np.sqrt(p / nt)[None, :]).astype(np.complex64)
    names = ("hh",) if cfg.kind == "slc" else ("hh", "hv", "vv")
    for name in names:
        out[name][dst] += z


def _check_window(cfg: SimConfig, r0: int, r1: int, c0: int, c1: int) -> tuple[int, int, int, int]:
    H, W = cfg.shape
    try:
        r0, r1, c0, c1 = (int(v) for v in (r0, r1, c0, c1))
    except (TypeError, ValueError):
        raise InputError(f"tile window must be integers, got {(r0, r1, c0, c1)!r}") from None
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise InputError(
            f"tile window rows [{r0}, {r1}) cols [{c0}, {c1}) must be a non-empty part of the {H}x{W} scene"
        )
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
                out[name][a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = blk[name][a0 - br0 : a1 - br0, b0 - bc0 : b1 - bc0]
    return out
