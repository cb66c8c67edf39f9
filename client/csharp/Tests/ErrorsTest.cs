// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Threading;

namespace Burrforce.Tests
{
    /// <summary>SPEC.md §3.4's answers as the SDK sees them, on a fresh si_mm session.</summary>
    public static class ErrorsTest
    {
        private const long WaitUs = 1000000;

        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            var checks = new Checks();
            var result = new Dictionary<string, object>();
            using (var rest = new BurrRest(opts["http-url"], opts["token"]))
            {
                SessionInfo s = rest.CreateSession("phantom:workpiece", "si_mm");
                try
                {
                    UnknownSession(s, checks, result);
                    BadTag(s, checks, result);
                    BadValueDuplicateMalformed(s, checks, result);
                    StreamerZeroesOnErrors(s, checks, result);
                    RestErrors(rest, s, checks, result);
                }
                finally
                {
                    rest.DeleteSession(s.Id);
                }
            }
            result["passed"] = (long)checks.Passed;
            result["failures"] = checks.Failures;
            return result;
        }

        private static readonly Vec3 Above = new Vec3(3.0, 0.0, 10.0); // mm, clear of the bone

        private static void UnknownSession(SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            using (var c = new BurrClient(s.UdpHost, s.UdpPort, 4000000123u, s.KeyHex))
            {
                try
                {
                    c.Exchange(Above, Quat.Identity, 0.0, false, WaitUs);
                    checks.That(false, "unknown session: answered with a REPLY");
                }
                catch (BurrServerException e)
                {
                    result["unknown_session_notice"] = (long)e.Code;
                    checks.That(c.LastNotice.Session == 4000000123u, "unknown session: the notice names the session");
                    checks.That(!c.LastNotice.Tagged, "unknown session: the notice is untagged");
                }
            }
        }

        private static void BadTag(SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            string wrong = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";
            using (var c = new BurrClient(s.UdpHost, s.UdpPort, s.Id, wrong))
            {
                try
                {
                    c.Exchange(Above, Quat.Identity, 0.0, false, WaitUs);
                    checks.That(false, "bad tag: answered with a REPLY");
                }
                catch (BurrServerException e)
                {
                    result["bad_tag_notice"] = (long)e.Code;
                    checks.That(c.LastNotice.Tagged, "bad tag: the notice is tagged (with the server's key)");
                    checks.That(!Tagger.FromHex(wrong).Verify(new byte[0], 0), "bad tag: (sanity)");
                }
            }
        }

