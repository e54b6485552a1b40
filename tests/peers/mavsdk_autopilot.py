#!/usr/bin/env python3
"""MAVSDK (PyPI `mavsdk`, the C++ library in-process) acting as an autopilot.

It configures MAVSDK with ComponentType.AUTOPILOT, sends to the ground
station's UDP port (shotpilot's link listens on a port it bound and told
the test; MAVSDK cannot say which port it bound itself), and uses the
MissionRawServer plugin to receive a mission from shotpilot. It prints
"ready" once connected, then one JSON line with the items MAVSDK received
(or a timeout note).

Usage: mavsdk_autopilot.py --gcs-port 14550 [--seconds 15]
"""
import argparse
import json
import math
import sys
import threading
import time

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.mission_raw_server.mission_raw_server import MissionRawServer


def clean(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--gcs-port", type=int, required=True)
    ap.add_argument("--seconds", type=float, default=15.0)
    args = ap.parse_args()

    cfg = Configuration.create_with_component_type(ComponentType.AUTOPILOT)
    sdk = Mavsdk(cfg)
    result = sdk.add_any_connection(f"udpout://127.0.0.1:{args.gcs_port}")
    server_component = sdk.server_component()
    if server_component is None:
        print(json.dumps({"error": f"no server component (connection {result})"}), flush=True)
        return 1
    server = MissionRawServer(server_component)
    got = {}
    done = threading.Event()

    def on_mission(res, plan, _ud):
        got["result"] = str(res)
        got["items"] = [
            {
                "seq": i.seq, "frame": i.frame, "command": i.command, "current": i.current,
                "autocontinue": i.autocontinue,
                "params": [clean(i.param1), clean(i.param2), clean(i.param3), clean(i.param4)],
                "x": i.x, "y": i.y, "z": clean(i.z), "mission_type": i.mission_type,
            }
            for i in plan.mission_items
        ]
        done.set()

    server.subscribe_incoming_mission(on_mission)
    print("ready", flush=True)
    if not done.wait(args.seconds):
        got["error"] = "no mission within the time limit"
    time.sleep(0.5)  # let MAVSDK's final ACK leave
    print(json.dumps(got), flush=True)
    sdk.destroy()
    return 0


if __name__ == "__main__":
    sys.exit(main())
