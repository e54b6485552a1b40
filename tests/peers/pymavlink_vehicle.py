#!/usr/bin/env python3
"""A minimal vehicle written with pymavlink, the independent peer of shotpilot's wire tests.

It listens on UDP, decodes what the ground station sends (heartbeats, a
mission upload), optionally with MAVLink 2 signing, answers as a PX4-like
autopilot (or an ArduPilot-like one with --autopilot ardupilot), and prints
one JSON summary on stdout. The first stdout line is "ready PORT" once the
socket is bound (PORT: the bound one; `--port 0` lets the kernel pick it). The summary's "items" are the uploaded MISSION_ITEM_INTs as
pymavlink decoded them, with the command's MAV_CMD name.

Usage: pymavlink_vehicle.py --port 0 [--key HEX] [--seconds 8] [--serve-upload]
                            [--autopilot px4|ardupilot]
"""
import argparse
import json
import math
import os
import sys
import time

os.environ["MAVLINK20"] = "1"
os.environ["MAVLINK_DIALECT"] = "common"
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mav  # noqa: E402


def clean(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--key", default="")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--serve-upload", action="store_true")
    ap.add_argument("--autopilot", choices=["px4", "ardupilot"], default="px4")
    args = ap.parse_args()
    if args.autopilot == "px4":
        autopilot, custom_mode = mav.MAV_AUTOPILOT_PX4, (4 << 16) | (3 << 24)  # AUTO.LOITER
    else:
        autopilot, custom_mode = mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 5  # LOITER

    m = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{args.port}", source_system=1, source_component=1, dialect="common"
    )
    if args.key:
        m.setup_signing(bytes.fromhex(args.key), sign_outgoing=True, link_id=0)
    print(f"ready {m.port.getsockname()[1]}", flush=True)

    out = {"heartbeats": 0, "signed_heartbeats": 0, "first_heartbeat": None, "items": None, "badsig": 0}
    deadline = time.time() + args.seconds
    next_hb = 0.0
    count = None
    nxt = 0
    items = []
    last_req = 0.0
    done_at = None
    gcs = (255, 190)
    while time.time() < deadline:
        now = time.time()
        if now >= next_hb:  # mavutil udpin sends only once a peer has spoken
            m.mav.heartbeat_send(
                mav.MAV_TYPE_QUADROTOR, autopilot, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                custom_mode, mav.MAV_STATE_STANDBY,
            )
            next_hb = now + 0.5
        if count is not None and nxt < count and now - last_req > 0.3:
            m.mav.mission_request_int_send(gcs[0], gcs[1], nxt, mav.MAV_MISSION_TYPE_MISSION)
            last_req = now
        if done_at is not None and now - done_at > 0.5:
            break
        msg = m.recv_match(blocking=True, timeout=0.05)
        if msg is None:
            continue
        t = msg.get_type()
        if t == "BAD_DATA":
            continue
        if t == "HEARTBEAT" and msg.get_srcSystem() != 1:
            out["heartbeats"] += 1
            if msg.get_signed():
                out["signed_heartbeats"] += 1
            if out["first_heartbeat"] is None:
                out["first_heartbeat"] = {
                    "sysid": msg.get_srcSystem(), "compid": msg.get_srcComponent(), "type": msg.type,
                    "autopilot": msg.autopilot, "base_mode": msg.base_mode, "custom_mode": msg.custom_mode,
                    "system_status": msg.system_status, "mavlink_version": msg.mavlink_version,
                }
        elif t == "MISSION_COUNT" and args.serve_upload and count is None:
            gcs = (msg.get_srcSystem(), msg.get_srcComponent())  # answer the uploader
            count = msg.count
            m.mav.mission_request_int_send(gcs[0], gcs[1], 0, mav.MAV_MISSION_TYPE_MISSION)
            last_req = time.time()
        elif t == "MISSION_ITEM_INT" and count is not None and msg.seq == nxt:
            items.append({
                "seq": msg.seq, "frame": msg.frame, "command": msg.command,
                "command_name": mav.enums["MAV_CMD"][msg.command].name if msg.command in mav.enums["MAV_CMD"] else None,
                "current": msg.current,
                "autocontinue": msg.autocontinue,
                "params": [clean(msg.param1), clean(msg.param2), clean(msg.param3), clean(msg.param4)],
                "x": msg.x, "y": msg.y, "z": clean(msg.z), "mission_type": msg.mission_type,
                "target_system": msg.target_system, "target_component": msg.target_component,
            })
            nxt += 1
            if nxt == count:
                m.mav.mission_ack_send(gcs[0], gcs[1], mav.MAV_MISSION_ACCEPTED, mav.MAV_MISSION_TYPE_MISSION)
                out["items"] = items
                done_at = time.time()
            else:
                m.mav.mission_request_int_send(gcs[0], gcs[1], nxt, mav.MAV_MISSION_TYPE_MISSION)
                last_req = time.time()
    out["badsig"] = m.mav.signing.badsig_count if args.key else 0
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    sys.exit(main())
