#!/usr/bin/env python3
"""OpenCV peer for shotpilot's geometry: PnP-RANSAC and two-view on the
scenes the Rust test `tests/suite/geometry_peer_opencv.rs` writes.

Usage: geometry_opencv.py SCENES.json  ->  prints one JSON object.

PnP: cv2.solvePnPRansac with SOLVEPNP_AP3P minimal samples (OpenCV refines
the consensus with EPnP + LM), same threshold (sqrt(5.991) px), confidence
and iteration cap as ours. Two-view: cv2.findEssentialMat (Nister 5-point in
RANSAC, 1 px threshold) + cv2.recoverPose, i.e. the calibrated route, and
cv2.findHomography for the planar model. Times are medians of `reps` runs,
with OpenCV limited to one thread like ours.
"""
import json
import sys
import time

import cv2
import numpy as np


def rot_err_deg(r_est, r_true):
    c = (np.trace(r_est.T @ r_true) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def median_time(fn, reps):
    ts = []
    out = None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    return ts[len(ts) // 2] * 1e3, out


def main():
    # Single-threaded like ours (and the machine is shared).
    cv2.setNumThreads(1)
    with open(sys.argv[1]) as f:
        data = json.load(f)
    reps = data.get("reps", 5)
    res = {"opencv": cv2.__version__, "pnp": [], "two_view": []}
    for s in data["pnp"]:
        pw = np.array(s["pw"], dtype=np.float64)
        px = np.array(s["px"], dtype=np.float64)
        k = np.array(s["k"], dtype=np.float64).reshape(3, 3)
        r_true = np.array(s["r"], dtype=np.float64).reshape(3, 3)

        def run():
            return cv2.solvePnPRansac(
                pw, px, k, None,
                iterationsCount=1000,
                reprojectionError=float(np.sqrt(5.991)),
                confidence=0.9999,
                flags=cv2.SOLVEPNP_AP3P,
            )

        ms, (ok, rvec, tvec, inl) = median_time(run, reps)
        err = rot_err_deg(cv2.Rodrigues(rvec)[0], r_true) if ok else None
        res["pnp"].append({"ms": ms, "ok": bool(ok), "rot_err_deg": err})
    for s in data["two_view"]:
        p1 = np.array(s["kp1"], dtype=np.float64)
        p2 = np.array(s["kp2"], dtype=np.float64)
        k = np.array(s["k"], dtype=np.float64).reshape(3, 3)
        r_true = np.array(s["r"], dtype=np.float64).reshape(3, 3)
        t_true = np.array(s["t"], dtype=np.float64)

        def run():
            e, mask = cv2.findEssentialMat(p1, p2, k, method=cv2.RANSAC, prob=0.999, threshold=1.0)
            _, r, t, _ = cv2.recoverPose(e, p1, p2, k, mask=mask)
            return r, t

        ms, (r, t) = median_time(run, reps)
        t = t.ravel() / np.linalg.norm(t)
        tdir = float(np.degrees(np.arccos(np.clip(t @ (t_true / np.linalg.norm(t_true)), -1.0, 1.0))))
        hms, _ = median_time(lambda: cv2.findHomography(p1, p2, cv2.RANSAC, 2.45), reps)
        res["two_view"].append({"ms": ms, "rot_err_deg": rot_err_deg(r, r_true), "t_dir_err_deg": tdir, "homography_ms": hms})
    print(json.dumps(res))


if __name__ == "__main__":
    main()
