"""``burrforce serve``: the hot loop (its own process) and the REST control plane (this one).

Starts the UDP hot loop, loads a bone into a default session through the control plane, serves
REST with uvicorn, prints the endpoints, writes the connection file for local clients, and
reports traffic every few seconds until Ctrl-C or SIGTERM. ``--demo`` also runs the client demo
against it.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import secrets
import signal
import threading
import time
from pathlib import Path

from ...client import connection
from ...proto.frames import FRAMES
from ...proto.tag import parse_key
from .. import compile_cache
from ..api.config import (
    DEFAULT_HTTP_PORT,
    DEFAULT_UDP_PORT,
    TOKEN_FILE,
    ServeConfig,
    is_loopback,
    load_config,
)
from ..api.data_lock import DataDirLock
from ..argtypes import float_in, int_at_least, int_in
from ..haptics.profiles import PROFILES
from .device import add_loop_options, loop_config
from .first_start import compile_first_start, load_bone_kernels, start_filler, stop_filler
from .invocation import process_age_s
from .serve_banner import pool_line, say_banner
from .serve_demo import run_demo

STATUS_INTERVAL_S = 2.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve", help="run the haptic force server: UDP hot loop + REST control plane",
        description="Start the UDP hot loop and the REST control plane, load a bone into "
                    "session 1, print the endpoints, key and token, and report traffic until "
                    "Ctrl-C. Engines stream poses over UDP (proto/SPEC.md); the REST API "
                    "(/docs) creates sessions, loads bones, sets Us and K and exports the "
                    "carved bone. Settings: flags, else BURRFORCE_* variables, else --config "
                    "TOML, else defaults.")
    p.add_argument("--config", type=Path, default=None, metavar="TOML",
                   help="a TOML configuration file ([server] and [session] tables)")
    p.add_argument("--host", default=None,
                   help="address for REST and UDP. Default 127.0.0.1 (this machine only)")
    p.add_argument("--http-port", type=int_in(0, 65535, "HTTP port"), default=None,
                   help=f"REST port (0: any free one). Default {DEFAULT_HTTP_PORT}")
    p.add_argument("--udp-port", type=int_in(0, 65535, "UDP port"), default=None,
                   help=f"UDP port (0: any free one). Default {DEFAULT_UDP_PORT}")
    p.add_argument("--workers", type=int_at_least(1, "--workers (hot-loop processes)"),
                   default=None, metavar="N",
                   help="hot-loop processes, each on its own core and UDP port: worker i "
                        "listens on UDP_PORT + i (all must be free; with --udp-port 0 each "
                        "takes any free one). A new session goes to the least-loaded worker "
                        "and stays there; its REST view says which (udp, worker). Default: "
                        "the cores this process may use, less one for the control plane "
                        "(at least 1)")
    p.add_argument("--wake-ahead-us", type=float_in(0.0, 5000.0, "--wake-ahead-us", "µs"),
                   default=None, metavar="US",
                   help="each hot loop wakes this long before a stream's predicted next "
                        "packet and polls for it, so a reply does not wait for the "
                        "scheduler to wake the loop (about 50 µs less round trip on a 2-core "
                        "VM); it polls only while a core is free and nothing else holds its "
                        "own. 0 turns it off. Default 250")
    p.add_argument("--wake-cpu-share", type=float_in(0.01, 1.0, "--wake-cpu-share"),
                   default=None, metavar="SHARE",
                   help="a hot loop polls only while it is awake (working or polling) less "
                        "than this share of a core, so busy loops leave the cores to others. "
                        "Default 0.4")
    p.add_argument("--realtime", action="store_true", default=None,
                   help="run each hot loop's packet thread under the real-time scheduler "
                        "(SCHED_FIFO, priority 5): it runs the moment a packet arrives, ahead "
                        "of every normal task, and blocks for each packet instead of waking "
                        "ahead. Needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO of 5; where it "
                        "is not allowed serve says so and runs without it")
    p.add_argument("--bone", default=None,
                   help="the default session's bone: phantom:NAME (workpiece, layered, "
                        "temporal) or a bone file. Default phantom:temporal")
    p.add_argument("--voxel-mm", type=float_in(1e-3, 10.0, "voxel size", "mm"), default=None,
                   help="a phantom's voxel size, mm. Default per phantom")
    p.add_argument("--kind", choices=("ct", "labels", "density"), default=None,
                   help="what a --bone file's voxels are (needed for npy, npz, NRRD, NIfTI, "
                        "PNG)")
    p.add_argument("--device", choices=tuple(PROFILES), default=None,
                   help="the haptic device the default session's force is for: the output "
                        "is then coupled (a burr proxy and a virtual coupling within the "
                        "device's limits; the reply carries the coupling model). Default: "
                        "none, the raw model force")
    p.add_argument("--frame", choices=tuple(FRAMES), default=None,
                   help="the engine's frame and units for the default session. Default si_mm")
    p.add_argument("--session-id", type=int_in(0, (1 << 32) - 1, "session id"), default=None,
                   help="the default session's id. Default 1")
    auth = p.add_mutually_exclusive_group()
    auth.add_argument("--key", default=None,
                      help="the default session's key in hex. Default: a fresh random key")
    auth.add_argument("--no-auth", action="store_true", default=None,
                      help="no key for the default session: untagged datagrams (loopback "
                           "only, for development)")
    p.add_argument("--token", default=None,
                   help="the REST bearer token. Default: generated at the first start, kept "
                        "in DATA_DIR/token and shown once")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="uploads, snapshots, recordings. Default ~/.local/share/burrforce")
    p.add_argument("--bone-library", type=Path, default=None,
                   help="a folder of bone files sessions may load as library:PATH")

    def data_budget(text: str) -> int:
        from ..api.config import parse_size_bytes

        try:
            return parse_size_bytes(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    p.add_argument("--data-budget", type=data_budget, default=None, metavar="SIZE",
                   help="what uploads, snapshots, recordings and exports may take in the data "
                        "directory together (20GiB, 500M, 0: no limit); writes beyond it are "
                        "refused, GET /v1/storage shows the usage. Default 20GiB")
    p.add_argument("--connection-file", type=Path, default=None,
                   help=f"where to write the connection file. Default "
                        f"{connection.default_path()}")
    p.add_argument("--fresh", action="store_true",
                   help="start with no sessions from the journal: forget the sessions (and "
                        "their carving) the last run left in DATA_DIR/journal. Default: "
                        "resume them, with their ids, keys and carved bones")
    p.add_argument("--demo", action="store_true",
                   help="once ready, cut a groove with `burrforce client demo` so forces flow")
    p.add_argument("--haptic-device", default=None, metavar="DEVICE",
                   help="drive a local haptic device from the default session: "
                        "NAME[:key=value,...] with NAME sim, falcon, forcedimension, "
                        "openhaptics or haply (e.g. falcon:firmware=nvent_firmware.bin); "
                        "`burrforce device list` shows what is plugged in. The session's "
                        "output is then coupled for the device's profile")
    add_loop_options(p)
    p.set_defaults(func=main)


def resolve_token(config: ServeConfig) -> tuple[str, bool]:
    """(token, new): the configured one, else the one kept in the data directory, else a
    fresh one saved there (readable by this user only) and shown once."""
    if config.token:
        return config.token, False
    path = Path(config.data_dir).expanduser() / TOKEN_FILE
    try:
        token = path.read_text().strip()
        if len(token) >= 16:
            return token, False
    except FileNotFoundError:
        pass
    except OSError as exc:
        raise OSError(f"cannot read the token file {path}: {exc.strerror}") from None
    token = secrets.token_urlsafe(24)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, True


def _say_realtime(say, plane) -> None:
    """Whether ``--realtime`` took: each loop thread switches before it reports ready (a
    worker restarted later is reported by ``/v1/health``)."""
    from ..realtime import HOT_LOOP_PRIORITY, REFUSED, is_realtime

    pids = [hot.pid for hot in plane.workers if hot.is_alive()]
    granted = sum(is_realtime(pid) for pid in pids)
    if granted == len(pids):
        say(f"--realtime: {granted} hot loop(s) under SCHED_FIFO, priority {HOT_LOOP_PRIORITY}")
    else:
        say(f"--realtime: not permitted for {len(pids) - granted} of {len(pids)} hot loop(s), "
            f"which run without it: {REFUSED.format(priority=HOT_LOOP_PRIORITY)}")


def main(args: argparse.Namespace) -> int:
    # "ready in" counts from the command's start, its own imports included.
    t0 = time.monotonic() - process_age_s()
    flags = {"host": args.host, "http_port": args.http_port, "udp_port": args.udp_port,
             "workers": args.workers, "wake_ahead_us": args.wake_ahead_us,
             "wake_cpu_share": args.wake_cpu_share, "realtime": args.realtime,
             "bone": args.bone, "voxel_mm": args.voxel_mm, "frame": args.frame,
             "device": args.device,
             "session_id": args.session_id, "key": args.key, "no_auth": args.no_auth,
             "token": args.token, "data_dir": args.data_dir,
             "bone_library": args.bone_library, "data_budget_bytes": args.data_budget}
    if args.demo and args.haptic_device:
        raise ValueError("--demo and --haptic-device both stream the default session: choose "
                         "one (the device cuts with its own hand)")
    config = load_config(args.config, flags)
    if config.workers is None:
        from ..hotloop.pool import default_workers

        config = dataclasses.replace(config, workers=default_workers())
    if config.no_auth and not is_loopback(config.host):
        raise ValueError(f"--no-auth is for loopback development; {config.host} is reachable "
                         "from other machines, so its session needs a key")
    key_hex = None
    if not config.no_auth:
        key_hex = parse_key(config.key).hex() if config.key else None
    first_start = not compile_cache.is_complete()
    # The hot loops' interpreters start first and import beside this one, which imports
    # numba, the bone and the web stack and reads the token and the journal meanwhile: on two
    # cores the start-ups overlap. With every kernel in the cache the loops also load them
    # and open their ports meanwhile (on a first start they wait for the compile below).
    from ..hotloop.pool import spawn_pool  # light: nothing of numba, the bone or the web

    spawned = spawn_pool(config.host, config.udp_port, config.worker_count, wake=config.wake,
                         realtime=config.realtime, warm=not first_start)
    try:
        # Before anything in the data directory is read (the token, the journal): a second
        # server there would resume the first one's sessions.
        data_lock = DataDirLock(Path(config.data_dir))
        data_lock.acquire()
        try:
            _check_bone(config.bone, args.kind, config.voxel_mm)
        except BaseException:
            data_lock.release()
            raise
    except BaseException:
        for hot in spawned:
            hot.kill()
        raise
    try:
        say = functools.partial(print, flush=True)
        if first_start:
            # The web stack's imports (~1 s) overlap the compile's processes instead of
            # delaying their start.
            threading.Thread(target=_import_web_stack, name="burrforce-imports",
                             daemon=True).start()
            compile_first_start(say, on_packet_path=functools.partial(_start_loops, spawned),
                                on_phantoms=_load_bone_kernels_aside)
        else:
            _load_bone_kernels_aside()
        from ..api.models import Parameters
        from ..api.sources import file_source
        from ..api.stack import ServerStack

        token, new_token = resolve_token(config)
        bone = config.bone
        say(f"loading {bone}...")
        from ..api.journal import discard, discard_session

        if args.fresh:
            n = discard(Path(config.data_dir))
            if n:
                say(f"--fresh: {n} journaled session(s) forgotten")
        elif args.demo and discard_session(Path(config.data_dir), config.session_id):
            # The demo cuts a groove and compares it with the model: on fresh bone, not in
            # the groove the last demo left.
            say(f"--demo: session {config.session_id} starts on fresh bone (its journal from "
                "the last run is forgotten; other sessions are resumed)")
        stack = ServerStack(config, token, say=say)
    except BaseException:
        for hot in spawned:
            hot.kill()
        raise
    conn_path = conn = None
    filler = None
    try:
        stack.start_backend(spawned)
        plane = stack.plane
        if config.realtime:
            _say_realtime(say, plane)
        if bone.startswith("phantom:"):
            source = plane.resolve(bone, None, config.voxel_mm)
        elif bone.startswith(("library:", "upload:", "snapshot:")):
            source = plane.resolve(bone, args.kind)
        else:
            # The command line is the operator's own: any readable file, not only the library.
            path = Path(bone).expanduser().resolve()
            source = file_source(f"file:{path}", path, args.kind)
        device_profile = config.device
        if args.haptic_device and device_profile is None:
            from ..devices.registry import HAPTIC, check_spec

            name, options = check_spec(args.haptic_device, "haptic")
            device_profile = HAPTIC[name].profile_for(options)
        config = dataclasses.replace(config, device=device_profile)
        if config.session_id in stack.resumed:
            session = plane.get(config.session_id)
            _resumed_default(say, session, source, args.frame, key_hex)
        else:
            session = stack.add_session(source, Parameters(frame=config.frame,
                                                           device=device_profile),
                                        session_id=config.session_id, key_hex=key_hex,
                                        authenticated=not config.no_auth)
        if args.haptic_device:
            _start_device(say, plane, session, args)
        server = stack.server
        done = threading.Event()
        context = {}

        def announce() -> None:
            while not server.started and not done.wait(0.02):
                pass
            if not server.started:
                return
            # The default session's worker: with a pool it need not be worker 0.
            udp_host, udp_port = plane.address(session) or stack.udp_address
            if udp_host in ("0.0.0.0", "::"):  # bound to every interface: reach it locally
                udp_host = "127.0.0.1"
            c = connection.Connection(udp_host, udp_port, session.id, session.key_hex,
                                      session.config.frame,
                                      (session.bone_info or {}).get("voxel_mm"), stack.url,
                                      token)
            context["conn"] = c
            context["path"] = connection.write(c, args.connection_file)
            data_lock.note(stack.url, f"{udp_host}:{udp_port}")
            say_banner(say, time.monotonic() - t0, stack.url, c, token, new_token, config,
                       context["path"], args.haptic_device, pool_line(plane, session))
            if first_start:
                context["filler"] = start_filler(say, Path(config.data_dir))
            def report() -> None:
                _report(stack.stats, session.id, done, say, plane.devices)

            if args.demo:
                # The status lines from the end of the first groove's table on, beside the
                # demo's later grooves (which run until the server stops).
                run_demo(say, context["path"], done, session.bone_info, stack.url, plane,
                         session.id, threading.Thread(target=report, name="burrforce-status",
                                                      daemon=True).start)
            else:
                report()

        threading.Thread(target=announce, name="burrforce-announce", daemon=True).start()
        # uvicorn handles SIGINT/SIGTERM while it runs, then restores these handlers and
        # raises the signal again: they must let the clean-up below run (and a second Ctrl-C
        # must not cut it short; it is bounded by timeouts).
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, _ignore)
        server.run()
        done.set()
        conn, conn_path = context.get("conn"), context.get("path")
        filler = context.get("filler")
    finally:
        stop_filler(filler)
        say("stopping: sessions journaled (the next start resumes them; --fresh forgets "
            "them), hot loop stopped...")
        stack.stop()
        if conn_path is not None:
            connection.remove(conn_path, only_if=conn)
        data_lock.release()
    if stack.supervisor is not None and stack.supervisor.state == "lost":
        from ..api.supervisor import EXIT_LOOP_LOST

        say(f"stopped: the hot loop could not be restarted (exit {EXIT_LOOP_LOST})")
        return EXIT_LOOP_LOST
    say("stopped")
    return 0


def _check_bone(bone: str, kind: str | None, voxel_mm: float | None) -> None:
    """Refuse at once, before the token or the journal is read and the control plane starts,
    a phantom that does not exist or a bone file that cannot be read (``SourceError``, a
    ValueError: the command's error line, in the control plane's words). ``library:``,
    ``upload:`` and ``snapshot:`` sources live in the control plane's folders: it checks
    them."""
    from ..api.sources import SourceRoots, file_source, resolve

    if bone.startswith("phantom:"):
        resolve(bone, SourceRoots(None, Path(), Path()), None, voxel_mm)
    elif not bone.startswith(("library:", "upload:", "snapshot:")):
        path = Path(bone).expanduser().resolve()
        file_source(f"file:{path}", path, kind)


def _load_bone_kernels_aside() -> None:
    """While the hot loops warm up (other processes; on a first start, once the compile has
    put them in the cache), this process loads the kernels its own bone build needs: a
    process's first cached kernel costs ~1 s of numba set-up, which would otherwise follow,
    not overlap."""
    threading.Thread(target=load_bone_kernels, name="burrforce-kernels", daemon=True).start()


def _start_loops(spawned) -> None:
    """Send the spawned hot loops their config, once what they load without sessions (the
    packet path) is compiled: they warm up and open their ports while the tick still
    compiles. A loop that died meanwhile is reported when it is started."""
    for hot in spawned:
        try:
            hot.send_config()
        except OSError:
            pass


def _import_web_stack() -> None:
    """The control plane's modules (FastAPI, uvicorn, pydantic), imported ahead of their use
    (best effort: the use imports them again and reports any error)."""
    try:
        from ..api import stack  # noqa: F401
    except Exception:
        pass


def _ignore(signum: int, frame: object) -> None:
    pass


def _resumed_default(say, session, source, frame: str | None, key_hex: str | None) -> None:
    """The default session came back from the journal: say so, and what of the command line
    it does not follow (the journal wins: a restart must not throw away a trainee's carving
    unless asked to)."""
    lost = session.journal.recovery
    say(f"session {session.id} resumed from the journal: bone {session.source.source}, "
        + ("carving and key as they were" if lost is None else
           f"key as it was, carving up to its journal's last good records ({lost['summary']})"))
    differs = []
    if session.source.source != source.source:
        differs.append(f"--bone {source.source}")
    if key_hex is not None and key_hex != session.key_hex:
        differs.append("--key")
    if frame and frame != session.config.frame:
        differs.append(f"--frame {frame}")
    if differs:
        say(f"  not applied to it: {', '.join(differs)} (add --fresh to start over with them)")


def _start_device(say, plane, session, args: argparse.Namespace) -> None:
    """Attach ``--haptic-device`` to the default session (raises with the reason if it
    cannot be opened)."""
    from ..api.errors import ApiError

    def make_config(s, host: str, port: int):
        c = s.config
        return loop_config(args, args.haptic_device, host, port, s.id, s.key_hex, c.frame,
                           s.bone_info, c.placement_position, c.placement_orientation)

    say(f"opening {args.haptic_device}...")
    try:
        process = plane.attach_device(session.id, make_config)
    except ApiError as exc:
        raise RuntimeError(f"--haptic-device {args.haptic_device}: {exc.detail}") from None
    # The loop says what it opened once it has; the console shows the rest as it comes.
    deadline = time.monotonic() + 2.0
    while process.event_count == 0 and time.monotonic() < deadline:
        process.drain_events()
        time.sleep(0.02)
    process.console_seen, texts = process.events_since(0)
    for text in texts:
        say(f"  {text}")


def _report(stats, session_id: int, done: threading.Event, say, devices=None) -> None:
    """A status line every few seconds while packets arrive; device events as they come."""
    from ..hotloop.loop import LOOP_COUNTERS

    last_received = None
    last_t = time.monotonic()
    while not done.wait(STATUS_INTERVAL_S):
        if devices is not None:
            for sid, process in list(devices.loops.items()):
                process.console_seen, texts = process.events_since(process.console_seen)
                for text in texts:
                    say(f"device (session {sid}): {text}")
        latest = stats.latest
        if latest is None:
            continue
        now = time.monotonic()
        counters = latest["counters"]
        received = counters["received"]
        if last_received is not None and received < last_received:
            last_received = None  # a restarted hot loop counts from zero again
        if last_received is not None and received != last_received:
            rate = (received - last_received) / (now - last_t)
            s = latest["sessions"].get(session_id, {})
            removed = sum(s.get("removed_mm3", {}).values()) if s else 0.0
            quiet = ("received", "replied", "noticed", "new_stream", *LOOP_COUNTERS)  # hellos
            drops = {k: v for k, v in counters.items() if v and k not in quiet}
            tick = s.get("tick_p99_us")
            device = ""
            process = devices.loops.get(session_id) if devices is not None else None
            if process is not None:
                d = process.status()
                device = (f"  device {d['state']} {d['servo_rate_hz'] or 0:.0f} Hz"
                          + ("" if d["live"] else " (zero force: no fresh reply)"))
            say(f"{rate:6.0f} packets/s  |F| {s.get('last_force_N', 0.0):6.2f} N  removed "
                f"{removed:8.2f} mm³  tick p99 {tick or 0:5.0f} µs"
                + (f"  dropped {drops}" if drops else "") + device)
        last_received, last_t = received, now
