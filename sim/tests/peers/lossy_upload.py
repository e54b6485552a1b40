#!/usr/bin/env python3
"""pymavlink peer: mission uploads over a lossy link, retrying the way
QGroundControl's PlanManager does, then a download (also retrying) to check
that the vehicle stores exactly what was sent.

Client rules (QGC-like):
- send MISSION_COUNT; if no MISSION_REQUEST(_INT) arrives within the ack
  timeout, send MISSION_COUNT again (up to --retries times);
- answer every request, repeated ones included, with the requested item;
- after the last item, if no MISSION_ACK arrives within the timeout, send
  the last item again (the vehicle re-ACKs a duplicate of the last item);
- any other silence longer than the timeout re-sends the last message.
- The verifying download sends MISSION_REQUEST_LIST / MISSION_REQUEST_INT
  again on timeout (up to --verify-retries times: it checks the result, it
  is not the upload under test).

Usage: lossy_upload.py [--listen udpin:127.0.0.1:14550] [--tries 10] [--items 8]
Prints a JSON summary; exits non-zero unless every try succeeded.
With --listen udpin:HOST:0 the first line is "listening PORT", the port the
kernel picked (where the simulator must send).
"""
import argparse
import json
import math
import os
import random
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

m2 = mavutil.mavlink
MISSION = m2.MAV_MISSION_TYPE_MISSION


def recv(conn, types, timeout):
    end = time.time() + timeout
    while True:
        left = end - time.time()
        if left <= 0:
            return None
        msg = conn.recv_match(type=types, blocking=True, timeout=left)
        if msg is not None:
            return msg


def make_mission(rng, lat0, lon0, n):
    items = []
    for seq in range(n):
        north, east = rng.uniform(-50, 50), rng.uniform(-50, 50)
        lat = int(round((lat0 + math.degrees(north / 6378137.0)) * 1e7))
        lon = int(round((lon0 + math.degrees(east / (6378137.0 * math.cos(math.radians(lat0))))) * 1e7))
        if seq == 0:
            items.append((0, m2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, m2.MAV_CMD_NAV_TAKEOFF, 0, 1, 0.0, 0.0, 0.0, float("nan"), 0, 0, 10.0))
        elif seq % 3 == 2:
            items.append((seq, m2.MAV_FRAME_MISSION, m2.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, 0, 1, -float(rng.randint(10, 90)), 0.0, float("nan"), float("nan"), 0, 0, 0.0))
        else:
            items.append((seq, m2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, m2.MAV_CMD_NAV_WAYPOINT, 0, 1, float(rng.randint(0, 3)), 2.0, 0.0, float(rng.randint(0, 359)), lat, lon, float(rng.randint(10, 40))))
    return items


