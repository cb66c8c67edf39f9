// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;

namespace Burrforce
{
    /// <summary>Writes the canonical msgpack form of SPEC.md §2.3 into a caller's buffer:
    /// integers in their smallest unsigned form, every float as float 64 (cb), bin 8 tags.
    /// A struct over a byte array so that encoding a POSE allocates nothing.</summary>
    public struct MsgPackWriter
    {
        private readonly byte[] buffer;
        private int position;

        public MsgPackWriter(byte[] buffer, int offset)
        {
            if (buffer == null) throw new ArgumentNullException("buffer");
            this.buffer = buffer;
            position = offset;
        }

        /// <summary>Bytes written so far, counted from the start of the buffer.</summary>
        public int Position { get { return position; } }

        private void Need(int n)
        {
            if (position + n > buffer.Length)
                throw new ArgumentException("msgpack buffer too small");
        }

        public void WriteArrayHeader(int count)
        {
            if (count < 0 || count > 0xFFFF) throw new ArgumentOutOfRangeException("count");
            if (count <= 15)
            {
                Need(1);
                buffer[position++] = (byte)(0x90 | count);
            }
            else
            {
                Need(3);
                buffer[position++] = 0xdc;
                buffer[position++] = (byte)(count >> 8);
                buffer[position++] = (byte)count;
            }
        }

        public void WriteUInt(ulong value)
        {
            if (value <= 0x7f)
            {
                Need(1);
                buffer[position++] = (byte)value;
            }
            else if (value <= 0xff)
            {
                Need(2);
                buffer[position++] = 0xcc;
                buffer[position++] = (byte)value;
            }
            else if (value <= 0xffff)
            {
                Need(3);
                buffer[position++] = 0xcd;
                PutBigEndian(value, 2);
            }
            else if (value <= 0xffffffffUL)
            {
                Need(5);
                buffer[position++] = 0xce;
                PutBigEndian(value, 4);
            }
            else
            {
                Need(9);
                buffer[position++] = 0xcf;
                PutBigEndian(value, 8);
            }
        }

        /// <summary>A timestamp or other non-negative signed value (SPEC's integers are never
        /// negative on the wire).</summary>
        public void WriteUInt(long value)
        {
            if (value < 0) throw new ArgumentOutOfRangeException("value", "must be >= 0");
            WriteUInt((ulong)value);
        }

        public void WriteFloat64(double value)
        {
            Need(9);
            buffer[position++] = 0xcb;
            PutBigEndian((ulong)BitConverter.DoubleToInt64Bits(value), 8);
        }

        public void WriteVec3(Vec3 v)
        {
            WriteArrayHeader(3);
            WriteFloat64(v.X);
            WriteFloat64(v.Y);
            WriteFloat64(v.Z);
        }

        public void WriteQuat(Quat q)
        {
            WriteArrayHeader(4);
            WriteFloat64(q.X);
            WriteFloat64(q.Y);
            WriteFloat64(q.Z);
            WriteFloat64(q.W);
        }

        public void WriteBool(bool value)
        {
            Need(1);
            buffer[position++] = value ? (byte)0xc3 : (byte)0xc2;
        }

        public void WriteNil()
        {
            Need(1);
            buffer[position++] = 0xc0;
        }

        /// <summary>bin 8 header and 16 zero bytes: the tag's placeholder (SPEC.md §4.2).</summary>
        public void WriteTagPlaceholder()
        {
            Need(2 + Protocol.TagBytes);
            buffer[position++] = 0xc4;
            buffer[position++] = (byte)Protocol.TagBytes;
            Array.Clear(buffer, position, Protocol.TagBytes);
            position += Protocol.TagBytes;
        }

        private void PutBigEndian(ulong value, int bytes)
        {
            for (int i = bytes - 1; i >= 0; i--)
            {
                buffer[position + i] = (byte)value;
                value >>= 8;
            }
            position += bytes;
        }
    }
}
