// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Keeps a ChunkedMesh current over REST (proto/MESH.md section 4) on its own worker thread:
// it polls a bone version (typically Streamer::bone_version(), a lock-free read) and, when
// that rises past the mesh's `have`, fetches `GET /v1/sessions/{id}/mesh?since=have`
// page by page. An announced version the server's mesh does not reach (or a failing
// server) is retried with an exponential back-off, never at the poll rate. The C++ SDK polls instead of using the WebSocket push channel: a WebSocket
// client would double the HTTP code for a gain of one round trip per update, and the REPLY's
// bone_version already says when to ask. Never touches the haptic thread.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "burrforce/mesh.hpp"
#include "burrforce/rest.hpp"

namespace burrforce {

struct MeshSyncConfig {
  uint32_t session = 0;
  int chunk_bricks = 0;            ///< chunk edge in 8-voxel bricks, 1-8; 0: the server's
  std::string winding = "ccw";     ///< "cw" for Unreal and Godot (MESH.md 5)
  std::string frame = "session";   ///< or "server" (mm, server axes)
  int poll_interval_ms = 20;
  /// Longest wait between retries when an update brought nothing new or failed.
  int max_backoff_ms = 1000;
  size_t max_page_bytes = 4u << 20;
};

class MeshSync {
 public:
  using VersionSource = std::function<uint64_t()>;

  MeshSync(Rest rest, MeshSyncConfig cfg, VersionSource version = nullptr)
      : rest_(std::move(rest)), cfg_(std::move(cfg)), version_(std::move(version)) {}
  ~MeshSync() { stop(); }
  MeshSync(const MeshSync&) = delete;
  MeshSync& operator=(const MeshSync&) = delete;

  /// Starts the worker: a first full fetch, then one update whenever the version source
  /// rises past `have`.
  void start() {
    if (thread_.joinable()) return;
    stop_ = false;
    thread_ = std::thread([this] { run(); });
  }
  /// Stops the worker and waits for it: up to a whole HTTP request (Request::timeout_ms)
  /// if one is under way. Callers that must not block call request_stop() and leave the
  /// destruction (which joins) to a thread that may wait.
  void stop() {
    request_stop();
    if (thread_.joinable()) thread_.join();
  }
  /// Asks the worker to end after its current request; returns at once.
  void request_stop() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    cv_.notify_all();
  }

