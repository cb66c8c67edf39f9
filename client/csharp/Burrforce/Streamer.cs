// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Threading;

namespace Burrforce
{
    /// <summary>Streams POSEs at a fixed rate on a background thread, off the engine's frame
    /// rate, and keeps the newest believed REPLY for the engine to render.
    ///
    /// Threads: the engine's main thread calls Publish (newest tool pose), State (what to
    /// render) and Counters; everything else (socket, tags, sequence rules, callbacks) runs on
    /// the streamer's own thread. Hand-offs are under one lock held for a struct copy. The
    /// tick loop allocates nothing.</summary>
    public sealed class Streamer : IDisposable
    {
        private readonly UdpLink link;
        private readonly SessionRules rules;
        private readonly StreamerOptions options;
        private readonly double periodUs;
        private readonly object gate = new object();

        // Streamer-thread state.
        private readonly byte[] sendBuffer = new byte[Protocol.MaxPoseBytes + 64];
        private readonly byte[] receiveBuffer = new byte[Protocol.ReceiveBufferBytes];
        private readonly Pose pose = new Pose();
        private readonly Reply reply = new Reply();
        private readonly Notice notice = new Notice();
        private ToolPose tickPose;

        // Shared under gate.
        private ToolPose published;
        private int publishCount;
        private readonly PoseInterpolator interpolator = new PoseInterpolator();
        private ForceState state;
        private long lastGoodUs;
        private bool haveGood;
        private readonly StreamerCounters counters = new StreamerCounters();
        private bool restartRequested;

        private Thread thread;
        private volatile bool stopRequested;
        private volatile bool finished;
        private volatile Exception failure;

        /// <summary>Called on the streamer thread for each believed REPLY.</summary>
        public event ReplyHandler ReplyReceived;
        /// <summary>Called on the streamer thread for each NOTICE about this session, the
        /// handshake's NEW_STREAM and WRONG_STREAM only when they changed the stream.</summary>
        public event NoticeHandler NoticeReceived;

        public Streamer(string host, int port, uint session, string keyHex, StreamerOptions options = null)
        {
            this.options = options ?? new StreamerOptions();
            if (!(this.options.RateHz > 0.0 && this.options.RateHz <= 100000.0))
                throw new ArgumentOutOfRangeException("options", "RateHz must be in (0, 100000]");
            periodUs = 1e6 / this.options.RateHz;
            rules = new SessionRules(session, keyHex, this.options.FirstSeq);
            link = new UdpLink(host, port);
            state.AgeUs = long.MaxValue;
            interpolator.DelayFrames = this.options.InterpolationDelayFrames;
            published.Rotation = Quat.Identity;
        }

        public uint Session { get { return rules.Session; } }

        /// <summary>What ended the thread if it ended by an exception (a socket error, or one
        /// thrown by a PoseSource or an event handler); null otherwise.</summary>
        public Exception Failure { get { return failure; } }
        public bool Running { get { return thread != null && !finished; } }

        public void Start()
        {
            if (thread != null) throw new InvalidOperationException("already started");
            thread = new Thread(Run) { IsBackground = true, Name = "burrforce streamer", Priority = options.Priority };
            thread.Start();
        }

        /// <summary>Asks the thread to stop and waits for it (up to timeoutMs).</summary>
        public bool Stop(int timeoutMs = 1000)
        {
            stopRequested = true;
            return thread == null || thread.Join(timeoutMs);
        }

        /// <summary>Waits for the stream to end by itself (MaxTicks, or the source ending).</summary>
        public bool Join(int timeoutMs) { return thread == null || thread.Join(timeoutMs); }

        /// <summary>Main thread: the tool's newest pose, engine frame and units. Nothing is sent
        /// before the first call.</summary>
        public void Publish(ToolPose toolPose)
        {
            long now = MonotonicClock.NowUs();
            lock (gate)
            {
                published = toolPose;
                publishCount++;
                interpolator.Add(toolPose, now);
            }
        }

