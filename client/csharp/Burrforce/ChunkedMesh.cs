// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Text;

namespace Burrforce
{
    /// <summary>A client's copy of the bone's surface: chunk index → mesh, and the bone
    /// version <c>Have</c> every chunk is at least as new as (MESH.md §4). Messages are applied
    /// on a network thread; an engine's main thread takes the changed chunks with
    /// TakeChanges. Thread-safe.</summary>
    public sealed class ChunkedMesh
    {
        private readonly object gate = new object();
        private readonly Dictionary<ChunkIndex, MeshChunk> chunks = new Dictionary<ChunkIndex, MeshChunk>();
        private readonly Dictionary<ChunkIndex, MeshChunk> pending = new Dictionary<ChunkIndex, MeshChunk>();
        private bool pendingClear;
        private bool inUpdate;
        private ulong low;
        private ulong have;
        private bool complete;

        /// <summary>Chunks replaced or removed by updates after the first complete one.</summary>
        public long Replaced { get; private set; }
        /// <summary>Messages applied, and those of them with FULL set.</summary>
        public long Messages { get; private set; }
        public long FullMessages { get; private set; }
        /// <summary>Updates completed (a message without MORE applied).</summary>
        public long Updates { get; private set; }

        /// <summary>The bone version the copy is at: ask for since = Have next. Unset (0, with
        /// Complete false) before the first complete update: then ask without since.</summary>
        public ulong Have { get { lock (gate) return have; } }
        public bool Complete { get { lock (gate) return complete; } }
        public int Count { get { lock (gate) return chunks.Count; } }

        /// <summary>Raised (on the applying thread, outside the lock) when an update completes.</summary>
        public event Action<ulong> UpdateCompleted;

        /// <summary>Applies one message; true when it completed an update (Have moved).</summary>
        public bool Apply(MeshMessage m)
        {
            if (m == null) throw new ArgumentNullException("m");
            ulong completed;
            lock (gate)
            {
                Messages++;
                if (m.Full)
                {
                    FullMessages++;
                    chunks.Clear();
                    pending.Clear();
                    pendingClear = true;
                }
                foreach (MeshChunk c in m.Chunks)
                {
                    if (complete) Replaced++;
                    if (c.Empty) chunks.Remove(c.Index);
                    else chunks[c.Index] = c;
                    pending[c.Index] = c.Empty ? null : c;
                }
                low = inUpdate ? Math.Min(low, m.BoneVersion) : m.BoneVersion;
                inUpdate = true;
                if (m.More) return false;
                have = low;
                inUpdate = false;
                complete = true;
                Updates++;
                completed = have;
            }
            var h = UpdateCompleted;
            if (h != null) h(completed);
            return true;
        }

        /// <summary>Forgets every chunk: the next request asks for every chunk (no since).</summary>
        public void Reset()
        {
            lock (gate)
            {
                chunks.Clear();
                pending.Clear();
                pendingClear = true;
                inUpdate = false;
                have = 0;
                complete = false;
            }
        }

        /// <summary>Main thread: the chunks changed since the last call (null value: removed),
        /// and whether every chunk held before is to be dropped first. Coalesced: a chunk
        /// changed twice is given once, newest.</summary>
        public bool TakeChanges(List<KeyValuePair<ChunkIndex, MeshChunk>> changes)
        {
            lock (gate)
            {
                foreach (var kv in pending) changes.Add(kv);
                pending.Clear();
                bool clear = pendingClear;
                pendingClear = false;
                return clear;
            }
        }

        /// <summary>A snapshot of the chunks in index order.</summary>
        public List<MeshChunk> Snapshot()
        {
            lock (gate)
            {
                var keys = new List<ChunkIndex>(chunks.Keys);
                keys.Sort();
                var list = new List<MeshChunk>(keys.Count);
                foreach (var k in keys) list.Add(chunks[k]);
                return list;
            }
        }

        public long TriangleCount
        {
            get
            {
                long n = 0;
                foreach (var c in Snapshot()) n += c.TriangleCount;
                return n;
            }
        }

        /// <summary>The union of the chunks as OBJ: "v x y z" lines and 1-based "f a b c"
        /// lines, chunk after chunk, positions and winding as received.</summary>
        public void WriteObj(string path)
        {
            using (var w = new StreamWriter(path, false, new UTF8Encoding(false)))
            {
                w.NewLine = "\n";
                long offset = 1;
                foreach (MeshChunk c in Snapshot())
                {
                    for (int i = 0; i < c.VertexCount; i++)
                        w.WriteLine(string.Format(CultureInfo.InvariantCulture, "v {0:R} {1:R} {2:R}",
                            c.Positions[3 * i], c.Positions[3 * i + 1], c.Positions[3 * i + 2]));
                    for (int i = 0; i < c.TriangleCount; i++)
                        w.WriteLine(string.Format(CultureInfo.InvariantCulture, "f {0} {1} {2}",
                            offset + c.Triangles[3 * i], offset + c.Triangles[3 * i + 1], offset + c.Triangles[3 * i + 2]));
                    offset += c.VertexCount;
                }
            }
        }
    }
}
