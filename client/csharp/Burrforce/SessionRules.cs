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
        /// <summary>Not a well-formed REPLY or NOTICE of version 2 (nor v1's BAD_VERSION notice).</summary>
        Malformed,
        /// <summary>A REPLY, NEW_STREAM or WRONG_STREAM of a keyed session without a right
        /// tag (forged or corrupt).</summary>
        BadTag,
        /// <summary>About another session.</summary>
        Foreign,
        /// <summary>A REPLY not newer than the newest used (reordered or duplicated); a
        /// NEW_STREAM while a stream is open, or a WRONG_STREAM about a stream not in use.</summary>
        Stale,
        /// <summary>A REPLY that answers no POSE this client sent recently, or a NEW_STREAM
        /// that answers none of its hellos since it lost its stream (a replay).</summary>
        Unsolicited,
        Count,
    }

    /// <summary>What both the blocking client and the streamer do for one session, without
    /// I/O: number, tag and put the stream into outgoing POSEs (hellos, stream 0, until the
    /// server opens a stream), follow the handshake's NEW_STREAM and WRONG_STREAM notices,
    /// and decide which incoming datagrams to believe (SPEC.md §4.3, §5.1, §5.2, §10). Not
    /// thread-safe: one owner thread.</summary>
    public sealed class SessionRules
    {
        public readonly uint Session;
        private readonly Tagger tagger;
        // POSEs of a stream, awaiting their REPLY.
        private readonly SentPoses sent;
        // Hellos since the stream became 0: only a NEW_STREAM echoing one of them is taken,
        // so an old NEW_STREAM replayed to a new client cannot hand it a dead stream.
        private readonly SentPoses hellos;
        private uint nextSeq;
        private uint stream;
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
            hellos = new SentPoses(1024);
        }

        public bool Keyed { get { return tagger != null; } }

        /// <summary>The stream the server opened for this client; 0 while it says hello.</summary>
        public uint Stream { get { return stream; } }

        public uint NextSeq { get { return nextSeq; } }

        /// <summary>Gives up the stream: POSEs are hellos again until the server opens a new
        /// one, whose first tick starts sequence and velocity afresh. Never needed to follow
        /// the server (its WRONG_STREAM does that, e.g. after a REST restart-stream).</summary>
        public void Restart()
        {
            stream = Protocol.HelloStream;
            hellos.Clear();
        }

        /// <summary>Numbers <paramref name="pose"/>, puts the stream in (0: a hello, which the
        /// server answers with NEW_STREAM and does not tick), encodes and tags it into buffer;
        /// returns the length. pose.Session, Seq and Stream are set here.</summary>
        public int Encode(Pose pose, byte[] buffer, long tick = -1)
        {
            pose.Session = Session;
            pose.Seq = nextSeq;
            pose.Stream = stream;
            nextSeq = Sequence.Next(nextSeq);
            int n = Codec.EncodePose(pose, tagger, buffer);
            if (stream == Protocol.HelloStream) hellos.Add(pose.Seq, pose.TClientUs, tick);
            else sent.Add(pose.Seq, pose.TClientUs, tick);
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
            var no = new Notice { Session = Session, Error = Protocol.ErrorNewStream };
            n = Codec.EncodeNotice(no, tagger, scratch);
            Codec.TryDecodeServerMessage(scratch, n, reply, notice);
            long tick;
            sent.Take(0, -1, out tick);
            hellos.Take(0, -1, out tick);
            Sequence.IsNewer(1, 0);
        }

        /// <summary>Classifies a datagram. Returns Reply or Notice (decoded into the given
        /// objects) if it is to be believed, else None with the reason in
        /// <paramref name="reason"/>. A NEW_STREAM or WRONG_STREAM notice is returned only
        /// when it changed the stream (Stream tells to what). For a Reply, or a NEW_STREAM,
        /// <paramref name="tick"/> is the tick of the POSE it answers.</summary>
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
            bool handshake = kind == MessageKind.Notice
                && (notice.Error == Protocol.ErrorNewStream || notice.Error == Protocol.ErrorWrongStream);
            // Replies and the handshake's notices of a keyed session are always tagged. Other
            // notices pass unverified: they carry no force and change nothing, and a BAD_TAG
            // one is tagged with a key a client with the wrong key cannot check, yet it must
            // learn that its key is wrong.
            if ((kind == MessageKind.Reply || handshake) && tagger != null && !tagger.Verify(data, length))
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
            if (handshake) return Handshake(notice, out reason, out tick);
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

        private MessageKind Handshake(Notice notice, out DropReason reason, out long tick)
        {
            tick = -1;
            reason = DropReason.None;
            if (notice.Error == Protocol.ErrorNewStream)
            {
                // Hellos sent before the answer arrived get the same offer again, and a hello
                // replayed later gets a fresh one: neither may move an open stream.
                if (stream != Protocol.HelloStream)
                {
                    reason = DropReason.Stale;
                    return MessageKind.None;
                }
                if (notice.Stream == Protocol.HelloStream || !hellos.Take(notice.Seq, notice.TClientUs, out tick))
                {
                    reason = DropReason.Unsolicited;
                    return MessageKind.None;
                }
                stream = notice.Stream;
                hellos.Clear();
                return MessageKind.Notice;
            }
            // A WRONG_STREAM about a stream this client already left (in flight while it
            // took a new one) must not cost it the new one.
            if (stream == Protocol.HelloStream || notice.Stream != stream)
            {
                reason = DropReason.Stale;
                return MessageKind.None;
            }
            Restart();
            return MessageKind.Notice;
        }
    }
}