  /// Fetches one whole update (all pages) now, on the calling thread. Throws RestError or
  /// mesh::FormatError.
  void sync_once() {
    std::string since;  // omitted until the copy is complete: every chunk, FULL
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (mesh_.has_have()) since = "&since=" + std::to_string(mesh_.have());
    }
    uint32_t cursor = 0;
    for (int page = 0; page < 100000; ++page) {
      std::string target = "/sessions/" + std::to_string(cfg_.session) +
                           "/mesh?frame=" + http::url_encode(cfg_.frame) + since +
                           (cfg_.chunk_bricks > 0
                                ? "&chunk_bricks=" + std::to_string(cfg_.chunk_bricks)
                                : std::string()) +
                           "&winding=" + http::url_encode(cfg_.winding) +
                           "&cursor=" + std::to_string(cursor) +
                           "&max_bytes=" + std::to_string(cfg_.max_page_bytes);
      std::string body = rest_.get_bytes(target);
      mesh::Message m = mesh::parse(body);
      if (m.session != cfg_.session) throw mesh::FormatError("mesh of another session");
      bool more = m.more();
      cursor = m.next_cursor;
      {
        std::lock_guard<std::mutex> lock(mutex_);
        bytes_ += body.size();
        ++pages_;
        chunks_received_ += m.chunks.size();
        bool done = mesh_.apply(std::move(m));
        if (done) ++updates_;
      }
      cv_.notify_all();
      if (!more) return;
    }
    throw mesh::FormatError("mesh update never ended (MORE on every page)");
  }

  /// Calls `f(const mesh::ChunkedMesh&)` under the lock (keep it short: copy what you need).
  template <class F>
  void read(F&& f) {
    std::lock_guard<std::mutex> lock(mutex_);
    f(static_cast<const mesh::ChunkedMesh&>(mesh_));
  }
  /// Like read(), but may change the mesh (e.g. take_dirty()).
  template <class F>
  void modify(F&& f) {
    std::lock_guard<std::mutex> lock(mutex_);
    f(mesh_);
  }

  /// The chunks changed since the last call, shared rather than copied, so a render thread
  /// holds the lock only for a few pointer copies (ChunkedMesh::take_changes()).
  std::vector<mesh::ChunkChange> take_changes() {
    std::lock_guard<std::mutex> lock(mutex_);
    return mesh_.take_changes();
  }

  /// Waits until a complete update has brought `have` to at least `version`.
  bool wait_for_version(uint64_t version, int timeout_ms) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::milliseconds(timeout_ms),
                        [&] { return mesh_.has_have() && mesh_.have() >= version; });
  }

  uint64_t have() {
    std::lock_guard<std::mutex> lock(mutex_);
    return mesh_.have();
  }
  uint64_t updates() { std::lock_guard<std::mutex> l(mutex_); return updates_; }
  uint64_t pages() { std::lock_guard<std::mutex> l(mutex_); return pages_; }
  uint64_t bytes() { std::lock_guard<std::mutex> l(mutex_); return bytes_; }
  uint64_t chunks_received() { std::lock_guard<std::mutex> l(mutex_); return chunks_received_; }
  uint64_t errors() const { return errors_.load(); }
  /// Updates that ended without `have` moving while the announced version was ahead.
  uint64_t fruitless() { std::lock_guard<std::mutex> l(mutex_); return fruitless_; }
  std::string last_error() {
    std::lock_guard<std::mutex> l(mutex_);
    return last_error_;
  }

 private:
  void run() {
    using Clock = std::chrono::steady_clock;
    int backoff_ms = 0;          // 0: not backing off
    bool last_failed = false;    // the last attempt threw (the server is down or broken)
    uint64_t asked_for = 0;      // the announced version at the last attempt
    Clock::time_point retry_at = Clock::now();
    for (;;) {
      bool want = false;
      uint64_t announced = 0, before = 0;
      bool had = false;
      {
        std::lock_guard<std::mutex> lock(mutex_);
        if (stop_) return;
        had = mesh_.has_have();
        before = mesh_.have();
        announced = version_ ? version_() : 0;
        // Only a version past `have` is news: an equal or lower one (no REPLY yet, lost
        // REPLYs, a stopped stream) would otherwise make every poll a request.
        bool behind = !had || announced > before;
        if (!behind) backoff_ms = 0;
        // While backing off, a newer announcement may cut the wait short, but not after an
        // error: cutting moves the version every tick and would hammer a failing server.
        bool fresh = !last_failed && announced > asked_for;
        want = behind && (backoff_ms == 0 || fresh || Clock::now() >= retry_at);
      }
      if (want) {
        asked_for = announced;
        bool progressed = false;
        last_failed = false;
        try {
          sync_once();
          std::lock_guard<std::mutex> lock(mutex_);
          progressed = !had || mesh_.have() > before;
          if (!progressed) ++fruitless_;
        } catch (const std::exception& e) {
          last_failed = true;
          errors_.fetch_add(1);
          std::lock_guard<std::mutex> lock(mutex_);
          last_error_ = e.what();
        }
        if (progressed) {
          backoff_ms = 0;
        } else {
          int base = std::max(cfg_.poll_interval_ms, 1);
          backoff_ms = backoff_ms == 0 ? 2 * base : std::min(2 * backoff_ms, cfg_.max_backoff_ms);
          backoff_ms = std::max(backoff_ms, base);
          retry_at = Clock::now() + std::chrono::milliseconds(backoff_ms);
        }
      }
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait_for(lock, std::chrono::milliseconds(cfg_.poll_interval_ms),
                   [this] { return stop_; });
      if (stop_) return;
    }
  }

  Rest rest_;
  MeshSyncConfig cfg_;
  VersionSource version_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  bool stop_ = false;
  mesh::ChunkedMesh mesh_;
  uint64_t updates_ = 0, pages_ = 0, bytes_ = 0, chunks_received_ = 0, fruitless_ = 0;
  std::atomic<uint64_t> errors_{0};
  std::string last_error_;
};

}  // namespace burrforce
