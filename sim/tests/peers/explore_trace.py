#!/usr/bin/env python3
"""pymavlink peer: record the position trace of `shotpilot-sim --script
explore` until the script hands over (mode AUTO.LOITER / LOITER), and
summarise it (duration, path length, altitude bands, extent).

Usage: explore_trace.py [--listen udpin:127.0.0.1:14550] [--trace out.csv]
"""
import argparse
import json
import math
import os
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

m2 = mavutil.mavlink
PX4_LOITER = (4 << 16) | (3 << 24)
ARDU_LOITER = 5


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", default="udpin:127.0.0.1:14550")
    ap.add_argument("--trace", default=None)
    ap.add_argument("--timeout", type=float, default=900.0)
    args = ap.parse_args()
    conn = mavutil.mavlink_connection(args.listen, source_system=255, source_component=190)
    hb = conn.wait_heartbeat(timeout=15)
    if hb is None:
        print(json.dumps({"ok": False, "error": "no heartbeat"}))
        return 1
    loiter = ARDU_LOITER if hb.autopilot == m2.MAV_AUTOPILOT_ARDUPILOTMEGA else PX4_LOITER
    t0 = time.time()
    trace, modes, took_off = [], [], False
    done = False
    while time.time() - t0 < args.timeout and not done:
        msg = conn.recv_match(type=["LOCAL_POSITION_NED", "HEARTBEAT", "ATTITUDE"], blocking=True, timeout=1.0)
        if msg is None:
            continue
        if msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == conn.target_system:
            if not modes or modes[-1][1] != msg.custom_mode:
                modes.append((round(time.time() - t0, 1), msg.custom_mode))
            armed = bool(msg.base_mode & m2.MAV_MODE_FLAG_SAFETY_ARMED)
            if took_off and armed and msg.custom_mode == loiter:
                done = True
        elif msg.get_type() == "LOCAL_POSITION_NED":
            trace.append((round(time.time() - t0, 2), msg.x, msg.y, msg.z))
            if -msg.z > 2.0:
                took_off = True
    length = sum(math.dist(a[1:], b[1:]) for a, b in zip(trace, trace[1:]))
    alts = [-r[3] for r in trace]
    bands = {}
    for a in alts:
        if a > 1.0:
            b = int(round(a / 5.0) * 5)
            bands[b] = bands.get(b, 0) + 1
    if args.trace:
        with open(args.trace, "w") as f:
            f.write("t_s,north_m,east_m,down_m\n")
            for r in trace:
                f.write("%.2f,%.3f,%.3f,%.3f\n" % r)
    rate = len(trace) / max(1e-9, trace[-1][0] - trace[0][0]) if len(trace) > 1 else 0
    summary = {
        "ok": done,
        "seconds": round(trace[-1][0], 1) if trace else 0,
        "samples": len(trace),
        "local_position_rate_hz": round(rate, 2),
        "path_length_m": round(length, 1),
        "north_range_m": [round(min(r[1] for r in trace), 1), round(max(r[1] for r in trace), 1)] if trace else None,
        "east_range_m": [round(min(r[2] for r in trace), 1), round(max(r[2] for r in trace), 1)] if trace else None,
        "max_alt_m": round(max(alts), 1) if alts else None,
        "samples_per_5m_altitude_band": dict(sorted(bands.items())),
        "modes": modes,
        "final": [round(v, 2) for v in trace[-1][1:]] if trace else None,
    }
    print(json.dumps(summary))
    return 0 if done else 1


if __name__ == "__main__":
    sys.exit(main())
