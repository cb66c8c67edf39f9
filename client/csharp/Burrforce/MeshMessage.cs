// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;

namespace Burrforce
{
    /// <summary>A mesh chunk's index (a, b, c) (MESH.md §1).</summary>
    public struct ChunkIndex : IEquatable<ChunkIndex>, IComparable<ChunkIndex>
    {
        public readonly int A, B, C;

        public ChunkIndex(int a, int b, int c) { A = a; B = b; C = c; }

        public bool Equals(ChunkIndex o) { return A == o.A && B == o.B && C == o.C; }
        public override bool Equals(object o) { return o is ChunkIndex && Equals((ChunkIndex)o); }
        public override int GetHashCode() { return (A * 73856093) ^ (B * 19349663) ^ (C * 83492791); }

        public int CompareTo(ChunkIndex o)
        {
            if (A != o.A) return A.CompareTo(o.A);
            if (B != o.B) return B.CompareTo(o.B);
            return C.CompareTo(o.C);
        }

        public override string ToString() { return "(" + A + ", " + B + ", " + C + ")"; }
    }

    /// <summary>One chunk's surface, as delivered: positions and normals x, y, z per vertex
    /// (session frame and unit, or server mm), a material label per vertex, and triangles as
    /// vertex index triples in the winding asked for.</summary>
    public sealed class MeshChunk
    {
        public ChunkIndex Index;
        public int VertexCount;
        public int TriangleCount;
        /// <summary>3 · VertexCount floats.</summary>
        public float[] Positions;
        /// <summary>3 · VertexCount floats, unit vectors out of the bone.</summary>
        public float[] Normals;
        public byte[] Materials;
        /// <summary>3 · TriangleCount indices, each &lt; VertexCount.</summary>
        public int[] Triangles;

        /// <summary>No surface left (T = 0; the parser refuses vertices without triangles):
        /// the chunk is to be removed.</summary>
        public bool Empty { get { return TriangleCount == 0; } }
    }

    /// <summary>One mesh-chunk message (MESH.md §3).</summary>
    public sealed class MeshMessage
    {
        public const uint FlagMore = 1, FlagFull = 2, FlagCw = 4, FlagSessionFrame = 8;

        public int FormatVersion;
        public uint Flags;
        public uint Session;
        public uint ChunkCells;
        public ulong BoneVersion;
        public ulong Since;
        public uint NextCursor;
        public readonly List<MeshChunk> Chunks = new List<MeshChunk>();

        public bool More { get { return (Flags & FlagMore) != 0; } }
        public bool Full { get { return (Flags & FlagFull) != 0; } }
        public bool Clockwise { get { return (Flags & FlagCw) != 0; } }
        public bool SessionFrame { get { return (Flags & FlagSessionFrame) != 0; } }
    }

    /// <summary>Strict reader of mesh-chunk messages: every count is checked against the bytes
    /// left before anything is read, every triangle index against its chunk's vertex count;
    /// anything else throws FormatException.</summary>
    public static class MeshMessageParser
    {
        public const int HeaderBytes = 40;
        public const int ChunkHeadBytes = 20;
        public static readonly byte[] Magic = { 0x42, 0x46, 0x4d, 0x43 }; // "BFMC"

        public static MeshMessage Parse(byte[] data) { return Parse(data, 0, data.Length); }

