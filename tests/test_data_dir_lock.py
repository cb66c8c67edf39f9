"""One server per data directory: a second ``serve`` on a directory a running one holds exits
at once, naming the running server and ``--data-dir``, and reads nothing there (the first
server's journaled sessions stay the first one's)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from burrforce.server.api.data_lock import DataDirInUse, DataDirLock
from burrforce.server.bench.serve_process import spawn_serve


def test_the_lock_names_its_holder_and_goes_with_it(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys
            from burrforce.server.api.data_lock import DataDirLock
            lock = DataDirLock({str(tmp_path)!r})
            lock.acquire("http://127.0.0.1:8000", "127.0.0.1:9000")
            print("held", flush=True)
            sys.stdin.readline()
            """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(DataDirInUse) as caught:
            DataDirLock(tmp_path).acquire()
        message = str(caught.value)
        assert f"PID {holder.pid}" in message and "http://127.0.0.1:8000" in message
        assert str(tmp_path) in message and "--data-dir" in message
    finally:
        holder.kill()  # however the holder ends, the lock goes with it
        holder.wait()
    lock = DataDirLock(tmp_path)
    lock.acquire()
    lock.release()


def test_a_second_serve_on_the_same_data_directory_exits_at_once(tmp_path):
    first = spawn_serve(tmp_path)
    try:
        env = {k: v for k, v in os.environ.items() if k != "BURRFORCE_TOKEN"}
        second = subprocess.run(
            [sys.executable, "-m", "burrforce.server.cli", "serve", "--udp-port", "0",
             "--http-port", "0", "--data-dir", str(tmp_path / "data"), "--bone",
             "phantom:nope"], capture_output=True, text=True, env=env, timeout=60)
        assert second.returncode == 2
        assert "another burrforce serve" in second.stderr
        assert first.connection.http_url in second.stderr
        assert "--data-dir" in second.stderr
        # It stopped before reading anything: no resumed session, no bad --bone complaint.
        assert "resumed" not in second.stdout + second.stderr
        assert "phantom" not in second.stdout + second.stderr
    finally:
        code, after = first.stop()
    assert code == 0, after
