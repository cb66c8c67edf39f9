// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;

namespace Burrforce.Tests
{
    /// <summary>The stream handshake against the live server, on a fresh si_mm session: a
    /// client takes a stream with a hello; a new client object with the same key, numbering
    /// from 1 again, gets its own stream from its first hello and a REPLY to its second
    /// datagram (v1 had it wait out a second of silence); the first client's captured POSE,
    /// sent again, gets WRONG_STREAM and no REPLY; a replayed hello does not disturb the open
    /// stream; after a REST restart-stream the client says hello by itself; a Streamer, new
    /// again, streams at once.</summary>
    public static class HandshakeTest
    {
        private const long WaitUs = 1000000;
        // What arrives after this long is not an answer to what was sent (loopback).
        private const long QuietUs = 300000;
        private static readonly Vec3 Above = new Vec3(3.0, 0.0, 10.0); // mm, clear of the bone

        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            var checks = new Checks();
            var result = new Dictionary<string, object>();
            using (var rest = new BurrRest(opts["http-url"], opts["token"]))
            {
                SessionInfo s = rest.CreateSession("phantom:workpiece", "si_mm");
                try
                {
                    Exercise(rest, s, checks, result);
                }
                finally
                {
                    rest.DeleteSession(s.Id);
                }
                result["session"] = (long)s.Id;
            }
            result["passed"] = (long)checks.Passed;
            result["failures"] = checks.Failures;
            return result;
        }

        private static Reply Exchange(BurrClient c) { return c.Exchange(Above, Quat.Identity, 60000.0, true, WaitUs); }

        // Everything believed within QuietUs, by kind.
        private static void Listen(BurrClient c, out long replies, out long notices)
        {
            replies = notices = 0;
            long deadline = MonotonicClock.NowUs() + QuietUs;
            while (true)
            {
                long remaining = deadline - MonotonicClock.NowUs();
                if (remaining <= 0) return;
                MessageKind k = c.Receive(remaining);
                if (k == MessageKind.Reply) replies++;
                else if (k == MessageKind.Notice) notices++;
            }
        }

