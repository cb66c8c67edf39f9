// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The golden vectors (proto/vectors/vectors.json, read at run time so new cases are covered):
// encode each vector's fields to exactly its bytes, decode its bytes to exactly its fields
// (floats bit for bit), verify its tag with the key, reject it with another key and after
// every single-byte change. Also: non-canonical forms SPEC 2.2 allows decode to the same
// values, truncated or mutated datagrams never crash the decoder, and SessionRules follow
// the v2 stream handshake (offline: notices built here).
// Usage: vectors VECTORS_JSON. Prints one JSON line; exit status 1 on any failure.
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "burrforce/burrforce.hpp"

using namespace burrforce;

namespace {

std::vector<std::string> failures;

void fail(const std::string& name, const std::string& what) {
  failures.push_back(name + ": " + what);
}

uint64_t bits(double v) {
  uint64_t b;
  std::memcpy(&b, &v, sizeof b);
  return b;
}

void read_vec(const json::Value& v, double* out, size_t n) {
  if (v.size() != n) throw json::ParseError("vector of wrong length");
  for (size_t i = 0; i < n; ++i) out[i] = v[i].as_double();
}

bool same_vec(const double* a, const double* b, int n) {
  for (int i = 0; i < n; ++i)
    if (bits(a[i]) != bits(b[i])) return false;
  return true;
}

Pose pose_of(const json::Value& f) {
  Pose p;
  p.session = static_cast<uint32_t>(f["session"].as_int());
  p.seq = static_cast<uint32_t>(f["seq"].as_int());
  p.t_client_us = static_cast<uint64_t>(f["t_client_us"].as_int());
  read_vec(f["position"], p.position, 3);
  read_vec(f["orientation"], p.orientation, 4);
  p.rpm = f["rpm"].as_double();
  p.spindle_on = f["spindle_on"].as_bool();
  p.has_velocity = !f["velocity"].is_null();
  if (p.has_velocity) read_vec(f["velocity"], p.velocity, 3);
  p.flags = static_cast<uint32_t>(f["flags"].as_int());
  p.stream = static_cast<uint32_t>(f["stream"].as_int());
  return p;
}

Reply reply_of(const json::Value& f) {
  Reply r;
  r.session = static_cast<uint32_t>(f["session"].as_int());
  r.seq = static_cast<uint32_t>(f["seq"].as_int());
  r.t_client_us = static_cast<uint64_t>(f["t_client_us"].as_int());
  r.t_recv_us = static_cast<uint64_t>(f["t_recv_us"].as_int());
  r.t_send_us = static_cast<uint64_t>(f["t_send_us"].as_int());
  r.error = static_cast<uint16_t>(f["error"].as_int());
  r.status = static_cast<uint32_t>(f["status"].as_int());
  read_vec(f["force"], r.force, 3);
  read_vec(f["resistive"], r.resistive, 3);
  read_vec(f["torque"], r.torque, 3);
  r.power_w = f["power_w"].as_double();
  r.vibration_amplitude = f["vibration_amplitude"].as_double();
  r.vibration_frequency_hz = f["vibration_frequency_hz"].as_double();
  read_vec(f["vibration_axis"], r.vibration_axis, 3);
  read_vec(f["proxy_position"], r.proxy_position, 3);
  read_vec(f["proxy_velocity"], r.proxy_velocity, 3);
  r.coupling_stiffness = f["coupling_stiffness"].as_double();
  r.coupling_damping = f["coupling_damping"].as_double();
  r.removed_mm3 = f["removed_mm3"].as_double();
  r.bone_version = static_cast<uint64_t>(f["bone_version"].as_int());
  read_vec(f["feed_velocity"], r.feed_velocity, 3);
  return r;
}

// The version is not among a vector's fields: a NOTICE's comes from its datagram (v1's
// BAD_VERSION answer has v1's shape), any other message's is kVersion.
Notice notice_of(const json::Value& f, uint32_t version) {
  Notice n;
  n.version = version;
  n.session = static_cast<uint32_t>(f["session"].as_int());
  n.seq = static_cast<uint32_t>(f["seq"].as_int());
  n.t_client_us = static_cast<uint64_t>(f["t_client_us"].as_int());
  n.error = static_cast<uint16_t>(f["error"].as_int());
  n.stream = f.has("stream") ? static_cast<uint32_t>(f["stream"].as_int()) : 0;
  return n;
}

bool same(const Pose& a, const Pose& b) {
  return a.session == b.session && a.seq == b.seq && a.t_client_us == b.t_client_us &&
         same_vec(a.position, b.position, 3) && same_vec(a.orientation, b.orientation, 4) &&
         bits(a.rpm) == bits(b.rpm) && a.spindle_on == b.spindle_on &&
         a.has_velocity == b.has_velocity &&
         (!a.has_velocity || same_vec(a.velocity, b.velocity, 3)) && a.flags == b.flags &&
         a.stream == b.stream;
}

bool same(const Reply& a, const Reply& b) {
  return a.session == b.session && a.seq == b.seq && a.t_client_us == b.t_client_us &&
         a.t_recv_us == b.t_recv_us && a.t_send_us == b.t_send_us && a.error == b.error &&
         a.status == b.status && same_vec(a.force, b.force, 3) &&
         same_vec(a.resistive, b.resistive, 3) && same_vec(a.torque, b.torque, 3) &&
         bits(a.power_w) == bits(b.power_w) &&
         bits(a.vibration_amplitude) == bits(b.vibration_amplitude) &&
         bits(a.vibration_frequency_hz) == bits(b.vibration_frequency_hz) &&
         same_vec(a.vibration_axis, b.vibration_axis, 3) &&
         same_vec(a.proxy_position, b.proxy_position, 3) &&
         same_vec(a.proxy_velocity, b.proxy_velocity, 3) &&
         bits(a.coupling_stiffness) == bits(b.coupling_stiffness) &&
         bits(a.coupling_damping) == bits(b.coupling_damping) &&
         bits(a.removed_mm3) == bits(b.removed_mm3) && a.bone_version == b.bone_version &&
         same_vec(a.feed_velocity, b.feed_velocity, 3);
}

bool same(const Notice& a, const Notice& b) {
  return a.version == b.version && a.session == b.session && a.seq == b.seq &&
         a.t_client_us == b.t_client_us && a.error == b.error && a.stream == b.stream;
}

// Known answers for the hash itself (FIPS 180-4 examples, RFC 4231 case 2), so a failure
// points at SHA-256/HMAC rather than at the encoder.
void check_crypto() {
  auto sha = [](const std::string& s) {
    Sha256 h;
    h.update(reinterpret_cast<const uint8_t*>(s.data()), s.size());
    uint8_t d[32];
    h.finish(d);
    return to_hex(d, 32);
  };
  if (sha("abc") != "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad")
    fail("sha256", "abc");
  if (sha("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq") !=
      "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1")
    fail("sha256", "two blocks");
  std::string key = "Jefe", msg = "what do ya want for nothing?";
  HmacSha256 h(reinterpret_cast<const uint8_t*>(key.data()), key.size());
  uint8_t d[32];
  h.mac(reinterpret_cast<const uint8_t*>(msg.data()), msg.size(), d);
  if (to_hex(d, 32) != "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843")
    fail("hmac", "RFC 4231 case 2");
}

// SPEC 2.2: the value counts, not the form. A POSE with a wider/signed integer, a float 32,
// an integer where a float goes and an array 16 header must decode to the same values.
void check_noncanonical() {
  std::vector<uint8_t> b = {0xdc, 0x00, 0x0d,                     // array 16, 13 elements
                            0x02, 0x01, 0xd2, 0x00, 0x00, 0x00, 0x07,  // session int 32
                            0xcf, 0, 0, 0, 0, 0, 0, 0, 0x02,       // seq uint 64
                            0xd1, 0x03, 0xe8,                      // t int 16 = 1000
                            0x93, 0xca, 0x3f, 0xc0, 0x00, 0x00,    // 1.5f
                            0xff,                                  // -1 (negative fixint)
                            0xd0, 0x05,                            // int 8: 5
                            0xdc, 0x00, 0x04, 0x00, 0x00, 0x00, 0x01,  // array 16 quaternion
                            0xcd, 0xea, 0x60,                      // rpm 60000 as uint 16
                            0xc3, 0xc0, 0x04,                      // flags: reserved bit 2
                            0xd3, 0, 0, 0, 0, 0, 0, 0x01, 0x00,    // stream int 64 = 256
                            0xc0};
  Decoded d = decode(b.data(), b.size());
  const Pose& p = d.pose;
  if (!d.ok || p.session != 7 || p.seq != 2 || p.t_client_us != 1000 || p.position[0] != 1.5 ||
      p.position[1] != -1.0 || p.position[2] != 5.0 || p.orientation[3] != 1.0 ||
      p.rpm != 60000.0 || !p.spindle_on || p.has_velocity || p.flags != 4 || p.stream != 256)
    fail("noncanonical", "valid non-canonical POSE not decoded to its values");
  // Things that are not numbers or not bools must be refused.
  std::vector<uint8_t> bad = b;
  bad[bad.size() - 13] = 0x01;  // spindle_on = 1 (an int is not a bool)
  if (decode(bad.data(), bad.size()).ok) fail("noncanonical", "int accepted as bool");
  bad = b;
  bad[22] = 0x93;
  bad[23] = 0xc0;  // nil as a coordinate
  if (decode(bad.data(), bad.size()).ok) fail("noncanonical", "nil accepted as float");
  bad = b;
  bad.push_back(0x00);  // trailing byte
  if (decode(bad.data(), bad.size()).ok) fail("noncanonical", "trailing byte accepted");
  bad = b;
  bad[bad.size() - 10] = 0xc0;  // a stream of nil
  bad.erase(bad.end() - 9, bad.end() - 1);
  if (decode(bad.data(), bad.size()).ok) fail("noncanonical", "nil accepted as stream");
  // v1's 12-element POSE: readable header (so a server can answer BAD_VERSION), not a
  // message of this version; likewise a v2 header on v1's layout.
  bad = b;
  bad[2] = 0x0c;
  bad.erase(bad.end() - 10, bad.end() - 1);  // without the stream
  for (uint8_t version : {uint8_t(1), uint8_t(2)}) {
    bad[3] = version;
    Decoded v = decode(bad.data(), bad.size());
    if (v.ok || !v.header_ok || v.version != version)
      fail("noncanonical", "a 12-element POSE of version " + std::to_string(version));
  }
  // Of v1 only the NOTICE decodes (7 elements, no stream); not with v2's 8.
  const uint8_t v1_notice[] = {0x97, 0x01, 0x03, 0x07, 0x2a, 0x00, 0x03, 0xc0};
  Decoded n1 = decode(v1_notice, sizeof v1_notice);
  if (!n1.ok || n1.type != kTypeNotice || n1.notice.version != 1 ||
      n1.notice.error != BAD_VERSION || n1.notice.stream != 0 || n1.session() != 7)
    fail("noncanonical", "v1's BAD_VERSION notice");
  const uint8_t v1_notice8[] = {0x98, 0x01, 0x03, 0x07, 0x2a, 0x00, 0x03, 0x00, 0xc0};
  const uint8_t v2_notice7[] = {0x97, 0x02, 0x03, 0x07, 0x2a, 0x00, 0x03, 0xc0};
  if (decode(v1_notice8, sizeof v1_notice8).ok || decode(v2_notice7, sizeof v2_notice7).ok)
    fail("noncanonical", "a notice of the other version's length");
}

// SessionRules' stream handshake (protocol v2) without a server: hellos until an authentic
// NEW_STREAM answers one of this round's hellos; forged, unsolicited, late and foreign
// notices change nothing; a WRONG_STREAM for the current stream (and only that one) goes
// back to hello; sequence numbers count on. Returns the number of checks made.
int check_stream_rules() {
  int checks = 0;
  auto expect = [&](bool ok, const std::string& what) {
    ++checks;
    if (!ok) fail("stream_rules", what);
  };
  const std::vector<uint8_t> key(32, 0x11), other_key(32, 0x22);
  const Tagger good(key.data(), key.size()), forger(other_key.data(), other_key.size());
  SessionRules rules(9, key, 100);
  uint8_t out[kMaxServerBytes], in[64];
  auto send = [&](uint64_t t) {
    Pose p;
    p.t_client_us = t;
    size_t n = rules.encode_next(p, 0, out, sizeof out);
    Decoded d = decode(out, n);
    if (!d.ok || !good.verify_tag(out, n)) fail("stream_rules", "encode_next");
    return d.pose;
  };
  auto notice = [&](const Tagger* tagger, uint32_t session, uint32_t seq, uint64_t t,
                    uint16_t error, uint32_t stream, uint32_t version = kVersion) {
    Notice no;
    no.version = version;
    no.session = session;
    no.seq = seq;
    no.t_client_us = t;
    no.error = error;
    no.stream = stream;
    size_t n = encode_notice(no, tagger, in, sizeof in);
    return rules.accept(in, n, 0);
  };
  auto unchanged = [&](const Event& e, uint32_t stream) {
    return e.kind == Event::Kind::Notice && !e.stream_changed && rules.stream() == stream;
  };

  const Pose h1 = send(1000);
  expect(h1.stream == kHelloStream && h1.seq == 100 && rules.stream() == 0, "first POSE a hello");
  Event e = notice(&forger, 9, h1.seq, 1000, NEW_STREAM, 77);
  expect(unchanged(e, 0) && !e.verified, "NEW_STREAM tagged with another key");
  expect(unchanged(notice(nullptr, 9, h1.seq, 1000, NEW_STREAM, 77), 0),
         "untagged NEW_STREAM on a keyed session");
  expect(unchanged(notice(&good, 9, h1.seq, 999, NEW_STREAM, 77), 0),
         "NEW_STREAM echoing another t_client_us");
  expect(unchanged(notice(&good, 9, h1.seq + 5, 1000, NEW_STREAM, 77), 0),
         "NEW_STREAM for a seq never sent");
  expect(unchanged(notice(&good, 9, h1.seq, 1000, NEW_STREAM, 0), 0), "NEW_STREAM of stream 0");
  e = notice(&good, 8, h1.seq, 1000, NEW_STREAM, 77);
  expect(e.kind == Event::Kind::Dropped && e.drop == Drop::Foreign && rules.stream() == 0,
         "another session's NEW_STREAM");
  e = notice(&good, 9, h1.seq, 1000, NEW_STREAM, 77);
  expect(e.kind == Event::Kind::Notice && e.verified && e.stream_changed &&
             e.notice.stream == 77 && rules.stream() == 77,
         "NEW_STREAM answering our hello");
  const Pose p2 = send(2000);
  expect(p2.stream == 77 && p2.seq == h1.seq + 1, "POSEs carry the stream, seq counts on");
  expect(unchanged(notice(&good, 9, h1.seq, 1000, NEW_STREAM, 78), 77),
         "a second offer while streaming");
  expect(unchanged(notice(&good, 9, p2.seq, 2000, WRONG_STREAM, 76), 77),
         "WRONG_STREAM for another stream");
  expect(unchanged(notice(&forger, 9, p2.seq, 2000, WRONG_STREAM, 77), 77),
         "forged WRONG_STREAM");
  expect(unchanged(notice(&good, 9, p2.seq, 2000, BAD_TAG, 77), 77),
         "another notice with a stream");
  e = notice(&good, 9, p2.seq, 2000, WRONG_STREAM, 77);
  expect(e.verified && e.stream_changed && rules.stream() == 0, "WRONG_STREAM for our stream");
  const Pose h3 = send(3000);
  expect(h3.stream == kHelloStream && h3.seq == p2.seq + 1, "hello again, seq counts on");
  expect(unchanged(notice(&good, 9, h1.seq, 1000, NEW_STREAM, 79), 0),
         "a late answer to a hello of the previous round");
  e = notice(&good, 9, h3.seq, 3000, NEW_STREAM, 80);
  expect(e.stream_changed && rules.stream() == 80, "NEW_STREAM answering this round's hello");
  // A hello is never ticked: a REPLY echoing one answers nothing we asked.
  Reply r;
  r.session = 9;
  r.seq = h3.seq;
  r.t_client_us = 3000;
  size_t n = encode_reply(r, &good, out, sizeof out);
  e = rules.accept(out, n, 0);
  expect(e.kind == Event::Kind::Dropped && e.drop == Drop::Unsolicited, "a REPLY to a hello");
  const Pose p4 = send(4000);
  r.seq = p4.seq;
  r.t_client_us = 4000;
  n = encode_reply(r, &good, out, sizeof out);
  expect(rules.accept(out, n, 0).kind == Event::Kind::Reply, "a REPLY on the new stream");
  // A v1 server's answer to our v2 POSE: shown, counted, no stream change.
  e = notice(nullptr, 9, p4.seq, 4000, BAD_VERSION, 0, kVersion1);
  expect(unchanged(e, 80) && e.notice.version == kVersion1 && e.notice.error == BAD_VERSION,
         "a v1 BAD_VERSION notice");
  const Counters& c = rules.counters();
  expect(c.hellos == 2 && c.streams == 2 && c.streams_lost == 1 && c.by_error[BAD_VERSION] == 1,
         "counters");
  // restart(): hello again, and only this round's hellos count.
  rules.restart();
  const Pose h5 = send(5000);
  expect(h5.stream == kHelloStream && rules.stream() == 0, "restart() says hello");
  expect(unchanged(notice(&good, 9, h3.seq, 3000, NEW_STREAM, 81), 0),
         "an answer to a hello before restart()");
  expect(notice(&good, 9, h5.seq, 5000, NEW_STREAM, 82).stream_changed && rules.stream() == 82,
         "NEW_STREAM after restart()");

  // A session without a key: notices are untagged and count as authentic.
  SessionRules open(3, {}, 1);
  Pose hp;
  hp.t_client_us = 10;
  n = open.encode_next(hp, 0, out, sizeof out);
  Notice no;
  no.session = 3;
  no.seq = hp.seq;
  no.t_client_us = 10;
  no.error = NEW_STREAM;
  no.stream = 5;
  n = encode_notice(no, nullptr, in, sizeof in);
  e = open.accept(in, n, 0);
  expect(e.verified && e.stream_changed && open.stream() == 5, "an unkeyed session's NEW_STREAM");
  return checks;
}

// SPEC 5.1 (serial arithmetic at the wrap), 5.5 (the worked example's rtt and offset) and
// 6.2/6.3 (frames: Unity's axes, Unreal's reflection, the tool axis of a shortest arc).
void check_sequence_clock_frames() {
  if (!seq_newer(0, 0xFFFFFFFFu) || seq_newer(0xFFFFFFFFu, 0) || seq_newer(5, 5) ||
      seq_newer(0x80000000u, 0) || seq_newer(0, 0x80000000u) || !seq_newer(0x7FFFFFFFu, 0) ||
      seq_next(0xFFFFFFFFu) != 0)
    fail("sequence", "RFC 1982 comparison");
  RoundTrip rt = RoundTrip::of(1000000, 5000250, 5000300, 1000400);
  if (rt.rtt_us != 400 || rt.server_us != 50 || rt.network_us != 350 ||
      rt.offset_us != 4000075.0)
    fail("clock", "SPEC 5.5 example");
  auto near = [](const Vec3& a, const Vec3& b) {
    return std::fabs(a.x - b.x) + std::fabs(a.y - b.y) + std::fabs(a.z - b.z) < 1e-12;
  };
  FrameTransform unity(frames::unity());
  if (!near(unity.point_from_server({1, 2, 3}), {-0.002, 0.003, 0.001}) ||
      !near(unity.point_to_server({-0.002, 0.003, 0.001}), {1, 2, 3}))
    fail("frames", "unity axes and metres");
  FrameTransform unreal(frames::unreal());
  if (!near(unreal.point_from_server({10, 20, 30}), {1, -2, 3}) ||
      !near(unreal.direction_from_server({0, 1, 0}), {0, -1, 0}) ||
      !near(unreal.torque_from_server({10, 0, 0}), {-1, 0, 0}))  // det -1, N·mm → N·cm
    fail("frames", "unreal reflection and centimetres");
  for (const Frame* f : {&frames::si_mm(), &frames::unity(), &frames::unreal(),
                         &frames::godot(), &frames::ros()}) {
    FrameTransform tf(*f);
    const Vec3 axis{-0.5, 0.0, std::sqrt(0.75)};
    Quat q = tf.orientation_for_axis(axis, f->tool_axis);
    if (!near(tf.tool_axis_to_server(q, f->tool_axis), axis))
      fail("frames", std::string(f->name) + ": shortest arc does not reach the tool axis");
    if (f->right_handed() != (std::string(f->name) != "unity" &&
                              std::string(f->name) != "unreal"))
      fail("frames", std::string(f->name) + ": handedness");
  }
  Quat half = shortest_arc({0, 0, 1}, {0, 0, -1});  // opposite vectors: half a turn
  if (!near(rotate(half, {0, 0, 1}), {0, 0, -1})) fail("frames", "opposite shortest arc");
}

// The REST plumbing's pure parts: chunked transfer decoding, URL parsing, and the JSON
// reader's strictness (garbage throws ParseError, never crashes).
void check_json_http(const std::string& vectors_text) {
  auto dechunk = [](const std::string& raw, std::string& out) {
    out.clear();
    http::detail::Dechunker d(0);
    return d.feed(raw, out);
  };
  std::string body;
  const std::string chunked = "4\r\nWiki\r\n5;ext=1\r\npedia\r\n0\r\n\r\n";
  if (!dechunk(chunked, body) || body != "Wikipedia") fail("http", "chunked body");
  if (dechunk(chunked.substr(0, 12), body)) fail("http", "partial chunks");
  // Fed one byte at a time, as a slow server sends it: the same body, complete only at the
  // final CRLF.
  {
    http::detail::Dechunker d(0);
    std::string raw;
    body.clear();
    bool done = false;
    for (size_t i = 0; i < chunked.size(); ++i) {
      raw.push_back(chunked[i]);
      done = d.feed(raw, body);
      if (done != (i + 1 == chunked.size())) fail("http", "byte-wise chunks: early or late end");
    }
    if (!done || body != "Wikipedia") fail("http", "byte-wise chunked body");
  }
  // Trailer fields after the last chunk end at an empty line, not at the first CRLF.
  const std::string trailed = "4\r\nWiki\r\n0\r\nX-Checksum: 1\r\nX-More: 2\r\n\r\n";
  if (dechunk(trailed.substr(0, trailed.size() - 2), body))
    fail("http", "trailers: complete before their empty line");
  if (!dechunk(trailed, body) || body != "Wiki") fail("http", "trailers");
  for (const char* bad : {"zz\r\n", "4\r\nWikiXY5\r\npedia\r\n0\r\n\r\n",
                          "4\r\nWikipedia\r\n0\r\n\r\n"}) {
    try {
      dechunk(bad, body);
      fail("http", std::string("bad chunked body accepted: ") + bad);
    } catch (const http::Error&) {
    }
  }
  // A megabyte in 64 KiB reads of 1-byte chunks: linear, not a re-parse per read.
  {
    std::string big;
    for (int i = 0; i < 200000; ++i) big += "1\r\nx\r\n";
    big += "0\r\n\r\n";
    http::detail::Dechunker d(0);
    std::string raw;
    body.clear();
    auto t0 = std::chrono::steady_clock::now();
    bool done = false;
    for (size_t off = 0; off < big.size(); off += 65536) {
      raw.append(big, off, 65536);
      done = d.feed(raw, body);
    }
    double s_taken = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!done || body.size() != 200000) fail("http", "many small chunks");
    if (s_taken > 1.0) fail("http", "many small chunks took " + std::to_string(s_taken) + " s");
  }
  if (http::detail::content_length("1234") != 1234) fail("http", "Content-Length");
  for (const char* bad : {"", "12abc", "-1", "1e3", "99999999999999999999", " 1"}) {
    try {
      http::detail::content_length(bad);
      fail("http", std::string("bad Content-Length accepted: ") + bad);
    } catch (const http::Error&) {
    }
  }
  http::Url u = http::Url::parse("http://[::1]:8080/prefix/");
  if (u.host != "::1" || u.port != 8080 || u.path != "/prefix" || u.host_header() != "[::1]:8080")
    fail("http", "URL parsing");
  json::Value v = json::parse("{\"a\": [1, -2.5e3, true, null, \"\\u00e9\\n\"], \"id\": 4294967295}");
  if (v["a"][1].as_double() != -2500.0 || v["a"][4].as_string() != "\xc3\xa9\n" ||
      v["id"].as_int() != 4294967295LL || !v["a"][3].is_null())
    fail("json", "values");
  // A number beyond float64 is an error, not the largest double.
  for (const char* huge : {"1e400", "-1e400", "[2e308]"}) {
    json::Value h = json::parse(huge);
    const json::Value& n = h.is_array() ? h[0] : h;
    try {
      n.as_double();
      fail("json", std::string("out-of-range number read: ") + huge);
    } catch (const json::ParseError&) {
    }
  }
  if (json::parse("1e-400").as_double() != 0.0) fail("json", "underflow is zero");
  for (const char* bad : {"{\"a\": 1,}", "[01]", "{\"a\" 1}", "\"\\x\"", "[1] 2", "nan", ""}) {
    try {
      json::parse(bad);
      fail("json", std::string("accepted ") + bad);
    } catch (const json::ParseError&) {
    }
  }
  std::mt19937 rng(99);
  for (int k = 0; k < 300; ++k) {
    std::string t = vectors_text.substr(0, 1 + rng() % 2000);
    for (int e = 0; e < 3; ++e) t[rng() % t.size()] = static_cast<char>(rng());
    try {
      json::parse(t);
    } catch (const json::ParseError&) {
    }
  }
}

