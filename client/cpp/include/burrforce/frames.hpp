// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Engine frames and units (SPEC.md section 6). The server is right-handed, mm, z up; each
// session names the engine's frame once, and every vector is converted at the edge:
// server_vector = M · engine_vector, scaled by s mm per engine unit. Forces stay newtons in
// every frame. Placement (where the server frame sits in the engine's world) is applied as
// in SPEC 6.3.
#pragma once

#include <cmath>
#include <string>

namespace burrforce {

struct Vec3 {
  double x = 0, y = 0, z = 0;
};
struct Quat {
  double x = 0, y = 0, z = 0, w = 1;  ///< component order of Unity, Unreal and Godot
};

inline Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double norm(const Vec3& a) { return std::sqrt(dot(a, a)); }

/// rotate(q, v) as SPEC 6.3 writes it (q normalized first): t = 2 (q_xyz × v),
/// v' = v + w·t + q_xyz × t. Every engine's quaternion product gives the same.
inline Vec3 rotate(const Quat& q_in, const Vec3& v) {
  double n = std::sqrt(q_in.x * q_in.x + q_in.y * q_in.y + q_in.z * q_in.z + q_in.w * q_in.w);
  Quat q{q_in.x / n, q_in.y / n, q_in.z / n, q_in.w / n};
  Vec3 t{2.0 * (q.y * v.z - q.z * v.y), 2.0 * (q.z * v.x - q.x * v.z),
         2.0 * (q.x * v.y - q.y * v.x)};
  return {v.x + q.w * t.x + (q.y * t.z - q.z * t.y), v.y + q.w * t.y + (q.z * t.x - q.x * t.z),
          v.z + q.w * t.z + (q.x * t.y - q.y * t.x)};
}

/// The quaternion turning unit vector `a` onto unit vector `b` by the shortest arc (half a
/// turn about an axis normal to `a` when they are opposite).
inline Quat shortest_arc(const Vec3& a, const Vec3& b) {
  double d = dot(a, b);
  if (d < -1.0 + 1e-12) {
    Vec3 other = std::fabs(a.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0};
    Vec3 axis = cross(a, other);
    double n = norm(axis);
    return {axis.x / n, axis.y / n, axis.z / n, 0.0};
  }
  Vec3 c = cross(a, b);
  double w = 1.0 + d;
  double n = std::sqrt(c.x * c.x + c.y * c.y + c.z * c.z + w * w);
  return {c.x / n, c.y / n, c.z / n, w / n};
}

/// An engine frame of SPEC 6.2.
struct Frame {
  const char* name;
  double m[3][3];        ///< server = M · engine (rows)
  double mm_per_unit;    ///< s
  Vec3 tool_axis;        ///< default local tool axis, burr → handle
  const char* unit;
  /// The mesh `winding` (MESH.md 5) whose triangles this frame's engine draws as front
  /// faces. A convention of each renderer, not of the frame's handedness: Unity and Godot
  /// differ in handedness yet both need the opposite of what their handedness suggests.
  const char* winding;

  double det() const {
    return m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
           m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
           m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  }
  bool right_handed() const { return det() > 0; }
};

namespace frames {
inline const Frame& si_mm() {
  static const Frame f{"si_mm", {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}}, 1.0, {0, 0, 1}, "mm", "ccw"};
  return f;
}
inline const Frame& unity() {
  static const Frame f{"unity", {{0, 0, 1}, {-1, 0, 0}, {0, 1, 0}}, 1000.0, {0, 1, 0}, "m", "ccw"};
  return f;
}
inline const Frame& unreal() {
  static const Frame f{"unreal", {{1, 0, 0}, {0, -1, 0}, {0, 0, 1}}, 10.0, {0, 0, 1}, "cm", "cw"};
  return f;
}
inline const Frame& godot() {
  static const Frame f{"godot", {{0, 0, -1}, {-1, 0, 0}, {0, 1, 0}}, 1000.0, {0, 1, 0}, "m", "cw"};
  return f;
}
inline const Frame& ros() {
  static const Frame f{"ros", {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}}, 1000.0, {0, 0, 1}, "m", "ccw"};
  return f;
}
/// The frame called `name`, or nullptr.
inline const Frame* by_name(const std::string& name) {
  for (const Frame* f : {&si_mm(), &unity(), &unreal(), &godot(), &ros()})
    if (name == f->name) return f;
  return nullptr;
}
}  // namespace frames

