// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The client clock (SPEC.md 5.3, 5.5): monotonic microseconds, never wall-clock time (which
// jumps), and the round trip and clock offset computed from a REPLY's four stamps.
#pragma once

#include <chrono>
#include <cstdint>
#include <thread>

namespace burrforce {

/// Microseconds of std::chrono::steady_clock: what goes into t_client_us.
inline int64_t now_us() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

/// SPEC 5.5: T1 = t_client_us, T2 = t_recv_us, T3 = t_send_us (server clock), T4 = arrival
/// (client clock), all µs.
struct RoundTrip {
  int64_t rtt_us;       ///< T4 - T1: what the reference client reports
  int64_t server_us;    ///< T3 - T2: time spent in the server
  int64_t network_us;   ///< rtt - server time
  double offset_us;     ///< server clock - client clock, NTP estimate

  static RoundTrip of(uint64_t t1, uint64_t t2, uint64_t t3, int64_t t4) {
    RoundTrip r;
    int64_t T1 = static_cast<int64_t>(t1), T2 = static_cast<int64_t>(t2),
            T3 = static_cast<int64_t>(t3);
    r.rtt_us = t4 - T1;
    r.server_us = T3 - T2;
    r.network_us = r.rtt_us - r.server_us;
    r.offset_us = (static_cast<double>(T2 - T1) + static_cast<double>(T3 - t4)) / 2.0;
    return r;
  }
};

/// Sleeps until close to `deadline_us`, then spins: OS sleeps overshoot by 50 µs to
/// milliseconds, which at 1 kHz is most of a tick.
inline void sleep_until_us(int64_t deadline_us, int64_t spin_us = 300) {
  for (;;) {
    int64_t left = deadline_us - now_us();
    if (left <= 0) return;
    if (left > spin_us)
      std::this_thread::sleep_for(std::chrono::microseconds(left - spin_us));
    else
      std::this_thread::yield();
  }
}

}  // namespace burrforce