// A mesh message (MESH.md 3) built byte by byte: one chunk per entry, V vertices (all at
// the origin) and T triangles (0, 0, 0).
struct TestChunk {
  int32_t a;
  uint32_t v, t;
};
std::string mesh_message(uint16_t flags, uint64_t version, const std::vector<TestChunk>& cs) {
  std::string b;
  auto u16 = [&](uint32_t x) { b.push_back(char(x & 255)); b.push_back(char((x >> 8) & 255)); };
  auto u32 = [&](uint32_t x) { u16(x & 0xffff); u16(x >> 16); };
  auto u64 = [&](uint64_t x) { u32(uint32_t(x & 0xffffffffu)); u32(uint32_t(x >> 32)); };
  b += "BFMC";
  u16(1);
  u16(flags);
  u32(1);        // session
  u32(16);       // chunk_cells
  u64(version);  // bone_version
  u64(0);        // since
  u32(0);        // next_cursor
  u32(static_cast<uint32_t>(cs.size()));
  for (const TestChunk& c : cs) {
    u32(static_cast<uint32_t>(c.a));
    u32(0);
    u32(0);
    u32(c.v);
    u32(c.t);
    b.append(24 * c.v, '\0');  // positions and normals
    b.append(c.v, '\1');       // materials
    b.append((4 - (20 + 25 * c.v) % 4) % 4, '\0');
    for (uint32_t k = 0; k < 3 * c.t; ++k) u32(0);
  }
  return b;
}

