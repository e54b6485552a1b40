#!/usr/bin/env python3
"""A second ground station written with pymavlink, the independent peer of
the forward-endpoint tests: it stands where QGroundControl would (system
255, component 190), listening on UDP for shotpilot's `udpout:` forward.

It prints one line per step on stdout, each a JSON object with "step":
  {"step": "ready", "port": PORT}        socket bound (--port 0: the kernel's pick)
  {"step": "vehicle", ...}               the vehicle's heartbeat arrived through shotpilot
  {"step": "window_start"} / {"step": "window_end", "counts": {...}}
                                         messages from the vehicle's system (all its
                                         components) counted over --window s
  {"step": "armed", "result": N}         COMMAND_ACK of MAV_CMD_COMPONENT_ARM_DISARM
  {"step": "uploaded", "result": NAME, "seconds": S, "tries": N}
and then reads commands on stdin: "upload" (another upload, items moved a
little each time: another "uploaded" line), "download"
  {"step": "downloaded", "items": [[command, lat_e7, lon_e7, alt], ...]}
"capture COMPONENT" (MAV_CMD_IMAGE_START_CAPTURE, one image, to that
component of the vehicle: {"step": "captured", "result": N}) and "quit".
With --no-arm it neither arms nor uploads before reading stdin;
"upload-json" uploads the items of --items-json FILE (shotpilot's
MissionItem JSON) instead of its own.
The mission transfers resend on timeouts as QGroundControl does (1.5 s,
several tries), so they work over a lossy link.

Usage: gcs_peer.py --port 0 [--window 10] [--items 3] [--no-arm] [--items-json FILE]
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

MISSION = mav.MAV_MISSION_TYPE_MISSION
RESEND_S = 1.5
TRIES = 8


def say(**kw):
    print(json.dumps(kw), flush=True)


class Gcs:
    def __init__(self, port):
        self.m = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=255, source_component=190, dialect="common"
        )
        self.vehicle = None
        self.next_hb = 0.0

    def port(self):
        return self.m.port.getsockname()[1]

    def heartbeat(self):
        now = time.time()
        if now >= self.next_hb:
            self.m.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
            self.next_hb = now + 1.0

    def recv(self, timeout):
        """The next message (None on timeout), heartbeats sent meanwhile."""
        end = time.time() + timeout
        while True:
            self.heartbeat()
            left = end - time.time()
            if left <= 0:
                return None
            msg = self.m.recv_match(blocking=True, timeout=min(left, 0.2))
            if msg is not None and msg.get_type() != "BAD_DATA":
                return msg

    def for_us(self, msg):
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, 255) and tc in (0, 190)

    def wait_vehicle(self, timeout):
        end = time.time() + timeout
        while time.time() < end:
            msg = self.recv(end - time.time())
            # the autopilot (not a camera or gimbal component of the vehicle)
            if msg is not None and msg.get_type() == "HEARTBEAT" and msg.autopilot != mav.MAV_AUTOPILOT_INVALID:
                self.vehicle = (msg.get_srcSystem(), msg.get_srcComponent())
                return msg
        return None

    def count(self, seconds):
        counts = {}
        end = time.time() + seconds
        while time.time() < end:
            msg = self.recv(end - time.time())
            if msg is None:
                continue
            if msg.get_srcSystem() == self.vehicle[0]:  # every component of the vehicle
                t = msg.get_type()
                counts[t] = counts.get(t, 0) + 1
        return counts

    def command(self, cmd, params):
        for _ in range(TRIES):
            self.m.mav.command_long_send(self.vehicle[0], self.vehicle[1], cmd, 0, *params)
            end = time.time() + RESEND_S
            while time.time() < end:
                msg = self.recv(end - time.time())
                if msg is not None and msg.get_type() == "COMMAND_ACK" and msg.command == cmd and self.for_us(msg):
                    return msg.result
        return None

    def upload(self, items):
        """QGroundControl's upload: COUNT, answer each request, until ACK."""
        sys_, comp = self.vehicle
        t0 = time.time()
        tries = 0
        last = None
        sent = None

        def send_item(seq):
            it = items[seq]
            if isinstance(it, dict):  # a whole item (--items-json)
                p = [float("nan") if v is None else v for v in it["params"]]
                self.m.mav.mission_item_int_send(
                    sys_, comp, seq, it["frame"], it["command"], 1 if it["current"] else 0,
                    1 if it["autocontinue"] else 0, p[0], p[1], p[2], p[3], it["x"], it["y"],
                    float("nan") if it["z"] is None else it["z"], MISSION)
                return
            cmd, lat, lon, alt = it
            self.m.mav.mission_item_int_send(
                sys_, comp, seq, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd,
                1 if seq == 0 else 0, 1, 0, 1.0, 0, float("nan"), lat, lon, alt, MISSION)

        end = t0 + RESEND_S * TRIES * 3
        while time.time() < end:
            if last is None or time.time() - last > RESEND_S:
                if last is None or not self.started:
                    self.m.mav.mission_count_send(sys_, comp, len(items), MISSION)
                    tries += 1
                elif sent is not None:
                    # no request and no ACK: resend the last item (a lost
                    # final ACK is sent again for it)
                    send_item(sent)
                    tries += 1
                last = time.time()
            msg = self.recv(0.2)
            if msg is None or not self.for_us(msg):
                continue
            t = msg.get_type()
            if t in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and msg.mission_type == MISSION:
                self.started = True
                if msg.seq < len(items):
                    sent = msg.seq
                    send_item(sent)
                last = time.time()
            elif t == "MISSION_ACK" and msg.mission_type == MISSION:
                name = mav.enums["MAV_MISSION_RESULT"][msg.type].name
                if msg.type == mav.MAV_MISSION_ACCEPTED or self.started:
                    return name, time.time() - t0, tries
                # refused before it started (the vehicle was busy): try again
                last = None
                time.sleep(0.5)
        return "TIMEOUT", time.time() - t0, tries

    def download(self):
        sys_, comp = self.vehicle
        count = None
        items = {}
        for _ in range(TRIES * 10):
            if count is None:
                self.m.mav.mission_request_list_send(sys_, comp, MISSION)
            else:
                missing = [s for s in range(count) if s not in items]
                if not missing:
                    self.m.mav.mission_ack_send(sys_, comp, mav.MAV_MISSION_ACCEPTED, MISSION)
                    return [items[s] for s in range(count)]
                self.m.mav.mission_request_int_send(sys_, comp, missing[0], MISSION)
            end = time.time() + RESEND_S
            while time.time() < end:
                msg = self.recv(end - time.time())
                if msg is None or not self.for_us(msg):
                    continue
                t = msg.get_type()
                if t == "MISSION_COUNT" and count is None:
                    count = msg.count
                    break
                if t == "MISSION_ITEM_INT" and count is not None:
                    items[msg.seq] = [msg.command, msg.x, msg.y, round(msg.z, 2) if math.isfinite(msg.z) else None]
                    break
        return None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--window", type=float, default=10.0)
    ap.add_argument("--items", type=int, default=3)
    ap.add_argument("--no-arm", action="store_true")
    ap.add_argument("--items-json", default="", help="upload these items (shotpilot's MissionItem JSON) first")
    args = ap.parse_args()
    g = Gcs(args.port)
    g.started = False
    say(step="ready", port=g.port())
    hb = g.wait_vehicle(30.0)
    if hb is None:
        say(step="error", what="no vehicle heartbeat through the forward endpoint")
        return 1
    say(step="vehicle", system=g.vehicle[0], component=g.vehicle[1], autopilot=hb.autopilot)
    if args.window > 0:
        say(step="window_start")
        counts = g.count(args.window)
        say(step="window_end", counts=counts, seconds=args.window)
    if not args.no_arm:
        result = g.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, [1, 0, 0, 0, 0, 0, 0])
        say(step="armed", result=result)
    lat0, lon0 = 473977420, 85455940
    round_ = 0

    def upload(given=False):
        g.started = False
        if given:
            with open(args.items_json) as f:
                whole = json.load(f)
            name, seconds, tries = g.upload(whole)
            listed = [[it["command"], it["x"], it["y"], it["z"]] for it in whole]
            say(step="uploaded", result=name, seconds=round(seconds, 3), tries=tries, items=listed)
            return
        items = [
            [mav.MAV_CMD_NAV_WAYPOINT, lat0 + 100 * (k + 1), lon0 + 150 * k + 7 * round_, 15.0 + k]
            for k in range(args.items)
        ]
        name, seconds, tries = g.upload(items)
        say(step="uploaded", result=name, seconds=round(seconds, 3), tries=tries, items=items)

    if not args.no_arm:
        upload()
    for line in sys.stdin:
        if line.strip() == "download":
            say(step="downloaded", items=g.download())
        elif line.strip() == "upload":
            round_ += 1
            upload()
        elif line.strip() == "upload-json":
            upload(given=True)
        elif line.strip().startswith("capture "):
            # MAV_CMD_IMAGE_START_CAPTURE to a component of the vehicle: one image
            comp = int(line.split()[1])
            g.vehicle, autopilot = (g.vehicle[0], comp), g.vehicle
            result = g.command(mav.MAV_CMD_IMAGE_START_CAPTURE, [0, 0, 1, 0, 0, 0, 0])
            g.vehicle = autopilot
            say(step="captured", result=result)
        elif line.strip() == "quit":
            break
    return 0


if __name__ == "__main__":
    sys.exit(main())
