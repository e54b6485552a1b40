#!/usr/bin/python3
"""A real RTP sender that answers feedback, for shotpilot's lossy-link video
tests: GStreamer's rtpbin (AVPF profile) sends H.264 (x264enc, baseline,
slices capped at one packet) as RTP to --host:--rtp-port, with rtprtxsend
retransmitting what a receiver's RTCP NACK asks for (RFC 4588, payload type
97 for 96, its own SSRC), and x264enc making a key frame when a receiver's
RTCP PLI asks for one. RTCP is symmetric: sender reports go to --rtcp-port
from the socket the feedback is read on.

With --no-retransmission, the same stream with plain RTCP (AVP, no
rtprtxsend): NACKs go unanswered, a PLI still makes a key frame.

Prints "SENDING" once playing, "DONE" at the end of the stream (--secs).
Run with Debian's python3 (/usr/bin/python3), which has gi.
"""
import argparse
import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("Gio", "2.0")
from gi.repository import Gio, GLib, Gst  # noqa: E402

# GstRTPProfile: 3 is AVPF (RFC 4585), 1 plain AVP.
PROFILE_AVPF = 3
PROFILE_AVP = 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--rtp-port", type=int, required=True)
    ap.add_argument("--rtcp-port", type=int, required=True)
    ap.add_argument("--secs", type=int, default=20)
    ap.add_argument("--fps", type=int, default=15)
    ap.add_argument("--gop", type=int, default=30, help="pictures between IDR pictures")
    ap.add_argument(
        "--intra-refresh",
        action="store_true",
        help="periodic intra refresh instead of IDR pictures (x264's moving "
        "intra column, a recovery point SEI every --gop pictures)",
    )
    ap.add_argument("--bitrate-kbps", type=int, default=1500)
    ap.add_argument("--slice-bytes", type=int, default=1200)
    ap.add_argument("--no-retransmission", action="store_true")
    ap.add_argument(
        "--frames",
        help="a printf pattern of numbered PNG frames (000000.png ...) to send "
        "instead of the test pattern, paced at --fps, to their end",
    )
    a = ap.parse_args()

    Gst.init(None)
    pipe = Gst.Pipeline.new("sender")
    if a.frames:
        raw = (
            f"multifilesrc location={a.frames} index=0 "
            f"caps=image/png,framerate={a.fps}/1 ! pngdec "
        )
    else:
        raw = (
            "videotestsrc is-live=true pattern=smpte horizontal-speed=3 "
            f"num-buffers={a.secs * a.fps} "
            f"! video/x-raw,width=640,height=480,framerate={a.fps}/1 "
        )
    src = Gst.parse_bin_from_description(
        raw + "! videoconvert ! video/x-raw,format=I420 "
        f"! x264enc tune=zerolatency speed-preset=veryfast threads=1 bitrate={a.bitrate_kbps} "
        f"key-int-max={a.gop} intra-refresh={'true' if a.intra_refresh else 'false'} "
        f"option-string=slice-max-size={a.slice_bytes}:scenecut=0 "
        "! video/x-h264,profile=constrained-baseline "
        "! rtph264pay pt=96 mtu=1400 config-interval=-1",
        True,
    )
    pipe.add(src)
    rtpbin = Gst.ElementFactory.make("rtpbin", "rtpbin")
    rtpbin.set_property("rtp-profile", PROFILE_AVP if a.no_retransmission else PROFILE_AVPF)
    pipe.add(rtpbin)

    def aux_sender(_bin, _session):
        rtx = Gst.ElementFactory.make("rtprtxsend")
        rtx.set_property(
            "payload-type-map",
            Gst.Structure.new_from_string("application/x-rtp-pt-map, 96=(uint)97"),
        )
        rtx.set_property("max-size-time", 2000)
        b = Gst.Bin.new(None)
        b.add(rtx)
        b.add_pad(Gst.GhostPad.new("sink_0", rtx.get_static_pad("sink")))
        b.add_pad(Gst.GhostPad.new("src_0", rtx.get_static_pad("src")))
        return b

    if not a.no_retransmission:
        rtpbin.connect("request-aux-sender", aux_sender)

    rtp_sink = rtpbin.request_pad_simple("send_rtp_sink_0")
    # Sender reports every half second, so the receiver learns early where
    # to send feedback (the first one still comes 0.3-1 s in).
    rtpbin.emit("get-internal-session", 0).set_property("rtcp-min-interval", 500_000_000)
    src.get_static_pad("src").link(rtp_sink)

    udp_rtp = Gst.ElementFactory.make("udpsink", "rtp_out")
    udp_rtp.set_property("host", a.host)
    udp_rtp.set_property("port", a.rtp_port)
    pipe.add(udp_rtp)
    rtpbin.get_static_pad("send_rtp_src_0").link(udp_rtp.get_static_pad("sink"))

    # One socket for RTCP both ways (symmetric RTCP, RFC 4961).
    sock = Gio.Socket.new(Gio.SocketFamily.IPV4, Gio.SocketType.DATAGRAM, Gio.SocketProtocol.UDP)
    sock.bind(Gio.InetSocketAddress.new_from_string("127.0.0.1", 0), True)
    rtcp_out = Gst.ElementFactory.make("udpsink", "rtcp_out")
    rtcp_out.set_property("host", a.host)
    rtcp_out.set_property("port", a.rtcp_port)
    rtcp_out.set_property("socket", sock)
    rtcp_out.set_property("close-socket", False)
    rtcp_out.set_property("sync", False)
    rtcp_out.set_property("async", False)
    rtcp_in = Gst.ElementFactory.make("udpsrc", "rtcp_in")
    rtcp_in.set_property("socket", sock)
    rtcp_in.set_property("close-socket", False)
    rtcp_in.set_property("caps", Gst.Caps.from_string("application/x-rtcp"))
    pipe.add(rtcp_out)
    pipe.add(rtcp_in)
    rtpbin.request_pad_simple("send_rtcp_src_0").link(rtcp_out.get_static_pad("sink"))
    rtcp_in.get_static_pad("src").link(rtpbin.request_pad_simple("recv_rtcp_sink_0"))

    loop = GLib.MainLoop()
    result = {"rc": 0}

    def on_message(_bus, msg):
        if msg.type == Gst.MessageType.EOS:
            loop.quit()
        elif msg.type == Gst.MessageType.ERROR:
            err, dbg = msg.parse_error()
            print(f"ERROR {err.message} {dbg}", file=sys.stderr, flush=True)
            result["rc"] = 1
            loop.quit()

    # The end of the media: rtpbin's own end of stream waits for its RTCP
    # BYE, which an RTCP session with feedback in it can put off for long;
    # the stream is over once the payloader has sent its last packet, and
    # half a second more lets the last retransmissions and reports go out.
    def on_end(_pad, info):
        ev = info.get_event()
        if ev is not None and ev.type == Gst.EventType.EOS:
            GLib.timeout_add(500, lambda: loop.quit() or False)
        return Gst.PadProbeReturn.OK

    src.get_static_pad("src").add_probe(Gst.PadProbeType.EVENT_DOWNSTREAM, on_end)

    bus = pipe.get_bus()
    bus.add_signal_watch()
    bus.connect("message", on_message)
    if pipe.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
        print("ERROR the pipeline did not start", file=sys.stderr, flush=True)
        return 1
    print("SENDING", flush=True)
    loop.run()
    pipe.set_state(Gst.State.NULL)
    print("DONE", flush=True)
    return result["rc"]


if __name__ == "__main__":
    sys.exit(main())