// MESH.md 3's rule (T = 0: remove; V > 0 with T = 0: malformed), the per-frame winding
// table of MESH.md 5, and take_changes() handing out the held chunks, not copies.
void check_mesh_rules() {
  try {
    mesh::parse(mesh_message(0, 1, {{0, 3, 0}}));
    fail("mesh", "a chunk with vertices and no triangles parsed");
  } catch (const mesh::FormatError&) {
  }
  mesh::ChunkedMesh m;
  m.apply(mesh::parse(mesh_message(mesh::FLAG_FULL, 1, {{0, 3, 1}, {1, 4, 2}, {2, 3, 1}})));
  if (m.size() != 3 || m.triangle_count() != 4) fail("mesh", "first full update");
  std::vector<mesh::ChunkChange> first = m.take_changes();
  if (first.size() != 3) fail("mesh", "take_changes after the full update");
  for (const mesh::ChunkChange& c : first)
    if (c.removed() || m.find(c.key) != c.chunk.get())
      fail("mesh", "take_changes did not hand out the held chunk");
  const mesh::Chunk* kept = m.find({2, 0, 0});
  m.apply(mesh::parse(mesh_message(0, 2, {{0, 0, 0}, {1, 3, 1}})));  // remove 0, replace 1
  if (m.size() != 2 || m.find({0, 0, 0}) || m.chunks_removed != 1 || m.chunks_replaced != 1)
    fail("mesh", "T = 0 removes the chunk");
  if (m.find({2, 0, 0}) != kept) fail("mesh", "an untouched chunk was replaced");
  std::vector<mesh::ChunkChange> second = m.take_changes();
  if (second.size() != 2 || !second[0].removed() || second[1].removed() ||
      second[1].chunk->triangle_count() != 1 || first[1].chunk->triangle_count() != 2)
    fail("mesh", "changes of the second update (or a taken chunk changed under its holder)");
  if (!m.take_changes().empty()) fail("mesh", "changes taken twice");

  // Loopback names try IPv4 first (Windows resolves localhost to ::1 first); anything else
  // keeps the resolver's order.
  {
    sockaddr_in6 v6{};
    v6.sin6_family = AF_INET6;
    v6.sin6_addr.s6_addr[15] = 1;  // ::1
    sockaddr_in v4{};
    v4.sin_family = AF_INET;
    v4.sin_addr.s_addr = htonl(0x7f000001);  // 127.0.0.1
    addrinfo a4{}, a6{};
    a6.ai_family = AF_INET6;
    a6.ai_addr = reinterpret_cast<sockaddr*>(&v6);
    a6.ai_next = &a4;
    a4.ai_family = AF_INET;
    a4.ai_addr = reinterpret_cast<sockaddr*>(&v4);
    std::vector<const addrinfo*> order = burrforce::detail::connect_order(&a6);
    if (order.size() != 2 || order[0] != &a4) fail("net", "localhost: IPv4 not first");
    v6.sin6_addr.s6_addr[0] = 0x20;  // 2000::1, not loopback: the resolver's order stands
    order = burrforce::detail::connect_order(&a6);
    if (order.size() != 2 || order[0] != &a6) fail("net", "a global IPv6 address was reordered");
  }

  const std::pair<const char*, const char*> table[] = {
      {"si_mm", "ccw"}, {"unity", "ccw"}, {"unreal", "cw"}, {"godot", "cw"}, {"ros", "ccw"}};
  for (const auto& row : table) {
    const char* w = mesh_winding(std::string(row.first));
    if (!w || std::string(w) != row.second ||
        std::string(mesh_winding(*frames::by_name(row.first))) != row.second)
      fail("mesh", std::string("winding of ") + row.first);
  }
  if (mesh_winding(std::string("nonsense")) != nullptr) fail("mesh", "winding of no frame");
}

