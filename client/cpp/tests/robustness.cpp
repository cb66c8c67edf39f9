// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The SDK's behaviour at the edges, against a live server: a throwing PoseSource or callback
// ends the stream (not the process) with zero force; restart_stream() in publish mode gets
// a new stream, answered although no new pose is published; rtt_us is measured from the
// send, not the pose's sample time; a stale coupled state clears the proxy too; MeshSync
// backs off when an announced version is never reached and does not poll before the first
// REPLY; the HTTP client decodes chunked trailers, rejects a bad Content-Length as
// RestError and bounds a connect that is never answered.
// Usage: robustness --url HTTP_URL --token TOKEN; prints one JSON line.
#include <atomic>
#include <chrono>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <thread>

#include "burrforce/burrforce.hpp"
#include "test_util.hpp"

using namespace burrforce;

namespace {

const char* tf(bool b) { return b ? "true" : "false"; }

StreamerConfig config_for(const SessionInfo& s) {
  StreamerConfig cfg;
  cfg.host = s.udp_host;
  cfg.port = s.udp_port;
  cfg.session = s.id;
  cfg.key = s.key;
  return cfg;
}

ToolPose pose_at(const Vec3& p) {
  ToolPose t;
  t.position = p;
  t.orientation = {0, 0, 0, 1};
  t.rpm = 60000.0;
  t.spindle_on = true;
  return t;
}

void sleep_ms(int ms) { std::this_thread::sleep_for(std::chrono::milliseconds(ms)); }

/// A one-shot HTTP server on 127.0.0.1: accepts one connection, reads the request head and
/// answers `response` as is. The SDK's client against real sockets, with answers a FastAPI
/// server would not give.
class CannedServer {
 public:
  explicit CannedServer(std::string response) : response_(std::move(response)) {
    fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    a.sin_port = 0;
    if (::bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 || ::listen(fd_, 4) != 0)
      throw std::runtime_error("canned server: bind/listen");
    socklen_t len = sizeof a;
    ::getsockname(fd_, reinterpret_cast<sockaddr*>(&a), &len);
    port_ = ntohs(a.sin_port);
    thread_ = std::thread([this] {
      int c = ::accept(fd_, nullptr, nullptr);
      if (c < 0) return;
      std::string head;
      char buf[4096];
      while (head.find("\r\n\r\n") == std::string::npos) {
        ssize_t n = ::recv(c, buf, sizeof buf, 0);
        if (n <= 0) break;
        head.append(buf, static_cast<size_t>(n));
      }
      // Byte by byte: the client must assemble the body across many reads.
      for (char ch : response_) ::send(c, &ch, 1, MSG_NOSIGNAL);
      ::close(c);
    });
  }
  ~CannedServer() {
    ::shutdown(fd_, SHUT_RDWR);
    ::close(fd_);
    if (thread_.joinable()) thread_.join();
  }
  std::string url() const { return "http://127.0.0.1:" + std::to_string(port_); }

 private:
  std::string response_;
  int fd_ = -1;
  uint16_t port_ = 0;
  std::thread thread_;
};

}  // namespace

