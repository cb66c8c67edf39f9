// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Sequence numbers (SPEC.md 5.1, RFC 1982 serial arithmetic on uint32).
#pragma once

#include <cstdint>

namespace burrforce {

/// `a` is newer than `b` iff 0 < (a - b) mod 2^32 < 2^31; numbers exactly 2^31 apart are
/// not newer (the server treats them as stale, so must we).
inline bool seq_newer(uint32_t a, uint32_t b) {
  uint32_t d = a - b;
  return d != 0 && d < 0x80000000u;
}

inline uint32_t seq_next(uint32_t s) { return s + 1u; }  // unsigned wrap is defined

}  // namespace burrforce
