#!/usr/bin/python3
"""A real RTSP server for shotpilot's video tests: GStreamer's gst-rtsp-server
(Debian: gir1.2-gst-rtsp-server-1.0, python3-gi, gstreamer1.0-plugins-*),
serving H.264 (x264enc) or H.265 (x265enc) encoded from the simulator's MJPEG
stream or from GStreamer's test pattern.

Prints "LISTENING <port>" once bound (port 0 lets the OS choose), then serves
until killed. Run with Debian's python3 (/usr/bin/python3), which has gi.
"""
import argparse
import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--path", default="/main.264")
    ap.add_argument("--mjpeg", help="MJPEG URL to encode (default: test pattern)")
    ap.add_argument("--codec", choices=["h264", "h265"], default="h264")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--fps", type=int, default=15)
    ap.add_argument("--bitrate-kbps", type=int, default=1500)
    ap.add_argument("--gop", type=int, default=15)
    ap.add_argument("--user")
    ap.add_argument("--password")
    a = ap.parse_args()

    Gst.init(None)
    if a.mjpeg:
        src = (
            f"souphttpsrc location={a.mjpeg} is-live=true do-timestamp=true "
            "! multipartdemux ! jpegdec ! videoconvert ! video/x-raw,format=I420"
        )
    else:
        src = (
            "videotestsrc is-live=true pattern=ball "
            f"! video/x-raw,width={a.width},height={a.height},framerate={a.fps}/1 "
            "! videoconvert ! video/x-raw,format=I420"
        )
    if a.codec == "h264":
        enc = (
            f"x264enc tune=zerolatency speed-preset=ultrafast bitrate={a.bitrate_kbps} "
            f"key-int-max={a.gop} ! rtph264pay name=pay0 pt=96 config-interval=1"
        )
    else:
        enc = (
            f"x265enc tune=zerolatency speed-preset=ultrafast bitrate={a.bitrate_kbps} "
            f"key-int-max={a.gop} ! rtph265pay name=pay0 pt=96 config-interval=1"
        )
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(a.port))
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(f"( {src} ! {enc} )")
    factory.set_shared(True)
    if a.user is not None:
        auth = GstRtspServer.RTSPAuth()
        token = GstRtspServer.RTSPToken()
        token.set_string(GstRtspServer.RTSP_TOKEN_MEDIA_FACTORY_ROLE, "operator")
        auth.add_basic(GstRtspServer.RTSPAuth.make_basic(a.user, a.password or ""), token)
        server.set_auth(auth)
        perms = GstRtspServer.RTSPPermissions()
        perms.add_permission_for_role("operator", "media.factory.access", True)
        perms.add_permission_for_role("operator", "media.factory.construct", True)
        factory.set_permissions(perms)
    server.get_mount_points().add_factory(a.path, factory)
    if server.attach(None) == 0:
        print(f"cannot listen on port {a.port}", file=sys.stderr, flush=True)
        return 1
    print(f"LISTENING {server.get_bound_port()}", flush=True)
    GLib.MainLoop().run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
