// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>The tool as the engine sees it, engine frame and units: what one POSE carries.</summary>
    public struct ToolPose
    {
        /// <summary>Burr centre, engine length unit (Unity, Godot: m).</summary>
        public Vec3 Position;
        /// <summary>The tool's world rotation, the engine's own quaternion components.</summary>
        public Quat Rotation;
        /// <summary>Spindle speed, rev/min; + is the session's forward spin.</summary>
        public double Rpm;
        public bool SpindleOn;
        /// <summary>True to send Velocity (L/s, engine axes); false lets the server estimate it.</summary>
        public bool HasVelocity;
        public Vec3 Velocity;
        /// <summary>POSE flags such as Protocol.FlagNoCarve or FlagResetVelocity (the stream handshake is the SDK's job).</summary>
        public uint Flags;

        public ToolPose(Vec3 position, Quat rotation, double rpm, bool spindleOn)
        {
            Position = position;
            Rotation = rotation;
            Rpm = rpm;
            SpindleOn = spindleOn;
            HasVelocity = false;
            Velocity = Vec3.Zero;
            Flags = 0;
        }
    }
}
