// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Protocol v2's server-issued streams against a live server: a client's first POSE is a
// hello answered with NEW_STREAM; a restarted client (a new object, the same key, seq from 1
// again, right after the old stream was used) gets its own stream from its first hello and
// its first POSE on it is answered; captured datagrams of an earlier stream are never
// answered with a REPLY (WRONG_STREAM instead), and a replayed hello does not disturb the
// live stream; the old client, refused with WRONG_STREAM, says hello again; a REST
// restart-stream closes the Streamer's stream and it recovers by itself.
// Usage: handshake --url HTTP_URL --token TOKEN. Prints one JSON line.
#include <functional>
#include <iostream>
#include <sstream>
#include <thread>
#include <vector>

#include "burrforce/burrforce.hpp"
#include "test_util.hpp"

using namespace burrforce;

namespace {
// Generous: this machine is shared, and a loaded server answers a loopback POSE late. The
// server answers each datagram at most once, so nothing waits for the full time unless the
// answer was lost.
constexpr int64_t kWaitUs = 5000000;
// After a replay's answer, how long to go on listening for a second datagram (there should
// be none; the server answers a datagram once).
constexpr int64_t kAfterAnswerUs = 100000;

const char* tf(bool b) { return b ? "true" : "false"; }

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
    o << "{\"kind\": \"notice\", \"error\": " << ev.notice.error << ", \"stream\": "
      << ev.notice.stream << ", \"seq\": " << ev.notice.seq << ", \"verified\": "
      << tf(ev.verified) << ", \"stream_changed\": " << tf(ev.stream_changed) << "}";
  else if (ev.kind == Event::Kind::Reply)
    o << "{\"kind\": \"reply\", \"error\": " << ev.reply.error << ", \"status\": "
      << ev.reply.status << ", \"seq\": " << ev.reply.seq << "}";
  else
    o << "{\"kind\": \"none\"}";
  return o.str();
}

/// Sends `datagram` as it is from a socket of its own and decodes what comes back (its
/// answer, and anything else within kAfterAnswerUs of it): the server's raw answers, not
/// filtered by any client's rules.
std::string replay_json(const SessionInfo& s, const std::vector<uint8_t>& datagram,
                        const Tagger& tagger) {
  UdpSocket u(s.udp_host, s.udp_port);
  u.send(datagram.data(), datagram.size());
  int replies = 0, notices = 0, verified = 0;
  std::ostringstream errors, streams;
  int64_t deadline = now_us() + kWaitUs;
  uint8_t buf[kMaxServerBytes + 2];
  for (int64_t left = kWaitUs; left > 0; left = deadline - now_us()) {
    if (!u.wait_readable(left)) continue;
    long n = u.receive(buf, sizeof buf);
    if (n < 0) continue;
    if (replies + notices == 0) deadline = now_us() + kAfterAnswerUs;
    Decoded d = decode(buf, static_cast<size_t>(n));
    if (!d.ok) continue;
    if (d.type == kTypeReply) ++replies;
    if (d.type == kTypeNotice) {
      errors << (notices ? ", " : "") << d.notice.error;
      streams << (notices ? ", " : "") << d.notice.stream;
      ++notices;
      if (d.tagged && tagger.verify_tag(buf, static_cast<size_t>(n))) ++verified;
    }
  }
  std::ostringstream o;
  o << "{\"replies\": " << replies << ", \"notices\": " << notices << ", \"verified\": "
    << verified << ", \"errors\": [" << errors.str() << "], \"streams\": [" << streams.str()
    << "]}";
  return o.str();
}

