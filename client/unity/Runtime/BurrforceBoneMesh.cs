// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using UnityEngine;
using UnityEngine.Rendering;

namespace Burrforce.Unity
{
    /// <summary>The carved bone: one child GameObject (MeshFilter + MeshRenderer) per mesh
    /// chunk, kept current over the mesh WebSocket on a background task; chunk swaps happen
    /// here on the main thread. Chunks arrive in Unity world coordinates (the session's
    /// `unity` frame, placement applied) with winding ccw (MESH.md §5): keep this object's
    /// transform at identity.</summary>
    [AddComponentMenu("Burrforce/Burrforce Bone Mesh")]
    public sealed class BurrforceBoneMesh : MonoBehaviour
    {
        public BurrforceSession session;
        public Material material;
        [Range(1, 8)] public int chunkBricks = 2;
        [Range(10, 1000)] public int intervalMs = 33;
        [Tooltip("Apply at most this many chunk swaps per frame (spreads a full load over frames)")]
        public int maxChunksPerFrame = 64;

        /// <summary>Chunks shown, and the bone version they are at.</summary>
        public int ChunkCount { get { return objects.Count; } }
        public ulong MeshBoneVersion { get { return follower != null ? follower.Mesh.Have : 0; } }

        private readonly Dictionary<ChunkIndex, GameObject> objects = new Dictionary<ChunkIndex, GameObject>();
        private readonly List<KeyValuePair<ChunkIndex, MeshChunk>> changes = new List<KeyValuePair<ChunkIndex, MeshChunk>>();
        private readonly Queue<KeyValuePair<ChunkIndex, MeshChunk>> backlog = new Queue<KeyValuePair<ChunkIndex, MeshChunk>>();
        private MeshFollower follower;
        private Exception seenError;
        private string loggedMessage;
        private long loggedAtUpdates;

        private void OnEnable()
        {
            if (transform.position != Vector3.zero || transform.rotation != Quaternion.identity || transform.lossyScale != Vector3.one)
                Debug.LogWarning("burrforce: the bone mesh's transform is not identity; chunks are in world coordinates");
        }

        private void Update()
        {
            if (session == null) return;
            if (session.Ready)
            {
                if (session.Rest == null)
                {
                    Debug.LogError("burrforce: the bone mesh needs the session's REST URL and token");
                    enabled = false;
                    return;
                }
                if (follower == null)
                {
                    var options = new MeshSyncOptions { ChunkBricks = chunkBricks, IntervalMs = intervalMs, Frame = "session", Winding = Frame.Unity.MeshWinding };
                    follower = new MeshFollower(new ChunkedMesh(), options);
                }
                // Restarts after a fault or a close, and switches when the session is re-created.
                follower.Follow(session.Rest, session.SessionId);
            }
            else if (follower != null)
            {
                follower.Stop(); // the session's client is gone; its chunks stay shown until it is back
            }
            if (follower == null) return;
            if (follower.LastError != null && follower.LastError != seenError)
            {
                seenError = follower.LastError;
                // A refusing server fails every retry the same way: say it again only when it
                // changed or the sync worked in between.
                if (seenError.Message != loggedMessage || follower.Mesh.Updates > loggedAtUpdates)
                {
                    loggedMessage = seenError.Message;
                    loggedAtUpdates = follower.Mesh.Updates;
                    Debug.LogWarning("burrforce: mesh sync stopped, retrying: " + seenError.Message);
                }
            }
            changes.Clear();
            if (follower.Mesh.TakeChanges(changes))
            {
                backlog.Clear();
                foreach (var kv in objects) DestroyChunk(kv.Value);
                objects.Clear();
            }
            foreach (var c in changes) backlog.Enqueue(c);
            for (int n = 0; n < maxChunksPerFrame && backlog.Count > 0; n++)
            {
                var c = backlog.Dequeue();
                Swap(c.Key, c.Value);
            }
        }

        // A Mesh is an asset: destroying its GameObject leaves it alive.
        private static void DestroyChunk(GameObject go)
        {
            if (go == null) return;
            var f = go.GetComponent<MeshFilter>();
            if (f != null) Destroy(f.sharedMesh);
            Destroy(go);
        }

        private void Swap(ChunkIndex index, MeshChunk chunk)
        {
            GameObject go;
            objects.TryGetValue(index, out go);
            if (chunk == null)
            {
                DestroyChunk(go);
                objects.Remove(index);
                return;
            }
            if (go == null)
            {
                go = new GameObject("chunk " + index);
                go.transform.SetParent(transform, false);
                go.AddComponent<MeshFilter>().sharedMesh = new Mesh { name = "bone chunk " + index };
                go.AddComponent<MeshRenderer>().sharedMaterial = material;
                objects[index] = go;
            }
            Mesh m = go.GetComponent<MeshFilter>().sharedMesh;
            m.Clear();
            m.indexFormat = chunk.VertexCount > 65535 ? IndexFormat.UInt32 : IndexFormat.UInt16;
            var vertices = new Vector3[chunk.VertexCount];
            var normals = new Vector3[chunk.VertexCount];
            var uv = new Vector2[chunk.VertexCount];
            for (int i = 0; i < chunk.VertexCount; i++)
            {
                vertices[i] = new Vector3(chunk.Positions[3 * i], chunk.Positions[3 * i + 1], chunk.Positions[3 * i + 2]);
                normals[i] = new Vector3(chunk.Normals[3 * i], chunk.Normals[3 * i + 1], chunk.Normals[3 * i + 2]);
                // The material label, for shaders that colour cortical, cancellous, nerve...
                uv[i] = new Vector2(chunk.Materials[i], 0f);
            }
            m.vertices = vertices;
            m.normals = normals;
            m.uv2 = uv;
            m.SetTriangles(chunk.Triangles, 0, true);
        }

        private void OnDisable()
        {
            if (follower != null)
            {
                follower.Dispose();
                follower = null;
            }
            seenError = null;
            loggedMessage = null;
            backlog.Clear();
            foreach (var kv in objects) DestroyChunk(kv.Value);
            objects.Clear();
        }
    }
}
