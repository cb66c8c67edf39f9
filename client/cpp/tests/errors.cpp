// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// SPEC 3.4's error answers as the SDK sees them, against a live server: UNKNOWN_SESSION and
// BAD_TAG notices (to a hello: the session and the tag are checked before the stream), a
// BAD_VALUE error REPLY (seq consumed, force zero), silence for a duplicate datagram, a
// MALFORMED notice for v1's element count under version 2; and the Streamer's
// rendering rules: zero force after an error REPLY and once REPLYs stop (SPEC 7.6).
// Usage: errors --url HTTP_URL --token TOKEN. Prints one JSON line.
#include <cmath>
#include <iostream>
#include <limits>
#include <sstream>
#include <thread>

#include "burrforce/burrforce.hpp"
#include "test_util.hpp"

using namespace burrforce;

namespace {
constexpr int64_t kWaitUs = 1000000;
constexpr int64_t kSilenceUs = 300000;

Pose above_bone() {
  Pose p;
  p.position[0] = 3.0;
  p.position[2] = 5.0;  // mm above the workpiece: no contact
  p.rpm = 60000.0;
  p.spindle_on = true;
  return p;
}

std::string event_json(const Event& ev) {
  std::ostringstream o;
  if (ev.kind == Event::Kind::Notice)
    o << "{\"kind\": \"notice\", \"error\": " << ev.notice.error << ", \"session\": "
      << ev.notice.session << ", \"seq\": " << ev.notice.seq << "}";
  else if (ev.kind == Event::Kind::Reply)
    o << "{\"kind\": \"reply\", \"error\": " << ev.reply.error << ", \"status\": "
      << ev.reply.status << ", \"seq\": " << ev.reply.seq << ", \"force_zero\": "
      << (ev.reply.force[0] == 0 && ev.reply.force[1] == 0 && ev.reply.force[2] == 0 ? "true"
                                                                                    : "false")
      << "}";
  else
    o << "{\"kind\": \"none\"}";
  return o.str();
}
}  // namespace

