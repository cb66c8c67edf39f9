// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The mesh chunks against a live server: a session in the engine's frame (REST helper),
// MeshSync started (a first full copy), the groove cut through the Streamer while MeshSync
// follows the REPLYs' bone_version, then wait until the copy has caught up with the last
// REPLY's version and dump the union of chunks as OBJ. Also: the parser refuses truncated,
// mis-versioned and corrupted messages without crashing.
// Usage: mesh --url HTTP_URL --token TOKEN --obj OUT.obj [--frame unreal] [--winding cw]
// Leaves the session alive (the caller compares it with the server's export, then deletes
// it); prints one JSON line.
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>

#include "burrforce/burrforce.hpp"
#include "groove_path.hpp"
#include "test_util.hpp"

using namespace burrforce;

namespace {

/// Every truncation and a few thousand random corruptions of a real message: parse must
/// either succeed or throw FormatError, never crash (run under ASan to see overreads).
std::string fuzz_parser(const std::string& bytes, size_t& cases, size_t& rejected) {
  auto attempt = [&](const std::string& b) {
    ++cases;
    try {
      mesh::parse(b);
    } catch (const mesh::FormatError&) {
      ++rejected;
    }
  };
  for (size_t n = 0; n < bytes.size(); n += 1 + n / 64) {
    ++cases;
    try {
      mesh::parse(bytes.substr(0, n));
      return "a truncated message parsed";
    } catch (const mesh::FormatError&) {
      ++rejected;
    }
  }
  std::string bad = bytes;
  bad[0] = 'X';
  try {
    mesh::parse(bad);
    return "bad magic accepted";
  } catch (const mesh::FormatError&) {
  }
  bad = bytes;
  bad[4] = 2;
  try {
    mesh::parse(bad);
    return "format version 2 accepted";
  } catch (const mesh::FormatError&) {
  }
  std::mt19937 rng(7);
  for (int k = 0; k < 3000; ++k) {
    std::string b = bytes;
    // Corrupt the header and the first chunk's counts most often: where lengths live.
    size_t span = std::min<size_t>(b.size(), k % 2 ? 80 : b.size());
    for (int e = 0; e < 3; ++e) b[rng() % span] = static_cast<char>(rng());
    attempt(b);
  }
  return "";
}

}  // namespace

