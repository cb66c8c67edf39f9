// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Security.Cryptography;

namespace Burrforce.Tests
{
    /// <summary>Offline checks of the core: the decoder's accepted forms and limits
    /// (SPEC.md §2.2, §2.4), fuzzing, HMAC against the BCL's, sequence arithmetic, round
    /// trip, frames, the session rules, JSON and the mesh-message parser.</summary>
    public static class SelfTest
    {
        private const string Key = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

        public static Dictionary<string, object> Run()
        {
            var c = new Checks();
            var result = new Dictionary<string, object>();
            AcceptedForms(c);
            Limits(c);
            result["fuzz_cases"] = Fuzz(c);
            Hmac(c);
            SequenceAndTiming(c);
            Frames(c);
            Rules(c);
            JsonChecks(c);
            MeshParser(c);
            Interpolation(c);
            Endpoints(c);
            Zeroing(c);
            result["passed"] = (long)c.Passed;
            result["failures"] = c.Failures;
            return result;
        }

        // A NOTICE / REPLY built token by token from raw msgpack bytes.
        private static byte[] B(params object[] parts)
        {
            var list = new List<byte>();
            foreach (object p in parts)
            {
                if (p is byte[]) list.AddRange((byte[])p);
                else if (p is string) list.AddRange(Hex.Decode((string)p));
                else if (p is int) list.Add((byte)(int)p);
                else throw new ArgumentException();
            }
            return list.ToArray();
        }

        private static string F64(double d)
        {
            var buf = new byte[9];
            var w = new MsgPackWriter(buf, 0);
            w.WriteFloat64(d);
            return Hex.Encode(buf);
        }

        private static byte[] CanonicalReply(uint seq, Tagger tagger, Action<Reply> edit = null)
        {
            var r = new Reply
            {
                Session = 1, Seq = seq, TClientUs = 1000000, TRecvUs = 5000250, TSendUs = 5000300, Status = 3,
                Force = new Vec3(-0.75, 0, 1), Resistive = new Vec3(-0.75, 0, 1), Torque = new Vec3(0, 0, -0.375),
                PowerW = 9.375, VibrationAmplitudeN = 0.5, VibrationFrequencyHz = 1000, VibrationAxis = new Vec3(-0.6, 0, 0.8),
                RemovedMm3 = 0.01171875, BoneVersion = 17, FeedVelocity = new Vec3(3, 0, 0),
            };
            if (edit != null) edit(r);
            var buf = new byte[1024];
            int n = Codec.EncodeReply(r, tagger, buf);
            var d = new byte[n];
            Buffer.BlockCopy(buf, 0, d, 0, n);
            return d;
        }

        private static MessageKind Decode(byte[] d, Reply r, Notice n)
        {
            return Codec.TryDecodeServerMessage(d, d.Length, r, n);
        }

        private static void AcceptedForms(Checks c)
        {
            var r = new Reply();
            var n = new Notice();
            // SPEC §9.2's REPLY is what our encoder writes.
            byte[] spec = Hex.Decode("dc00180202012ace000f4240ce004c4c3ace004c4c6c000393cbbfe8000000000000cb0000000000000000cb3ff0" +
                "00000000000093cbbfe8000000000000cb0000000000000000cb3ff000000000000093cb0000000000000000cb00" +
                "00000000000000cbbfd8000000000000cb4022c00000000000cb3fe0000000000000cb408f40000000000093cbbf" +
                "e3333333333333cb0000000000000000cb3fe999999999999a93cb0000000000000000cb0000000000000000cb00" +
                "0000000000000093cb0000000000000000cb0000000000000000cb0000000000000000cb0000000000000000cb00" +
                "00000000000000cb3f880000000000001193cb4008000000000000cb0000000000000000cb0000000000000000c4" +
                "10836ea61cd35f9b958e7d3d6fa361f16f");
            c.That(Hex.Encode(CanonicalReply(42, Tagger.FromHex(Key))) == Hex.Encode(spec), "SPEC 9.2 REPLY bytes");
            // Non-canonical NOTICE: header integers in signed and wide forms, array 16 header.
            byte[] notice = B("dc0008", "d002", "d10003", "d2", "00000007", "cf000000000000002a", "d3000000000000000b", "cd0005",
                              "d20000004d", "c0");
            c.That(Decode(notice, r, n) == MessageKind.Notice && n.Session == 7 && n.Seq == 42 && n.TClientUs == 11 && n.Error == 5
                   && n.Stream == 77 && n.Version == 2, "notice with signed/wide integer forms and an array 16 header");
            // Floats as float 32 and as integers (positive and negative fixint, int 16).
            byte[] canon = CanonicalReply(42, null);
            string hex = Hex.Encode(canon);
            string forceCanon = "93" + F64(-0.75) + F64(0.0) + F64(1.0);
            string forceAlt = "dd00000003" + "cabf400000" + "00" + "01";
            c.That(hex.Contains(forceCanon), "(force located)");
            byte[] alt = Hex.Decode(ReplaceFirst(hex, forceCanon, forceAlt));
            c.That(Decode(alt, r, n) == MessageKind.Reply && r.Force.X == -0.75 && r.Force.Y == 0.0 && r.Force.Z == 1.0,
                   "floats as float 32, fixint and an array 32 header");
            alt = Hex.Decode(ReplaceFirst(hex, forceCanon, "93" + "ff" + "d1ff38" + "cb7ff8000000000000"));
            c.That(Decode(alt, r, n) == MessageKind.Reply && r.Force.X == -1.0 && r.Force.Y == -200.0 && double.IsNaN(r.Force.Z),
                   "floats as negative fixint, int 16, and a NaN float 64 (decoding takes it; rendering is the caller's)");
            alt = Hex.Decode(ReplaceFirst(hex, forceCanon, "93" + "ca00000001" + "ca7f800000" + "ca80000000"));
            c.That(Decode(alt, r, n) == MessageKind.Reply && r.Force.X == 1.401298464324817e-45 && double.IsPositiveInfinity(r.Force.Y)
                   && BitConverter.DoubleToInt64Bits(r.Force.Z) == long.MinValue, "float 32 subnormal, infinity and −0.0 widen exactly");
            // A tag in bin 16 form decodes (but never verifies).
            byte[] tagged = CanonicalReply(42, Tagger.FromHex(Key));
            string th = Hex.Encode(tagged);
            byte[] bin16 = Hex.Decode(th.Substring(0, th.Length - 36) + "c50010" + th.Substring(th.Length - 32));
            c.That(Decode(bin16, r, n) == MessageKind.Reply && r.Tagged, "a bin 16 tag decodes");
            c.That(!Tagger.FromHex(Key).Verify(bin16, bin16.Length), "a bin 16 tag never verifies");
        }

