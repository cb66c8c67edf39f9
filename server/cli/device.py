"""``burrforce device``: list, test and run haptic devices and vibration actuators."""

from __future__ import annotations

import argparse
import json
import sys
import time

from ..argtypes import float_in


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "device", help="haptic devices and vibration actuators: list, test, run",
        description="Find, check and drive a local haptic device (Novint Falcon over USB, a "
                    "simulated device, vendor devices) and a vibration actuator. docs/devices.md "
                    "explains set-up, udev rules and the workspace mapping.")
    dsub = p.add_subparsers(dest="device_command", metavar="ACTION", required=True)

    ls = dsub.add_parser("list", help="supported back-ends and the devices plugged in",
                         description="Every supported haptic device and actuator back-end, "
                                     "whether its requirements are installed, and the units "
                                     "detected on USB and sound cards; on Linux, the udev "
                                     "rule a detected but inaccessible device needs.")
    ls.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ls.set_defaults(func=_list)

    test = dsub.add_parser("test", help="home a device, render a gentle spring, report its "
                                        "servo rate and jitter",
                           description="Open the device, home it (the Falcon: move the grip "
                                       "through its range), render a gentle spring to the "
                                       "workspace centre, and report rate, period jitter, the "
                                       "range moved and the buttons seen. No server needed.")
    test.add_argument("device", metavar="DEVICE",
                      help="NAME[:key=value,...], e.g. falcon:firmware=nvent_firmware.bin, sim")
    test.add_argument("--seconds", type=float_in(0.1, 3600.0, "duration", "s"), default=5.0,
                      help="how long to render the spring. Default 5")
    test.add_argument("--no-home", action="store_true", help="skip homing")
    test.add_argument("--json", action="store_true", help="print the report as JSON")
    test.set_defaults(func=_test)

    run = dsub.add_parser("run", help="drive a device (and actuator) from a running server's "
                                      "session",
                          description="A device host: stream the device's pose into a session "
                                      "of a running `burrforce serve` (its connection file, or "
                                      "--server/--session/--key) and render the coupling "
                                      "model at the device's servo rate with the watchdog. "
                                      "`serve --haptic-device` does the same inside the server.")
    run.add_argument("device", metavar="DEVICE", help="NAME[:key=value,...]")
    add_loop_options(run)
    run.add_argument("--connection", default=None,
                     help="the connection file `burrforce serve` wrote (default: its default "
                          "path)")
    run.add_argument("--server", default=None, metavar="HOST:PORT",
                     help="the UDP endpoint instead of the connection file")
    run.add_argument("--session", type=int, default=None, help="session id (with --server)")
    run.add_argument("--key", default=None, help="session key in hex (with --server)")
    run.add_argument("--frame", default=None, help="the session's frame (with --server). "
                                                   "Default si_mm")
    run.add_argument("--seconds", type=float_in(0.0, 1e7, "duration", "s"), default=0.0,
                     help="stop after this long (0: until Ctrl-C)")
    run.set_defaults(func=_run)


def add_loop_options(p: argparse.ArgumentParser) -> None:
    """The device loop's options (shared with ``serve --haptic-device``)."""
    p.add_argument("--actuator", default=None, metavar="ACTUATOR",
                   help="vibration actuator: audio[:device=N], usb, wav:path=FILE")
    p.add_argument("--placement-mm", default=None, metavar="X,Y,Z",
                   help="where the device's workspace centre lies in the bone's frame, mm. "
                        "Default: the top centre of the bone's bounding box")
    p.add_argument("--workspace-scale", type=float_in(0.01, 100.0, "scale"), default=1.0,
                   help="bone mm per device mm. Default 1")
    p.add_argument("--spindle", choices=("on", "off", "button"), default="on",
                   help="spindle: always on, off, or on while the device's first button is "
                        "held. Default on")
    p.add_argument("--rpm", type=float_in(-1e6, 1e6, "rpm"), default=60_000.0,
                   help="spindle speed sent with each pose. Default 60000")
    p.add_argument("--rotation", default=None, metavar="X,Y,Z,W",
                   help="the device frame's orientation in the bone's frame, a quaternion. "
                        "Default identity (device up = bone up, toward the user = bone +x)")
    p.add_argument("--stale-ms", type=float_in(1.0, 50.0, "watchdog", "ms"), default=30.0,
                   help="zero force when the newest reply is older than this. Default 30")
    p.add_argument("--no-home", action="store_true", help="do not home the device first")


