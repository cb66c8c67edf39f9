// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Encoding and decoding of POSE, REPLY and NOTICE (SPEC.md sections 2-4). Encoders write the
// canonical form into a caller's buffer (no allocation: they run on the haptic thread);
// decoders accept every form of section 2.2 and fail cleanly on anything else.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>

#include "burrforce/hmac.hpp"
#include "burrforce/messages.hpp"
#include "burrforce/msgpack.hpp"

namespace burrforce {

namespace detail {
constexpr uint64_t kMaxTimestamp = 0x7FFFFFFFFFFFFFFFull;
constexpr uint64_t kMaxU32 = 0xFFFFFFFFull;
constexpr uint64_t kMaxU64 = ~0ull;

inline size_t finish_tag(msgpack::Writer& w, const Tagger* tagger) {
  if (tagger) {
    static const uint8_t zeros[kTagBytes] = {0};
    w.bin8(zeros, kTagBytes);
  } else {
    w.nil();
  }
  if (!w.ok()) return 0;
  if (tagger) tagger->sign(w.data(), w.size());
  return w.size();
}

inline void header(msgpack::Writer& w, uint32_t version, uint32_t elements, uint32_t type,
                   uint32_t session, uint32_t seq, uint64_t t_client_us) {
  w.array(elements);
  w.uint(version);
  w.uint(type);
  w.uint(session);
  w.uint(seq);
  w.uint(t_client_us);
}
}  // namespace detail

/// Encodes a POSE, tagged with `tagger` (nil tag without one). Returns the datagram's size,
/// 0 if `capacity` is too small (153 bytes always suffice).
inline size_t encode_pose(const Pose& p, const Tagger* tagger, uint8_t* out, size_t capacity) {
  msgpack::Writer w(out, capacity);
  detail::header(w, kVersion, kPoseElements, kTypePose, p.session, p.seq, p.t_client_us);
  w.vec(p.position, 3);
  w.vec(p.orientation, 4);
  w.f64(p.rpm);
  w.boolean(p.spindle_on);
  if (p.has_velocity)
    w.vec(p.velocity, 3);
  else
    w.nil();
  w.uint(p.flags);
  w.uint(p.stream);
  return detail::finish_tag(w, tagger);
}

/// Encodes a REPLY (a server's job; here for tests, simulators and the golden vectors).
inline size_t encode_reply(const Reply& r, const Tagger* tagger, uint8_t* out,
                           size_t capacity) {
  msgpack::Writer w(out, capacity);
  detail::header(w, kVersion, kReplyElements, kTypeReply, r.session, r.seq, r.t_client_us);
  w.uint(r.t_recv_us);
  w.uint(r.t_send_us);
  w.uint(r.error);
  w.uint(r.status);
  w.vec(r.force, 3);
  w.vec(r.resistive, 3);
  w.vec(r.torque, 3);
  w.f64(r.power_w);
  w.f64(r.vibration_amplitude);
  w.f64(r.vibration_frequency_hz);
  w.vec(r.vibration_axis, 3);
  w.vec(r.proxy_position, 3);
  w.vec(r.proxy_velocity, 3);
  w.f64(r.coupling_stiffness);
  w.f64(r.coupling_damping);
  w.f64(r.removed_mm3);
  w.uint(r.bone_version);
  w.vec(r.feed_velocity, 3);
  return detail::finish_tag(w, tagger);
}

/// Encodes a NOTICE (a server's job, as encode_reply); `n.version == kVersion1` writes v1's
/// shape, without the stream.
inline size_t encode_notice(const Notice& n, const Tagger* tagger, uint8_t* out,
                            size_t capacity) {
  msgpack::Writer w(out, capacity);
  const bool v1 = n.version == kVersion1;
  detail::header(w, v1 ? kVersion1 : kVersion, v1 ? kNoticeV1Elements : kNoticeElements,
                 kTypeNotice, n.session, n.seq, n.t_client_us);
  w.uint(n.error);
  if (!v1) w.uint(n.stream);
  return detail::finish_tag(w, tagger);
}

/// The result of decoding one datagram.
struct Decoded {
  /// Elements 0-4 were readable (SPEC 2.2): the message can be attributed to a session and
  /// a packet even when the rest is malformed.
  bool header_ok = false;
  /// The whole message is a well-formed v2 POSE, REPLY or NOTICE, or a NOTICE in v1's shape
  /// (notice.version 1: a v1 server saying BAD_VERSION to our v2 POSEs).
  bool ok = false;
  uint32_t version = 0;
  uint32_t type = 0;
  uint32_t elements = 0;
  bool tagged = false;  ///< the tag element is a 16-byte bin (verify with Tagger on the bytes)
  Pose pose;
  Reply reply;
  Notice notice;