        private static string ReplaceFirst(string s, string what, string with)
        {
            int i = s.IndexOf(what, StringComparison.Ordinal);
            if (i < 0) throw new ArgumentException("not found: " + what);
            return s.Substring(0, i) + with + s.Substring(i + what.Length);
        }

        private static void Limits(Checks c)
        {
            var r = new Reply();
            var n = new Notice();
            string ok = "9802030107" + "00" + "05" + "00" + "c0";
            c.That(Decode(Hex.Decode(ok), r, n) == MessageKind.Notice, "(baseline notice)");
            string v1 = "9701030107" + "00" + "03" + "c0";
            c.That(Decode(Hex.Decode(v1), r, n) == MessageKind.Notice && n.Version == 1 && n.Error == 3 && n.Stream == 0, "(v1 BAD_VERSION notice)");
            var bad = new Dictionary<string, string>
            {
                { "trailing byte", ok + "00" },
                { "truncated", ok.Substring(0, ok.Length - 2) },
                { "empty", "" },
                { "not an array", "c0" },
                { "a map", "81" + "01" + "01" },
                { "4 elements", "9402030107" },
                { "7 elements (no stream)", "9702030107" + "0005c0" },
                { "9 elements", "9902030107" + "00050000c0" },
                { "version 1, other error", "9701030107" + "0005c0" },
                { "version 1, 8 elements", "9801030107" + "000300c0" },
                { "version 1 REPLY", Hex.Encode(CanonicalReply(42, null)).Remove(6, 2).Insert(6, "01") },
                { "version 3", "9803030107" + "000500c0" },
                { "type 1 from a server", "9802010107" + "000500c0" },
                { "negative seq", "98020301ff" + "000500c0" },
                { "seq above 2^32", "980203" + "01" + "cf0000000100000000" + "00" + "0500c0" },
                { "t_client_us 2^63", "98020301" + "07" + "cf8000000000000000" + "0500c0" },
                { "error 65536", "9802030107" + "00" + "ce00010000" + "00c0" },
                { "error as float", "9802030107" + "00" + "cb4014000000000000" + "00c0" },
                { "stream above 2^32", "9802030107" + "00" + "05" + "cf0000000100000000" + "c0" },
                { "negative stream", "9802030107" + "00" + "05" + "ff" + "c0" },
                { "stream nil", "9802030107" + "00" + "05" + "c0" + "c0" },
                { "tag of 15 bytes", "9802030107" + "00" + "05" + "00" + "c40f" + new string('0', 30) },
                { "tag of 65 bytes", "9802030107" + "00" + "05" + "00" + "c441" + new string('0', 130) },
                { "tag as str", "9802030107" + "00" + "05" + "00" + "a3616263" },
                { "tag as ext", "9802030107" + "00" + "05" + "00" + "d40100" },
                { "array of 33", "dc0021" + "0203010700" + "05" + "00" + "c0" },
                { "bin length beyond the data", "9802030107" + "00" + "05" + "00" + "c6ffffffff" },
                { "array 32 length huge", "ddffffffff" },
            };
            foreach (var kv in bad)
            {
                MessageKind k;
                try { k = Decode(kv.Value.Length == 0 ? new byte[0] : Hex.Decode(kv.Value), r, n); }
                catch (Exception e) { c.Failures.Add("limits: " + kv.Key + " threw " + e.GetType().Name); continue; }
                c.That(k == MessageKind.None, "limits: " + kv.Key + " was accepted");
            }
            // REPLY fields of the wrong kind.
            string reply = Hex.Encode(CanonicalReply(42, null));
            string spindleLike = F64(9.375); // power_w
            foreach (string wrong in new[] { "c3", "c0", "a0", "80", "90" })
            {
                byte[] d = Hex.Decode(ReplaceFirst(reply, spindleLike, wrong));
                c.That(Decode(d, r, n) == MessageKind.None, "a float field holding " + wrong + " was accepted");
            }
            // POSE: 0 and 1 are not bools; a 2-float vector is not a vector.
            var pose = new Pose { Session = 1, Seq = 2, TClientUs = 3, Orientation = Quat.Identity, SpindleOn = true, Rpm = 1.0 };
            var buf = new byte[256];
            int len = Codec.EncodePose(pose, null, buf);
            string ph = Hex.Encode(buf, 0, len);
            var p = new Pose();
            foreach (var kv in new Dictionary<string, string> { { "spindle 1", ph.Replace("c3c0", "01c0") }, { "spindle 0", ph.Replace("c3c0", "00c0") } })
            {
                bool threw = false;
                try { Codec.DecodePose(Hex.Decode(kv.Value), kv.Value.Length / 2, p); }
                catch (ProtocolException) { threw = true; }
                c.That(threw, "pose: " + kv.Key + " accepted as a bool");
            }
            Codec.DecodePose(buf, len, p);
            c.That(p.SpindleOn && p.Rpm == 1.0 && !p.HasVelocity && !p.Tagged, "pose round trip");
            c.That(len <= Protocol.MaxPoseBytes, "pose size");
            var big = new Pose { Session = uint.MaxValue, Seq = uint.MaxValue, TClientUs = long.MaxValue, HasVelocity = true,
                                 Flags = uint.MaxValue, Stream = uint.MaxValue, Orientation = Quat.Identity };
            c.That(Codec.EncodePose(big, Tagger.FromHex(Key), buf) == Protocol.MaxPoseBytes, "the largest POSE is 153 bytes");
            var bigReply = new byte[1024];
            int rl = Codec.EncodeReply(new Reply { Session = uint.MaxValue, Seq = uint.MaxValue, TClientUs = long.MaxValue,
                TRecvUs = ulong.MaxValue, TSendUs = ulong.MaxValue, Error = 65535, Status = uint.MaxValue, BoneVersion = ulong.MaxValue },
                Tagger.FromHex(Key), bigReply);
            c.That(rl == Protocol.MaxReplyBytes, "the largest REPLY is 327 bytes, got " + rl);
            // Negative stamps cannot be encoded.
            bool refused = false;
            try { Codec.EncodePose(new Pose { TClientUs = -1 }, null, buf); }
            catch (ArgumentOutOfRangeException) { refused = true; }
            c.That(refused, "a negative t_client_us is refused by the encoder");
        }

