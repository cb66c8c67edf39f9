// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// A minimal blocking HTTP/1.1 client over plain sockets for the REST plane: one request per
// connection (Connection: close), Content-Length, chunked and until-close bodies. The
// request's timeout bounds the connect (all addresses together) and each send and receive;
// name resolution (getaddrinfo) has no portable timeout and takes as long as the OS
// resolver does (instant for literals and hosts-file names, seconds for a dead DNS). No TLS: the REST plane is served on a trusted network (put a
// TLS-terminating proxy and an engine HTTP client in front for anything else). Blocking:
// never call it on the haptic or the render thread.
#pragma once

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <map>
#include <stdexcept>
#include <string>

#include "burrforce/clock.hpp"
#include "burrforce/udp_socket.hpp"  // socket headers, net_init, close_socket, connect_order

namespace burrforce {
namespace http {

class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct Url {
  std::string host;
  uint16_t port = 80;
  std::string path;  ///< prefix, without a trailing slash

  /// "http://host:port/prefix" (IPv6 literals in brackets).
  static Url parse(const std::string& text) {
    const std::string scheme = "http://";
    if (text.compare(0, scheme.size(), scheme) != 0)
      throw Error("only http:// URLs are supported: " + text);
    Url u;
    std::string rest = text.substr(scheme.size());
    size_t slash = rest.find('/');
    std::string authority = rest.substr(0, slash);
    u.path = slash == std::string::npos ? "" : rest.substr(slash);
    while (!u.path.empty() && u.path.back() == '/') u.path.pop_back();
    size_t colon;
    if (!authority.empty() && authority[0] == '[') {
      size_t close = authority.find(']');
      if (close == std::string::npos) throw Error("bad IPv6 literal in " + text);
      u.host = authority.substr(1, close - 1);
      colon = authority.find(':', close);
    } else {
      colon = authority.rfind(':');
      u.host = authority.substr(0, colon);
    }
    if (colon != std::string::npos) {
      long port = std::strtol(authority.c_str() + colon + 1, nullptr, 10);
      if (port <= 0 || port > 65535) throw Error("bad port in " + text);
      u.port = static_cast<uint16_t>(port);
    }
    if (u.host.empty()) throw Error("no host in " + text);
    return u;
  }
  std::string host_header() const {
    std::string h = host.find(':') != std::string::npos ? "[" + host + "]" : host;
    return h + ":" + std::to_string(port);
  }
};

struct Response {
  int status = 0;
  std::string reason;
  std::map<std::string, std::string> headers;  ///< names lower-case
  std::string body;

  bool ok() const { return status >= 200 && status < 300; }
  std::string header(const std::string& lower_name) const {
    auto it = headers.find(lower_name);
    return it == headers.end() ? std::string() : it->second;
  }
};

namespace detail {

class TcpConnection {
 public:
  TcpConnection(const std::string& host, uint16_t port, int timeout_ms) {
    burrforce::detail::net_init();
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* res = nullptr;
    if (getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &res) != 0 || !res)
      throw Error("cannot resolve " + host);
    const int64_t deadline_us = now_us() + static_cast<int64_t>(timeout_ms) * 1000;
    bool timed_out = false;
    for (const addrinfo* a : burrforce::detail::connect_order(res)) {
      socket_t s = ::socket(a->ai_family, a->ai_socktype, a->ai_protocol);
      if (s == kNoSocket) continue;
      set_timeouts(s, timeout_ms);
      int r = connect_before(s, a, deadline_us);
      if (r == 0) {
        fd_ = s;
        break;
      }
      burrforce::detail::close_socket(s);
      if (r < 0) {
        timed_out = true;
        break;
      }
    }
    freeaddrinfo(res);
    if (fd_ == kNoSocket)
      throw Error((timed_out ? "timed out connecting to " : "cannot connect to ") + host + ":" +
                  std::to_string(port));
  }
  ~TcpConnection() {
    if (fd_ != kNoSocket) burrforce::detail::close_socket(fd_);
  }
  TcpConnection(const TcpConnection&) = delete;
  TcpConnection& operator=(const TcpConnection&) = delete;

