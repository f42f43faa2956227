"""``csk`` and the complex statistics on the real OpenSARShip SLC chips (issue 15's checks).

The dual-pol Sentinel-1 IW SLC chips of OpenSARShip (Huang et al. 2018; the shared data folder,
``../shared/data/real/opensarship/S1A_IW_SLC__*``: bands [VH re, VH im, VV re, VV im], each chip
centred on one AIS-matched ship): each channel is taken as a single-channel SLC. For each:

- ``csk`` at its defaults (or ``--pfa``, ``--window``): whether a detection covers the chip's
  ship (a detection pixel in the central quarter of the chip, |dy| <= H/4 and |dx| <= W/4:
  the data's README says the ship fills about the central quarter), and how many other
  detections (components joined by ``merge_px`` as the pipeline joins them);
- the sea CSK near 0 (the paper's claim): the zero-mean CSK of eq 37 of the chip's border frame
  (outer ``--border`` fraction of each side, away from the centred ship), and the mean window CSK
  there;
- the detections' complex properties (``csk``, ``noncircularity``, ``rfi``) of the centre ship.

``python bench/realdata_csk.py [--pfa 1e-6] [--window 7]``; prints Markdown for bench/REALDATA.md.
"""

from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path

import numpy as np
from scipy import ndimage

from sarship.pipeline.detectors import csk
from sarship.pipeline.targets.components import merge_radius
from sarship.pipeline.tiling import boxsum
from sarship.pipeline.tiling.windows import mirror_pad

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "opensarship"


def chips() -> list[tuple[str, str, np.ndarray]]:
    import tifffile

    out = []
    for f in sorted(glob.glob(str(DATA / "S1A_IW_SLC*" / "Patch" / "*.tif"))):
        a = tifffile.imread(f).astype(np.float64)
        for k, ch in enumerate(("vh", "vv")):
            out.append((os.path.basename(f), ch, (a[..., 2 * k] + 1j * a[..., 2 * k + 1]).astype(np.complex64)))
    return out


def run(pfa: float, window: int, border: float) -> str:
    p = csk.CSKParams(pfa=pfa, window=window)
    prep = csk.prepare(p)
    h = window // 2
    rows = []
    found = 0
    others = []
    sea_csk, sea_win = [], []
    for name, ch, z in chips():
        mask, stat = csk.detect(mirror_pad(z, h), h, (-h, -h), p, prep)
        r = merge_radius(p.merge_px)
        lab, n = ndimage.label(
            ndimage.binary_dilation(mask, np.ones((2 * r + 1,) * 2)) if r else mask, structure=np.ones((3, 3))
        )
        lab = np.where(mask, lab, 0)
        H, W = z.shape
        cy, cx = (H - 1) / 2, (W - 1) / 2
        yy, xx = np.nonzero(mask)
        near = (np.abs(yy - cy) <= H / 4) & (np.abs(xx - cx) <= W / 4)
        centre_labels = set(lab[yy[near], xx[near]].tolist())
        hit = bool(centre_labels)
        found += hit
        n_other = len(set(np.unique(lab[lab > 0]).tolist()) - centre_labels)
        others.append(n_other)
        b = max(3, int(round(border * min(H, W))))
        frame = np.ones(z.shape, bool)
        frame[b : H - b, b : W - b] = False
        kb, _ = csk.complex_stats(z[frame])
        sea_csk.append(kb)
        k, tested, pw, s11 = csk.csk_window(mirror_pad(z, h), h, (-h, -h), window, None, boxsum.centered_box_sum, np)
        sea_win.append(float(k[frame & tested].mean()))
        if hit:
            comp = np.isin(lab, list(centre_labels))
            kc, nc = csk.complex_stats(z[comp])
            rfi = csk.rfi_flag(int(comp.sum()), kc, nc)
        else:
            kc = nc = float("nan")
            rfi = False
        rows.append(
            f"| {name} | {ch} | {H}x{W} | {'yes' if hit else 'no'} | {n_other} | {kc:.2f} | {nc:.2f} | "
            f"{'yes' if rfi else 'no'} | {kb:.2f} | {sea_win[-1]:.2f} |"
        )
    n = len(rows)
    head = [
        f"`csk` pfa {pfa:g}, window {window} (threshold {prep['threshold']:.3f}, cells {p.cells}); centre ship "
        f"= a detection pixel in the chip's central quarter; sea = the outer {border:.0%} frame.",
        "",
        "| chip | channel | size | centre ship found | other detections | centre CSK | centre non-circ. | rfi | "
        "sea frame CSK | sea mean window CSK |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    tail = [
        "",
        f"Centre ship found on {found} of {n} channel-chips ({found / n:.0%}); other detections per chip: "
        f"mean {np.mean(others):.2f}, max {max(others)}; sea frame CSK: median {np.median(sea_csk):.2f} "
        f"(range {min(sea_csk):.2f} .. {max(sea_csk):.2f}); mean window CSK on the frame: median "
        f"{np.median(sea_win):.2f} (circular Gaussian: {-4 / (window * window + 1):.2f}).",
    ]
    return "\n".join(head + rows + tail)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pfa", type=float, default=1e-6)
    ap.add_argument("--window", type=int, default=7)
    ap.add_argument("--border", type=float, default=0.15)
    a = ap.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"no OpenSARShip data at {DATA}")
    print(run(a.pfa, a.window, a.border))


if __name__ == "__main__":
    main()
