// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// A connected UDP socket (POSIX or Winsock): send a datagram, receive without blocking, wait
// until readable. connect() makes the kernel deliver only the server's datagrams to it.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#ifdef _WIN32
#ifndef WIN32_LEAN_AND_MEAN
#define WIN32_LEAN_AND_MEAN
#endif
#include <winsock2.h>
#include <ws2tcpip.h>
#include <mstcpip.h>
#else
#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <time.h>
#include <sys/socket.h>
#include <sys/types.h>
#include <unistd.h>
#endif

namespace burrforce {

#ifdef _WIN32
using socket_t = SOCKET;
constexpr socket_t kNoSocket = INVALID_SOCKET;
namespace detail {
/// Winsock needs WSAStartup once per process before any socket call.
inline void net_init() {
  static const bool done = [] {
    WSADATA data;
    return WSAStartup(MAKEWORD(2, 2), &data) == 0;
  }();
  if (!done) throw std::runtime_error("WSAStartup failed");
}
inline void close_socket(socket_t s) { closesocket(s); }
inline int last_error() { return WSAGetLastError(); }
inline bool connect_to(socket_t s, const addrinfo* a) {
  return ::connect(s, a->ai_addr, static_cast<int>(a->ai_addrlen)) == 0;
}
}  // namespace detail
#else
using socket_t = int;
constexpr socket_t kNoSocket = -1;
namespace detail {
inline void net_init() {}
inline void close_socket(socket_t s) { ::close(s); }
inline int last_error() { return errno; }
inline bool connect_to(socket_t s, const addrinfo* a) {
  return ::connect(s, a->ai_addr, a->ai_addrlen) == 0;
}
}  // namespace detail
#endif

namespace detail {
inline bool is_loopback(const addrinfo* a) {
  if (a->ai_family == AF_INET) {
    const auto* in = reinterpret_cast<const sockaddr_in*>(a->ai_addr);
    return (ntohl(in->sin_addr.s_addr) >> 24) == 127;
  }
  if (a->ai_family == AF_INET6) {
    const auto* in6 = reinterpret_cast<const sockaddr_in6*>(a->ai_addr);
    static const unsigned char one[16] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1};
    return std::equal(one, one + 16, reinterpret_cast<const unsigned char*>(&in6->sin6_addr));
  }
  return false;
}

/// getaddrinfo's answers in the order to try them. A name that resolves only to loopback
/// addresses ("localhost") puts IPv4 first: Windows lists ::1 first, while the server binds
/// 127.0.0.1 by default, and a UDP connect() to ::1 succeeds although nothing listens there.
inline std::vector<const addrinfo*> connect_order(const addrinfo* res) {
  std::vector<const addrinfo*> out;
  bool all_loopback = true;
  for (const addrinfo* a = res; a; a = a->ai_next) {
    out.push_back(a);
    all_loopback = all_loopback && is_loopback(a);
  }
  if (all_loopback)
    std::stable_partition(out.begin(), out.end(),
                          [](const addrinfo* a) { return a->ai_family == AF_INET; });
  return out;
}
}  // namespace detail

class UdpSocket {
 public:
  UdpSocket() = default;
  UdpSocket(const std::string& host, uint16_t port) { open(host, port); }
  ~UdpSocket() { close(); }
  UdpSocket(const UdpSocket&) = delete;
  UdpSocket& operator=(const UdpSocket&) = delete;
  UdpSocket(UdpSocket&& o) noexcept : fd_(o.fd_), family_(o.family_) { o.fd_ = kNoSocket; }
  UdpSocket& operator=(UdpSocket&& o) noexcept {
    if (this != &o) {
      close();
      fd_ = o.fd_;
      family_ = o.family_;
      o.fd_ = kNoSocket;
    }
    return *this;
  }

  /// Resolves `host` (IPv4 or IPv6, name or literal) and connects to the first address
  /// that takes a socket; for a loopback-only name (localhost) an IPv4 one first.
  void open(const std::string& host, uint16_t port) {
    close();
    detail::net_init();
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_DGRAM;
    addrinfo* res = nullptr;
    std::string service = std::to_string(port);
    int rc = getaddrinfo(host.c_str(), service.c_str(), &hints, &res);
    if (rc != 0 || !res) throw std::runtime_error("cannot resolve UDP host " + host);
    for (const addrinfo* a : detail::connect_order(res)) {
      socket_t s = ::socket(a->ai_family, a->ai_socktype, a->ai_protocol);
      if (s == kNoSocket) continue;
      if (detail::connect_to(s, a)) {
        fd_ = s;
        family_ = a->ai_family;
        break;
      }
      detail::close_socket(s);
    }
    freeaddrinfo(res);
    if (fd_ == kNoSocket) throw std::runtime_error("cannot open a UDP socket to " + host);
#ifdef _WIN32
    u_long nonblocking = 1;
    ioctlsocket(fd_, FIONBIO, &nonblocking);
    // Windows reports an ICMP port-unreachable as WSAECONNRESET on the next recv and would
    // otherwise make a restarting server look like a broken socket.
    BOOL report = FALSE;
    DWORD bytes = 0;
    WSAIoctl(fd_, SIO_UDP_CONNRESET, &report, sizeof report, nullptr, 0, &bytes, nullptr,
             nullptr);
#else
    fcntl(fd_, F_SETFL, fcntl(fd_, F_GETFL, 0) | O_NONBLOCK);
#endif
  }

