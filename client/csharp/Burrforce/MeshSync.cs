// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.IO;
using System.Net.WebSockets;
using System.Threading;
using System.Threading.Tasks;

namespace Burrforce
{
    /// <summary>What to ask the mesh endpoints for (MESH.md §2).</summary>
    public sealed class MeshSyncOptions
    {
        /// <summary>Chunk edge in 8-voxel bricks, 1–8.</summary>
        public int ChunkBricks = 2;
        /// <summary>"session" (the session's engine frame and unit) or "server" (mm).</summary>
        public string Frame = "session";
        /// <summary>"ccw" or "cw": Frame.MeshWinding is the one an engine draws.</summary>
        public string Winding = "ccw";
        /// <summary>WebSocket: the shortest time between two updates, 10–1000 ms.</summary>
        public int IntervalMs = 33;
        /// <summary>REST: a page's size budget, bytes.</summary>
        public int MaxBytes = 4 << 20;
        /// <summary>A WebSocket message larger than this is refused.</summary>
        public int MaxMessageBytes = 256 << 20;
        /// <summary>WebSocket: wait this long before reconnecting after a dropped connection
        /// (or, in MeshFollower, before restarting an ended sync); doubled after each attempt
        /// that brought no update, up to MaxReconnectDelayMs.</summary>
        public int ReconnectDelayMs = 500;
        public int MaxReconnectDelayMs = 10000;
    }

    /// <summary>The WebSocket was closed with one of the endpoint's error codes (4401 token,
    /// 4404 session, 4409 not ready or deltas off, 4422 bad parameter).</summary>
    public sealed class MeshSyncException : Exception
    {
        public readonly int CloseCode;

        public MeshSyncException(int code, string reason)
            : base("mesh WebSocket closed: " + code + " " + reason)
        {
            CloseCode = code;
        }
    }

    /// <summary>Keeps a ChunkedMesh current from the server: over REST (SyncOnceAsync: every
    /// page since Have) or the WebSocket push channel (RunWebSocketAsync: until cancelled,
    /// reconnecting with since = Have). Runs on whatever thread awaits it, never the caller's
    /// synchronization context.</summary>
    public sealed class MeshSync
    {
        private readonly BurrRest rest;
        private readonly uint session;
        private readonly ChunkedMesh mesh;
        private readonly MeshSyncOptions options;

        public MeshSync(BurrRest rest, uint session, ChunkedMesh mesh, MeshSyncOptions options = null)
        {
            if (rest == null) throw new ArgumentNullException("rest");
            if (mesh == null) throw new ArgumentNullException("mesh");
            this.rest = rest;
            this.session = session;
            this.mesh = mesh;
            this.options = options ?? new MeshSyncOptions();
        }

        public ChunkedMesh Mesh { get { return mesh; } }

        /// <summary>Messages received over the WebSocket since it (re)connected first.</summary>
        public long WebSocketMessages { get; private set; }
        public long Reconnects { get; private set; }
        /// <summary>The since of the newest WebSocket connection (null: it asked for every chunk).</summary>
        public ulong? ConnectedSince { get; private set; }

        internal static int Doubled(int delayMs, MeshSyncOptions o)
        {
            return (int)Math.Min(Math.Max((long)delayMs * 2, o.ReconnectDelayMs), o.MaxReconnectDelayMs);
        }

        /// <summary>Brings the mesh up to date over REST: every page of one update. Returns the
        /// pages fetched.</summary>
        public async Task<int> SyncOnceAsync(CancellationToken ct = default(CancellationToken))
        {
            ulong? since = mesh.Complete ? mesh.Have : (ulong?)null;
            uint cursor = 0;
            int pages = 0;
            while (true)
            {
                byte[] data = await rest.GetMeshAsync(session, since, options.ChunkBricks, options.Frame,
                    options.Winding, cursor, options.MaxBytes, ct).ConfigureAwait(false);
                MeshMessage m = MeshMessageParser.Parse(data);
                Check(m);
                pages++;
                mesh.Apply(m);
                if (!m.More) return pages;
                cursor = m.NextCursor;
            }
        }

        public int SyncOnce() { return SyncOnceAsync().GetAwaiter().GetResult(); }

