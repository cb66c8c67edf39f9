# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
"""The C++ SDK (client/cpp) against the golden vectors and a live server: its test programs
are compiled with the Debian toolchain (warnings as errors) and run; their JSON results are
checked here, the groove against the Python client's."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import pytest
from harness import TICKS, check_groove, check_mesh_obj, run_json

ROOT = Path(__file__).resolve().parents[2]
SDK = ROOT / "client" / "cpp"
VECTORS = ROOT / "proto" / "vectors" / "vectors.json"
PROGRAMS = ("vectors", "groove", "errors", "mesh", "robustness", "handshake")
FLAGS = ["-std=c++17", "-O2", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-pthread"]
COMPILE_TIMEOUT_S = 300


def _compile(compiler: str, out_dir: Path, extra: list[str] = ()) -> dict[str, Path]:
    """All test programs, compiled in parallel."""
    jobs = {}
    for name in PROGRAMS:
        exe = out_dir / name
        cmd = [compiler, *FLAGS, *extra, "-I", str(SDK / "include"),
               str(SDK / "tests" / f"{name}.cpp"), "-o", str(exe)]
        jobs[name] = (exe, subprocess.Popen(cmd, stdout=subprocess.PIPE,
                                            stderr=subprocess.STDOUT, text=True))
    bins = {}
    for name, (exe, proc) in jobs.items():
        out, _ = proc.communicate(timeout=COMPILE_TIMEOUT_S)
        assert proc.returncode == 0, f"{compiler} failed on {name}.cpp:\n{out}"
        bins[name] = exe
    return bins


@pytest.fixture(scope="session")
def cpp_bins(tmp_path_factory) -> dict[str, Path]:
    if shutil.which("g++") is None:
        pytest.skip("g++ not installed (apt-get install g++)")
    return _compile("g++", tmp_path_factory.mktemp("cpp-bin"))


def _server_args(live_server) -> list[str]:
    return ["--url", live_server["http_url"], "--token", live_server["token"]]


def test_cpp_vectors(cpp_bins):
    """Every golden vector (protocol v2, the hello, NEW_STREAM, WRONG_STREAM and v1's
    BAD_VERSION notice among them), byte for byte both ways, its tag verified and every
    single-byte change and another key rejected; non-canonical forms decode; fuzzing does
    not crash; SessionRules follow the stream handshake (offline)."""
    got = run_json([str(cpp_bins["vectors"]), str(VECTORS)], timeout_s=60)
    vectors = json.loads(VECTORS.read_text())
    names = {v["name"] for v in vectors}
    assert {"pose_hello", "notice_new_stream", "notice_wrong_stream",
            "notice_bad_version_v1"} <= names, sorted(names)
    assert got["failures"] == []
    assert got["vectors"] == len(vectors)
    assert got["encoded"] == got["decoded"] == len(vectors)
    assert got["tag_checked"] == sum(v["key_hex"] is not None for v in vectors)
    assert got["fuzzed"] > 10_000
    assert got["stream_rule_checks"] >= 25


def test_cpp_vectors_sanitized(tmp_path):
    """The vectors and the decoder fuzzing under AddressSanitizer and UBSan: no read outside
    a datagram, no undefined behaviour."""
    if shutil.which("g++") is None:
        pytest.skip("g++ not installed (apt-get install g++)")
    exe = tmp_path / "vectors_asan"
    p = subprocess.run(["g++", *FLAGS, "-O1", "-g", "-fsanitize=address,undefined",
                        "-fno-sanitize-recover=undefined", "-I", str(SDK / "include"),
                        str(SDK / "tests" / "vectors.cpp"), "-o", str(exe)],
                       capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
    if p.returncode != 0 and "asan" in p.stderr.lower():
        pytest.skip(f"the sanitizer runtimes are not installed (apt-get install libasan8 "
                    f"libubsan1): {p.stderr[-300:]}")
    assert p.returncode == 0, p.stderr
    got = run_json([str(exe), str(VECTORS)], timeout_s=120)
    assert got["failures"] == []


def test_cpp_clang(tmp_path):
    """The headers also compile warning-free with clang++ (Unreal's Mac and Linux compiler)."""
    compiler = shutil.which("clang++")
    if compiler is None:
        pytest.skip("clang++ not installed (apt-get install clang)")
    bins = _compile(compiler, tmp_path)
    got = run_json([str(bins["vectors"]), str(VECTORS)], timeout_s=60)
    assert got["failures"] == []


def test_cpp_unreal_compatible(tmp_path):
    """What the Unreal plugin needs of the core, checked without Unreal: it compiles as
    C++20 (UE 5.3+'s default), and after Unreal's function-like macros (check, verify,
    ensure, TEXT) it still compiles (it uses none of those names), free of conversion and
    shadowing warnings."""
    if shutil.which("g++") is None:
        pytest.skip("g++ not installed (apt-get install g++)")
    strict = ["-Wconversion", "-Wsign-conversion", "-Wshadow"]  # headers only
    for source, std, more in (("macro_guard.cpp", "-std=c++17", strict),
                              ("mesh.cpp", "-std=c++20", []), ("errors.cpp", "-std=c++20", [])):
        flags = [f for f in FLAGS if not f.startswith("-std=")] + more
        p = subprocess.run(["g++", std, *flags, "-fsyntax-only", "-I", str(SDK / "include"),
                            str(SDK / "tests" / source)],
                           capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
        assert p.returncode == 0, f"{source} {std}:\n{p.stderr}"


def test_cpp_cmake_package(tmp_path):
    """The CMake package: install it, then build a program against it with
    find_package(burrforce) and run it on the vectors."""
    if shutil.which("cmake") is None or shutil.which("g++") is None:
        pytest.skip("cmake or g++ not installed (apt-get install cmake g++)")
    prefix, build, consumer = tmp_path / "prefix", tmp_path / "build", tmp_path / "consumer"

    def run(*cmd: str) -> None:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
        assert p.returncode == 0, f"{' '.join(cmd)}:\n{p.stdout}\n{p.stderr}"

    run("cmake", "-S", str(SDK), "-B", str(build), f"-DCMAKE_INSTALL_PREFIX={prefix}")
    run("cmake", "--install", str(build))
    assert (prefix / "include" / "burrforce" / "burrforce.hpp").is_file()
    consumer.mkdir()
    (consumer / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.14)\nproject(consumer CXX)\n"
        "find_package(burrforce 1 REQUIRED)\n"
        f"add_executable(vectors {SDK / 'tests' / 'vectors.cpp'})\n"
        "target_link_libraries(vectors PRIVATE burrforce::burrforce)\n"
        "target_compile_options(vectors PRIVATE -Wall -Wextra -Wpedantic -Werror)\n")
    run("cmake", "-S", str(consumer), "-B", str(consumer / "b"),
        f"-DCMAKE_PREFIX_PATH={prefix}")
    run("cmake", "--build", str(consumer / "b"))
    got = run_json([str(consumer / "b" / "vectors"), str(VECTORS)], timeout_s=60)
    assert got["failures"] == []


@pytest.fixture(scope="module")
def cpp_groove_si_mm(cpp_bins, live_server) -> dict:
    return run_json([str(cpp_bins["groove"]), *_server_args(live_server), "--frame", "si_mm"])


def test_cpp_groove_si_mm(cpp_groove_si_mm, python_groove):
    """The groove at 1 kHz through the Streamer, si_mm: the Python client's steady forces."""
    got = cpp_groove_si_mm
    print("C++ si_mm groove:", json.dumps(got))
    print("Python groove:", json.dumps(python_groove))
    assert got["sent"] + got["skipped_ticks"] == TICKS
    check_groove(got, python_groove)


def test_cpp_groove_unreal(cpp_bins, live_server, python_groove, cpp_groove_si_mm):
    """The same groove in an `unreal` session (cm, left-handed): the resistive components
    match Python's, and the force, back on the server's axes, points as in si_mm."""
    got = run_json([str(cpp_bins["groove"]), *_server_args(live_server), "--frame", "unreal"])
    print("C++ unreal groove:", json.dumps(got))
    check_groove(got, python_groove)
    # Unreal's y is the server's −y (SPEC 6.2): the engine force is the server force mirrored.
    fx, fy, fz = got["steady_force_server_N"]
    ex, ey, ez = got["steady_force_engine_N"]
    assert (ex, -ey, ez) == pytest.approx((fx, fy, fz), abs=1e-12)
    ref = cpp_groove_si_mm["steady_force_server_N"]
    dot = fx * ref[0] + fy * ref[1] + fz * ref[2]
    cos = dot / (math.hypot(fx, fy, fz) * math.hypot(*ref))
    assert cos > 0.9999, (got["steady_force_server_N"], ref)
    assert math.hypot(fx, fy, fz) == pytest.approx(math.hypot(*ref), rel=0.01)


def test_cpp_errors(cpp_bins, live_server):
    """SPEC 3.4's answers as the SDK reports them, and the Streamer's zero-force rules."""
    got = run_json([str(cpp_bins["errors"]), *_server_args(live_server)], timeout_s=120)
    print(json.dumps(got))
    assert got["unknown_session"]["kind"] == "notice"
    assert got["unknown_session"]["error"] == 5
    assert got["bad_tag"]["kind"] == "notice" and got["bad_tag"]["error"] == 6
    assert got["opened"]
    assert got["first"]["kind"] == "reply" and got["first"]["error"] == 0
    assert got["first"]["status"] & 16  # STALE: the first tick of a stream
    assert got["duplicate"]["kind"] == "none"
    assert got["nan_valid_locally"] is False
    bad = got["bad_value"]
    assert bad["kind"] == "reply" and bad["error"] == 7 and bad["force_zero"]
    assert bad["status"] == 0 and bad["seq"] == got["first"]["seq"] + 1
    assert got["bad_value_resent"]["kind"] == "none"  # its seq was consumed
    after = got["after_bad_value"]
    assert after["kind"] == "reply" and after["error"] == 0 and after["seq"] == bad["seq"] + 1
    assert after["status"] & 16  # STALE: the velocity estimate restarted
    assert got["malformed"]["kind"] == "notice" and got["malformed"]["error"] == 1
    st = got["streamer"]
    assert st["finished"] and st["valid_before_nan"] and st["force_before_nan_N"] > 0.1
    assert st["error_after_nan"] == 7 and st["bad_value_replies"] > 50
    assert st["force_after_nan_N"] == 0 and st["vibration_after_nan_N"] == 0
    assert not st["valid_after_nan"] and not st["valid_after_silence"]
    stall = got["stall"]  # a 25 ms stall from tick 100: ~24 ticks skipped, then 1 ms apart
    assert 15 <= stall["skipped"] <= 200 and stall["sent"] + stall["skipped"] == 300, stall
    assert stall["first_tick_after"] >= stall["stalled_at"] + 15, stall
    # No burst: the next tick sent after the jump waits for its own scheduled time (the gap to
    # it is shorter than a period when the jumped-to tick itself left late; on a loaded
    # machine the tick right after the jump may be skipped as well).
    assert stall["next_after"] > stall["first_tick_after"], stall
    assert stall["gap_after_us"] > 0 and stall["next_early_us"] <= 0, stall
    assert stall["replies"] >= 0.9 * stall["sent"], stall
    wk = got["streamer_wrong_key"]
    assert wk["replies"] == 0 and wk["bad_tag_notices"] > 0 and not wk["valid"]
    assert got["rest_404"]["status"] == 404 and got["rest_404"]["detail"]
    assert "rest_error" not in got, got["rest_error"]
    assert got["us_after_patch"] == 1610.2 and got["frame_param"] == "si_mm"
    assert got["rest_422"]["status"] == 422 and got["rest_422"]["detail"]
    assert got["restart_stream"] and got["view_id"] == got["session"]
    assert got["view_state"] == "ready" and got["deleted"]


def test_cpp_handshake(cpp_bins, live_server):
    """Protocol v2's streams (tests/handshake.cpp): a hello opens a stream; a restarted
    client (new object, same key, seq from 1 again, right after the old stream was used) is
    answered from its first hello and its first POSE on, with no idle wait; captured
    datagrams of an earlier stream get WRONG_STREAM, never a REPLY, and a replayed hello
    leaves the live stream alone; the refused old client says hello again; a REST
    restart-stream is recovered from by the Streamer itself."""
    got = run_json([str(cpp_bins["handshake"]), *_server_args(live_server)], timeout_s=120)
    print(json.dumps(got))
    assert "error" not in got and "streamer_error" not in got, got
    new_stream, wrong_stream, stale = 11, 12, 16
    hello = got["a_hello"]
    assert hello["kind"] == "notice" and hello["error"] == new_stream and hello["verified"]
    assert hello["stream_changed"] and hello["stream"] == got["a_stream"] != 0
    assert got["a_first"]["kind"] == "reply" and got["a_first"]["error"] == 0
    assert got["a_first"]["status"] & stale
    assert got["a_replies"] == 20
    assert got["captured_stream"] == got["a_stream"]
    # The restarted client: its first hello (seq 1) answered with a stream of its own, its
    # first POSE (seq 2, older than the old stream's) ticked.
    b_hello, b_first = got["b_hello"], got["b_first"]
    assert b_hello["kind"] == "notice" and b_hello["error"] == new_stream, b_hello
    assert b_hello["seq"] == 1 and b_hello["verified"] and b_hello["stream_changed"]
    assert got["b_stream"] == b_hello["stream"] not in (0, got["a_stream"])
    assert got["b_hellos_sent"] == 1
    assert b_first["kind"] == "reply" and b_first["error"] == 0 and b_first["seq"] == 2
    assert b_first["seq"] < got["captured_seq"] and b_first["status"] & stale
    assert got["b_replies"] == 20
    # Replays: no REPLY; the old stream's POSE is refused with a tagged WRONG_STREAM naming
    # that stream; the hello gets an offer (tagged NEW_STREAM) and nothing else.
    rp = got["replayed_pose"]
    assert rp["replies"] == 0 and rp["notices"] == 1 and rp["verified"] == 1, rp
    assert set(rp["errors"]) == {wrong_stream} and set(rp["streams"]) == {got["a_stream"]}, rp
    rh = got["replayed_hello"]
    assert rh["replies"] == 0 and rh["notices"] == 1 and rh["errors"] == [new_stream], rh
    assert got["a_stream"] not in rh["streams"] and got["b_stream"] not in rh["streams"], rh
    b_after = got["b_after_replays"]
    assert b_after["kind"] == "reply" and b_after["error"] == 0, b_after
    assert got["b_stream_after_replays"] == got["b_stream"]
    # The old client: refused on its closed stream, then a stream of its own again.
    refused = got["a_refused"]
    assert refused["kind"] == "notice" and refused["error"] == wrong_stream, refused
    assert refused["stream"] == got["a_stream"] and refused["stream_changed"]
    assert got["a_stream_after_refusal"] == 0 and got["a_reopened"]
    assert got["a_new_stream"] not in (0, got["a_stream"], got["b_stream"])
    assert got["a_again"]["kind"] == "reply" and got["a_again"]["error"] == 0
    # Streamers (the second one a restart of the first): hellos until the stream, and the
    # first tick sent on it is the first one answered.
    for run in ("streamer_0", "streamer_1"):
        st = got[run]
        assert st["finished"] and st["streams"] == 1 and st["stream"] != 0, st
        assert st["first_stream_tick"] >= 1 and 1 <= st["hellos"] <= st["first_stream_tick"], st
        assert st["first_reply_tick"] == st["first_stream_tick"], st
    assert got["streamer_0"]["stream"] != got["streamer_1"]["stream"]
    rr = got["rest_restart"]
    assert rr["streaming"] and rr["recovered"] and not rr["failed"], rr
    assert rr["stream_before"] != 0 and rr["stream_after"] not in (0, rr["stream_before"]), rr
    assert rr["streams"] == 2 and rr["streams_lost"] == 1 and rr["wrong_stream_notices"] >= 1
    assert rr["replies_after"] >= 50, rr


def test_cpp_robustness(cpp_bins, live_server):
    """The SDK at its edges (tests/robustness.cpp): exceptions end the stream, not the
    process; restart_stream() in publish mode is answered; rtt_us is the send-to-reply time;
    a stale coupled state clears the proxy; MeshSync backs off; HTTP trailers, a bad
    Content-Length and an unanswered connect."""
    got = run_json([str(cpp_bins["robustness"]), *_server_args(live_server)], timeout_s=120)
    print(json.dumps(got))
    assert "error" not in got, got
    for case, why in (("source_throws", "physics blew up"), ("callback_throws", "callback bug")):
        r = got[case]
        assert r["finished"] and r["failed"] and r["failure"] == why and not r["valid"], r
    assert got["source_throws"]["replies"] > 0 and not got["source_throws"]["running"]
    pub = got["publish"]
    # The pose was stamped 30 ms before it was published and then held for 300 ms: SPEC
    # 5.5's sample-based rtt holds that age, the send-based one only the loopback trip.
    assert pub["valid"] and 0 <= pub["rtt_us"] < 20_000 and pub["sample_rtt_us"] >= 300_000, pub
    # restart_stream() says hello again: a new stream, answered although the held pose's
    # t_client_us repeats the old stream's.
    assert pub["replies_after_restart"] > 100 and pub["valid_after_restart"], pub
    assert pub["stream_after_restart"] not in (0, pub["stream_before_restart"]), pub
    c = got["coupled"]
    assert c["valid"] and c["stiffness"] > 0 and c["proxy_norm"] > 1.0, c
    assert not c["stale_valid"] and c["stale_proxy_norm"] == 0 and c["stale_stiffness"] == 0
    m = got["mesh_poll"]
    # Back-off 40, 80, ... 640, 1000 ms: at most 6 attempts in 2 s (the old loop made ~96).
    assert 1 <= m["never_reached_updates_in_2s"] <= 8 and m["fruitless"] >= 1, m
    assert m["idle_updates_in_2s"] == 0 and m["errors"] == 0, m
    assert m["request_stop_ms"] < 50, m
    assert got["localhost"]["ipv4"] and got["localhost"]["replies"] > 100
    assert got.get("chunked_trailer_value") == 42, got
    assert got["bad_content_length"] == "RestError"
    uc = got["unanswered_connect"]
    assert 400 <= uc["ms"] < 1500 and "connect" in uc["error"], uc


def test_cpp_mesh(cpp_bins, live_server, rest, tmp_path):
    """Mesh chunks in an `unreal` session (winding cw): a full first copy, updates while the
    groove is cut, caught up with the last REPLY's bone_version; the union of the chunks is
    the server's export (closed, same volume)."""
    obj = tmp_path / "cpp_mesh.obj"
    got = run_json([str(cpp_bins["mesh"]), *_server_args(live_server), "--obj", str(obj),
                    "--frame", "unreal", "--winding", "cw"], timeout_s=240)
    print(json.dumps(got))
    try:
        assert "error" not in got, got
        assert got["fuzz_failure"] == "" and got["fuzz_rejected"] > 0
        assert got["first_page"]["flags"] & 2  # FULL without `since`
        assert got["first_page"]["flags"] & 4 and got["first_page"]["flags"] & 8  # CW, frame
        assert got["stream_finished"] and got["replies"] >= TICKS - 20
        assert got["initial_chunks"] > 0 and got["full_resets"] == 1
        assert got["last_bone_version"] > 0
        assert got["caught_up"] and got["have"] == got["last_bone_version"]
        assert got["updates_during_cut"] > 0 and got["chunks_replaced"] > 0
        assert got["sync_errors"] == 0, got["last_error"]
        result = check_mesh_obj(obj, rest, got["session"], "unreal", "cw")
        print(result)
        assert result["triangles"] == got["triangles"]
    finally:
        rest.delete_session(got["session"])


def test_cpp_quickstart(live_server, tmp_path):
    """The README's quickstart (examples/quickstart.cpp): the connection file, a session
    created over REST, poses published from a 90 Hz loop (the Streamer sends at 1 kHz),
    forces while cutting, the mesh caught up."""
    if shutil.which("g++") is None:
        pytest.skip("g++ not installed (apt-get install g++)")
    exe = tmp_path / "quickstart"
    p = subprocess.run(["g++", *FLAGS, "-I", str(SDK / "include"),
                        str(SDK / "examples" / "quickstart.cpp"), "-o", str(exe)],
                       capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
    assert p.returncode == 0, p.stderr
    got = run_json([str(exe), "--connection", live_server["connection_file"], "--create", "1",
                    "--seconds", "2.5"], timeout_s=120)
    print(json.dumps(got))
    assert got["sent"] > 1000 and got["replies"] > 0.9 * got["sent"]
    assert got["max_force_N"] > 0.5
    assert got["bone_version"] > 0 and got["mesh_caught_up"]
    assert got["winding"] == "ccw"  # si_mm (MESH.md 5)
    assert got["chunks"] > 0 and got["triangles"] > 0
