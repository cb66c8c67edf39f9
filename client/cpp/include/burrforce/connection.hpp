// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The connection file `burrforce serve` writes for local tools (SPEC.md 6.4): UDP endpoint,
// session, key, frame, REST URL and token, so a developer's engine finds the server without
// copying anything by hand.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "burrforce/hmac.hpp"
#include "burrforce/json.hpp"

namespace burrforce {

struct Connection {
  std::string host;
  uint16_t udp_port = 0;
  uint32_t session = 0;
  std::string key_hex;
  std::vector<uint8_t> key;
  std::string frame;
  std::string http_url;
  std::string token;

  /// $BURRFORCE_CONNECTION, else $XDG_RUNTIME_DIR/burrforce/connection.json, else
  /// ~/.cache/burrforce/connection.json (%USERPROFILE%\.cache\... on Windows), as the server
  /// writes it.
  static std::string default_path() {
    std::string v;
    if (env("BURRFORCE_CONNECTION", v)) return v;
    if (env("XDG_RUNTIME_DIR", v)) return v + "/burrforce/connection.json";
#ifdef _WIN32
    // Where the server writes it there: Python's Path.home() is %USERPROFILE%.
    if (env("USERPROFILE", v)) return v + "\\.cache\\burrforce\\connection.json";
#endif
    if (env("HOME", v)) return v + "/.cache/burrforce/connection.json";
    return "connection.json";
  }

  /// A non-empty environment variable (without MSVC's getenv deprecation warning).
  static bool env(const char* name, std::string& out) {
#ifdef _MSC_VER
    char* value = nullptr;
    size_t n = 0;
    if (_dupenv_s(&value, &n, name) != 0 || value == nullptr) return false;
    out = value;
    std::free(value);
#else
    const char* value = std::getenv(name);
    if (value == nullptr) return false;
    out = value;
#endif
    return !out.empty();
  }

  static Connection read(const std::string& path = default_path()) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw std::runtime_error("cannot read connection file " + path);
    std::stringstream text;
    text << in.rdbuf();
    json::Value v = json::parse(text.str());
    Connection c;
    c.host = v["host"].as_string();
    c.udp_port = static_cast<uint16_t>(v["udp_port"].as_int());
    c.session = static_cast<uint32_t>(v["session"].as_int());
    if (v.has("key_hex") && v["key_hex"].is_string()) {
      c.key_hex = v["key_hex"].as_string();
      if (!parse_hex(c.key_hex, c.key)) throw std::runtime_error("key_hex is not hex");
    }
    if (v.has("frame") && v["frame"].is_string()) c.frame = v["frame"].as_string();
    if (v.has("http_url") && v["http_url"].is_string()) c.http_url = v["http_url"].as_string();
    if (v.has("token") && v["token"].is_string()) c.token = v["token"].as_string();
    return c;
  }
};

}  // namespace burrforce