        private void Check(MeshMessage m)
        {
            if (m.Session != session) throw new FormatException("mesh message for session " + m.Session + ", expected " + session);
            bool cw = options.Winding == "cw";
            if (m.Clockwise != cw) throw new FormatException("mesh message in the other winding than asked for");
        }

        /// <summary>Follows the push channel until cancelled (returns) or the server closes
        /// it for good (1001: session deleted or server stopping: returns; 44xx: throws
        /// MeshSyncException). A dropped connection is reopened with since = Have.</summary>
        public async Task RunWebSocketAsync(CancellationToken ct)
        {
            bool first = true;
            int delayMs = options.ReconnectDelayMs;
            long updates = mesh.Updates;
            while (!ct.IsCancellationRequested)
            {
                if (!first)
                {
                    Reconnects++;
                    // A server that is down or refusing is not hammered; one that was
                    // delivering gets the short delay again.
                    if (mesh.Updates > updates) delayMs = options.ReconnectDelayMs;
                    updates = mesh.Updates;
                    try { await Task.Delay(delayMs, ct).ConfigureAwait(false); }
                    catch (OperationCanceledException) { return; }
                    delayMs = Doubled(delayMs, options);
                }
                first = false;
                int closeCode;
                string reason;
                try
                {
                    closeCode = await OneConnectionAsync(ct).ConfigureAwait(false);
                    reason = lastCloseReason;
                }
                catch (OperationCanceledException)
                {
                    return;
                }
                catch (WebSocketException)
                {
                    if (ct.IsCancellationRequested) return;
                    continue; // dropped: reconnect
                }
                if (closeCode == 1001 || closeCode == 1000) return;
                if (closeCode >= 4000 && closeCode < 5000) throw new MeshSyncException(closeCode, reason);
            }
        }

        private string lastCloseReason;

        private async Task<int> OneConnectionAsync(CancellationToken ct)
        {
            ulong? since = mesh.Complete ? mesh.Have : (ulong?)null;
            ConnectedSince = since;
            Uri uri = rest.MeshWebSocketUri(session, since, options.ChunkBricks, options.Frame, options.Winding,
                                            options.IntervalMs);
            using (var ws = new ClientWebSocket())
            {
                if (!string.IsNullOrEmpty(rest.Token)) ws.Options.SetRequestHeader("Authorization", "Bearer " + rest.Token);
                await ws.ConnectAsync(uri, ct).ConfigureAwait(false);
                var chunk = new byte[1 << 16];
                var message = new MemoryStream();
                try
                {
                    while (true)
                    {
                        WebSocketReceiveResult r = await ws.ReceiveAsync(new ArraySegment<byte>(chunk), ct).ConfigureAwait(false);
                        if (r.MessageType == WebSocketMessageType.Close)
                        {
                            lastCloseReason = r.CloseStatusDescription;
                            int code = r.CloseStatus.HasValue ? (int)r.CloseStatus.Value : 1005;
                            try
                            {
                                await ws.CloseOutputAsync(WebSocketCloseStatus.NormalClosure, "", CancellationToken.None).ConfigureAwait(false);
                            }
                            catch (WebSocketException) { }
                            return code;
                        }
                        if (message.Length + r.Count > options.MaxMessageBytes)
                            throw new FormatException("mesh WebSocket message larger than " + options.MaxMessageBytes + " bytes");
                        message.Write(chunk, 0, r.Count);
                        if (!r.EndOfMessage) continue;
                        if (r.MessageType == WebSocketMessageType.Binary)
                        {
                            MeshMessage m = MeshMessageParser.Parse(message.GetBuffer(), 0, (int)message.Length);
                            Check(m);
                            // A cancelled sync may no longer own the mesh (MeshFollower switched it).
                            ct.ThrowIfCancellationRequested();
                            WebSocketMessages++;
                            mesh.Apply(m);
                        }
                        message.SetLength(0);
                    }
                }
                finally
                {
                    if (ws.State == WebSocketState.Open && ct.IsCancellationRequested)
                    {
                        try
                        {
                            using (var quick = new CancellationTokenSource(1000))
                                await ws.CloseAsync(WebSocketCloseStatus.NormalClosure, "", quick.Token).ConfigureAwait(false);
                        }
                        catch (Exception) { }
                    }
                }
            }
        }
    }

