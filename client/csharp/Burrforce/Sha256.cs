// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>SHA-256 (FIPS 180-4) with a copyable state, so that HMAC can start from
    /// precomputed inner and outer pad states and tag a datagram without allocating
    /// (System.Security.Cryptography allocates a result array per call). Not thread-safe.</summary>
    public sealed class Sha256
    {
        public const int DigestBytes = 32;
        public const int BlockBytes = 64;

        private static readonly uint[] K =
        {
            0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
            0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
            0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
            0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
            0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
            0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
            0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
            0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2,
        };

        private readonly uint[] state = new uint[8];
        private readonly byte[] block = new byte[BlockBytes];
        private readonly uint[] schedule = new uint[64];
        private int blockFill;
        private ulong totalBytes;

        public Sha256() { Reset(); }

        public void Reset()
        {
            state[0] = 0x6a09e667; state[1] = 0xbb67ae85; state[2] = 0x3c6ef372; state[3] = 0xa54ff53a;
            state[4] = 0x510e527f; state[5] = 0x9b05688c; state[6] = 0x1f83d9ab; state[7] = 0x5be0cd19;
            blockFill = 0;
            totalBytes = 0;
        }

        /// <summary>Makes this hash continue from exactly where <paramref name="other"/> is.</summary>
        public void CopyFrom(Sha256 other)
        {
            Array.Copy(other.state, state, 8);
            Array.Copy(other.block, block, BlockBytes);
            blockFill = other.blockFill;
            totalBytes = other.totalBytes;
        }

        public void Update(byte[] data, int offset, int count)
        {
            if (data == null) throw new ArgumentNullException("data");
            if (offset < 0 || count < 0 || offset + count > data.Length)
                throw new ArgumentOutOfRangeException("count");
            totalBytes += (ulong)count;
            while (count > 0)
            {
                if (blockFill == 0 && count >= BlockBytes)
                {
                    Compress(data, offset);
                    offset += BlockBytes;
                    count -= BlockBytes;
                    continue;
                }
                int n = Math.Min(BlockBytes - blockFill, count);
                Buffer.BlockCopy(data, offset, block, blockFill, n);
                blockFill += n;
                offset += n;
                count -= n;
                if (blockFill == BlockBytes)
                {
                    Compress(block, 0);
                    blockFill = 0;
                }
            }
        }

        /// <summary>Pads, writes the 32-byte digest to <paramref name="output"/> and leaves the
        /// state spent (Reset or CopyFrom before reuse).</summary>
        public void Final(byte[] output, int offset)
        {
            ulong bits = totalBytes * 8;
            block[blockFill++] = 0x80;
            if (blockFill > BlockBytes - 8)
            {
                Array.Clear(block, blockFill, BlockBytes - blockFill);
                Compress(block, 0);
                blockFill = 0;
            }
            Array.Clear(block, blockFill, BlockBytes - 8 - blockFill);
            for (int i = 0; i < 8; i++) block[BlockBytes - 1 - i] = (byte)(bits >> (8 * i));
            Compress(block, 0);
            blockFill = 0;
            for (int i = 0; i < 8; i++)
            {
                uint s = state[i];
                output[offset + 4 * i] = (byte)(s >> 24);
                output[offset + 4 * i + 1] = (byte)(s >> 16);
                output[offset + 4 * i + 2] = (byte)(s >> 8);
                output[offset + 4 * i + 3] = (byte)s;
            }
        }

        private static uint Rotr(uint x, int n) { return (x >> n) | (x << (32 - n)); }

        private void Compress(byte[] data, int offset)
        {
            uint[] w = schedule;
            for (int i = 0; i < 16; i++)
            {
                int j = offset + 4 * i;
                w[i] = ((uint)data[j] << 24) | ((uint)data[j + 1] << 16) | ((uint)data[j + 2] << 8) | data[j + 3];
            }
            for (int i = 16; i < 64; i++)
            {
                uint s0 = Rotr(w[i - 15], 7) ^ Rotr(w[i - 15], 18) ^ (w[i - 15] >> 3);
                uint s1 = Rotr(w[i - 2], 17) ^ Rotr(w[i - 2], 19) ^ (w[i - 2] >> 10);
                w[i] = w[i - 16] + s0 + w[i - 7] + s1;
            }
            uint a = state[0], b = state[1], c = state[2], d = state[3];
            uint e = state[4], f = state[5], g = state[6], h = state[7];
            for (int i = 0; i < 64; i++)
            {
                uint t1 = h + (Rotr(e, 6) ^ Rotr(e, 11) ^ Rotr(e, 25)) + ((e & f) ^ (~e & g)) + K[i] + w[i];
                uint t2 = (Rotr(a, 2) ^ Rotr(a, 13) ^ Rotr(a, 22)) + ((a & b) ^ (a & c) ^ (b & c));
                h = g; g = f; f = e; e = d + t1;
                d = c; c = b; b = a; a = t1 + t2;
            }
            state[0] += a; state[1] += b; state[2] += c; state[3] += d;
            state[4] += e; state[5] += f; state[6] += g; state[7] += h;
        }
    }
}