  void close() {
    if (fd_ != kNoSocket) detail::close_socket(fd_);
    fd_ = kNoSocket;
  }
  bool is_open() const { return fd_ != kNoSocket; }
  /// AF_INET or AF_INET6: the address family connected to.
  int family() const { return family_; }

  /// True if the whole datagram went out (a full send buffer or an ICMP error drops it:
  /// UDP gives no other guarantee anyway).
  bool send(const uint8_t* data, size_t n) {
    if (fd_ == kNoSocket) return false;
#ifdef _WIN32
    int sent = ::send(fd_, reinterpret_cast<const char*>(data), static_cast<int>(n), 0);
#else
    ssize_t sent = ::send(fd_, data, n, 0);
#endif
    return sent == static_cast<decltype(sent)>(n);
  }

  /// One datagram if one is waiting: its size, or -1 if none. Pass a capacity one byte
  /// larger than the largest datagram you accept: a larger datagram then reports a size
  /// above your limit (exactly `capacity` + 1 on Linux and Windows).
  long receive(uint8_t* buffer, size_t capacity) {
    if (fd_ == kNoSocket) return -1;
    for (;;) {
#ifdef _WIN32
      int n = ::recv(fd_, reinterpret_cast<char*>(buffer), static_cast<int>(capacity), 0);
      if (n < 0 && WSAGetLastError() == WSAEMSGSIZE) return static_cast<long>(capacity) + 1;
#elif defined(__linux__)
      // MSG_TRUNC: the real length of an oversized datagram, so the caller rejects it.
      ssize_t n = ::recv(fd_, buffer, capacity, MSG_DONTWAIT | MSG_TRUNC);
      if (n > static_cast<ssize_t>(capacity)) return static_cast<long>(capacity) + 1;
#else
      // An oversized datagram is cut to `capacity`: callers pass one byte more than they
      // accept, so it is still rejected.
      ssize_t n = ::recv(fd_, buffer, capacity, MSG_DONTWAIT);
#endif
      if (n >= 0) return static_cast<long>(n);
      int e = detail::last_error();
#ifdef _WIN32
      if (e == WSAECONNRESET) continue;  // an ICMP error of an earlier send
#else
      if (e == ECONNREFUSED) continue;  // nothing listens (yet): not this datagram's fault
      if (e == EINTR) continue;
#endif
      return -1;
    }
  }

  /// Waits up to `timeout_us` for a datagram; true if one is waiting.
  bool wait_readable(int64_t timeout_us) {
    if (fd_ == kNoSocket) return false;
    if (timeout_us < 0) timeout_us = 0;
#ifdef _WIN32
    WSAPOLLFD p{};
    p.fd = fd_;
    p.events = POLLRDNORM;
    // Round down, as poll() below: WSAPoll sleeps in timer periods (1 ms at best, 15.6 ms
    // unless the process raised the resolution with timeBeginPeriod), so a sub-millisecond
    // wait must not sleep at all; the caller spins the rest. At 1 kHz every wait is below
    // 1 ms and the stream thread never sleeps in WSAPoll.
    int ms = static_cast<int>(timeout_us / 1000);
    return WSAPoll(&p, 1, ms) > 0;
#elif defined(__linux__)
    // ppoll: µs resolution, so a 1 kHz loop can sleep on the socket between ticks.
    pollfd p{};
    p.fd = fd_;
    p.events = POLLIN;
    timespec ts{static_cast<time_t>(timeout_us / 1000000),
                static_cast<long>((timeout_us % 1000000) * 1000)};
    return ::ppoll(&p, 1, &ts, nullptr) > 0;
#else
    // poll() has ms resolution: round down so a 1 kHz loop is never made late; the caller
    // spins the rest.
    pollfd p{};
    p.fd = fd_;
    p.events = POLLIN;
    int ms = static_cast<int>(timeout_us / 1000);
    return ::poll(&p, 1, ms) > 0;
#endif
  }

 private:
  socket_t fd_ = kNoSocket;
  int family_ = 0;
};

}  // namespace burrforce