  void send_all(const std::string& data) {
    size_t off = 0;
    while (off < data.size()) {
#ifdef _WIN32
      int n = ::send(fd_, data.data() + off, static_cast<int>(data.size() - off), 0);
#elif defined(MSG_NOSIGNAL)
      // A server that closed the connection must not kill the process with SIGPIPE.
      ssize_t n = ::send(fd_, data.data() + off, data.size() - off, MSG_NOSIGNAL);
#else
      ssize_t n = ::send(fd_, data.data() + off, data.size() - off, 0);  // SO_NOSIGPIPE set
#endif
      if (n <= 0) throw Error("HTTP send failed or timed out");
      off += static_cast<size_t>(n);
    }
  }
  /// Appends what arrives to `buf`; false at end of stream.
  bool read_some(std::string& buf) {
    char tmp[16384];
#ifdef _WIN32
    int n = ::recv(fd_, tmp, sizeof tmp, 0);
#else
    ssize_t n = ::recv(fd_, tmp, sizeof tmp, 0);
#endif
    if (n < 0) throw Error("HTTP receive failed or timed out");
    if (n == 0) return false;
    buf.append(tmp, static_cast<size_t>(n));
    return true;
  }

 private:
  /// A non-blocking connect waited for until `deadline_us`, then blocking again (reads and
  /// writes have their own timeouts): SO_SNDTIMEO does not bound connect() on Windows (21 s
  /// of SYN retries) nor everywhere else. 0: connected; 1: refused or failed (try the next
  /// address); -1: the deadline passed.
  static int connect_before(socket_t s, const addrinfo* a, int64_t deadline_us) {
#ifdef _WIN32
    u_long on = 1, off = 0;
    ioctlsocket(s, FIONBIO, &on);
    if (::connect(s, a->ai_addr, static_cast<int>(a->ai_addrlen)) != 0) {
      if (WSAGetLastError() != WSAEWOULDBLOCK) return 1;
      int64_t left_us = deadline_us - now_us();
      if (left_us <= 0) return -1;
      // select, not WSAPoll: WSAPoll does not report a refused connect before Windows 10 2004.
      fd_set w, e;
      FD_ZERO(&w);
      FD_ZERO(&e);
      FD_SET(s, &w);
      FD_SET(s, &e);
      timeval tv{static_cast<long>(left_us / 1000000), static_cast<long>(left_us % 1000000)};
      int n = ::select(0, nullptr, &w, &e, &tv);
      if (n == 0) return -1;
      if (n < 0 || FD_ISSET(s, &e)) return 1;
      int err = 0;
      int len = sizeof err;
      if (getsockopt(s, SOL_SOCKET, SO_ERROR, reinterpret_cast<char*>(&err), &len) != 0 || err)
        return 1;
    }
    ioctlsocket(s, FIONBIO, &off);
    return 0;
#else
    int flags = fcntl(s, F_GETFL, 0);
    fcntl(s, F_SETFL, flags | O_NONBLOCK);
    if (::connect(s, a->ai_addr, a->ai_addrlen) != 0) {
      if (errno != EINPROGRESS && errno != EINTR) return 1;
      for (;;) {
        int64_t left_us = deadline_us - now_us();
        if (left_us <= 0) return -1;
        pollfd p{};
        p.fd = s;
        p.events = POLLOUT;
        int n = ::poll(&p, 1, static_cast<int>((left_us + 999) / 1000));
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) return 1;
        if (n == 0) return -1;
        break;
      }
      int err = 0;
      socklen_t len = sizeof err;
      if (getsockopt(s, SOL_SOCKET, SO_ERROR, &err, &len) != 0 || err) return 1;
    }
    fcntl(s, F_SETFL, flags);
    return 0;
#endif
  }

