"""Peer timing for benches/shot.rs: OpenCV's warpPerspective on the same
640x480 synthetic image and anchors (inverse map, bilinear, black border).

Run: /work/venv/bin/python benches/peers/shot_warp_opencv.py
"""
import time

import cv2
import numpy as np

w, h = 640, 480
y, x = np.mgrid[0:h, 0:w]
img = ((x * 7 + y * 13) % 251).astype(np.uint8)
corners = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
anchors = np.float32([[40, 25], [610, 5], [630, 470], [15, 455]])
H = cv2.getPerspectiveTransform(corners, anchors)  # shot pixel -> keyframe pixel
flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
for threads in (1, 0):
    cv2.setNumThreads(threads)
    for _ in range(20):
        cv2.warpPerspective(img, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    n = 300
    t0 = time.perf_counter()
    for _ in range(n):
        cv2.warpPerspective(img, H, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    dt = (time.perf_counter() - t0) / n
    print(f"opencv warpPerspective 640x480 (threads={threads or 'default'}): {dt * 1e3:.3f} ms")
