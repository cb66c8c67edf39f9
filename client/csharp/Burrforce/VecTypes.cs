// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>A 3-vector of doubles (a position, velocity, force, axis...). Its unit and
    /// frame are said by whoever holds it.</summary>
    public struct Vec3
    {
        public double X, Y, Z;

        public Vec3(double x, double y, double z) { X = x; Y = y; Z = z; }

        public static readonly Vec3 Zero = new Vec3(0.0, 0.0, 0.0);

        public double Length { get { return System.Math.Sqrt(X * X + Y * Y + Z * Z); } }

        public override string ToString()
        {
            return string.Format(System.Globalization.CultureInfo.InvariantCulture,
                "({0:R}, {1:R}, {2:R})", X, Y, Z);
        }
    }

    /// <summary>A quaternion (x, y, z, w), w last, in the engine's own components.</summary>
    public struct Quat
    {
        public double X, Y, Z, W;

        public Quat(double x, double y, double z, double w) { X = x; Y = y; Z = z; W = w; }

        public static readonly Quat Identity = new Quat(0.0, 0.0, 0.0, 1.0);

        public override string ToString()
        {
            return string.Format(System.Globalization.CultureInfo.InvariantCulture,
                "({0:R}, {1:R}, {2:R}, {3:R})", X, Y, Z, W);
        }
    }
}
