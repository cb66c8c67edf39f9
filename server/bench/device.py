"""``burrforce bench device``: the device loop's servo rate and jitter, pose-to-force latency
and watchdog reaction, with the simulated device and a Falcon: the one plugged in here, or
(the project's own run, ``python -m benchmarks.device``) the USB-emulated one.

Each device runs for real, in wall time: a server (real hot loop, real UDP on 127.0.0.1)
with the workpiece phantom and a session coupled for the device's profile, and the device loop
in its own process streaming into it while the device's hand cuts grooves. Measured, from the
loop's own statistics (``devices.stats``):

- ``servo_rate_hz``: cycles per second of wall time; ``period_p50_us``/``period_p99_us``: the
  time between successive device I/O cycles (10 µs bins); ``overruns``: cycles that started
  more than half a period late;
- ``round_trip_p50_us``/``p99``: a pose's sampling to the loop reading its reply;
  ``pose_to_force_p50_us``/``p99``: a pose's sampling to the device being sent the first force
  rendered from its reply;
- ``watchdog_ms``: the hot loop is then killed (SIGKILL) while the device is pushed; the time
  from the newest reply's arrival to the device being sent zero force. ``watchdog_ms`` in
  the rows is the worst of ``--repeats`` such kills (a fresh server each).
- ``cycle_cpu_us`` (the same in every row): the loop's CPU work per cycle without sockets or
  a device (``device_cycle``), and with ``--callgrind`` ``cycle_instructions`` per cycle;
- ``stop_ms`` (emulated Falcon only, one more run): SIGTERM to the device process while the
  device is pushed → the last non-zero motor command the emulated Falcon received, from the
  emulator's own log (and the last command must be zero).

A real Falcon is run with the user's hand on its grip (cut into the bone while it streams);
without one plugged in and accessible, its row says why it was skipped. The emulated Falcon
(``FalconSource``: the project's harness, ``tests/support/emulation``, not installed) is the
real driver (pyusb → libusb → usbfs) against umockdev: its timing includes the emulation's
cost per transfer and says nothing about real hardware.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import signal
import sys
import tempfile
import time
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from . import runner
from .timing import machine_line

DEVICES = ("sim", "falcon")
SIM_SPEC = "sim:profile=falcon,hand=groove,depth_mm=4"
KEY = "5a" * 32


def _wait(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def falcon_groove_path(seconds: float) -> list[list[float]]:
    """The emulated Falcon's hand: grooves like the sim device's, as waypoints
    ``[t_s, x, y, z]`` in the Falcon's own frame (mm from its workspace centre; x right,
    y up, z toward the user): down 4 mm below the workspace centre (into the bone, with the
    default placement), 16 mm toward the user, up, back, for ``seconds``."""
    cycle = ((0.0, (0.0, 6.0, -8.0)), (0.5, (0.0, -4.0, -8.0)), (3.7, (0.0, -4.0, 8.0)),
             (4.2, (0.0, 6.0, 8.0)), (4.7, (0.0, 6.0, -8.0)))
    period = cycle[-1][0]
    path, t0 = [], 0.0
    while t0 <= seconds + period:
        for t, p in (cycle if t0 == 0.0 else cycle[1:]):
            path.append([t0 + t, *p])
        t0 += period
    return path


class FalconSource(Protocol):
    """Where the ``falcon`` row's device comes from instead of the USB bus: an emulator."""

    def unavailable(self) -> str | None:
        """None when the source can run here, else why not (the row's ``skipped``)."""

    def start(self) -> AbstractContextManager[Any]:
        """A started emulator for one run: its ``client_env()`` is the device process's
        environment, its ``control(cmd, **args)`` scripts the hand (``set_hand``) and reads
        the motor log (``log``)."""


def real_falcon_missing() -> str | None:
    """None when a Falcon is plugged in and this user may open it, else why not."""
    from ..devices.discovery import list_devices

    entry = next(e for e in list_devices(audio=False) if e["name"] == "falcon")
    if any(u["accessible"] for u in entry["units"]):
        return None
    problems = [u["problem"] for u in entry["units"] if u["problem"]]
    return ("; ".join(problems) if problems else "no Falcon connected") + \
        " (the project's emulated run: python -m benchmarks.device)"


