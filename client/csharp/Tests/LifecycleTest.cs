// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Net;
using System.Net.Sockets;
using System.Threading;
using System.Threading.Tasks;

namespace Burrforce.Tests
{
    /// <summary>What an engine component goes through against the live server: a session given
    /// up while the server is still creating it (OwnedSession), and a mesh follower whose
    /// connection drops, whose session is deleted, then replaced, then reached through a new
    /// client (MeshFollower). The WebSocket runs through a TCP relay here, so the test can cut
    /// the connection the way a network does.</summary>
    public static class LifecycleTest
    {
        public static Dictionary<string, object> Run(Dictionary<string, string> opts)
        {
            var checks = new Checks();
            var result = new Dictionary<string, object>();
            string url = opts["http-url"], token = opts["token"];
            using (var rest = new BurrRest(url, token))
            {
                Owned(rest, url, token, checks, result);
                Follower(rest, url, token, checks, result);
            }
            result["passed"] = (long)checks.Passed;
            result["failures"] = checks.Failures;
            return result;
        }

        private static void Owned(BurrRest rest, string url, string token, Checks checks, Dictionary<string, object> result)
        {
            var frame = new Dictionary<string, object> { { "frame", "unity" } };
            // Released before the server has answered: the session must still go away.
            OwnedSession early = OwnedSession.Create(url, token, "phantom:workpiece", frame);
            bool pending = !early.Created.IsCompleted;
            Task<bool> released = early.Release();
            result["released_while_creating"] = pending;
            checks.That(early.Release() == released, "a second Release gives the same task");
            checks.That(released.Wait(120000) && released.Result, "release during creation deleted the session");
            checks.That(early.Created.Status == TaskStatus.RanToCompletion, "the creation was not cancelled");
            if (early.Created.Status == TaskStatus.RanToCompletion)
            {
                uint id = early.Created.Result.Id;
                result["early_session"] = (long)id;
                checks.That(StatusOf(rest, id) == 404, "the session released during creation is gone: " + StatusOf(rest, id));
            }

            OwnedSession late = OwnedSession.Create(url, token, "phantom:workpiece", frame);
            SessionInfo s = late.Created.GetAwaiter().GetResult();
            checks.That(StatusOf(rest, s.Id) == 200, "an owned session exists until released");
            checks.That(late.Release().GetAwaiter().GetResult() && StatusOf(rest, s.Id) == 404, "released after creation: deleted");

            OwnedSession failed = OwnedSession.Create(url, token, "phantom:no-such-bone", frame);
            checks.That(!failed.Release().GetAwaiter().GetResult() && failed.Created.IsFaulted,
                        "a failed creation releases to false, its error kept in Created");
        }

        private static int StatusOf(BurrRest rest, uint id)
        {
            try { rest.GetSession(id); return 200; }
            catch (BurrRestException e) { return e.Status; }
        }

