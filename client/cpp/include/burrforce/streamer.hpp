// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The haptic stream: a background thread that sends one POSE per tick at a fixed rate
// (default 1 kHz) on an absolute schedule, independent of the engine's frame rate, and
// receives REPLYs between ticks without ever blocking on one.
//
// Two ways to feed it:
//  - publish(): the engine's main thread hands over the newest tool pose (each frame); every
//    tick samples the newest one. A pose is stamped with the time it was published (when
//    the engine sampled it), so the server's velocity estimate sees real motion, not the
//    steps of a 60-90 Hz frame loop (repeated stamps leave the estimate unchanged, SPEC 5.4).
//  - a PoseSource callback: called on the stream thread for each tick with its scheduled
//    time (µs); the pose is stamped with that scheduled time (trajectories, device hosts).
//
// After a stall (the process was descheduled) missed ticks are skipped and counted: only
// the newest due tick is sent, never a burst.
//
// Streams (protocol v2) need nothing from the engine: until the server has given the
// streamer a stream, each tick's POSE is a hello (not ticked, no REPLY); the NEW_STREAM
// answer arrives within a round trip and the next tick streams. A closed stream (the server
// restarted, a REST restart-stream) answers WRONG_STREAM, and the streamer says hello again.
//
// An exception thrown by a PoseSource or a callback ends the stream instead of the process:
// it is kept in failure(), the streamer counts as finished and state() renders zero force.
#pragma once

#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "burrforce/clock.hpp"
#include "burrforce/frames.hpp"
#include "burrforce/session.hpp"
#include "burrforce/udp_socket.hpp"

namespace burrforce {

/// The tool as the engine sees it (engine frame and units).
struct ToolPose {
  Vec3 position;         ///< burr centre, L
  Quat orientation;      ///< engine quaternion, sent as is
  double rpm = 0;        ///< + = the session's forward spin
  bool spindle_on = false;
  bool has_velocity = false;
  Vec3 velocity;         ///< L/s, only if has_velocity
  uint32_t flags = 0;    ///< FLAG_NO_CARVE, FLAG_RESET_VELOCITY
  int64_t t_sampled_us = 0;  ///< publish(): 0 = now
};

/// What to render, from the newest good REPLY. All zero (valid false) until one arrives,
/// after an error REPLY, once no good REPLY has arrived for `stale_after_us` (SPEC 7.6),
/// and after the stream failed. Zeroing clears every force, vibration, proxy and coupling
/// field, as an error REPLY carries them (SPEC 3.4); the diagnostics below stay.
struct HapticState {
  bool valid = false;
  uint16_t error = 0;        ///< error of the newest REPLY (its force is zero if not 0)
  uint32_t status = 0;
  uint32_t seq = 0;
  Vec3 force;                ///< N, engine axes: what the hand should feel
  Vec3 resistive;            ///< N: feed, lateral, normal
  Vec3 torque;               ///< N·L, engine axes
  double power_w = 0;
  double vibration_amplitude_N = 0;
  double vibration_frequency_hz = 0;
  Vec3 vibration_axis;
  Vec3 proxy_position;       ///< L
  Vec3 proxy_velocity;       ///< L/s
  double coupling_stiffness = 0;  ///< N/L; 0 = raw output (render `force`)
  double coupling_damping = 0;    ///< N·s/L
  Vec3 feed_velocity;        ///< L/s
  uint64_t bone_version = 0;
  double removed_mm3 = 0;         ///< this REPLY's tick
  double removed_total_mm3 = 0;   ///< every REPLY of this streamer
  /// Send to reply: the network round trip plus the server's time. Not SPEC 5.5's rtt,
  /// which starts at the pose's sample time (that is sample_rtt_us).
  int64_t rtt_us = 0;
  /// SPEC 5.5's rtt = T4 - t_client_us: rtt_us plus the pose's age when it was sent (with
  /// publish(), up to one engine frame; with a PoseSource, the tick's lateness).
  int64_t sample_rtt_us = 0;
  double clock_offset_us = 0;     ///< server - client, NTP estimate from the send time
  int64_t received_us = 0;        ///< arrival of the newest good REPLY, client clock
};

struct StreamerConfig {
  std::string host = "127.0.0.1";
  uint16_t port = 47810;
  uint32_t session = 1;
  std::vector<uint8_t> key;       ///< empty: a session without a key (loopback only)
  double rate_hz = 1000.0;
  uint32_t first_seq = 1;
  int64_t stale_after_us = 50000; ///< SPEC 7.6
  uint64_t max_ticks = 0;         ///< 0: until stop(); else stop after this many ticks
  int64_t linger_us = 50000;      ///< after max_ticks: keep receiving this long
  int64_t spin_us = 200;          ///< spin (not sleep) this close to a tick
  /// After a stall, send at most this many overdue ticks back to back before skipping.
  /// 0 (live engines): skip every missed tick, never a burst. A replayed trajectory that
  /// must send every sample (tests, recordings) sets a few dozen.
  uint64_t max_catch_up_ticks = 0;
};

class Streamer {
 public:
  /// tick: the tick number from 0; t_us: its scheduled time. Return false to end the stream.
  using PoseSource = std::function<bool(uint64_t tick, int64_t t_us, ToolPose& out)>;
  /// Called on the stream thread for each REPLY used and each NOTICE: keep it short.
  using EventCallback = std::function<void(const Event&)>;

