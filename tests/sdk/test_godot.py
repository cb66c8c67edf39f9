# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
"""The Godot SDK (client/godot) against a live server, run headless.

The core scripts are written in the GDScript subset shared by Godot 3 and 4; Debian ships
Godot 3 only (``godot3-server``), so that is what runs them here. Each test program prints one
JSON line (``run_json``).
"""

from __future__ import annotations

import json
import math
import shutil
import struct
from pathlib import Path

import pytest
from harness import (
    ANGLE_DEG,
    FEED_TICKS,
    PLUNGE_TICKS,
    RPM,
    STEADY_FROM,
    TICKS,
    check_groove,
    check_mesh_obj,
    new_session,
    run_json,
)

ROOT = Path(__file__).resolve().parents[2]
GODOT_DIR = ROOT / "client" / "godot"
VECTORS = ROOT / "proto" / "vectors" / "vectors.json"
GROOVE_ARGS = [f"--plunge={PLUNGE_TICKS}", f"--feed={FEED_TICKS}", f"--steady-from={STEADY_FROM}",
               f"--rpm={RPM!r}", f"--angle={ANGLE_DEG!r}"]


def godot() -> str:
    exe = shutil.which("godot3-server") or shutil.which("godot3")
    if exe is None:
        pytest.skip("Godot 3 headless not installed (apt-get install godot3-server)")
    return exe


_HOME: list[Path] = []


def _home() -> Path:
    """Godot's res:// for the runs: a scratch folder linking to the addon and the test
    programs (without a project, Godot 3 takes the working directory as res:// and writes its
    logs/ there: not into the source tree)."""
    if not _HOME:
        import tempfile
        home = Path(tempfile.mkdtemp(prefix="burrforce-godot-"))
        (home / "addons").symlink_to(GODOT_DIR / "addons", target_is_directory=True)
        (home / "tests").symlink_to(GODOT_DIR / "tests", target_is_directory=True)
        _HOME.append(home)
    return _HOME[0]


def run_godot(script: str, *args: str, timeout_s: float = 180.0) -> dict:
    # --quit: the programs do their work in _init; a script error there would otherwise leave
    # Godot idling in its main loop until the timeout.
    return run_json([godot(), "--no-window", "--quit", "-s", f"tests/{script}", "--", *args],
                    timeout_s=timeout_s, cwd=_home())


def _exact(value):
    """JSON's numbers as text GDScript cannot round: float64 bits and decimal integers (Godot's
    JSON parser reads every number as a double and loses -0.0 and denormals)."""
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, float):
        return "f:" + struct.pack(">d", value).hex()
    if isinstance(value, int):
        return f"i:{value}"
    if isinstance(value, list):
        return [_exact(v) for v in value]
    return value


def _endpoint(live_server, session: dict) -> list[str]:
    return [f"--host={live_server['host']}", f"--port={session['udp']['port']}",
            f"--session={session['id']}", f"--key={session['key']}"]


def test_golden_vectors(tmp_path):
    vectors = json.loads(VECTORS.read_text())
    for v in vectors:
        v["fields"] = {k: _exact(x) for k, x in v["fields"].items()}
    path = tmp_path / "vectors-exact.json"
    path.write_text(json.dumps(vectors))
    got = run_godot("test_vectors.gd", f"--vectors={path}", timeout_s=120)
    assert got["failures"] == [], got
    tagged = sum(1 for v in vectors if v["key_hex"])
    assert got["vectors"] == len(vectors)
    assert got["encoded"] == got["decoded"] == len(vectors), got
    assert got["verified"] == got["rejected_key"] == got["rejected_bytes"] == tagged, got
    # The v2 vectors, the handshake's among them, and v1's BAD_VERSION notice.
    names = {v["name"] for v in vectors}
    assert {"pose_hello", "notice_new_stream", "notice_wrong_stream",
            "notice_bad_version_v1"} <= names, names
    assert {v["version"] for v in vectors} == {1, 2}, vectors


