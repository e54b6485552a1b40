#!/bin/bash
# By hand, not part of CI: the operator page's event stream bandwidth (idle
# and while a shot is flown and refined) and its JS heap over MINUTES, on a
# daemon with the in-process simulator, from copied binaries (see the
# brief's SP_COPY_TO). Usage:
#
#   tests/browser/measure_page.sh BIN_DIR OUT_DIR [MINUTES]
#
# Writes OUT_DIR/{config.toml,daemon.log,idle_events.txt,flying_events.txt,
# heap.log} and prints kB per minute of each event kind, and what the
# tracked-features overlay costs while it is on (features_bw.js).
set -u
BIN=$1/shotpilot; D=$2; MIN=${3:-30}
HERE=$(cd "$(dirname "$0")" && pwd); REPO=$(cd "$HERE/../.." && pwd)
rm -rf "$D"; mkdir -p "$D"
# Two free ports for the simulator's video and MAVLink (picked, then freed).
read VP MP <<<"$(python3 -c "
import socket
a=socket.socket(); a.bind(('127.0.0.1',0)); b=socket.socket(socket.AF_INET,socket.SOCK_DGRAM); b.bind(('127.0.0.1',0))
print(a.getsockname()[1], b.getsockname()[1])")"
sed -e "s#^video_listen = .*#video_listen = \"127.0.0.1:$VP\"#" \
    -e "s#^mavlink = .*#mavlink = \"udpout:127.0.0.1:$MP\"#" \
    -e "s#^url = \"http://127.0.0.1:8554/video.mjpg\"#url = \"http://127.0.0.1:$VP/video.mjpg\"#" \
    -e "s#^url = \"udpin:0.0.0.0:14550\"#url = \"udpin:127.0.0.1:$MP\"#" \
    "$REPO/config.toml" > "$D/config.toml"
cd "$D"
nice -n 19 "$BIN" --config "$D/config.toml" run --bind 127.0.0.1:0 > "$D/daemon.log" 2>&1 &
DPID=$!
trap 'kill $DPID 2>/dev/null' EXIT
U=
for _ in $(seq 60); do U=$(grep -o 'http://127.0.0.1:[0-9]*/' "$D/daemon.log" | head -1); [ -n "$U" ] && break; sleep 1; done
echo "daemon at $U"
# The page open from the start, its heap looked at while the rest runs.
(cd "$HERE" && node heap.js "$U" "$MIN" > "$D/heap.log" 2>&1) &
HPID=$!
g=
for _ in $(seq 240); do
  g=$(curl -s "${U}api/v1/status" | python3 -c "import json,sys; s=json.load(sys.stdin); print(s['vehicle'].get('georeference',{}).get('state'), s['slam']['state'], s['slam']['keyframes'])" 2>/dev/null)
  case "$g" in ok\ tracking*) break;; esac; sleep 1
done
echo "status: $g"
kinds() {
  python3 - "$1" <<'PY'
import sys, collections
text = open(sys.argv[1], encoding='utf-8', errors='replace').read()
n = collections.Counter(); b = collections.Counter()
for block in text.split('\n\n'):
    name = next((l[7:] for l in block.split('\n') if l.startswith('event: ')), None)
    if name: n[name] += 1; b[name] += len(block) + 2
print('  total %.1f kB: ' % (len(text) / 1e3) + ', '.join('%s %d events %.1f kB' % (k, n[k], b[k] / 1e3) for k in sorted(n)))
PY
}
echo "idle: /events for 60 s"; curl -sN --max-time 60 "${U}api/v1/events" > "$D/idle_events.txt"; kinds "$D/idle_events.txt"
if [ -f "$HERE/features_bw.js" ]; then
  echo "the tracked-features overlay switched on, for 60 s:"
  (cd "$HERE" && node features_bw.js "$U" 60)
fi
KF=$(curl -s "${U}api/v1/keyframes" | python3 -c "import json,sys; print(min(k['id'] for k in json.load(sys.stdin)['keyframes']))")
ID=$(curl -s -H 'Content-Type: application/json' -d "{\"keyframe_id\": $KF, \"anchors\": [[32,24],[608,24],[608,456],[32,456]]}" "${U}api/v1/shots" | python3 -c "import json,sys; s=json.load(sys.stdin); print(s['id'], s['status'])")
echo "shot: $ID"; ID=${ID%% *}
curl -s -X POST "${U}api/v1/shots/$ID/mission" > /dev/null
curl -s -X POST "${U}api/v1/shots/$ID/start" > /dev/null
echo "flying and refining: /events for 60 s"; curl -sN --max-time 60 "${U}api/v1/events" > "$D/flying_events.txt"; kinds "$D/flying_events.txt"
wait $HPID
echo "heap:"; cat "$D/heap.log"
