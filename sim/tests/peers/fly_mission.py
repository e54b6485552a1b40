#!/usr/bin/env python3
"""pymavlink peer: connect to shotpilot-sim over UDP, see heartbeat and
position, upload a 3-item mission, download it back and compare, arm, start
it and record the position trace until the mission completes.

Usage: fly_mission.py [--listen udpin:127.0.0.1:14550] [--trace trace.csv]
Prints a JSON summary on stdout; exits non-zero on failure.
With --listen udpin:HOST:0 the first line is "listening PORT", the port the
kernel picked (where the simulator must send).
"""
import argparse
import json
import math
import os
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from lossy_upload import download as robust_download  # noqa: E402
from lossy_upload import upload as robust_upload  # noqa: E402

m2 = mavutil.mavlink


def wait(conn, types, timeout, cond=None):
    end = time.time() + timeout
    while time.time() < end:
        msg = conn.recv_match(type=types, blocking=True, timeout=max(0.01, end - time.time()))
        if msg is None:
            continue
        if cond is None or cond(msg):
            return msg
    return None


def ned_to_latlon(lat0, lon0, north, east):
    # Small offsets: spherical approximation is plenty for choosing targets.
    r = 6378137.0
    lat = lat0 + math.degrees(north / r)
    lon = lon0 + math.degrees(east / (r * math.cos(math.radians(lat0))))
    return int(round(lat * 1e7)), int(round(lon * 1e7))


