// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>The POSEs sent recently, by sequence number: a REPLY is believed only if it
    /// answers one of them with the same seq and t_client_us (SPEC.md §4.4: old REPLYs
    /// replayed to a restarted client). A fixed ring: no allocation per POSE.</summary>
    public sealed class SentPoses
    {
        private readonly uint[] seqs;
        private readonly long[] stamps;
        private readonly long[] ticks;
        private readonly bool[] used;
        private readonly int mask;

        /// <param name="capacity">rounded up to a power of two; at 1 kHz, 1024 covers ~1 s of
        /// replies in flight</param>
        public SentPoses(int capacity)
        {
            int n = 1;
            while (n < capacity) n <<= 1;
            seqs = new uint[n];
            stamps = new long[n];
            ticks = new long[n];
            used = new bool[n];
            mask = n - 1;
        }

        public void Clear() { System.Array.Clear(used, 0, used.Length); }

        public void Add(uint seq, long tClientUs, long tick)
        {
            int i = (int)(seq & (uint)mask);
            seqs[i] = seq;
            stamps[i] = tClientUs;
            ticks[i] = tick;
            used[i] = true;
        }

        /// <summary>True (with the tick it was sent for) if (seq, t_client_us) was sent and
        /// is still remembered; the entry is then forgotten (one answer per POSE).</summary>
        public bool Take(uint seq, long tClientUs, out long tick)
        {
            int i = (int)(seq & (uint)mask);
            tick = ticks[i];
            if (!used[i] || seqs[i] != seq || stamps[i] != tClientUs) return false;
            used[i] = false;
            return true;
        }
    }
}