        private static long Fuzz(Checks c)
        {
            var rng = new Random(12345);
            var r = new Reply();
            var n = new Notice();
            var p = new Pose();
            var seeds = new List<byte[]> { CanonicalReply(42, Tagger.FromHex(Key)), CanonicalReply(7, null),
                                           NoticeBytes(1, 42, 1000000, Protocol.ErrorNewStream, 305419896, Tagger.FromHex(Key)),
                                           Hex.Decode("970103012ace000f424003c0") };
            var pb = new byte[256];
            int pl = Codec.EncodePose(new Pose { Orientation = Quat.Identity, HasVelocity = true }, Tagger.FromHex(Key), pb);
            var pose = new byte[pl];
            Buffer.BlockCopy(pb, 0, pose, 0, pl);
            seeds.Add(pose);
            long cases = 0;
            for (int iter = 0; iter < 60000; iter++)
            {
                byte[] seed = seeds[iter % seeds.Count];
                byte[] d;
                int mode = rng.Next(4);
                if (mode == 0)
                {
                    d = new byte[rng.Next(0, 400)];
                    rng.NextBytes(d);
                }
                else
                {
                    d = (byte[])seed.Clone();
                    int edits = 1 + rng.Next(4);
                    for (int e = 0; e < edits; e++) d[rng.Next(d.Length)] = (byte)rng.Next(256);
                    if (mode == 2) Array.Resize(ref d, rng.Next(d.Length + 1));
                }
                cases++;
                try
                {
                    Codec.TryDecodeServerMessage(d, d.Length, r, n);
                    try { Codec.DecodePose(d, d.Length, p); } catch (ProtocolException) { }
                    Tagger.FromHex(Key).Verify(d, d.Length);
                }
                catch (Exception e)
                {
                    c.Failures.Add("fuzz: " + e.GetType().Name + " on " + Hex.Encode(d));
                    if (c.Failures.Count > 20) break;
                }
            }
            c.Passed++;
            return cases;
        }

        private static void Hmac(Checks c)
        {
            var rng = new Random(7);
            foreach (int keyLength in new[] { 1, 16, 32, 63, 64, 65, 100, 200 })
            {
                var key = new byte[keyLength];
                rng.NextBytes(key);
                var tagger = new Tagger(key);
                using (var bcl = new HMACSHA256(key))
                {
                    for (int length = 0; length < 300; length += 1 + length / 8)
                    {
                        var data = new byte[length];
                        rng.NextBytes(data);
                        var mine = new byte[32];
                        tagger.Mac(data, 0, length, mine, 0);
                        c.That(Hex.Encode(mine) == Hex.Encode(bcl.ComputeHash(data)),
                               "HMAC-SHA256 differs from the BCL's, key " + keyLength + " data " + length);
                    }
                }
            }
            SpecExample(c);
        }

