// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Datagram tags (SPEC.md §4): HMAC-SHA256 with the session key over every byte
    /// before the tag's 16 bytes (its <c>c4 10</c> header included), truncated to 16 bytes.
    /// The pad states are hashed once per key; one Tagger per thread (it keeps scratch
    /// state so that signing and verifying allocate nothing).</summary>
    public sealed class Tagger
    {
        private readonly Sha256 innerStart = new Sha256();
        private readonly Sha256 outerStart = new Sha256();
        private readonly Sha256 work = new Sha256();
        private readonly byte[] digest = new byte[Sha256.DigestBytes];

        public Tagger(byte[] key)
        {
            if (key == null || key.Length == 0) throw new ArgumentException("a session key must not be empty");
            byte[] k = key;
            if (k.Length > Sha256.BlockBytes)
            {
                // RFC 2104: a key longer than a block is hashed first.
                var h = new Sha256();
                h.Update(k, 0, k.Length);
                k = new byte[Sha256.DigestBytes];
                h.Final(k, 0);
            }
            var pad = new byte[Sha256.BlockBytes];
            for (int i = 0; i < pad.Length; i++) pad[i] = (byte)((i < k.Length ? k[i] : 0) ^ 0x36);
            innerStart.Update(pad, 0, pad.Length);
            for (int i = 0; i < pad.Length; i++) pad[i] = (byte)((i < k.Length ? k[i] : 0) ^ 0x5c);
            outerStart.Update(pad, 0, pad.Length);
        }

        /// <summary>A Tagger for a key in hex (as REST and `burrforce serve` show it), or null
        /// for a session without a key (null or empty text).</summary>
        public static Tagger FromHex(string keyHex)
        {
            if (string.IsNullOrEmpty(keyHex)) return null;
            return new Tagger(Hex.Decode(keyHex));
        }

        /// <summary>The full 32-byte HMAC-SHA256 of data[offset, offset+count) into output.</summary>
        public void Mac(byte[] data, int offset, int count, byte[] output32, int outputOffset)
        {
            work.CopyFrom(innerStart);
            work.Update(data, offset, count);
            work.Final(digest, 0);
            work.CopyFrom(outerStart);
            work.Update(digest, 0, Sha256.DigestBytes);
            work.Final(output32, outputOffset);
        }

        /// <summary>Fills the last 16 bytes of datagram[0, length) (encoded with a placeholder
        /// tag) with the tag.</summary>
        public void Sign(byte[] datagram, int length)
        {
            if (length < Protocol.TagBytes + 2) throw new ArgumentException("too short to hold a tag");
            Mac(datagram, 0, length - Protocol.TagBytes, digest, 0);
            Buffer.BlockCopy(digest, 0, datagram, length - Protocol.TagBytes, Protocol.TagBytes);
        }

        /// <summary>True if datagram[0, length) ends with <c>c4 10</c> and a right tag
        /// (compared in constant time).</summary>
        public bool Verify(byte[] datagram, int length)
        {
            if (datagram == null || length < Protocol.TagBytes + 2 || length > datagram.Length) return false;
            int tagAt = length - Protocol.TagBytes;
            if (datagram[tagAt - 2] != 0xc4 || datagram[tagAt - 1] != Protocol.TagBytes) return false;
            Mac(datagram, 0, tagAt, digest, 0);
            int diff = 0;
            for (int i = 0; i < Protocol.TagBytes; i++) diff |= digest[i] ^ datagram[tagAt + i];
            return diff == 0;
        }
    }
}