def test_offline_checks():
    """Core scripts parse; RFC 1982; decoder forms, limits and garbage; mesh bounds checks;
    the client's side of the stream handshake."""
    got = run_godot("test_strict.gd", timeout_s=120)
    assert got["failures"] == [], got
    assert len(got["parsed"]) == 13, got
    h = got["handshake"]
    # Forged, untagged, foreign, unsolicited (seq, stamp), streamless, and a WRONG_STREAM
    # without a stream: none gives or takes a stream.
    assert h["refused_offers"] == ["bad_tag", "bad_tag", "foreign", "ignored", "ignored",
                                   "ignored", "ignored"], h
    assert h["reply_to_hello"] == "unsolicited", h  # hellos get no REPLY
    assert h["adopted"] == ["notice", True, 40], h
    # Streaming: a late second offer and a WRONG_STREAM for another stream change nothing.
    assert h["while_streaming"] == [False, False, "reply", 40], h
    assert h["closed"] == ["bad_tag", True, 0], h
    # After the stream closed: hello again; an offer answering a hello of the previous round
    # is ignored, this round's taken; seq counts on (13, 14).
    assert h["reopened"] == [0, False, True, 42, 14], h
    assert h["unkeyed"] == [True, 5], h
    assert h["v1_bad_version"] == ["notice", 3, 1], h


def _groove(live_server, rest, frame: str) -> dict:
    s = new_session(rest, frame)
    try:
        got = run_godot("test_groove.gd", *_endpoint(live_server, s), f"--frame={frame}",
                        "--rate=1000", *GROOVE_ARGS)
    finally:
        rest.delete_session(s["id"])
    print(f"godot groove ({frame}):", json.dumps(got))
    return got


@pytest.fixture(scope="module")
def godot_groove_si(live_server, rest):
    return _groove(live_server, rest, "si_mm")


def test_groove_si_mm(godot_groove_si, python_groove):
    print("python groove:", json.dumps(python_groove))
    check_groove(godot_groove_si, python_groove)
    assert godot_groove_si["dropped"] == {}, godot_groove_si


def test_groove_godot_frame(live_server, rest, godot_groove_si, python_groove):
    got = _groove(live_server, rest, "godot")
    check_groove(got, python_groove)
    # The force comes back on Godot's axes; turned back to the server's it must point as the
    # si_mm groove's does.
    a = godot_groove_si["steady_force_server_N"]
    b = got["steady_force_server_N"]
    na, nb = math.hypot(*a), math.hypot(*b)
    assert nb == pytest.approx(na, rel=0.01)
    assert sum(x * y for x, y in zip(a, b, strict=True)) / (na * nb) > 0.999, (a, b)
    # ... and differ from it on Godot's own axes (server x = -z, y = -x, z = y).
    e = got["steady_force_engine_N"]
    assert e == pytest.approx([-b[1], b[2], -b[0]], rel=1e-9, abs=1e-12)


def test_error_answers(live_server, rest):
    s = new_session(rest)
    try:
        got = run_godot("test_errors.gd", *_endpoint(live_server, s), timeout_s=60)
    finally:
        rest.delete_session(s["id"])
    assert [e["error"] for e in got["unknown_session"]] == [5], got  # UNKNOWN_SESSION
    assert [e["error"] for e in got["bad_tag"]] == [6], got  # BAD_TAG
    assert got["opened"], got
    dup = got["duplicate"]
    assert [(e["kind"], e["error"]) for e in dup["first"]] == [("reply", 0)], got
    assert dup["again"] == [], got  # a duplicate is never answered
    bv = got["bad_value"]
    assert bv["reply"]["error"] == 7 and bv["reply"]["seq"] == bv["sent_seq"], got
    assert bv["reply"]["force"] == [0.0, 0.0, 0.0] and bv["reply"]["status"] == 0, got
    assert [(e["kind"], e["seq"], e["error"]) for e in bv["next"]] == \
        [("reply", bv["sent_seq"] + 1, 0)], got
    assert bv["reused_seq"] == [], got  # the NaN POSE's seq was consumed
    assert [e["error"] for e in got["malformed"]] == [1], got  # MALFORMED
    # A v1 POSE: BAD_VERSION in v1's own NOTICE shape.
    assert got["bad_version"] == [{"kind": "notice", "error": 3, "version": 1}], got
    st = got["streamer"]
    # From seq 1, right after the seq-1000 stream above: a stream of its own, no idle wait.
    assert st["streams"] == 1, got
    assert st["error"] == 7 and st["error_replies"] >= 10 and not st["fresh"], got
    assert st["force"] == [0.0, 0.0, 0.0] and st["vibration_amplitude"] == 0.0, got
    # A 30 ms stall: the missed ticks are skipped and counted, not sent in a burst.
    stall = got["stall"]
    assert 25 <= stall["skipped"] <= 200, got  # 30 ms of ticks, plus what a busy machine adds
    assert stall["sent"] + stall["skipped"] == 300, got
    assert stall["first_after_stall"] >= stall["stalled_at"] + 29, got  # 30 ms skipped
    assert stall["close_sends_after"] <= 3, got  # a burst would send ~30 back to back
    assert stall["stamps_on_schedule"], got
    # Hellos until the stream opened, then a REPLY for (nearly) every POSE.
    assert stall["streams"] == 1 and 1 <= stall["hellos"] < stall["sent"], got
    assert stall["replies"] >= 0.9 * (stall["sent"] - stall["hellos"]), got
    assert 0 < stall["rtt_us"] < 100_000, got