def loop_config(args: argparse.Namespace, device: str, host: str, port: int, session: int,
                key_hex: str | None, frame: str, bone_info: dict | None,
                placement_position=(0.0, 0.0, 0.0),
                placement_orientation=(0.0, 0.0, 0.0, 1.0)):
    from ..devices.loop import DeviceLoopConfig
    from ..devices.mapping import WorkspaceMap, bone_top_centre, parse_vector
    from ..devices.registry import check_spec

    check_spec(device, "haptic")
    if args.actuator:
        check_spec(args.actuator, "actuator")
    placement = (parse_vector(args.placement_mm, 3, "--placement-mm")
                 if args.placement_mm else bone_top_centre(bone_info))
    rotation = (parse_vector(args.rotation, 4, "--rotation") if args.rotation
                else (0.0, 0.0, 0.0, 1.0))
    return DeviceLoopConfig(
        device=device, host=host, port=port, session=session, key_hex=key_hex, frame=frame,
        placement_position=tuple(placement_position),
        placement_orientation=tuple(placement_orientation),
        workspace=WorkspaceMap(placement, rotation, args.workspace_scale),
        actuator=args.actuator, rpm=args.rpm, spindle=args.spindle, home=not args.no_home,
        stale_s=args.stale_ms * 1e-3)


def _session_settings(c, profile: str | None) -> dict:
    """The session's bone, frame and placement over REST, having made its output coupled
    for the device's ``profile`` if it had no device profile ({} without a REST URL and
    token, or if the server does not answer)."""
    if not (c.http_url and c.token):
        return {}
    import httpx

    from ...client.rest import BurrRest, RestError

    try:
        with BurrRest(c.http_url, c.token, timeout_s=10.0) as rest:
            bone = rest.session(c.session).get("bone")
            params = rest.parameters(c.session)
            if params["device"] is None and profile is not None:
                # A raw session's force would be rendered as it is: it buzzes on a device.
                params = rest.set_parameters(c.session, device=profile)
                print(f"session {c.session}: coupled output for the {profile} profile",
                      file=sys.stderr)
    except (RestError, httpx.HTTPError) as exc:
        print(f"note: could not read session {c.session} over REST ({exc})", file=sys.stderr)
        return {}
    return {"bone": bone, "frame": params["frame"],
            "placement_position": tuple(params["placement_position"]),
            "placement_orientation": tuple(params["placement_orientation"])}


def _list(args: argparse.Namespace) -> int:
    from ..devices.discovery import format_devices, list_devices

    devices = list_devices()
    if args.json:
        print(json.dumps(devices, indent=2))
    else:
        print(format_devices(devices))
    return 0


def _test(args: argparse.Namespace) -> int:
    from ..devices.selftest import run_selftest

    say = (lambda text: print(text, file=sys.stderr, flush=True)) if args.json else \
        (lambda text: print(text, flush=True))
    report = run_selftest(args.device, args.seconds, home=not args.no_home, say=say)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        rate = report["servo_rate_hz"]
        print(f"{report['cycles']} cycles in {report['seconds']:.2f} s: "
              f"{rate or 0:.0f} Hz, period p50 {report['period_p50_us'] or 0:.0f} µs, "
              f"p99 {report['period_p99_us'] or 0:.0f} µs, max "
              f"{report['period_max_us'] or 0:.0f} µs; peak force "
              f"{report['peak_force_N']:.2f} N; buttons seen {report['buttons_seen']:#x}")
    for warning in report.get("warnings", ()):
        say(f"warning: {warning}")
    return 0


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ...client import connection
    from ..devices.process import DeviceProcess

    if args.server:
        host, _, port = args.server.rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"--server must be HOST:PORT, got {args.server!r}")
        if args.session is None:
            raise ValueError("--server needs --session (and --key for a keyed session)")
        c = connection.Connection(host.strip("[]"), int(port), args.session, args.key,
                                  args.frame or "si_mm")
    else:
        c = connection.read(Path(args.connection) if args.connection else None)
    from ..devices.registry import HAPTIC, check_spec

    name, options = check_spec(args.device, "haptic")
    session = _session_settings(c, HAPTIC[name].profile_for(options))
    config = loop_config(args, args.device, c.host, c.udp_port, c.session, c.key_hex,
                         session.get("frame", c.frame), session.get("bone"),
                         session.get("placement_position", (0.0, 0.0, 0.0)),
                         session.get("placement_orientation", (0.0, 0.0, 0.0, 1.0)))
    if not session:
        print("note: without the session's REST URL and token (the connection file has "
              "them) its bone, frame and placement are unknown — the workspace centre sits at "
              "the server frame's origin unless --placement-mm says otherwise — and its "
              "output must already be coupled for a device (parameters.device): a raw "
              "output's force is rendered as it is", file=sys.stderr)
    process = DeviceProcess(config)
    process.start()
    t0 = time.monotonic()
    try:
        while process.is_alive():
            for text in process.drain_events():
                print(text, flush=True)
            if args.seconds and time.monotonic() - t0 >= args.seconds:
                break
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        process.stop()
        for text in process.drain_events():
            print(text, flush=True)
    s = process.status()
    print(f"{s['state']}: {s['counters']['cycles']} cycles, {s['servo_rate_hz'] or 0:.0f} Hz, "
          f"period p50 {s['period_p50_us'] or 0:.0f} / p99 {s['period_p99_us'] or 0:.0f} µs, "
          f"{s['counters']['watchdog_trips']} watchdog trips")
    return 0 if s["state"] == "stopped" else 1
