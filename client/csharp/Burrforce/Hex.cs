// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Text;

namespace Burrforce
{
    /// <summary>Hex text ↔ bytes (session keys, test vectors).</summary>
    public static class Hex
    {
        /// <summary>Bytes of hex text (surrounding white space ignored). Throws FormatException
        /// for an odd length, a non-hex digit or empty text.</summary>
        public static byte[] Decode(string text)
        {
            if (text == null) throw new ArgumentNullException("text");
            string t = text.Trim();
            if (t.Length == 0 || t.Length % 2 != 0)
                throw new FormatException("hex text must have an even, non-zero number of digits");
            var bytes = new byte[t.Length / 2];
            for (int i = 0; i < bytes.Length; i++)
                bytes[i] = (byte)((Digit(t[2 * i]) << 4) | Digit(t[2 * i + 1]));
            return bytes;
        }

        public static string Encode(byte[] data, int offset, int count)
        {
            const string digits = "0123456789abcdef";
            var sb = new StringBuilder(count * 2);
            for (int i = 0; i < count; i++)
            {
                byte b = data[offset + i];
                sb.Append(digits[b >> 4]).Append(digits[b & 15]);
            }
            return sb.ToString();
        }

        public static string Encode(byte[] data) { return Encode(data, 0, data.Length); }

        private static int Digit(char c)
        {
            if (c >= '0' && c <= '9') return c - '0';
            if (c >= 'a' && c <= 'f') return c - 'a' + 10;
            if (c >= 'A' && c <= 'F') return c - 'A' + 10;
            throw new FormatException("not a hex digit: '" + c + "'");
        }
    }
}
