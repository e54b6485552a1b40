#!/usr/bin/env python3
"""OpenCV ORB peer for shotpilot's extractor timing.

Usage: orb_opencv.py DATASET_DIR [--features N] [--repeat R]

Reads the frames listed in DATASET_DIR/rgb.txt (TUM layout), converts them to
gray (cv2.cvtColor RGB->GRAY, the weights shotpilot uses), then times
cv2.ORB_create(nfeatures=N, scaleFactor=1.2, nlevels=8).detectAndCompute on each
frame with cv2.setNumThreads(1), after 3 warm-up calls. Prints one JSON object
per repeat: {"frames", "median_ms", "p95_ms", "mean_keypoints"}, the keys of
`shotpilot features --json`.
"""
import argparse
import json
import os
import time

import cv2
import numpy as np


def load_frames(root):
    frames = []
    with open(os.path.join(root, "rgb.txt")) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            rel = line.split()[1]
            bgr = cv2.imread(os.path.join(root, rel), cv2.IMREAD_COLOR)
            if bgr is None:
                raise SystemExit(f"cannot read {rel}")
            frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    return frames


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--features", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    frames = load_frames(args.dataset)
    orb = cv2.ORB_create(nfeatures=args.features, scaleFactor=1.2, nlevels=8)
    for _ in range(3):
        orb.detectAndCompute(frames[0], None)
    for _ in range(args.repeat):
        ms = []
        kps = 0
        for img in frames:
            t = time.perf_counter()
            k, d = orb.detectAndCompute(img, None)
            ms.append((time.perf_counter() - t) * 1e3)
            kps += len(k)
        ms.sort()
        pick = lambda q: ms[min(len(ms) - 1, int(round((len(ms) - 1) * q)))]
        print(json.dumps({
            "frames": len(frames),
            "median_ms": pick(0.5),
            "p95_ms": pick(0.95),
            "mean_keypoints": kps / len(frames),
        }))


if __name__ == "__main__":
    main()
