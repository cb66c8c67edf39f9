// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Turns poses published at the engine's frame rate into a continuous path that
    /// can be sampled at any tick: piecewise linear through the recent published samples,
    /// evaluated a little over one (smoothed) frame interval in the past, so that the sample
    /// time almost always falls between two known poses even when frames jitter. The delay
    /// adapts slowly; a delay that followed each frame's own interval would make the path jump
    /// back and forth in time, which the server reads as velocity spikes. Not thread-safe
    /// (the Streamer holds its lock around it).</summary>
    public sealed class PoseInterpolator
    {
        private const int Capacity = 8;
        private readonly ToolPose[] poses = new ToolPose[Capacity];
        private readonly long[] times = new long[Capacity];
        private int count;
        private int newest = -1;
        private double meanIntervalUs = -1.0;
        private double appliedDelayUs = -1.0;
        private long lastSampleUs;
        private int intervals;

        /// <summary>Frame intervals averaged plainly before the slow average takes over; until
        /// then the delay follows the average at once (a start-up, the tool not cutting yet).</summary>
        public const int WarmUpIntervals = 16;

        /// <summary>Delay = this × the smoothed frame interval.</summary>
        public double DelayFrames = 1.5;

        public int Count { get { return count; } }

        /// <summary>The delay the path is sampled at, µs: it follows DelayFrames × the smoothed
        /// frame interval at a rate of at most 1 % of the time passing, so that it never
        /// changes the sampled speed by more than 1 %.</summary>
        public double DelayUs { get { return Math.Max(appliedDelayUs, 0.0); } }

        /// <summary>How far a delay change may bend the sampled speed.</summary>
        public double MaxDelayRate = 0.01;

        public void Clear()
        {
            count = 0;
            newest = -1;
            meanIntervalUs = -1.0;
            appliedDelayUs = -1.0;
            intervals = 0;
        }

        public void Add(ToolPose pose, long timeUs)
        {
            if (count > 0)
            {
                long dt = timeUs - times[newest];
                if (dt <= 0) { poses[newest] = pose; return; } // same instant: the newer wins
                double clamped = Math.Min(Math.Max(dt, 1000.0), 100000.0);
                intervals++;
                double weight = Math.Max(1.0 / intervals, 0.05);
                meanIntervalUs = meanIntervalUs < 0 ? clamped : meanIntervalUs + (clamped - meanIntervalUs) * weight;
            }
            newest = (newest + 1) % Capacity;
            poses[newest] = pose;
            times[newest] = timeUs;
            if (count < Capacity) count++;
        }

        /// <summary>The pose at <paramref name="timeUs"/> − delay; false before any Add.
        /// Everything but position and rotation comes from the newest pose.</summary>
        public bool Sample(long timeUs, out ToolPose pose)
        {
            pose = default(ToolPose);
            if (count == 0) return false;
            if (meanIntervalUs >= 0)
            {
                double wanted = DelayFrames * meanIntervalUs;
                if (appliedDelayUs < 0 || intervals <= WarmUpIntervals) appliedDelayUs = wanted;
                else
                {
                    double step = MaxDelayRate * Math.Max(timeUs - lastSampleUs, 0);
                    appliedDelayUs += Math.Max(-step, Math.Min(step, wanted - appliedDelayUs));
                }
            }
            lastSampleUs = timeUs;
            pose = poses[newest];
            if (count == 1) return true;
            double target = timeUs - DelayUs;
            if (target >= times[newest]) return true; // the engine stalled: hold the newest
            // Walk back from the newest sample to the segment holding the target.
            int later = newest;
            for (int k = 1; k < count; k++)
            {
                int earlier = (newest - k + Capacity) % Capacity;
                if (target >= times[earlier])
                {
                    double alpha = (target - times[earlier]) / (times[later] - times[earlier]);
                    Vec3 a = poses[earlier].Position, b = poses[later].Position;
                    pose.Position = new Vec3(a.X + (b.X - a.X) * alpha, a.Y + (b.Y - a.Y) * alpha, a.Z + (b.Z - a.Z) * alpha);
                    pose.Rotation = Rotations.Nlerp(poses[earlier].Rotation, poses[later].Rotation, alpha);
                    return true;
                }
                later = earlier;
            }
            // Older than every sample kept: the oldest.
            pose.Position = poses[later].Position;
            pose.Rotation = poses[later].Rotation;
            return true;
        }
    }
}
