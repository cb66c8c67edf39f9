"""``burrforce device`` and ``serve --haptic-device`` as a user runs them (subprocesses)."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from burrforce.client import connection

CLI = [sys.executable, "-m", "burrforce.server.cli"]
ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


def test_device_list_json_names_every_backend():
    out = _run("device", "list", "--json")
    assert out.returncode == 0, out.stderr
    entries = {e["name"]: e for e in json.loads(out.stdout)}
    assert {"sim", "falcon", "forcedimension", "openhaptics", "haply", "audio", "usb",
            "wav"} <= set(entries)
    assert entries["sim"]["kind"] == "haptic" and entries["audio"]["kind"] == "actuator"
    table = _run("device", "list")
    assert table.returncode == 0 and "falcon" in table.stdout


def test_device_test_reports_rate_and_jitter():
    out = _run("device", "test", "sim:hand=groove", "--seconds", "0.5", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["cycles"] > 10
    assert report["period_p50_us"] > 0 and report["period_p99_us"] >= report["period_p50_us"]
    assert report["info"]["backend"] == "sim"
    # The spring fades in and stays gentle: a quarter of the device's maximum at most.
    assert report["peak_force_N"] <= 0.25 * report["info"]["limits"]["max_force_N"] + 1e-9
    # The groove script moved the grip: the range shows it.
    lo, hi = report["range_mm"]["min"], report["range_mm"]["max"]
    assert hi[2] - lo[2] > 1.0


def test_device_test_sim_moves_its_hand_and_the_spring_follows():
    out = _run("device", "test", "sim", "--seconds", "1.5", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert "the simulated hand moves the grip" in out.stderr
    assert "move the grip to feel it" not in out.stderr
    lo, hi = report["range_mm"]["min"], report["range_mm"]["max"]
    assert hi[0] - lo[0] > 2.0 and hi[1] - lo[1] > 2.0  # round a circle
    assert report["peak_force_N"] > 0.05
    assert isinstance(report["warnings"], list)


def test_a_servo_that_misses_its_rating_is_warned_about():
    from burrforce.server.devices.selftest import servo_warnings

    assert servo_warnings(1000.0, 1000.0, 1100.0, 3000.0) == []
    slow = servo_warnings(702.0, 1000.0, 8109.0, 143_000.0)
    assert len(slow) == 3
    assert "702 Hz, below the device's rated 1000 Hz" in slow[0]
    assert "p99 is 8109 µs" in slow[1] and "143.0 ms" in slow[2]
    assert servo_warnings(None, 1000.0, None, None) == []


def test_device_commands_refuse_bad_input_clearly():
    for args, words in ((("device", "test", "nosuch"), "unknown haptic device"),
                        (("device", "test", "sim:speed"), "options are key=value"),
                        (("device", "test", "falcon", "--seconds", "1"), "0403:cb48"),
                        (("device", "test", "sim", "--seconds", "-1"), "duration")):
        out = _run(*args)
        assert out.returncode == 2, (args, out.stdout, out.stderr)
        assert words in out.stderr, (args, out.stderr)
        assert "Traceback" not in out.stderr


def test_bench_device_json_rows():
    out = _run("bench", "device", "--devices", "sim", "--seconds", "1", "--repeats", "1",
               "--no-write", "--json", timeout=300.0)
    assert out.returncode == 0, out.stderr
    (row,) = json.loads(out.stdout)
    for key in ("device", "servo_rate_hz", "period_p50_us", "period_p99_us", "watchdog_ms"):
        assert key in row
    assert row["device"] == "sim" and 0.0 < row["watchdog_ms"] <= 50.0
    assert row["cycle_cpu_us"] > 0.0


def test_bench_device_without_a_falcon_says_why_its_row_is_skipped():
    """The installed command measures a Falcon plugged in here, never an emulated one."""
    out = _run("bench", "device", "--devices", "falcon", "--no-write", "--json")
    assert out.returncode == 0, out.stderr
    (row,) = json.loads(out.stdout)
    if "skipped" not in row:
        pytest.skip("a Falcon is plugged in here (allowed in CI)")
    assert "python -m benchmarks.device" in row["skipped"]


def test_the_projects_device_bench_runs_the_emulated_falcon():
    """``python -m benchmarks.device`` (from the checkout): the Falcon row from umockdev's
    emulated Falcon, with the SIGTERM run only its motor log can time."""
    from support.emulation import emulation_unavailable_reason

    reason = emulation_unavailable_reason()
    if reason is not None:
        pytest.skip(f"umockdev emulation unavailable: {reason}")
    out = subprocess.run([sys.executable, "-m", "benchmarks.device", "--devices", "falcon",
                          "--seconds", "1", "--repeats", "1", "--no-write", "--json"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    (row,) = json.loads(out.stdout)
    assert row["device"] == "falcon" and row["servo_rate_hz"] > 0
    assert 0.0 < row["watchdog_ms"] <= 50.0 and row["stop_ms"] is not None


def test_serve_with_a_haptic_device(tmp_path):
    conn = tmp_path / "connection.json"
    wav = tmp_path / "cue.wav"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    serve = subprocess.Popen(
        [*CLI, "serve", "--udp-port", "0", "--http-port", "0", "--bone", "phantom:workpiece",
         "--data-dir", str(tmp_path / "data"), "--connection-file", str(conn),
         "--haptic-device", "sim:profile=falcon,hand=groove,depth_mm=4",
         "--actuator", f"wav:path={wav}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(t) for t in serve.stdout], daemon=True).start()

    def read_until(words: str, timeout_s: float) -> str:
        seen = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                seen.append(lines.get(timeout=0.5))
            except queue.Empty:
                continue
            if words in seen[-1]:
                break
        return "".join(seen)

    try:
        out = read_until("Ctrl-C stops", 300.0)
        assert "coupled output (device falcon)" in out, out
        assert "simulated falcon" in out, out
        c = connection.read(conn)
        with httpx.Client(base_url=c.http_url + "/v1", timeout=30.0,
                          headers={"Authorization": f"Bearer {c.token}"}) as api:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                status = api.get(f"/sessions/{c.session}/device").json()
                if status["counters"]["replies"] > 500:
                    break
                time.sleep(0.2)
            assert status["state"] == "running" and status["counters"]["replies"] > 500
            assert api.get("/devices").status_code == 200
        serve.send_signal(signal.SIGTERM)
        serve.wait(timeout=60)
        rest = read_until("stopped\n", 10.0)
        assert serve.returncode == 0, rest
        assert "stopped" in rest, rest
        assert wav.stat().st_size > 1000
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait()


def test_device_run_drives_a_running_servers_session(tmp_path):
    from burrforce.server.api.config import ServeConfig
    from burrforce.server.api.models import Parameters
    from burrforce.server.api.stack import ServerStack

    token = "device-run-token-0123456789abcdef"
    with ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path / "data"),
                     token) as stack:
        source = stack.plane.resolve("phantom:workpiece", None, 0.1)
        session = stack.add_session(source, Parameters(), session_id=3, key_hex="ab" * 32)
        host, port = stack.udp_address
        conn = connection.write(connection.Connection(host, port, 3, "ab" * 32, "si_mm", 0.1,
                                                      stack.url, token), tmp_path / "c.json")
        out = _run("device", "run", "sim:hand=groove,depth_mm=4", "--connection", str(conn),
                   "--seconds", "3")
        assert out.returncode == 0, out.stderr
        assert "coupled output for the generic profile" in out.stderr
        assert out.stdout.splitlines()[-1].startswith("stopped:"), out.stdout
        assert stack.plane.get(3).device.name == "generic"
        assert stack.plane.session_state(3)["accepted"] > 1000
        assert session.bone_info is not None
