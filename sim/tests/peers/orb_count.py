#!/usr/bin/env python3
"""Counts OpenCV ORB features on every frame of a rendered TUM-layout dataset.

Usage: orb_count.py DATASET_DIR [--features 1000] [--min 500] [--share 0.95]

Reads DATASET_DIR/rgb.txt, runs cv2.ORB_create(N) on each frame, and reports
the per-frame counts (min, percentiles, mean), the share of frames with at
least --min features, and how well spread they are (occupied cells of an
8x6 grid). Exits 1 if fewer than --share of the frames reach --min.
Peer: opencv-python-headless (pip install into /work/venv).
"""
import argparse
import os
import sys

import cv2
import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--features", type=int, default=1000)
    ap.add_argument("--min", type=int, default=500)
    ap.add_argument("--share", type=float, default=0.95)
    args = ap.parse_args()

    frames = []
    with open(os.path.join(args.dataset, "rgb.txt")) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            ts, name = line.split()[:2]
            frames.append((float(ts), os.path.join(args.dataset, name)))
    if not frames:
        print("no frames", file=sys.stderr)
        return 1

    orb = cv2.ORB_create(args.features)
    counts, cells = [], []
    for ts, path in frames:
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            print(f"cannot read {path}", file=sys.stderr)
            return 1
        kps = orb.detect(img, None)
        counts.append(len(kps))
        h, w = img.shape
        occupied = {(int(k.pt[0] * 8 // w), int(k.pt[1] * 6 // h)) for k in kps}
        cells.append(len(occupied))
    counts = np.array(counts)
    cells = np.array(cells)
    ok = counts >= args.min
    share = ok.mean()
    print(f"frames: {len(counts)}")
    print(f"ORB({args.features}) features per frame: min {counts.min()}, p5 {np.percentile(counts, 5):.0f}, "
          f"median {np.median(counts):.0f}, mean {counts.mean():.1f}, max {counts.max()}")
    print(f"frames with >= {args.min} features: {ok.sum()} / {len(counts)} = {100 * share:.1f}%")
    print(f"occupied cells of an 8x6 grid: min {cells.min()}, median {np.median(cells):.0f} of 48")
    worst = np.argsort(counts)[:5]
    print("fewest: " + ", ".join(f"{frames[i][0]:.3f}s:{counts[i]}" for i in worst))
    return 0 if share >= args.share else 1


if __name__ == "__main__":
    sys.exit(main())
