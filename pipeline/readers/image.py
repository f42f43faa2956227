"""PNG / JPEG amplitude input (Pillow), decoded whole.

**PNG / JPEG** (Pillow): grey, or RGB whose three channels are equal (HRSID stores grey
as RGB). JPEG noise may make grey channels differ slightly, so an RGB image is accepted as
grey when ``max |R-G|, |R-B|, |G-B| <= GREY_TOLERANCE_DN`` (8 DN) and ingested as the
mean of the three; any other colour image is refused. Pillow decodes the whole image
(8-bit, 1-3 bytes per pixel): PNG/JPEG are *not* streamed; use a tiled GeoTIFF for scenes
larger than memory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _check_hw, _one_line, _Source
from sarship.pipeline.readers.limits import InputLimits

#: Largest channel difference (digital numbers) of an RGB image still taken as grey.
GREY_TOLERANCE_DN = 8


class _ImageSource(_Source):
    data: np.ndarray | None = None

    def _read(self, r0, r1, c0, c1):
        return self.data[r0:r1, c0:c1, None]


def _open_image(p: Path, limits: InputLimits | None = None) -> _Source:
    from PIL import Image

    try:
        with Image.open(p) as im:
            (limits or InputLimits()).check_pixels(p, im.size[1], im.size[0])  # from the header
            im.load()
            mode = im.mode
            if mode == "1":
                im = im.convert("L")
            elif mode in ("P", "PA"):
                im = im.convert("RGBA")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
            a = np.asarray(im)
    except Image.DecompressionBombError as exc:
        raise InputError(
            f"'{p}': image too large to decode whole ({_one_line(exc)}); convert it to a tiled GeoTIFF"
        ) from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputError(f"'{p}': cannot decode image (truncated or damaged? {_one_line(exc)})") from None
    if a.ndim == 3:
        nch = a.shape[2]
        if nch == 2:  # LA: grey + alpha
            a = a[..., 0]
        elif nch >= 3:
            rgb = a[..., :3]
            diff = 0
            for r0 in range(0, rgb.shape[0], 1024):  # bounded temporaries
                blk = rgb[r0 : r0 + 1024].astype(np.int16)
                diff = max(
                    diff,
                    int(np.abs(blk[..., 0] - blk[..., 1]).max(initial=0)),
                    int(np.abs(blk[..., 0] - blk[..., 2]).max(initial=0)),
                    int(np.abs(blk[..., 1] - blk[..., 2]).max(initial=0)),
                )
            if diff > GREY_TOLERANCE_DN:
                raise InputError(
                    f"'{p}': colour image (RGB channels differ by up to {diff} DN > "
                    f"{GREY_TOLERANCE_DN}); expected a grey SAR amplitude image"
                )
            if diff == 0:
                a = np.ascontiguousarray(rgb[..., 0])
            else:
                g = np.empty(rgb.shape[:2], np.float32)
                for r0 in range(0, rgb.shape[0], 1024):
                    g[r0 : r0 + 1024] = rgb[r0 : r0 + 1024].astype(np.float32).mean(axis=2)
                a = g
        else:
            a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"'{p}': unsupported image layout {a.shape}")
    _check_hw(p, a.shape[0], a.shape[1])
    src = _ImageSource(path=p, shape=(a.shape[0], a.shape[1]), nbands=1, dtype=a.dtype, fmt="image")
    src.data = a
    src.meta["kind_hint"] = ("amplitude", "PNG/JPEG images are amplitude")
    src.meta["grey_from"] = mode
    return src
