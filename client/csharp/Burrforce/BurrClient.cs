// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>The server refused a POSE: a NOTICE, or a REPLY with error ≠ 0.</summary>
    public sealed class BurrServerException : Exception
    {
        public readonly int Code;
        public readonly uint Seq;

        public BurrServerException(int code, uint seq)
            : base("server refused packet " + seq + ": " + Protocol.ErrorName(code) + Hint(code))
        {
            Code = code;
            Seq = seq;
        }

        private static string Hint(int code)
        {
            switch (code)
            {
                case Protocol.ErrorUnknownSession: return " (no such session: check the session id, or whether the server restarted)";
                case Protocol.ErrorBadTag: return " (wrong or missing key: use the key the server printed)";
                case Protocol.ErrorBadVersion: return " (protocol version mismatch: update the client or the server)";
                case Protocol.ErrorBadValue: return " (a value is unusable: NaN, infinite, or a quaternion far from unit length)";
                default: return "";
            }
        }
    }

    /// <summary>A blocking UDP client for one session: send POSEs, receive believed REPLYs and
    /// NOTICEs, or exchange one POSE for its answer. For tools and tests; an engine uses the
    /// <see cref="Streamer"/>. Not thread-safe.</summary>
    public sealed class BurrClient : IDisposable
    {
        private readonly UdpLink link;
        private readonly byte[] sendBuffer = new byte[Protocol.MaxPoseBytes + 64];
        private readonly byte[] receiveBuffer = new byte[Protocol.ReceiveBufferBytes];
        private readonly Pose pose = new Pose();
        private readonly long[] dropped = new long[(int)DropReason.Count];
        private int lastLength;

        public readonly SessionRules Rules;
        /// <summary>The newest believed REPLY (valid after Receive returned Reply).</summary>
        public readonly Reply LastReply = new Reply();
        public readonly Notice LastNotice = new Notice();
        /// <summary>Client clock when the last believed datagram arrived, µs.</summary>
        public long LastArrivedUs { get; private set; }
        public long Sent { get; private set; }
        public long Replies { get; private set; }
        public long Notices { get; private set; }

        public BurrClient(string host, int port, uint session, string keyHex, uint firstSeq = 1)
        {
            Rules = new SessionRules(session, keyHex, firstSeq);
            link = new UdpLink(host, port);
        }

        public long Dropped(DropReason reason) { return dropped[(int)reason]; }

        /// <summary>Sends one POSE (engine frame and units), stamped <paramref name="tClientUs"/>
        /// (when it was sampled; default now): a hello while Rules.Stream is 0. Returns its
        /// sequence number.</summary>
        public uint Send(Vec3 position, Quat orientation, double rpm, bool spindleOn,
                         uint flags = 0, long tClientUs = -1, Vec3? velocity = null)
        {
            pose.Position = position;
            pose.Orientation = orientation;
            pose.Rpm = rpm;
            pose.SpindleOn = spindleOn;
            pose.HasVelocity = velocity.HasValue;
            pose.Velocity = velocity.HasValue ? velocity.Value : Vec3.Zero;
            pose.Flags = flags;
            pose.TClientUs = tClientUs >= 0 ? tClientUs : MonotonicClock.NowUs();
            int n = Rules.Encode(pose, sendBuffer);
            lastLength = n;
            link.Send(sendBuffer, n);
            Sent++;
            return pose.Seq;
        }

        /// <summary>Sends bytes as they are (tests of the server's error answers).</summary>
        public void SendRaw(byte[] datagram, int length) { link.Send(datagram, length); }

        /// <summary>A copy of the last POSE datagram sent (to resend it, say).</summary>
        public byte[] LastDatagram()
        {
            var copy = new byte[lastLength];
            Buffer.BlockCopy(sendBuffer, 0, copy, 0, lastLength);
            return copy;
        }

        /// <summary>Waits up to timeoutUs for a believed datagram: Reply (in LastReply) or
        /// Notice (in LastNotice), or None.</summary>
        public MessageKind Receive(long timeoutUs)
        {
            long deadline = MonotonicClock.NowUs() + timeoutUs;
            while (true)
            {
                long remaining = deadline - MonotonicClock.NowUs();
                int n = link.Receive(receiveBuffer, Math.Max(remaining, 0));
                if (n < 0)
                {
                    if (remaining <= 0) return MessageKind.None;
                    continue;
                }
                long arrived = MonotonicClock.NowUs();
                DropReason reason;
                long tick;
                MessageKind kind = Rules.Accept(receiveBuffer, n, LastReply, LastNotice, out reason, out tick);
                if (kind == MessageKind.None)
                {
                    dropped[(int)reason]++;
                    continue;
                }
                LastArrivedUs = arrived;
                if (kind == MessageKind.Reply) Replies++; else Notices++;
                return kind;
            }
        }

        /// <summary>Sends a POSE and waits for its answer. Without a stream (the first call, or
        /// after the server said WRONG_STREAM) the POSE goes out as a hello first and again once
        /// the server opened a stream. Throws TimeoutException without an answer within
        /// timeoutUs in all, BurrServerException for another NOTICE about it or an error REPLY.</summary>
        public Reply Exchange(Vec3 position, Quat orientation, double rpm, bool spindleOn,
                              long timeoutUs = 1000000, uint flags = 0)
        {
            long deadline = MonotonicClock.NowUs() + timeoutUs;
            while (true)
            {
                uint seq = Send(position, orientation, rpm, spindleOn, flags);
                while (true)
                {
                    long remaining = deadline - MonotonicClock.NowUs();
                    MessageKind kind = remaining > 0 ? Receive(remaining) : MessageKind.None;
                    if (kind == MessageKind.None)
                        throw new TimeoutException("no answer to packet " + seq + " within " + timeoutUs / 1000 + " ms");
                    if (kind == MessageKind.Notice)
                    {
                        if (LastNotice.Seq != seq) continue;
                        // Believed handshake notices have already moved Rules to a stream or
                        // back to hello: the same pose goes out again under it.
                        if (LastNotice.Error == Protocol.ErrorNewStream || LastNotice.Error == Protocol.ErrorWrongStream) break;
                        throw new BurrServerException(LastNotice.Error, seq);
                    }
                    if (LastReply.Seq != seq) continue;
                    if (LastReply.Error != Protocol.ErrorOk) throw new BurrServerException(LastReply.Error, seq);
                    return LastReply;
                }
            }
        }

        public void Dispose() { link.Dispose(); }
    }
}
