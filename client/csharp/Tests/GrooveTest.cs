// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;

namespace Burrforce.Tests
{
    /// <summary>The groove every SDK cuts (tests/sdk/conftest.py): a fresh session in a frame,
    /// created with BurrRest, streamed by the Streamer at 1 kHz from a PoseSource, each POSE
    /// stamped with its scheduled time.</summary>
    public static class GrooveTest
    {
        public const int PlungeTicks = 1000, FeedTicks = 1200, Ticks = PlungeTicks + FeedTicks + 1;
        public const int SteadyFrom = PlungeTicks + 240;
        public const double Rpm = 60000.0, AngleDeg = 60.0;

        /// <summary>Tick i's burr centre, server frame, mm (the same arithmetic as conftest.py).</summary>
        public static Vec3 PositionMm(int i)
        {
            if (i <= PlungeTicks) return new Vec3(3.0, 0.0, 2.5 - 0.001 * i);
            return new Vec3(3.0 + 0.005 * (i - PlungeTicks), 0.0, 1.5);
        }

        /// <summary>The tool axis toward the handle, server frame.</summary>
        public static Vec3 AxisServer()
        {
            double a = AngleDeg * (Math.PI / 180.0);
            return new Vec3(-Math.Cos(a), 0.0, Math.Sin(a));
        }

        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            string frameName = opts["frame"];
            using (var rest = new BurrRest(opts["http-url"], opts["token"]))
            {
                SessionInfo s = rest.CreateSession("phantom:workpiece", frameName);
                try
                {
                    string host = opts.ContainsKey("host") ? opts["host"] : s.UdpHost;
                    var result = Cut(host, s.UdpPort, s.Id, s.KeyHex, Frame.Named(frameName));
                    result["session"] = (long)s.Id;
                    result["frame"] = frameName;
                    return result;
                }
                finally
                {
                    rest.DeleteSession(s.Id);
                }
            }
        }

        public static Dictionary<string, object> Cut(string host, int port, uint session, string keyHex, Frame frame)
        {
            var tf = new FrameTransform(frame);
            Quat q = Rotations.ShortestArc(frame.DefaultToolAxis, tf.DirectionToEngine(AxisServer()));
            var positions = new Vec3[Ticks];
            for (int i = 0; i < Ticks; i++) positions[i] = tf.PointToEngine(PositionMm(i));

            var got = new bool[Ticks];
            var status = new uint[Ticks];
            var error = new int[Ticks];
            var resistive = new Vec3[Ticks];
            var force = new Vec3[Ticks];
            var rtt = new long[Ticks];
            var removed = new double[Ticks];
            ulong lastBoneVersion = 0;
            long allocatedFrom = 0, allocatedTo = 0;
            var options = new StreamerOptions
            {
                RateHz = 1000.0,
                MaxTicks = Ticks,
                LingerUs = 100000,
                // Like the Python reference, send every tick (late if this machine stalls),
                // so that the server sees exactly its inputs; skipping is tested by "stall".
                CatchUpTicks = Ticks,
                Source = (long tick, long scheduledUs, ref ToolPose pose) =>
                {
                    // The tick loop (send, receive, verify, decode, hand-off) must not allocate.
                    if (tick == 1100) allocatedFrom = GC.GetAllocatedBytesForCurrentThread();
                    if (tick == 2100) allocatedTo = GC.GetAllocatedBytesForCurrentThread();
                    pose.Position = positions[tick];
                    pose.Rotation = q;
                    pose.Rpm = Rpm;
                    pose.SpindleOn = true;
                    pose.HasVelocity = false;
                    pose.Flags = 0;
                    return true;
                },
            };
            StreamerCounters counters;
            ForceState finalState;
            using (var streamer = new Streamer(host, port, session, keyHex, options))
            {
                streamer.ReplyReceived += (tick, reply, rt) =>
                {
                    if (tick < 0 || tick >= Ticks) return;
                    got[tick] = true;
                    status[tick] = reply.Status;
                    error[tick] = reply.Error;
                    resistive[tick] = reply.Resistive;
                    force[tick] = reply.Force;
                    rtt[tick] = rt.RttUs;
                    removed[tick] = reply.RemovedMm3;
                    lastBoneVersion = reply.BoneVersion;
                };
                streamer.Start();
                if (!streamer.Join(60000)) throw new TimeoutException("the groove did not finish within 60 s");
                counters = streamer.Counters;
                finalState = streamer.State;
            }

            int replies = 0, steady = 0;
            double removedTotal = 0.0, forceSum = 0.0;
            Vec3 resSum = Vec3.Zero, serverForceSum = Vec3.Zero;
            var rtts = new List<long>();
            for (int i = 0; i < Ticks; i++)
            {
                if (!got[i]) continue;
                replies++;
                removedTotal += removed[i];
                rtts.Add(rtt[i]);
                if (i >= SteadyFrom && error[i] == 0 && (status[i] & Protocol.StatusCutting) != 0)
                {
                    steady++;
                    resSum = new Vec3(resSum.X + resistive[i].X, resSum.Y + resistive[i].Y, resSum.Z + resistive[i].Z);
                    forceSum += force[i].Length;
                    Vec3 fs = tf.DirectionToServer(force[i]);
                    serverForceSum = new Vec3(serverForceSum.X + fs.X, serverForceSum.Y + fs.Y, serverForceSum.Z + fs.Z);
                }
            }
            rtts.Sort();
            double k = steady > 0 ? 1.0 / steady : 0.0;
            return new Dictionary<string, object>
            {
                { "ticks", counters.Ticks }, { "sent", counters.Sent }, { "replies", (long)replies },
                { "lost", counters.Ticks - replies }, { "steady_ticks", (long)steady },
                { "steady_feed_N", resSum.X * k }, { "steady_lateral_N", resSum.Y * k }, { "steady_normal_N", resSum.Z * k },
                { "steady_force_N", forceSum * k },
                { "steady_force_server_N", new List<object> { serverForceSum.X * k, serverForceSum.Y * k, serverForceSum.Z * k } },
                { "removed_mm3", removedTotal },
                { "rtt_p50_us", Percentile(rtts, 50.0) }, { "rtt_p99_us", Percentile(rtts, 99.0) },
                { "late_ticks", counters.LateTicks }, { "skipped_ticks", counters.SkippedTicks },
                { "error_replies", counters.ErrorReplyCount }, { "notices", counters.NoticeCount },
                { "new_stream_notices", counters.Notices[Protocol.ErrorNewStream] }, { "hellos", counters.Hellos },
                { "counters", counters.ToString() },
                { "last_bone_version", (long)lastBoneVersion },
                { "allocated_bytes_1000_ticks", allocatedTo - allocatedFrom },
                { "state_bone_version", (long)finalState.BoneVersion },
                { "state_removed_total_mm3", finalState.RemovedTotalMm3 },
            };
        }

        /// <summary>numpy's default (linear) percentile of sorted values.</summary>
        public static double Percentile(List<long> sorted, double p)
        {
            if (sorted.Count == 0) return 0.0;
            double pos = p / 100.0 * (sorted.Count - 1);
            int lo = (int)Math.Floor(pos);
            int hi = Math.Min(lo + 1, sorted.Count - 1);
            return sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo);
        }
    }
}
