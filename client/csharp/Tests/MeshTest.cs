// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Threading;
using System.Threading.Tasks;

namespace Burrforce.Tests
{
    /// <summary>Mesh chunks (MESH.md) on a fresh session in an engine frame: follow the
    /// WebSocket while the groove is cut, wait until the copy has caught up with the last
    /// REPLY's bone_version, check a REST copy (small pages, then an incremental update)
    /// agrees, and dump the union as OBJ. The session is left for the caller to compare with
    /// the server's export and delete.</summary>
    public static class MeshTest
    {
        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            var checks = new Checks();
            var result = new Dictionary<string, object>();
            var clock = System.Diagnostics.Stopwatch.StartNew();
            var phases = new Dictionary<string, object>();
            result["phase_ms"] = phases;
            Frame frame = Frame.Named(opts["frame"]);
            var rest = new BurrRest(opts["http-url"], opts["token"]);
            SessionInfo s = rest.CreateSession("phantom:workpiece", frame.Name);
            result["session"] = (long)s.Id;
            var options = new MeshSyncOptions { Winding = frame.MeshWinding, IntervalMs = 20 };
            var mesh = new ChunkedMesh();
            var sync = new MeshSync(rest, s.Id, mesh, options);
            using (var cts = new CancellationTokenSource())
            {
                Task ws = Task.Run(() => sync.RunWebSocketAsync(cts.Token));
                checks.That(WaitFor(() => mesh.Complete || ws.IsCompleted, 60000), "the first WebSocket update arrived");
                if (ws.IsFaulted) throw ws.Exception.GetBaseException();
                phases["first_update"] = clock.ElapsedMilliseconds;
                int before = mesh.Count;
                long triBefore = mesh.TriangleCount;
                result["chunks_before"] = (long)before;
                result["triangles_before"] = triBefore;

                // Drain the first update's changes as an engine would, then cut.
                var changes = new List<KeyValuePair<ChunkIndex, MeshChunk>>();
                bool clear = mesh.TakeChanges(changes);
                checks.That(clear && changes.Count == before, "the first update hands every chunk over, after a clear");

                var groove = GrooveTest.Cut(s.UdpHost, s.UdpPort, s.Id, s.KeyHex, frame);
                long replyVersion = (long)groove["last_bone_version"];
                result["reply_bone_version"] = replyVersion;
                result["groove_replies"] = groove["replies"];
                checks.That(replyVersion > 0, "the groove removed bone");
                checks.That(WaitFor(() => (long)mesh.Have >= replyVersion || ws.IsCompleted, 60000),
                            "the mesh caught up with the last REPLY's bone_version");
                if (ws.IsFaulted) throw ws.Exception.GetBaseException();
                phases["caught_up"] = clock.ElapsedMilliseconds;
                result["mesh_bone_version"] = (long)mesh.Have;
                changes.Clear();
                clear = mesh.TakeChanges(changes);
                checks.That(!clear && changes.Count > 0, "the cut handed changed chunks over without a clear");
                result["chunks_changed_handed"] = (long)changes.Count;
                cts.Cancel();
                checks.That(ws.Wait(10000), "the WebSocket task ended on cancel");
            }
            result["chunks"] = (long)mesh.Count;
            result["chunks_replaced"] = mesh.Replaced;
            result["full_messages"] = mesh.FullMessages;
            result["messages"] = mesh.Messages;
            result["ws_messages"] = sync.WebSocketMessages;
            result["triangles"] = mesh.TriangleCount;

            // A REST copy: every chunk in 256 KiB pages, then nothing new since.
            var restMesh = new ChunkedMesh();
            var restSync = new MeshSync(rest, s.Id, restMesh, new MeshSyncOptions
            {
                Winding = frame.MeshWinding, MaxBytes = 262144,
            });
            phases["ws_closed"] = clock.ElapsedMilliseconds;
            int pages = restSync.SyncOnce();
            phases["rest_full"] = clock.ElapsedMilliseconds;
            result["rest_pages"] = (long)pages;
            checks.That(pages > 1, "small pages: several pages (MORE and next_cursor followed)");
            checks.That(restMesh.Count == mesh.Count && restMesh.TriangleCount == mesh.TriangleCount,
                        "REST and WebSocket copies agree: " + restMesh.Count + "/" + restMesh.TriangleCount);
            long messagesBefore = restMesh.Messages;
            restSync.SyncOnce();
            checks.That(restMesh.Messages == messagesBefore + 1 && restMesh.Count == mesh.Count,
                        "an incremental REST update with nothing new changes nothing");

            // Strictness of the parser on a real message: every truncation is refused.
            byte[] real = rest.GetMeshAsync(s.Id, null, 2, "session", frame.MeshWinding, 0, 65536).GetAwaiter().GetResult();
            int refused = 0;
            for (int cut = 0; cut < real.Length; cut += Math.Max(1, real.Length / 300))
            {
                try { MeshMessageParser.Parse(real, 0, cut); }
                catch (FormatException) { refused++; continue; }
                checks.Failures.Add("a message cut to " + cut + " bytes parsed");
            }
            result["truncations_refused"] = (long)refused;

            // Errors: a missing session over REST (404 with the server's detail) and over the
            // WebSocket (closed with 4404).
            try
            {
                new MeshSync(rest, 4000000123u, new ChunkedMesh()).SyncOnce();
                checks.Failures.Add("mesh of a missing session over REST answered");
            }
            catch (BurrRestException e)
            {
                checks.That(e.Status == 404, "mesh of a missing session over REST: " + e.Status + " " + e.Detail);
            }
            try
            {
                using (var cts = new CancellationTokenSource(20000))
                    new MeshSync(rest, 4000000123u, new ChunkedMesh()).RunWebSocketAsync(cts.Token).GetAwaiter().GetResult();
                checks.Failures.Add("mesh WebSocket of a missing session did not fail");
            }
            catch (MeshSyncException e)
            {
                result["ws_missing_close_code"] = (long)e.CloseCode;
                checks.That(e.CloseCode == 4404, "mesh WebSocket of a missing session closed with " + e.CloseCode);
            }

            phases["errors"] = clock.ElapsedMilliseconds;
            mesh.WriteObj(opts["obj"]);
            rest.Dispose();
            result["passed"] = (long)checks.Passed;
            result["failures"] = checks.Failures;
            return result;
        }

        private static bool WaitFor(Func<bool> condition, int timeoutMs)
        {
            long end = MonotonicClock.NowUs() + timeoutMs * 1000L;
            while (MonotonicClock.NowUs() < end)
            {
                if (condition()) return true;
                Thread.Sleep(10);
            }
            return condition();
        }
    }
}