  explicit Streamer(StreamerConfig cfg)
      : cfg_(std::move(cfg)), rules_(cfg_.session, cfg_.key, cfg_.first_seq) {
    if (!(cfg_.rate_hz > 0 && cfg_.rate_hz <= 100000))
      throw std::invalid_argument("rate_hz must be in (0, 100000]");
  }
  ~Streamer() { stop(); }
  Streamer(const Streamer&) = delete;
  Streamer& operator=(const Streamer&) = delete;

  // Set these before start().
  void set_pose_source(PoseSource s) { source_ = std::move(s); }
  void on_reply(EventCallback cb) { on_reply_ = std::move(cb); }
  void on_notice(EventCallback cb) { on_notice_ = std::move(cb); }

  void start() {
    if (thread_.joinable()) return;
    socket_.open(cfg_.host, cfg_.port);
    stop_ = false;
    finished_ = false;
    thread_ = std::thread([this] { run(); });
  }

  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }

  /// For a finite run (max_ticks or a source that ends): true once it has finished.
  bool wait_finished(int64_t timeout_us) {
    std::unique_lock<std::mutex> lock(done_mutex_);
    return done_cv_.wait_for(lock, std::chrono::microseconds(timeout_us),
                             [this] { return finished_.load(); });
  }
  bool running() const { return thread_.joinable() && !finished_; }

  /// True once the stream thread ended on an exception (from a PoseSource, on_reply or
  /// on_notice); failure() says what it was. The stream is then finished and silent.
  bool failed() const { return failed_.load(); }
  std::string failure() const {
    std::lock_guard<std::mutex> lock(state_mutex_);
    return failure_;
  }

  /// The engine's newest tool pose (any thread, typically once per frame).
  void publish(const ToolPose& pose) {
    std::lock_guard<std::mutex> lock(pose_mutex_);
    published_ = pose;
    if (published_.t_sampled_us == 0) published_.t_sampled_us = now_us();
    has_published_ = true;
  }

  /// Asks the server for a new stream from the next tick on (hellos until it answers; the
  /// new stream's first tick reports STALE, a fresh velocity estimate). Not needed after a
  /// server restart or a REST restart-stream: the closed stream's WRONG_STREAM answer makes
  /// the streamer say hello by itself. Sequence numbers go on counting.
  void restart_stream() { restart_ = true; }

  /// The stream the server gave (any thread); 0 while the streamer says hello.
  uint32_t stream() const { return rules_.stream(); }

