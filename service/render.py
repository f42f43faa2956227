"""Products rendered from a finished job's outputs: the quicklook PNG and the mask GeoTIFF."""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path


def preview_png(job_dir: Path, size: int) -> Path:
    """Quicklook of a finished job (made once per size, atomically): the scene's intensity
    in dB (2-98 % stretch) decimated to at most ``size`` pixels a side, detected pixels in
    red, detection boxes in yellow."""
    out = job_dir / f"preview-{size}.png"
    if out.exists():
        return out
    import numpy as np
    import zarr
    from PIL import Image, ImageDraw

    from pipeline.inputs import intensity_source, make_reader
    from pipeline.scene import open_scene

    run = json.loads((job_dir / "run.json").read_text())
    scene = open_scene(run["scene"]["path"])
    H, W = scene.shape
    step = max(1, -(-max(H, W) // size))
    var, transform = intensity_source(scene)
    read = make_reader(str(scene.path), var, transform)
    rows = []
    for r0 in range(0, H, 1024 * step):  # bounded memory: strips of rows, decimated as read
        r1 = min(r0 + 1024 * step, H)
        rows.append(read(r0, r1, 0, W)[::step, ::step])
    x = np.concatenate(rows).astype(np.float32)
    with np.errstate(all="ignore"):
        db = 10.0 * np.log10(np.where(x > 0, x, np.nan))
    fin = np.isfinite(db)
    lo, hi = (np.percentile(db[fin], [2, 98]) if fin.any() else (0.0, 1.0))
    g = np.clip((np.nan_to_num(db, nan=lo) - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    rgb = np.stack([g, g, g], -1)
    m = zarr.open_group(str(job_dir / "mask.zarr"), mode="r")["mask"]
    mrows = [np.asarray(m[r0: min(r0 + 1024 * step, H), :])[::step, ::step] for r0 in range(0, H, 1024 * step)]
    mk = np.concatenate(mrows).astype(bool)
    rgb[mk] = (255, 40, 40)
    img = Image.fromarray(rgb)
    draw = ImageDraw.Draw(img)
    fc = json.loads((job_dir / "detections.geojson").read_text())
    for f in fc.get("features", []):
        bb = f["properties"].get("bbox_px")
        if bb:
            r0, c0, r1, c1 = bb
            draw.rectangle([c0 // step - 2, r0 // step - 2, c1 // step + 2, r1 // step + 2], outline=(255, 220, 0))
    tmp = job_dir / f".preview-{uuid.uuid4().hex[:8]}.png"
    img.save(tmp, format="PNG")
    os.replace(tmp, out)
    return out


def mask_geotiff(job_dir: Path) -> Path:
    """The job's mask as a tiled, deflate-compressed GeoTIFF (made once, atomically)."""
    out = job_dir / "mask.tif"
    if out.exists():
        return out
    import numpy as np
    import tifffile
    import zarr

    g = zarr.open_group(str(job_dir / "mask.zarr"), mode="r")
    arr = g["mask"]
    tmp = job_dir / f".mask-{uuid.uuid4().hex[:8]}.tif"
    extratags = []
    tr = g.attrs.get("transform")
    if tr:  # ModelPixelScale + ModelTiepoint for a north-up affine (a, b, c, d, e, f)
        a, b, c, d, e, f = tr[:6]
        if b == 0 and d == 0:
            extratags = [(33550, "d", 3, (a, -e, 0.0)), (33922, "d", 6, (0.0, 0.0, 0.0, c, f, 0.0))]
    data = np.asarray(arr[...], dtype=np.uint8)
    tifffile.imwrite(tmp, data, tile=(256, 256), compression="zlib", extratags=extratags,
                     metadata=None, photometric="minisblack")
    os.replace(tmp, out)
    return out