int main(int argc, char** argv) {
  auto o = testutil::options(argc, argv);
  const std::string frame_name = o.count("frame") ? o["frame"] : "unreal";
  const std::string winding = o.count("winding") ? o["winding"] : "cw";
  const std::string obj_path = testutil::need(o, "obj");
  const Frame* frame = frames::by_name(frame_name);
  if (!frame) return 2;
  Rest rest(testutil::need(o, "url"), testutil::need(o, "token"));
  SessionInfo s = rest.create_session("phantom:workpiece", frame_name);
  std::ostringstream out;
  out << "{\"session\": " << s.id << ", \"frame\": " << json::quote(frame_name)
      << ", \"winding\": " << json::quote(winding);
  try {
    // A small page of the real thing for the parser's robustness check.
    std::string page = rest.get_bytes("/sessions/" + std::to_string(s.id) +
                                      "/mesh?max_bytes=65536&winding=" + winding);
    mesh::Message first = mesh::parse(page);
    size_t cases = 0, rejected = 0;
    std::string fuzz_failure = fuzz_parser(page, cases, rejected);
    out << ", \"first_page\": {\"bytes\": " << page.size() << ", \"chunks\": "
        << first.chunks.size() << ", \"flags\": " << first.flags
        << ", \"chunk_cells\": " << first.chunk_cells << "}, \"fuzz_cases\": " << cases
        << ", \"fuzz_rejected\": " << rejected
        << ", \"fuzz_failure\": " << json::quote(fuzz_failure);

    FrameTransform tf(*frame);
    const Quat q = tf.orientation_for_axis(groove::axis(), frame->tool_axis);
    StreamerConfig cfg;
    cfg.host = s.udp_host;
    cfg.port = s.udp_port;
    cfg.session = s.id;
    cfg.key = s.key;
    cfg.max_ticks = groove::kTicks;
    cfg.max_catch_up_ticks = 50;
    Streamer streamer(cfg);
    std::atomic<uint64_t> max_version{0};
    streamer.set_pose_source([&](uint64_t tick, int64_t, ToolPose& p) {
      p.position = tf.point_from_server(groove::position_mm(tick));
      p.orientation = q;
      p.rpm = groove::kRpm;
      p.spindle_on = true;
      return true;
    });
    streamer.on_reply([&](const Event& ev) {
      if (ev.reply.bone_version > max_version.load()) max_version.store(ev.reply.bone_version);
    });

    MeshSyncConfig mc;
    mc.session = s.id;
    mc.winding = winding;
    MeshSync sync(rest, mc, [&] { return streamer.bone_version(); });
    sync.start();
    if (!sync.wait_for_version(0, 60000)) throw std::runtime_error("no first mesh in 60 s");
    size_t initial_chunks = 0, initial_tris = 0;
    uint64_t initial_have = 0;
    sync.read([&](const mesh::ChunkedMesh& m) {
      initial_chunks = m.size();
      initial_tris = m.triangle_count();
      initial_have = m.have();
    });
    uint64_t updates_before = sync.updates();

    streamer.start();
    bool finished = streamer.wait_finished(60000000);
    streamer.stop();
    const uint64_t last_version = max_version.load();
    bool caught_up = sync.wait_for_version(last_version, 30000);
    sync.stop();

    std::string obj;
    size_t chunks = 0, tris = 0;
    uint64_t have = 0, added = 0, replaced = 0, removed = 0, fulls = 0;
    sync.read([&](const mesh::ChunkedMesh& m) {
      obj = m.to_obj();
      chunks = m.size();
      tris = m.triangle_count();
      have = m.have();
      added = m.chunks_added;
      replaced = m.chunks_replaced;
      removed = m.chunks_removed;
      fulls = m.full_resets;
    });
    std::ofstream(obj_path, std::ios::binary) << obj;
    out << ", \"stream_finished\": " << (finished ? "true" : "false")
        << ", \"replies\": " << streamer.counters().replies.load()
        << ", \"sent\": " << streamer.counters().sent.load()
        << ", \"skipped_ticks\": " << streamer.counters().skipped_ticks.load()
        << ", \"hellos\": " << streamer.counters().hellos.load()
        << ", \"streams\": " << streamer.counters().streams.load()
        << ", \"streams_lost\": " << streamer.counters().streams_lost.load()
        << ", \"notices\": " << streamer.counters().notices.load()
        << ", \"initial_have\": " << initial_have << ", \"initial_chunks\": " << initial_chunks
        << ", \"initial_triangles\": " << initial_tris
        << ", \"last_bone_version\": " << last_version
        << ", \"caught_up\": " << (caught_up ? "true" : "false") << ", \"have\": " << have
        << ", \"chunks\": " << chunks << ", \"triangles\": " << tris
        << ", \"chunks_added\": " << added << ", \"chunks_replaced\": " << replaced
        << ", \"chunks_removed\": " << removed << ", \"full_resets\": " << fulls
        << ", \"updates\": " << sync.updates() << ", \"updates_during_cut\": "
        << sync.updates() - updates_before << ", \"pages\": " << sync.pages()
        << ", \"bytes\": " << sync.bytes() << ", \"sync_errors\": " << sync.errors()
        << ", \"last_error\": " << json::quote(sync.last_error())
        << ", \"obj\": " << json::quote(obj_path);
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    out << ", \"error\": " << json::quote(e.what());
  }
  out << "}";
  std::cout << out.str() << std::endl;
  return 0;
}
