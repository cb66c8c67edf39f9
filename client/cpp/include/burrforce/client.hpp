// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// A blocking UDP client for one session: send a POSE, wait for what comes back. For tools,
// tests and request/response use; an engine's haptic loop uses the Streamer instead.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "burrforce/clock.hpp"
#include "burrforce/session.hpp"
#include "burrforce/udp_socket.hpp"

namespace burrforce {

class Client {
 public:
  Client(const std::string& host, uint16_t port, uint32_t session,
         const std::vector<uint8_t>& key, uint32_t first_seq = 1)
      : socket_(host, port), rules_(session, key, first_seq) {}

  SessionRules& rules() { return rules_; }
  Counters& counters() { return rules_.counters(); }

  /// Sends `p` (its session, seq and stream are filled in; t_client_us = now if 0): a hello
  /// while the client has no stream (see open_stream). Returns the seq used.
  /// `last_datagram()` holds the bytes sent.
  uint32_t send(Pose p) {
    if (p.t_client_us == 0) p.t_client_us = static_cast<uint64_t>(now_us());
    uint32_t seq = rules_.next_seq();
    last_size_ = rules_.encode_next(p, ticks_++, last_, sizeof last_, now_us());
    send_raw(last_, last_size_);
    return seq;
  }

  /// Sends bytes as they are (resends, hand-made datagrams).
  bool send_raw(const uint8_t* data, size_t n) {
    bool ok = socket_.send(data, n);
    rules_.counters().sent.fetch_add(1, std::memory_order_relaxed);
    if (!ok) rules_.counters().send_failed.fetch_add(1, std::memory_order_relaxed);
    return ok;
  }
  const uint8_t* last_datagram() const { return last_; }
  size_t last_size() const { return last_size_; }

  /// The next REPLY or NOTICE within `timeout_us`; an Event of kind Dropped with drop None
  /// means nothing came. Dropped datagrams are skipped (and counted).
  Event receive(int64_t timeout_us) {
    int64_t deadline = now_us() + timeout_us;
    for (;;) {
      long n = socket_.receive(buffer_, sizeof buffer_ - 1);
      if (n >= 0) {
        Event ev = rules_.accept(buffer_, static_cast<size_t>(n), now_us());
        if (ev.kind != Event::Kind::Dropped) return ev;
        continue;
      }
      int64_t left = deadline - now_us();
      if (left <= 0) return Event{};
      socket_.wait_readable(left);
    }
  }

  /// The stream the server gave; 0 until open_stream() (or a NEW_STREAM) succeeded.
  uint32_t stream() const { return rules_.stream(); }

  /// Says hello with `p` (not ticked) until a NEW_STREAM notice gives a stream, resending
  /// every `retry_us` in case a datagram was lost. True once the client has a stream; false
  /// after `timeout_us` (no server, wrong key: see the notices counted). The next POSE
  /// streams; a client with a stream returns true at once.
  bool open_stream(const Pose& p, int64_t timeout_us, int64_t retry_us = 100000) {
    int64_t deadline = now_us() + timeout_us;
    while (rules_.stream() == kHelloStream) {
      int64_t left = deadline - now_us();
      if (left <= 0) return false;
      send(p);
      int64_t until = now_us() + (retry_us < left ? retry_us : left);
      while (rules_.stream() == kHelloStream) {
        Event ev = receive(until - now_us());
        if (ev.kind == Event::Kind::Dropped) break;  // nothing came: say hello again
      }
    }
    return true;
  }

  /// Sends `p` and waits for the answer to that seq (REPLY or NOTICE), skipping others.
  Event exchange(const Pose& p, int64_t timeout_us) {
    uint32_t seq = send(p);
    int64_t deadline = now_us() + timeout_us;
    for (;;) {
      Event ev = receive(deadline - now_us());
      if (ev.kind == Event::Kind::Dropped) return ev;
      if (ev.kind == Event::Kind::Reply && ev.reply.seq == seq) return ev;
      if (ev.kind == Event::Kind::Notice && ev.notice.seq == seq) return ev;
    }
  }

 private:
  UdpSocket socket_;
  SessionRules rules_;
  uint64_t ticks_ = 0;
  uint8_t last_[kMaxPoseBytes];
  size_t last_size_ = 0;
  uint8_t buffer_[kMaxServerBytes + 2];
};

}  // namespace burrforce
