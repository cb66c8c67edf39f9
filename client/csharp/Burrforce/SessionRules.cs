// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Why an incoming datagram was not believed.</summary>
    public enum DropReason
    {
        None = 0,
        /// <summary>Longer than the server's 1024-byte limit.</summary>
        TooBig,
        /// <summary>Not a well-formed REPLY or NOTICE of version 1.</summary>
        Malformed,
        /// <summary>A REPLY of a keyed session without a right tag (forged or corrupt).</summary>
        BadTag,
        /// <summary>About another session.</summary>
        Foreign,
        /// <summary>Not newer than the newest REPLY used (reordered or duplicated).</summary>
        Stale,
        /// <summary>Answers no POSE this client sent recently (a replay).</summary>
        Unsolicited,
        Count,
    }

    /// <summary>What both the blocking client and the streamer do for one session, without
    /// I/O: number and tag outgoing POSEs (FLAG_NEW_STREAM until the first REPLY), and decide
    /// which incoming datagrams to believe (SPEC.md §4.3, §5.1, §10). Not thread-safe: one
    /// owner thread.</summary>
    public sealed class SessionRules
    {
        public readonly uint Session;
        private readonly Tagger tagger;
        private readonly SentPoses sent;
        private uint nextSeq;
        private bool haveNewest;
        private uint newest;

        public SessionRules(uint session, string keyHex, uint firstSeq = 1)
            : this(session, Tagger.FromHex(keyHex), firstSeq) { }

        public SessionRules(uint session, Tagger tagger, uint firstSeq = 1)
        {
            Session = session;
            this.tagger = tagger;
            nextSeq = firstSeq;
            sent = new SentPoses(1024);
        }

        public bool Keyed { get { return tagger != null; } }

        /// <summary>True once a REPLY (of any error value) has been accepted.</summary>
        public bool StreamAnswered { get { return haveNewest; } }

        public uint NextSeq { get { return nextSeq; } }

        /// <summary>Starts a new stream: FLAG_NEW_STREAM again until the next REPLY, and
        /// earlier POSEs' replies are no longer believed.</summary>
        public void Restart()
        {
            haveNewest = false;
            sent.Clear();
        }

        /// <summary>Numbers (and flags) <paramref name="pose"/>, encodes and tags it into
        /// buffer; returns the length. pose.Session, Seq and Flags are set here.</summary>
        public int Encode(Pose pose, byte[] buffer, long tick = -1)
        {
            pose.Session = Session;
            pose.Seq = nextSeq;
            nextSeq = Sequence.Next(nextSeq);
            if (!haveNewest) pose.Flags |= Protocol.FlagNewStream;
            int n = Codec.EncodePose(pose, tagger, buffer);
            sent.Add(pose.Seq, pose.TClientUs, tick);
            return n;
        }

        /// <summary>Runs the encode, tag and decode paths once on scratch data without touching
        /// the stream's state, so that a JIT compiles them before the first timed tick.</summary>
        public void WarmUp(byte[] scratch, Reply reply, Notice notice)
        {
            var p = new Pose { Session = Session, Orientation = Quat.Identity };
            int n = Codec.EncodePose(p, tagger, scratch);
            if (tagger != null) tagger.Verify(scratch, n);
            Codec.TryDecodeServerMessage(scratch, n, reply, notice);
            var r = new Reply { Session = Session };
            n = Codec.EncodeReply(r, tagger, scratch);
            Codec.TryDecodeServerMessage(scratch, n, reply, notice);
            long tick;
            sent.Take(0, -1, out tick);
            Sequence.IsNewer(1, 0);
        }

        /// <summary>Classifies a datagram. Returns Reply or Notice (decoded into the given
        /// objects) if it is to be believed, else None with the reason in
        /// <paramref name="reason"/>. For a Reply, <paramref name="tick"/> is the tick of the
        /// POSE it answers.</summary>
        public MessageKind Accept(byte[] data, int length, Reply reply, Notice notice,
                                  out DropReason reason, out long tick)
        {
            tick = -1;
            reason = DropReason.None;
            if (length > Protocol.MaxServerDatagramBytes)
            {
                reason = DropReason.TooBig;
                return MessageKind.None;
            }
            MessageKind kind = Codec.TryDecodeServerMessage(data, length, reply, notice);
            if (kind == MessageKind.None)
            {
                reason = DropReason.Malformed;
                return kind;
            }
            // Replies of a keyed session are always tagged. Notices pass unverified: they
            // carry no force, and a BAD_TAG one is tagged with a key a client with the wrong
            // key cannot check, yet it must learn that its key is wrong.
            if (kind == MessageKind.Reply && tagger != null && !tagger.Verify(data, length))
            {
                reason = DropReason.BadTag;
                return MessageKind.None;
            }
            uint session = kind == MessageKind.Reply ? reply.Session : notice.Session;
            if (session != Session)
            {
                reason = DropReason.Foreign;
                return MessageKind.None;
            }
            if (kind == MessageKind.Notice) return kind;
            if (haveNewest && !Sequence.IsNewer(reply.Seq, newest))
            {
                reason = DropReason.Stale;
                return MessageKind.None;
            }
            if (!sent.Take(reply.Seq, reply.TClientUs, out tick))
            {
                reason = DropReason.Unsolicited;
                return MessageKind.None;
            }
            haveNewest = true;
            newest = reply.Seq;
            return kind;
        }
    }
}
