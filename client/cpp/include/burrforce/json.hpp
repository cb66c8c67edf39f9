// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// A small strict JSON reader (RFC 8259) for the REST plane's answers and connection files,
// plus the string escaping a writer needs. Numbers keep their text: integers convert exactly
// (ids, versions) and floats parse locale-independently to the nearest float64.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <locale>
#include <map>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace burrforce {
namespace json {

class ParseError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class Value {
 public:
  enum class Kind { Null, Bool, Number, String, Array, Object };

  Value() = default;

  Kind kind() const { return kind_; }
  bool is_null() const { return kind_ == Kind::Null; }
  bool is_number() const { return kind_ == Kind::Number; }
  bool is_string() const { return kind_ == Kind::String; }
  bool is_object() const { return kind_ == Kind::Object; }
  bool is_array() const { return kind_ == Kind::Array; }

  bool as_bool() const {
    expect(Kind::Bool, "a boolean");
    return bool_;
  }
  const std::string& as_string() const {
    expect(Kind::String, "a string");
    return text_;
  }
  double as_double() const {
    expect(Kind::Number, "a number");
    std::istringstream in(text_);
    in.imbue(std::locale::classic());
    double v = 0;
    in >> v;
    // Out-of-range text ("1e400") sets failbit and leaves DBL_MAX: a silent clamp would
    // turn a server bug into a plausible huge number.
    if (in.fail() || !std::isfinite(v)) throw ParseError("number out of range: " + text_);
    return v;
  }
  int64_t as_int() const {
    expect(Kind::Number, "a number");
    size_t i = 0;
    bool neg = text_[0] == '-';
    if (neg) i = 1;
    uint64_t v = 0;
    for (; i < text_.size(); ++i) {
      char c = text_[i];
      if (c < '0' || c > '9') throw ParseError("not an integer: " + text_);
      if (v > (UINT64_MAX - 9) / 10) throw ParseError("integer out of range: " + text_);
      v = v * 10 + static_cast<uint64_t>(c - '0');
    }
    if (v > static_cast<uint64_t>(INT64_MAX)) throw ParseError("integer out of range: " + text_);
    return neg ? -static_cast<int64_t>(v) : static_cast<int64_t>(v);
  }
  const std::vector<Value>& as_array() const {
    expect(Kind::Array, "an array");
    return items_;
  }
  const std::map<std::string, Value>& as_object() const {
    expect(Kind::Object, "an object");
    return *fields_;
  }
  bool has(const std::string& key) const {
    return kind_ == Kind::Object && fields_->count(key) != 0;
  }
  const Value& operator[](const std::string& key) const {
    expect(Kind::Object, "an object");
    auto it = fields_->find(key);
    if (it == fields_->end()) throw ParseError("missing field \"" + key + "\"");
    return it->second;
  }
  const Value& operator[](size_t i) const {
    expect(Kind::Array, "an array");
    if (i >= items_.size()) throw ParseError("index out of range");
    return items_[i];
  }
  size_t size() const { return kind_ == Kind::Array ? items_.size()
                               : kind_ == Kind::Object ? fields_->size() : 0; }
  /// The number's text as written (for an exact round trip).
  const std::string& number_text() const {
    expect(Kind::Number, "a number");
    return text_;
  }

 private:
  friend class Parser;
  void expect(Kind k, const char* what) const {
    if (kind_ != k) throw ParseError(std::string("JSON value is not ") + what);
  }

  Kind kind_ = Kind::Null;
  bool bool_ = false;
  std::string text_;
  std::vector<Value> items_;
  std::shared_ptr<std::map<std::string, Value>> fields_;
};

class Parser {
 public:
  static constexpr int kMaxDepth = 64;

  explicit Parser(const std::string& text) : s_(text) {}

  Value parse() {
    Value v = value(0);
    ws();
    if (i_ != s_.size()) error("trailing characters");
    return v;
  }

