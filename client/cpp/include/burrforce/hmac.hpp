// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// HMAC-SHA256 (RFC 2104) and the protocol's 16-byte tag (SPEC.md section 4). The keyed
// inner and outer states are computed once per key, so tagging a datagram on the haptic
// thread costs two short hashes and no allocation.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "burrforce/sha256.hpp"

namespace burrforce {

constexpr size_t kTagBytes = 16;

/// Equal in time independent of where the bytes differ (a tag check must not leak how many
/// leading bytes of a forgery were right).
inline bool constant_time_equal(const uint8_t* a, const uint8_t* b, size_t n) {
  uint8_t diff = 0;
  for (size_t i = 0; i < n; ++i) diff = static_cast<uint8_t>(diff | (a[i] ^ b[i]));
  return diff == 0;
}

class HmacSha256 {
 public:
  HmacSha256() = default;
  HmacSha256(const uint8_t* key, size_t n) { set_key(key, n); }

  void set_key(const uint8_t* key, size_t n) {
    uint8_t k[Sha256::kBlockBytes] = {0};
    if (n > Sha256::kBlockBytes) {
      Sha256 h;
      h.update(key, n);
      h.finish(k);
    } else if (n) {
      for (size_t i = 0; i < n; ++i) k[i] = key[i];
    }
    uint8_t pad[Sha256::kBlockBytes];
    for (size_t i = 0; i < sizeof pad; ++i) pad[i] = static_cast<uint8_t>(k[i] ^ 0x36);
    inner_.reset();
    inner_.update(pad, sizeof pad);
    for (size_t i = 0; i < sizeof pad; ++i) pad[i] = static_cast<uint8_t>(k[i] ^ 0x5c);
    outer_.reset();
    outer_.update(pad, sizeof pad);
  }

  void mac(const uint8_t* data, size_t n, uint8_t out[Sha256::kDigestBytes]) const {
    Sha256 in = inner_;
    in.update(data, n);
    uint8_t inner_digest[Sha256::kDigestBytes];
    in.finish(inner_digest);
    Sha256 out_h = outer_;
    out_h.update(inner_digest, sizeof inner_digest);
    out_h.finish(out);
  }

 private:
  Sha256 inner_;
  Sha256 outer_;
};

/// The session key: signs outgoing datagrams and verifies incoming ones (SPEC 4.2, 4.3).
class Tagger {
 public:
  Tagger(const uint8_t* key, size_t n) : hmac_(key, n) {}

  /// Writes the tag over `datagram[0 : n-16]` into its last 16 bytes.
  void sign(uint8_t* datagram, size_t n) const {
    if (n < kTagBytes + 2) return;
    uint8_t mac[Sha256::kDigestBytes];
    hmac_.mac(datagram, n - kTagBytes, mac);
    for (size_t i = 0; i < kTagBytes; ++i) datagram[n - kTagBytes + i] = mac[i];
  }

  /// True iff the datagram ends in a bin 8 tag (`c4 10` + 16 bytes) that this key made.
  // Not named `verify`: Unreal defines a function-like macro of that name.
  bool verify_tag(const uint8_t* datagram, size_t n) const {
    if (n < kTagBytes + 2) return false;
    if (datagram[n - 18] != 0xc4 || datagram[n - 17] != 0x10) return false;
    uint8_t mac[Sha256::kDigestBytes];
    hmac_.mac(datagram, n - kTagBytes, mac);
    return constant_time_equal(mac, datagram + n - kTagBytes, kTagBytes);
  }

 private:
  HmacSha256 hmac_;
};

inline int hex_digit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

/// Hex text to bytes; false on an odd length or a non-hex digit.
inline bool parse_hex(const std::string& hex, std::vector<uint8_t>& out) {
  if (hex.size() % 2) return false;
  out.clear();
  out.reserve(hex.size() / 2);
  for (size_t i = 0; i < hex.size(); i += 2) {
    int hi = hex_digit(hex[i]), lo = hex_digit(hex[i + 1]);
    if (hi < 0 || lo < 0) return false;
    out.push_back(static_cast<uint8_t>(hi * 16 + lo));
  }
  return true;
}

inline std::string to_hex(const uint8_t* data, size_t n) {
  static const char* digits = "0123456789abcdef";
  std::string s;
  s.reserve(2 * n);
  for (size_t i = 0; i < n; ++i) {
    s.push_back(digits[data[i] >> 4]);
    s.push_back(digits[data[i] & 15]);
  }
  return s;
}

}  // namespace burrforce
