// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Mesh chunks (proto/MESH.md): the strict parser of one message, and ChunkedMesh, the copy of
// the carved bone's surface an engine keeps (chunk index → vertices, normals, materials,
// triangles), updated by the FULL / MORE / `have` rules of MESH.md section 4. Little-endian
// on the wire; every count and index is checked before it is used.
#pragma once

#include <cstdint>
#include <cstdio>
#include <cstring>
#include <map>
#include <memory>
#include <set>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

namespace burrforce {
namespace mesh {

constexpr uint16_t kFormatVersion = 1;
constexpr size_t kHeaderBytes = 40;
constexpr uint16_t FLAG_MORE = 1, FLAG_FULL = 2, FLAG_CW = 4, FLAG_SESSION_FRAME = 8;

class FormatError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct ChunkKey {
  int32_t a = 0, b = 0, c = 0;
  bool operator<(const ChunkKey& o) const {
    return std::tie(a, b, c) < std::tie(o.a, o.b, o.c);
  }
  bool operator==(const ChunkKey& o) const { return a == o.a && b == o.b && c == o.c; }
};

/// One chunk's own mesh: indices refer to this chunk's vertices only.
struct Chunk {
  ChunkKey key;
  std::vector<float> positions;   ///< x, y, z per vertex (session frame and unit, or mm)
  std::vector<float> normals;     ///< unit, out of the bone
  std::vector<uint8_t> materials; ///< label per vertex
  std::vector<uint32_t> triangles;///< 3 per triangle, winding as the message says
  size_t vertex_count() const { return materials.size(); }
  size_t triangle_count() const { return triangles.size() / 3; }
};

struct Message {
  uint16_t flags = 0;
  uint32_t session = 0;
  uint32_t chunk_cells = 0;
  uint64_t bone_version = 0;
  uint64_t since = 0;
  uint32_t next_cursor = 0;
  std::vector<Chunk> chunks;