def _run_once(spec: str, seconds: float, env: dict | None, emulator=None,
              finish: str = "kill") -> dict:
    """One server + device loop: stream for ``seconds``, then ``finish``: ``kill`` the hot
    loop and time the watchdog, or ``sigterm`` the device process and time (from the
    emulated Falcon's own log) its last non-zero motor command."""
    from ..api.config import ServeConfig
    from ..api.models import Parameters
    from ..api.stack import ServerStack
    from ..devices import stats as st
    from ..devices.loop import DeviceLoopConfig
    from ..devices.mapping import WorkspaceMap, bone_top_centre
    from ..devices.process import DeviceProcess

    with tempfile.TemporaryDirectory() as tmp:
        stack = ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=Path(tmp)), "b" * 24)
        stack.start_backend()
        process = None
        try:
            source = stack.plane.resolve("phantom:workpiece", None, 0.1)
            session = stack.add_session(source, Parameters(device="falcon"), session_id=1,
                                        key_hex=KEY)
            host, port = stack.udp_address
            config = DeviceLoopConfig(spec, host, port, 1, KEY, workspace=WorkspaceMap(
                bone_top_centre(session.bone_info)), home=True, home_timeout_s=30.0)
            process = DeviceProcess(config)
            process.start(env)
            state = process.wait_state(("running", "failed", "stopped"), 120.0)
            if state != "running":
                raise RuntimeError(f"{spec}: the device loop is {state}: "
                                   f"{[t for _, t in process.events]}")
            if emulator is not None:
                emulator.control("set_hand", path=falcon_groove_path(seconds))
            time.sleep(seconds)
            status = process.status()
            s = process.stats
            # Act while the device is pushed.
            pushed = _wait(lambda: s[st.ST_LIVE] > 0 and np.linalg.norm(
                s[st.ST_FORCE:st.ST_FORCE + 3]) > 0.05, 10.0)
            out = {"status": status, "watchdog_ms": None, "stop_ms": None}
            if finish == "sigterm":
                if not pushed:
                    raise RuntimeError(f"{spec}: the device was never pushed")
                t_term = time.monotonic_ns()
                process.stop()
                rows = emulator.control("log", since_ns=t_term)["rows"]
                nonzero = [r[0] for r in rows if any(r[1:4])]
                if rows and any(rows[-1][1:4]):
                    raise RuntimeError(f"{spec}: the last motor command after SIGTERM is not "
                                       f"zero: {rows[-1]}")
                out["stop_ms"] = (max(nonzero) - t_term) * 1e-6 if nonzero else 0.0
                return out
            before = s[st.ST_T_DEVICE_ZERO]
            os.kill(stack.hot.pid, signal.SIGKILL)
            if not _wait(lambda: s[st.ST_T_DEVICE_ZERO] != before, 2.0):
                raise RuntimeError(f"{spec}: the force did not go to zero within 2 s of the "
                                   "hot loop's death")
            out["watchdog_ms"] = float(s[st.ST_T_DEVICE_ZERO] - s[st.ST_T_LAST_REPLY]) * 1e3
            return out
        finally:
            if process is not None:
                process.stop()
            stack.stop()


