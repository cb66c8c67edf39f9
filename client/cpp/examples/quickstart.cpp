// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The shape of an engine integration, without an engine: a 90 Hz "frame loop" publishes the
// tool's pose to the Streamer (which sends at 1 kHz on its own thread), reads the newest
// force each frame, and keeps the carved bone's mesh chunks current with MeshSync.
//
//   burrforce serve --demo           # prints the endpoint; writes the connection file
//   ./quickstart                     # uses the connection file's session
//   ./quickstart --create 1          # creates (and deletes) its own session over REST
//   options: --connection FILE  --seconds S  --frame NAME (with --create)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <map>
#include <string>
#include <thread>

#include "burrforce/burrforce.hpp"

using namespace burrforce;

int main(int argc, char** argv) {
  std::map<std::string, std::string> opt;
  for (int i = 1; i + 1 < argc; i += 2) opt[std::string(argv[i]).substr(2)] = argv[i + 1];
  try {
    Connection conn = Connection::read(opt.count("connection") ? opt["connection"]
                                                               : Connection::default_path());
    const double seconds = opt.count("seconds") ? std::stod(opt["seconds"]) : 5.0;
    Rest rest(conn.http_url, conn.token);

    // 1. A session: the server's own (connection file) or a fresh one.
    SessionInfo s;
    bool created = opt.count("create") && opt["create"] != "0";
    if (created) {
      s = rest.create_session("phantom:workpiece", opt.count("frame") ? opt["frame"] : "si_mm");
    } else {
      s.id = conn.session;
      s.key = conn.key;
      s.udp_host = conn.host;
      s.udp_port = conn.udp_port;
      s.frame = conn.frame;
    }
    const Frame* frame = frames::by_name(s.frame);
    if (!frame) throw std::runtime_error("unknown frame " + s.frame);
    FrameTransform tf(*frame);

    // 2. The haptic stream (its own thread, 1 kHz).
    StreamerConfig cfg;
    cfg.host = s.udp_host;
    cfg.port = s.udp_port;
    cfg.session = s.id;
    cfg.key = s.key;
    Streamer streamer(cfg);
    streamer.start();

    // 3. The bone mesh (its own worker; polls when the bone_version moves).
    MeshSyncConfig mc;
    mc.session = s.id;
    mc.winding = mesh_winding(*frame);  // the engine's front faces (MESH.md 5)
    MeshSync mesh(rest, mc, [&] { return streamer.bone_version(); });
    mesh.start();

    // 4. The frame loop: the tool dips into the workpiece and moves along +x (server mm,
    //    converted to the engine frame as an engine's transforms would be).
    const Quat tilt = tf.orientation_for_axis({-0.5, 0.0, std::sqrt(0.75)}, frame->tool_axis);
    const auto t0 = std::chrono::steady_clock::now();
    double max_force_N = 0;
    int frames_run = 0;
    for (;;) {
      double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      if (t > seconds) break;
      double depth = std::min(t, 1.0);           // 1 s plunge of 1 mm
      double x = 3.0 + 5.0 * std::max(0.0, t - 1.0);  // then 5 mm/s along +x
      ToolPose pose;
      pose.position = tf.point_from_server({x, 0.0, 2.5 - depth});
      pose.orientation = tilt;
      pose.rpm = 60000.0;
      pose.spindle_on = true;
      streamer.publish(pose);  // stamped now: when this frame sampled the tool

      HapticState h = streamer.state();  // what to render this frame
      double f = std::sqrt(h.force.x * h.force.x + h.force.y * h.force.y + h.force.z * h.force.z);
      max_force_N = std::max(max_force_N, f);
      if (frames_run % 45 == 0)
        std::printf("t=%.2fs force=(%.3f %.3f %.3f) N %s vib=%.2f N @ %.0f Hz rtt=%lld us\n", t,
                    h.force.x, h.force.y, h.force.z,
                    (h.status & STATUS_CUTTING) ? "cutting" : "       ",
                    h.vibration_amplitude_N, h.vibration_frequency_hz,
                    static_cast<long long>(h.rtt_us));
      ++frames_run;
      std::this_thread::sleep_for(std::chrono::microseconds(11111));  // ~90 Hz
    }
    streamer.stop();
    uint64_t last = streamer.bone_version();
    bool caught_up = mesh.wait_for_version(last, 10000);
    mesh.stop();
    size_t chunks = 0, triangles = 0;
    mesh.read([&](const mesh::ChunkedMesh& m) {
      chunks = m.size();
      triangles = m.triangle_count();
    });
    const Counters& c = streamer.counters();
    if (created) rest.delete_session(s.id);
    std::printf("{\"session\": %u, \"frames\": %d, \"sent\": %llu, \"replies\": %llu, "
                "\"max_force_N\": %.6f, \"bone_version\": %llu, \"mesh_caught_up\": %s, "
                "\"chunks\": %zu, \"triangles\": %zu, \"winding\": \"%s\"}\n",
                s.id, frames_run, static_cast<unsigned long long>(c.sent.load()),
                static_cast<unsigned long long>(c.replies.load()), max_force_N,
                static_cast<unsigned long long>(last), caught_up ? "true" : "false", chunks,
                triangles, mc.winding.c_str());
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "quickstart: " << e.what() << "\n";
    return 1;
  }
}