int main(int argc, char** argv) {
  auto o = testutil::options(argc, argv);
  Rest rest(testutil::need(o, "url"), testutil::need(o, "token"));
  SessionInfo s = rest.create_session("phantom:workpiece", "si_mm");
  std::ostringstream out;
  out << "{\"session\": " << s.id;
  try {
    {  // UNKNOWN_SESSION: a session id nobody created.
      Client c(s.udp_host, s.udp_port, s.id + 100000u, s.key);
      Event ev = c.exchange(above_bone(), kWaitUs);
      out << ", \"unknown_session\": " << event_json(ev);
    }
    {  // BAD_TAG: the right session, another key.
      std::vector<uint8_t> wrong(32, 0x5a);
      Client c(s.udp_host, s.udp_port, s.id, wrong);
      Event ev = c.exchange(above_bone(), kWaitUs);
      out << ", \"bad_tag\": " << event_json(ev);
    }
    {
      Client c(s.udp_host, s.udp_port, s.id, s.key, 500);
      out << ", \"opened\": " << (c.open_stream(above_bone(), kWaitUs) ? "true" : "false");
      Event first = c.exchange(above_bone(), kWaitUs);
      out << ", \"first\": " << event_json(first);
      // DUPLICATE: the same bytes again are never answered.
      c.send_raw(c.last_datagram(), c.last_size());
      Event dup = c.receive(kSilenceUs);
      out << ", \"duplicate\": " << event_json(dup);
      // BAD_VALUE: a NaN position. Its seq is consumed: resending it is a duplicate.
      Pose nan = above_bone();
      nan.position[1] = std::numeric_limits<double>::quiet_NaN();
      out << ", \"nan_valid_locally\": " << (pose_values_valid(nan) ? "true" : "false");
      Event bad = c.exchange(nan, kWaitUs);
      out << ", \"bad_value\": " << event_json(bad);
      c.send_raw(c.last_datagram(), c.last_size());
      Event bad_again = c.receive(kSilenceUs);
      out << ", \"bad_value_resent\": " << event_json(bad_again);
      // The next POSE is processed again, its velocity estimate restarted (STALE).
      Event after = c.exchange(above_bone(), kWaitUs);
      out << ", \"after_bad_value\": " << event_json(after);
      // MALFORMED: a valid v2 header on v1's layout (12 elements, no stream).
      uint8_t buf[256];
      msgpack::Writer w(buf, sizeof buf);
      w.array(12);
      w.uint(kVersion);
      w.uint(kTypePose);
      w.uint(s.id);
      w.uint(c.rules().next_seq() + 5);
      w.uint(static_cast<uint64_t>(now_us()));
      double pos[3] = {3, 0, 5}, q[4] = {0, 0, 0, 1};
      w.vec(pos, 3);
      w.vec(q, 4);
      w.f64(60000.0);
      w.boolean(true);
      w.nil();
      w.uint(0);
      w.nil();
      c.send_raw(buf, w.size());
      Event malformed = c.receive(kWaitUs);
      out << ", \"malformed\": " << event_json(malformed);
      out << ", \"client_counters\": {\"replies\": " << c.counters().replies.load()
          << ", \"notices\": " << c.counters().notices.load() << "}";
    }
    {  // The Streamer: an error REPLY renders nothing; silence renders nothing after 50 ms.
      StreamerConfig cfg;
      cfg.host = s.udp_host;
      cfg.port = s.udp_port;
      cfg.session = s.id;
      cfg.key = s.key;
      cfg.first_seq = 1000;
      cfg.max_ticks = 300;
      cfg.max_catch_up_ticks = 50;
      Streamer st(cfg);
      HapticState before_nan;
      bool captured = false;
      st.set_pose_source([](uint64_t tick, int64_t, ToolPose& p) {
        // In bone (cutting) for 200 ticks, then a NaN from a physics blow-up.
        p.position = {3.0 + 0.005 * static_cast<double>(tick), 0.0, 1.5};
        if (tick >= 200) p.position.y = std::numeric_limits<double>::quiet_NaN();
        p.rpm = 60000.0;
        p.spindle_on = true;
        return true;
      });
      st.on_reply([&](const Event& ev) {
        (void)ev;
        if (!captured && ev.tick >= 150 && ev.tick < 200 && ev.reply.error == 0) {
          before_nan = st.state();
          captured = true;
        }
      });
      st.start();
      bool finished = st.wait_finished(10000000);
      HapticState after_nan = st.state();
      st.stop();
      std::this_thread::sleep_for(std::chrono::milliseconds(80));
      HapticState later = st.state();
      const Counters& c = st.counters();
      auto fmag = [](const HapticState& h) {
        return std::sqrt(h.force.x * h.force.x + h.force.y * h.force.y + h.force.z * h.force.z);
      };
      out << ", \"streamer\": {\"finished\": " << (finished ? "true" : "false")
          << ", \"force_before_nan_N\": " << json::number(fmag(before_nan))
          << ", \"valid_before_nan\": " << (before_nan.valid ? "true" : "false")
          << ", \"status_before_nan\": " << before_nan.status
          << ", \"error_after_nan\": " << after_nan.error
          << ", \"force_after_nan_N\": " << json::number(fmag(after_nan))
          << ", \"vibration_after_nan_N\": " << json::number(after_nan.vibration_amplitude_N)
          << ", \"valid_after_nan\": " << (after_nan.valid ? "true" : "false")
          << ", \"bad_value_replies\": " << c.by_error[BAD_VALUE].load()
          << ", \"valid_after_silence\": " << (later.valid ? "true" : "false")
          << ", \"replies\": " << c.replies.load() << "}";
    }
    {  // A stall of the stream thread (25 ms at tick 100): the missed ticks are skipped and
       // counted, and the stream resumes on its schedule, not with a burst.
      StreamerConfig cfg;
      cfg.host = s.udp_host;
      cfg.port = s.udp_port;
      cfg.session = s.id;
      cfg.key = s.key;
      cfg.first_seq = 5000;
      cfg.max_ticks = 300;
      Streamer st(cfg);
      std::vector<int64_t> called_us(300, -1);
      // The first tick sent from 100 on stalls: a busy machine may itself skip tick 100.
      uint64_t stalled_at = 0;
      std::vector<int64_t> due_us(300, -1);
      st.set_pose_source([&](uint64_t tick, int64_t due, ToolPose& p) {
        called_us[tick] = now_us();
        due_us[tick] = due;
        if (tick >= 100 && !stalled_at) {
          stalled_at = tick;
          std::this_thread::sleep_for(std::chrono::milliseconds(25));
        }
        p.position = {3.0, 0.0, 5.0};
        p.rpm = 60000.0;
        p.spindle_on = true;
        return true;
      });
      st.start();
      st.wait_finished(10000000);
      st.stop();
      uint64_t first_after = 0;
      for (uint64_t k = stalled_at + 1; k < 300 && !first_after; ++k)
        if (called_us[k] >= 0) first_after = k;
      // The next tick called after it (a loaded machine may skip that one too).
      uint64_t next_after = 0;
      for (uint64_t k = first_after + 1; first_after && k < 300 && !next_after; ++k)
        if (called_us[k] >= 0) next_after = k;
      int64_t gap_us = next_after ? called_us[next_after] - called_us[first_after] : -1;
      const Counters& c = st.counters();
      out << ", \"stall\": {\"sent\": " << c.sent.load()
          << ", \"skipped\": " << c.skipped_ticks.load()
          << ", \"stalled_at\": " << stalled_at << ", \"first_tick_after\": " << first_after
          << ", \"next_after\": " << next_after << ", \"gap_after_us\": " << gap_us
          << ", \"next_early_us\": "
          << (next_after ? due_us[next_after] - called_us[next_after] : -1)
          << ", \"replies\": " << c.replies.load() << "}";
    }
    {  // The Streamer with a wrong key: BAD_TAG notices counted, never a force.
      StreamerConfig cfg;
      cfg.host = s.udp_host;
      cfg.port = s.udp_port;
      cfg.session = s.id;
      cfg.key = std::vector<uint8_t>(32, 0x33);
      cfg.max_ticks = 20;
      cfg.rate_hz = 200;
      Streamer st(cfg);
      st.publish(ToolPose{{3.0, 0.0, 5.0}, {}, 60000.0, true, false, {}, 0, 0});
      st.start();
      st.wait_finished(5000000);
      st.stop();
      const Counters& c = st.counters();
      out << ", \"streamer_wrong_key\": {\"sent\": " << c.sent.load()
          << ", \"bad_tag_notices\": " << c.by_error[BAD_TAG].load()
          << ", \"replies\": " << c.replies.load()
          << ", \"valid\": " << (st.state().valid ? "true" : "false") << "}";
    }
  } catch (const std::exception& e) {
    rest.delete_session(s.id);
    std::cerr << "error: " << e.what() << "\n";
    return 1;
  }
  // REST errors carry the server's detail text.
  try {
    rest.session(s.id + 100000u);
    out << ", \"rest_404\": null";
  } catch (const RestError& e) {
    out << ", \"rest_404\": {\"status\": " << e.status() << ", \"detail\": "
        << json::quote(e.detail()) << "}";
  }
  // The rest of the REST helper: parameters read and changed, a refused change's detail,
  // restart-stream, the session's own view.
  try {
    json::Value changed = rest.set_parameters(s.id, "{\"us_n_mm2\": 1610.2}");
    json::Value read = rest.parameters(s.id);
    out << ", \"us_after_patch\": " << json::number(read["us_n_mm2"].as_double())
        << ", \"patch_answer_us\": "
        << (changed.has("us_n_mm2") ? json::number(changed["us_n_mm2"].as_double()) : "null")
        << ", \"frame_param\": " << json::quote(read["frame"].as_string());
    try {
      rest.set_parameters(s.id, "{\"us_n_mm2\": \"soft\"}");
      out << ", \"rest_422\": null";
    } catch (const RestError& e) {
      out << ", \"rest_422\": {\"status\": " << e.status() << ", \"detail\": "
          << json::quote(e.detail()) << "}";
    }
    rest.restart_stream(s.id);
    json::Value view = rest.session(s.id);
    out << ", \"restart_stream\": true, \"view_id\": " << view["id"].as_int()
        << ", \"view_state\": " << json::quote(view["state"].as_string());
  } catch (const std::exception& e) {
    out << ", \"rest_error\": " << json::quote(e.what());
  }
  rest.delete_session(s.id);
  try {
    rest.session(s.id);
    out << ", \"deleted\": false";
  } catch (const RestError& e) {
    out << ", \"deleted\": " << (e.status() == 404 ? "true" : "false");
  }
  out << "}";
  std::cout << out.str() << std::endl;
  return 0;
}
