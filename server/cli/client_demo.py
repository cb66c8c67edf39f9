"""``burrforce client demo``: the command over the demo client (``burrforce.client.demo``),
and the flat-workpiece model's forces for the same cut, which its summary prints beside the
measured ones. The client package itself never imports the server's."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ...client import connection
from ...client.demo import plot, run_demo, summary
from ...client.udp import BurrClient, ServerGone, StreamTaken
from ...proto import frames
from ..argtypes import float_in, int_in


def model_expectation(depth_mm: float, feed_mm_s: float, rpm: float, angle_deg: float,
                      radius_mm: float, us_n_mm2: float | None = None,
                      k: float | None = None) -> tuple[float, float, float]:
    """(feed, lateral, normal) N of the flat-workpiece model for the same cut, with ``Us``
    and ``K`` (default: the thesis's cortical bone)."""
    # Here, not at the top: the model's kernels load only once the groove is cut.
    from ..model import CuttingModel, CuttingParams
    from ..model.cases import CuttingCase

    case = CuttingCase("parallel", angle_deg, radius_mm, depth_mm, feed_mm_s, rpm)
    params = CuttingParams(radius_mm=radius_mm)
    params = params.with_(us_n_mm2=params.us_n_mm2 if us_n_mm2 is None else us_n_mm2,
                          k=params.k if k is None else k)
    r = CuttingModel(params).evaluate(case.centre_mm, case.axis, case.feed_velocity_mm_s, rpm)
    return (r.feed_N, r.lateral_N, r.normal_N)


def session_parameters(conn: connection.Connection | None, host: str, port: int,
                       session: int) -> dict | None:
    """The session's parameters over REST (``GET /v1/sessions/ID/parameters``), when the
    connection file is that of the server the demo cut on and names its REST URL and token;
    else None."""
    if (conn is None or not conn.http_url or not conn.token or conn.session != session
            or (conn.host, conn.udp_port) != (host, port)):
        return None
    from ...client.rest import BurrRest, RestError

    try:
        with BurrRest(conn.http_url, conn.token, timeout_s=5.0) as rest:
            return rest.parameters(session)
    except (RestError, OSError, ValueError):
        return None


def model_line(parameters: dict | None, radius_mm: float) -> tuple[str, dict]:
    """What the model line says it compares with, and the Us/K arguments it takes: the
    session's own material when its parameters were read and its burr is the demo's round
    one, else the thesis's cortical bone, saying why."""
    if parameters is None:
        return ("flat-workpiece model, the thesis's cortical bone (the session's own Us and "
                "K were not read: no REST URL and token in the connection file)", {})
    burr = parameters.get("burr") or {}
    if (burr.get("shape", {}).get("kind") != "sphere"
            or burr.get("cutter", {}).get("kind") != "abrasive"):
        return ("flat-workpiece model, the thesis's cortical bone and a round burr of "
                f"R {radius_mm:g} mm (the session cuts with another burr: compare with care)",
                {})
    us, k = parameters.get("us_n_mm2"), parameters.get("k")
    if us is None or k is None:
        return "flat-workpiece model, the thesis's cortical bone", {}
    return (f"flat-workpiece model, the session's Us {us:g} N/mm² and K {k:g}",
            {"us_n_mm2": float(us), "k": float(k)})


# -- the command --------------------------------------------------------------------------------
def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("client", help="talk to a running server over UDP")
    client_sub = p.add_subparsers(dest="client", metavar="COMMAND", required=True)
    d = client_sub.add_parser(
        "demo", help="cut a groove in a running server's bone and print the forces",
        description="Probe for the bone's surface, plunge and cut a straight groove at 1 kHz, "
                    "printing the forces as they come back; then a summary against the "
                    "flat-workpiece model. Reads the endpoint and key from the connection "
                    "file `burrforce serve` writes, unless given.")
    d.add_argument("--server", metavar="HOST:PORT",
                   help="the server's UDP endpoint. Default: from the connection file")
    d.add_argument("--session", type=int_in(0, (1 << 32) - 1, "session id"),
                   help="session id. Default: from the connection file")
    d.add_argument("--key", help="session key in hex. Default: from the connection file")
    d.add_argument("--frame", choices=tuple(frames.FRAMES),
                   help="the session's frame. Default: from the connection file, else si_mm")
    d.add_argument("--connection", type=Path, help="connection file to read")
    d.add_argument("--x-mm", type=float_in(-1e4, 1e4, "x", "mm"), default=-5.0,
                   help="groove start x, mm. Default -5")
    d.add_argument("--y-mm", type=float_in(-1e4, 1e4, "y", "mm"), default=0.0,
                   help="groove y, mm. Default 0")
    d.add_argument("--length-mm", type=float_in(0.5, 100.0, "groove length", "mm"),
                   default=10.0, help="groove length, mm. Default 10")
    d.add_argument("--depth-mm", type=float_in(0.05, 3.0, "depth of cut", "mm"), default=0.5,
                   help="depth of cut, mm. Default 0.5")
    d.add_argument("--feed-mm-s", type=float_in(0.1, 100.0, "feed speed", "mm/s"),
                   default=5.0, help="feed speed, mm/s. Default 5")
    d.add_argument("--rpm", type=float_in(1000.0, 200_000.0, "spindle speed", "rpm"),
                   default=60_000.0, help="spindle speed. Default 60000")
    d.add_argument("--angle-deg", type=float_in(10.0, 90.0, "tool angle", "°"), default=60.0,
                   help="tool angle to the surface, degrees (tilted back). Default 60")
    d.add_argument("--radius-mm", type=float_in(0.1, 10.0, "burr radius", "mm"), default=2.0,
                   help="the server's burr radius, mm (to find the surface). Default 2")
    d.add_argument("--voxel-mm", type=float_in(1e-3, 10.0, "voxel size", "mm"), default=None,
                   help="the bone's voxel size, mm, to place the surface to within a quarter "
                        "voxel. Default: from the connection file")
    d.add_argument("--plot", type=Path, metavar="PATH", help="also write a PNG of the forces")
    d.add_argument("--json", action="store_true", help="print the summary as JSON")
    d.add_argument("--give-way", action="store_true",
                   help="stop (exit status 4) if another client takes the session's stream, "
                        "instead of taking it back (what `serve --demo`'s own grooves do)")
    d.set_defaults(func=main)


#: ``client demo``'s exit status when it gave the session's stream way (``--give-way``).
EXIT_GAVE_WAY = 4


def _connection(args: argparse.Namespace) -> connection.Connection | None:
    try:
        return connection.read(args.connection)
    except (ValueError, OSError):
        return None


def _endpoint(args: argparse.Namespace) -> tuple[str, int, int, str | None, str,
                                                float | None]:
    conn = None
    if args.server is None or args.session is None or (args.key is None and args.frame is None):
        try:
            conn = connection.read(args.connection)
        except ValueError:
            if args.server is None:
                raise
    host, port = (conn.host, conn.udp_port) if conn else ("127.0.0.1", 0)
    if args.server is not None:
        host, _, port_text = args.server.rpartition(":")
        try:
            port = int(port_text)
        except ValueError:
            raise ValueError(f"--server must be HOST:PORT, got {args.server!r}") from None
        if not host or not 0 < port < 65536:
            raise ValueError(f"--server must be HOST:PORT, got {args.server!r}")
    session = args.session if args.session is not None else (conn.session if conn else 1)
    key = args.key if args.key is not None else (conn.key_hex if conn else None)
    frame = args.frame or (conn.frame if conn else frames.DEFAULT_FRAME)
    same_server = conn is not None and (host, port) == (conn.host, conn.udp_port)
    voxel = args.voxel_mm if args.voxel_mm is not None else (
        conn.voxel_mm if same_server else None)
    return host.strip("[]"), port, session, key, frame, voxel


def main(args: argparse.Namespace) -> int:
    host, port, session, key, frame, voxel_mm = _endpoint(args)

    def say(text: str) -> None:
        print(text, file=sys.stderr if args.json else sys.stdout, flush=True)

    say(f"server {host}:{port}, session {session}, frame {frame}")
    with BurrClient(host, port, session, key, timeout_s=0.5, give_way=args.give_way) as client:
        try:
            run = run_demo(client, frame, args.x_mm, args.y_mm, args.length_mm, args.depth_mm,
                           args.feed_mm_s, args.rpm, args.angle_deg, args.radius_mm,
                           voxel_mm=voxel_mm, say=say)
        except StreamTaken as taken:
            print(f"burrforce client demo: {taken}", file=sys.stderr, flush=True)
            return EXIT_GAVE_WAY
        except TimeoutError:
            if client.counters["wrong_stream"]:
                # Each side's hello took the stream from the other: neither was answered.
                raise RuntimeError(
                    f"session {session} streams to another client: the server ended this "
                    f"client's stream {client.counters['wrong_stream']} times. Wait until it "
                    "stops, or use another --session") from None
            raise RuntimeError(f"no answer from {host}:{port}: is `burrforce serve` running "
                               "there?") from None
        except ServerGone as error:  # before or after the groove: nothing to go on with
            raise RuntimeError(str(error)) from None
    result = summary(run)
    label, material = model_line(session_parameters(_connection(args), host, port, session),
                                 args.radius_mm)
    expected = model_expectation(args.depth_mm, args.feed_mm_s, args.rpm, args.angle_deg,
                                 args.radius_mm, **material)
    result["model_feed_N"], result["model_lateral_N"], result["model_normal_N"] = expected
    result["model_parameters"] = "session" if material else "thesis"
    if args.plot is not None:
        result["plot"] = str(plot(run, args.plot))
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    say(f"\ncut {result['cutting_ticks']} ticks, removed {result['removed_mm3']:.2f} mm³; "
        f"{result['lost']} packets lost; round trip p50 {result['rtt_p50_us']:.0f} µs, "
        f"p99 {result['rtt_p99_us']:.0f} µs")
    say(f"steady cut: feed {result['steady_feed_N']:.3f} N, lateral "
        f"{result['steady_lateral_N']:.3f} N, normal {result['steady_normal_N']:.3f} N")
    if run.coupled:
        say("the session renders the coupled output (a device profile is set): the burr "
            "proxy cut where the coupling spring's pull met the bone's resistance, not at the "
            "demo's 0.5 mm, so the model's forces for a 0.5 mm cut do not apply")
    else:
        say(f"{label}: feed {expected[0]:.3f} N, lateral {expected[1]:.3f} N, normal "
            f"{expected[2]:.3f} N")
    if result["forbidden_ticks"]:
        say(f"warning: the burr touched a forbidden structure in {result['forbidden_ticks']} "
            "ticks")
    if args.plot is not None:
        say(f"plot written to {result['plot']}")
    say(f"the groove stays cut: run again with another --y-mm for fresh bone (or reset the "
        f"bone: POST /v1/sessions/{session}/reset)")
    return 0
