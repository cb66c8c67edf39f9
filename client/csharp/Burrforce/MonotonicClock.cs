// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System.Diagnostics;

namespace Burrforce
{
    /// <summary>The client's monotonic clock in µs: what goes into t_client_us (SPEC.md §5.3).
    /// Never wall-clock time (it jumps), never Unity's Time.time (frame-quantized, scaled).</summary>
    public static class MonotonicClock
    {
        private static readonly long Frequency = Stopwatch.Frequency;

        /// <summary>µs since an arbitrary, fixed origin (system boot on most platforms).
        /// Split into whole seconds and remainder so that neither overflows nor rounds.</summary>
        public static long NowUs()
        {
            long t = Stopwatch.GetTimestamp();
            return t / Frequency * 1000000L + t % Frequency * 1000000L / Frequency;
        }
    }
}
