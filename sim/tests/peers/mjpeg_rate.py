#!/usr/bin/env python3
"""Checks a captured multipart/x-mixed-replace MJPEG stream and reports its rate.

Usage:
  curl -s -N -m 10 -D headers.txt -o stream.mjpg http://ADDR/video.mjpg
  mjpeg_rate.py stream.mjpg [--headers headers.txt]

Verifies the response Content-Type names the boundary, that every part starts
with the boundary, carries Content-Type image/jpeg, a Content-Length equal to
its body, an X-Timestamp, and a JPEG body (SOI..EOI); reports the number of
parts, sequence gaps, the rate from capture timestamps and from arrival count.
"""
import argparse
import sys


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stream")
    ap.add_argument("--headers")
    args = ap.parse_args()
    boundary = b"shotpilotframe"
    if args.headers:
        heads = open(args.headers, encoding="latin-1").read().lower()
        if "multipart/x-mixed-replace" not in heads or "boundary=" not in heads:
            print("response is not multipart/x-mixed-replace", file=sys.stderr)
            return 1
        boundary = heads.split("boundary=")[1].split()[0].strip().encode()
    data = open(args.stream, "rb").read()
    delim = b"--" + boundary + b"\r\n"
    parts, pos = [], 0
    while pos < len(data):
        if not data.startswith(delim, pos):
            print(f"byte {pos}: part does not start with the boundary", file=sys.stderr)
            return 1
        head_end = data.find(b"\r\n\r\n", pos)
        if head_end < 0:
            break  # truncated by the capture timeout
        headers = {}
        for line in data[pos + len(delim):head_end].decode("latin-1").split("\r\n"):
            k, v = line.split(":", 1)
            headers[k.strip().lower()] = v.strip()
        n = int(headers["content-length"])
        body = data[head_end + 4:head_end + 4 + n]
        if len(body) < n:
            break  # truncated
        if headers.get("content-type") != "image/jpeg" or body[:2] != b"\xff\xd8" or body[-2:] != b"\xff\xd9":
            print(f"part {len(parts)} is not a JPEG", file=sys.stderr)
            return 1
        if data[head_end + 4 + n:head_end + 6 + n] not in (b"\r\n", b""):
            print(f"part {len(parts)}: body longer than Content-Length", file=sys.stderr)
            return 1
        parts.append((float(headers["x-timestamp"]), int(headers.get("x-sequence", -1)), n))
        pos = head_end + 6 + n
    if len(parts) < 2:
        print("fewer than two parts", file=sys.stderr)
        return 1
    ts = [p[0] for p in parts]
    seqs = [p[1] for p in parts]
    gaps = sum(1 for a, b in zip(seqs, seqs[1:]) if b != a + 1)
    d = [b - a for a, b in zip(ts, ts[1:])]
    span = ts[-1] - ts[0]
    print(f"parts: {len(parts)} valid JPEG parts, mean {sum(p[2] for p in parts) / len(parts) / 1024:.1f} KiB")
    print(f"sequence {seqs[0]}..{seqs[-1]}, gaps {gaps}, repeats {sum(1 for a, b in zip(seqs, seqs[1:]) if b <= a)}")
    print(f"rate from capture timestamps: {(len(parts) - 1) / span:.2f} frames/s over {span:.2f} s "
          f"(interval min {min(d) * 1e3:.1f} ms, max {max(d) * 1e3:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
