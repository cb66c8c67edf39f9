// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Reads the msgpack forms a receiver must accept (SPEC.md §2.2) for the fixed
    /// message layouts, field by field, and enforces the limits of §2.4. Any other byte,
    /// a truncated value or an out-of-range number throws <see cref="ProtocolException"/>;
    /// nothing is read past <c>end</c>.</summary>
    public struct MsgPackReader
    {
        public const int MaxArrayElements = 32;
        public const int MaxBinBytes = 64;

        private readonly byte[] data;
        private readonly int end;
        private int position;

        public MsgPackReader(byte[] data, int offset, int count)
        {
            if (data == null) throw new ArgumentNullException("data");
            if (offset < 0 || count < 0 || offset + count > data.Length)
                throw new ArgumentOutOfRangeException("count");
            this.data = data;
            position = offset;
            end = offset + count;
        }

        public int Position { get { return position; } }
        public bool AtEnd { get { return position == end; } }

        private byte Next()
        {
            if (position >= end) throw new ProtocolException("truncated msgpack");
            return data[position++];
        }

        private ulong BigEndian(int bytes)
        {
            if (end - position < bytes) throw new ProtocolException("truncated msgpack");
            ulong v = 0;
            for (int i = 0; i < bytes; i++) v = (v << 8) | data[position++];
            return v;
        }

        /// <summary>An array header (fixarray, array 16, array 32) of at most 32 elements.</summary>
        public int ReadArrayHeader()
        {
            byte b = Next();
            ulong n;
            if ((b & 0xf0) == 0x90) n = (ulong)(b & 0x0f);
            else if (b == 0xdc) n = BigEndian(2);
            else if (b == 0xdd) n = BigEndian(4);
            else throw new ProtocolException("expected an array");
            if (n > MaxArrayElements) throw new ProtocolException("array longer than 32 elements");
            return (int)n;
        }

        /// <summary>The next value as a non-negative integer; throws for a negative integer or
        /// a non-integer.</summary>
        private ulong ReadNonNegativeInteger()
        {
            bool negative;
            ulong v = ReadIntegerBits(out negative);
            if (negative) throw new ProtocolException("negative integer");
            return v;
        }

        // The value as magnitude bits; signed forms report their sign. Throws if the next
        // value is not an integer (a float is not an integer here).
        private ulong ReadIntegerBits(out bool negative)
        {
            negative = false;
            byte b = Next();
            if (b <= 0x7f) return b;
            if (b >= 0xe0)
            {
                negative = true;
                return (ulong)(-(long)(sbyte)b);
            }
            switch (b)
            {
                case 0xcc: return BigEndian(1);
                case 0xcd: return BigEndian(2);
                case 0xce: return BigEndian(4);
                case 0xcf: return BigEndian(8);
                case 0xd0: return Signed((long)(sbyte)(byte)BigEndian(1), out negative);
                case 0xd1: return Signed((long)(short)(ushort)BigEndian(2), out negative);
                case 0xd2: return Signed((long)(int)(uint)BigEndian(4), out negative);
                case 0xd3: return Signed((long)BigEndian(8), out negative);
            }
            position--;
            throw new ProtocolException("expected an integer");
        }

        private static ulong Signed(long v, out bool negative)
        {
            negative = v < 0;
            // -long.MinValue overflows; its magnitude as ulong is still right.
            return negative ? (ulong)(-(v + 1)) + 1UL : (ulong)v;
        }

        /// <summary>An integer of any form in 0 … <paramref name="max"/>.</summary>
        public ulong ReadUInt(ulong max)
        {
            ulong v = ReadNonNegativeInteger();
            if (v > max) throw new ProtocolException("integer out of range");
            return v;
        }

        public uint ReadUInt32() { return (uint)ReadUInt(uint.MaxValue); }

        /// <summary>A timestamp: any integer form, 0 … 2^63−1.</summary>
        public long ReadTimestamp() { return (long)ReadUInt(long.MaxValue); }

        /// <summary>A float field: float 64, float 32 or any integer form (SPEC.md §2.2).</summary>
        public double ReadFloat()
        {
            if (position >= end) throw new ProtocolException("truncated msgpack");
            byte b = data[position];
            if (b == 0xcb)
            {
                position++;
                return BitConverter.Int64BitsToDouble((long)BigEndian(8));
            }
            if (b == 0xca)
            {
                position++;
                uint bits = (uint)BigEndian(4);
                return Float32FromBits(bits);
            }
            bool negative;
            ulong magnitude = ReadIntegerBits(out negative);
            return negative ? -(double)magnitude : (double)magnitude;
        }

        // Widening float32 → float64 is exact, so the double's bits are built directly
        // (no BitConverter.Int32BitsToSingle on older .NET profiles, no allocation).
        private static double Float32FromBits(uint bits)
        {
            ulong sign = (ulong)(bits >> 31) << 63;
            int exponent = (int)((bits >> 23) & 0xff);
            ulong mantissa = bits & 0x7fffffUL;
            if (exponent == 0xff)
                return BitConverter.Int64BitsToDouble((long)(sign | (0x7ffUL << 52) | (mantissa << 29)));
            if (exponent == 0)
            {
                double magnitude = mantissa * 1.401298464324817e-45; // 2^-149, exact
                return sign != 0 ? -magnitude : magnitude;
            }
            ulong e64 = (ulong)(exponent - 127 + 1023);
            return BitConverter.Int64BitsToDouble((long)(sign | (e64 << 52) | (mantissa << 29)));
        }

        public bool ReadBool()
        {
            byte b = Next();
            if (b == 0xc3) return true;
            if (b == 0xc2) return false;
            position--;
            throw new ProtocolException("expected a bool");
        }

        /// <summary>True (and consumed) if the next value is nil.</summary>
        public bool TryReadNil()
        {
            if (position >= end) throw new ProtocolException("truncated msgpack");
            if (data[position] != 0xc0) return false;
            position++;
            return true;
        }

        public Vec3 ReadVec3()
        {
            if (ReadArrayHeader() != 3) throw new ProtocolException("expected 3 floats");
            double x = ReadFloat(), y = ReadFloat(), z = ReadFloat();
            return new Vec3(x, y, z);
        }

        public Quat ReadQuat()
        {
            if (ReadArrayHeader() != 4) throw new ProtocolException("expected 4 floats");
            double x = ReadFloat(), y = ReadFloat(), z = ReadFloat(), w = ReadFloat();
            return new Quat(x, y, z, w);
        }

        /// <summary>The tag element: nil (false) or a bin 8/16/32 of exactly 16 bytes (true).
        /// Only bin 8 verifies (SPEC.md §4.3); the verifier checks that itself.</summary>
        public bool ReadTag()
        {
            if (TryReadNil()) return false;
            byte b = Next();
            ulong n;
            if (b == 0xc4) n = BigEndian(1);
            else if (b == 0xc5) n = BigEndian(2);
            else if (b == 0xc6) n = BigEndian(4);
            else
            {
                position--;
                throw new ProtocolException("the tag is neither nil nor bin");
            }
            if (n > MaxBinBytes) throw new ProtocolException("bin longer than 64 bytes");
            if (n != Protocol.TagBytes) throw new ProtocolException("a tag is 16 bytes");
            if (end - position < (int)n) throw new ProtocolException("truncated msgpack");
            position += (int)n;
            return true;
        }

        /// <summary>Throws unless every byte has been read (a datagram is one object).</summary>
        public void ExpectEnd()
        {
            if (position != end) throw new ProtocolException("trailing bytes after the message");
        }
    }
}