        // SPEC 9.1 and 9.3 through the session rules: the hello, the NEW_STREAM answering it,
        // the POSE on that stream, byte for byte; then the other notices of 9.3.
        private static void SpecExample(Checks c)
        {
            var rules = new SessionRules(1, Key, 41);
            var pose = new Pose { TClientUs = 999000, Position = new Vec3(12.5, -3.0, 0.75), Orientation = Quat.Identity,
                                  Rpm = 60000.0, SpindleOn = true };
            var buf = new byte[256];
            int n = rules.Encode(pose, buf);
            c.That(Hex.Encode(buf, 0, n) == "9d02010129ce000f3e5893cb4029000000000000cbc008000000000000cb3fe800000000000094cb000000000000" +
                   "0000cb0000000000000000cb0000000000000000cb3ff0000000000000cb40ed4c0000000000c3c00000c4101ae9" +
                   "5451a4250938a378fffec016763d", "SPEC 9.1 hello");
            var r = new Reply();
            var no = new Notice();
            DropReason why;
            long tick;
            byte[] offer = Hex.Decode("9802030129ce000f3e580bce12345678c4101c5597f491d12765d5436e7dd245f2eb");
            c.That(rules.Accept(offer, offer.Length, r, no, out why, out tick) == MessageKind.Notice && rules.Stream == 0x12345678,
                   "SPEC 9.3 NEW_STREAM opens stream 0x12345678: " + why);
            pose.TClientUs = 1000000;
            n = rules.Encode(pose, buf);
            c.That(n == 110 && Hex.Encode(buf, 0, n) == "9d0201012ace000f424093cb4029000000000000cbc008000000000000cb3fe800000000000094cb000000000000" +
                   "0000cb0000000000000000cb0000000000000000cb3ff0000000000000cb40ed4c0000000000c3c000ce12345678" +
                   "c4108bfe6d5e5ee63ff610237b36ec9435f7", "SPEC 9.1 POSE");
            var mac = new byte[32];
            Tagger.FromHex(Key).Mac(buf, 0, n - 16, mac, 0);
            c.That(Hex.Encode(mac) == "8bfe6d5e5ee63ff610237b36ec9435f75f58e3b6b9b3705ae0730e9c902287b8", "SPEC 9.1 MAC");
            int plain = Codec.EncodePose(pose, null, buf);
            c.That(plain == 93 && Hex.Encode(buf, plain - 6, 6) == "ce12345678c0", "SPEC 9.1 untagged");
            var notices = new Dictionary<string, int>
            {
                { "980203012bce000f46280cce12345678c41069f2c53e1c34f9fb00c26aacb828a5c5", Protocol.ErrorWrongStream },
                { "980203012ace000f42400600c41013f418699a205e37d769c9ad651f824c", Protocol.ErrorBadTag },
                { "980203072ace000f42400500c0", Protocol.ErrorUnknownSession },
                { "970103012ace000f424003c0", Protocol.ErrorBadVersion },
            };
            foreach (var kv in notices)
            {
                byte[] d = Hex.Decode(kv.Key);
                c.That(Decode(d, r, no) == MessageKind.Notice && no.Error == kv.Value
                       && no.Stream == (kv.Value == Protocol.ErrorWrongStream ? 0x12345678u : 0u)
                       && no.Version == (kv.Value == Protocol.ErrorBadVersion ? 1 : 2), "SPEC 9.3 " + Protocol.ErrorName(kv.Value));
            }
            byte[] wrong = Hex.Decode("980203012bce000f46280cce12345678c41069f2c53e1c34f9fb00c26aacb828a5c5");
            c.That(rules.Accept(wrong, wrong.Length, r, no, out why, out tick) == MessageKind.Notice && rules.Stream == 0,
                   "SPEC 9.3 WRONG_STREAM ends it");
        }

        private static void SequenceAndTiming(Checks c)
        {
            c.That(Sequence.IsNewer(1, 0) && Sequence.IsNewer(0, uint.MaxValue) && Sequence.IsNewer(0x7fffffff, 0), "newer");
            c.That(!Sequence.IsNewer(0, 0) && !Sequence.IsNewer(0x80000000, 0) && !Sequence.IsNewer(0, 0x80000000)
                   && !Sequence.IsNewer(uint.MaxValue, 0), "not newer");
            c.That(Sequence.Next(uint.MaxValue) == 0 && Sequence.Next(41) == 42, "next wraps");
            RoundTrip rt = RoundTrip.Of(1000000, 5000250, 5000300, 1000400);
            c.That(rt.RttUs == 400 && rt.ServerUs == 50 && rt.NetworkUs == 350 && rt.ClockOffsetUs == 4000075.0, "SPEC 5.5 example");
            long a = MonotonicClock.NowUs();
            System.Threading.Thread.Sleep(20);
            long b = MonotonicClock.NowUs();
            c.That(b - a >= 19000 && b - a < 2000000 && a > 0, "monotonic clock in µs: " + (b - a));
        }

        private static bool Near(Vec3 a, Vec3 b, double tol = 1e-9)
        {
            return Math.Abs(a.X - b.X) <= tol && Math.Abs(a.Y - b.Y) <= tol && Math.Abs(a.Z - b.Z) <= tol;
        }

        private static void Frames(Checks c)
        {
            var unity = new FrameTransform(Frame.Unity);
            c.That(Near(unity.PointToServer(new Vec3(0.001, 0.002, 0.003)), new Vec3(3, -1, 2)), "unity point: server x = z, y = −x, z = y, m → mm");
            c.That(Near(unity.ToolAxisToServer(Quat.Identity, Frame.Unity.DefaultToolAxis), new Vec3(0, 0, 1)), "unity tool axis up");
            c.That(Frame.Unity.Determinant == -1 && Frame.Unreal.Determinant == -1 && Frame.Godot.Determinant == 1, "handedness");
            c.That(Near(unity.TorqueToEngine(new Vec3(1000, 0, 0)), new Vec3(0, 0, -1)), "unity torque: det and unit");
            var placed = new FrameTransform(Frame.Godot, new Vec3(0.1, -0.2, 0.3), new Quat(0.1, 0.2, 0.3, 0.9));
            var rng = new Random(3);
            foreach (Frame f in new[] { Frame.SiMm, Frame.Unity, Frame.Unreal, Frame.Godot, Frame.Ros })
            {
                var t = new FrameTransform(f, new Vec3(0.5, 0.25, -1), new Quat(-0.2, 0.4, 0.1, 0.8));
                for (int i = 0; i < 20; i++)
                {
                    var v = new Vec3(rng.NextDouble() - 0.5, rng.NextDouble() - 0.5, rng.NextDouble() - 0.5);
                    c.That(Near(t.PointToEngine(t.PointToServer(v)), v, 1e-12), f.Name + ": point round trip");
                    c.That(Near(t.DirectionToEngine(t.DirectionToServer(v)), v, 1e-12), f.Name + ": direction round trip");
                    c.That(Near(t.VectorToServer(v), t.PointToServer(v).Sub(t.PointToServer(Vec3.Zero)), 1e-9), f.Name + ": vector vs points");
                    c.That(Near(t.TorqueToServer(t.TorqueToEngine(v)), v, 1e-12), f.Name + ": torque round trip");
                }
                Vec3 a = Rotations.Normalized(new Vec3(0.3, -0.4, 0.5));
                Vec3 b = Rotations.Normalized(new Vec3(-0.7, 0.1, 0.2));
                c.That(Near(Rotations.Rotate(Rotations.ShortestArc(a, b), a), b, 1e-12), "shortest arc");
                c.That(Near(Rotations.Rotate(Rotations.ShortestArc(a, new Vec3(-a.X, -a.Y, -a.Z)), a), new Vec3(-a.X, -a.Y, -a.Z), 1e-12),
                       "shortest arc, opposite");
            }
            c.That(Near(placed.PointToServer(new Vec3(0.1, -0.2, 0.3)), Vec3.Zero, 1e-9), "placement origin maps to the server origin");
        }

