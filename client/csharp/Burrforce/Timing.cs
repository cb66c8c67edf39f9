// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>Round trip and clock offset from one REPLY (SPEC.md §5.5). T1 = t_client_us,
    /// T2 = t_recv_us, T3 = t_send_us, T4 = the client clock when the REPLY arrived; all µs,
    /// signed 64-bit (server epochs are arbitrary: only differences mean anything).</summary>
    public struct RoundTrip
    {
        /// <summary>T4 − T1: what the reference client reports, server time included.</summary>
        public long RttUs;
        /// <summary>T3 − T2: time the server spent on the POSE.</summary>
        public long ServerUs;
        /// <summary>(T4 − T1) − (T3 − T2): the network's share.</summary>
        public long NetworkUs;
        /// <summary>Server clock − client clock, µs (exact when both directions take equally long).</summary>
        public double ClockOffsetUs;

        public static RoundTrip Of(long t1, long t2, long t3, long t4)
        {
            RoundTrip r;
            r.RttUs = t4 - t1;
            r.ServerUs = t3 - t2;
            r.NetworkUs = r.RttUs - r.ServerUs;
            r.ClockOffsetUs = ((double)(t2 - t1) + (double)(t3 - t4)) / 2.0;
            return r;
        }

        public static RoundTrip Of(Reply reply, long arrivedUs)
        {
            return Of(reply.TClientUs, unchecked((long)reply.TRecvUs), unchecked((long)reply.TSendUs), arrivedUs);
        }
    }
}
