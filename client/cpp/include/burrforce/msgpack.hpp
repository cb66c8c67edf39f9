// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The msgpack subset of the burrforce wire protocol (SPEC.md section 2), hand-written because
// no general library writes the canonical form (integral doubles stay `cb` float64).
// Writer: canonical bytes into a caller's buffer. Reader: every form section 2.2 accepts,
// with the limits of section 2.4; every read is bounds-checked and reports failure instead
// of throwing, so garbage from the network can never crash it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>

namespace burrforce {
namespace msgpack {

constexpr uint32_t kMaxArray = 32;   // SPEC 2.4
constexpr uint32_t kMaxBinStr = 64;  // SPEC 2.4

/// Writes canonical msgpack into a fixed buffer; `ok()` turns false (and stays false) when
/// the buffer is too small, so callers check once at the end.
class Writer {
 public:
  Writer(uint8_t* buffer, size_t capacity) : buf_(buffer), cap_(capacity) {}

  void array(uint32_t n) {
    if (n <= 15) {
      byte(static_cast<uint8_t>(0x90 | n));
    } else if (n <= 0xFFFF) {
      byte(0xdc);
      be(n, 2);
    } else {
      byte(0xdd);
      be(n, 4);
    }
  }
  /// Smallest unsigned form, never a signed one (SPEC 2.3).
  void uint(uint64_t v) {
    if (v <= 0x7F) {
      byte(static_cast<uint8_t>(v));
    } else if (v <= 0xFF) {
      byte(0xcc);
      be(v, 1);
    } else if (v <= 0xFFFF) {
      byte(0xcd);
      be(v, 2);
    } else if (v <= 0xFFFFFFFFull) {
      byte(0xce);
      be(v, 4);
    } else {
      byte(0xcf);
      be(v, 8);
    }
  }
  /// Always float 64, even for integral values and -0.0 (SPEC 2.3).
  void f64(double v) {
    uint64_t bits;
    std::memcpy(&bits, &v, sizeof bits);
    byte(0xcb);
    be(bits, 8);
  }
  void vec(const double* v, int n) {
    array(static_cast<uint32_t>(n));
    for (int i = 0; i < n; ++i) f64(v[i]);
  }
  void boolean(bool b) { byte(b ? 0xc3 : 0xc2); }
  void nil() { byte(0xc0); }
  void bin8(const uint8_t* data, uint8_t n) {
    byte(0xc4);
    byte(n);
    raw(data, n);
  }
  void raw(const uint8_t* data, size_t n) {
    if (!ok_ || n > cap_ - len_) {
      ok_ = false;
      return;
    }
    if (n) std::memcpy(buf_ + len_, data, n);
    len_ += n;
  }

  bool ok() const { return ok_; }
  size_t size() const { return len_; }
  uint8_t* data() { return buf_; }

 private:
  void byte(uint8_t b) {
    if (!ok_ || len_ >= cap_) {
      ok_ = false;
      return;
    }
    buf_[len_++] = b;
  }
  void be(uint64_t v, int n) {
    for (int i = n - 1; i >= 0; --i) byte(static_cast<uint8_t>(v >> (8 * i)));
  }

  uint8_t* buf_;
  size_t cap_;
  size_t len_ = 0;
  bool ok_ = true;
};

/// A cursor over one datagram. Each read either succeeds and advances, or returns false
/// and leaves `ok()` false: the message is MALFORMED.
class Reader {
 public:
  Reader(const uint8_t* data, size_t n) : p_(data), end_(data + n), begin_(data) {}

  bool ok() const { return ok_; }
  bool at_end() const { return p_ == end_; }
  size_t offset() const { return static_cast<size_t>(p_ - begin_); }

  /// Any array header (fixarray, array 16, array 32) up to kMaxArray elements.
  bool array(uint32_t& n) {
    uint8_t b;
    if (!peek(b)) return fail();
    if ((b & 0xF0) == 0x90) {
      ++p_;
      n = b & 0x0F;
    } else if (b == 0xdc || b == 0xdd) {
      ++p_;
      uint64_t v;
      if (!be(v, b == 0xdc ? 2 : 4)) return fail();
      n = static_cast<uint32_t>(v);
    } else {
      return fail();
    }
    return n <= kMaxArray ? true : fail();
  }