  /// What to render now (any thread).
  HapticState state() const {
    std::lock_guard<std::mutex> lock(state_mutex_);
    HapticState s = state_;
    if (s.valid && (failed_ || now_us() - s.received_us > cfg_.stale_after_us)) silence(s);
    return s;
  }

  /// The newest bone version seen (lock-free; what a mesh sync polls).
  uint64_t bone_version() const { return bone_version_.load(std::memory_order_relaxed); }
  const Counters& counters() const { return rules_.counters(); }
  const StreamerConfig& config() const { return cfg_; }

 private:
  static void silence(HapticState& s) {
    s.valid = false;
    s.status = 0;
    s.force = s.resistive = s.torque = s.vibration_axis = Vec3{};
    s.power_w = s.vibration_amplitude_N = s.vibration_frequency_hz = 0;
    s.coupling_stiffness = s.coupling_damping = 0;
    s.proxy_position = s.proxy_velocity = s.feed_velocity = Vec3{};
  }

  void run() {
    try {
      loop();
    } catch (const std::exception& e) {
      fail(e.what());
    } catch (...) {
      fail("unknown exception");
    }
    {
      std::lock_guard<std::mutex> lock(done_mutex_);
      finished_ = true;
    }
    done_cv_.notify_all();
  }

  void fail(const char* what) {
    std::lock_guard<std::mutex> lock(state_mutex_);
    failure_ = what;
    failed_ = true;
    silence(state_);
  }

  void loop() {
    const double period_us = 1e6 / cfg_.rate_hz;
    const int64_t start_us = now_us();
    uint64_t k = 0;
    auto due_of = [&](uint64_t tick) {
      return start_us + static_cast<int64_t>(std::llround(static_cast<double>(tick) * period_us));
    };
    while (!stop_) {
      if (cfg_.max_ticks && k >= cfg_.max_ticks) break;
      int64_t due = due_of(k);
      pump_until(due);
      if (stop_) break;
      int64_t now = now_us();
      // A stall: jump to the newest tick that is due (less the allowed catch-up), so the
      // server never gets a burst.
      uint64_t newest = static_cast<uint64_t>(static_cast<double>(now - start_us) / period_us);
      if (newest > k + cfg_.max_catch_up_ticks) {
        uint64_t target = newest - cfg_.max_catch_up_ticks;
        if (cfg_.max_ticks && target >= cfg_.max_ticks) target = cfg_.max_ticks;
        rules_.counters().skipped_ticks.fetch_add(target - k, std::memory_order_relaxed);
        k = target;
        if (cfg_.max_ticks && k >= cfg_.max_ticks) break;
        due = due_of(k);
      }
      if (now - due > static_cast<int64_t>(0.2 * period_us))
        rules_.counters().late_ticks.fetch_add(1, std::memory_order_relaxed);
      if (!send_tick(k, due)) break;
      ++k;
      drain();
    }
    if (!stop_) pump_until(now_us() + cfg_.linger_us);
  }

  /// Sends tick `k`; false when the pose source ended the stream.
  bool send_tick(uint64_t k, int64_t due_us) {
    if (restart_.exchange(false)) rules_.restart();
    ToolPose tp;
    int64_t stamp;
    if (source_) {
      if (!source_(k, due_us, tp)) return false;
      stamp = due_us;  // the scheduled sample time: a late send must not look like motion
    } else {
      std::lock_guard<std::mutex> lock(pose_mutex_);
      if (!has_published_) return true;  // nothing to say yet
      tp = published_;
      stamp = tp.t_sampled_us;
    }
    Pose p;
    p.t_client_us = static_cast<uint64_t>(stamp < 0 ? 0 : stamp);
    p.position[0] = tp.position.x;
    p.position[1] = tp.position.y;
    p.position[2] = tp.position.z;
    p.orientation[0] = tp.orientation.x;
    p.orientation[1] = tp.orientation.y;
    p.orientation[2] = tp.orientation.z;
    p.orientation[3] = tp.orientation.w;
    p.rpm = tp.rpm;
    p.spindle_on = tp.spindle_on;
    p.has_velocity = tp.has_velocity;
    p.velocity[0] = tp.velocity.x;
    p.velocity[1] = tp.velocity.y;
    p.velocity[2] = tp.velocity.z;
    p.flags = tp.flags;
    size_t n = rules_.encode_next(p, k, out_, sizeof out_, now_us());
    Counters& c = rules_.counters();
    c.sent.fetch_add(1, std::memory_order_relaxed);
    if (n == 0 || !socket_.send(out_, n)) c.send_failed.fetch_add(1, std::memory_order_relaxed);
    return true;
  }

