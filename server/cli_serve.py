"""``burrforce serve``: the hot loop on a bone, with one session ready for an engine.

The REST control plane joins this command later; today it starts the UDP hot loop (its own
process), prints how to connect, writes the connection file for local clients, and reports
traffic every few seconds until Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import functools
import ipaddress
import signal
import time
from pathlib import Path

from ..client import connection
from ..proto.frames import DEFAULT_FRAME, FRAMES
from ..proto.tag import new_key, parse_key
from .cli_args import float_in, int_in

DEFAULT_UDP_PORT = 47810
STATUS_INTERVAL_S = 2.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    from .hotloop import DEFAULT_BONE

    p = sub.add_parser(
        "serve", help="run the haptic force server (UDP hot loop) on a bone",
        description="Start the UDP hot loop on a bone with one session, print its endpoint "
                    "and key, and report traffic until Ctrl-C. Engines stream poses to it "
                    "(proto/SPEC.md); `burrforce client demo` cuts a groove in it.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on. Default 127.0.0.1 (this machine only)")
    p.add_argument("--udp-port", type=int_in(0, 65535, "UDP port"), default=DEFAULT_UDP_PORT,
                   help=f"UDP port (0: any free one). Default {DEFAULT_UDP_PORT}")
    p.add_argument("--bone", default=DEFAULT_BONE,
                   help="phantom:NAME (workpiece, layered, temporal) or a bone file. "
                        f"Default {DEFAULT_BONE}")
    p.add_argument("--voxel-mm", type=float_in(1e-3, 10.0, "voxel size", "mm"), default=None,
                   help="a phantom's voxel size, mm. Default per phantom")
    p.add_argument("--frame", choices=tuple(FRAMES), default=DEFAULT_FRAME,
                   help="the engine's frame and units for the session. Default si_mm")
    p.add_argument("--session-id", type=int_in(0, (1 << 32) - 1, "session id"), default=1,
                   help="the session's id. Default 1")
    auth = p.add_mutually_exclusive_group()
    auth.add_argument("--key", help="the session key in hex. Default: a fresh random key")
    auth.add_argument("--no-auth", action="store_true",
                      help="no key, untagged datagrams (loopback only, for development)")
    p.add_argument("--connection-file", type=Path, default=None,
                   help=f"where to write the connection file. Default "
                        f"{connection.default_path()}")
    p.set_defaults(func=main)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def main(args: argparse.Namespace) -> int:
    from .hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec

    if args.no_auth and not _is_loopback(args.host):
        raise ValueError(f"--no-auth is for loopback development; {args.host} is reachable "
                         "from other machines, so its session needs a key")
    key_hex = None if args.no_auth else (args.key.strip().lower() if args.key
                                         else new_key().hex())
    key = None if key_hex is None else parse_key(key_hex)
    spec = SessionSpec(args.session_id, args.bone, args.voxel_mm, key,
                       SessionConfig(frame=args.frame))
    say = functools.partial(print, flush=True)
    say(f"loading {args.bone} and warming up the kernels (the first start compiles them: "
        "up to a minute)...")
    hot = HotLoopProcess(HotLoopConfig(args.host, args.udp_port, (spec,)))
    t0 = time.monotonic()
    host, port = hot.start()
    stopping = []

    def stop(signum: int, frame: object) -> None:
        stopping.append(signum)

    old_term = signal.signal(signal.SIGTERM, stop)
    conn = connection.Connection(host, port, args.session_id, key_hex, args.frame,
                                 hot.bones[args.session_id]["voxel_mm"])
    conn_path = None
    try:
        conn_path = connection.write(conn, args.connection_file)
        say(f"ready in {time.monotonic() - t0:.1f} s: UDP {host}:{port}, session "
            f"{args.session_id}, frame {args.frame}")
        say(f"session key: {key_hex}" if key_hex else
            "no key: datagrams are not tagged (loopback development)")
        say(f"connection file: {conn_path}")
        say("try it:   burrforce client demo        (Ctrl-C stops the server)")
        _report(hot, args.session_id, stopping, say)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old_term)
        say("stopping...")
        hot.stop()
        if conn_path is not None:
            connection.remove(conn_path, only_if=conn)
    say("stopped")
    return 0


def _report(hot, session_id: int, stopping: list, say) -> None:
    """A status line every few seconds while packets arrive; returns on SIGTERM."""
    last_received = 0
    last_t = time.monotonic()
    while not stopping:
        time.sleep(0.1)
        if time.monotonic() - last_t < STATUS_INTERVAL_S:
            continue
        if not hot.is_alive():
            raise RuntimeError("the hot-loop process died; see the messages above")
        stats = hot.stats()
        now = time.monotonic()
        counters = stats["counters"]
        received = counters["received"]
        if received != last_received:
            rate = (received - last_received) / (now - last_t)
            s = stats["sessions"].get(session_id, {})
            removed = sum(s.get("removed_mm3", {}).values()) if s else 0.0
            drops = {k: v for k, v in counters.items()
                     if v and k not in ("received", "replied", "noticed")}
            tick = s.get("tick_p99_us")
            say(f"{rate:6.0f} packets/s  |F| {s.get('last_force_N', 0.0):6.2f} N  removed "
                f"{removed:8.2f} mm³  tick p99 {tick or 0:5.0f} µs"
                + (f"  dropped {drops}" if drops else ""))
        last_received, last_t = received, now
