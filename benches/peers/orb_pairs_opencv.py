#!/usr/bin/env python3
"""OpenCV ORB on shotpilot's homography-warp evaluation pairs.

Usage: orb_pairs_opencv.py PAIRS_DIR [--features N]

PAIRS_DIR holds what shotpilot's `features_eval::write_pairs` writes:
pairs.json and a_NNN.png / b_NNN.png / mask_NNN.png. For every pair this runs
cv2.ORB_create(nfeatures=N, scaleFactor=1.2, nlevels=8).detectAndCompute on a
(no mask) and on b (with its mask, as shotpilot does), and writes
PAIRS_DIR/opencv_features.json:
[{"a": {"kps": [[x, y, angle, octave, response, size], ...], "desc": [hex, ...]}, "b": {...}}]
Descriptors are OpenCV's 32 bytes in hex. The metrics are computed in Rust on
these, with the same code as for shotpilot's own features.
"""
import argparse
import json
import os

import cv2


def side(orb, img, mask):
    kps, desc = orb.detectAndCompute(img, mask)
    out = {"kps": [], "desc": []}
    if desc is None:
        return out
    for k, d in zip(kps, desc):
        out["kps"].append([float(k.pt[0]), float(k.pt[1]), float(k.angle),
                           int(k.octave), float(k.response), float(k.size)])
        out["desc"].append(bytes(d).hex())
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("pairs_dir")
    ap.add_argument("--features", type=int, default=1000)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    orb = cv2.ORB_create(nfeatures=args.features, scaleFactor=1.2, nlevels=8)
    with open(os.path.join(args.pairs_dir, "pairs.json")) as f:
        pairs = json.load(f)
    result = []
    for p in pairs:
        read = lambda name: cv2.imread(os.path.join(args.pairs_dir, name), cv2.IMREAD_GRAYSCALE)
        a, b, mask = read(p["a"]), read(p["b"]), read(p["mask"])
        if a is None or b is None or mask is None:
            raise SystemExit(f"cannot read pair {p}")
        result.append({"a": side(orb, a, None), "b": side(orb, b, mask)})
    with open(os.path.join(args.pairs_dir, "opencv_features.json"), "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