// Truncations and random mutations: the decoder must return, never crash or read past the
// end (run under -fsanitize=address to make the latter visible).
size_t fuzz(const std::vector<std::vector<uint8_t>>& seeds) {
  std::mt19937 rng(12345);
  size_t runs = 0;
  for (const auto& s : seeds) {
    for (size_t n = 0; n <= s.size(); ++n) {
      std::vector<uint8_t> t(s.begin(), s.begin() + static_cast<long>(n));
      Decoded d = decode(t.data(), t.size());
      if (n < s.size() && d.ok) fail("fuzz", "truncated datagram decoded");
      ++runs;
    }
    for (int k = 0; k < 2000; ++k) {
      std::vector<uint8_t> t = s;
      int edits = 1 + static_cast<int>(rng() % 4);
      for (int e = 0; e < edits; ++e) t[rng() % t.size()] = static_cast<uint8_t>(rng());
      (void)decode(t.data(), t.size());
      ++runs;
    }
  }
  return runs;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: vectors VECTORS_JSON\n";
    return 2;
  }
  std::ifstream in(argv[1], std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  json::Value all = json::parse(text.str());
  const std::vector<uint8_t> other_key(32, 0x42);
  const Tagger other(other_key.data(), other_key.size());
  size_t encoded = 0, decoded = 0, tag_checked = 0, byte_changes = 0;
  std::vector<std::vector<uint8_t>> seeds;
  for (const json::Value& v : all.as_array()) {
    const std::string name = v["name"].as_string();
    try {
      const std::string type = v["type"].as_string();
      std::vector<uint8_t> want;
      if (!parse_hex(v["hex"].as_string(), want)) throw json::ParseError("bad hex");
      seeds.push_back(want);
      std::vector<uint8_t> key;
      std::unique_ptr<Tagger> tagger;
      if (!v["key_hex"].is_null()) {
        if (!parse_hex(v["key_hex"].as_string(), key)) throw json::ParseError("bad key hex");
        tagger.reset(new Tagger(key.data(), key.size()));
      }
      const json::Value& f = v["fields"];
      uint8_t out[1024];
      size_t n = 0;
      Decoded d = decode(want.data(), want.size());
      bool fields_equal = false;
      if (type == "pose") {
        Pose p = pose_of(f);
        n = encode_pose(p, tagger.get(), out, sizeof out);
        fields_equal = d.ok && d.type == kTypePose && same(d.pose, p);
      } else if (type == "reply") {
        Reply r = reply_of(f);
        n = encode_reply(r, tagger.get(), out, sizeof out);
        fields_equal = d.ok && d.type == kTypeReply && same(d.reply, r);
      } else if (type == "notice") {
        Notice no = notice_of(f, d.header_ok ? d.version : kVersion);
        n = encode_notice(no, tagger.get(), out, sizeof out);
        fields_equal = d.ok && d.type == kTypeNotice && same(d.notice, no);
      } else {
        fail(name, "unknown type " + type);
        continue;
      }
      if (n == want.size() && std::memcmp(out, want.data(), n) == 0)
        ++encoded;
      else
        fail(name, "encoded " + to_hex(out, n) + " want " + to_hex(want.data(), want.size()));
      if (fields_equal)
        ++decoded;
      else
        fail(name, "decoded fields differ");
      if (d.tagged != (tagger != nullptr)) fail(name, "tag presence differs");
      if (tagger) {
        bool good = tagger->verify_tag(want.data(), want.size());
        bool wrong_key = other.verify_tag(want.data(), want.size());
        bool any_change_passed = false;
        for (size_t i = 0; i < want.size(); ++i) {
          for (uint8_t x : {uint8_t(0x01), uint8_t(0x80), uint8_t(0xff)}) {
            std::vector<uint8_t> t = want;
            t[i] ^= x;
            ++byte_changes;
            if (tagger->verify_tag(t.data(), t.size())) any_change_passed = true;
          }
        }
        if (good && !wrong_key && !any_change_passed)
          ++tag_checked;
        else
          fail(name, "tag check: good=" + std::to_string(good) + " other key=" +
                         std::to_string(wrong_key) + " changed=" +
                         std::to_string(any_change_passed));
      }
    } catch (const std::exception& e) {
      fail(name, e.what());
    }
  }
  check_crypto();
  check_noncanonical();
  int stream_rule_checks = check_stream_rules();
  check_sequence_clock_frames();
  check_json_http(text.str());
  check_mesh_rules();
  size_t fuzzed = fuzz(seeds);
  std::cout << "{\"vectors\": " << all.size() << ", \"encoded\": " << encoded
            << ", \"decoded\": " << decoded << ", \"tag_checked\": " << tag_checked
            << ", \"byte_changes\": " << byte_changes << ", \"fuzzed\": " << fuzzed
            << ", \"stream_rule_checks\": " << stream_rule_checks << ", \"failures\": [";
  for (size_t i = 0; i < failures.size(); ++i)
    std::cout << (i ? ", " : "") << json::quote(failures[i]);
  std::cout << "]}" << std::endl;
  return failures.empty() ? 0 : 1;
}