        private static byte[] NoticeBytes(uint session, uint seq, long tClientUs, int error, uint stream, Tagger tagger)
        {
            var buf = new byte[256];
            int len = Codec.EncodeNotice(new Notice { Session = session, Seq = seq, TClientUs = tClientUs, Error = error, Stream = stream },
                                         tagger, buf);
            var d = new byte[len];
            Buffer.BlockCopy(buf, 0, d, 0, len);
            return d;
        }

        private static void Rules(Checks c)
        {
            var tagger = Tagger.FromHex(Key);
            var forger = new Tagger(new byte[] { 1, 2, 3 });
            var rules = new SessionRules(1, Key, 42);
            var pose = new Pose { Position = new Vec3(12.5, -3.0, 0.75), Orientation = Quat.Identity, Rpm = 60000.0, SpindleOn = true, TClientUs = 1000000 };
            var buf = new byte[256];
            var r = new Reply();
            var n = new Notice();
            DropReason why = DropReason.None;
            long tick = -1;
            Func<byte[], MessageKind> accept = d => rules.Accept(d, d.Length, r, n, out why, out tick);
            Func<byte[], DropReason, bool> dropped = (d, reason) => accept(d) == MessageKind.None && why == reason;

            // Without a stream every POSE is a hello; only a tagged NEW_STREAM echoing one opens it.
            rules.Encode(pose, buf, 0);
            c.That(pose.Seq == 42 && pose.Stream == 0 && rules.Stream == 0, "first POSE: a hello");
            byte[] toHello = CanonicalReply(42, tagger);
            c.That(dropped(toHello, DropReason.Unsolicited), "a REPLY to a hello");
            pose.TClientUs = 1001000;
            rules.Encode(pose, buf, 1);
            c.That(pose.Seq == 43 && pose.Stream == 0, "hellos until a NEW_STREAM");
            c.That(dropped(NoticeBytes(1, 43, 1001000, Protocol.ErrorNewStream, 500, forger), DropReason.BadTag), "a forged NEW_STREAM");
            c.That(dropped(NoticeBytes(1, 43, 1001000, Protocol.ErrorNewStream, 500, null), DropReason.BadTag), "an untagged NEW_STREAM");
            c.That(dropped(NoticeBytes(2, 43, 1001000, Protocol.ErrorNewStream, 500, tagger), DropReason.Foreign), "another session's NEW_STREAM");
            c.That(dropped(NoticeBytes(1, 44, 1001000, Protocol.ErrorNewStream, 500, tagger), DropReason.Unsolicited), "a NEW_STREAM to an unsent seq");
            c.That(dropped(NoticeBytes(1, 43, 999, Protocol.ErrorNewStream, 500, tagger), DropReason.Unsolicited), "a NEW_STREAM with another stamp");
            c.That(dropped(NoticeBytes(1, 43, 1001000, Protocol.ErrorNewStream, 0, tagger), DropReason.Unsolicited), "a NEW_STREAM to stream 0");
            c.That(dropped(NoticeBytes(1, 43, 1001000, Protocol.ErrorWrongStream, 500, tagger), DropReason.Stale), "a WRONG_STREAM without a stream");
            c.That(rules.Stream == 0, "still saying hello");
            c.That(accept(NoticeBytes(1, 43, 1001000, Protocol.ErrorNewStream, 500, tagger)) == MessageKind.Notice
                   && n.Stream == 500 && rules.Stream == 500 && tick == 1, "a NEW_STREAM answering a hello opens the stream");
            c.That(dropped(NoticeBytes(1, 42, 1000000, Protocol.ErrorNewStream, 500, tagger), DropReason.Stale), "the same offer for the first hello");
            c.That(dropped(NoticeBytes(1, 42, 1000000, Protocol.ErrorNewStream, 501, tagger), DropReason.Stale), "another offer while the stream is open");
            pose.TClientUs = 1002000;
            rules.Encode(pose, buf, 2);
            c.That(pose.Seq == 44 && pose.Stream == 500, "then POSEs carry the stream");

            // REPLYs: answers to POSEs sent, newer than the newest used, tagged with the key.
            byte[] reply = CanonicalReply(44, tagger, x => x.TClientUs = 1002000);
            c.That(accept(reply) == MessageKind.Reply && tick == 2, "the answer is believed");
            c.That(dropped(reply, DropReason.Stale), "a duplicate REPLY is stale");
            pose.TClientUs = 1003000;
            rules.Encode(pose, buf, 3);
            c.That(dropped(CanonicalReply(46, tagger), DropReason.Unsolicited), "a REPLY to an unsent seq");
            c.That(dropped(CanonicalReply(45, tagger, x => x.TClientUs = 999), DropReason.Unsolicited), "a REPLY with another stamp");
            c.That(dropped(CanonicalReply(45, tagger, x => { x.Session = 2; x.TClientUs = 1003000; }), DropReason.Foreign), "another session's REPLY");
            c.That(dropped(CanonicalReply(45, null, x => x.TClientUs = 1003000), DropReason.BadTag), "an untagged REPLY");
            c.That(dropped(CanonicalReply(45, forger, x => x.TClientUs = 1003000), DropReason.BadTag), "a forged REPLY");
            c.That(accept(CanonicalReply(45, tagger, x => x.TClientUs = 1003000)) == MessageKind.Reply, "the right answer");

            // Other notices pass unverified and change nothing.
            c.That(accept(NoticeBytes(1, 45, 1003000, Protocol.ErrorBadTag, 0, forger)) == MessageKind.Notice && n.Error == 6,
                   "a NOTICE passes unverified");
            byte[] v1 = Hex.Decode("970103012ace000f424003c0");
            c.That(accept(v1) == MessageKind.Notice && n.Version == 1 && n.Error == Protocol.ErrorBadVersion && n.Seq == 42,
                   "v1's BAD_VERSION notice is understood");
            c.That(rules.Stream == 500, "other notices leave the stream");
            var huge = new byte[1025];
            c.That(dropped(huge, DropReason.TooBig), "a datagram over 1024 bytes");

            // WRONG_STREAM about this stream, tagged: hellos again, seqs going on.
            c.That(dropped(NoticeBytes(1, 45, 1003000, Protocol.ErrorWrongStream, 501, tagger), DropReason.Stale), "a WRONG_STREAM about another stream");
            c.That(dropped(NoticeBytes(1, 45, 1003000, Protocol.ErrorWrongStream, 500, forger), DropReason.BadTag), "a forged WRONG_STREAM");
            c.That(rules.Stream == 500, "the stream survives them");
            c.That(accept(NoticeBytes(1, 45, 1003000, Protocol.ErrorWrongStream, 500, tagger)) == MessageKind.Notice && rules.Stream == 0,
                   "a WRONG_STREAM about the stream closes it");
            pose.TClientUs = 1004000;
            rules.Encode(pose, buf, 4);
            c.That(pose.Seq == 46 && pose.Stream == 0, "hello again, seqs going on");
            c.That(dropped(NoticeBytes(1, 43, 1001000, Protocol.ErrorNewStream, 500, tagger), DropReason.Unsolicited),
                   "a replayed NEW_STREAM for a hello of an earlier stream");
            c.That(accept(NoticeBytes(1, 46, 1004000, Protocol.ErrorNewStream, 600, tagger)) == MessageKind.Notice && rules.Stream == 600,
                   "the next stream");
            rules.Restart();
            pose.TClientUs = 1005000;
            rules.Encode(pose, buf, 5);
            c.That(pose.Seq == 47 && pose.Stream == 0 && rules.Stream == 0, "after Restart: a hello");

            // A session without a key: the handshake by session and echo alone.
            var open = new SessionRules(3, (Tagger)null, 1);
            int len = open.Encode(pose, buf, 0);
            c.That(buf[len - 1] == 0xc0 && pose.Stream == 0, "keyless: an untagged hello");
            byte[] offer = NoticeBytes(3, 1, 1005000, Protocol.ErrorNewStream, 7, null);
            c.That(open.Accept(offer, offer.Length, r, n, out why, out tick) == MessageKind.Notice && open.Stream == 7, "keyless: stream opened");
        }

