// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>Supplies the pose for one tick: <paramref name="tick"/> counts from 0 and
    /// <paramref name="scheduledUs"/> is the tick's scheduled time on MonotonicClock (what the
    /// POSE is stamped with). Runs on the streamer thread: keep it short. Return false to end
    /// the stream.</summary>
    public delegate bool PoseSource(long tick, long scheduledUs, ref ToolPose pose);

    /// <summary>A believed REPLY, on the streamer thread. <paramref name="reply"/> is reused
    /// for the next one: copy what you keep. <paramref name="tick"/> is the tick of the POSE
    /// it answers.</summary>
    public delegate void ReplyHandler(long tick, Reply reply, RoundTrip roundTrip);

    /// <summary>A NOTICE about this session, on the streamer thread (a diagnostic, never a force).</summary>
    public delegate void NoticeHandler(Notice notice);

    /// <summary>How the streamer turns the engine's frame-rate poses into tick-rate poses.</summary>
    public enum PoseSmoothing
    {
        /// <summary>Interpolate between the recent published poses, about 1.5 engine frames
        /// behind (PoseInterpolator): the server sees smooth motion (its velocity estimate
        /// differentiates positions over the 1 ms stamps, and a pose held for a whole frame
        /// then jumping reads as standstill followed by a spike).</summary>
        Interpolate = 0,
        /// <summary>Send the newest published pose as it is (lowest latency, steppy).</summary>
        Hold = 1,
    }

    public sealed class StreamerOptions
    {
        /// <summary>POSEs per second (1000 typical; the absolute schedule never drifts).</summary>
        public double RateHz = 1000.0;
        /// <summary>First sequence number (any works: the server accepts whatever seq opens a
        /// stream, and seqs go on counting across streams).</summary>
        public uint FirstSeq = 1;
        /// <summary>No good REPLY for this long: render zero force and no vibration (SPEC.md §7.6).</summary>
        public long StaleAfterUs = 50000;
        /// <summary>Stop after this many ticks (sent or skipped); −1: run until Stop.</summary>
        public long MaxTicks = -1;
        /// <summary>After the last tick (MaxTicks or the source ending), keep receiving this long.</summary>
        public long LingerUs = 50000;
        /// <summary>Null: sample the pose the engine publishes (Streamer.Publish). Else the
        /// pose of each tick comes from here.</summary>
        public PoseSource Source;
        public PoseSmoothing Smoothing = PoseSmoothing.Interpolate;
        /// <summary>Interpolate: how many (smoothed) engine frames behind the newest published
        /// pose the path is sampled. Lower is less latency; below ~1.2 a late frame leaves the
        /// path without a pose to go to, and it stalls for a moment.</summary>
        public double InterpolationDelayFrames = 1.5;
        /// <summary>While more than this is left before a tick, the thread sleeps in the
        /// socket's wait (waking at once for a REPLY; .NET's waits have 1 ms resolution);
        /// closer to the tick it yields the CPU in a loop. Large (e.g. 1000): ticks leave
        /// within a few µs of schedule but a core spins; small (default): ticks leave up to
        /// ~1 ms late, stamped with their scheduled time all the same (so the server's velocity
        /// estimate is unaffected), and the thread mostly sleeps, which also keeps the
        /// scheduler from parking it for milliseconds on a busy machine.</summary>
        public long SpinBelowUs = 300;
        /// <summary>Behind by more than this many periods (a stall: GC, a scene load, a busy
        /// machine): jump to the present tick and skip the missed ones instead of sending them
        /// in a burst. Behind by up to this many: the late ticks go out back to back, each with
        /// its own scheduled stamp.</summary>
        public int CatchUpTicks = 10;
        public System.Threading.ThreadPriority Priority = System.Threading.ThreadPriority.Highest;
    }
}
