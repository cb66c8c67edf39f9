// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The SDK test groove of tests/sdk/conftest.py, computed with the same float64 arithmetic:
// server frame, mm; 1000 ticks plunging 1 mm, 1200 ticks feeding 6 mm along +x.
#pragma once

#include <cmath>
#include <cstdint>

#include "burrforce/frames.hpp"

namespace groove {
constexpr uint64_t kPlunge = 1000, kFeed = 1200, kTicks = kPlunge + kFeed + 1;
constexpr uint64_t kSteadyFrom = kPlunge + 240;
constexpr double kRpm = 60000.0;
constexpr double kPi = 3.141592653589793;

inline burrforce::Vec3 position_mm(uint64_t i) {
  double t = static_cast<double>(i);
  if (i <= kPlunge) return {3.0, 0.0, 2.5 - 0.001 * t};
  return {3.0 + 0.005 * (t - static_cast<double>(kPlunge)), 0.0, 1.5};
}

/// The tool axis toward the handle, server frame (60° back against the feed).
inline burrforce::Vec3 axis() {
  double a = 60.0 * (kPi / 180.0);  // as Python's math.radians
  return {-std::cos(a), 0.0, std::sin(a)};
}
}  // namespace groove