def upload(conn, items, timeout, retries):
    stats = {"count_sends": 1, "item_sends": 0, "last_item_resends": 0, "requests_seen": 0}
    ts, tc = conn.target_system, conn.target_component
    conn.mav.mission_count_send(ts, tc, len(items), MISSION)
    got_request = False
    last_sent = None
    silent = 0
    t0 = time.time()
    while True:
        msg = recv(conn, ["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], timeout)
        if msg is None:
            silent += 1
            if silent > retries:
                return False, "timeout", time.time() - t0, stats
            if not got_request:
                conn.mav.mission_count_send(ts, tc, len(items), MISSION)
                stats["count_sends"] += 1
            elif last_sent is not None:
                conn.mav.mission_item_int_send(ts, tc, *items[last_sent], MISSION)
                stats["item_sends"] += 1
                if last_sent == len(items) - 1:
                    stats["last_item_resends"] += 1
            continue
        silent = 0
        if msg.get_type() == "MISSION_ACK":
            if getattr(msg, "mission_type", MISSION) != MISSION:
                continue
            if msg.type == m2.MAV_MISSION_ACCEPTED and got_request:
                return True, "accepted", time.time() - t0, stats
            if msg.type == m2.MAV_MISSION_ACCEPTED:
                continue  # stale ACK of an earlier upload
            return False, "nack %d" % msg.type, time.time() - t0, stats
        got_request = True
        stats["requests_seen"] += 1
        stats.setdefault("request_types", []).append(
            ("INT" if msg.get_type() == "MISSION_REQUEST_INT" else "legacy", msg.seq))
        if 0 <= msg.seq < len(items):
            conn.mav.mission_item_int_send(ts, tc, *items[msg.seq], MISSION)
            stats["item_sends"] += 1
            last_sent = msg.seq


def download(conn, timeout, retries):
    ts, tc = conn.target_system, conn.target_component
    count = None
    for _ in range(retries + 1):
        conn.mav.mission_request_list_send(ts, tc, MISSION)
        msg = recv(conn, ["MISSION_COUNT"], timeout)
        if msg is not None and getattr(msg, "mission_type", MISSION) == MISSION:
            count = msg.count
            break
    if count is None:
        return None
    got = []
    for seq in range(count):
        item = None
        for _ in range(retries + 1):
            conn.mav.mission_request_int_send(ts, tc, seq, MISSION)
            end = time.time() + timeout
            while time.time() < end:
                msg = recv(conn, ["MISSION_ITEM_INT"], end - time.time())
                if msg is not None and msg.seq == seq:
                    item = msg
                    break
            if item is not None:
                break
        if item is None:
            return None
        got.append(item)
    conn.mav.mission_ack_send(ts, tc, m2.MAV_MISSION_ACCEPTED, MISSION)
    return got


def same(it, ref):
    def feq(x, y):
        return (math.isnan(x) and math.isnan(y)) or x == y
    return (it.seq == ref[0] and it.frame == ref[1] and it.command == ref[2] and feq(it.param1, ref[5])
            and feq(it.param2, ref[6]) and feq(it.param3, ref[7]) and feq(it.param4, ref[8])
            and it.x == ref[9] and it.y == ref[10] and feq(it.z, ref[11]))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", default="udpin:127.0.0.1:14550")
    ap.add_argument("--tries", type=int, default=10)
    ap.add_argument("--items", type=int, default=8)
    ap.add_argument("--ack-timeout", type=float, default=1.5)
    ap.add_argument("--retries", type=int, default=5)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--verify-retries", type=int, default=25,
                    help="retries of the verifying download (not part of the upload under test)")
    args = ap.parse_args()
    conn = mavutil.mavlink_connection(args.listen, source_system=255, source_component=190)
    if args.listen.endswith(":0"):
        # Port 0: the kernel picked one; the simulator is told to send there.
        print(f"listening {conn.port.getsockname()[1]}", flush=True)
    if conn.wait_heartbeat(timeout=15) is None:
        print(json.dumps({"ok": False, "error": "no heartbeat"}))
        return 1
    conn.mav.heartbeat_send(m2.MAV_TYPE_GCS, m2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    home = None
    while home is None:
        home = recv(conn, ["HOME_POSITION"], 10)
    lat0, lon0 = home.latitude * 1e-7, home.longitude * 1e-7
    rng = random.Random(args.seed)
    results = []
    for k in range(args.tries):
        items = make_mission(rng, lat0, lon0, args.items)
        ok, why, secs, stats = upload(conn, items, args.ack_timeout, args.retries)
        verified = False
        detail = None
        if ok:
            got = download(conn, args.ack_timeout, args.verify_retries)
            if got is None:
                detail = "download failed"
            else:
                verified = len(got) == len(items) and all(same(g, r) for g, r in zip(got, items))
                if not verified:
                    detail = "mismatch: got %d items, first bad %s" % (len(got), next(
                        (str((g.seq, g.command, g.x, g.y, g.z)) + " vs " + str(r) for g, r in zip(got, items) if not same(g, r)), None))
        stats.pop("request_types", None)
        results.append({"try": k, "ok": ok and verified, "upload": why, "verified": verified,
                        "seconds": round(secs, 2), **stats, **({"detail": detail} if detail else {})})
        # Let stale retransmissions drain before the next try.
        time.sleep(0.6)
        while conn.recv_match(blocking=False) is not None:
            pass
    n_ok = sum(r["ok"] for r in results)
    times = sorted(r["seconds"] for r in results if r["ok"])
    summary = {
        "ok": n_ok == args.tries,
        "succeeded": n_ok,
        "tries": args.tries,
        "items": args.items,
        "upload_seconds_min_median_max": [times[0], times[len(times) // 2], times[-1]] if times else None,
        "count_resends_total": sum(r["count_sends"] - 1 for r in results),
        "last_item_resends_total": sum(r["last_item_resends"] for r in results),
        "results": results,
    }
    print(json.dumps(summary))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