/// MESH.md 5's table: `ccw` for si_mm, unity and ros (OpenGL-style tools), `cw` for unreal
/// and godot. A frame of your own without a winding gets `ccw`, the endpoint's default.
inline const char* mesh_winding(const Frame& f) { return f.winding ? f.winding : "ccw"; }
/// The same by frame name (a session's `frame`); nullptr for an unknown name.
inline const char* mesh_winding(const std::string& frame_name) {
  const Frame* f = frames::by_name(frame_name);
  return f ? mesh_winding(*f) : nullptr;
}

/// Conversions between one session's engine frame (with its placement) and the server
/// frame. Engines only need the "from server" half for REPLY fields they re-express; the
/// "to server" half is for tools and tests that think in server millimetres.
class FrameTransform {
 public:
  explicit FrameTransform(const Frame& f, Vec3 placement_position = {},
                          Quat placement_orientation = {})
      : frame_(f), p0_(placement_position) {
    // P's columns are the placement rotation applied to the engine's unit axes.
    Vec3 c0 = rotate(placement_orientation, {1, 0, 0});
    Vec3 c1 = rotate(placement_orientation, {0, 1, 0});
    Vec3 c2 = rotate(placement_orientation, {0, 0, 1});
    double p[3][3] = {{c0.x, c1.x, c2.x}, {c0.y, c1.y, c2.y}, {c0.z, c1.z, c2.z}};
    // A = M · Pᵀ (engine → server axes); its transpose goes back.
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        double s = 0;
        for (int k = 0; k < 3; ++k) s += f.m[i][k] * p[j][k];
        a_[i][j] = s;
      }
    det_ = f.det() > 0 ? 1.0 : -1.0;
  }

  const Frame& frame() const { return frame_; }

  // engine → server
  Vec3 direction_to_server(const Vec3& d) const { return mul(d); }
  Vec3 vector_to_server(const Vec3& v) const { return scale(mul(v), frame_.mm_per_unit); }
  Vec3 point_to_server(const Vec3& p) const {
    return vector_to_server({p.x - p0_.x, p.y - p0_.y, p.z - p0_.z});
  }
  /// The tool axis (burr → handle) in server axes for an engine orientation.
  Vec3 tool_axis_to_server(const Quat& q, const Vec3& local_axis) const {
    Vec3 a = mul(rotate(q, local_axis));
    double n = norm(a);
    return {a.x / n, a.y / n, a.z / n};
  }

  // server → engine
  /// Forces (N), unit directions (vibration axis): never scaled.
  Vec3 direction_from_server(const Vec3& d) const { return mul_t(d); }
  Vec3 vector_from_server(const Vec3& v_mm) const {
    return divide(mul_t(v_mm), frame_.mm_per_unit);
  }
  Vec3 point_from_server(const Vec3& p_mm) const {
    Vec3 v = vector_from_server(p_mm);
    return {v.x + p0_.x, v.y + p0_.y, v.z + p0_.z};
  }
  /// Torque is a pseudovector: a reflection (det -1) flips it (SPEC 6.3).
  Vec3 torque_from_server(const Vec3& t_nmm) const {
    return scale(divide(mul_t(t_nmm), frame_.mm_per_unit), det_);
  }
  /// The engine orientation whose tool axis points along `axis_server` (shortest arc from
  /// the local axis).
  Quat orientation_for_axis(const Vec3& axis_server, const Vec3& local_axis) const {
    return shortest_arc(local_axis, direction_from_server(axis_server));
  }

 private:
  static Vec3 scale(const Vec3& v, double s) { return {v.x * s, v.y * s, v.z * s}; }
  // Dividing (not multiplying by 1/s) keeps results bit-identical to the Python reference.
  static Vec3 divide(const Vec3& v, double s) { return {v.x / s, v.y / s, v.z / s}; }
  Vec3 mul(const Vec3& v) const {
    return {a_[0][0] * v.x + a_[0][1] * v.y + a_[0][2] * v.z,
            a_[1][0] * v.x + a_[1][1] * v.y + a_[1][2] * v.z,
            a_[2][0] * v.x + a_[2][1] * v.y + a_[2][2] * v.z};
  }
  Vec3 mul_t(const Vec3& v) const {
    return {a_[0][0] * v.x + a_[1][0] * v.y + a_[2][0] * v.z,
            a_[0][1] * v.x + a_[1][1] * v.y + a_[2][1] * v.z,
            a_[0][2] * v.x + a_[1][2] * v.y + a_[2][2] * v.z};
  }

  Frame frame_;
  Vec3 p0_;
  double a_[3][3];
  double det_;
};

}  // namespace burrforce