  uint32_t session() const { return type == kTypeReply ? reply.session
                                    : type == kTypeNotice ? notice.session : pose.session; }
  uint32_t seq() const { return type == kTypeReply ? reply.seq
                                : type == kTypeNotice ? notice.seq : pose.seq; }
};

namespace detail {
inline bool read_tag(msgpack::Reader& r, bool& tagged) {
  if (r.take_nil()) {
    tagged = false;
    return true;
  }
  const uint8_t* p;
  uint32_t n;
  if (!r.bin(p, n) || n != kTagBytes) return false;
  tagged = true;
  return true;
}

inline bool read_u16(msgpack::Reader& r, uint16_t& v) {
  uint64_t x;
  if (!r.uint(x, 0xFFFF)) return false;
  v = static_cast<uint16_t>(x);
  return true;
}
inline bool read_u32(msgpack::Reader& r, uint32_t& v) {
  uint64_t x;
  if (!r.uint(x, kMaxU32)) return false;
  v = static_cast<uint32_t>(x);
  return true;
}
}  // namespace detail

/// Decodes any v2 message, and v1's NOTICE. Never throws, never reads outside `data[0:n]`.
inline Decoded decode(const uint8_t* data, size_t n) {
  Decoded d;
  msgpack::Reader r(data, n);
  uint32_t count;
  if (!r.array(count) || count < 5) return d;
  uint64_t version, type;
  bool neg0, neg1;
  if (!r.integer(version, neg0) || !r.integer(type, neg1)) return d;
  uint32_t session, seq;
  uint64_t t;
  if (!detail::read_u32(r, session) || !detail::read_u32(r, seq) ||
      !r.uint(t, detail::kMaxTimestamp))
    return d;
  d.header_ok = true;
  d.elements = count;
  d.version = neg0 || version > detail::kMaxU32 ? 0xFFFFFFFFu : static_cast<uint32_t>(version);
  d.type = neg1 || type > detail::kMaxU32 ? 0xFFFFFFFFu : static_cast<uint32_t>(type);
  bool ok = false;
  if (d.version == kVersion1) {
    // Of v1 only the NOTICE: the one message a v1 server sends a v2 client.
    if (d.type == kTypeNotice && count == kNoticeV1Elements) {
      Notice& p = d.notice;
      p.version = kVersion1;
      p.session = session;
      p.seq = seq;
      p.t_client_us = t;
      ok = detail::read_u16(r, p.error) && detail::read_tag(r, d.tagged) && r.at_end();
    }
    d.ok = ok;
    return d;
  }
  if (d.version != kVersion) return d;
  if (d.type == kTypePose && count == kPoseElements) {
    Pose& p = d.pose;
    p.session = session;
    p.seq = seq;
    p.t_client_us = t;
    ok = r.vec(p.position, 3) && r.vec(p.orientation, 4) && r.number(p.rpm) &&
         r.boolean(p.spindle_on);
    if (ok) {
      p.has_velocity = !r.take_nil();
      if (p.has_velocity) ok = r.vec(p.velocity, 3);
    }
    ok = ok && detail::read_u32(r, p.flags) && detail::read_u32(r, p.stream);
  } else if (d.type == kTypeReply && count == kReplyElements) {
    Reply& p = d.reply;
    p.session = session;
    p.seq = seq;
    p.t_client_us = t;
    ok = r.uint(p.t_recv_us, detail::kMaxU64) && r.uint(p.t_send_us, detail::kMaxU64) &&
         detail::read_u16(r, p.error) && detail::read_u32(r, p.status) &&
         r.vec(p.force, 3) && r.vec(p.resistive, 3) && r.vec(p.torque, 3) &&
         r.number(p.power_w) && r.number(p.vibration_amplitude) &&
         r.number(p.vibration_frequency_hz) && r.vec(p.vibration_axis, 3) &&
         r.vec(p.proxy_position, 3) && r.vec(p.proxy_velocity, 3) &&
         r.number(p.coupling_stiffness) && r.number(p.coupling_damping) &&
         r.number(p.removed_mm3) && r.uint(p.bone_version, detail::kMaxU64) &&
         r.vec(p.feed_velocity, 3);
  } else if (d.type == kTypeNotice && count == kNoticeElements) {
    Notice& p = d.notice;
    p.session = session;
    p.seq = seq;
    p.t_client_us = t;
    ok = detail::read_u16(r, p.error) && detail::read_u32(r, p.stream);
  }
  ok = ok && detail::read_tag(r, d.tagged) && r.at_end();
  d.ok = ok;
  return d;
}

/// SPEC 3.1's value checks: what the server answers with BAD_VALUE. Engines can test a pose
/// before sending it (a NaN from a physics blow-up costs the stream its velocity estimate).
inline bool pose_values_valid(const Pose& p) {
  auto fin = [](double v, double lim) { return std::isfinite(v) && std::fabs(v) <= lim; };
  for (double v : p.position)
    if (!fin(v, 1e9)) return false;
  double n2 = 0;
  for (double v : p.orientation) {
    if (!fin(v, 1e9)) return false;
    n2 += v * v;
  }
  double norm = std::sqrt(n2);
  if (!(norm >= 0.5 && norm <= 1.5)) return false;
  if (p.has_velocity)
    for (double v : p.velocity)
      if (!fin(v, 1e9)) return false;
  return fin(p.rpm, 1e7);
}

}  // namespace burrforce