  void pump_until(int64_t deadline_us) {
    for (;;) {
      drain();
      int64_t left = deadline_us - now_us();
      if (left <= 0 || stop_) return;
      if (left > cfg_.spin_us)
        socket_.wait_readable(left - cfg_.spin_us);
      else
        std::this_thread::yield();
    }
  }

  void drain() {
    for (;;) {
      long n = socket_.receive(in_, kMaxServerBytes + 1);
      if (n < 0) return;
      Event ev = rules_.accept(in_, static_cast<size_t>(n), now_us());
      if (ev.kind == Event::Kind::Reply) {
        apply(ev);
        if (on_reply_) on_reply_(ev);
      } else if (ev.kind == Event::Kind::Notice) {
        if (on_notice_) on_notice_(ev);
      }
    }
  }

  void apply(const Event& ev) {
    const Reply& r = ev.reply;
    bone_version_.store(r.bone_version, std::memory_order_relaxed);
    std::lock_guard<std::mutex> lock(state_mutex_);
    HapticState& s = state_;
    s.error = r.error;
    s.seq = r.seq;
    s.bone_version = r.bone_version;
    s.rtt_us = ev.round_trip.rtt_us;
    s.sample_rtt_us = ev.sample_round_trip.rtt_us;
    s.clock_offset_us = ev.round_trip.offset_us;
    s.removed_mm3 = r.removed_mm3;
    s.removed_total_mm3 += r.removed_mm3;
    if (r.error != OK) {  // not a force: render nothing from it (SPEC 7.6)
      silence(s);
      return;
    }
    s.valid = true;
    s.received_us = ev.arrival_us;
    s.status = r.status;
    s.force = {r.force[0], r.force[1], r.force[2]};
    s.resistive = {r.resistive[0], r.resistive[1], r.resistive[2]};
    s.torque = {r.torque[0], r.torque[1], r.torque[2]};
    s.power_w = r.power_w;
    s.vibration_amplitude_N = r.vibration_amplitude;
    s.vibration_frequency_hz = r.vibration_frequency_hz;
    s.vibration_axis = {r.vibration_axis[0], r.vibration_axis[1], r.vibration_axis[2]};
    s.proxy_position = {r.proxy_position[0], r.proxy_position[1], r.proxy_position[2]};
    s.proxy_velocity = {r.proxy_velocity[0], r.proxy_velocity[1], r.proxy_velocity[2]};
    s.coupling_stiffness = r.coupling_stiffness;
    s.coupling_damping = r.coupling_damping;
    s.feed_velocity = {r.feed_velocity[0], r.feed_velocity[1], r.feed_velocity[2]};
  }

  StreamerConfig cfg_;
  SessionRules rules_;
  UdpSocket socket_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> finished_{false};
  std::atomic<bool> failed_{false};
  std::string failure_;  // guarded by state_mutex_
  std::mutex done_mutex_;
  std::condition_variable done_cv_;
  PoseSource source_;
  EventCallback on_reply_, on_notice_;
  std::mutex pose_mutex_;
  ToolPose published_;
  bool has_published_ = false;
  std::atomic<bool> restart_{false};
  mutable std::mutex state_mutex_;
  HapticState state_;
  std::atomic<uint64_t> bone_version_{0};
  uint8_t out_[kMaxPoseBytes];
  uint8_t in_[kMaxServerBytes + 2];
};

}  // namespace burrforce
