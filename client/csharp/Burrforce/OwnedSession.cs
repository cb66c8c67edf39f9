// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Threading.Tasks;

namespace Burrforce
{
    /// <summary>A session created over REST for one owner, deleted when the owner releases it,
    /// even while the server is still creating it (an engine component disabled during the
    /// bone's load). Cancelling the creation instead would leave the server's session behind
    /// with nobody knowing its id, so the deletion waits for the creation to finish. It has
    /// its own BurrRest: the owner may dispose its client at any time. Thread-safe.</summary>
    public sealed class OwnedSession
    {
        private readonly object gate = new object();
        private readonly BurrRest rest;
        private Task<bool> released;

        private OwnedSession(BurrRest rest, Task<SessionInfo> created)
        {
            this.rest = rest;
            Created = created;
        }

        /// <summary>Starts creating a session on <paramref name="boneSource"/>; await Created.</summary>
        public static OwnedSession Create(string httpUrl, string token, string boneSource,
                                          IDictionary<string, object> parameters = null)
        {
            var rest = new BurrRest(httpUrl, token);
            return new OwnedSession(rest, Task.Run(() => rest.CreateSessionAsync(boneSource, parameters)));
        }

        /// <summary>The new session, once the server has it ready.</summary>
        public Task<SessionInfo> Created { get; private set; }

        public bool IsReleased { get { lock (gate) return released != null; } }

        /// <summary>Gives the session up: deletes it as soon as it exists, then disposes the
        /// client. True when a session was deleted, false when creation had failed. Calling it
        /// again returns the same task.</summary>
        public Task<bool> Release()
        {
            lock (gate)
            {
                if (released == null) released = ReleaseAsync();
                return released;
            }
        }

        private async Task<bool> ReleaseAsync()
        {
            try
            {
                SessionInfo s;
                try { s = await Created.ConfigureAwait(false); }
                catch (Exception) { return false; } // the owner saw this failure through Created
                await rest.DeleteSessionAsync(s.Id).ConfigureAwait(false);
                return true;
            }
            finally
            {
                rest.Dispose();
            }
        }
    }
}
