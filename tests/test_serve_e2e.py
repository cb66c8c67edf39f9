"""``burrforce serve`` as a user runs it: a subprocess with its REST port and UDP port, the
CLI demo cutting, REST calls changing Us and exporting the carved bone, SIGTERM. Bounded."""

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
import numpy as np
import pytest

from burrforce.server.bench.procstat import children
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.bone import LoadOptions, load_bone


def _demo(env, conn, tmp_path, y_mm: float, plot: bool = False) -> dict:
    args = [sys.executable, "-m", "burrforce.server.cli", "client", "demo", "--connection",
            str(conn), "--x-mm", "3", "--y-mm", str(y_mm), "--length-mm", "6", "--json"]
    if plot:
        args += ["--plot", str(tmp_path / "demo.png")]
    demo = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env)
    assert demo.returncode == 0, demo.stderr
    return json.loads(demo.stdout)


def test_serve_cut_change_us_over_rest_and_export(tmp_path):
    conn = tmp_path / "connection.json"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("BURRFORCE_TOKEN", None)
    serve = spawn_serve(tmp_path, "--bone", "phantom:workpiece")
    try:
        out = serve.banner
        assert conn.exists() and oct(conn.stat().st_mode & 0o777) == "0o600"
        c = serve.connection
        token = (tmp_path / "data" / "token").read_text().strip()
        assert c.token == token and f"token {token}" in out  # shown once, at the first start
        result = _demo(env, conn, tmp_path, -4.0, plot=True)
        assert result["lost"] <= 5
        assert result["surface_z_mm"] == pytest.approx(0.0, abs=0.03)
        assert result["steady_feed_N"] == pytest.approx(result["model_feed_N"], rel=0.05)
        assert result["steady_normal_N"] == pytest.approx(result["model_normal_N"], rel=0.05)
        assert (tmp_path / "demo.png").stat().st_size > 10_000
        with httpx.Client(base_url=c.http_url + "/v1", timeout=60.0,
                          headers={"Authorization": f"Bearer {token}"}) as api:
            r = api.patch(f"/sessions/{c.session}/parameters", json={"us_n_mm2": 1610.2})
            assert r.status_code == 200, r.text
            doubled = _demo(env, conn, tmp_path, 4.0)
            # The server now cuts with 2× Us, and the demo's model line is the session's.
            assert doubled["steady_feed_N"] == pytest.approx(2 * result["steady_feed_N"],
                                                             rel=0.05)
            assert doubled["steady_normal_N"] == pytest.approx(
                2 * result["steady_normal_N"], rel=0.05)
            assert result["model_parameters"] == doubled["model_parameters"] == "session"
            assert doubled["model_feed_N"] == pytest.approx(2 * result["model_feed_N"],
                                                            rel=1e-3)
            assert doubled["steady_feed_N"] == pytest.approx(doubled["model_feed_N"],
                                                             rel=0.05)
            r = api.get(f"/sessions/{c.session}/export/volume")
            assert r.status_code == 200
            (tmp_path / "carved.nrrd").write_bytes(r.content)
        grid = load_bone(tmp_path / "carved.nrrd", LoadOptions(kind="density")).grid

        def at(x, y, z):
            index = tuple(np.rint(grid.to_grid_point((x, y, z)) / grid.spacing_mm).astype(int))
            return int(grid.density[index])
        # Both grooves (y = −4 and y = +4, 0.5 mm deep from x = 3 to 9) are in the export.
        assert at(6.0, -4.0, -0.25) == 0 and at(6.0, 4.0, -0.25) == 0
        assert at(6.0, 0.0, -0.25) == 255
    finally:
        code, out = serve.stop()
    assert code == 0, out
    assert "stopped" in out
    assert not conn.exists()


