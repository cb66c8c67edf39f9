// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Encoding (canonical form, SPEC.md §2.3) and decoding (every accepted form,
    /// §2.2) of POSE, REPLY and NOTICE. Encoders write into a caller's buffer and return the
    /// length; decoders fill a caller's object, so a 1 kHz loop allocates nothing.</summary>
    public static class Codec
    {
        /// <summary>Encodes <paramref name="pose"/> into buffer (≥ Protocol.MaxPoseBytes) and
        /// tags it with <paramref name="tagger"/> (null: nil tag). Returns the length.</summary>
        public static int EncodePose(Pose pose, Tagger tagger, byte[] buffer)
        {
            var w = new MsgPackWriter(buffer, 0);
            w.WriteArrayHeader(Protocol.PoseElements);
            w.WriteUInt(Protocol.Version);
            w.WriteUInt(Protocol.TypePose);
            w.WriteUInt(pose.Session);
            w.WriteUInt(pose.Seq);
            w.WriteUInt(pose.TClientUs);
            w.WriteVec3(pose.Position);
            w.WriteQuat(pose.Orientation);
            w.WriteFloat64(pose.Rpm);
            w.WriteBool(pose.SpindleOn);
            if (pose.HasVelocity) w.WriteVec3(pose.Velocity); else w.WriteNil();
            w.WriteUInt(pose.Flags);
            w.WriteUInt(pose.Stream);
            return FinishTag(ref w, tagger, buffer);
        }

        public static int EncodeReply(Reply r, Tagger tagger, byte[] buffer)
        {
            var w = new MsgPackWriter(buffer, 0);
            w.WriteArrayHeader(Protocol.ReplyElements);
            w.WriteUInt(Protocol.Version);
            w.WriteUInt(Protocol.TypeReply);
            w.WriteUInt(r.Session);
            w.WriteUInt(r.Seq);
            w.WriteUInt(r.TClientUs);
            w.WriteUInt(r.TRecvUs);
            w.WriteUInt(r.TSendUs);
            w.WriteUInt((ulong)r.Error);
            w.WriteUInt(r.Status);
            w.WriteVec3(r.Force);
            w.WriteVec3(r.Resistive);
            w.WriteVec3(r.Torque);
            w.WriteFloat64(r.PowerW);
            w.WriteFloat64(r.VibrationAmplitudeN);
            w.WriteFloat64(r.VibrationFrequencyHz);
            w.WriteVec3(r.VibrationAxis);
            w.WriteVec3(r.ProxyPosition);
            w.WriteVec3(r.ProxyVelocity);
            w.WriteFloat64(r.CouplingStiffness);
            w.WriteFloat64(r.CouplingDamping);
            w.WriteFloat64(r.RemovedMm3);
            w.WriteUInt(r.BoneVersion);
            w.WriteVec3(r.FeedVelocity);
            return FinishTag(ref w, tagger, buffer);
        }

        public static int EncodeNotice(Notice n, Tagger tagger, byte[] buffer)
        {
            var w = new MsgPackWriter(buffer, 0);
            w.WriteArrayHeader(Protocol.NoticeElements);
            w.WriteUInt(Protocol.Version);
            w.WriteUInt(Protocol.TypeNotice);
            w.WriteUInt(n.Session);
            w.WriteUInt(n.Seq);
            w.WriteUInt(n.TClientUs);
            w.WriteUInt((ulong)n.Error);
            w.WriteUInt(n.Stream);
            return FinishTag(ref w, tagger, buffer);
        }

        private static int FinishTag(ref MsgPackWriter w, Tagger tagger, byte[] buffer)
        {
            if (tagger == null)
            {
                w.WriteNil();
                return w.Position;
            }
            w.WriteTagPlaceholder();
            tagger.Sign(buffer, w.Position);
            return w.Position;
        }

        // Elements 0-4, the same in every message type (SPEC.md §2.1).
        private static int ReadHeader(ref MsgPackReader r, out ulong version, out int type,
                                      out uint session, out uint seq, out long tClientUs)
        {
            int count = r.ReadArrayHeader();
            if (count < 5) throw new ProtocolException("fewer than 5 elements");
            version = r.ReadUInt(ulong.MaxValue);
            ulong t = r.ReadUInt(ulong.MaxValue);
            session = r.ReadUInt32();
            seq = r.ReadUInt32();
            tClientUs = r.ReadTimestamp();
            type = t > 255 ? 0 : (int)t;
            return count;
        }

        /// <summary>Decodes a POSE; throws ProtocolException for anything else.</summary>
        public static void DecodePose(byte[] data, int length, Pose into)
        {
            var r = new MsgPackReader(data, 0, length);
            ulong version; int type; uint session, seq; long t;
            int count = ReadHeader(ref r, out version, out type, out session, out seq, out t);
            if (version != Protocol.Version) throw new ProtocolException("protocol version " + version);
            if (type != Protocol.TypePose) throw new ProtocolException("not a POSE");
            if (count != Protocol.PoseElements) throw new ProtocolException("a POSE has 13 elements");
            into.Session = session; into.Seq = seq; into.TClientUs = t;
            into.Position = r.ReadVec3();
            into.Orientation = r.ReadQuat();
            into.Rpm = r.ReadFloat();
            into.SpindleOn = r.ReadBool();
            into.HasVelocity = !r.TryReadNil();
            into.Velocity = into.HasVelocity ? r.ReadVec3() : Vec3.Zero;
            into.Flags = r.ReadUInt32();
            into.Stream = r.ReadUInt32();
            into.Tagged = r.ReadTag();
            r.ExpectEnd();
        }

        /// <summary>Decodes a server datagram into <paramref name="reply"/> or
        /// <paramref name="notice"/> and says which; throws ProtocolException if it is neither
        /// a well-formed REPLY nor NOTICE of version 2 nor v1's BAD_VERSION notice (or is longer
        /// than 1024 bytes).</summary>
        public static MessageKind DecodeServerMessage(byte[] data, int length, Reply reply, Notice notice)
        {
            if (length > Protocol.MaxServerDatagramBytes) throw new ProtocolException("datagram longer than 1024 bytes");
            var r = new MsgPackReader(data, 0, length);
            ulong version; int type; uint session, seq; long t;
            int count = ReadHeader(ref r, out version, out type, out session, out seq, out t);
            if (version == Protocol.VersionV1 && type == Protocol.TypeNotice && count == Protocol.NoticeV1Elements)
            {
                // A peer of the other version says so in v1's shape; nothing else of v1 is
                // understood, so only that answer is taken (the caller can then say "update").
                int error = (int)r.ReadUInt(0xffff);
                if (error != Protocol.ErrorBadVersion) throw new ProtocolException("a version 1 notice other than BAD_VERSION");
                notice.Version = Protocol.VersionV1;
                notice.Session = session; notice.Seq = seq; notice.TClientUs = t;
                notice.Error = error;
                notice.Stream = 0;
                notice.Tagged = r.ReadTag();
                r.ExpectEnd();
                return MessageKind.Notice;
            }
            if (version != Protocol.Version) throw new ProtocolException("protocol version " + version);
            if (type == Protocol.TypeReply)
            {
                if (count != Protocol.ReplyElements) throw new ProtocolException("a REPLY has 24 elements");
                reply.Session = session; reply.Seq = seq; reply.TClientUs = t;
                reply.TRecvUs = r.ReadUInt(ulong.MaxValue);
                reply.TSendUs = r.ReadUInt(ulong.MaxValue);
                reply.Error = (int)r.ReadUInt(0xffff);
                reply.Status = r.ReadUInt32();
                reply.Force = r.ReadVec3();
                reply.Resistive = r.ReadVec3();
                reply.Torque = r.ReadVec3();
                reply.PowerW = r.ReadFloat();
                reply.VibrationAmplitudeN = r.ReadFloat();
                reply.VibrationFrequencyHz = r.ReadFloat();
                reply.VibrationAxis = r.ReadVec3();
                reply.ProxyPosition = r.ReadVec3();
                reply.ProxyVelocity = r.ReadVec3();
                reply.CouplingStiffness = r.ReadFloat();
                reply.CouplingDamping = r.ReadFloat();
                reply.RemovedMm3 = r.ReadFloat();
                reply.BoneVersion = r.ReadUInt(ulong.MaxValue);
                reply.FeedVelocity = r.ReadVec3();
                reply.Tagged = r.ReadTag();
                r.ExpectEnd();
                return MessageKind.Reply;
            }
            if (type == Protocol.TypeNotice)
            {
                if (count != Protocol.NoticeElements) throw new ProtocolException("a NOTICE has 8 elements");
                notice.Version = Protocol.Version;
                notice.Session = session; notice.Seq = seq; notice.TClientUs = t;
                notice.Error = (int)r.ReadUInt(0xffff);
                notice.Stream = r.ReadUInt32();
                notice.Tagged = r.ReadTag();
                r.ExpectEnd();
                return MessageKind.Notice;
            }
            throw new ProtocolException("not a server message (type " + type + ")");
        }

        /// <summary>Like DecodeServerMessage, but says None instead of throwing.</summary>
        public static MessageKind TryDecodeServerMessage(byte[] data, int length, Reply reply, Notice notice)
        {
            try
            {
                return DecodeServerMessage(data, length, reply, notice);
            }
            catch (ProtocolException)
            {
                return MessageKind.None;
            }
        }
    }
}
