// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>Constants of the wire protocol, version 2 (SPEC.md §3).</summary>
    public static class Protocol
    {
        public const int Version = 2;
        /// <summary>The previous version: a v2 server answers a v1 datagram (and a v1 server a
        /// v2 one) with a BAD_VERSION notice in v1's shape, the only v1 message decoded.</summary>
        public const int VersionV1 = 1;
        public const int TypePose = 1, TypeReply = 2, TypeNotice = 3;
        public const int PoseElements = 13, ReplyElements = 24, NoticeElements = 8, NoticeV1Elements = 7;
        public const int TagBytes = 16;
        /// <summary>POSE stream 0: a hello, asking the server for a stream (not ticked).</summary>
        public const uint HelloStream = 0;

        // The true maxima (a uint64 clock in a POSE from a machine up > 71.6 min); a receive
        // buffer larger than the server's limit lets an oversized datagram be seen and dropped.
        public const int MaxPoseBytes = 153;
        public const int MaxReplyBytes = 327;
        public const int MaxServerDatagramBytes = 1024;
        public const int ReceiveBufferBytes = 2048;

        // Bit 2 (v1's FLAG_NEW_STREAM) is reserved again: the server hands out streams.
        public const uint FlagResetVelocity = 1, FlagNoCarve = 2;

        public const uint StatusCutting = 1, StatusContact = 2, StatusForbidden = 4,
            StatusClamped = 8, StatusStale = 16, StatusShaftContact = 32, StatusSlowSpindle = 64;

        public const int ErrorOk = 0, ErrorMalformed = 1, ErrorTooBig = 2, ErrorBadVersion = 3,
            ErrorBadType = 4, ErrorUnknownSession = 5, ErrorBadTag = 6, ErrorBadValue = 7,
            ErrorStale = 8, ErrorDuplicate = 9, ErrorInternal = 10,
            // Notices only, tagged with the session's key: the stream handshake (SPEC.md §5.2).
            ErrorNewStream = 11, ErrorWrongStream = 12;

        /// <summary>The name of an error code ("BAD_TAG"), or its number as text.</summary>
        public static string ErrorName(int code)
        {
            switch (code)
            {
                case 0: return "OK";
                case 1: return "MALFORMED";
                case 2: return "TOO_BIG";
                case 3: return "BAD_VERSION";
                case 4: return "BAD_TYPE";
                case 5: return "UNKNOWN_SESSION";
                case 6: return "BAD_TAG";
                case 7: return "BAD_VALUE";
                case 8: return "STALE";
                case 9: return "DUPLICATE";
                case 10: return "INTERNAL";
                case 11: return "NEW_STREAM";
                case 12: return "WRONG_STREAM";
                default: return code.ToString(System.Globalization.CultureInfo.InvariantCulture);
            }
        }
    }

    /// <summary>A POSE (client → server), engine frame and units (SPEC.md §3.1).</summary>
    public sealed class Pose
    {
        public uint Session;
        public uint Seq;
        /// <summary>When the pose was sampled, µs, client monotonic clock.</summary>
        public long TClientUs;
        /// <summary>Burr centre, engine length unit L.</summary>
        public Vec3 Position;
        public Quat Orientation = Quat.Identity;
        public double Rpm;
        public bool SpindleOn;
        /// <summary>False: velocity nil (the server estimates it).</summary>
        public bool HasVelocity;
        /// <summary>Burr centre velocity, L/s, engine axes (used when HasVelocity).</summary>
        public Vec3 Velocity;
        public uint Flags;
        /// <summary>The stream the server opened for this client, or HelloStream (0) to ask
        /// for one (SessionRules sets it).</summary>
        public uint Stream;
        /// <summary>Decoding only: the tag element was a 16-byte bin (else nil).</summary>
        public bool Tagged;
    }

    /// <summary>A REPLY (server → client), engine frame and units (SPEC.md §3.2).</summary>
    public sealed class Reply
    {
        public uint Session;
        public uint Seq;
        public long TClientUs;
        /// <summary>Server monotonic clock, µs (uint64 on the wire; below 2^63 in practice).</summary>
        public ulong TRecvUs;
        public ulong TSendUs;
        public int Error;
        public uint Status;
        /// <summary>Force of the bone on the tool, N, engine axes.</summary>
        public Vec3 Force;
        /// <summary>(feed, lateral, normal) components of the cutting force, N; frame-free.</summary>
        public Vec3 Resistive;
        /// <summary>N·L, engine axes (a pseudovector, already corrected for reflections).</summary>
        public Vec3 Torque;
        public double PowerW;
        public double VibrationAmplitudeN;
        public double VibrationFrequencyHz;
        public Vec3 VibrationAxis;
        public Vec3 ProxyPosition;
        public Vec3 ProxyVelocity;
        public double CouplingStiffness;
        public double CouplingDamping;
        public double RemovedMm3;
        public ulong BoneVersion;
        public Vec3 FeedVelocity;
        public bool Tagged;

        /// <summary>Copies every field of <paramref name="other"/> into this one (no allocation).</summary>
        public void CopyFrom(Reply other)
        {
            Session = other.Session; Seq = other.Seq; TClientUs = other.TClientUs;
            TRecvUs = other.TRecvUs; TSendUs = other.TSendUs; Error = other.Error;
            Status = other.Status; Force = other.Force; Resistive = other.Resistive;
            Torque = other.Torque; PowerW = other.PowerW;
            VibrationAmplitudeN = other.VibrationAmplitudeN;
            VibrationFrequencyHz = other.VibrationFrequencyHz; VibrationAxis = other.VibrationAxis;
            ProxyPosition = other.ProxyPosition; ProxyVelocity = other.ProxyVelocity;
            CouplingStiffness = other.CouplingStiffness; CouplingDamping = other.CouplingDamping;
            RemovedMm3 = other.RemovedMm3; BoneVersion = other.BoneVersion;
            FeedVelocity = other.FeedVelocity; Tagged = other.Tagged;
        }
    }

    /// <summary>A NOTICE: "the request with this header was not processed" (SPEC.md §3.3).
    /// Unauthenticated in general: a diagnostic, never a force; only the handshake's
    /// NEW_STREAM and WRONG_STREAM are believed, and only when their tag verifies.</summary>
    public sealed class Notice
    {
        /// <summary>Decoding only: Protocol.Version, or VersionV1 for the v1-shaped
        /// BAD_VERSION notice of a peer speaking the other version.</summary>
        public int Version = Protocol.Version;
        public uint Session;
        public uint Seq;
        public long TClientUs;
        public int Error;
        /// <summary>NEW_STREAM: the stream to use; WRONG_STREAM: the refused POSE's stream; else 0.</summary>
        public uint Stream;
        public bool Tagged;
    }

    /// <summary>What a server datagram decoded to.</summary>
    public enum MessageKind
    {
        None = 0,
        Reply = 2,
        Notice = 3,
    }
}