        private static void JsonChecks(Checks c)
        {
            foreach (string bad in new[] { "", "{", "[1,]", "{\"a\":1,}", "01", "1.", ".5", "-", "1e", "\"\\x\"", "tru", "{\"a\":1}x",
                                           "{\"a\":1,\"a\":2}", "\"a\nb\"", "[" + new string('[', 70) + new string(']', 71), "NaN" })
            {
                bool threw = false;
                try { Json.Parse(bad); } catch (FormatException) { threw = true; }
                c.That(threw, "JSON accepted " + bad);
            }
            var o = (Dictionary<string, object>)Json.Parse("{\"a\": [1, -0.0, 2.5e-3, true, null, \"x\\u00e9\\n\"], \"b\": {}}");
            var a = (List<object>)o["a"];
            c.That((long)a[0] == 1 && BitConverter.DoubleToInt64Bits((double)a[1]) == long.MinValue && (double)a[2] == 0.0025
                   && (bool)a[3] && a[4] == null && (string)a[5] == "x\u00e9\n", "JSON values");
            c.That(Json.Write(o) == "{\"a\":[1,-0.0,0.0025,true,null,\"x\u00e9\\n\"],\"b\":{}}", "JSON write: " + Json.Write(o));
            c.That((double)Json.Parse("0.7071067811865476") == Math.Sqrt(0.5), "JSON float parses to the nearest double");
            foreach (string huge in new[] { "1e400", "-1e400", "[1.5e309]", "1" + new string('0', 400) })
            {
                Exception thrown = null;
                try { Json.Parse(huge); } catch (Exception e) { thrown = e; }
                c.That(thrown is FormatException, "JSON out of range " + huge + ": " + (thrown == null ? "accepted" : thrown.GetType().Name));
            }
            c.That((double)Json.Parse("1e-400") == 0.0 && (double)Json.Parse("1.7976931348623157e308") == double.MaxValue, "JSON: underflow to 0, the largest double");
            string body = "{\"detail\": 1e400}";
            string detail = null;
            try { detail = BurrRest.DetailOf(body); } catch (Exception e) { detail = e.GetType().Name; }
            c.That(detail == body, "DetailOf of an out-of-range number gives the body: " + detail);
        }