        /// <summary>Gives up the stream at the next tick: hellos until the server opens a new
        /// one, whose first tick starts sequence and velocity afresh. Not needed after a REST
        /// restart-stream or a server restart (the server's WRONG_STREAM leads to a hello by
        /// itself); for a teleport of the tool, FlagResetVelocity on one pose is enough.</summary>
        public void RestartStream()
        {
            lock (gate) restartRequested = true;
        }

        /// <summary>What to render now (zero force and no vibration when stale or an error).</summary>
        public ForceState State
        {
            get
            {
                long now = MonotonicClock.NowUs();
                ForceState s;
                bool good;
                long last;
                lock (gate)
                {
                    s = state;
                    good = haveGood;
                    last = lastGoodUs;
                }
                s.AgeUs = good ? now - last : long.MaxValue;
                if (!good || s.AgeUs > options.StaleAfterUs || s.Error != Protocol.ErrorOk) s.ZeroOutput();
                return s;
            }
        }

        /// <summary>How far behind the engine's newest pose the interpolated path is sampled, µs
        /// (PoseSmoothing.Interpolate): the latency smoothing adds.</summary>
        public double InterpolationDelayUs
        {
            get { lock (gate) return interpolator.DelayUs; }
        }

        /// <summary>A snapshot of the counters.</summary>
        public StreamerCounters Counters
        {
            get
            {
                var copy = new StreamerCounters();
                lock (gate) counters.CopyTo(copy);
                copy.Unreachable = link.Unreachable;
                return copy;
            }
        }

        private long Scheduled(long start, long tick)
        {
            return start + (long)Math.Round(tick * periodUs);
        }

        private void Run()
        {
            try
            {
                rules.WarmUp(receiveBuffer, reply, notice);
                Drain();
                MonotonicClock.NowUs();
                long start = MonotonicClock.NowUs();
                long tick = 0;
                while (!stopRequested)
                {
                    if (options.MaxTicks >= 0 && tick >= options.MaxTicks) break;
                    long due = Scheduled(start, tick);
                    WaitUntil(due);
                    if (stopRequested) break;
                    long now = MonotonicClock.NowUs();
                    if (now - due > options.CatchUpTicks * periodUs)
                    {
                        // A stall: skip to the newest tick due rather than catch up in a burst.
                        long newest = (long)Math.Floor((now - start) / periodUs);
                        if (options.MaxTicks >= 0) newest = Math.Min(newest, options.MaxTicks - 1);
                        if (newest > tick)
                        {
                            lock (gate)
                            {
                                counters.SkippedTicks += newest - tick;
                                counters.Ticks += newest - tick;
                            }
                            tick = newest;
                            due = Scheduled(start, tick);
                        }
                    }
                    int sample = SampleTick(tick, due);
                    if (sample < 0) break;
                    if (sample > 0) SendTick(tick, due, now);
                    tick++;
                    Drain();
                }
                long lingerEnd = MonotonicClock.NowUs() + options.LingerUs;
                while (!stopRequested && MonotonicClock.NowUs() < lingerEnd)
                {
                    Drain();
                    Thread.Sleep(1);
                }
                Drain();
            }
            catch (Exception e)
            {
                failure = e;
            }
            finally
            {
                finished = true;
            }
        }

        private void WaitUntil(long due)
        {
            while (!stopRequested)
            {
                Drain();
                long remaining = due - MonotonicClock.NowUs();
                if (remaining <= 0) return;
                if (remaining > options.SpinBelowUs) link.WaitReadable(1000);
                else Thread.Yield();
            }
        }

        // 1: send tickPose; 0: nothing to send yet (the engine has published no pose); −1: stop.
        private int SampleTick(long tick, long due)
        {
            if (options.Source != null) return options.Source(tick, due, ref tickPose) ? 1 : -1;
            lock (gate)
            {
                if (publishCount == 0) return 0;
                if (options.Smoothing == PoseSmoothing.Hold) tickPose = published;
                else interpolator.Sample(due, out tickPose);
            }
            return 1;
        }