    /// <summary>Keeps a ChunkedMesh following the session an engine has now: call Follow each
    /// frame (Stop while there is none). It runs a WebSocket sync and starts it again, after a
    /// back-off, whenever it ended: the server closed it (1000, 1001: deleted session or
    /// stopping server), refused it (44xx) or it faulted. A restart continues with since = Have
    /// (MESH.md §4: a bone that was replaced meanwhile comes back FULL). Another session id or
    /// another BurrRest drops the chunks first and asks for every chunk: the server reuses
    /// the ids of deleted sessions, and a new client usually means a new session. Main thread
    /// only; the sync runs on the thread pool.</summary>
    public sealed class MeshFollower : IDisposable
    {
        private readonly ChunkedMesh mesh;
        private readonly MeshSyncOptions options;
        private BurrRest targetRest;
        private uint targetSession;
        private bool resetPending;
        private CancellationTokenSource cts;
        private Task run;
        private Task stopping;
        private long updatesAtStart;
        private long notBeforeUs;
        private int delayMs;

        public MeshFollower(ChunkedMesh mesh = null, MeshSyncOptions options = null)
        {
            this.mesh = mesh ?? new ChunkedMesh();
            this.options = options ?? new MeshSyncOptions();
            delayMs = this.options.ReconnectDelayMs;
        }

        public ChunkedMesh Mesh { get { return mesh; } }
        /// <summary>The newest run's sync (its counters), null before the first.</summary>
        public MeshSync Sync { get; private set; }
        /// <summary>Runs started, and those that ended with an error (the newest: LastError).</summary>
        public long Starts { get; private set; }
        public long Errors { get; private set; }
        public Exception LastError { get; private set; }
        public bool Running { get { return run != null && !run.IsCompleted; } }

        /// <summary>Follows <paramref name="session"/> of the server <paramref name="rest"/>
        /// talks to. Cheap when nothing changed; never blocks.</summary>
        public void Follow(BurrRest rest, uint session)
        {
            if (rest == null) throw new ArgumentNullException("rest");
            long now = MonotonicClock.NowUs();
            if (rest != targetRest || session != targetSession)
            {
                Stop();
                resetPending = targetRest != null; // the old session's chunks mean nothing here
                targetRest = rest;
                targetSession = session;
                delayMs = options.ReconnectDelayMs;
                notBeforeUs = now;
            }
            if (run != null)
            {
                if (!run.IsCompleted) return;
                Ended(now);
            }
            // The old run must be gone before the mesh is reset or a new run applies to it.
            if (stopping != null)
            {
                if (!stopping.IsCompleted) return;
                stopping = null;
            }
            if (now < notBeforeUs) return;
            if (resetPending)
            {
                mesh.Reset();
                resetPending = false;
            }
            Start(rest, session);
        }

        private void Start(BurrRest rest, uint session)
        {
            var sync = new MeshSync(rest, session, mesh, options);
            Sync = sync;
            cts = new CancellationTokenSource();
            CancellationToken token = cts.Token;
            updatesAtStart = mesh.Updates;
            Starts++;
            run = Task.Run(() => sync.RunWebSocketAsync(token));
        }

        private void Ended(long now)
        {
            if (run.IsFaulted)
            {
                LastError = run.Exception.GetBaseException();
                Errors++;
            }
            bool progressed = mesh.Updates > updatesAtStart;
            int wait = progressed ? options.ReconnectDelayMs : delayMs;
            delayMs = MeshSync.Doubled(wait, options);
            notBeforeUs = now + wait * 1000L;
            run = null;
            cts.Dispose();
            cts = null;
        }

        /// <summary>Stops the sync; the chunks are kept (Follow with the same client and
        /// session goes on from them).</summary>
        public void Stop()
        {
            if (run == null) return;
            cts.Cancel();
            // Observed here: a cancelled run may still fault on a disposed client.
            Task old = run;
            CancellationTokenSource oldCts = cts;
            stopping = old.ContinueWith(t => { _ = t.Exception; oldCts.Dispose(); }, TaskScheduler.Default);
            run = null;
            cts = null;
        }

        public void Dispose() { Stop(); }
    }
}
