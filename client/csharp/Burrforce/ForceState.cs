// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>What to render now: the newest good REPLY, engine axes and units, or zero
    /// force and no vibration when there is none (no good REPLY for StaleAfterUs, or the
    /// newest REPLY was an error: SPEC.md §7.6). A value copy: safe to keep.</summary>
    public struct ForceState
    {
        /// <summary>True when the fields come from a good REPLY younger than the stale limit.</summary>
        public bool Valid;
        /// <summary>Force of the bone on the tool (what the hand feels), N, engine axes.</summary>
        public Vec3 Force;
        /// <summary>Reaction torque about the burr centre, N·L, engine axes.</summary>
        public Vec3 Torque;
        /// <summary>(feed, lateral, normal) of the cutting force, N (frame-free, SPEC.md §7.3).</summary>
        public Vec3 Resistive;
        public double PowerW;
        public double VibrationAmplitudeN;
        public double VibrationFrequencyHz;
        /// <summary>Unit vector, engine axes.</summary>
        public Vec3 VibrationAxis;
        /// <summary>Status bits (Protocol.Status*) of the newest REPLY (0 after an error one).</summary>
        public uint Status;
        /// <summary>Error of the newest REPLY (0 OK; 7 BAD_VALUE; 10 INTERNAL).</summary>
        public int Error;
        /// <summary>Coupling model (SPEC.md §7.5); CouplingStiffness 0 means none.</summary>
        public Vec3 ProxyPosition;
        public Vec3 ProxyVelocity;
        /// <summary>N/L and N·s/L.</summary>
        public double CouplingStiffness;
        public double CouplingDamping;
        /// <summary>Burr velocity the model used, L/s, engine axes.</summary>
        public Vec3 FeedVelocity;
        /// <summary>The bone's version after the newest REPLY's tick (any error value).</summary>
        public ulong BoneVersion;
        /// <summary>Bone removed by the newest REPLY's tick, mm³ (jumpy: average it).</summary>
        public double RemovedMm3;
        /// <summary>Bone removed over every REPLY this streamer believed, mm³.</summary>
        public double RemovedTotalMm3;
        public uint Seq;
        /// <summary>Round trip of the newest REPLY (T4 − T1), µs.</summary>
        public long RttUs;
        /// <summary>Server clock − client clock, µs, from the newest REPLY.</summary>
        public double ClockOffsetUs;
        /// <summary>How old the newest good REPLY is, µs (long.MaxValue: none yet).</summary>
        public long AgeUs;

        public bool Cutting { get { return (Status & Protocol.StatusCutting) != 0; } }
        public bool Contact { get { return (Status & Protocol.StatusContact) != 0; } }
        public bool Forbidden { get { return (Status & Protocol.StatusForbidden) != 0; } }

        /// <summary>Silences everything a hand or a speaker would render.</summary>
        public void ZeroOutput()
        {
            Valid = false;
            Force = Vec3.Zero;
            Torque = Vec3.Zero;
            Resistive = Vec3.Zero;
            PowerW = 0.0;
            VibrationAmplitudeN = 0.0;
            VibrationFrequencyHz = 0.0;
            VibrationAxis = Vec3.Zero;
            // A coupled renderer springs the hand toward the proxy: a stale one would pull it.
            ProxyPosition = Vec3.Zero;
            ProxyVelocity = Vec3.Zero;
            CouplingStiffness = 0.0;
            CouplingDamping = 0.0;
            FeedVelocity = Vec3.Zero;
        }
    }
}
