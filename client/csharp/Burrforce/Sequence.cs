// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

namespace Burrforce
{
    /// <summary>RFC 1982 serial number arithmetic on uint32 sequence numbers (SPEC.md §5.1).</summary>
    public static class Sequence
    {
        /// <summary>True if <paramref name="a"/> is newer than <paramref name="b"/>:
        /// 0 &lt; (a − b) mod 2^32 &lt; 2^31. Numbers exactly 2^31 apart are not newer.</summary>
        public static bool IsNewer(uint a, uint b)
        {
            return unchecked((int)(a - b)) > 0;
        }

        /// <summary>The number after <paramref name="seq"/> (4294967295 is followed by 0).</summary>
        public static uint Next(uint seq)
        {
            return unchecked(seq + 1u);
        }
    }
}
