#!/usr/bin/python3
"""The web streams' loss against a held-out camera's captured image, from web_bench's outputs.

  /usr/bin/python3 bench/web_loss.py DIR [CAMERA] [FRAME]

DIR is web_bench's work folder (DIR/take, DIR/site, DIR/browser/<stream>.png: the page's
pictures through CAMERA's pose at FRAME). The page draws the subject over black; the captured
image shows the studio behind it, so each picture is laid over the clean plate (the take's frame
set 0) where the page left black, then compared with the captured image inside the subject's
bounding box (its ground-truth silhouette's rectangle, grown by 8 px). The loss of a level is how
far its PSNR falls below the lossless stream's of the same kind.
"""
import json
import math
import sys

import cv2
import numpy as np


def psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255.0**2
    return 99.0 if mse <= 1e-12 else 10 * math.log10(1 / mse)


def main():
    root = sys.argv[1]
    camera = sys.argv[2] if len(sys.argv) > 2 else "cam1"
    frame = int(sys.argv[3]) if len(sys.argv) > 3 else 15
    manifest = json.load(open(f"{root}/site/manifest.json"))
    frame_set = manifest["frames"][frame]["set"]
    captured = cv2.imread(f"{root}/take/frames/{camera}/{frame_set:06d}.png")
    plate = cv2.imread(f"{root}/take/frames/{camera}/000000.png")
    mask = cv2.imread(f"{root}/take/gt/masks/{camera}/{frame_set:06d}.png", cv2.IMREAD_GRAYSCALE)
    ys, xs = np.nonzero(mask)
    y0, y1 = max(ys.min() - 8, 0), min(ys.max() + 9, mask.shape[0])
    x0, x1 = max(xs.min() - 8, 0), min(xs.max() + 9, mask.shape[1])
    print(f"# {camera}, frame {frame} (set {frame_set}): subject box x {x0}..{x1 - 1}, "
          f"y {y0}..{y1 - 1} ({(x1 - x0) * (y1 - y0)} px); pictures over the clean plate")
    rows = []
    for stream in manifest["streams"]:
        shot = cv2.imread(f"{root}/browser/{stream['name']}.png")
        empty = np.all(shot == 0, axis=2)
        shot[empty] = plate[empty]
        db = psnr(shot[y0:y1, x0:x1], captured[y0:y1, x0:x1])
        rows.append((stream, db))
    lossless = {s["kind"]: db for s, db in rows if s["quality"] == "lossless"}
    print(f"{'stream':15s} {'Mbps@30':>8s} {'PSNR cap':>9s} {'loss dB':>8s}")
    for stream, db in rows:
        print(f"{stream['name']:15s} {stream['mbps']:8.2f} {db:9.2f} "
              f"{lossless[stream['kind']] - db:8.2f}")


if __name__ == "__main__":
    main()