        private static void BadValueDuplicateMalformed(SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            using (var c = new BurrClient(s.UdpHost, s.UdpPort, s.Id, s.KeyHex, 100))
            {
                Reply first = c.Exchange(Above, Quat.Identity, 60000.0, true, WaitUs);
                checks.That(first.Error == 0 && first.Seq == 101 && c.Rules.Stream != 0,
                            "a hello (seq 100) opens a stream; its first POSE gets a good REPLY");

                // BAD_VALUE: a NaN position. The seq is consumed; the REPLY carries no force.
                uint badSeq = c.Send(new Vec3(double.NaN, 0.0, 10.0), Quat.Identity, 60000.0, true);
                MessageKind kind = c.Receive(WaitUs);
                checks.That(kind == MessageKind.Reply, "bad value: answered with a REPLY, got " + kind);
                if (kind == MessageKind.Reply)
                {
                    Reply r = c.LastReply;
                    result["bad_value_error"] = (long)r.Error;
                    checks.That(r.Seq == badSeq, "bad value: the REPLY answers the NaN POSE");
                    checks.That(r.Status == 0, "bad value: status 0");
                    checks.That(r.Force.X == 0.0 && r.Force.Y == 0.0 && r.Force.Z == 0.0, "bad value: force zero");
                    checks.That(r.VibrationAmplitudeN == 0.0, "bad value: no vibration");
                    checks.That(r.Tagged, "bad value: the error REPLY is tagged");
                }
                // The next seq is accepted: the NaN POSE consumed its own.
                Reply next = c.Exchange(Above, Quat.Identity, 60000.0, true, WaitUs);
                checks.That(next.Seq == Sequence.Next(badSeq), "after bad value: the next seq is answered");
                checks.That((next.Status & Protocol.StatusStale) != 0, "after bad value: the velocity estimate restarted (STALE)");

                // A duplicate datagram (the same bytes again) is never answered.
                byte[] again = c.LastDatagram();
                c.SendRaw(again, again.Length);
                long answers = 0;
                long deadline = MonotonicClock.NowUs() + 300000;
                while (MonotonicClock.NowUs() < deadline)
                    if (c.Receive(deadline - MonotonicClock.NowUs()) != MessageKind.None) answers++;
                result["duplicate_answers"] = answers;

                // MALFORMED: a valid header but 12 elements (v1's POSE: no stream element).
                var buf = new byte[256];
                var w = new MsgPackWriter(buf, 0);
                uint seq = c.Rules.NextSeq + 1000;
                long t = MonotonicClock.NowUs();
                w.WriteArrayHeader(12);
                w.WriteUInt((ulong)Protocol.Version); w.WriteUInt(1UL); w.WriteUInt(s.Id); w.WriteUInt(seq); w.WriteUInt(t);
                w.WriteVec3(Above); w.WriteQuat(Quat.Identity); w.WriteFloat64(0.0); w.WriteBool(false);
                w.WriteNil(); w.WriteUInt(0UL);
                w.WriteTagPlaceholder();
                Tagger.FromHex(s.KeyHex).Sign(buf, w.Position);
                c.SendRaw(buf, w.Position);
                kind = c.Receive(WaitUs);
                checks.That(kind == MessageKind.Notice, "malformed: answered with a NOTICE, got " + kind);
                if (kind == MessageKind.Notice)
                {
                    result["malformed_notice"] = (long)c.LastNotice.Error;
                    checks.That(c.LastNotice.Seq == seq && c.LastNotice.TClientUs == t, "malformed: the header is echoed");
                    checks.That(!c.LastNotice.Tagged, "malformed: the notice is untagged");
                }

                // BAD_VERSION: a v1 POSE (12 elements, version 1) gets v1's NOTICE shape, which
                // this client understands so that it can say "update".
                w = new MsgPackWriter(buf, 0);
                seq++;
                w.WriteArrayHeader(12);
                w.WriteUInt((ulong)Protocol.VersionV1); w.WriteUInt(1UL); w.WriteUInt(s.Id); w.WriteUInt(seq); w.WriteUInt(t);
                w.WriteVec3(Above); w.WriteQuat(Quat.Identity); w.WriteFloat64(0.0); w.WriteBool(false);
                w.WriteNil(); w.WriteUInt(0UL);
                w.WriteTagPlaceholder();
                Tagger.FromHex(s.KeyHex).Sign(buf, w.Position);
                c.SendRaw(buf, w.Position);
                kind = c.Receive(WaitUs);
                checks.That(kind == MessageKind.Notice, "bad version: answered with a NOTICE, got " + kind);
                if (kind == MessageKind.Notice)
                {
                    result["bad_version_notice"] = (long)c.LastNotice.Error;
                    checks.That(c.LastNotice.Version == Protocol.VersionV1 && c.LastNotice.Seq == seq && !c.LastNotice.Tagged,
                                "bad version: v1's shape, the header echoed, untagged");
                }
                checks.That(c.Dropped(DropReason.BadTag) == 0 && c.Dropped(DropReason.Malformed) == 0,
                            "nothing the server sent was dropped as forged or malformed");
            }
        }