/// Polls `done` until it holds or `timeout_us` passed; the caller asserts on the state, not
/// on the time it took.
bool wait_until(const std::function<bool()>& done, int64_t timeout_us) {
  int64_t deadline = now_us() + timeout_us;
  while (!done()) {
    if (now_us() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return true;
}
}  // namespace

int main(int argc, char** argv) {
  auto o = testutil::options(argc, argv);
  Rest rest(testutil::need(o, "url"), testutil::need(o, "token"));
  SessionInfo s = rest.create_session("phantom:workpiece", "si_mm");
  const Tagger tagger(s.key.data(), s.key.size());
  std::ostringstream out;
  out << "{\"session\": " << s.id;
  try {
    const Pose pose = above_bone();
    // 1. The first client: hello, NEW_STREAM, then streaming. It keeps its first hello and
    //    one of its streamed POSEs, as an eavesdropper would.
    Client a(s.udp_host, s.udp_port, s.id, s.key, 1);
    Event a_hello = a.exchange(pose, kWaitUs);
    std::vector<uint8_t> hello_bytes(a.last_datagram(), a.last_datagram() + a.last_size());
    const uint32_t a_stream = a.stream();
    out << ", \"a_hello\": " << event_json(a_hello) << ", \"a_stream\": " << a_stream;
    Event a_first = a.exchange(pose, kWaitUs);
    out << ", \"a_first\": " << event_json(a_first);
    std::vector<uint8_t> captured;
    int a_replies = 0;
    for (int i = 0; i < 20; ++i) {
      Event ev = a.exchange(pose, kWaitUs);
      if (ev.kind == Event::Kind::Reply && ev.reply.error == OK) ++a_replies;
      if (i == 5) captured.assign(a.last_datagram(), a.last_datagram() + a.last_size());
    }
    const Decoded captured_pose = decode(captured.data(), captured.size());
    out << ", \"a_replies\": " << a_replies << ", \"a_next_seq\": " << a.rules().next_seq()
        << ", \"captured_stream\": " << captured_pose.pose.stream
        << ", \"captured_seq\": " << captured_pose.pose.seq;

    // 2. A restarted client right away: a new object, the same key, seq from 1 again (older
    //    than the stream's). v1 dropped such POSEs until the session had been idle for 1 s;
    //    now its first hello opens a stream and its first POSE is answered.
    Client b(s.udp_host, s.udp_port, s.id, s.key, 1);
    Event b_hello = b.exchange(pose, kWaitUs);
    const uint32_t b_stream = b.stream();
    Event b_first = b.exchange(pose, kWaitUs);
    int b_replies = 0;
    for (int i = 0; i < 20; ++i) {
      Event ev = b.exchange(pose, kWaitUs);
      if (ev.kind == Event::Kind::Reply && ev.reply.error == OK) ++b_replies;
    }
    out << ", \"b_hello\": " << event_json(b_hello) << ", \"b_stream\": " << b_stream
        << ", \"b_first\": " << event_json(b_first) << ", \"b_replies\": " << b_replies
        << ", \"b_hellos_sent\": " << b.counters().hellos.load();

    // 3. Replays: the captured POSE of the first stream is refused (WRONG_STREAM, no
    //    REPLY); the captured hello gets an offer but leaves the live stream alone.
    out << ", \"replayed_pose\": " << replay_json(s, captured, tagger);
    out << ", \"replayed_hello\": " << replay_json(s, hello_bytes, tagger);
    Event b_after = b.exchange(pose, kWaitUs);
    out << ", \"b_after_replays\": " << event_json(b_after)
        << ", \"b_stream_after_replays\": " << b.stream();

    // 4. The first client, still on its closed stream: refused, it says hello again and
    //    gets a third stream.
    Event a_refused = a.exchange(pose, kWaitUs);
    out << ", \"a_refused\": " << event_json(a_refused)
        << ", \"a_stream_after_refusal\": " << a.stream();
    bool a_reopened = a.open_stream(pose, kWaitUs);
    Event a_again = a.exchange(pose, kWaitUs);
    out << ", \"a_reopened\": " << tf(a_reopened) << ", \"a_new_stream\": " << a.stream()
        << ", \"a_again\": " << event_json(a_again);
  } catch (const std::exception& e) {
    out << ", \"error\": " << json::quote(e.what());
  }

  try {
    // 5. A restarted Streamer (seq from 1 again, right after another one streamed): the
    //    first POSE sent on its stream is answered; every tick before it was a hello.
    StreamerConfig cfg;
    cfg.host = s.udp_host;
    cfg.port = s.udp_port;
    cfg.session = s.id;
    cfg.key = s.key;
    cfg.max_catch_up_ticks = 50;
    for (int run = 0; run < 2; ++run) {
      cfg.max_ticks = 500;
      cfg.linger_us = 1000000;  // a late answer to the last ticks still counts
      Streamer st(cfg);
      std::vector<uint32_t> stream_at(cfg.max_ticks, 0);
      int64_t first_reply_tick = -1;
      st.set_pose_source([&](uint64_t tick, int64_t, ToolPose& p) {
        stream_at[tick] = st.stream();  // the stream thread's own: what this tick carries
        p.position = {3.0, 0.0, 5.0};
        p.orientation = {0, 0, 0, 1};
        p.rpm = 60000.0;
        p.spindle_on = true;
        return true;
      });
      st.on_reply([&](const Event& ev) {
        if (first_reply_tick < 0) first_reply_tick = static_cast<int64_t>(ev.tick);
      });
      st.start();
      bool finished = st.wait_finished(20000000);
      st.stop();
      int64_t first_stream_tick = -1;
      for (size_t k = 0; k < stream_at.size() && first_stream_tick < 0; ++k)
        if (stream_at[k] != 0) first_stream_tick = static_cast<int64_t>(k);
      const Counters& c = st.counters();
      out << ", \"streamer_" << run << "\": {\"finished\": " << tf(finished)
          << ", \"stream\": " << st.stream() << ", \"first_stream_tick\": " << first_stream_tick
          << ", \"first_reply_tick\": " << first_reply_tick
          << ", \"hellos\": " << c.hellos.load() << ", \"streams\": " << c.streams.load()
          << ", \"sent\": " << c.sent.load() << ", \"replies\": " << c.replies.load()
          << ", \"skipped\": " << c.skipped_ticks.load() << "}";
    }

    // 6. REST restart-stream while a Streamer runs: its stream is closed, the next POSE is
    //    refused with WRONG_STREAM, and it says hello and streams on, on a new stream.
    cfg.max_ticks = 0;
    Streamer st(cfg);
    st.start();
    ToolPose tp;
    tp.position = {3.0, 0.0, 5.0};
    tp.orientation = {0, 0, 0, 1};
    tp.rpm = 60000.0;
    tp.spindle_on = true;
    st.publish(tp);
    const Counters& c = st.counters();
    bool streaming = wait_until([&] { return c.replies.load() >= 50; }, 10000000);
    const uint32_t before = st.stream();
    const uint64_t replies_before = c.replies.load();
    rest.restart_stream(s.id);
    bool recovered = wait_until(
        [&] {
          return c.streams_lost.load() >= 1 && st.stream() != 0 &&
                 c.replies.load() >= replies_before + 50;
        },
        10000000);
    const uint32_t after = st.stream();
    st.stop();
    out << ", \"rest_restart\": {\"streaming\": " << tf(streaming) << ", \"recovered\": "
        << tf(recovered) << ", \"stream_before\": " << before << ", \"stream_after\": " << after
        << ", \"streams\": " << c.streams.load() << ", \"streams_lost\": "
        << c.streams_lost.load() << ", \"wrong_stream_notices\": "
        << c.by_error[WRONG_STREAM].load() << ", \"replies_after\": "
        << c.replies.load() - replies_before << ", \"failed\": " << tf(st.failed()) << "}";
  } catch (const std::exception& e) {
    out << ", \"streamer_error\": " << json::quote(e.what());
  }
  rest.delete_session(s.id);
  out << "}";
  std::cout << out.str() << std::endl;
  return 0;
}