        private static void Follower(BurrRest rest, string url, string token, Checks checks, Dictionary<string, object> result)
        {
            var target = new Uri(url);
            using (var relay = new TcpRelay(target.Host, target.Port))
            {
                string relayed = "http://127.0.0.1:" + relay.Port;
                var viaRelay = new BurrRest(relayed, token);
                Frame frame = Frame.Named("si_mm");
                SessionInfo a = rest.CreateSession("phantom:workpiece", frame.Name);
                var options = new MeshSyncOptions { IntervalMs = 20, ReconnectDelayMs = 100, MaxReconnectDelayMs = 800 };
                var f = new MeshFollower(new ChunkedMesh(), options);
                ChunkedMesh mesh = f.Mesh;
                var changes = new List<KeyValuePair<ChunkIndex, MeshChunk>>();

                checks.That(Follow(f, viaRelay, a.Id, () => mesh.Complete, 60000), "the follower's first update");
                var groove = GrooveTest.Cut(a.UdpHost, a.UdpPort, a.Id, a.KeyHex, frame);
                long version = (long)groove["last_bone_version"];
                checks.That(Follow(f, viaRelay, a.Id, () => (long)mesh.Have >= version, 60000), "the follower caught up with the cut");
                ulong have = mesh.Have;
                long full = mesh.FullMessages, messages = mesh.Messages, accepted = relay.Accepted;
                result["have_before_drop"] = (long)have;

                // A dropped connection: reconnect with since = Have, no FULL resend.
                result["dropped_connections"] = (long)relay.DropAll();
                checks.That(Follow(f, viaRelay, a.Id, () => relay.Accepted > accepted && mesh.Messages > messages, 20000),
                            "a message after the reconnect");
                checks.That(f.Sync.ConnectedSince.HasValue && f.Sync.ConnectedSince.Value == have,
                            "reconnected with since = Have: " + f.Sync.ConnectedSince + " vs " + have);
                checks.That(mesh.FullMessages == full && mesh.Have == have, "no FULL resend after the reconnect");

                // The session deleted: the server closes with 1001, the follower keeps trying
                // (4404 now) with a growing delay.
                long starts = f.Starts;
                rest.DeleteSession(a.Id);
                checks.That(Follow(f, viaRelay, a.Id, () => f.LastError is MeshSyncException, 20000),
                            "the follower restarted after the close and met 4404");
                var refused = f.LastError as MeshSyncException;
                result["close_code_after_delete"] = refused != null ? (long)refused.CloseCode : -1L;
                long startsAt = f.Starts;
                Follow(f, viaRelay, a.Id, () => false, 3000);
                result["restarts_after_delete"] = f.Starts - starts;
                result["starts_in_3s_refused"] = f.Starts - startsAt;
                checks.That(f.Starts - startsAt >= 2 && f.Starts - startsAt <= 7,
                            "back-off: " + (f.Starts - startsAt) + " starts in 3 s (100 ms doubling to 800 ms)");

                // The server reuses a deleted session's id: a new session under the old id,
                // through the same client. The follower's since = Have is newer than the new
                // bone, so the server resends everything (FULL) and Have drops to its version.
                SessionInfo b = rest.CreateSession("phantom:workpiece", frame.Name);
                result["id_reused"] = b.Id == a.Id;
                long updates = mesh.Updates;
                mesh.TakeChanges(changes);
                changes.Clear();
                checks.That(Follow(f, viaRelay, b.Id, () => mesh.FullMessages > full && mesh.Updates > updates, 60000),
                            "the follower got the new session's chunks");
                checks.That(mesh.TakeChanges(changes) && changes.Count == mesh.Count && mesh.Count > 0,
                            "a clear and every chunk of the new session handed over");
                checks.That(mesh.Have == 0, "the new session's bone is uncarved: Have " + mesh.Have);

                // A new client (an engine re-enabled its session component): start afresh.
                long fullB = mesh.FullMessages, startsB = f.Starts;
                updates = mesh.Updates;
                var again = new BurrRest(relayed, token);
                viaRelay.Dispose();
                changes.Clear();
                checks.That(Follow(f, again, b.Id, () => f.Starts > startsB && mesh.Updates > updates, 20000),
                            "the follower moved to the new client");
                checks.That(mesh.FullMessages == fullB + 1 && !f.Sync.ConnectedSince.HasValue && mesh.Count > 0,
                            "the new client asked for every chunk");
                checks.That(mesh.TakeChanges(changes) && changes.Count == mesh.Count, "the new client's copy handed over after a clear");

                f.Dispose();
                again.Dispose();
                rest.DeleteSession(b.Id);
                result["follower_starts"] = f.Starts;
                result["follower_errors"] = f.Errors;
            }
        }

        // An engine's frame loop: Follow each "frame" until the condition holds.
        private static bool Follow(MeshFollower f, BurrRest rest, uint session, Func<bool> condition, int timeoutMs)
        {
            long end = MonotonicClock.NowUs() + timeoutMs * 1000L;
            while (MonotonicClock.NowUs() < end)
            {
                f.Follow(rest, session);
                if (condition()) return true;
                Thread.Sleep(10);
            }
            return condition();
        }
    }

    /// <summary>Relays TCP connections from a loopback port to the server, and cuts them all on
    /// demand (reset, as a failing network or a sleeping laptop does).</summary>
    public sealed class TcpRelay : IDisposable
    {
        private readonly TcpListener listener;
        private readonly string host;
        private readonly int port;
        private readonly List<TcpClient> open = new List<TcpClient>();
        private long accepted;

        public TcpRelay(string host, int port)
        {
            this.host = host;
            this.port = port;
            listener = new TcpListener(IPAddress.Loopback, 0);
            listener.Start();
            Task.Run(() => AcceptLoop());
        }

        public int Port { get { return ((IPEndPoint)listener.LocalEndpoint).Port; } }
        public long Accepted { get { return Interlocked.Read(ref accepted); } }

        private async Task AcceptLoop()
        {
            while (true)
            {
                TcpClient inbound;
                try { inbound = await listener.AcceptTcpClientAsync().ConfigureAwait(false); }
                catch (Exception) { return; }
                var outbound = new TcpClient();
                try { await outbound.ConnectAsync(host, port).ConfigureAwait(false); }
                catch (Exception) { inbound.Close(); continue; }
                lock (open) { open.Add(inbound); open.Add(outbound); }
                Interlocked.Increment(ref accepted);
                _ = Pump(inbound, outbound);
                _ = Pump(outbound, inbound);
            }
        }

        private static async Task Pump(TcpClient from, TcpClient to)
        {
            try { await from.GetStream().CopyToAsync(to.GetStream()).ConfigureAwait(false); }
            catch (Exception) { }
            try { to.Close(); from.Close(); } catch (Exception) { }
        }

        /// <summary>Resets every relayed connection; returns how many were open.</summary>
        public int DropAll()
        {
            lock (open)
            {
                int n = 0;
                foreach (TcpClient c in open)
                {
                    try
                    {
                        if (!c.Connected) continue;
                        c.Client.LingerState = new LingerOption(true, 0);
                        c.Close();
                        n++;
                    }
                    catch (Exception) { }
                }
                open.Clear();
                return n / 2;
            }
        }

        public void Dispose()
        {
            listener.Stop();
            DropAll();
        }
    }
}