 private:
  [[noreturn]] void error(const std::string& what) const {
    throw ParseError("JSON: " + what + " at offset " + std::to_string(i_));
  }
  void ws() {
    while (i_ < s_.size() && (s_[i_] == ' ' || s_[i_] == '\t' || s_[i_] == '\n' ||
                              s_[i_] == '\r'))
      ++i_;
  }
  bool literal(const char* word) {
    size_t n = std::char_traits<char>::length(word);
    if (s_.compare(i_, n, word) != 0) return false;
    i_ += n;
    return true;
  }
  Value value(int depth) {
    if (depth > kMaxDepth) error("nested too deeply");
    ws();
    if (i_ >= s_.size()) error("unexpected end");
    Value v;
    char c = s_[i_];
    if (c == '{') {
      ++i_;
      v.kind_ = Value::Kind::Object;
      v.fields_ = std::make_shared<std::map<std::string, Value>>();
      ws();
      if (i_ < s_.size() && s_[i_] == '}') {
        ++i_;
        return v;
      }
      for (;;) {
        ws();
        if (i_ >= s_.size() || s_[i_] != '"') error("expected a key");
        std::string key = string();
        ws();
        if (i_ >= s_.size() || s_[i_] != ':') error("expected ':'");
        ++i_;
        (*v.fields_)[key] = value(depth + 1);
        ws();
        if (i_ < s_.size() && s_[i_] == ',') {
          ++i_;
          continue;
        }
        if (i_ < s_.size() && s_[i_] == '}') {
          ++i_;
          return v;
        }
        error("expected ',' or '}'");
      }
    }
    if (c == '[') {
      ++i_;
      v.kind_ = Value::Kind::Array;
      ws();
      if (i_ < s_.size() && s_[i_] == ']') {
        ++i_;
        return v;
      }
      for (;;) {
        v.items_.push_back(value(depth + 1));
        ws();
        if (i_ < s_.size() && s_[i_] == ',') {
          ++i_;
          continue;
        }
        if (i_ < s_.size() && s_[i_] == ']') {
          ++i_;
          return v;
        }
        error("expected ',' or ']'");
      }
    }
    if (c == '"') {
      v.kind_ = Value::Kind::String;
      v.text_ = string();
      return v;
    }
    if (literal("true")) {
      v.kind_ = Value::Kind::Bool;
      v.bool_ = true;
      return v;
    }
    if (literal("false")) {
      v.kind_ = Value::Kind::Bool;
      return v;
    }
    if (literal("null")) return v;
    if (c == '-' || (c >= '0' && c <= '9')) {
      v.kind_ = Value::Kind::Number;
      v.text_ = number();
      return v;
    }
    error("unexpected character");
  }
  std::string number() {
    size_t start = i_;
    auto digits = [&] {
      size_t d = i_;
      while (i_ < s_.size() && s_[i_] >= '0' && s_[i_] <= '9') ++i_;
      if (i_ == d) error("expected a digit");
    };
    if (s_[i_] == '-') ++i_;
    if (i_ < s_.size() && s_[i_] == '0')
      ++i_;
    else
      digits();
    if (i_ < s_.size() && s_[i_] == '.') {
      ++i_;
      digits();
    }
    if (i_ < s_.size() && (s_[i_] == 'e' || s_[i_] == 'E')) {
      ++i_;
      if (i_ < s_.size() && (s_[i_] == '+' || s_[i_] == '-')) ++i_;
      digits();
    }
    return s_.substr(start, i_ - start);
  }
  unsigned hex4() {
    if (i_ + 4 > s_.size()) error("short \\u escape");
    unsigned v = 0;
    for (int k = 0; k < 4; ++k) {
      char c = s_[i_++];
      v <<= 4;
      if (c >= '0' && c <= '9') v |= static_cast<unsigned>(c - '0');
      else if (c >= 'a' && c <= 'f') v |= static_cast<unsigned>(c - 'a' + 10);
      else if (c >= 'A' && c <= 'F') v |= static_cast<unsigned>(c - 'A' + 10);
      else error("bad \\u escape");
    }
    return v;
  }
  static void utf8(std::string& out, unsigned cp) {
    if (cp < 0x80) {
      out.push_back(static_cast<char>(cp));
    } else if (cp < 0x800) {
      out.push_back(static_cast<char>(0xC0 | (cp >> 6)));
      out.push_back(static_cast<char>(0x80 | (cp & 0x3F)));
    } else if (cp < 0x10000) {
      out.push_back(static_cast<char>(0xE0 | (cp >> 12)));
      out.push_back(static_cast<char>(0x80 | ((cp >> 6) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | (cp & 0x3F)));
    } else {
      out.push_back(static_cast<char>(0xF0 | (cp >> 18)));
      out.push_back(static_cast<char>(0x80 | ((cp >> 12) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | ((cp >> 6) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | (cp & 0x3F)));
    }
  }
  std::string string() {
    ++i_;  // opening quote
    std::string out;
    for (;;) {
      if (i_ >= s_.size()) error("unterminated string");
      char c = s_[i_++];
      if (c == '"') return out;
      if (static_cast<unsigned char>(c) < 0x20) error("control character in string");
      if (c != '\\') {
        out.push_back(c);
        continue;
      }
      if (i_ >= s_.size()) error("unterminated escape");
      char e = s_[i_++];
      switch (e) {
        case '"': out.push_back('"'); break;
        case '\\': out.push_back('\\'); break;
        case '/': out.push_back('/'); break;
        case 'b': out.push_back('\b'); break;
        case 'f': out.push_back('\f'); break;
        case 'n': out.push_back('\n'); break;
        case 'r': out.push_back('\r'); break;
        case 't': out.push_back('\t'); break;
        case 'u': {
          unsigned cp = hex4();
          if (cp >= 0xD800 && cp < 0xDC00) {
            if (i_ + 2 > s_.size() || s_[i_] != '\\' || s_[i_ + 1] != 'u')
              error("lone surrogate");
            i_ += 2;
            unsigned lo = hex4();
            if (lo < 0xDC00 || lo > 0xDFFF) error("bad surrogate pair");
            cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
          } else if (cp >= 0xDC00 && cp <= 0xDFFF) {
            error("lone surrogate");
          }
          utf8(out, cp);
          break;
        }
        default: error("bad escape");
      }
    }
  }

  const std::string& s_;
  size_t i_ = 0;
};

inline Value parse(const std::string& text) { return Parser(text).parse(); }

/// `s` as a JSON string literal, quotes included.
inline std::string quote(const std::string& s) {
  std::string out = "\"";
  for (char ch : s) {
    const auto c = static_cast<unsigned char>(ch);
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      default:
        if (c < 0x20) {
          static const char* hex = "0123456789abcdef";
          out += "\\u00";
          out.push_back(hex[c >> 4]);
          out.push_back(hex[c & 15]);
        } else {
          out.push_back(static_cast<char>(c));
        }
    }
  }
  return out + "\"";
}

/// A float64 as JSON text that parses back to the same bits (17 significant digits).
inline std::string number(double v) {
  std::ostringstream out;
  out.imbue(std::locale::classic());
  out.precision(17);
  out << v;
  std::string s = out.str();
  if (s == "nan" || s == "inf" || s == "-inf" || s == "-nan") return "null";
  return s;
}

}  // namespace json
}  // namespace burrforce
