// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// One session's rules, without I/O (SPEC.md sections 4, 5, 10): number, tag and stream
// outgoing POSEs, and decide which incoming datagrams to believe: a REPLY must verify,
// belong to the session, be newer than the newest one used and answer a POSE sent recently
// (its seq and t_client_us), else it is dropped and counted.
//
// Streams (protocol v2): the server hands them out and never hands one out twice, so a
// captured POSE can never be accepted again. Without a stream every POSE is a hello
// (stream 0, not ticked); a NEW_STREAM notice that verifies and answers a hello sent since
// the stream was last lost gives the stream; a verified WRONG_STREAM notice for the current
// stream takes it away (hello again). Sequence numbers go on counting across streams.
// Used by the Streamer (haptic thread) and the blocking Client (tools, tests).
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <vector>

#include "burrforce/clock.hpp"
#include "burrforce/hmac.hpp"
#include "burrforce/messages.hpp"
#include "burrforce/protocol.hpp"
#include "burrforce/sequence.hpp"

namespace burrforce {

/// Why a datagram from the server was not used.
enum class Drop : int {
  None = 0,
  Malformed,    ///< not a well-formed v2 message (nor v1's NOTICE), or over 1024 bytes
  BadTag,       ///< a REPLY of a keyed session without a valid tag (forged or corrupt)
  Foreign,      ///< another session's message
  Stale,        ///< a REPLY not newer than the newest one used (reordered, duplicated)
  Unsolicited,  ///< a REPLY to no POSE sent recently (or to a hello, which is never ticked)
  WrongType,    ///< a POSE (servers never send one)
  Count
};

inline const char* drop_name(Drop d) {
  static const char* names[] = {"none",  "malformed",   "bad_tag",   "foreign",
                                "stale", "unsolicited", "wrong_type"};
  int i = static_cast<int>(d);
  return i >= 0 && i < static_cast<int>(Drop::Count) ? names[i] : "?";
}

/// What a received datagram turned out to be.
struct Event {
  enum class Kind { Dropped, Reply, Notice } kind = Kind::Dropped;
  Drop drop = Drop::None;
  Reply reply;
  Notice notice;
  /// A NOTICE tagged with the session's key (always true without a key). Only such a
  /// NEW_STREAM or WRONG_STREAM changes the stream; the others are diagnostics.
  bool verified = false;
  /// This NOTICE gave the client its stream (NEW_STREAM) or took it away (WRONG_STREAM).
  bool stream_changed = false;
  /// From the POSE's send time: the network round trip plus the server's time, and the
  /// clock offset (NTP). What to monitor the link with.
  RoundTrip round_trip{};
  /// SPEC 5.5 literally, T1 = t_client_us: from the pose's sample time, so it also holds how
  /// old the pose was when sent (with publish(), up to a frame). Same as round_trip when the
  /// pose is sampled as it is sent.
  RoundTrip sample_round_trip{};
  int64_t arrival_us = 0;
  uint64_t tick = 0;  ///< the caller's tick number of the POSE this REPLY answers
};

/// Counters, readable from any thread while the haptic thread updates them.
struct Counters {
  static constexpr int kErrorCodes = 16;
  std::atomic<uint64_t> sent{0};
  std::atomic<uint64_t> send_failed{0};
  std::atomic<uint64_t> replies{0};        ///< REPLYs used (error 0 or not)
  std::atomic<uint64_t> error_replies{0};  ///< of which error != 0
  std::atomic<uint64_t> notices{0};
  std::atomic<uint64_t> hellos{0};         ///< POSEs sent without a stream (not ticked)
  std::atomic<uint64_t> streams{0};        ///< streams taken from NEW_STREAM notices
  std::atomic<uint64_t> streams_lost{0};   ///< streams given up on a WRONG_STREAM notice
  std::array<std::atomic<uint64_t>, kErrorCodes> by_error{};  ///< notices + error replies
  std::array<std::atomic<uint64_t>, static_cast<int>(Drop::Count)> dropped{};
  std::atomic<uint64_t> late_ticks{0};     ///< ticks sent more than 20 % of a period late
  std::atomic<uint64_t> skipped_ticks{0};  ///< ticks not sent at all (a stall)