  bool more() const { return flags & FLAG_MORE; }
  bool full() const { return flags & FLAG_FULL; }
  bool cw() const { return flags & FLAG_CW; }
  bool session_frame() const { return flags & FLAG_SESSION_FRAME; }
};

namespace detail {
inline uint16_t u16(const uint8_t* p) { return static_cast<uint16_t>(p[0] | (p[1] << 8)); }
inline uint32_t u32(const uint8_t* p) {
  return uint32_t(p[0]) | (uint32_t(p[1]) << 8) | (uint32_t(p[2]) << 16) |
         (uint32_t(p[3]) << 24);
}
inline uint64_t u64(const uint8_t* p) { return uint64_t(u32(p)) | (uint64_t(u32(p + 4)) << 32); }
inline float f32(const uint8_t* p) {
  uint32_t b = u32(p);
  float f;
  std::memcpy(&f, &b, sizeof f);
  return f;
}
}  // namespace detail

/// Parses one message; throws FormatError on anything out of bounds or inconsistent.
inline Message parse(const uint8_t* data, size_t n) {
  using namespace detail;
  if (n < kHeaderBytes) throw FormatError("mesh message shorter than its header");
  if (std::memcmp(data, "BFMC", 4) != 0) throw FormatError("not a mesh message (magic)");
  if (u16(data + 4) != kFormatVersion)
    throw FormatError("mesh format version " + std::to_string(u16(data + 4)) + " unsupported");
  Message m;
  m.flags = u16(data + 6);
  m.session = u32(data + 8);
  m.chunk_cells = u32(data + 12);
  m.bone_version = u64(data + 16);
  m.since = u64(data + 24);
  m.next_cursor = u32(data + 32);
  uint32_t count = u32(data + 36);
  size_t off = kHeaderBytes;
  // Each chunk takes at least 20 bytes: a count that cannot fit is rejected before any
  // allocation, so a corrupt header cannot make us reserve gigabytes.
  if (count > (n - off) / 20) throw FormatError("chunk_count exceeds the message");
  m.chunks.reserve(count);
  for (uint32_t i = 0; i < count; ++i) {
    if (n - off < 20) throw FormatError("chunk header past the end");
    const uint8_t* c = data + off;
    Chunk ch;
    ch.key = {static_cast<int32_t>(u32(c)), static_cast<int32_t>(u32(c + 4)),
              static_cast<int32_t>(u32(c + 8))};
    uint64_t v = u32(c + 12), t = u32(c + 16);
    uint64_t body = 25 * v;
    uint64_t pad = (4 - ((20 + body) % 4)) % 4;
    uint64_t size = 20 + body + pad + 12 * t;
    if (size > n - off) throw FormatError("chunk larger than the bytes left");
    // MESH.md 3: T = 0 is "no surface, remove the chunk" and comes with V = 0; vertices
    // without triangles would be a surface we cannot draw, so the message is not trusted.
    if (t == 0 && v > 0) throw FormatError("chunk with vertices but no triangles");
    const uint8_t* p = c + 20;
    ch.positions.resize(3 * v);
    for (uint64_t k = 0; k < 3 * v; ++k) ch.positions[k] = f32(p + 4 * k);
    p += 12 * v;
    ch.normals.resize(3 * v);
    for (uint64_t k = 0; k < 3 * v; ++k) ch.normals[k] = f32(p + 4 * k);
    p += 12 * v;
    ch.materials.assign(p, p + v);
    p += v + pad;
    ch.triangles.resize(3 * t);
    for (uint64_t k = 0; k < 3 * t; ++k) {
      uint32_t idx = u32(p + 4 * k);
      if (idx >= v) throw FormatError("triangle index out of range");
      ch.triangles[k] = idx;
    }
    off += size;
    m.chunks.push_back(std::move(ch));
  }
  if (off != n) throw FormatError("trailing bytes after the last chunk");
  return m;
}

inline Message parse(const std::string& bytes) {
  return parse(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
}

/// A chunk as ChunkedMesh holds it: immutable once received, shared, so an engine can take
/// it to another thread without copying its vertices (see take_changes()).
using ChunkPtr = std::shared_ptr<const Chunk>;

/// One changed chunk: its newest mesh, or null when it was removed.
struct ChunkChange {
  ChunkKey key;
  ChunkPtr chunk;
  bool removed() const { return !chunk; }
};

/// The engine's copy of the surface. Not thread-safe by itself (MeshSync guards it); the
/// chunks it hands out are immutable and safe to read on any thread.
class ChunkedMesh {
 public:
  /// The bone version the whole copy is known to be at (MESH.md 4: `have`); meaningful only
  /// once has_have() (before the first complete update, ask without `since`).
  uint64_t have() const { return have_; }
  bool has_have() const { return has_have_; }
  const std::map<ChunkKey, ChunkPtr>& chunks() const { return chunks_; }
  /// The chunk at `key`, or null.
  const Chunk* find(const ChunkKey& key) const {
    auto it = chunks_.find(key);
    return it == chunks_.end() ? nullptr : it->second.get();
  }
  size_t size() const { return chunks_.size(); }

  /// Counters since construction.
  uint64_t chunks_added = 0, chunks_replaced = 0, chunks_removed = 0, full_resets = 0;

  /// Applies one page of an update; returns true when the update is complete (no MORE),
  /// and `have` moved to the lowest bone_version of its pages.
  bool apply(Message&& m) {
    if (!in_update_) {
      in_update_ = true;
      low_ = m.bone_version;
    }
    if (m.bone_version < low_) low_ = m.bone_version;
    if (m.full()) {
      for (const auto& kv : chunks_) dirty_.insert(kv.first);
      chunks_.clear();
      ++full_resets;
    }
    for (Chunk& c : m.chunks) {
      dirty_.insert(c.key);
      auto it = chunks_.find(c.key);
      if (c.triangles.empty()) {  // T = 0: no surface left (MESH.md 3)
        if (it != chunks_.end()) {
          chunks_.erase(it);
          ++chunks_removed;
        }
        continue;
      }
      // A new object per update, never an edit in place: a consumer may still be reading
      // the previous one outside the lock.
      ChunkPtr fresh = std::make_shared<const Chunk>(std::move(c));
      if (it == chunks_.end()) {
        ++chunks_added;
        chunks_.emplace(fresh->key, std::move(fresh));
      } else {
        ++chunks_replaced;
        it->second = std::move(fresh);
      }
    }
    if (m.more()) return false;
    have_ = low_;
    has_have_ = true;
    in_update_ = false;
    return true;
  }

  /// Chunk keys changed (added, replaced or removed) since the last call: what an engine
  /// re-uploads. A key no longer in chunks() was removed.
  std::set<ChunkKey> take_dirty() {
    std::set<ChunkKey> d;
    d.swap(dirty_);
    return d;
  }

  /// The chunks changed since the last call (take_dirty() or take_changes()), each with its
  /// newest mesh (shared, not copied: cheap under a lock even for a first full copy of
  /// hundreds of chunks), or null if it was removed. Ordered by key.
  std::vector<ChunkChange> take_changes() {
    std::vector<ChunkChange> out;
    out.reserve(dirty_.size());
    for (const ChunkKey& k : dirty_) {
      auto it = chunks_.find(k);
      out.push_back({k, it == chunks_.end() ? ChunkPtr() : it->second});
    }
    dirty_.clear();
    return out;
  }

  size_t triangle_count() const {
    size_t n = 0;
    for (const auto& kv : chunks_) n += kv.second->triangle_count();
    return n;
  }

  /// The union of the chunks as Wavefront OBJ text: `v x y z` lines and 1-based `f a b c`,
  /// chunk after chunk, coordinates and winding exactly as received.
  std::string to_obj() const {
    std::string out;
    char line[128];
    size_t base = 1;
    for (const auto& kv : chunks_) {
      const Chunk& c = *kv.second;
      for (size_t i = 0; i < c.vertex_count(); ++i) {
        std::snprintf(line, sizeof line, "v %.9g %.9g %.9g\n",
                      static_cast<double>(c.positions[3 * i]),
                      static_cast<double>(c.positions[3 * i + 1]),
                      static_cast<double>(c.positions[3 * i + 2]));
        out += line;
      }
      for (size_t t = 0; t < c.triangle_count(); ++t) {
        std::snprintf(line, sizeof line, "f %zu %zu %zu\n", base + c.triangles[3 * t],
                      base + c.triangles[3 * t + 1], base + c.triangles[3 * t + 2]);
        out += line;
      }
      base += c.vertex_count();
    }
    return out;
  }

 private:
  std::map<ChunkKey, ChunkPtr> chunks_;
  std::set<ChunkKey> dirty_;
  uint64_t have_ = 0;
  bool has_have_ = false;
  uint64_t low_ = 0;
  bool in_update_ = false;
};

}  // namespace mesh
}  // namespace burrforce