        private static byte[] MeshMessageBytes(uint vertices, uint triangles, Action<byte[]> edit = null)
        {
            var list = new List<byte>();
            Action<uint> u32 = v => { for (int i = 0; i < 4; i++) list.Add((byte)(v >> (8 * i))); };
            list.AddRange(new byte[] { 0x42, 0x46, 0x4d, 0x43, 1, 0, 2 | 8, 0 });
            u32(9); u32(32);
            u32(5); u32(0); // bone_version
            u32(0); u32(0); // since
            u32(0); u32(1); // next_cursor, chunk_count
            u32(1); u32(unchecked((uint)-2)); u32(3);
            u32(vertices); u32(triangles);
            for (uint i = 0; i < 3 * vertices; i++) u32((uint)BitConverter.ToInt32(BitConverter.GetBytes((float)i), 0));
            for (uint i = 0; i < 3 * vertices; i++) u32((uint)BitConverter.ToInt32(BitConverter.GetBytes(1.0f), 0));
            for (uint i = 0; i < vertices; i++) list.Add(7);
            while ((list.Count - 40) % 4 != 0) list.Add(0);
            for (uint i = 0; i < 3 * triangles; i++) u32(i % Math.Max(vertices, 1));
            byte[] d = list.ToArray();
            if (edit != null) edit(d);
            return d;
        }

        private static void MeshParser(Checks c)
        {
            MeshMessage m = MeshMessageParser.Parse(MeshMessageBytes(3, 1));
            MeshChunk ch = m.Chunks[0];
            c.That(m.Full && m.SessionFrame && !m.More && !m.Clockwise && m.Session == 9 && m.ChunkCells == 32 && m.BoneVersion == 5,
                   "mesh header");
            c.That(ch.Index.Equals(new ChunkIndex(1, -2, 3)) && ch.VertexCount == 3 && ch.TriangleCount == 1 && ch.Positions[8] == 8.0f
                   && ch.Normals[0] == 1.0f && ch.Materials[2] == 7 && ch.Triangles[2] == 2, "mesh chunk");
            var bad = new Dictionary<string, byte[]>
            {
                { "bad magic", MeshMessageBytes(3, 1, d => d[0] = 0x41) },
                { "version 2", MeshMessageBytes(3, 1, d => d[4] = 2) },
                { "index out of range", MeshMessageBytes(3, 1, d => d[d.Length - 4] = 3) },
                { "vertex count beyond the data", MeshMessageBytes(3, 1, d => d[52] = 4) },
                { "huge vertex count", MeshMessageBytes(3, 1, d => { d[52] = 0xff; d[53] = 0xff; d[54] = 0xff; d[55] = 0xff; }) },
                { "huge triangle count", MeshMessageBytes(3, 1, d => { d[56] = 0xff; d[57] = 0xff; d[58] = 0xff; d[59] = 0x7f; }) },
                { "chunk count beyond the data", MeshMessageBytes(3, 1, d => d[36] = 2) },
                { "non-zero padding", MeshMessageBytes(3, 1, d => d[40 + 20 + 75] = 1) },
                { "trailing bytes", Concat(MeshMessageBytes(3, 1), new byte[4]) },
                { "short header", new byte[39] },
                { "vertices without triangles", MeshMessageBytes(3, 0) },
            };
            foreach (var kv in bad)
            {
                bool threw = false;
                try { MeshMessageParser.Parse(kv.Value); }
                catch (FormatException) { threw = true; }
                catch (Exception e) { c.Failures.Add("mesh: " + kv.Key + " threw " + e.GetType().Name); continue; }
                c.That(threw, "mesh: " + kv.Key + " was accepted");
            }
            // ChunkedMesh: FULL clears, V = 0 removes, MORE defers Have to the lowest version.
            var mesh = new ChunkedMesh();
            mesh.Apply(MeshMessageParser.Parse(MeshMessageBytes(3, 1)));
            c.That(mesh.Complete && mesh.Have == 5 && mesh.Count == 1, "mesh: first update");
            byte[] more = MeshMessageBytes(0, 0, d => { d[6] = 1 | 8; d[16] = 9; });
            mesh.Apply(MeshMessageParser.Parse(more));
            c.That(mesh.Have == 5 && mesh.Count == 0 && mesh.Replaced == 1, "mesh: removal, update not complete under MORE");
            byte[] last = MeshMessageBytes(3, 1, d => { d[6] = 8; d[16] = 7; });
            c.That(mesh.Apply(MeshMessageParser.Parse(last)) && mesh.Have == 7 && mesh.Count == 1, "mesh: Have = the lowest version of the update");
            var changes = new List<KeyValuePair<ChunkIndex, MeshChunk>>();
            c.That(mesh.TakeChanges(changes) && changes.Count == 1 && changes[0].Value != null, "mesh: coalesced changes after a clear");
            MeshChunk gone = MeshMessageParser.Parse(MeshMessageBytes(0, 0)).Chunks[0];
            c.That(gone.Empty && gone.VertexCount == 0, "mesh: V = T = 0 is an empty chunk");
        }

