// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The three messages of protocol version 2 (SPEC.md section 3) as plain structs, with the
// protocol's constants. Vectors are engine axes and units unless a field's name says
// otherwise (resistive: N components; removed_mm3: mm³ in every frame).
#pragma once

#include <cstdint>

namespace burrforce {

constexpr uint32_t kVersion = 2;
/// The previous version: what a v1 server answers a v2 POSE with (a BAD_VERSION NOTICE in
/// v1's shape), and what a v2 server answers a v1 client with.
constexpr uint32_t kVersion1 = 1;
constexpr uint32_t kTypePose = 1, kTypeReply = 2, kTypeNotice = 3;
constexpr uint32_t kPoseElements = 13, kReplyElements = 24, kNoticeElements = 8;
constexpr uint32_t kNoticeV1Elements = 7;
/// POSE element 11: a POSE carrying this stream asks for one ("hello"); it is not ticked.
constexpr uint32_t kHelloStream = 0;
/// Real maxima (a uint64 clock and wide integers): POSE 153 bytes, REPLY 327 bytes.
constexpr size_t kMaxPoseBytes = 512;
/// Receive buffer: anything larger than a REPLY may be is rejected, so 1024 + 1 detects it.
constexpr size_t kMaxServerBytes = 1024;

// POSE flags (3.1.1). Bit 2 (v1's FLAG_NEW_STREAM) is reserved again: streams are handed
// out by the server (NEW_STREAM notices), so a restarted client needs no flag.
constexpr uint32_t FLAG_RESET_VELOCITY = 1, FLAG_NO_CARVE = 2;

// REPLY status bits (3.2.1)
constexpr uint32_t STATUS_CUTTING = 1, STATUS_CONTACT = 2, STATUS_FORBIDDEN = 4,
                   STATUS_CLAMPED = 8, STATUS_STALE = 16, STATUS_SHAFT_CONTACT = 32,
                   STATUS_SLOW_SPINDLE = 64;

// Error codes (3.4)
enum ErrorCode : uint16_t {
  OK = 0,
  MALFORMED = 1,
  TOO_BIG = 2,
  BAD_VERSION = 3,
  BAD_TYPE = 4,
  UNKNOWN_SESSION = 5,
  BAD_TAG = 6,
  BAD_VALUE = 7,
  STALE = 8,
  DUPLICATE = 9,
  INTERNAL = 10,
  NEW_STREAM = 11,    ///< notice: use the notice's stream in your POSEs (answers a hello)
  WRONG_STREAM = 12,  ///< notice: the POSE's stream is not open (any more): say hello again
};

inline const char* error_name(unsigned code) {
  static const char* names[] = {"OK",         "MALFORMED",       "TOO_BIG",
                                "BAD_VERSION", "BAD_TYPE",       "UNKNOWN_SESSION",
                                "BAD_TAG",    "BAD_VALUE",       "STALE",
                                "DUPLICATE",  "INTERNAL",        "NEW_STREAM",
                                "WRONG_STREAM"};
  return code < sizeof names / sizeof names[0] ? names[code] : "UNKNOWN_ERROR";
}

struct Pose {
  uint32_t session = 0;
  uint32_t seq = 0;
  uint64_t t_client_us = 0;   ///< when the pose was sampled, client monotonic clock
  double position[3] = {0, 0, 0};           ///< L, engine frame
  double orientation[4] = {0, 0, 0, 1};     ///< x, y, z, w as the engine stores it
  double rpm = 0;
  bool spindle_on = false;
  bool has_velocity = false;
  double velocity[3] = {0, 0, 0};           ///< L/s, engine axes (only if has_velocity)
  uint32_t flags = 0;
  uint32_t stream = kHelloStream;  ///< the stream the server gave; 0: a hello
};

struct Reply {
  uint32_t session = 0;
  uint32_t seq = 0;
  uint64_t t_client_us = 0;
  uint64_t t_recv_us = 0;
  uint64_t t_send_us = 0;
  uint16_t error = 0;
  uint32_t status = 0;
  double force[3] = {0, 0, 0};              ///< N, engine axes
  double resistive[3] = {0, 0, 0};          ///< N: feed, lateral, normal
  double torque[3] = {0, 0, 0};             ///< N·L, engine axes
  double power_w = 0;
  double vibration_amplitude = 0;           ///< N
  double vibration_frequency_hz = 0;
  double vibration_axis[3] = {0, 0, 0};     ///< unit, engine axes
  double proxy_position[3] = {0, 0, 0};     ///< L
  double proxy_velocity[3] = {0, 0, 0};     ///< L/s
  double coupling_stiffness = 0;            ///< N/L; 0 = raw output
  double coupling_damping = 0;              ///< N·s/L
  double removed_mm3 = 0;
  uint64_t bone_version = 0;
  double feed_velocity[3] = {0, 0, 0};      ///< L/s
};

struct Notice {
  /// kVersion, or kVersion1 for a BAD_VERSION notice in v1's shape (which has no stream):
  /// a v1 server's answer to a v2 POSE.
  uint32_t version = kVersion;
  uint32_t session = 0;
  uint32_t seq = 0;
  uint64_t t_client_us = 0;
  uint16_t error = 0;
  /// NEW_STREAM: the stream to use; WRONG_STREAM: the refused POSE's stream; else 0.
  uint32_t stream = 0;
};

}  // namespace burrforce