def test_serve_demo_prints_the_live_view_and_keeps_cutting(tmp_path):
    serve = spawn_serve(tmp_path, "--demo", "--bone", "phantom:workpiece")
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x) for x in serve.proc.stdout],
                              daemon=True)
    reader.start()
    try:
        token = (tmp_path / "data" / "token").read_text().strip()
        c = serve.connection
        # The first start shows the token, so its link carries it (in the fragment).
        assert f"VIEW  {c.http_url}/ui/#token={token}" in serve.banner
        assert httpx.get(c.http_url + "/ui/", timeout=30.0).status_code == 200
        deadline = time.monotonic() + 120
        seen = ""
        while "watch it in the live view" not in seen:
            seen += lines.get(timeout=max(deadline - time.monotonic(), 0.1))
        assert "--demo finished (exit 0)" in seen
        with httpx.Client(base_url=c.http_url + "/v1", timeout=30.0,
                          headers={"Authorization": f"Bearer {token}"}) as api:
            def removed() -> float:
                return sum(api.get(f"/sessions/{c.session}/state").json()
                           ["removed_mm3"].values())
            first = removed()
            assert first > 1.0
            # Another groove beside the first, a few seconds later, with nobody asking.
            deadline = time.monotonic() + 60
            while removed() < 1.5 * first:
                assert time.monotonic() < deadline, "the demo cut no second groove"
                time.sleep(0.5)
        # A person's own `client demo` on the same session, as the demo's output suggests,
        # started while one of the demo's grooves is being cut: that groove gives way to it,
        # the next ones wait, and it cuts undisturbed.
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        deadline = time.monotonic() + 30
        while _demo_client(serve.proc.pid) is None:  # both clients start up together
            assert time.monotonic() < deadline, "no demo groove was being cut"
            time.sleep(0.02)
        # Two grooves back to back: longer than the demo's interval, so one of its grooves
        # falls due while they are cut.
        for y_mm in (-4.5, 4.5):
            mine = _demo(env, tmp_path / "connection.json", tmp_path, y_mm)
            assert mine["lost"] <= 5 and mine["cutting_ticks"] > 500
            # At most a demo groove's first hello took the stream from it, once.
            assert mine["streams_ended"] <= 1
        deadline = time.monotonic() + 60
        while "has been quiet" not in seen:
            seen += lines.get(timeout=max(deadline - time.monotonic(), 0.1))
        assert "--demo: another client streams on session" in seen
        # serve's status line, every few seconds while packets arrive: the demo's too.
        assert "packets/s  |F|" in seen
        assert "'new_stream'" not in seen  # a hello answered is a handshake, not a drop
        # Stopped as Ctrl-C or `timeout` stop it: the signal reaches the whole process group,
        # so the groove being cut ends (killed) a moment before serve begins to stop.
        deadline = time.monotonic() + 30
        while (client := _demo_client(serve.proc.pid)) is None:
            assert time.monotonic() < deadline, "no demo groove was being cut"
            time.sleep(0.1)
        os.kill(client, signal.SIGTERM)
        time.sleep(0.2)
    finally:
        serve.proc.send_signal(signal.SIGTERM)
        code = serve.proc.wait(timeout=60)
        reader.join(timeout=10)
    rest = "".join(lines.queue)
    assert code == 0, rest
    assert "--demo: stopped" not in rest  # not "a groove failed"


def _demo_client(serve_pid: int) -> int | None:
    """The pid of the `burrforce client demo` that serve --demo is running, if any."""
    for pid in children().get(serve_pid, []):
        try:
            if b"client\0demo" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:
            continue  # gone meanwhile
    return None


def test_a_bone_the_control_plane_refuses_is_an_error_not_a_traceback(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "burrforce.server.cli", "serve", "--bone", "phantom:nope",
         "--http-port", "0", "--udp-port", "0", "--data-dir", str(tmp_path / "data"),
         "--connection-file", str(tmp_path / "conn.json"), "--no-auth"],
        capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "burrforce serve: error: unknown phantom 'nope'; built in:" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("bone, says", [
    ("phantom:nope", "unknown phantom 'nope'"),
    ("missing.nrrd", "missing.nrrd"),
])
def test_a_bad_bone_is_refused_before_the_data_directory_is_read(tmp_path, bone, says):
    """At once, before the token or the journal is read and the control plane starts (the
    hot loops spawned ahead are stopped; a second server on the same data directory hears of
    the first one instead: test_data_dir_lock)."""
    done = subprocess.run(
        [sys.executable, "-m", "burrforce.server.cli", "serve", "--bone", bone,
         "--http-port", "0", "--udp-port", "0", "--data-dir", str(tmp_path / "data"),
         "--connection-file", str(tmp_path / "conn.json"), "--no-auth"],
        capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL, cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith("burrforce serve: error: ") and says in done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
    assert [p.name for p in (tmp_path / "data").iterdir()] == ["serve.lock"]  # no token, journal
