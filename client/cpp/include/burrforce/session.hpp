// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// One session's rules, without I/O (SPEC.md sections 4, 5, 10): number and tag outgoing
// POSEs (FLAG_NEW_STREAM until the first REPLY), and decide which incoming datagrams to
// believe: a REPLY must verify, belong to the session, be newer than the newest one used and
// answer a POSE sent recently (its seq and t_client_us), else it is dropped and counted.
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
  Malformed,    ///< not a well-formed v1 message, or larger than 1024 bytes
  BadTag,       ///< a REPLY of a keyed session without a valid tag (forged or corrupt)
  Foreign,      ///< another session's message
  Stale,        ///< a REPLY not newer than the newest one used (reordered, duplicated)
  Unsolicited,  ///< a REPLY to no POSE sent recently (a replay of an old stream's REPLY)
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
  /// True until the first REPLY (any error value) of this stream.
  bool new_stream() const { return !has_newest_; }
  uint32_t next_seq() const { return seq_; }
  Counters& counters() { return counters_; }
  const Counters& counters() const { return counters_; }

  /// Fills in `p`'s session, seq and FLAG_NEW_STREAM, encodes and tags it into `out`
  /// (>= 160 bytes), remembers it as sent at `tick` and at `sent_us` (client clock; < 0:
  /// t_client_us). Returns the datagram's size.
  size_t encode_next(Pose& p, uint64_t tick, uint8_t* out, size_t capacity,
                     int64_t sent_us = -1) {
    p.session = session_;
    p.seq = seq_;
    if (!has_newest_) p.flags |= FLAG_NEW_STREAM;
    size_t n = encode_pose(p, tagger_.get(), out, capacity);
    if (n == 0) return 0;
    SentRecord& r = sent_[seq_ % kRecent];
    r.seq = seq_;
    r.t_client_us = p.t_client_us;
    r.sent_us = sent_us < 0 ? static_cast<int64_t>(p.t_client_us) : sent_us;
    r.tick = tick;
    r.valid = true;
    seq_ = seq_next(seq_);
    return n;
  }

  /// Starts a new stream: the server accepts any seq again (FLAG_NEW_STREAM until the next
  /// REPLY), and REPLYs of the old stream are no longer believed.
  void restart(uint32_t first_seq) {
    seq_ = first_seq;
    has_newest_ = false;
    for (auto& r : sent_) r.valid = false;
  }

  /// Classifies one datagram that arrived at `arrival_us` (client clock).
  Event accept(const uint8_t* data, size_t n, int64_t arrival_us) {
    Event ev;
    ev.arrival_us = arrival_us;
    if (n > kMaxServerBytes) return drop(ev, Drop::Malformed);
    Decoded d = decode(data, n);
    if (!d.ok) return drop(ev, Drop::Malformed);
    if (d.type == kTypePose) return drop(ev, Drop::WrongType);
    // A keyed session's REPLYs are always tagged. NOTICEs pass unverified: they carry no
    // force, and a BAD_TAG notice is tagged with a key a misconfigured client lacks, yet it
    // must learn that its key is wrong (SPEC 4.3).
    if (d.type == kTypeReply && tagger_ && !(d.tagged && tagger_->verify_tag(data, n)))
      return drop(ev, Drop::BadTag);
    if (d.session() != session_) return drop(ev, Drop::Foreign);
    if (d.type == kTypeNotice) {
      ev.kind = Event::Kind::Notice;
      ev.notice = d.notice;
      counters_.notices.fetch_add(1, std::memory_order_relaxed);
      counters_.count_error(d.notice.error);
      return ev;
    }
    const Reply& r = d.reply;
    if (has_newest_ && !seq_newer(r.seq, newest_)) return drop(ev, Drop::Stale);
    const SentRecord& s = sent_[r.seq % kRecent];
    if (!s.valid || s.seq != r.seq || s.t_client_us != r.t_client_us)
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
    bool valid = false;
  };

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
  std::array<SentRecord, kRecent> sent_;
  Counters counters_;
};

}  // namespace burrforce
