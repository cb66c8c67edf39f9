// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Text;

namespace Burrforce
{
    /// <summary>A snapshot of what a streamer did.</summary>
    public sealed class StreamerCounters
    {
        /// <summary>Ticks of the schedule that passed: sent + skipped.</summary>
        public long Ticks;
        public long Sent;
        /// <summary>POSEs sent as hellos (stream 0: asking for a stream, never answered by a REPLY).</summary>
        public long Hellos;
        /// <summary>The stream in use at the snapshot; 0 while saying hello. Notices[NEW_STREAM]
        /// counts the streams taken, Notices[WRONG_STREAM] those the server closed.</summary>
        public uint Stream;
        /// <summary>REPLYs believed (any error value).</summary>
        public long Replies;
        /// <summary>REPLYs with error ≠ 0, by error code (index = code, last slot = any ≥ 15).</summary>
        public readonly long[] ErrorReplies = new long[16];
        /// <summary>NOTICEs about this session, by error code (index = code, last slot = any ≥ 15).</summary>
        public readonly long[] Notices = new long[16];
        /// <summary>Datagrams not believed, by DropReason.</summary>
        public readonly long[] Dropped = new long[(int)DropReason.Count];
        /// <summary>POSEs sent more than half a period after their scheduled time.</summary>
        public long LateTicks;
        /// <summary>Ticks not sent because the thread was more than CatchUpTicks behind (a stall):
        /// the schedule stays absolute, so there is no burst afterwards.</summary>
        public long SkippedTicks;
        /// <summary>ICMP "port unreachable" answers (no server on the port).</summary>
        public long Unreachable;

        public long NoticeCount
        {
            get { long n = 0; foreach (long c in Notices) n += c; return n; }
        }

        public long ErrorReplyCount
        {
            get { long n = 0; foreach (long c in ErrorReplies) n += c; return n; }
        }

        internal void CopyTo(StreamerCounters other)
        {
            other.Ticks = Ticks; other.Sent = Sent; other.Hellos = Hellos; other.Stream = Stream; other.Replies = Replies;
            other.LateTicks = LateTicks; other.SkippedTicks = SkippedTicks; other.Unreachable = Unreachable;
            Array.Copy(ErrorReplies, other.ErrorReplies, ErrorReplies.Length);
            Array.Copy(Notices, other.Notices, Notices.Length);
            Array.Copy(Dropped, other.Dropped, Dropped.Length);
        }

        internal static int Slot(int code) { return code < 0 || code > 15 ? 15 : code; }

        public override string ToString()
        {
            var sb = new StringBuilder();
            sb.Append("ticks ").Append(Ticks).Append(", sent ").Append(Sent).Append(", hellos ").Append(Hellos)
              .Append(", stream ").Append(Stream).Append(", replies ").Append(Replies)
              .Append(", late ").Append(LateTicks).Append(", skipped ").Append(SkippedTicks);
            for (int i = 0; i < Notices.Length; i++)
                if (Notices[i] > 0) sb.Append(", notice ").Append(Protocol.ErrorName(i)).Append(' ').Append(Notices[i]);
            for (int i = 0; i < ErrorReplies.Length; i++)
                if (ErrorReplies[i] > 0) sb.Append(", error reply ").Append(Protocol.ErrorName(i)).Append(' ').Append(ErrorReplies[i]);
            for (int i = 1; i < Dropped.Length; i++)
                if (Dropped[i] > 0) sb.Append(", dropped ").Append(((DropReason)i).ToString()).Append(' ').Append(Dropped[i]);
            return sb.ToString();
        }
    }
}