def command(conn, cmd, params, timeout=3.0):
    p = list(params) + [0.0] * (7 - len(params))
    for _ in range(5):
        conn.mav.command_long_send(conn.target_system, conn.target_component, cmd, 0, *p)
        ack = wait(conn, ["COMMAND_ACK"], timeout / 5, lambda m: m.command == cmd)
        if ack is not None:
            return ack.result
    return None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", default="udpin:127.0.0.1:14550")
    ap.add_argument("--trace", default=None)
    ap.add_argument("--timeout", type=float, default=180.0)
    ap.add_argument("--capture", action="store_true",
                    help="add a gimbal pitch -90 and an IMAGE_START_CAPTURE after waypoint 1 and check "
                         "CAMERA_IMAGE_CAPTURED and the file")
    args = ap.parse_args()

    conn = mavutil.mavlink_connection(args.listen, source_system=255, source_component=190)
    if args.listen.endswith(":0"):
        # Port 0: the kernel picked one; the simulator is told to send there.
        print(f"listening {conn.port.getsockname()[1]}", flush=True)
    t0 = time.time()
    hb = conn.wait_heartbeat(timeout=10)
    if hb is None:
        print(json.dumps({"ok": False, "error": "no heartbeat"}))
        return 1
    hb_latency = time.time() - t0
    summary = {
        "heartbeat": {
            "autopilot": hb.autopilot,
            "type": hb.type,
            "custom_mode": hb.custom_mode,
            "system": conn.target_system,
        }
    }
    # Tell the sim who we are.
    conn.mav.heartbeat_send(m2.MAV_TYPE_GCS, m2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    home = wait(conn, ["HOME_POSITION"], 5.0)
    pos = wait(conn, ["GLOBAL_POSITION_INT"], 5.0)
    if pos is None or home is None:
        print(json.dumps({"ok": False, "error": "no position/home"}))
        return 1
    lat0, lon0 = home.latitude * 1e-7, home.longitude * 1e-7
    summary["first_position"] = {"lat": pos.lat * 1e-7, "lon": pos.lon * 1e-7, "relative_alt_m": pos.relative_alt / 1000}

    # The 3-item mission: takeoff to 15 m, waypoint 40 m north / 20 m east
    # with a 2 s hold and yaw 90, waypoint 40 m north / 20 m west.
    a = ned_to_latlon(lat0, lon0, 40.0, 20.0)
    b = ned_to_latlon(lat0, lon0, 40.0, -20.0)
    frame = m2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    items = [
        (0, frame, m2.MAV_CMD_NAV_TAKEOFF, 0, 1, 0.0, 0.0, 0.0, float("nan"), 0, 0, 15.0),
        (1, frame, m2.MAV_CMD_NAV_WAYPOINT, 0, 1, 2.0, 1.0, 0.0, 90.0, a[0], a[1], 15.0),
        (2, frame, m2.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 1.0, 0.0, float("nan"), b[0], b[1], 15.0),
    ]
    ardupilot = hb.autopilot == m2.MAV_AUTOPILOT_ARDUPILOTMEGA
    if args.capture:
        # Gimbal protocol v2: PX4 runs mission gimbal items as the autopilot,
        # which must be in control (a CONFIGURE item, -2: itself); ArduPilot
        # has no such item, the ground station takes control before the start.
        gimbal = [(2, m2.MAV_FRAME_MISSION, m2.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, 0, 1, -90.0, 0.0, float("nan"), float("nan"), 0, 0, 0.0)]
        if not ardupilot:
            gimbal = [(2, m2.MAV_FRAME_MISSION, m2.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, 0, 1, -2.0, -2.0, -1.0, -1.0, 0, 0, 0.0)] + gimbal
        rest = [(m2.MAV_FRAME_MISSION, m2.MAV_CMD_IMAGE_START_CAPTURE, 0, 1, 0.0, 0.0, 1.0, 0.0, 0, 0, 0.0), items[2][1:]]
        items = items[:2] + [(2 + i,) + g[1:] for i, g in enumerate(gimbal)] + [
            (2 + len(gimbal) + i,) + r for i, r in enumerate(rest)]
    if ardupilot:
        # ArduPilot: item 0 is home (its content is replaced by the vehicle).
        items = [(0, m2.MAV_FRAME_GLOBAL, m2.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
                  int(round(lat0 * 1e7)), int(round(lon0 * 1e7)), home.altitude / 1000.0)] + [
            (it[0] + 1,) + it[1:] for it in items]
    # Upload with QGC-like retries (lossy_upload.py): re-send MISSION_COUNT
    # until requested, answer every request, re-send the last item until ACKed.
    t_up = time.time()
    ok_up, why, secs, stats = robust_upload(conn, items, 1.5, 5)
    result = m2.MAV_MISSION_ACCEPTED if ok_up else why
    requests = stats
    summary["upload"] = {"result": result, "requests": requests, "seconds": round(time.time() - t_up, 3)}
    if result != m2.MAV_MISSION_ACCEPTED:
        print(json.dumps({"ok": False, **summary}))
        return 1

    # Download it back (re-requesting on timeout).
    got = robust_download(conn, 1.5, 10) or []
    def same(it, ref):
        def feq(x, y):
            return (math.isnan(x) and math.isnan(y)) or x == y
        return (it.seq == ref[0] and it.frame == ref[1] and it.command == ref[2] and it.autocontinue == ref[4]
                and feq(it.param1, ref[5]) and feq(it.param2, ref[6]) and feq(it.param3, ref[7]) and feq(it.param4, ref[8])
                and it.x == ref[9] and it.y == ref[10] and feq(it.z, ref[11]))


    first = 1 if ardupilot else 0
    identical = len(got) == len(items) and all(same(g, r) for g, r in zip(got[first:], items[first:]))
    summary["download"] = {"count": len(got), "identical": identical}
    if ardupilot and got:
        summary["download"]["seq0_home"] = [got[0].x, got[0].y, got[0].z]
    if not identical:
        print(json.dumps({"ok": False, **summary}))
        return 1

    # Arm and start.
    if args.capture and ardupilot:
        command(conn, m2.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, [-2, -2, -1, -1, 0, 0, 0])
    arm = command(conn, m2.MAV_CMD_COMPONENT_ARM_DISARM, [1])
    start = command(conn, m2.MAV_CMD_MISSION_START, [0, 0])
    summary["arm_result"] = arm
    summary["mission_start_result"] = start
    t_start = time.time()
    trace = []
    reached = []
    done = False
    while time.time() - t_start < args.timeout and not done:
        msg = wait(conn, ["GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "MISSION_ITEM_REACHED", "MISSION_CURRENT",
                          "CAMERA_IMAGE_CAPTURED"], 1.0)
        if msg is None:
            continue
        t = msg.get_type()
        if t == "LOCAL_POSITION_NED":
            trace.append((round(time.time() - t_start, 2), round(msg.x, 2), round(msg.y, 2), round(msg.z, 2)))
        elif t == "MISSION_ITEM_REACHED":
            if msg.seq not in reached:
                reached.append(msg.seq)
                summary.setdefault("reached_at_s", {})[msg.seq] = round(time.time() - t_start, 2)
        elif t == "CAMERA_IMAGE_CAPTURED":
            url = msg.file_url if isinstance(msg.file_url, str) else msg.file_url.decode(errors="replace")
            path = url[len("file://"):] if url.startswith("file://") else url
            summary.setdefault("captures", []).append({
                "index": msg.image_index, "result": msg.capture_result, "file": path,
                "exists": os.path.exists(path), "bytes": os.path.getsize(path) if os.path.exists(path) else 0,
                "relative_alt_m": msg.relative_alt / 1000.0, "q": [round(v, 4) for v in msg.q]})
        elif t == "MISSION_CURRENT":
            if getattr(msg, "mission_state", 0) == m2.MISSION_STATE_COMPLETE:
                done = True
    summary["reached"] = reached
    summary["mission_complete"] = done
    if args.trace:
        with open(args.trace, "w") as f:
            f.write("t_s,north_m,east_m,down_m\n")
            for row in trace:
                f.write(",".join(str(v) for v in row) + "\n")
    if trace:
        summary["trace"] = {
            "samples": len(trace),
            "max_alt_m": max(-r[3] for r in trace),
            "max_north_m": max(r[1] for r in trace),
            "min_east_m": min(r[2] for r in trace),
            "max_east_m": max(r[2] for r in trace),
            "final": trace[-1][1:],
            "every_5s": [r for i, r in enumerate(trace) if i % 25 == 0],
        }
    want = list(range(len(items)))[1:] if ardupilot else list(range(len(items)))
    ok = done and reached == want and arm == 0 and start == 0
    if args.capture:
        caps = summary.get("captures", [])
        ok = ok and len(caps) == 1 and caps[0]["exists"] and caps[0]["result"] == 1
    summary["ok"] = ok
    print(json.dumps(summary))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