        private void SendTick(long tick, long due, long now)
        {
            bool restart;
            lock (gate)
            {
                restart = restartRequested;
                restartRequested = false;
            }
            if (restart) rules.Restart();
            pose.TClientUs = due; // the sample's scheduled time: a late send must not look like faster motion
            pose.Position = tickPose.Position;
            pose.Orientation = tickPose.Rotation;
            pose.Rpm = tickPose.Rpm;
            pose.SpindleOn = tickPose.SpindleOn;
            pose.HasVelocity = tickPose.HasVelocity;
            pose.Velocity = tickPose.Velocity;
            pose.Flags = tickPose.Flags;
            int n = rules.Encode(pose, sendBuffer, tick);
            link.Send(sendBuffer, n);
            lock (gate)
            {
                counters.Sent++;
                if (pose.Stream == Protocol.HelloStream) counters.Hellos++;
                counters.Stream = pose.Stream;
                counters.Ticks++;
                if (now - due > periodUs / 2) counters.LateTicks++;
            }
        }

        private void Drain()
        {
            while (true)
            {
                int n = link.Receive(receiveBuffer, 0);
                if (n < 0) return;
                long arrived = MonotonicClock.NowUs();
                DropReason reason;
                long tick;
                MessageKind kind = rules.Accept(receiveBuffer, n, reply, notice, out reason, out tick);
                if (kind == MessageKind.None)
                {
                    lock (gate) counters.Dropped[(int)reason]++;
                    continue;
                }
                if (kind == MessageKind.Notice)
                {
                    lock (gate)
                    {
                        counters.Notices[StreamerCounters.Slot(notice.Error)]++;
                        counters.Stream = rules.Stream;
                    }
                    var nh = NoticeReceived;
                    if (nh != null) nh(notice);
                    continue;
                }
                RoundTrip rt = RoundTrip.Of(reply, arrived);
                lock (gate)
                {
                    counters.Replies++;
                    if (reply.Error != Protocol.ErrorOk) counters.ErrorReplies[StreamerCounters.Slot(reply.Error)]++;
                    Store(rt, arrived);
                }
                var rh = ReplyReceived;
                if (rh != null) rh(tick, reply, rt);
            }
        }

        // Under gate.
        private void Store(RoundTrip rt, long arrived)
        {
            state.Seq = reply.Seq;
            state.Error = reply.Error;
            state.BoneVersion = reply.BoneVersion;
            state.RttUs = rt.RttUs;
            state.ClockOffsetUs = rt.ClockOffsetUs;
            state.RemovedMm3 = reply.RemovedMm3;
            state.RemovedTotalMm3 += reply.RemovedMm3;
            if (reply.Error != Protocol.ErrorOk)
            {
                // An error REPLY is not a force: render nothing from it (SPEC.md §7.6).
                state.ZeroOutput();
                state.Status = 0;
                return;
            }
            state.Valid = true;
            state.Force = reply.Force;
            state.Torque = reply.Torque;
            state.Resistive = reply.Resistive;
            state.PowerW = reply.PowerW;
            state.VibrationAmplitudeN = reply.VibrationAmplitudeN;
            state.VibrationFrequencyHz = reply.VibrationFrequencyHz;
            state.VibrationAxis = reply.VibrationAxis;
            state.Status = reply.Status;
            state.ProxyPosition = reply.ProxyPosition;
            state.ProxyVelocity = reply.ProxyVelocity;
            state.CouplingStiffness = reply.CouplingStiffness;
            state.CouplingDamping = reply.CouplingDamping;
            state.FeedVelocity = reply.FeedVelocity;
            haveGood = true;
            lastGoodUs = arrived;
        }

        public void Dispose()
        {
            Stop();
            link.Dispose();
        }
    }
}