def test_stream_handshake(live_server, rest):
    s = new_session(rest)
    try:
        got = run_godot("test_handshake.gd", *_endpoint(live_server, s),
                        f"--url={live_server['http_url']}", f"--token={live_server['token']}",
                        timeout_s=120)
    finally:
        rest.delete_session(s["id"])
    print("godot handshake:", json.dumps(got))

    def one(rows, kind, error=None):
        """The single datagram as the first Rules judged it: [kind, error, seq, stream,
        changed, status]."""
        assert len(rows) == 1, rows
        row = rows[0][0]
        assert row[0] == kind and (error is None or row[1] == error), rows
        return row

    new_stream, wrong_stream = 11, 12
    hello = one(got["a_hello"], "notice", new_stream)
    assert hello[2] == 1 and hello[4] is True and hello[3] == got["a"]["stream"] != 0, got
    assert got["a"]["replies"] == 20 and got["a"]["next_seq"] == 22, got
    # B from seq 1 right after A reached seq 21: its first hello opens a stream of its own,
    # and its very next POSE (seq 2) is answered, STALE only on that first tick.
    b_hello = one(got["b_hello"], "notice", new_stream)
    assert b_hello[2] == 1 and b_hello[4] is True, got
    b = got["b"]
    assert b["stream"] not in (0, got["a"]["stream"]), got
    replies = [one(p, "reply", 0) for p in b["poses"]]
    assert [r[2] for r in replies] == [2, 3, 4], got
    stale = 16
    assert [bool(r[5] & stale) for r in replies] == [True, False, False], got
    # A's POSE replayed: WRONG_STREAM for A's stream, tagged (A's rules believe it and say
    # hello again); B's rules ignore it, and B streams on.
    (a_view, b_view), = got["replayed_pose"]
    assert a_view[:2] == ["notice", wrong_stream] and a_view[3] == got["a"]["stream"], got
    assert a_view[4] is True and b_view[0] == "notice" and b_view[4] is False, got
    one(got["after_replayed_pose"], "reply", 0)
    # A's hello replayed: an offer nobody takes; B's stream untouched.
    (a_view, b_view), = got["replayed_hello"]
    assert a_view[:2] == ["notice", new_stream] and a_view[4] is False, got
    assert b_view[4] is False, got
    one(got["after_replayed_hello"], "reply", 0)
    assert got["states"] == {"a": 0, "b": b["stream"]}, got
    # REST restart-stream under a running streamer: it was told (WRONG_STREAM), said hello,
    # got a second stream and streamed on.
    st = got["streamer"]
    assert st["restart_status"] == 204, got
    assert st["before"]["streams"] == 1 and st["before"]["stream"] != 0, got
    after = st["after"]
    assert after["streams"] == 2 and after["stream"] not in (0, st["before"]["stream"]), got
    assert after["wrong_stream"] >= 1 and after["new_stream"] >= 2, got
    assert after["replies"] >= st["before"]["replies"] + 20, got
    assert after["dropped"] == {}, got