  static void set_timeouts(socket_t s, int timeout_ms) {
#ifdef _WIN32
    DWORD t = static_cast<DWORD>(timeout_ms);
    setsockopt(s, SOL_SOCKET, SO_RCVTIMEO, reinterpret_cast<const char*>(&t), sizeof t);
    setsockopt(s, SOL_SOCKET, SO_SNDTIMEO, reinterpret_cast<const char*>(&t), sizeof t);
#else
    timeval tv{timeout_ms / 1000, (timeout_ms % 1000) * 1000};
    setsockopt(s, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    setsockopt(s, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);
#ifdef SO_NOSIGPIPE
    int one = 1;
    setsockopt(s, SOL_SOCKET, SO_NOSIGPIPE, &one, sizeof one);
#endif
#endif
  }
  socket_t fd_ = kNoSocket;
};

inline std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

inline std::string trim(const std::string& s) {
  size_t a = s.find_first_not_of(" \t"), b = s.find_last_not_of(" \t\r");
  return a == std::string::npos ? std::string() : s.substr(a, b - a + 1);
}

/// Decodes a chunked body (RFC 9112 7.1) as it arrives: each call goes on from where the
/// previous one stopped, so a large body costs linear time however it is split into reads.
class Dechunker {
 public:
  explicit Dechunker(size_t pos) : pos_(pos) {}

  /// Consumes what `raw` holds past the last call; true once the body and its trailers are
  /// complete. Throws Error on a malformed body.
  bool feed(const std::string& raw, std::string& body) {
    for (;;) {
      switch (state_) {
        case State::Size: {
          size_t eol;
          if (!line(raw, eol)) return false;
          std::string size_text = raw.substr(pos_, eol - pos_);
          size_t semi = size_text.find(';');  // chunk extensions are ignored
          if (semi != std::string::npos) size_text.resize(semi);
          size_text = trim(size_text);
          if (size_text.empty() ||
              size_text.find_first_not_of("0123456789abcdefABCDEF") != std::string::npos ||
              size_text.size() > 15)
            throw Error("bad chunk size in HTTP response");
          left_ = static_cast<size_t>(std::strtoull(size_text.c_str(), nullptr, 16));
          pos_ = eol + 2;
          state_ = left_ == 0 ? State::Trailers : State::Data;
          break;
        }
        case State::Data: {
          size_t n = std::min(left_, raw.size() - pos_);
          body.append(raw, pos_, n);
          pos_ += n;
          left_ -= n;
          if (left_ > 0) return false;
          state_ = State::DataEnd;
          break;
        }
        case State::DataEnd:
          if (raw.size() < pos_ + 2) return false;
          if (raw.compare(pos_, 2, "\r\n") != 0)
            throw Error("chunk data not followed by CRLF in HTTP response");
          pos_ += 2;
          state_ = State::Size;
          break;
        case State::Trailers: {  // header lines after the last chunk, up to an empty one
          size_t eol;
          if (!line(raw, eol)) return false;
          bool empty = eol == pos_;
          pos_ = eol + 2;
          if (empty) {
            state_ = State::Done;
            return true;
          }
          break;
        }
        case State::Done:
          return true;
      }
    }
  }

 private:
  enum class State { Size, Data, DataEnd, Trailers, Done };
  static constexpr size_t kMaxLine = 8192;

  /// A whole line from pos_: its CRLF at `eol`. Searched only in what is new since the last
  /// look, so a line trickling in byte by byte is not rescanned.
  bool line(const std::string& raw, size_t& eol) {
    size_t from = std::max(pos_, scanned_ > 0 ? scanned_ - 1 : 0);
    eol = raw.find("\r\n", from);
    if (eol == std::string::npos) {
      scanned_ = raw.size();
      if (raw.size() - pos_ > kMaxLine) throw Error("HTTP chunk line too long");
      return false;
    }
    scanned_ = 0;
    return true;
  }