def bench_device(name: str, seconds: float, repeats: int,
                 falcon: FalconSource | None = None) -> dict:
    """The row for one device (``sim`` or ``falcon``: the real one, or ``falcon``'s)."""
    runs = []
    if name == "sim":
        runs = [_run_once(SIM_SPEC, seconds, None) for _ in range(repeats)]
    elif falcon is None:
        reason = real_falcon_missing()
        if reason is not None:
            return {"device": name, "skipped": reason}
        runner.say(f"falcon: hold the grip and cut into the bone for {seconds:g} s, "
                   f"{repeats} times")
        runs = [_run_once("falcon", seconds, None) for _ in range(repeats)]
    else:
        reason = falcon.unavailable()
        if reason is not None:
            return {"device": name, "skipped": reason}
        for finish in ("kill",) * repeats + ("sigterm",):
            with falcon.start() as emu:
                runs.append(_run_once("falcon", seconds, emu.client_env(), emu, finish))
    first = runs[0]["status"]
    watchdog = [r["watchdog_ms"] for r in runs if r["watchdog_ms"] is not None]
    stops = [r["stop_ms"] for r in runs if r["stop_ms"] is not None]
    return {"device": name, "seconds": seconds, "repeats": len(watchdog),
            "servo_rate_hz": first["servo_rate_hz"],
            "period_p50_us": first["period_p50_us"], "period_p99_us": first["period_p99_us"],
            "overruns": first["counters"]["overruns"], "cycles": first["counters"]["cycles"],
            "round_trip_p50_us": first["round_trip_p50_us"],
            "round_trip_p99_us": first["round_trip_p99_us"],
            "pose_to_force_p50_us": first["pose_to_force_p50_us"],
            "pose_to_force_p99_us": first["pose_to_force_p99_us"],
            "device_io_p50_us": first["device_io_p50_us"],
            "device_io_p99_us": first["device_io_p99_us"],
            "loop_work_p50_us": first["loop_work_p50_us"],
            "loop_work_p99_us": first["loop_work_p99_us"],
            "replies": first["counters"]["replies"],
            "watchdog_ms": max(watchdog), "watchdog_all_ms": watchdog,
            "stop_ms": max(stops) if stops else None}


CPU_CYCLES = 3000
CALLGRIND_CYCLES = (1000, 2000)


def cycle_cpu(callgrind: bool) -> dict:
    """The loop's CPU work per cycle without sockets or a device (``device_cycle``): µs in
    this process, and with ``callgrind`` the instructions per cycle (valgrind's count for
    CALLGRIND_CYCLES[1] cycles minus that for CALLGRIND_CYCLES[0], over the difference)."""
    from .device_cycle import CycleWork

    row = {"cycle_cpu_us": CycleWork(CPU_CYCLES).run(CPU_CYCLES), "cycle_instructions": None}
    if callgrind:
        import re
        import shutil
        import subprocess

        if shutil.which("valgrind") is None:
            raise RuntimeError("--callgrind needs valgrind (apt-get install valgrind)")
        counts = []
        with tempfile.TemporaryDirectory() as tmp:
            for n in CALLGRIND_CYCLES:
                out = subprocess.run(
                    ["valgrind", "--tool=callgrind", f"--callgrind-out-file={tmp}/cg.out",
                     sys.executable, "-m", "burrforce.server.bench.device_cycle", str(n)],
                    capture_output=True, text=True, check=True)
                m = re.search(r"Collected : (\d+)", out.stderr)
                if m is None:
                    raise RuntimeError(f"valgrind printed no count: {out.stderr[-400:]}")
                counts.append(int(m.group(1)))
        row["cycle_instructions"] = (counts[1] - counts[0]) / (CALLGRIND_CYCLES[1]
                                                               - CALLGRIND_CYCLES[0])
    return row


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = runner.add_bench(
        sub, "device", main,
        help="device loop: servo rate, jitter, pose-to-force latency, watchdog",
        description="Run the device loop in wall time with the simulated device and a "
                    "Falcon plugged in here (skipped without one) against a real server; "
                    "measure its servo rate and period jitter, the pose-to-reply and "
                    "pose-to-force latency, and the watchdog's reaction to a killed hot "
                    "loop. Writes OUT/device.md and device.json.", json_help=runner.JSON_ROWS)
    p.add_argument("--devices", nargs="+", choices=DEVICES, default=list(DEVICES))
    p.add_argument("--seconds", type=float, default=5.0,
                   help="how long each device streams before the watchdog test. Default 5")
    p.add_argument("--repeats", type=int, default=3,
                   help="watchdog kills per device (fresh server each). Default 3")
    p.add_argument("--no-write", action="store_true", help="print only, write no files")
    p.add_argument("--callgrind", action="store_true",
                   help="also count the loop's instructions per cycle with valgrind's "
                        "callgrind (repeatable on a busy machine; about a minute)")
    p.set_defaults(falcon=None)
    return p


