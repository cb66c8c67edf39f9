// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.IO;

namespace Burrforce.Tests
{
    /// <summary>SPEC.md §8 against proto/vectors/vectors.json, read at run time: encode each
    /// vector's fields to exactly its bytes, decode its bytes to exactly its fields (floats
    /// bit for bit), verify tags with the key, reject them with another key and after every
    /// single-byte change. The version-1 BAD_VERSION notice is only decoded: a client never
    /// encodes it.</summary>
    public static class VectorsTest
    {
        public static Dictionary<string, object> Run(string path)
        {
            var vectors = (List<object>)Json.Parse(File.ReadAllText(path));
            var checks = new Checks();
            var names = new List<object>();
            int mutations = 0;
            foreach (object item in vectors)
            {
                var v = Json.AsObject(item, "a vector");
                string name = Json.GetString(v, "name");
                names.Add(name);
                string type = Json.GetString(v, "type");
                long version = Json.GetLong(v, "version");
                string keyHex = Json.GetString(v, "key_hex");
                var fields = Json.AsObject(Json.Get(v, "fields"), "fields");
                byte[] expected = Hex.Decode(Json.GetString(v, "hex"));
                Tagger tagger = Tagger.FromHex(keyHex);
                var buffer = new byte[2048];
                int n;
                // Encode.
                if (version == Protocol.Version)
                {
                    if (type == "pose") n = Codec.EncodePose(PoseFrom(fields), tagger, buffer);
                    else if (type == "reply") n = Codec.EncodeReply(ReplyFrom(fields), tagger, buffer);
                    else if (type == "notice") n = Codec.EncodeNotice(NoticeFrom(fields), tagger, buffer);
                    else throw new FormatException("unknown vector type " + type);
                    checks.That(Hex.Encode(buffer, 0, n) == Hex.Encode(expected), name + ": encoded " + Hex.Encode(buffer, 0, n));
                }
                else
                {
                    checks.That(version == Protocol.VersionV1 && type == "notice", name + ": version " + version + " " + type);
                }
                // Decode.
                if (type == "pose")
                {
                    var p = new Pose();
                    Codec.DecodePose(expected, expected.Length, p);
                    CompareFields(checks, name, fields, PoseFields(p));
                    checks.That(p.Tagged == (keyHex != null), name + ": tag presence");
                }
                else
                {
                    var r = new Reply();
                    var no = new Notice();
                    MessageKind kind = Codec.DecodeServerMessage(expected, expected.Length, r, no);
                    checks.That(kind == (type == "reply" ? MessageKind.Reply : MessageKind.Notice), name + ": kind " + kind);
                    if (kind == MessageKind.Reply)
                    {
                        CompareFields(checks, name, fields, ReplyFields(r));
                        checks.That(r.Tagged == (keyHex != null), name + ": tag presence");
                    }
                    else
                    {
                        CompareFields(checks, name, fields, NoticeFields(no));
                        checks.That(no.Tagged == (keyHex != null), name + ": tag presence");
                        checks.That(no.Version == version, name + ": decoded as version " + no.Version);
                    }
                }
                // Tags.
                if (tagger != null)
                {
                    checks.That(tagger.Verify(expected, expected.Length), name + ": verifies with its key");
                    byte[] other = Hex.Decode(keyHex);
                    other[0] ^= 0x01;
                    checks.That(!new Tagger(other).Verify(expected, expected.Length), name + ": verifies with another key");
                    checks.That(!Tagger.FromHex("00112233").Verify(expected, expected.Length), name + ": verifies with a short key");
                    var copy = (byte[])expected.Clone();
                    foreach (byte flip in new byte[] { 0x01, 0x80, 0xff })
                    {
                        for (int i = 0; i < copy.Length; i++)
                        {
                            copy[i] ^= flip;
                            bool accepted = tagger.Verify(copy, copy.Length);
                            copy[i] ^= flip;
                            mutations++;
                            if (accepted) checks.Failures.Add(name + ": verifies after byte " + i + " ^ " + flip);
                        }
                    }
                    checks.That(!tagger.Verify(expected, expected.Length - 1), name + ": verifies truncated");
                }
                else
                {
                    checks.That(expected[expected.Length - 1] == 0xc0, name + ": untagged ends with nil");
                }
            }
            return new Dictionary<string, object>
            {
                { "vectors", (long)vectors.Count }, { "names", names }, { "passed", (long)checks.Passed },
                { "mutations_rejected", (long)mutations }, { "failures", checks.Failures },
            };
        }

        private static Vec3 V3(object o)
        {
            var l = (List<object>)o;
            if (l.Count != 3) throw new FormatException("expected 3 numbers");
            return new Vec3(D(l[0]), D(l[1]), D(l[2]));
        }

        private static double D(object o) { return o is long ? (long)o : (double)o; }

        private static Pose PoseFrom(Dictionary<string, object> f)
        {
            var q = (List<object>)f["orientation"];
            var p = new Pose
            {
                Session = (uint)Json.GetLong(f, "session"),
                Seq = (uint)Json.GetLong(f, "seq"),
                TClientUs = Json.GetLong(f, "t_client_us"),
                Position = V3(f["position"]),
                Orientation = new Quat(D(q[0]), D(q[1]), D(q[2]), D(q[3])),
                Rpm = Json.GetDouble(f, "rpm"),
                SpindleOn = (bool)f["spindle_on"],
                HasVelocity = f["velocity"] != null,
                Flags = (uint)Json.GetLong(f, "flags"),
                Stream = (uint)Json.GetLong(f, "stream"),
            };
            if (p.HasVelocity) p.Velocity = V3(f["velocity"]);
            return p;
        }