        private static void Exercise(BurrRest rest, SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            using (var a = new BurrClient(s.UdpHost, s.UdpPort, s.Id, s.KeyHex))
            using (var b = new BurrClient(s.UdpHost, s.UdpPort, s.Id, s.KeyHex))
            {
                // A: a hello (seq 1), the stream's first POSE (seq 2, STALE: nothing to
                // differentiate yet), then a stream in use up to seq 22.
                Reply first = Exchange(a);
                uint streamA = a.Rules.Stream;
                checks.That(streamA != 0 && a.Sent == 2 && a.Notices == 1 && first.Seq == 2, "A: a hello, then its stream's first REPLY: " + a.Sent);
                checks.That((first.Status & Protocol.StatusStale) != 0, "A: the stream's first tick is STALE");
                for (int i = 0; i < 20; i++) Exchange(a);
                byte[] captured = a.LastDatagram();
                uint capturedSeq = a.Rules.NextSeq - 1u;
                checks.That(a.Replies == 21 && a.Rules.Stream == streamA, "A: 21 REPLYs on one stream");

                // B: same key, seq from 1 again, right after A's stream was used.
                b.Send(Above, Quat.Identity, 60000.0, true);
                byte[] hello = b.LastDatagram();
                MessageKind kind = b.Receive(WaitUs);
                checks.That(kind == MessageKind.Notice && b.LastNotice.Error == Protocol.ErrorNewStream && b.LastNotice.Seq == 1
                            && b.LastNotice.Tagged, "B: its hello (seq 1) answered by a tagged NEW_STREAM, got " + kind);
                uint streamB = b.Rules.Stream;
                checks.That(streamB != 0 && streamB != streamA, "B: a stream of its own: " + streamB + " (A's " + streamA + ")");
                long t0 = MonotonicClock.NowUs();
                uint seq2 = b.Send(Above, Quat.Identity, 60000.0, true);
                kind = b.Receive(WaitUs);
                result["b_second_datagram_rtt_us"] = MonotonicClock.NowUs() - t0;
                checks.That(kind == MessageKind.Reply && b.LastReply.Seq == 2 && seq2 == 2 && b.LastReply.Error == 0,
                            "B: its second datagram (seq 2, below A's 22) answered by a REPLY, got " + kind);
                result["b_datagrams_to_first_reply"] = kind == MessageKind.Reply ? b.Sent : -1L;

                // A's captured POSE again: its stream closed when B's opened.
                a.SendRaw(captured, captured.Length);
                kind = a.Receive(WaitUs);
                checks.That(kind == MessageKind.Notice, "replay: answered with a NOTICE, got " + kind);
                if (kind == MessageKind.Notice)
                {
                    result["replay_notice"] = (long)a.LastNotice.Error;
                    checks.That(a.LastNotice.Stream == streamA && a.LastNotice.Seq == capturedSeq && a.LastNotice.Tagged,
                                "replay: WRONG_STREAM names A's stream and seq, tagged");
                }
                checks.That(a.Rules.Stream == 0, "replay: A, believing it, says hello again");
                long replayReplies, replayNotices;
                Listen(a, out replayReplies, out replayNotices);
                result["replay_replies"] = replayReplies + (kind == MessageKind.Reply ? 1 : 0);

                // B's own hello again: the server offers a stream, B keeps the one it has.
                long staleBefore = b.Dropped(DropReason.Stale);
                b.SendRaw(hello, hello.Length);
                long helloReplies, helloNotices;
                Listen(b, out helloReplies, out helloNotices);
                checks.That(helloReplies == 0 && helloNotices == 0 && b.Dropped(DropReason.Stale) == staleBefore + 1,
                            "replayed hello: its NEW_STREAM dropped as stale by B");
                Reply still = Exchange(b);
                checks.That(b.Rules.Stream == streamB && still.Error == 0 && b.Sent == 3, "replayed hello: B's stream goes on");

                // REST restart-stream: B's next POSE gets WRONG_STREAM, B says hello, streams on.
                long noticesBefore = b.Notices;
                rest.RestartStream(s.Id);
                Reply after = Exchange(b);
                uint streamC = b.Rules.Stream;
                checks.That(streamC != 0 && streamC != streamB && streamC != streamA, "restart-stream: a new stream " + streamC);
                checks.That(b.Notices - noticesBefore == 2 && b.Sent == 6 && after.Seq == 6,
                            "restart-stream: WRONG_STREAM, hello, NEW_STREAM, REPLY with seqs going on: " + b.Sent);
                result["streams"] = new List<object> { (long)streamA, (long)streamB, (long)streamC };
            }

            // A Streamer, new again and numbering from 1: streams at once.
            long firstTick = -1;
            var options = new StreamerOptions
            {
                MaxTicks = 200,
                Source = (long tick, long due, ref ToolPose p) =>
                {
                    p.Position = Above;
                    p.Rotation = Quat.Identity;
                    p.Rpm = 60000.0;
                    p.SpindleOn = true;
                    return true;
                },
            };
            using (var streamer = new Streamer(s.UdpHost, s.UdpPort, s.Id, s.KeyHex, options))
            {
                streamer.ReplyReceived += (tick, reply, rt) => { if (firstTick < 0) firstTick = tick; };
                streamer.Start();
                checks.That(streamer.Join(20000), "streamer: finished");
                StreamerCounters counters = streamer.Counters;
                result["streamer_hellos"] = counters.Hellos;
                result["streamer_first_reply_tick"] = firstTick;
                result["streamer_counters"] = counters.ToString();
                checks.That(counters.Notices[Protocol.ErrorNewStream] == 1 && counters.NoticeCount == 1 && counters.Stream != 0,
                            "streamer: one stream taken: " + counters);
                // Hellos are never ticked: REPLYs answer only the POSEs after them.
                checks.That(counters.Hellos >= 1 && counters.Replies > 0 && counters.Replies <= counters.Sent - counters.Hellos,
                            "streamer: REPLYs to the POSEs after the hellos: " + counters);
                checks.That(firstTick >= counters.Hellos, "streamer: the first REPLY answers a tick after the hellos: " + firstTick);
            }
        }
    }
}
