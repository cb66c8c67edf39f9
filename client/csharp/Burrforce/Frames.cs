// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>An engine frame (SPEC.md §6.2): server_vector = M · engine_vector, and s = mm
    /// per engine length unit. The server frame is right-handed, mm, x forward, y left, z up.</summary>
    public sealed class Frame
    {
        public readonly string Name;
        /// <summary>M row-major: M[3*row + column].</summary>
        private readonly double[] m;
        public readonly double MmPerUnit;
        public readonly string LengthUnit;
        /// <summary>Default local tool axis, from the burr toward the handle, engine axes.</summary>
        public readonly Vec3 DefaultToolAxis;
        /// <summary>The winding (MESH.md §5) this engine draws as front faces: "ccw" or "cw".</summary>
        public readonly string MeshWinding;

        private Frame(string name, double[] m, double mmPerUnit, string unit, Vec3 toolAxis, string winding)
        {
            Name = name; this.m = m; MmPerUnit = mmPerUnit; LengthUnit = unit;
            DefaultToolAxis = toolAxis; MeshWinding = winding;
        }

        public double M(int row, int column) { return m[3 * row + column]; }

        /// <summary>det M: +1 right-handed, −1 for the reflections (Unity, Unreal).</summary>
        public double Determinant
        {
            get
            {
                return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
                     + m[2] * (m[3] * m[7] - m[4] * m[6]);
            }
        }

        public bool RightHanded { get { return Determinant > 0.0; } }

        public static readonly Frame SiMm = new Frame("si_mm", new double[] { 1, 0, 0, 0, 1, 0, 0, 0, 1 }, 1.0, "mm", new Vec3(0, 0, 1), "ccw");
        public static readonly Frame Unity = new Frame("unity", new double[] { 0, 0, 1, -1, 0, 0, 0, 1, 0 }, 1000.0, "m", new Vec3(0, 1, 0), "ccw");
        public static readonly Frame Unreal = new Frame("unreal", new double[] { 1, 0, 0, 0, -1, 0, 0, 0, 1 }, 10.0, "cm", new Vec3(0, 0, 1), "cw");
        public static readonly Frame Godot = new Frame("godot", new double[] { 0, 0, -1, -1, 0, 0, 0, 1, 0 }, 1000.0, "m", new Vec3(0, 1, 0), "cw");
        public static readonly Frame Ros = new Frame("ros", new double[] { 1, 0, 0, 0, 1, 0, 0, 0, 1 }, 1000.0, "m", new Vec3(0, 0, 1), "ccw");

        private static readonly Frame[] All = { SiMm, Unity, Unreal, Godot, Ros };

        /// <summary>The frame called <paramref name="name"/>; ArgumentException lists the known ones.</summary>
        public static Frame Named(string name)
        {
            foreach (var f in All) if (f.Name == name) return f;
            throw new ArgumentException("unknown frame '" + name + "'; choose one of si_mm, unity, unreal, godot, ros");
        }
    }

    /// <summary>Conversions between an engine frame (with the session's placement) and the
    /// server frame (SPEC.md §6.3). x_s = s·A·x_e + b with A = M·Pᵀ orthogonal (det ±1) and
    /// b = −s·A·p0. The arithmetic follows the Python reference's order so that the same
    /// inputs give bit-identical outputs.</summary>
    public sealed class FrameTransform
    {
        public readonly Frame Frame;
        private readonly double[] a = new double[9];
        private readonly Vec3 offsetMm;
        public readonly double Det;

        public FrameTransform(Frame frame) : this(frame, Vec3.Zero, Quat.Identity) { }

        /// <param name="placementPosition">where the server frame's origin lies in the engine's world, L</param>
        /// <param name="placementOrientation">the server frame's rotation in the engine's world (engine quaternion)</param>
        public FrameTransform(Frame frame, Vec3 placementPosition, Quat placementOrientation)
        {
            if (frame == null) throw new ArgumentNullException("frame");
            Frame = frame;
            // P's columns are the rotated unit vectors; A = M·Pᵀ.
            Vec3 c0 = Rotations.Rotate(placementOrientation, new Vec3(1, 0, 0));
            Vec3 c1 = Rotations.Rotate(placementOrientation, new Vec3(0, 1, 0));
            Vec3 c2 = Rotations.Rotate(placementOrientation, new Vec3(0, 0, 1));
            double[] p = { c0.X, c1.X, c2.X, c0.Y, c1.Y, c2.Y, c0.Z, c1.Z, c2.Z };
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                {
                    double sum = 0.0;
                    for (int k = 0; k < 3; k++) sum += frame.M(i, k) * p[3 * j + k];
                    a[3 * i + j] = sum;
                }
            double s = frame.MmPerUnit;
            Vec3 p0 = new Vec3(placementPosition.X * s, placementPosition.Y * s, placementPosition.Z * s);
            Vec3 ap0 = Apply(p0);
            offsetMm = new Vec3(-ap0.X + 0.0, -ap0.Y + 0.0, -ap0.Z + 0.0);
            Det = Math.Sign(frame.Determinant);
        }

        public double Scale { get { return Frame.MmPerUnit; } }

        private Vec3 Apply(Vec3 v)
        {
            return new Vec3(a[0] * v.X + a[1] * v.Y + a[2] * v.Z,
                            a[3] * v.X + a[4] * v.Y + a[5] * v.Z,
                            a[6] * v.X + a[7] * v.Y + a[8] * v.Z);
        }

        private Vec3 ApplyTransposed(Vec3 v)
        {
            return new Vec3(a[0] * v.X + a[3] * v.Y + a[6] * v.Z,
                            a[1] * v.X + a[4] * v.Y + a[7] * v.Z,
                            a[2] * v.X + a[5] * v.Y + a[8] * v.Z);
        }

        // engine → server

        /// <summary>An engine point (L) → server frame, mm.</summary>
        public Vec3 PointToServer(Vec3 p)
        {
            double s = Scale;
            Vec3 r = Apply(new Vec3(p.X * s, p.Y * s, p.Z * s));
            return new Vec3(r.X + offsetMm.X, r.Y + offsetMm.Y, r.Z + offsetMm.Z);
        }

        /// <summary>A direction or force (unitless or N) from engine axes to server axes.</summary>
        public Vec3 DirectionToServer(Vec3 d) { return Apply(d); }

        /// <summary>A velocity or displacement: L(/s), engine axes → mm(/s), server axes.</summary>
        public Vec3 VectorToServer(Vec3 v)
        {
            Vec3 d = Apply(v);
            double s = Scale;
            return new Vec3(d.X * s, d.Y * s, d.Z * s);
        }

        /// <summary>The tool axis (toward the handle) in server axes for an engine rotation.</summary>
        public Vec3 ToolAxisToServer(Quat q, Vec3 localToolAxis)
        {
            return Rotations.Normalized(Apply(Rotations.Rotate(q, localToolAxis)));
        }

        // server → engine

        /// <summary>A force (N) or direction: server axes → engine axes.</summary>
        public Vec3 DirectionToEngine(Vec3 d) { return ApplyTransposed(d); }

        /// <summary>A velocity or displacement: mm(/s) → L(/s), engine axes.</summary>
        public Vec3 VectorToEngine(Vec3 v)
        {
            Vec3 d = ApplyTransposed(v);
            double s = Scale;
            return new Vec3(d.X / s, d.Y / s, d.Z / s);
        }

        /// <summary>A server point (mm) → engine point (L).</summary>
        public Vec3 PointToEngine(Vec3 p)
        {
            return VectorToEngine(new Vec3(p.X - offsetMm.X, p.Y - offsetMm.Y, p.Z - offsetMm.Z));
        }

        /// <summary>A torque (pseudovector) N·mm, server axes → N·L, engine axes.</summary>
        public Vec3 TorqueToEngine(Vec3 t)
        {
            Vec3 d = ApplyTransposed(t);
            double k = Det / Scale;
            return new Vec3(d.X * k, d.Y * k, d.Z * k);
        }

        /// <summary>An engine torque (N·L) → server axes, N·mm.</summary>
        public Vec3 TorqueToServer(Vec3 t)
        {
            Vec3 d = Apply(t);
            double k = Det * Scale;
            return new Vec3(d.X * k, d.Y * k, d.Z * k);
        }
    }

    /// <summary>Quaternion helpers with the formula every engine uses (SPEC.md §6.3).</summary>
    public static class Rotations
    {
        /// <summary>Rotates v by q (x, y, z, w), q normalized first:
        /// t = 2 (q_xyz × v), v' = v + w·t + q_xyz × t.</summary>
        public static Vec3 Rotate(Quat q, Vec3 v)
        {
            double n = Math.Sqrt(q.X * q.X + q.Y * q.Y + q.Z * q.Z + q.W * q.W);
            double x = q.X / n, y = q.Y / n, z = q.Z / n, w = q.W / n;
            double tx = 2.0 * (y * v.Z - z * v.Y);
            double ty = 2.0 * (z * v.X - x * v.Z);
            double tz = 2.0 * (x * v.Y - y * v.X);
            return new Vec3(v.X + w * tx + (y * tz - z * ty),
                            v.Y + w * ty + (z * tx - x * tz),
                            v.Z + w * tz + (x * ty - y * tx));
        }

        public static Vec3 Normalized(Vec3 v)
        {
            double n = v.Length;
            return n > 0.0 ? new Vec3(v.X / n, v.Y / n, v.Z / n) : v;
        }

        public static Vec3 Cross(Vec3 a, Vec3 b)
        {
            return new Vec3(a.Y * b.Z - a.Z * b.Y, a.Z * b.X - a.X * b.Z, a.X * b.Y - a.Y * b.X);
        }

        public static double Dot(Vec3 a, Vec3 b) { return a.X * b.X + a.Y * b.Y + a.Z * b.Z; }

        /// <summary>The shortest-arc quaternion rotating unit vector a onto unit vector b, in
        /// the (right-handed) component algebra engines use for their quaternions.</summary>
        public static Quat ShortestArc(Vec3 a, Vec3 b)
        {
            double dot = Dot(a, b);
            if (dot < -1.0 + 1e-12)
            {
                // Opposite: half a turn about any axis normal to a.
                Vec3 helper = Math.Abs(a.X) < 0.9 ? new Vec3(1, 0, 0) : new Vec3(0, 1, 0);
                Vec3 axis = Normalized(Cross(a, helper));
                return new Quat(axis.X, axis.Y, axis.Z, 0.0);
            }
            Vec3 c = Cross(a, b);
            double w = 1.0 + dot;
            double n = Math.Sqrt(c.X * c.X + c.Y * c.Y + c.Z * c.Z + w * w);
            return new Quat(c.X / n, c.Y / n, c.Z / n, w / n);
        }

        /// <summary>Normalized linear interpolation of rotations along the shorter way.</summary>
        public static Quat Nlerp(Quat a, Quat b, double t)
        {
            double dot = a.X * b.X + a.Y * b.Y + a.Z * b.Z + a.W * b.W;
            double sign = dot < 0.0 ? -1.0 : 1.0;
            double x = a.X + (sign * b.X - a.X) * t, y = a.Y + (sign * b.Y - a.Y) * t;
            double z = a.Z + (sign * b.Z - a.Z) * t, w = a.W + (sign * b.W - a.W) * t;
            double n = Math.Sqrt(x * x + y * y + z * z + w * w);
            return n > 0.0 ? new Quat(x / n, y / n, z / n, w / n) : b;
        }
    }
}
