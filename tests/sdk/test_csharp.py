# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
"""The C# SDK (client/csharp/Burrforce) against the live server: Mono's C# compiler builds the
core library warning-free and a test program (client/csharp/Tests) that prints one JSON line
per command; the checks on those results are here."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from harness import TICKS, check_groove, check_mesh_obj, run_json

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "client" / "csharp" / "Burrforce"
TESTS = ROOT / "client" / "csharp" / "Tests"
UNITY = ROOT / "client" / "unity"
VECTORS = ROOT / "proto" / "vectors" / "vectors.json"
INSTALL = "apt-get install mono-mcs mono-runtime libmono-system-net-http4.0-cil"
# mcs 6.8 knows C# up to 7.2; the SDK keeps to it (Unity and .NET compile it as well).
MCS = ["-langversion:7.2", "-warnaserror+", "-warn:4", "-nologo", "-r:System.Net.Http.dll"]


def _toolchain() -> tuple[str, str]:
    mcs, mono = shutil.which("mcs"), shutil.which("mono")
    if not mcs or not mono:
        pytest.skip(f"Mono's mcs/mono not installed ({INSTALL})")
    probe = subprocess.run([mono, "--version"], capture_output=True, text=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip(f"mono does not run ({INSTALL})")
    if not list(Path("/usr/lib/mono").glob("**/System.Net.Http.dll")):
        pytest.skip(f"System.Net.Http.dll missing ({INSTALL})")
    return mcs, mono


def _compile(mcs: str, out: Path, sources: list[Path], target: str) -> None:
    p = subprocess.run([mcs, *MCS, f"-target:{target}", f"-out:{out}", *map(str, sources)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, f"mcs failed:\n{p.stdout}\n{p.stderr}"


@pytest.fixture(scope="module")
def program(tmp_path_factory) -> list[str]:
    """The test program, compiled with warnings as errors: the command prefix to run it."""
    mcs, mono = _toolchain()
    out = tmp_path_factory.mktemp("csharp")
    core = sorted(CORE.glob("*.cs"))
    _compile(mcs, out / "Burrforce.Core.dll", core, "library")
    _compile(mcs, out / "BurrforceTests.exe", core + sorted(TESTS.glob("*.cs")), "exe")
    return [mono, "--debug", str(out / "BurrforceTests.exe")]


def _rest_args(live_server) -> list[str]:
    return ["--http-url", live_server["http_url"], "--token", live_server["token"]]


def test_sources_carry_the_licence_header():
    files = sorted(CORE.glob("*.cs")) + sorted(TESTS.rglob("*.cs")) \
        + sorted((UNITY / "Runtime").glob("*.cs")) + [UNITY / "Tools~" / "stage_core.py"]
    assert len(files) > 30
    for f in files:
        head = "\n".join(f.read_text().splitlines()[:3])
        assert "SPDX-License-Identifier: MIT" in head, f
        assert "Copyright (c) 2026 the burrforce authors" in head, f


def test_unity_scripts_type_check(program, tmp_path):
    """client/unity/Runtime/*.cs against the core and hand-written UnityEngine stand-ins
    (Tests/UnityStubs): catches C# errors in the package's scripts; Unity itself is not here."""
    mcs, _ = _toolchain()
    _compile(mcs, tmp_path / "UnityEngine.dll", sorted((TESTS / "UnityStubs").glob("*.cs")),
             "library")
    _compile(mcs, tmp_path / "Burrforce.Core.dll", sorted(CORE.glob("*.cs")), "library")
    p = subprocess.run([mcs, *MCS, "-target:library", f"-r:{tmp_path / 'UnityEngine.dll'}",
                        f"-r:{tmp_path / 'Burrforce.Core.dll'}",
                        f"-out:{tmp_path / 'Burrforce.Unity.dll'}",
                        *map(str, sorted((UNITY / "Runtime").glob("*.cs")))],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, f"mcs failed:\n{p.stdout}\n{p.stderr}"


def test_unity_package_layout():
    """package.json, the assembly definitions, and a committed .meta (stable GUID) for every
    asset: Unity imports git and tarball packages read-only and ignores files without one."""
    manifest = json.loads((UNITY / "package.json").read_text())
    assert manifest["name"] == "com.burrforce.haptics"
    assert manifest["version"] == "0.1.0" and manifest["unity"] == "2021.3"
    assert manifest["displayName"]
    unity_asm = json.loads((UNITY / "Runtime" / "Burrforce.Unity.asmdef").read_text())
    core_asm = json.loads((UNITY / "Runtime" / "Core" / "Burrforce.Core.asmdef").read_text())
    assert unity_asm["references"] == ["Burrforce.Core"] and core_asm["noEngineReferences"]
    for name in ("README.md", "LICENSE.md", "CHANGELOG.md"):
        assert (UNITY / name).is_file(), name
    p = subprocess.run([sys.executable, str(UNITY / "Tools~" / "stage_core.py"), "--check"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    guids = [line for m in UNITY.rglob("*.meta") for line in m.read_text().splitlines()
             if line.startswith("guid:")]
    assert len(guids) == len(set(guids))


def test_golden_vectors(program):
    got = run_json([*program, "vectors", "--vectors", str(VECTORS)], timeout_s=120)
    names = [v["name"] for v in json.loads(VECTORS.read_text())]
    assert got["names"] == names
    assert got["failures"] == [], got["failures"]
    assert got["mutations_rejected"] > 0


def test_self_checks(program):
    """Codec robustness (non-canonical forms, limits, fuzz), HMAC against the BCL's,
    sequence arithmetic, round trip, frames, JSON and mesh-message parsing."""
    got = run_json([*program, "selftest"], timeout_s=120)
    assert got["failures"] == [], got["failures"]
    assert got["passed"] > 100


def test_streamer_schedule_and_stalls(program):
    """Against a local UDP sink that plays the server's side of the handshake: POSEs stamped
    on the absolute 1 ms schedule with consecutive seqs, hellos until a tagged NEW_STREAM
    answers one (forged, unsolicited and repeated ones change nothing), that stream until a
    tagged WRONG_STREAM about it, then hellos again; a 40 ms stall skips the missed ticks (no
    burst), a 5 ms one sends them late."""
    got = run_json([*program, "stall"], timeout_s=60)
    assert got["failures"] == [], got
    assert got["streams"] == [0, 77, 0], got
    assert 0 < got["hellos"] < got["sent"], got


@pytest.fixture(scope="module")
def si_groove(program, live_server) -> dict:
    return run_json([*program, "groove", "--frame", "si_mm", *_rest_args(live_server)],
                    timeout_s=120)


def test_groove_si_mm(si_groove, python_groove):
    check_groove(si_groove, python_groove)
    assert si_groove["sent"] + si_groove["skipped_ticks"] == TICKS
    assert si_groove["error_replies"] == 0, si_groove
    # One stream, taken with hellos before the first tick; no other notice.
    assert si_groove["notices"] == si_groove["new_stream_notices"] == 1, si_groove
    assert si_groove["hellos"] >= 1, si_groove
    # 1000 ticks of the streamer thread (send, receive, verify, decode, hand-off): no garbage.
    assert si_groove["allocated_bytes_1000_ticks"] == 0, si_groove
    print("C# si_mm groove", si_groove, "python", python_groove)


def test_groove_unity(program, live_server, python_groove, si_groove):
    got = run_json([*program, "groove", "--frame", "unity", *_rest_args(live_server)],
                   timeout_s=120)
    check_groove(got, python_groove)
    # The force, turned back to server axes, points where the si_mm groove's does.
    a, b = got["steady_force_server_N"], si_groove["steady_force_server_N"]
    dot = sum(x * y for x, y in zip(a, b, strict=True))
    na, nb = math.sqrt(sum(x * x for x in a)), math.sqrt(sum(x * x for x in b))
    assert dot / (na * nb) > 0.9999, (a, b)
    assert na == pytest.approx(nb, rel=0.01)
    print("C# unity groove", got)


def test_engine_publish_at_frame_rate(program, live_server, python_groove):
    """The engine path: a 90 Hz "main thread" publishes the tool pose of the moment, the
    streamer interpolates it to 1 kHz: the steady cut matches the Python client's within 1 %
    (the reference samples the path at every tick; here the path is sampled per frame)."""
    got = run_json([*program, "publish", "--frame", "unity", "--fps", "90",
                    *_rest_args(live_server)], timeout_s=120)
    assert got["steady_ticks"] > 0.8 * python_groove["steady_ticks"], got
    for name in ("steady_feed_N", "steady_normal_N"):
        assert got[name] == pytest.approx(python_groove[name], rel=0.01), (name, got)
    # Contact starts half a second in: most frames after it render a force.
    assert got["frames_with_force"] > 0.5 * got["frames"], got
    print("C# publish", got)


def test_error_answers(program, live_server):
    """SPEC 3.4 through the SDK: UNKNOWN_SESSION and BAD_TAG notices, a BAD_VALUE error
    reply (seq consumed, force zero), silence for a duplicate, MALFORMED for a wrong
    element count."""
    got = run_json([*program, "errors", *_rest_args(live_server)], timeout_s=120)
    assert got["failures"] == [], got
    assert got["unknown_session_notice"] == 5
    assert got["bad_tag_notice"] == 6
    assert got["bad_value_error"] == 7
    assert got["duplicate_answers"] == 0
    assert got["malformed_notice"] == 1
    assert got["bad_version_notice"] == 3


def test_stream_handshake(program, live_server):
    """Streams are the server's (wire protocol 2): a new client object with the same key,
    numbering from 1 again right after another client's stream was used, gets its own stream
    from its first hello and a REPLY to its second datagram (no second of silence as in v1); a
    captured POSE of the earlier stream sent again gets WRONG_STREAM, never a REPLY; a replayed
    hello leaves the open stream alone; after a REST restart-stream the client says hello by
    itself; a new Streamer streams at once."""
    got = run_json([*program, "handshake", *_rest_args(live_server)], timeout_s=120)
    assert got["failures"] == [], got
    assert got["b_datagrams_to_first_reply"] == 2, got
    assert got["replay_notice"] == 12 and got["replay_replies"] == 0, got
    assert len(set(got["streams"])) == 3 and 0 not in got["streams"], got
    assert got["streamer_hellos"] >= 1, got
    print("C# handshake", got)


def test_mesh_chunks(program, live_server, rest, tmp_path):
    """A unity-frame session created by the SDK's REST helper; its WebSocket sync follows the
    groove; the union of its chunks (OBJ, as received) against the server's export."""
    obj = tmp_path / "unity.obj"
    got = run_json([*program, "mesh", "--frame", "unity", "--obj", str(obj),
                    *_rest_args(live_server)], timeout_s=240)
    try:
        assert got["failures"] == [], got
        assert got["mesh_bone_version"] >= got["reply_bone_version"] > 0
        assert got["full_messages"] >= 1 and got["chunks_before"] > 0
        assert got["chunks_replaced"] > 0 and got["chunks_changed_handed"] > 0
        result = check_mesh_obj(obj, rest, got["session"], "unity", "ccw")
    finally:
        rest.delete_session(got["session"])
    print("C# mesh", got, result)


def test_session_and_mesh_lifecycle(program, live_server):
    """What a Unity component lives through: an OwnedSession released while the server is
    still creating it is deleted once created (not left behind by a cancelled request); a
    MeshFollower reconnects a cut WebSocket with since = Have, restarts with back-off after the
    server closes it (session deleted: 1001, then 4404), switches to a new session (clear,
    FULL) and moves to a new client of the same session without a FULL resend."""
    got = run_json([*program, "lifecycle", *_rest_args(live_server)], timeout_s=240)
    assert got["failures"] == [], got
    assert got["released_while_creating"] is True, got
    assert got["have_before_drop"] > 0 and got["dropped_connections"] >= 1, got
    assert got["close_code_after_delete"] == 4404, got
    print("C# lifecycle", got)