        /// <summary>The streamer renders zero force for error REPLYs, counts them by code, and
        /// zero force once replies stop (stale after 50 ms).</summary>
        private static void StreamerZeroesOnErrors(SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            var tf = new FrameTransform(Frame.SiMm);
            var errorStates = new List<ForceState>();
            Streamer streamer = null;
            var options = new StreamerOptions
            {
                MaxTicks = 400,
                Source = (long tick, long due, ref ToolPose p) =>
                {
                    // Into the bone and cutting, with a stretch of NaN positions in the middle.
                    Vec3 mm = GrooveTest.PositionMm((int)Math.Min(tick * 4, 2000));
                    p.Position = tick >= 300 && tick < 310 ? new Vec3(double.NaN, 0, 0) : tf.PointToEngine(mm);
                    p.Rotation = Quat.Identity;
                    p.Rpm = 60000.0;
                    p.SpindleOn = true;
                    return true;
                },
            };
            var goodWithForce = 0;
            using (streamer = new Streamer(s.UdpHost, s.UdpPort, s.Id, s.KeyHex, options))
            {
                streamer.ReplyReceived += (tick, reply, rt) =>
                {
                    if (reply.Error != 0) errorStates.Add(streamer.State);
                    else if (reply.Force.Length > 0.0) goodWithForce++;
                };
                streamer.Start();
                checks.That(streamer.Join(20000), "streamer: finished");
                StreamerCounters counters = streamer.Counters;
                result["streamer_error_replies"] = counters.ErrorReplies[Protocol.ErrorBadValue];
                // Ticks skipped by a stall may fall into the NaN stretch.
                long badValue = counters.ErrorReplies[Protocol.ErrorBadValue];
                checks.That(badValue <= 10 && badValue >= 10 - counters.SkippedTicks && badValue > 0,
                            "streamer: the BAD_VALUE replies counted: " + counters);
                checks.That(goodWithForce > 0, "streamer: some good REPLYs carried force");
                foreach (ForceState st in errorStates)
                    checks.That(!st.Valid && st.Force.Length == 0.0 && st.VibrationAmplitudeN == 0.0 && st.Error == 7,
                                "streamer: an error REPLY renders zero");
                Thread.Sleep(120);
                ForceState late = streamer.State;
                checks.That(!late.Valid && late.Force.Length == 0.0 && late.AgeUs > 50000,
                            "streamer: zero force once no REPLY came for 50 ms");
            }
        }

        private static void RestErrors(BurrRest rest, SessionInfo s, Checks checks, Dictionary<string, object> result)
        {
            try
            {
                rest.GetSession(4000000123u);
                checks.That(false, "REST: a missing session answered");
            }
            catch (BurrRestException e)
            {
                result["rest_missing_status"] = (long)e.Status;
                checks.That(e.Status == 404 && e.Detail.Contains("4000000123"), "REST: 404 with the server's detail: " + e.Detail);
            }
            try
            {
                rest.PatchParameters(s.Id, new Dictionary<string, object> { { "bogus", 1L } });
                checks.That(false, "REST: a bad parameter was accepted");
            }
            catch (BurrRestException e)
            {
                checks.That(e.Status == 422 && e.Detail.Contains("bogus"), "REST: 422 names the parameter: " + e.Detail);
            }
            var p = rest.PatchParameters(s.Id, new Dictionary<string, object> { { "us_n_mm2", 1610.2 } });
            checks.That(p != null && Json.GetDouble(p, "us_n_mm2") == 1610.2, "REST: patch returns the parameters");
            checks.That(Json.GetDouble(rest.GetParameters(s.Id), "us_n_mm2") == 1610.2, "REST: get sees the patch");
            rest.RestartStream(s.Id);
            checks.That(rest.GetSession(s.Id).State == "ready", "REST: the session is ready");
            using (var bad = new BurrRest(rest.HttpUrl, "not-the-token"))
            {
                try
                {
                    bad.GetSession(s.Id);
                    checks.That(false, "REST: a wrong token was accepted");
                }
                catch (BurrRestException e)
                {
                    checks.That(e.Status == 401, "REST: a wrong token gets 401, got " + e.Status);
                }
            }
        }
    }
}
