"""The vessels of a simulated scene as AIS knows them: identities, dark ships, AIS-only vessels.

With ``ais`` (a ``geo`` scene), every vessel is one row of :class:`Vessels`:

* the scene's ships (``kind`` ``"ship"``, ``ship_id`` the truth Feature's ``id``): each gets a
  unique MMSI (a 3-digit maritime identification digit of :data:`MIDS` and 6 random digits),
  except ``round(dark_fraction * ships)`` of them, chosen at random, which never report (``dark``;
  MMSI null in the truth);
* ``ais_outside`` vessels outside the swath (``"outside"``): at the scene time at least the
  largest possible azimuth displacement plus a ship length plus :data:`OUTSIDE_MARGIN_M` beyond the
  scene's edge (so that they could not be imaged in it), in a band as wide as half the scene
  (at least :data:`OUTSIDE_BAND_M`) around it; lengths as the scene's ships;
* ``ais_small`` vessels inside the swath too small to be imaged (``"small"``): lengths
  U(:data:`SMALL_LENGTH_FRACTION`) times the smaller of the scene's coarser pixel spacing and its
  shortest ship (``length_m[0]``), on sea at least :data:`SMALL_CLEARANCE_PX` pixels from every
  ship's box, never rendered.

A vessel's true position is where it is at its own zero-Doppler time (the time of its true row,
:mod:`~sarship.pipeline.simulate.motion`); AIS-only vessels move with the same mix of speeds as
the ships (at anchor without ``moving``), COG uniform, heading = COG + N(0, 2 deg) under way.
Class A where the length is at least :data:`CLASS_A_MIN_LENGTH_M`, else class B (a simple rule:
SOLAS ships and larger fishing vessels carry class A; small craft class B).
All draws come from the streams ``_S_AIS`` (identities) and ``_S_AIS_EXTRA`` (AIS-only vessels).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.ais.reports import KNOT_M_S
from sarship.pipeline.errors import InputError
from sarship.pipeline.simulate.config import BORDER_PX, SimConfig, validate
from sarship.pipeline.simulate.fields import _S_AIS, _S_AIS_EXTRA, _rng
from sarship.pipeline.simulate.geometry import PLATFORM_VELOCITY_M_S, slant_range_m
from sarship.pipeline.simulate.land import _land_mask, geo_lonlat
from sarship.pipeline.simulate.model import _Model, _model
from sarship.pipeline.simulate.motion import ANCHORED_MAX_KN, COG_NOISE_DEG, draw_motion, iso_time, zero_doppler_time_s

#: Maritime identification digits the MMSIs are drawn with (Denmark, Norway, USA, China, Hong
#: Kong, Marshall Islands, Liberia).
MIDS = (219, 257, 338, 412, 477, 538, 636)
#: Vessels at least this long carry class A, shorter ones class B.
CLASS_A_MIN_LENGTH_M = 24.0
#: AIS-only vessels outside the swath: margin beyond the largest displacement plus a ship length,
#: and the least width of their band around the scene (m).
OUTSIDE_MARGIN_M = 500.0
OUTSIDE_BAND_M = 2000.0
#: Lengths of the vessels too small to be imaged, as fractions of the scene's detectable size.
SMALL_LENGTH_FRACTION = (0.2, 0.5)
#: Least distance (px) of a small vessel from every ship's (true or imaged) box.
SMALL_CLEARANCE_PX = 10


@dataclass(frozen=True)
class Vessels:
    """Every vessel of a scene with ``ais``, one row each (scene ships first, by id).

    ``mmsi`` is -1 for a dark ship. ``row``, ``col``: the true position (continuous pixels, outside
    the scene for ``"outside"``) at ``t_s``, the vessel's zero-Doppler time (POSIX seconds).
    """

    kind: np.ndarray  # str: "ship" | "outside" | "small"
    ship_id: np.ndarray  # int64, -1 for AIS-only vessels
    mmsi: np.ndarray  # int64
    dark: np.ndarray  # bool
    class_a: np.ndarray  # bool
    name: np.ndarray  # str
    length_m: np.ndarray
    width_m: np.ndarray
    row: np.ndarray
    col: np.ndarray
    t_s: np.ndarray
    sog_kn: np.ndarray
    cog_deg: np.ndarray
    heading_deg: np.ndarray
    anchored: np.ndarray  # bool

    def __len__(self) -> int:
        return int(self.mmsi.size)


def _speeds(cfg: SimConfig, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """SOG (kn) and ``anchored`` of ``n`` AIS-only vessels (the ships' mix; anchored without moving)."""
    anchored = rng.random(n) < cfg.anchored_fraction
    sog = np.where(anchored, rng.uniform(0.0, ANCHORED_MAX_KN, n), rng.uniform(*cfg.speed_kn, n))
    if not cfg.moving:
        return np.zeros(n), np.ones(n, dtype=bool)
    return sog, anchored


def _outside_positions(cfg: SimConfig, rng: np.random.Generator, n: int, max_len_m: float) -> np.ndarray:
    """``(n, 2)`` rows and columns of vessels outside the swath (see the module docstring)."""
    H, W = cfg.shape
    dy, dx = cfg.pixel_spacing_m
    v_max = max(cfg.speed_kn[1], ANCHORED_MAX_KN) * KNOT_M_S if cfg.moving else 0.0
    shift_m = float(slant_range_m(cfg.shape, cfg.pixel_spacing_m, W)) * v_max / PLATFORM_VELOCITY_M_S
    margin_m = shift_m + max_len_m + OUTSIDE_MARGIN_M
    band_m = max(OUTSIDE_BAND_M, 0.5 * max(H * dy, W * dx))
    out = np.empty((0, 2))
    while out.shape[0] < n:  # uniform over the band: the outer box less the inner one (acceptance >= 1/2)
        m = 2 * (n - out.shape[0]) + 8
        r = rng.uniform(-(margin_m + band_m) / dy, H + (margin_m + band_m) / dy, m)
        c = rng.uniform(-(margin_m + band_m) / dx, W + (margin_m + band_m) / dx, m)
        inner = (r > -margin_m / dy) & (r < H + margin_m / dy) & (c > -margin_m / dx) & (c < W + margin_m / dx)
        out = np.concatenate([out, np.stack([r, c], axis=1)[~inner]])
    return out[:n]


def _on_sea(cfg: SimConfig, m: _Model, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Whether each position has no land within SMALL_CLEARANCE_PX pixels (all True without land)."""
    if m.land is None:
        return np.ones(r.shape, dtype=bool)
    H, W = cfg.shape
    k = SMALL_CLEARANCE_PX
    return np.array(
        [
            not _land_mask(
                cfg, m.land, max(int(a) - k, 0), min(int(a) + k + 1, H), max(int(b) - k, 0), min(int(b) + k + 1, W)
            ).any()
            for a, b in zip(r, c)
        ],
        dtype=bool,
    )


def _small_positions(cfg: SimConfig, m: _Model, rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 2)`` rows and columns of small vessels on free sea inside the scene."""
    H, W = cfg.shape
    k = SMALL_CLEARANCE_PX
    b = np.array([[s.r0, s.r1, s.c0, s.c1] for s in m.ships], dtype=np.float64).reshape(-1, 4)
    shift = np.array([s.rc - (s.rc if s.rc_true is None else s.rc_true) for s in m.ships]).reshape(-1)
    lo_r, hi_r = np.minimum(b[:, 0], b[:, 0] - shift) - k, np.maximum(b[:, 1], b[:, 1] - shift) + k
    lo_c, hi_c = b[:, 2] - k, b[:, 3] + k
    found = np.empty((0, 2))
    for _batch in range(50):
        r = rng.uniform(BORDER_PX, H - BORDER_PX, 4 * n + 8)
        c = rng.uniform(BORDER_PX, W - BORDER_PX, 4 * n + 8)
        near = ((r[:, None] > lo_r) & (r[:, None] < hi_r) & (c[:, None] > lo_c) & (c[:, None] < hi_c)).any(axis=1)
        r, c = r[~near], c[~near]
        ok = _on_sea(cfg, m, r, c)
        found = np.concatenate([found, np.stack([r[ok], c[ok]], axis=1)])
        if found.shape[0] >= n:
            return found[:n]
    raise InputError(
        f"simulation ais_small: could not place {n} small vessels on free sea in the scene (use fewer: ais_small)"
    )


def _extra(cfg: SimConfig, m: _Model) -> dict[str, np.ndarray]:
    """The AIS-only vessels (outside the swath, then too small to see), drawn from ``_S_AIS_EXTRA``."""
    rng = _rng(cfg.seed, _S_AIS_EXTRA)
    n_out, n_small = cfg.ais_outside, cfg.ais_small
    lo, hi = cfg.length_m
    length = np.exp(rng.uniform(math.log(lo), math.log(hi), n_out))
    detectable = min(max(cfg.pixel_spacing_m), lo)
    length = np.concatenate([length, rng.uniform(*SMALL_LENGTH_FRACTION, n_small) * detectable])
    n = n_out + n_small
    width = length / rng.uniform(6.0, 8.0, n)
    sog, anchored = _speeds(cfg, rng, n)
    cog = rng.uniform(0.0, 360.0, n)
    heading = np.where(anchored, rng.uniform(0.0, 360.0, n), cog + rng.normal(0.0, COG_NOISE_DEG, n)) % 360.0
    pos = np.concatenate(
        [
            _outside_positions(cfg, rng, n_out, hi),
            _small_positions(cfg, m, rng, n_small) if n_small else np.empty((0, 2)),
        ]
    )
    kind = np.array(["outside"] * n_out + ["small"] * n_small, dtype=object)
    return {
        "kind": kind,
        "length_m": length,
        "width_m": width,
        "row": pos[:, 0],
        "col": pos[:, 1],
        "sog_kn": sog,
        "cog_deg": cog,
        "heading_deg": heading,
        "anchored": anchored,
    }


def _identities(cfg: SimConfig, n_ships: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique MMSIs of ``n`` vessels (ships first) and the dark flags, drawn from ``_S_AIS``."""
    rng = _rng(cfg.seed, _S_AIS)
    u = rng.choice(len(MIDS) * 1_000_000, size=n, replace=False)
    mmsi = np.asarray(MIDS, dtype=np.int64)[u // 1_000_000] * 1_000_000 + u % 1_000_000
    dark = np.zeros(n, dtype=bool)
    dark[rng.permutation(n_ships)[: math.floor(cfg.dark_fraction * n_ships + 0.5)]] = True
    return np.where(dark, -1, mmsi), dark


@functools.lru_cache(maxsize=8)
def _vessels(cfg: SimConfig) -> Vessels:
    m = _model(cfg)
    ships = m.ships
    motion = draw_motion(cfg)
    assert motion is not None  # cfg.ais
    x = _extra(cfg, m)
    n_s = len(ships)
    n = n_s + len(x["kind"])
    mmsi, dark = _identities(cfg, n_s, n)
    length = np.concatenate([[s.drawn_m[0] for s in ships], x["length_m"]])
    row = np.concatenate([[s.rc_true for s in ships], x["row"]])
    names = (
        [f"SARSHIP {s.idx:04d}" for s in ships]
        + [f"SARSHIP X{j:03d}" for j in range(cfg.ais_outside)]
        + [f"SARSHIP S{j:03d}" for j in range(cfg.ais_small)]
    )
    return Vessels(
        kind=np.concatenate([np.array(["ship"] * n_s, dtype=object), x["kind"]]),
        ship_id=np.concatenate([np.arange(n_s), np.full(n - n_s, -1)]).astype(np.int64),
        mmsi=mmsi,
        dark=dark,
        class_a=length >= CLASS_A_MIN_LENGTH_M,
        name=np.array(names, dtype=object),
        length_m=length,
        width_m=np.concatenate([[s.drawn_m[1] for s in ships], x["width_m"]]),
        row=row,
        col=np.concatenate([[s.cc for s in ships], x["col"]]),
        t_s=zero_doppler_time_s(cfg, row),
        sog_kn=np.concatenate([[s.sog_kn for s in ships], x["sog_kn"]]),
        cog_deg=np.concatenate([[s.cog_deg for s in ships], x["cog_deg"]]),
        heading_deg=np.concatenate([[s.bow_deg for s in ships], x["heading_deg"]]),
        anchored=np.concatenate([motion.anchored, x["anchored"]]).astype(bool),
    )


def scene_vessels(cfg: SimConfig) -> Vessels:
    """Every vessel of the scene ``cfg`` as AIS knows it (see the module docstring).

    Parameters
    ----------
    cfg
        A simulation with ``ais`` (so ``geo``).

    Returns
    -------
    Vessels
        The scene's ships (by id), then the AIS-only vessels outside the swath and too small to see.
    """
    cfg = validate(cfg)
    if not cfg.ais:
        raise InputError("simulation ais: must be true for the scene's AIS vessels (got False)")
    return _vessels(cfg)


def ais_member(cfg: SimConfig) -> dict[str, Any]:
    """The truth's top-level ``ais`` member: the dark fraction and counts, and the AIS-only
    vessels (``kind`` outside / small) with their true position at their zero-Doppler time."""
    v = scene_vessels(cfg)
    ships = v.kind == "ship"
    lon, lat = geo_lonlat(cfg, v.row, v.col)
    extra = [
        {
            "kind": str(v.kind[j]),
            "mmsi": int(v.mmsi[j]),
            "name": str(v.name[j]),
            "ais_class": "A" if v.class_a[j] else "B",
            "length_m": float(v.length_m[j]),
            "width_m": float(v.width_m[j]),
            "sog_kn": float(v.sog_kn[j]),
            "cog_deg": float(v.cog_deg[j]),
            "heading_deg": float(v.heading_deg[j]),
            "true_position_px": [float(v.row[j]), float(v.col[j])],
            "lon": float(lon[j]),
            "lat": float(lat[j]),
            "zero_doppler_time": iso_time(float(v.t_s[j])),
        }
        for j in np.flatnonzero(~ships)
    ]
    return {
        "dark_fraction": cfg.dark_fraction,
        "ships_dark": int(v.dark[ships].sum()),
        "ships_reporting": int((~v.dark[ships]).sum()),
        "vessels": extra,
    }


def ais_properties(cfg: SimConfig, ship_id: int) -> dict[str, Any]:
    """A truth Feature's AIS properties: ``mmsi`` (null: dark), ``dark``, ``ais_class``, ``ais_name``."""
    v = scene_vessels(cfg)
    j = int(ship_id)  # the ships come first, by id
    dark = bool(v.dark[j])
    return {
        "mmsi": None if dark else int(v.mmsi[j]),
        "dark": dark,
        "ais_class": None if dark else ("A" if v.class_a[j] else "B"),
        "ais_name": None if dark else str(v.name[j]),
    }


__all__ = ["CLASS_A_MIN_LENGTH_M", "MIDS", "Vessels", "ais_member", "ais_properties", "scene_vessels"]
