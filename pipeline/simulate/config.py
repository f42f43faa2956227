"""Simulation parameters (:class:`SimConfig`) and their validation.

The physics of each component is described in the docstrings of the modules
:mod:`~sarship.pipeline.simulate.clutter`, :mod:`~sarship.pipeline.simulate.land`,
:mod:`~sarship.pipeline.simulate.ships` and :mod:`~sarship.pipeline.simulate.artefacts`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

#: Scene kinds the simulator writes.
KINDS = ("intensity", "slc", "quadpol")
#: Clutter models.
CLUTTERS = ("rayleigh", "gamma", "k", "g0", "ggd", "cggd")

# Ship placement constraints, checked by validate() (see the ships module docstring).
BORDER_PX = 5  # ships stay this far from the scene border
GAP_PX = 3  # min gap between ship bounding boxes


@dataclass(frozen=True)
class SimConfig:
    """Simulation parameters (the physics: clutter, land, ships and artefacts modules)."""

    kind: str = "intensity"  # "intensity" | "slc" | "quadpol"
    shape: tuple[int, int] = (2048, 2048)
    ships: int = 10
    seed: int = 0
    looks: float = 1.0  # intensity scenes: L-look gamma speckle; slc/quadpol are single-look
    clutter: str = "gamma"  # "rayleigh" | "gamma" | "k" | "g0" | "ggd"
    land: bool = False
    sidelobes: bool = False
    ambiguities: bool = False
    stripes: bool = False
    rfi: bool = False
    pixel_spacing_m: tuple[float, float] = (10.0, 10.0)  # [azimuth(row), range(col)]
    scr_db: float = 15.0  # mean ship power / mean sea power
    length_m: tuple[float, float] = (20.0, 400.0)
    texture_shape: float = 4.0  # K: gamma texture shape nu; G0: inverse-gamma shape a = -alpha > 1 (smaller = spikier)
    texture_corr_px: float = 16.0  # 1/e correlation length of the texture's Gaussian field
    clutter_mean: float = 1.0  # mean sea intensity (HH for quadpol)
    ggd_power: float = 0.7  # GGD clutter (intensity only): power v of (x / sigma)^v kappa ~ Gamma(kappa)
    ggd_shape: float = 3.0  # GGD clutter: shape kappa
    shape_beta: float = 1.0  # CGGD clutter (slc only): shape beta (1: complex Gaussian; < 1 super-Gaussian)
    geo: tuple[float, float] | None = None  # (lon, lat) of the scene centre: georeferenced (WGS84), land from GSHHG
    geo_gcps: bool = False  # with geo: the georeference as a grid of GCPs instead of an affine transform
    time: str | None = None  # first line time (ISO 8601 UTC); None: a fixed time derived from the seed
    moving: bool = False  # ships under way (SOG, COG) imaged at their azimuth-displaced position (motion module)
    speed_kn: tuple[float, float] = (2.0, 25.0)  # moving: SOG range (knots) of the ships under way, uniform
    anchored_fraction: float = 0.3  # moving: fraction of ships at anchor or drifting (SOG 0-1 kn)
    ais: bool = False  # with geo: ships get MMSIs (but dark_fraction of them), plus AIS-only vessels (ais_vessels)
    dark_fraction: float = 0.2  # ais: fraction of the scene's ships that never report (round(f * ships) ships)
    ais_outside: int = 8  # ais: AIS vessels outside the swath (never imaged)
    ais_small: int = 4  # ais: AIS vessels inside the swath too small to be imaged

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
    if clutter == "g0" and not nu > 1.0:
        raise _bad(
            "texture_shape",
            "a number in (1, 100] for g0 clutter (a = -alpha; the mean is finite for a > 1)",
            cfg.texture_shape,
        )
    gv = _num(cfg.ggd_power, "ggd_power", "a number in [0.1, 10]")
    if not 0.1 <= gv <= 10:
        raise _bad("ggd_power", "a number in [0.1, 10]", cfg.ggd_power)
    gk = _num(cfg.ggd_shape, "ggd_shape", "a number in [0.1, 100]")
    if not 0.1 <= gk <= 100:
        raise _bad("ggd_shape", "a number in [0.1, 100]", cfg.ggd_shape)
    sb = _num(cfg.shape_beta, "shape_beta", "a number in [0.05, 10]")
    if not 0.05 <= sb <= 10:
        raise _bad("shape_beta", "a number in [0.05, 10]", cfg.shape_beta)
    geo = None
    if cfg.geo is not None:
        grng = "two numbers (lon, lat) with lon in [-180, 180] and lat in [-80, 80] degrees"
        a, b = _pair(cfg.geo, "geo", grng)
        geo = (_num(a, "geo", grng), _num(b, "geo", grng))
        if not (-180 <= geo[0] <= 180 and -80 <= geo[1] <= 80):
            raise _bad("geo", grng, cfg.geo)
    if not isinstance(cfg.geo_gcps, (bool, np.bool_)):
        raise _bad("geo_gcps", "true or false", cfg.geo_gcps)
    if cfg.geo_gcps and geo is None:
        raise _bad("geo_gcps", "false without geo (GCPs need the scene's position)", cfg.geo_gcps)
    if clutter == "cggd" and kind != "slc":
        raise _bad("clutter", "cggd (a complex single-channel model) with kind slc only", clutter)
    if clutter == "ggd" and kind != "intensity":
        raise _bad("clutter", "rayleigh, gamma, k or g0 for slc/quadpol scenes (ggd is an intensity model)", clutter)
    cm = _num(cfg.clutter_mean, "clutter_mean", "a number in [1e-12, 1e12]")
    if not 1e-12 <= cm <= 1e12:
        raise _bad("clutter_mean", "a number in [1e-12, 1e12]", cfg.clutter_mean)
    out = SimConfig(
        kind=kind,
        shape=shape,
        ships=0,
        seed=seed,
        looks=looks,
        clutter=clutter,
        land=bool(cfg.land),
        sidelobes=bool(cfg.sidelobes),
        ambiguities=bool(cfg.ambiguities),
        stripes=bool(cfg.stripes),
        rfi=bool(cfg.rfi),
        pixel_spacing_m=spacing,
        scr_db=scr,
        length_m=length,
        texture_shape=nu,
        texture_corr_px=corr,
        clutter_mean=cm,
        ggd_power=gv,
        ggd_shape=gk,
        shape_beta=sb,
        geo=geo,
        geo_gcps=bool(cfg.geo_gcps),
    )
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
                f"(got length_m={cfg.length_m!r}; lower it, raise pixel_spacing_m or the shape)"
            )
        cap = max_ships(out)
        if ships > cap:
            raise _bad("ships", f"an integer in [0, {cap}] for this shape, length_m and land", ships)
    return dataclasses.replace(out, ships=ships, **_validate_motion(cfg, geo))


#: Latest first line time accepted (POSIX seconds of 2100-01-01T00:00:00Z).
_TIME_MAX = 4_102_444_800.0


def parse_time(text: Any) -> _dt.datetime:
    """An ISO 8601 time as an aware UTC datetime (no zone: UTC; an offset: converted).

    Raises :class:`InputError` (one line) for anything else or a time outside 1970-2099.
    """
    rng = "an ISO 8601 UTC time in 1970-2099 like 2021-06-01T10:30:00Z"
    if not isinstance(text, str):
        raise _bad("time", rng, text)
    try:
        t = _dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise _bad("time", rng, text) from None
    t = t.replace(tzinfo=_dt.UTC) if t.tzinfo is None else t.astimezone(_dt.UTC)
    if not 0.0 <= t.timestamp() < _TIME_MAX:
        raise _bad("time", rng, text)
    return t


def format_time(t: _dt.datetime) -> str:
    """``YYYY-MM-DDTHH:MM:SSZ``, with ``.ffffff`` where the time has microseconds."""
    t = t.astimezone(_dt.UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%S.%fZ" if t.microsecond else "%Y-%m-%dT%H:%M:%SZ")


def scene_time(cfg: SimConfig) -> str:
    """The scene's first line time (ISO 8601 UTC): ``cfg.time``, else a fixed time derived from
    the seed (2020-2024; the ``acquired`` time every simulated scene had before ``time``)."""
    if cfg.time is not None:
        return format_time(parse_time(cfg.time))
    t0 = _dt.datetime(2020, 1, 1, tzinfo=_dt.UTC)
    return format_time(t0 + _dt.timedelta(seconds=int(cfg.seed) % (5 * 365 * 86400)))


def _validate_motion(cfg: SimConfig, geo: tuple[float, float] | None) -> dict[str, Any]:
    """The normalised ``time``, motion and AIS fields of ``cfg`` (see :func:`validate`)."""
    out: dict[str, Any] = {"time": None if cfg.time is None else format_time(parse_time(cfg.time))}
    for name in ("moving", "ais"):
        v = getattr(cfg, name)
        if not isinstance(v, (bool, np.bool_)):
            raise _bad(name, "true or false", v)
        out[name] = bool(v)
    srng = "two numbers (min, max) of knots with 0 <= min <= max <= 60"
    a, b = _pair(cfg.speed_kn, "speed_kn", srng)
    out["speed_kn"] = (_num(a, "speed_kn", srng), _num(b, "speed_kn", srng))
    if not 0 <= out["speed_kn"][0] <= out["speed_kn"][1] <= 60:
        raise _bad("speed_kn", srng, cfg.speed_kn)
    for name in ("anchored_fraction", "dark_fraction"):
        f = _num(getattr(cfg, name), name, "a number in [0, 1]")
        if not 0 <= f <= 1:
            raise _bad(name, "a number in [0, 1]", getattr(cfg, name))
        out[name] = f
    for name in ("ais_outside", "ais_small"):
        n = _int(getattr(cfg, name), name, "an integer in [0, 10000]")
        if not 0 <= n <= 10000:
            raise _bad(name, "an integer in [0, 10000]", getattr(cfg, name))
        out[name] = n
    if out["ais"] and geo is None:
        raise _bad("ais", "false without geo (AIS reports are lon/lat positions)", cfg.ais)
    return out


def variables(cfg: SimConfig) -> dict[str, np.dtype]:
    """Scene variables and dtypes for ``cfg.kind``."""
    if cfg.kind == "intensity":
        return {"intensity": np.dtype(np.float32)}
    if cfg.kind == "slc":
        return {"hh": np.dtype(np.complex64)}
    return {"hh": np.dtype(np.complex64), "hv": np.dtype(np.complex64), "vv": np.dtype(np.complex64)}