  void count_error(unsigned code) {
    by_error[code < kErrorCodes ? code : kErrorCodes - 1].fetch_add(1, std::memory_order_relaxed);
  }
};

class SessionRules {
 public:
  /// How many recent POSEs a REPLY may answer (~1 s at 1 kHz; a REPLY later than that is
  /// useless for rendering anyway).
  static constexpr uint32_t kRecent = 1024;

  SessionRules(uint32_t session, const std::vector<uint8_t>& key, uint32_t first_seq = 1)
      : session_(session), seq_(first_seq) {
    if (!key.empty()) tagger_.reset(new Tagger(key.data(), key.size()));
    for (auto& r : sent_) r = SentRecord{};
  }

  uint32_t session() const { return session_; }
  bool keyed() const { return tagger_ != nullptr; }
  const Tagger* tagger() const { return tagger_.get(); }
  /// The stream the server gave (any thread); 0 while the client says hello.
  uint32_t stream() const { return stream_.load(std::memory_order_relaxed); }
  uint32_t next_seq() const { return seq_; }
  Counters& counters() { return counters_; }
  const Counters& counters() const { return counters_; }

  /// Fills in `p`'s session, seq and stream (0, a hello, until the server gave one),
  /// encodes and tags it into `out` (>= 160 bytes), remembers it as sent at `tick` and at
  /// `sent_us` (client clock; < 0: t_client_us). Returns the datagram's size.
  size_t encode_next(Pose& p, uint64_t tick, uint8_t* out, size_t capacity,
                     int64_t sent_us = -1) {
    p.session = session_;
    p.seq = seq_;
    p.stream = stream_.load(std::memory_order_relaxed);
    size_t n = encode_pose(p, tagger_.get(), out, capacity);
    if (n == 0) return 0;
    SentRecord& r = sent_[seq_ % kRecent];
    r.seq = seq_;
    r.t_client_us = p.t_client_us;
    r.sent_us = sent_us < 0 ? static_cast<int64_t>(p.t_client_us) : sent_us;
    r.tick = tick;
    r.stream = p.stream;
    r.hello_round = hello_round_;
    r.valid = true;
    if (p.stream == kHelloStream) counters_.hellos.fetch_add(1, std::memory_order_relaxed);
    seq_ = seq_next(seq_);
    return n;
  }

  /// Gives up the stream: the next POSEs are hellos, and the server's answer opens a new
  /// stream (its first tick STALE: a fresh velocity estimate). Never needed to recover: a
  /// closed stream (server restart, REST restart-stream) answers WRONG_STREAM, which does
  /// the same. Sequence numbers go on.
  void restart() { lose_stream(); }

