#!/usr/bin/env python3
"""The periodic ceiling of a render of `make_set.py`, measured with its ground-truth lattice.

    python ideal_ceiling.py DIR/NAME.png [...] [--oversample 3]

What `woven prep IMAGE` prints as "the photo's mean repeat against the photo" is the PSNR (sRGB, 8-bit
PNG) of the mean of the aligned repeats, registered back to the image. Preparation estimates the
rotation, the pitch and the period, resamples the image twice (rectification, then the map back) and
registers each repeat; this script does none of that. It takes the true lattice from `NAME.json`
(`rotation_deg`, `view`, the spacings and the pattern size, conventions as in README.md), folds every
pixel centre into one period in world coordinates, bins the folded positions on a grid of
`oversample` bins per pixel and predicts each pixel by the mean of the *other* pixels of its bin
(leave-one-out, so the noise of the pixel itself is not counted as fitted). No pixel is resampled.

The gap between the two figures is what preparation loses on a clean image (lattice error,
interpolation blur); the ideal figure itself is bounded by the render's own noise (a 64 spp render
against the same scene at 1024 spp: about 30 dB) and by the positions within a bin (1/oversample px).
Prints `NAME ideal_db` per image.
"""
import argparse
import json
import os

import numpy as np
from PIL import Image


def ideal_ceiling(png, meta, oversample):
    img = np.asarray(Image.open(png).convert("RGB"), dtype=np.float64) / 255.0
    h, w, _ = img.shape
    win = meta["view"]["window"]
    cx, cy = meta["view"]["centre"]
    t = np.radians(meta["rotation_deg"])
    right = np.array([np.cos(t), np.sin(t)])
    up = np.array([-np.sin(t), np.cos(t)])
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    # Pixel centre to world (README: pixel_to_world).
    u = (cols + 0.5) * win / w - win / 2
    v = win / 2 - (rows + 0.5) * win / h
    x = cx + u * right[0] + v * up[0]
    y = cy + u * right[1] + v * up[1]
    pat = np.array(meta["pattern"])
    period_x = pat.shape[1] * meta["warp"]["spacing"]
    period_y = pat.shape[0] * meta["weft"]["spacing"]
    px_per_world = w / win
    nbx = max(1, int(round(period_x * px_per_world * oversample)))
    nby = max(1, int(round(period_y * px_per_world * oversample)))
    bx = (np.mod(x, period_x) / period_x * nbx).astype(int) % nbx
    by = (np.mod(y, period_y) / period_y * nby).astype(int) % nby
    idx = (by * nbx + bx).ravel()
    n = np.bincount(idx, minlength=nbx * nby)[idx]
    pred = np.empty_like(img)
    for c in range(3):
        ch = img[..., c].ravel()
        s = np.bincount(idx, ch, minlength=nbx * nby)[idx]
        # A pixel alone in its bin has no other sample: it predicts itself (rare at oversample ≤ 3).
        pred[..., c] = np.where(n > 1, (s - ch) / np.maximum(n - 1, 1), ch).reshape(h, w)
    mse = np.mean((pred - img) ** 2)
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images", nargs="+", help="NAME.png files of make_set.py (NAME.json beside each)")
    ap.add_argument("--oversample", type=int, default=3, help="bins per pixel along each axis")
    a = ap.parse_args()
    if a.oversample < 1:
        ap.error("--oversample must be at least 1")
    for png in a.images:
        if png.endswith("_labels.png"):
            continue
        js = png[: -len(".png")] + ".json"
        if not os.path.exists(js):
            raise SystemExit(f"{png}: no ground truth {js} beside it")
        with open(js) as f:
            meta = json.load(f)
        name = os.path.basename(png)[: -len(".png")]
        print(f"{name} {ideal_ceiling(png, meta, a.oversample):.1f}")


if __name__ == "__main__":
    main()