int main(int argc, char** argv) {
  auto o = testutil::options(argc, argv);
  const std::string url = testutil::need(o, "url"), token = testutil::need(o, "token");
  std::ostringstream out;
  out << "{\"ok\": true";
  std::vector<uint32_t> sessions;
  Rest rest(url, token);
  try {
    SessionInfo s = rest.create_session("phantom:workpiece", "si_mm");
    sessions.push_back(s.id);
    out << ", \"session\": " << s.id;
    const Vec3 above{3.0, 0.0, 5.0};  // 5 mm over the workpiece's top face: no contact

    // 1. A PoseSource that throws: the stream ends, the failure is kept, force is zero.
    {
      StreamerConfig cfg = config_for(s);
      Streamer st(cfg);
      st.set_pose_source([&](uint64_t tick, int64_t, ToolPose& p) {
        // From tick 200 on, not at it: a loaded machine's streamer may skip that very tick.
        if (tick >= 200) throw std::runtime_error("physics blew up");
        p = pose_at(above);
        return true;
      });
      st.start();
      bool finished = st.wait_finished(5000000);
      HapticState h = st.state();
      out << ", \"source_throws\": {\"finished\": " << tf(finished)
          << ", \"failed\": " << tf(st.failed()) << ", \"failure\": " << json::quote(st.failure())
          << ", \"running\": " << tf(st.running()) << ", \"valid\": " << tf(h.valid)
          << ", \"replies\": " << st.counters().replies.load() << "}";
    }
    // ... and an on_reply callback that throws.
    {
      Streamer st(config_for(s));
      st.on_reply([](const Event&) { throw std::logic_error("callback bug"); });
      st.start();
      st.publish(pose_at(above));
      bool finished = st.wait_finished(5000000);
      out << ", \"callback_throws\": {\"finished\": " << tf(finished)
          << ", \"failed\": " << tf(st.failed()) << ", \"failure\": " << json::quote(st.failure())
          << ", \"valid\": " << tf(st.state().valid) << "}";
    }

    // 2. Publish mode: one pose, stamped 30 ms before it is published (an engine frame's
    //    age). rtt_us is the network round trip; sample_rtt_us (SPEC 5.5) includes the age.
    //    Then restart_stream() without publishing again: a hello, a new stream, and REPLYs
    //    resume (the held pose's t_client_us repeats: a new stream does not care).
    {
      Streamer st(config_for(s));
      st.start();
      ToolPose p = pose_at(above);
      p.t_sampled_us = now_us() - 30000;
      st.publish(p);
      sleep_ms(300);
      HapticState h = st.state();
      uint64_t before = st.counters().replies.load();
      const uint32_t stream_before = st.stream();
      st.restart_stream();
      sleep_ms(300);
      uint64_t after = st.counters().replies.load();
      HapticState h2 = st.state();
      st.stop();
      out << ", \"publish\": {\"valid\": " << tf(h.valid) << ", \"rtt_us\": " << h.rtt_us
          << ", \"sample_rtt_us\": " << h.sample_rtt_us
          << ", \"replies_before_restart\": " << before
          << ", \"replies_after_restart\": " << after - before
          << ", \"valid_after_restart\": " << tf(h2.valid)
          << ", \"stream_before_restart\": " << stream_before
          << ", \"stream_after_restart\": " << st.stream() << "}";
    }

    // 3. Coupled output (a device profile): the proxy is set while REPLYs arrive, and goes
    //    to zero with everything else once they stop (staleness).
    {
      SessionInfo c = rest.create_session("phantom:workpiece", "si_mm", "\"device\": \"generic\"");
      sessions.push_back(c.id);
      Streamer st(config_for(c));
      st.start();
      st.publish(pose_at(above));
      sleep_ms(300);
      HapticState live = st.state();
      st.stop();
      sleep_ms(120);  // > stale_after_us
      HapticState stale = st.state();
      out << ", \"coupled\": {\"valid\": " << tf(live.valid)
          << ", \"stiffness\": " << live.coupling_stiffness
          << ", \"proxy_norm\": " << norm(live.proxy_position)
          << ", \"stale_valid\": " << tf(stale.valid)
          << ", \"stale_proxy_norm\": " << norm(stale.proxy_position)
          << ", \"stale_stiffness\": " << stale.coupling_stiffness << "}";
    }

    // 4. MeshSync: a version that is never reached (lost final REPLYs, a lagging mesh) is
    //    retried with a back-off; a version source still at 0 (no REPLY yet) costs nothing
    //    after the first full copy.
    {
      MeshSyncConfig mc;
      mc.session = s.id;
      MeshSync never(rest, mc, [] { return uint64_t(1) << 40; });
      MeshSync idle(rest, mc, [] { return uint64_t(0); });
      never.start();
      idle.start();
      if (!never.wait_for_version(0, 60000) || !idle.wait_for_version(0, 60000))
        throw std::runtime_error("no first mesh in 60 s");
      uint64_t never0 = never.updates(), idle0 = idle.updates();
      sleep_ms(2000);
      uint64_t never_extra = never.updates() - never0, idle_extra = idle.updates() - idle0;
      auto t0 = std::chrono::steady_clock::now();
      never.request_stop();
      idle.request_stop();
      double stop_request_ms =
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      out << ", \"mesh_poll\": {\"never_reached_updates_in_2s\": " << never_extra
          << ", \"fruitless\": " << never.fruitless() << ", \"idle_updates_in_2s\": " << idle_extra
          << ", \"errors\": " << never.errors() + idle.errors()
          << ", \"request_stop_ms\": " << stop_request_ms << "}";
    }

    // 5. Loopback names go to IPv4, where the server listens.
    {
      UdpSocket u("localhost", s.udp_port);
      StreamerConfig cfg = config_for(s);
      cfg.host = "localhost";
      Streamer st(cfg);
      st.start();
      st.publish(pose_at(above));
      sleep_ms(200);
      st.stop();
      out << ", \"localhost\": {\"ipv4\": " << tf(u.family() == AF_INET)
          << ", \"replies\": " << st.counters().replies.load() << "}";
    }
  } catch (const std::exception& e) {
    out << ", \"error\": " << json::quote(e.what());
  }

  // 6. HTTP edge cases over real sockets.
  try {
    CannedServer chunked(
        "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
        "5\r\n{\"a\":\r\n3;x=y\r\n 42\r\n1\r\n}\r\n0\r\nX-Trailer: 1\r\n\r\n");
    json::Value v = Rest(chunked.url(), "t").call("GET", "/x");
    out << ", \"chunked_trailer_value\": " << v["a"].as_int();
  } catch (const std::exception& e) {
    out << ", \"chunked_trailer_error\": " << json::quote(e.what());
  }
  {
    CannedServer bad("HTTP/1.1 200 OK\r\nContent-Length: 12abc\r\n\r\n{}");
    std::string kind;
    try {
      Rest(bad.url(), "t").call("GET", "/x");
      kind = "none";
    } catch (const RestError&) {
      kind = "RestError";
    } catch (const std::exception& e) {
      kind = std::string("other: ") + e.what();
    }
    out << ", \"bad_content_length\": " << json::quote(kind);
  }
  {
    // A listener whose accept queue is full never completes a handshake: the connect must
    // give up at the request's timeout.
    int l = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ::bind(l, reinterpret_cast<sockaddr*>(&a), sizeof a);
    ::listen(l, 0);
    socklen_t len = sizeof a;
    ::getsockname(l, reinterpret_cast<sockaddr*>(&a), &len);
    std::vector<int> fillers;
    for (int i = 0; i < 8; ++i) {  // fill the queue (its length is the kernel's choice)
      int f = ::socket(AF_INET, SOCK_STREAM, 0);
      ::fcntl(f, F_SETFL, O_NONBLOCK);
      ::connect(f, reinterpret_cast<sockaddr*>(&a), sizeof a);
      fillers.push_back(f);
    }
    http::Url u = http::Url::parse("http://127.0.0.1:" + std::to_string(ntohs(a.sin_port)));
    http::Request req;
    req.target = "/";
    req.timeout_ms = 500;
    auto t0 = std::chrono::steady_clock::now();
    std::string what;
    try {
      http::send(u, req);
      what = "answered";
    } catch (const http::Error& e) {
      what = e.what();
    }
    double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    for (int f : fillers) ::close(f);
    ::close(l);
    out << ", \"unanswered_connect\": {\"ms\": " << ms << ", \"error\": " << json::quote(what)
        << "}";
  }

  for (uint32_t id : sessions) {
    try {
      rest.delete_session(id);
    } catch (const std::exception&) {
    }
  }
  out << "}";
  std::cout << out.str() << std::endl;
  return 0;
}