  /// Classifies one datagram that arrived at `arrival_us` (client clock).
  Event accept(const uint8_t* data, size_t n, int64_t arrival_us) {
    Event ev;
    ev.arrival_us = arrival_us;
    if (n > kMaxServerBytes) return drop(ev, Drop::Malformed);
    Decoded d = decode(data, n);
    if (!d.ok) return drop(ev, Drop::Malformed);
    if (d.type == kTypePose) return drop(ev, Drop::WrongType);
    const bool authentic = !tagger_ || (d.tagged && tagger_->verify_tag(data, n));
    // A keyed session's REPLYs are always tagged. NOTICEs pass unverified: they carry no
    // force, and a BAD_TAG notice is tagged with a key a misconfigured client lacks, yet it
    // must learn that its key is wrong (SPEC 4.3). Only authentic ones move the stream.
    if (d.type == kTypeReply && !authentic) return drop(ev, Drop::BadTag);
    if (d.session() != session_) return drop(ev, Drop::Foreign);
    if (d.type == kTypeNotice) {
      ev.kind = Event::Kind::Notice;
      ev.notice = d.notice;
      ev.verified = authentic;
      counters_.notices.fetch_add(1, std::memory_order_relaxed);
      counters_.count_error(d.notice.error);
      if (authentic && d.notice.version == kVersion) ev.stream_changed = follow(d.notice);
      return ev;
    }
    const Reply& r = d.reply;
    if (has_newest_ && !seq_newer(r.seq, newest_)) return drop(ev, Drop::Stale);
    const SentRecord& s = sent_[r.seq % kRecent];
    if (!s.valid || s.seq != r.seq || s.t_client_us != r.t_client_us ||
        s.stream == kHelloStream)
      return drop(ev, Drop::Unsolicited);
    newest_ = r.seq;
    has_newest_ = true;
    ev.kind = Event::Kind::Reply;
    ev.reply = r;
    ev.tick = s.tick;
    ev.round_trip = RoundTrip::of(static_cast<uint64_t>(s.sent_us), r.t_recv_us, r.t_send_us,
                                  arrival_us);
    ev.sample_round_trip = RoundTrip::of(r.t_client_us, r.t_recv_us, r.t_send_us, arrival_us);
    counters_.replies.fetch_add(1, std::memory_order_relaxed);
    if (r.error != OK) {
      counters_.error_replies.fetch_add(1, std::memory_order_relaxed);
      counters_.count_error(r.error);
    }
    return ev;
  }

 private:
  struct SentRecord {
    uint32_t seq = 0;
    uint64_t t_client_us = 0;
    int64_t sent_us = 0;
    uint64_t tick = 0;
    uint32_t stream = 0;
    uint32_t hello_round = 0;
    bool valid = false;
  };

  /// An authentic v2 NOTICE's effect on the stream; true if it changed it.
  bool follow(const Notice& n) {
    const uint32_t current = stream_.load(std::memory_order_relaxed);
    if (n.error == NEW_STREAM) {
      // Only as the answer to one of our hellos since the stream was last lost: a delayed
      // answer to an older hello offers a stream that may be closed by now, and an offer
      // is useless once a stream is open (the server keeps it, harmlessly).
      const SentRecord& s = sent_[n.seq % kRecent];
      if (current != kHelloStream || n.stream == kHelloStream || !s.valid || s.seq != n.seq ||
          s.t_client_us != n.t_client_us || s.stream != kHelloStream ||
          s.hello_round != hello_round_)
        return false;
      stream_.store(n.stream, std::memory_order_relaxed);
      counters_.streams.fetch_add(1, std::memory_order_relaxed);
      return true;
    }
    // Not checked against the POSEs sent: the server never reopens a stream, so a replayed
    // WRONG_STREAM names a stream this client can no longer be using.
    if (n.error == WRONG_STREAM && current != kHelloStream && n.stream == current) {
      lose_stream();
      counters_.streams_lost.fetch_add(1, std::memory_order_relaxed);
      return true;
    }
    return false;
  }

  void lose_stream() {
    stream_.store(kHelloStream, std::memory_order_relaxed);
    ++hello_round_;
  }

  Event& drop(Event& ev, Drop why) {
    ev.kind = Event::Kind::Dropped;
    ev.drop = why;
    counters_.dropped[static_cast<size_t>(why)].fetch_add(1, std::memory_order_relaxed);
    return ev;
  }

  uint32_t session_;
  std::unique_ptr<Tagger> tagger_;
  uint32_t seq_;
  uint32_t newest_ = 0;
  bool has_newest_ = false;
  std::atomic<uint32_t> stream_{kHelloStream};
  /// Counts the times the stream was lost, so a NEW_STREAM is taken only as the answer to a
  /// hello of the current round.
  uint32_t hello_round_ = 0;
  std::array<SentRecord, kRecent> sent_;
  Counters counters_;
};

}  // namespace burrforce