        public static MeshMessage Parse(byte[] data, int offset, int count)
        {
            if (data == null) throw new ArgumentNullException("data");
            if (offset < 0 || count < 0 || offset + count > data.Length) throw new ArgumentOutOfRangeException("count");
            int end = offset + count;
            if (count < HeaderBytes) throw new FormatException("mesh message shorter than its 40-byte header");
            for (int i = 0; i < 4; i++)
                if (data[offset + i] != Magic[i]) throw new FormatException("not a mesh-chunk message (bad magic)");
            var m = new MeshMessage();
            m.FormatVersion = U16(data, offset + 4);
            if (m.FormatVersion != 1) throw new FormatException("mesh format version " + m.FormatVersion + " (this reader knows 1)");
            m.Flags = (uint)U16(data, offset + 6);
            m.Session = U32(data, offset + 8);
            m.ChunkCells = U32(data, offset + 12);
            m.BoneVersion = U64(data, offset + 16);
            m.Since = U64(data, offset + 24);
            m.NextCursor = U32(data, offset + 32);
            uint chunkCount = U32(data, offset + 36);
            int p = offset + HeaderBytes;
            if ((ulong)chunkCount * ChunkHeadBytes > (ulong)(end - p)) throw new FormatException("chunk_count exceeds the message");
            for (uint k = 0; k < chunkCount; k++)
            {
                int start = p;
                if (end - p < ChunkHeadBytes) throw new FormatException("truncated chunk header");
                var c = new MeshChunk { Index = new ChunkIndex(I32(data, p), I32(data, p + 4), I32(data, p + 8)) };
                uint v = U32(data, p + 12), t = U32(data, p + 16);
                // MESH.md §3: T = 0 removes the chunk, so vertices with it would be silently lost.
                if (t == 0 && v != 0) throw new FormatException("chunk " + c.Index + ": " + v + " vertices but no triangles");
                p += ChunkHeadBytes;
                ulong vertexBytes = 25UL * v;
                ulong pad = (4 - (ChunkHeadBytes + vertexBytes) % 4) % 4;
                ulong need = vertexBytes + pad + 12UL * t;
                if (need > (ulong)(end - p)) throw new FormatException("chunk " + c.Index + ": counts exceed the message");
                c.VertexCount = (int)v;
                c.TriangleCount = (int)t;
                c.Positions = Floats(data, p, 3 * c.VertexCount);
                p += 12 * c.VertexCount;
                c.Normals = Floats(data, p, 3 * c.VertexCount);
                p += 12 * c.VertexCount;
                c.Materials = new byte[c.VertexCount];
                Buffer.BlockCopy(data, p, c.Materials, 0, c.VertexCount);
                p += c.VertexCount;
                for (int i = 0; i < (int)pad; i++)
                    if (data[p + i] != 0) throw new FormatException("chunk " + c.Index + ": non-zero padding");
                p += (int)pad;
                if ((p - start) % 4 != 0) throw new FormatException("internal: misaligned triangles");
                c.Triangles = new int[3 * c.TriangleCount];
                for (int i = 0; i < c.Triangles.Length; i++)
                {
                    uint index = U32(data, p + 4 * i);
                    if (index >= v) throw new FormatException("chunk " + c.Index + ": vertex index " + index + " >= " + v);
                    c.Triangles[i] = (int)index;
                }
                p += 12 * c.TriangleCount;
                m.Chunks.Add(c);
            }
            if (p != end) throw new FormatException("trailing bytes after the last chunk");
            return m;
        }

        private static float[] Floats(byte[] data, int p, int n)
        {
            var f = new float[n];
            if (BitConverter.IsLittleEndian)
            {
                Buffer.BlockCopy(data, p, f, 0, 4 * n);
                return f;
            }
            var tmp = new byte[4];
            for (int i = 0; i < n; i++)
            {
                for (int j = 0; j < 4; j++) tmp[j] = data[p + 4 * i + 3 - j];
                f[i] = BitConverter.ToSingle(tmp, 0);
            }
            return f;
        }

        private static int U16(byte[] d, int p) { return d[p] | (d[p + 1] << 8); }
        private static uint U32(byte[] d, int p) { return (uint)(d[p] | (d[p + 1] << 8) | (d[p + 2] << 16) | (d[p + 3] << 24)); }
        private static int I32(byte[] d, int p) { return (int)U32(d, p); }
        private static ulong U64(byte[] d, int p) { return U32(d, p) | ((ulong)U32(d, p + 4) << 32); }
    }
}