  /// Any integer form; `negative` tells a signed form's negative value apart.
  bool integer(uint64_t& magnitude, bool& negative) {
    uint8_t b;
    if (!peek(b)) return fail();
    negative = false;
    if (b <= 0x7F) {
      ++p_;
      magnitude = b;
      return true;
    }
    if (b >= 0xE0) {  // negative fixint
      ++p_;
      negative = true;
      magnitude = static_cast<uint64_t>(256 - b);
      return true;
    }
    if (b >= 0xcc && b <= 0xcf) {
      ++p_;
      return be(magnitude, 1 << (b - 0xcc)) ? true : fail();
    }
    if (b >= 0xd0 && b <= 0xd3) {
      ++p_;
      int n = 1 << (b - 0xd0);
      uint64_t raw;
      if (!be(raw, n)) return fail();
      // Sign-extend from n bytes.
      int shift = 64 - 8 * n;
      int64_t v = static_cast<int64_t>(raw << shift) >> shift;
      negative = v < 0;
      magnitude = negative ? (~static_cast<uint64_t>(v) + 1) : static_cast<uint64_t>(v);
      return true;
    }
    return fail();
  }

  /// An unsigned integer no larger than `max` (a negative value fails).
  bool uint(uint64_t& v, uint64_t max) {
    bool neg;
    uint64_t m;
    if (!integer(m, neg)) return false;
    if (neg && m != 0) return fail();
    if (m > max) return fail();
    v = m;
    return true;
  }

  /// A float field: float 64, float 32 or any integer (SPEC 2.2). bool/nil/str fail.
  bool number(double& v) {
    uint8_t b;
    if (!peek(b)) return fail();
    if (b == 0xcb) {
      ++p_;
      uint64_t bits;
      if (!be(bits, 8)) return fail();
      std::memcpy(&v, &bits, sizeof v);
      return true;
    }
    if (b == 0xca) {
      ++p_;
      uint64_t bits;
      if (!be(bits, 4)) return fail();
      uint32_t b32 = static_cast<uint32_t>(bits);
      float f;
      std::memcpy(&f, &b32, sizeof f);
      v = static_cast<double>(f);
      return true;
    }
    uint64_t m;
    bool neg;
    if (!integer(m, neg)) return false;
    v = neg ? -static_cast<double>(m) : static_cast<double>(m);
    return true;
  }

  bool vec(double* out, uint32_t n) {
    uint32_t got;
    if (!array(got)) return false;
    if (got != n) return fail();
    for (uint32_t i = 0; i < n; ++i)
      if (!number(out[i])) return false;
    return true;
  }

  bool boolean(bool& v) {
    uint8_t b;
    if (!peek(b)) return fail();
    if (b != 0xc2 && b != 0xc3) return fail();
    ++p_;
    v = b == 0xc3;
    return true;
  }

  /// True (and consumed) if the next element is nil.
  bool take_nil() {
    uint8_t b;
    if (ok_ && peek(b) && b == 0xc0) {
      ++p_;
      return true;
    }
    return false;
  }

  /// Any bin form up to kMaxBinStr bytes; `data` points into the datagram.
  bool bin(const uint8_t*& data, uint32_t& n) {
    uint8_t b;
    if (!peek(b)) return fail();
    if (b < 0xc4 || b > 0xc6) return fail();
    ++p_;
    uint64_t len;
    if (!be(len, 1 << (b - 0xc4))) return fail();
    if (len > kMaxBinStr || len > static_cast<uint64_t>(end_ - p_)) return fail();
    data = p_;
    n = static_cast<uint32_t>(len);
    p_ += len;
    return true;
  }

 private:
  bool peek(uint8_t& b) const {
    if (!ok_ || p_ >= end_) return false;
    b = *p_;
    return true;
  }
  bool be(uint64_t& v, int n) {
    if (static_cast<ptrdiff_t>(n) > end_ - p_) return false;
    v = 0;
    for (int i = 0; i < n; ++i) v = (v << 8) | p_[i];
    p_ += n;
    return true;
  }
  bool fail() {
    ok_ = false;
    return false;
  }

  const uint8_t* p_;
  const uint8_t* end_;
  const uint8_t* begin_;
  bool ok_ = true;
};

}  // namespace msgpack
}  // namespace burrforce
