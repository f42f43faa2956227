"""Sensor artefacts: sidelobes, azimuth ambiguities, stripes and RFI.

Artefacts (none is in the truth features)
    * ``sidelobes``: the impulse response of an unweighted processor is sinc^2 in range and
      azimuth (first sidelobe -13.26 dB; Cumming & Wong, *Digital Processing of SAR Data*,
      2005). For every dominant scatterer >= 10 x the sea power a cross of sidelobes is added
      along its row and column: P sinc^2((k - d)/os) / sinc^2(d/os) at offset k != 0 px,
      d the sub-pixel position, os = 1.2 (pixel spacing = resolution / 1.2), out to where the
      envelope is 5 % of the sea power; coherent (sinc amplitude with the scatterer's phase) for
      complex data.
    * ``ambiguities``: azimuth ambiguities (ghosts, orders k = -1 and +1) of every ship, where
      :mod:`sarship.pipeline.targets.ambiguity` expects them (eq. 1: ``dt_k = -k lambda R PRF / (2
      Vr^2)`` along azimuth, ~5 km; eq. 3: the range shift ``lambda^2 R ((f_dc + k PRF)^2 -
      f_dc^2) / (8 Vr^2)``, 3-4 columns at 10 m) for the simulated sensor of
      :mod:`~sarship.pipeline.simulate.geometry` (written to the scene as ``sar_geometry``),
      rounded to whole pixels; at -20 dB (the azimuth ambiguity-to-signal ratio of C-band
      sensors, -20 to -25 dB: Sentinel-1 requires <= -22 dB, docs/references.md#torres2012),
      smeared over 7 rows (defocus: a quadratic-phase kernel for complex data). A ghost of a
      faint ship lies below the sea and is not seen. Listed under the truth member
      ``ambiguities`` (``ambiguity_of``: the ship's id; ``order``: k).
    * ``stripes``: azimuth stripes (antenna-pattern / beam-seam gain errors): a gain constant
      along azimuth, piecewise constant across range in bands 24-384 px wide, N(0, 0.8) dB
      clipped to +-2.5 dB; multiplies everything (sqrt of it for complex data).
    * ``rfi``: radio interference: 1 + rows // 1024 bands of 1-4 range lines (rows), over
      30-100 % of the columns, +3..12 dB over the sea, sinusoidally modulated (60 %) along
      range, added before the stripes. Intensity scenes: noise-like (exponential intensity).
      Complex scenes: narrow-band, 1-2 tones along range (frequencies U(0.02, 0.48) cycles/px,
      a random phase per range line), so RFI has the complex character of Leng et al. 2019
      (docs/references.md#leng2019rfi): constant envelope up to the modulation and the tones'
      beating (sub-Gaussian, CSK -1 to -0.5) and circular over a line.
      Listed under the truth member ``rfi``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sarship.pipeline.simulate.config import SimConfig
from sarship.pipeline.simulate.fields import _S_RFI, _S_STRIPES, _rng

SIDELOBE_OS = 1.2  # resolution / pixel spacing
SIDELOBE_MIN = 10.0  # scatterer power / sea power for drawing sidelobes
SIDELOBE_FLOOR = 0.05  # sidelobes drawn out to this fraction of the sea power
SIDELOBE_MAX_PX = 1024
AMBIG_LEVEL_DB = -20.0
AMBIG_SMEAR = 3  # ghost smear half-length (rows)


def _stripes_gain(cfg: SimConfig) -> np.ndarray:
    W = cfg.shape[1]
    rng = _rng(cfg.seed, _S_STRIPES)
    g = np.empty(W, dtype=np.float64)
    c = 0
    while c < W:
        w = int(rng.integers(24, 385))
        db = float(np.clip(rng.normal(0.0, 0.8), -2.5, 2.5))
        g[c : c + w] = 10.0 ** (db / 10.0)
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
        out.append(
            {
                "id": e,
                "rows": [r0, r0 + thick],
                "cols": [c0, c0 + n],
                "level_db": float(rng.uniform(3.0, 12.0)),
                "period_px": float(rng.uniform(40.0, 400.0)),
                "phase": float(rng.uniform(0.0, 2 * math.pi)),
                "modulation": 0.6,
            }
        )
    return out


def _sidelobe_ratio(k: np.ndarray, d: float) -> np.ndarray:
    """Amplitude of the sinc IRF at integer offsets k from the peak pixel (sub-pixel offset d)."""
    return np.sinc((k - d) / SIDELOBE_OS) / np.sinc(-d / SIDELOBE_OS)