        private static Reply ReplyFrom(Dictionary<string, object> f)
        {
            return new Reply
            {
                Session = (uint)Json.GetLong(f, "session"),
                Seq = (uint)Json.GetLong(f, "seq"),
                TClientUs = Json.GetLong(f, "t_client_us"),
                TRecvUs = (ulong)Json.GetLong(f, "t_recv_us"),
                TSendUs = (ulong)Json.GetLong(f, "t_send_us"),
                Error = (int)Json.GetLong(f, "error"),
                Status = (uint)Json.GetLong(f, "status"),
                Force = V3(f["force"]),
                Resistive = V3(f["resistive"]),
                Torque = V3(f["torque"]),
                PowerW = Json.GetDouble(f, "power_w"),
                VibrationAmplitudeN = Json.GetDouble(f, "vibration_amplitude"),
                VibrationFrequencyHz = Json.GetDouble(f, "vibration_frequency_hz"),
                VibrationAxis = V3(f["vibration_axis"]),
                ProxyPosition = V3(f["proxy_position"]),
                ProxyVelocity = V3(f["proxy_velocity"]),
                CouplingStiffness = Json.GetDouble(f, "coupling_stiffness"),
                CouplingDamping = Json.GetDouble(f, "coupling_damping"),
                RemovedMm3 = Json.GetDouble(f, "removed_mm3"),
                BoneVersion = (ulong)Json.GetLong(f, "bone_version"),
                FeedVelocity = V3(f["feed_velocity"]),
            };
        }

        private static Notice NoticeFrom(Dictionary<string, object> f)
        {
            return new Notice
            {
                Session = (uint)Json.GetLong(f, "session"),
                Seq = (uint)Json.GetLong(f, "seq"),
                TClientUs = Json.GetLong(f, "t_client_us"),
                Error = (int)Json.GetLong(f, "error"),
                Stream = (uint)Json.GetLong(f, "stream"),
            };
        }

        // Decoded messages as JSON-like values, to compare with "fields" key by key.
        private static List<object> L(Vec3 v) { return new List<object> { v.X, v.Y, v.Z }; }

        private static Dictionary<string, object> PoseFields(Pose p)
        {
            return new Dictionary<string, object>
            {
                { "session", (long)p.Session }, { "seq", (long)p.Seq }, { "t_client_us", p.TClientUs },
                { "position", L(p.Position) },
                { "orientation", new List<object> { p.Orientation.X, p.Orientation.Y, p.Orientation.Z, p.Orientation.W } },
                { "rpm", p.Rpm }, { "spindle_on", p.SpindleOn },
                { "velocity", p.HasVelocity ? L(p.Velocity) : null }, { "flags", (long)p.Flags },
                { "stream", (long)p.Stream },
            };
        }

        private static Dictionary<string, object> ReplyFields(Reply r)
        {
            return new Dictionary<string, object>
            {
                { "session", (long)r.Session }, { "seq", (long)r.Seq }, { "t_client_us", r.TClientUs },
                { "t_recv_us", (long)r.TRecvUs }, { "t_send_us", (long)r.TSendUs }, { "error", (long)r.Error },
                { "status", (long)r.Status }, { "force", L(r.Force) }, { "resistive", L(r.Resistive) },
                { "torque", L(r.Torque) }, { "power_w", r.PowerW }, { "vibration_amplitude", r.VibrationAmplitudeN },
                { "vibration_frequency_hz", r.VibrationFrequencyHz }, { "vibration_axis", L(r.VibrationAxis) },
                { "proxy_position", L(r.ProxyPosition) }, { "proxy_velocity", L(r.ProxyVelocity) },
                { "coupling_stiffness", r.CouplingStiffness }, { "coupling_damping", r.CouplingDamping },
                { "removed_mm3", r.RemovedMm3 }, { "bone_version", (long)r.BoneVersion },
                { "feed_velocity", L(r.FeedVelocity) },
            };
        }

        private static Dictionary<string, object> NoticeFields(Notice n)
        {
            var d = new Dictionary<string, object>
            {
                { "session", (long)n.Session }, { "seq", (long)n.Seq }, { "t_client_us", n.TClientUs },
                { "error", (long)n.Error },
            };
            // v1's notice has no stream element.
            if (n.Version == Protocol.Version) d["stream"] = (long)n.Stream;
            return d;
        }

        private static void CompareFields(Checks checks, string name, Dictionary<string, object> expected,
                                          Dictionary<string, object> got)
        {
            foreach (var kv in expected)
            {
                object g;
                bool has = got.TryGetValue(kv.Key, out g);
                checks.That(has, name + ": decoder has no field " + kv.Key);
                if (has) checks.That(Same(kv.Value, g), name + ": field " + kv.Key + " decoded as " + Json.Write(g));
            }
            checks.That(expected.Count == got.Count, name + ": field count " + expected.Count + " vs " + got.Count);
        }

        // JSON floats against decoded doubles bit for bit; integers exactly.
        private static bool Same(object want, object got)
        {
            if (want == null || got == null) return want == null && got == null;
            if (want is List<object>)
            {
                var a = (List<object>)want;
                var b = got as List<object>;
                if (b == null || a.Count != b.Count) return false;
                for (int i = 0; i < a.Count; i++) if (!Same(a[i], b[i])) return false;
                return true;
            }
            if (want is double) return got is double && BitConverter.DoubleToInt64Bits((double)want) == BitConverter.DoubleToInt64Bits((double)got);
            if (want is long) return got is long && (long)want == (long)got;
            if (want is bool) return got is bool && (bool)want == (bool)got;
            return false;
        }
    }
}
