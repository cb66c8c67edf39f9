// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Cuts the SDK test groove (tests/sdk/conftest.py) through the Streamer at 1 kHz in a fresh
// session of the given frame created with the REST helper: the same poses on the same
// schedule as the Python reference, converted to the engine frame. Prints one JSON line
// with the steady forces, losses and round trips.
// Usage: groove --url HTTP_URL --token TOKEN [--frame si_mm] [--bone phantom:workpiece]
#include <cmath>
#include <cstdint>
#include <iostream>
#include <sstream>
#include <vector>

#include "burrforce/burrforce.hpp"
#include "groove_path.hpp"
#include "test_util.hpp"

using namespace burrforce;

using namespace groove;

namespace {
struct TickResult {
  bool got = false;
  uint32_t status = 0;
  uint16_t error = 0;
  double resistive[3];
  double force[3];
  double removed_mm3;
  double rtt_us;
};

std::string vec_json(const Vec3& v) {
  return "[" + json::number(v.x) + ", " + json::number(v.y) + ", " + json::number(v.z) + "]";
}
}  // namespace

int main(int argc, char** argv) {
  auto o = testutil::options(argc, argv);
  const std::string frame_name = o.count("frame") ? o["frame"] : "si_mm";
  const std::string bone = o.count("bone") ? o["bone"] : "phantom:workpiece";
  const Frame* frame = frames::by_name(frame_name);
  if (!frame) {
    std::cerr << "unknown frame " << frame_name << "\n";
    return 2;
  }
  Rest rest(testutil::need(o, "url"), testutil::need(o, "token"));
  SessionInfo s = rest.create_session(bone, frame_name);
  if (s.frame != frame_name) {
    std::cerr << "session frame " << s.frame << " != " << frame_name << "\n";
    return 1;
  }
  FrameTransform tf(*frame);
  const Quat q = tf.orientation_for_axis(groove::axis(), frame->tool_axis);

  StreamerConfig cfg;
  cfg.host = s.udp_host;
  cfg.port = s.udp_port;
  cfg.session = s.id;
  cfg.key = s.key;
  cfg.max_ticks = kTicks;
  // Like the Python reference, every sample of the groove is sent even after a hiccup of
  // this (shared, loaded) machine; a live engine keeps the default of skipping.
  cfg.max_catch_up_ticks = 50;
  Streamer streamer(cfg);
  // Preallocated: the callbacks run on the stream thread and must not allocate.
  std::vector<TickResult> results(kTicks);
  streamer.set_pose_source([&](uint64_t tick, int64_t, ToolPose& p) {
    p.position = tf.point_from_server(position_mm(tick));
    p.orientation = q;
    p.rpm = kRpm;
    p.spindle_on = true;
    return true;
  });
  streamer.on_reply([&](const Event& ev) {
    if (ev.tick >= kTicks) return;
    TickResult& r = results[ev.tick];
    r.got = true;
    r.status = ev.reply.status;
    r.error = ev.reply.error;
    for (int k = 0; k < 3; ++k) {
      r.resistive[k] = ev.reply.resistive[k];
      r.force[k] = ev.reply.force[k];
    }
    r.removed_mm3 = ev.reply.removed_mm3;
    r.rtt_us = static_cast<double>(ev.round_trip.rtt_us);
  });
  streamer.start();
  bool finished = streamer.wait_finished(60000000);
  streamer.stop();
  HapticState last = streamer.state();
  rest.delete_session(s.id);
  if (!finished) {
    std::cerr << "the stream did not finish in time\n";
    return 1;
  }

  size_t replies = 0, steady = 0;
  double mean_res[3] = {0, 0, 0}, force_norm = 0, removed = 0;
  Vec3 mean_force;
  std::vector<double> rtts;
  for (uint64_t i = 0; i < kTicks; ++i) {
    const TickResult& r = results[i];
    if (!r.got) continue;
    ++replies;
    removed += r.removed_mm3;
    rtts.push_back(r.rtt_us);
    if (i >= kSteadyFrom && r.error == 0 && (r.status & STATUS_CUTTING)) {
      ++steady;
      for (int k = 0; k < 3; ++k) mean_res[k] += r.resistive[k];
      force_norm += std::sqrt(r.force[0] * r.force[0] + r.force[1] * r.force[1] +
                              r.force[2] * r.force[2]);
      mean_force.x += r.force[0];
      mean_force.y += r.force[1];
      mean_force.z += r.force[2];
    }
  }
  if (steady) {
    for (double& m : mean_res) m /= static_cast<double>(steady);
    force_norm /= static_cast<double>(steady);
    double n = static_cast<double>(steady);
    mean_force = {mean_force.x / n, mean_force.y / n, mean_force.z / n};
  }
  const Counters& c = streamer.counters();
  Vec3 force_server = tf.direction_to_server(mean_force);
  std::ostringstream out;
  out << "{\"ticks\": " << kTicks << ", \"sent\": " << c.sent.load()
      << ", \"replies\": " << replies << ", \"lost\": " << kTicks - replies
      << ", \"steady_ticks\": " << steady
      << ", \"steady_feed_N\": " << json::number(mean_res[0])
      << ", \"steady_lateral_N\": " << json::number(mean_res[1])
      << ", \"steady_normal_N\": " << json::number(mean_res[2])
      << ", \"steady_force_N\": " << json::number(force_norm)
      << ", \"steady_force_engine_N\": " << vec_json(mean_force)
      << ", \"steady_force_server_N\": " << vec_json(force_server)
      << ", \"removed_mm3\": " << json::number(removed)
      << ", \"rtt_p50_us\": " << json::number(testutil::percentile(rtts, 50))
      << ", \"rtt_p99_us\": " << json::number(testutil::percentile(rtts, 99))
      << ", \"session\": " << s.id << ", \"frame\": " << json::quote(frame_name)
      << ", \"orientation\": [" << json::number(q.x) << ", " << json::number(q.y) << ", "
      << json::number(q.z) << ", " << json::number(q.w) << "]"
      << ", \"skipped_ticks\": " << c.skipped_ticks.load()
      << ", \"late_ticks\": " << c.late_ticks.load()
      << ", \"send_failed\": " << c.send_failed.load()
      << ", \"notices\": " << c.notices.load();
  for (int d = 1; d < static_cast<int>(Drop::Count); ++d)
    out << ", \"dropped_" << drop_name(static_cast<Drop>(d)) << "\": " << c.dropped[d].load();
  out << ", \"last_bone_version\": " << last.bone_version
      << ", \"removed_total_mm3\": " << json::number(last.removed_total_mm3) << "}";
  std::cout << out.str() << std::endl;
  return 0;
}