def test_rest_helper(live_server):
    got = run_godot("test_rest.gd", f"--url={live_server['http_url']}",
                    f"--token={live_server['token']}", timeout_s=120)
    print("godot rest:", json.dumps(got))
    assert got["create"]["ok"] and got["create"]["status"] == 201, got
    assert got["frame"] == "godot" and got["key_len"] == 64 and got["udp_port"] > 0, got
    assert got["get"] == {"status": 200, "id": got["session"], "state": "ready"}, got
    assert got["parameters"] == {"status": 200, "frame": "godot"}, got
    assert got["patch"] == {"status": 200, "us_n_mm2": 1610.2}, got
    bad = got["patch_bad"]
    assert not bad["ok"] and bad["status"] == 422 and "no_such_field" in bad["detail"], got
    assert got["restart"] == {"ok": True, "status": 204}, got
    assert got["delete"] == {"ok": True, "status": 204}, got
    gone = got["get_deleted"]
    assert gone["status"] == 404 and f"no session {got['session']}" in gone["detail"], got
    assert got["wrong_token"]["status"] == 401 and got["wrong_token"]["detail"], got
    assert got["no_server"]["status"] == 0 and "127.0.0.1:9" in got["no_server"]["detail"], got


@pytest.mark.parametrize("channel", ["rest", "ws"])
def test_mesh_chunks(live_server, rest, tmp_path, channel):
    obj = tmp_path / "godot-bone.obj"
    got = run_godot("test_mesh.gd", f"--url={live_server['http_url']}",
                    f"--token={live_server['token']}", f"--obj={obj}", f"--channel={channel}",
                    *GROOVE_ARGS, timeout_s=400)
    print("godot mesh:", json.dumps(got))
    try:
        assert "error" not in got, got
        assert got["frame"] == "godot"
        # Replies may come late while the server meshes: only the mesh is judged here.
        assert got["sent"] == TICKS and got["replies"] >= 0.9 * TICKS, got
        assert got["initial_chunks"] > 0 and got["initial_triangles"] > 0, got
        assert got["have"] >= got["last_bone_version"] > got["initial_have"], got
        # The cut changed chunks, and the store replaced them (not merely added).
        assert got["replaced"] > 0 and got["updates_during_cut"] > 0, got
        checked = check_mesh_obj(obj, rest, got["session"], "godot", "cw")
        print("godot mesh check:", json.dumps(checked))
    finally:
        if "session" in got:
            rest.delete_session(got["session"])


def test_addon_version_and_headers():
    """The addon's version is the project's (the release zip, .ci/release-sdks, checks it as
    well); every source carries the licence."""
    import re

    import tomllib
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    cfg = (GODOT_DIR / "addons" / "burrforce" / "plugin.cfg").read_text()
    m = re.search(r'^version\s*=\s*"([^"]+)"', cfg, re.M)
    assert m and m.group(1) == project, (m and m.group(1), project)
    assert (GODOT_DIR / "addons" / "burrforce" / "LICENSE").is_file()
    for src in GODOT_DIR.rglob("*.gd"):
        head = src.read_text().splitlines()[:3]
        assert any("SPDX-License-Identifier: MIT" in x for x in head), src
        assert any("Copyright (c) 2026 the burrforce authors" in x for x in head), src


def _gdtoolkit(tool: str) -> list[str]:
    import importlib.util
    import sys

    if importlib.util.find_spec("gdtoolkit") is not None:
        return [sys.executable, "-m", f"gdtoolkit.{tool}"]
    exe = shutil.which({"parser": "gdparse", "linter": "gdlint"}[tool])
    if exe is None:
        pytest.skip("gdtoolkit not installed (pip install 'gdtoolkit==4.5.*'): no Godot 4 "
                    "grammar check")
    return [exe]


def test_godot4_grammar_and_lint():
    """Godot 4 is not packaged for Debian: the Godot-4-only nodes cannot run here. gdtoolkit's
    Godot 4 parser at least checks every script's syntax, and gdlint its style."""
    import subprocess
    scripts = sorted(str(p) for p in GODOT_DIR.rglob("*.gd"))
    for script in scripts:
        p = subprocess.run([*_gdtoolkit("parser"), script], capture_output=True, text=True,
                           timeout=60)
        assert p.returncode == 0, f"{script}: {p.stderr[-2000:]}"
    p = subprocess.run(_gdtoolkit("linter") + scripts, capture_output=True, text=True,
                       timeout=120, cwd=GODOT_DIR)
    assert p.returncode == 0, p.stdout + p.stderr