  size_t pos_;
  size_t scanned_ = 0;
  size_t left_ = 0;
  State state_ = State::Size;
};

/// A Content-Length value: decimal digits only (RFC 9110 8.6).
inline size_t content_length(const std::string& text) {
  if (text.empty() || text.size() > 18 || text.find_first_not_of("0123456789") != std::string::npos)
    throw Error("bad Content-Length in HTTP response: " + text);
  return static_cast<size_t>(std::strtoull(text.c_str(), nullptr, 10));
}

}  // namespace detail

struct Request {
  std::string method = "GET";
  std::string target;  ///< path and query, starting with '/'
  std::map<std::string, std::string> headers;
  std::string body;
  int timeout_ms = 30000;
  size_t max_body_bytes = 256u << 20;
};

/// Sends one request to `url`'s host (its path prefix is prepended to `req.target`).
inline Response send(const Url& url, const Request& req) {
  detail::TcpConnection conn(url.host, url.port, req.timeout_ms);
  std::string head = req.method + " " + url.path + req.target + " HTTP/1.1\r\n";
  head += "Host: " + url.host_header() + "\r\nConnection: close\r\n";
  head += "User-Agent: burrforce-cpp/1\r\n";
  for (const auto& h : req.headers) head += h.first + ": " + h.second + "\r\n";
  if (!req.body.empty() || req.method == "POST" || req.method == "PATCH" ||
      req.method == "PUT")
    head += "Content-Length: " + std::to_string(req.body.size()) + "\r\n";
  head += "\r\n";
  conn.send_all(head + req.body);

  std::string raw;
  size_t header_end;
  while ((header_end = raw.find("\r\n\r\n")) == std::string::npos) {
    if (!conn.read_some(raw)) throw Error("connection closed before the HTTP headers");
    if (raw.size() > (64u << 10)) throw Error("HTTP headers too long");
  }
  Response r;
  std::string status_line = raw.substr(0, raw.find("\r\n"));
  if (status_line.compare(0, 5, "HTTP/") != 0 || status_line.size() < 12)
    throw Error("not an HTTP response: " + status_line);
  r.status = std::atoi(status_line.c_str() + 9);
  r.reason = status_line.size() > 13 ? status_line.substr(13) : "";
  size_t pos = raw.find("\r\n") + 2;
  while (pos < header_end) {
    size_t eol = raw.find("\r\n", pos);
    std::string line = raw.substr(pos, eol - pos);
    size_t colon = line.find(':');
    if (colon != std::string::npos)
      r.headers[detail::lower(detail::trim(line.substr(0, colon)))] =
          detail::trim(line.substr(colon + 1));
    pos = eol + 2;
  }
  size_t body_start = header_end + 4;
  bool no_body = req.method == "HEAD" || r.status == 204 || r.status == 304 ||
                 (r.status >= 100 && r.status < 200);
  if (no_body) return r;
  if (detail::lower(r.header("transfer-encoding")).find("chunked") != std::string::npos) {
    detail::Dechunker dechunker(body_start);
    while (!dechunker.feed(raw, r.body)) {
      if (!conn.read_some(raw)) throw Error("connection closed inside a chunked body");
      if (raw.size() > req.max_body_bytes) throw Error("HTTP body too large");
    }
    return r;
  }
  std::string length = r.header("content-length");
  if (!length.empty()) {
    size_t n = detail::content_length(length);
    if (n > req.max_body_bytes) throw Error("HTTP body too large");
    while (raw.size() < body_start + n)
      if (!conn.read_some(raw)) throw Error("connection closed inside the HTTP body");
    r.body = raw.substr(body_start, n);
    return r;
  }
  while (conn.read_some(raw))
    if (raw.size() > req.max_body_bytes) throw Error("HTTP body too large");
  r.body = raw.substr(body_start);
  return r;
}

/// Percent-encodes a query value.
inline std::string url_encode(const std::string& s) {
  static const char* hex = "0123456789ABCDEF";
  std::string out;
  for (char ch : s) {
    const auto c = static_cast<unsigned char>(ch);
    if (std::isalnum(c) || c == '-' || c == '_' || c == '.' || c == '~') {
      out.push_back(static_cast<char>(c));
    } else {
      out.push_back('%');
      out.push_back(hex[c >> 4]);
      out.push_back(hex[c & 15]);
    }
  }
  return out;
}

}  // namespace http
}  // namespace burrforce