def _fmt(value, digits: int = 0) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def write_results(rows: list[dict], out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    (out / "device.json").write_text(json.dumps({"date": stamp, "machine": machine_line(),
                                                 "rows": rows}, indent=2) + "\n")
    lines = ["# Device loop (`burrforce bench device`)", "",
             f"{stamp}; {machine_line()}. Method: the module docstring of "
             "`server/bench/device.py`. One run per device for the timing columns; "
             "`watchdog ms` is the worst of the repeats.", "",
             "| device | servo Hz | period p50 µs | period p99 µs | overruns | device I/O "
             "p50/p99 µs | loop work p50/p99 µs | round trip p50/p99 µs | pose→force p50/p99 µs "
             "| watchdog ms (all) | SIGTERM→zero ms |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if r.get("skipped"):
            lines.append(f"| {r['device']} | skipped: {r['skipped']} |||||||||| ")
            continue
        lines.append(
            f"| {r['device']} | {_fmt(r['servo_rate_hz'])} | {_fmt(r['period_p50_us'])} | "
            f"{_fmt(r['period_p99_us'])} | {r['overruns']} | "
            f"{_fmt(r['device_io_p50_us'])} / {_fmt(r['device_io_p99_us'])} | "
            f"{_fmt(r['loop_work_p50_us'])} / {_fmt(r['loop_work_p99_us'])} | "
            f"{_fmt(r['round_trip_p50_us'])} / {_fmt(r['round_trip_p99_us'])} | "
            f"{_fmt(r['pose_to_force_p50_us'])} / {_fmt(r['pose_to_force_p99_us'])} | "
            f"{_fmt(r['watchdog_ms'], 1)} ({', '.join(f'{w:.1f}' for w in r['watchdog_all_ms'])})"
            f" | {_fmt(r['stop_ms'], 1)} |")
    for r in rows[:1]:
        count = r["cycle_instructions"]
        lines += ["", f"The loop's CPU work per cycle without sockets or a device "
                  f"(`server/bench/device_cycle.py`: map, POSE, REPLY, render): "
                  f"{r['cycle_cpu_us']:.1f} µs"
                  + (f", {count / 1e3:.0f} k instructions (callgrind)" if count else "")
                  + "."]
    lines += ["", "Device I/O is one force-for-state exchange with the device; loop work is "
              "everything else the loop does in a cycle (pose, replies, render, statistics) "
              "but waiting for the reply and sleeping. The emulated Falcon's I/O is umockdev "
              "answering each usbfs call in Python (about 1.5–2.5 ms per exchange), so its "
              "rate here is the emulation's, not the driver's or a real Falcon's (unmeasured: "
              "no hardware)."]
    return runner.write_page(out, "device", lines)


def main(args: argparse.Namespace) -> int:
    """``args.falcon``: a :class:`FalconSource` (the project's emulated run), else None."""
    say = runner.say
    if not 0.5 <= args.seconds <= 600.0:
        raise ValueError("--seconds must be within [0.5, 600]")
    if not 1 <= args.repeats <= 20:
        raise ValueError("--repeats must be within [1, 20]")
    rows = []
    for name in args.devices:
        say(f"{name}: {args.repeats} × ({args.seconds:g} s streaming + a watchdog kill)...")
        row = bench_device(name, args.seconds, args.repeats, args.falcon)
        say(f"{name}: {row}")
        rows.append(row)
    cpu = cycle_cpu(args.callgrind)
    say(f"loop CPU per cycle: {cpu}")
    for row in rows:
        row.update(cpu)
    if args.no_write:
        if args.json:
            print(json.dumps(rows, indent=2))
        return 0
    return runner.report(args, write_results(rows, runner.out_dir(args)), rows=rows)
