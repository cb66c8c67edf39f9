// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Threading;

namespace Burrforce.Tests
{
    /// <summary>The groove the way an engine drives it: a "main thread" at ~90 frames/s
    /// publishes the tool pose of the current time (Streamer.Publish), the streamer samples it
    /// at 1 kHz with the chosen smoothing, and the main thread reads Streamer.State each frame.
    /// Reports the steady forces (by time) and what the main thread saw.</summary>
    public static class PublishTest
    {
        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            Frame frame = Frame.Named(opts["frame"]);
            double frameHz = opts.ContainsKey("fps") ? double.Parse(opts["fps"], System.Globalization.CultureInfo.InvariantCulture) : 90.0;
            PoseSmoothing smoothing = opts.ContainsKey("smoothing") && opts["smoothing"] == "hold" ? PoseSmoothing.Hold : PoseSmoothing.Interpolate;
            using (var rest = new BurrRest(opts["http-url"], opts["token"]))
            {
                SessionInfo s = rest.CreateSession("phantom:workpiece", frame.Name);
                try
                {
                    var result = Drive(s, frame, frameHz, smoothing);
                    result["session"] = (long)s.Id;
                    return result;
                }
                finally
                {
                    rest.DeleteSession(s.Id);
                }
            }
        }

        // The groove as a function of time (ms since the start), continuous.
        private static Vec3 PositionMm(double ms)
        {
            if (ms <= GrooveTest.PlungeTicks) return new Vec3(3.0, 0.0, 2.5 - 0.001 * ms);
            ms = Math.Min(ms, GrooveTest.PlungeTicks + GrooveTest.FeedTicks);
            return new Vec3(3.0 + 0.005 * (ms - GrooveTest.PlungeTicks), 0.0, 1.5);
        }

        private static Dictionary<string, object> Drive(SessionInfo s, Frame frame, double frameHz, PoseSmoothing smoothing)
        {
            var tf = new FrameTransform(frame);
            Quat q = Rotations.ShortestArc(frame.DefaultToolAxis, tf.DirectionToEngine(GrooveTest.AxisServer()));
            long start = 0;
            double steadySum0 = 0, steadySum2 = 0;
            long steady = 0, cutting = 0;
            var options = new StreamerOptions { Smoothing = smoothing };
            long framesRendered = 0, framesWithForce = 0;
            double maxForceSeen = 0;
            StreamerCounters counters;
            var delays = new Dictionary<string, object>();
            using (var streamer = new Streamer(s.UdpHost, s.UdpPort, s.Id, s.KeyHex, options))
            {
                // The pose a REPLY answers was sampled about one engine frame before its tick
                // (interpolation delay): the steady window is taken by time, with margins.
                long steadyFromUs = (long)((GrooveTest.SteadyFrom + 2 * 1000.0 / frameHz + 20) * 1000);
                long steadyToUs = (long)((GrooveTest.PlungeTicks + GrooveTest.FeedTicks - 20) * 1000);
                streamer.ReplyReceived += (tick, reply, rt) =>
                {
                    if (reply.Error != 0 || (reply.Status & Protocol.StatusCutting) == 0) return;
                    cutting++;
                    long t = reply.TClientUs - Interlocked.Read(ref start);
                    if (t < steadyFromUs || t > steadyToUs) return;
                    steady++;
                    steadySum0 += reply.Resistive.X;
                    steadySum2 += reply.Resistive.Z;
                };
                double frameMs = 1000.0 / frameHz;
                Interlocked.Exchange(ref start, MonotonicClock.NowUs());
                streamer.Publish(new ToolPose(tf.PointToEngine(PositionMm(0)), q, GrooveTest.Rpm, true));
                streamer.Start();
                long endUs = (GrooveTest.PlungeTicks + GrooveTest.FeedTicks + 100) * 1000L;
                long frameIndex = 0;
                while (true)
                {
                    long now = MonotonicClock.NowUs() - start;
                    if (now > endUs) break;
                    // The engine's frame: move the tool to where it is now, publish, render.
                    streamer.Publish(new ToolPose(tf.PointToEngine(PositionMm(now / 1000.0)), q, GrooveTest.Rpm, true));
                    ForceState st = streamer.State;
                    if (frameIndex == 50) delays["frame_50"] = streamer.InterpolationDelayUs;
                    if (frameIndex == 110) delays["frame_110"] = streamer.InterpolationDelayUs;
                    if (frameIndex == 190) delays["frame_190"] = streamer.InterpolationDelayUs;
                    framesRendered++;
                    if (st.Valid && st.Force.Length > 0) framesWithForce++;
                    maxForceSeen = Math.Max(maxForceSeen, st.Force.Length);
                    frameIndex++;
                    long next = (long)(frameIndex * frameMs * 1000.0);
                    long sleepMs = (next - (MonotonicClock.NowUs() - start)) / 1000;
                    if (sleepMs > 0) Thread.Sleep((int)sleepMs);
                }
                streamer.Stop();
                counters = streamer.Counters;
            }
            return new Dictionary<string, object>
            {
                { "frames", framesRendered }, { "frames_with_force", framesWithForce }, { "max_force_seen_N", maxForceSeen },
                { "ticks", counters.Ticks }, { "replies", counters.Replies }, { "cutting_replies", cutting },
                { "steady_ticks", steady },
                { "steady_feed_N", steady > 0 ? steadySum0 / steady : 0.0 },
                { "steady_normal_N", steady > 0 ? steadySum2 / steady : 0.0 },
                { "smoothing", smoothing.ToString() }, { "interpolation_delay_us", delays }, { "counters", counters.ToString() },
            };
        }
    }
}
