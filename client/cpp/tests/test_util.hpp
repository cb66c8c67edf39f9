// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Shared by the test programs: command-line options and statistics.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <map>
#include <string>
#include <vector>

namespace testutil {

/// `--name value` pairs.
inline std::map<std::string, std::string> options(int argc, char** argv) {
  std::map<std::string, std::string> o;
  for (int i = 1; i + 1 < argc; i += 2) {
    std::string k = argv[i];
    if (k.rfind("--", 0) != 0) {
      std::cerr << "unexpected argument " << k << "\n";
      std::exit(2);
    }
    o[k.substr(2)] = argv[i + 1];
  }
  return o;
}

inline std::string need(const std::map<std::string, std::string>& o, const std::string& k) {
  auto it = o.find(k);
  if (it == o.end()) {
    std::cerr << "missing --" << k << "\n";
    std::exit(2);
  }
  return it->second;
}

/// numpy.percentile's default (linear interpolation between closest ranks).
inline double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  double pos = q / 100.0 * static_cast<double>(v.size() - 1);
  size_t lo = static_cast<size_t>(std::floor(pos));
  size_t hi = std::min(lo + 1, v.size() - 1);
  double frac = pos - static_cast<double>(lo);
  return v[lo] + (v[hi] - v[lo]) * frac;
}

}  // namespace testutil