        private static void Endpoints(Checks c)
        {
            var cases = new[]
            {
                new[] { "0.0.0.0", "http://10.1.2.3:8080", "10.1.2.3" },
                new[] { "::", "http://10.1.2.3:8080/v1", "10.1.2.3" },
                new[] { "[::]", "http://[fd00::5]:8080", "fd00::5" },
                new[] { "0:0:0:0:0:0:0:0", "http://host.example:8080", "host.example" },
                new[] { "*", "https://host.example", "host.example" },
                new[] { "", "http://127.0.0.1:1", "127.0.0.1" },
                new[] { "0.0.0.0", "http://0.0.0.0:8080", "127.0.0.1" },
                new[] { "0.0.0.0", null, "127.0.0.1" },
                new[] { "192.168.1.9", "http://10.1.2.3:8080", "192.168.1.9" },
                new[] { "::1", "http://10.1.2.3:8080", "::1" },
                new[] { "burr.local", "http://10.1.2.3:8080", "burr.local" },
            };
            foreach (var k in cases)
            {
                string got = BurrRest.ReachableHost(k[0], k[1]);
                c.That(got == k[2], "udp.host " + k[0] + " via " + k[1] + ": " + got + ", expected " + k[2]);
            }
            var o = (Dictionary<string, object>)Json.Parse("{\"id\": 3, \"udp\": {\"host\": \"0.0.0.0\", \"port\": 47810}}");
            SessionInfo s = SessionInfo.From(o, "http://10.9.8.7:8080");
            c.That(s.UdpHost == "10.9.8.7" && s.UdpPort == 47810, "SessionInfo: wildcard udp.host replaced by the REST host: " + s.UdpHost);

            var v4 = System.Net.IPAddress.Loopback;
            var v6 = System.Net.IPAddress.IPv6Loopback;
            var lan = System.Net.IPAddress.Parse("fd00::7");
            c.That(UdpLink.Pick(new[] { v6, v4 }).Equals(v4), "localhost as ::1, 127.0.0.1: IPv4 preferred");
            c.That(UdpLink.Pick(new[] { v6 }).Equals(v6), "::1 alone is kept");
            c.That(UdpLink.Pick(new[] { lan, v4 }).Equals(lan), "a non-loopback name keeps the resolver's order");
            c.That(UdpLink.Resolve("localhost").Equals(v4), "localhost resolves to 127.0.0.1: " + UdpLink.Resolve("localhost"));
        }

        /// <summary>Staleness and error REPLYs zero everything rendered, the coupling model's
        /// proxy included (SPEC.md §3.4: an error REPLY carries zeros there).</summary>
        private static void Zeroing(Checks c)
        {
            var one = new Vec3(1, 2, 3);
            var f = new ForceState
            {
                Valid = true, Force = one, Torque = one, Resistive = one, PowerW = 1, VibrationAmplitudeN = 1,
                VibrationFrequencyHz = 1, VibrationAxis = one, ProxyPosition = one, ProxyVelocity = one,
                CouplingStiffness = 1, CouplingDamping = 1, FeedVelocity = one, Status = 3, BoneVersion = 9, Seq = 4,
            };
            f.ZeroOutput();
            var kept = new HashSet<string> { "Status", "Error", "BoneVersion", "RemovedMm3", "RemovedTotalMm3", "Seq", "RttUs", "ClockOffsetUs", "AgeUs" };
            foreach (var field in typeof(ForceState).GetFields())
            {
                if (kept.Contains(field.Name)) continue;
                object v = field.GetValue(f);
                bool zero = v is Vec3 ? ((Vec3)v).X == 0 && ((Vec3)v).Y == 0 && ((Vec3)v).Z == 0
                          : v is double ? (double)v == 0.0 : v is bool ? !(bool)v : false;
                c.That(zero, "ForceState.ZeroOutput leaves " + field.Name + " = " + v);
            }
        }

        /// <summary>Jittery frames along a straight line at 5 mm/s: the 1 kHz samples move at
        /// that speed tick after tick (no standstill-then-jump, no steps back).</summary>
        private static void Interpolation(Checks c)
        {
            var interp = new PoseInterpolator();
            var rng = new Random(11);
            long t = 0, nextFrame = 0;
            double lastX = double.NaN;
            int checkedTicks = 0, bad = 0;
            double worst = 0;
            var pose = new ToolPose(Vec3.Zero, Quat.Identity, 60000.0, true);
            for (long tick = 0; tick < 3000; tick++, t += 1000)
            {
                if (t >= nextFrame)
                {
                    pose.Position = new Vec3(0.005 * t / 1000.0, 0, 0); // mm at 5 mm/s, t in µs
                    interp.Add(pose, t);
                    nextFrame = t + 8000 + rng.Next(0, 9) * 1000; // 8-16 ms frames
                }
                ToolPose s;
                c.That(interp.Sample(t, out s) || tick == 0, "interpolator: a sample");
                if (tick > 200)
                {
                    double v = (s.Position.X - lastX) / 0.001; // mm/s
                    worst = Math.Max(worst, Math.Abs(v - 5.0));
                    if (Math.Abs(v - 5.0) > 0.1) bad++;
                    checkedTicks++;
                }
                lastX = s.Position.X;
            }
            c.That(bad == 0, "interpolator: " + bad + " of " + checkedTicks + " ticks off 5 mm/s by > 2 % (worst " + worst + ")");
        }

        private static byte[] Concat(byte[] a, byte[] b)
        {
            var d = new byte[a.Length + b.Length];
            Buffer.BlockCopy(a, 0, d, 0, a.Length);
            Buffer.BlockCopy(b, 0, d, a.Length, b.Length);
            return d;
        }
    }

    internal static class VecTestExtensions
    {
        public static Vec3 Sub(this Vec3 a, Vec3 b) { return new Vec3(a.X - b.X, a.Y - b.Y, a.Z - b.Z); }
    }
}
