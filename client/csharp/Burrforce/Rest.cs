// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.Globalization;
using System.Net;
using System.Net.Http;
using System.Net.Http.Headers;
using System.Text;
using System.Threading;
using System.Threading.Tasks;

namespace Burrforce
{
    /// <summary>The REST plane answered with an error: Status is the HTTP status, Detail the
    /// server's "detail" text (a validation error's list is given as its JSON).</summary>
    public sealed class BurrRestException : Exception
    {
        public readonly int Status;
        public readonly string Detail;

        public BurrRestException(int status, string detail, string what)
            : base(what + ": HTTP " + status + ": " + detail)
        {
            Status = status;
            Detail = detail;
        }
    }

    /// <summary>A session as REST describes it.</summary>
    public sealed class SessionInfo
    {
        public uint Id;
        /// <summary>Hex key, null for a session without one.</summary>
        public string KeyHex;
        public string UdpHost;
        public int UdpPort;
        public string State;
        public string Frame;
        /// <summary>The whole JSON object, for the fields not copied above.</summary>
        public Dictionary<string, object> Json;

        /// <param name="httpUrl">the REST root the answer came from: where a wildcard
        /// udp.host is to be sent instead</param>
        internal static SessionInfo From(Dictionary<string, object> o, string httpUrl)
        {
            var s = new SessionInfo { Json = o };
            s.Id = checked((uint)Burrforce.Json.GetLong(o, "id"));
            object key;
            s.KeyHex = o.TryGetValue("key", out key) ? key as string : null;
            object udp;
            if (o.TryGetValue("udp", out udp) && udp is Dictionary<string, object>)
            {
                var u = (Dictionary<string, object>)udp;
                s.UdpHost = BurrRest.ReachableHost(Burrforce.Json.GetString(u, "host"), httpUrl);
                s.UdpPort = (int)Burrforce.Json.GetLong(u, "port");
            }
            object v;
            if (o.TryGetValue("state", out v)) s.State = v as string;
            if (o.TryGetValue("frame", out v)) s.Frame = v as string;
            return s;
        }
    }

    /// <summary>The REST control plane (bearer token): create, inspect, tune and delete
    /// sessions; fetch mesh chunks. Async methods never capture the caller's synchronization
    /// context (safe to block on from Unity's main thread, though you should not: use the
    /// async forms there). Thread-safe.</summary>
    public sealed class BurrRest : IDisposable
    {
        public const string MeshMediaType = "application/vnd.burrforce.mesh-chunks";

        private readonly HttpClient http;
        private readonly string apiBase;
        private readonly string token;

        /// <param name="httpUrl">the server's REST root without /v1, e.g. http://127.0.0.1:8080</param>
        public BurrRest(string httpUrl, string token, TimeSpan? timeout = null)
        {
            if (string.IsNullOrEmpty(httpUrl)) throw new ArgumentException("httpUrl is empty");
            string root = httpUrl.TrimEnd('/');
            if (root.EndsWith("/v1", StringComparison.Ordinal)) root = root.Substring(0, root.Length - 3);
            apiBase = root + "/v1";
            HttpUrl = root;
            this.token = token;
            http = new HttpClient { Timeout = timeout ?? TimeSpan.FromSeconds(120) };
        }

        public string HttpUrl { get; private set; }

        /// <summary>Where to send datagrams for a server that reports <paramref name="udpHost"/>:
        /// the server gives its bind address, and a wildcard one (0.0.0.0, ::, *, empty) says
        /// where it listens, not where it can be reached; then the host of
        /// <paramref name="httpUrl"/> is used (127.0.0.1 if that is a wildcard too, or absent).</summary>
        public static string ReachableHost(string udpHost, string httpUrl)
        {
            if (!IsWildcard(udpHost)) return udpHost;
            Uri uri;
            if (!string.IsNullOrEmpty(httpUrl) && Uri.TryCreate(httpUrl, UriKind.Absolute, out uri)
                && !IsWildcard(uri.DnsSafeHost))
                return uri.DnsSafeHost;
            return "127.0.0.1";
        }

        private static bool IsWildcard(string host)
        {
            if (string.IsNullOrEmpty(host) || host == "*") return true;
            IPAddress a;
            if (!IPAddress.TryParse(host.Trim('[', ']'), out a)) return false;
            return a.Equals(IPAddress.Any) || a.Equals(IPAddress.IPv6Any);
        }
        public string Token { get { return token; } }

        private HttpRequestMessage Request(HttpMethod method, string path, object jsonBody)
        {
            var req = new HttpRequestMessage(method, apiBase + path);
            if (!string.IsNullOrEmpty(token)) req.Headers.Authorization = new AuthenticationHeaderValue("Bearer", token);
            if (jsonBody != null) req.Content = new StringContent(Json.Write(jsonBody), Encoding.UTF8, "application/json");
            return req;
        }

        private async Task<HttpResponseMessage> SendAsync(HttpMethod method, string path, object body, CancellationToken ct)
        {
            using (var req = Request(method, path, body))
            {
                HttpResponseMessage resp = await http.SendAsync(req, ct).ConfigureAwait(false);
                if (resp.IsSuccessStatusCode) return resp;
                string text = resp.Content != null ? await resp.Content.ReadAsStringAsync().ConfigureAwait(false) : "";
                int status = (int)resp.StatusCode;
                resp.Dispose();
                throw new BurrRestException(status, DetailOf(text), method + " " + path);
            }
        }

        /// <summary>The "detail" of an error body (FastAPI: a string, or a list of validation
        /// errors given here as JSON), else the body itself.</summary>
        public static string DetailOf(string body)
        {
            try
            {
                var o = Json.Parse(body) as Dictionary<string, object>;
                object d;
                if (o != null && o.TryGetValue("detail", out d)) return d as string ?? Json.Write(d);
            }
            catch (FormatException) { }
            return body;
        }

        private async Task<object> JsonAsync(HttpMethod method, string path, object body, CancellationToken ct)
        {
            using (var resp = await SendAsync(method, path, body, ct).ConfigureAwait(false))
            {
                if (resp.Content == null) return null;
                string text = await resp.Content.ReadAsStringAsync().ConfigureAwait(false);
                return text.Length == 0 ? null : Json.Parse(text);
            }
        }

        private static T Wait<T>(Task<T> task) { return task.GetAwaiter().GetResult(); }

        /// <summary>Creates a session on <paramref name="boneSource"/> (e.g. "phantom:workpiece")
        /// and waits until it is ready. <paramref name="parameters"/> e.g. {"frame": "unity"}.</summary>
        public async Task<SessionInfo> CreateSessionAsync(string boneSource, IDictionary<string, object> parameters = null,
                                                          CancellationToken ct = default(CancellationToken))
        {
            var body = new Dictionary<string, object>
            {
                { "bone", new Dictionary<string, object> { { "source", boneSource } } },
            };
            if (parameters != null) body["parameters"] = parameters;
            object o = await JsonAsync(HttpMethod.Post, "/sessions?wait=true", body, ct).ConfigureAwait(false);
            return SessionInfo.From(Json.AsObject(o, "the new session"), HttpUrl);
        }

        public SessionInfo CreateSession(string boneSource, IDictionary<string, object> parameters = null)
        {
            return Wait(CreateSessionAsync(boneSource, parameters));
        }

        /// <summary>Creates a session in an engine frame on a bone: the common case.</summary>
        public SessionInfo CreateSession(string boneSource, string frame)
        {
            return CreateSession(boneSource, new Dictionary<string, object> { { "frame", frame } });
        }

        public async Task<SessionInfo> GetSessionAsync(uint id, CancellationToken ct = default(CancellationToken))
        {
            object o = await JsonAsync(HttpMethod.Get, "/sessions/" + id, null, ct).ConfigureAwait(false);
            return SessionInfo.From(Json.AsObject(o, "the session"), HttpUrl);
        }

        public SessionInfo GetSession(uint id) { return Wait(GetSessionAsync(id)); }

        public async Task<Dictionary<string, object>> GetParametersAsync(uint id, CancellationToken ct = default(CancellationToken))
        {
            object o = await JsonAsync(HttpMethod.Get, "/sessions/" + id + "/parameters", null, ct).ConfigureAwait(false);
            return Json.AsObject(o, "the parameters");
        }

        public Dictionary<string, object> GetParameters(uint id) { return Wait(GetParametersAsync(id)); }

        /// <summary>Changes some parameters (e.g. {"us_n_mm2": 1610.2}); returns them all.</summary>
        public async Task<Dictionary<string, object>> PatchParametersAsync(uint id, IDictionary<string, object> changes,
                                                                          CancellationToken ct = default(CancellationToken))
        {
            object o = await JsonAsync(new HttpMethod("PATCH"), "/sessions/" + id + "/parameters", changes, ct).ConfigureAwait(false);
            return o as Dictionary<string, object>;
        }

        public Dictionary<string, object> PatchParameters(uint id, IDictionary<string, object> changes)
        {
            return Wait(PatchParametersAsync(id, changes));
        }

        public async Task<bool> RestartStreamAsync(uint id, CancellationToken ct = default(CancellationToken))
        {
            using (await SendAsync(HttpMethod.Post, "/sessions/" + id + "/restart-stream", null, ct).ConfigureAwait(false)) { }
            return true;
        }

        public void RestartStream(uint id) { Wait(RestartStreamAsync(id)); }

        public async Task<bool> DeleteSessionAsync(uint id, CancellationToken ct = default(CancellationToken))
        {
            using (await SendAsync(HttpMethod.Delete, "/sessions/" + id, null, ct).ConfigureAwait(false)) { }
            return true;
        }

        public void DeleteSession(uint id) { Wait(DeleteSessionAsync(id)); }

        /// <summary>One page of mesh chunks (MESH.md §2): the raw message bytes. since null:
        /// every chunk (FULL), for a client that holds none yet.</summary>
        public async Task<byte[]> GetMeshAsync(uint id, ulong? since, int chunkBricks = 2, string frame = "session",
                                               string winding = "ccw", uint cursor = 0, int maxBytes = 4 << 20,
                                               CancellationToken ct = default(CancellationToken))
        {
            string query = string.Format(CultureInfo.InvariantCulture,
                "/sessions/{0}/mesh?{1}chunk_bricks={2}&frame={3}&winding={4}&cursor={5}&max_bytes={6}",
                id, SinceParameter(since), chunkBricks, Uri.EscapeDataString(frame), Uri.EscapeDataString(winding), cursor, maxBytes);
            using (var resp = await SendAsync(HttpMethod.Get, query, null, ct).ConfigureAwait(false))
                return await resp.Content.ReadAsByteArrayAsync().ConfigureAwait(false);
        }

        /// <summary>The WebSocket URL of the mesh push channel. tokenInQuery: add ?token= for
        /// clients that cannot set an Authorization header (it may then end up in logs).</summary>
        public Uri MeshWebSocketUri(uint id, ulong? since, int chunkBricks, string frame, string winding, int intervalMs,
                                    bool tokenInQuery = false)
        {
            string root = HttpUrl;
            if (root.StartsWith("https://", StringComparison.OrdinalIgnoreCase)) root = "wss://" + root.Substring(8);
            else if (root.StartsWith("http://", StringComparison.OrdinalIgnoreCase)) root = "ws://" + root.Substring(7);
            string url = string.Format(CultureInfo.InvariantCulture,
                "{0}/v1/sessions/{1}/mesh/ws?{2}chunk_bricks={3}&frame={4}&winding={5}&interval_ms={6}",
                root, id, SinceParameter(since), chunkBricks, Uri.EscapeDataString(frame), Uri.EscapeDataString(winding), intervalMs);
            if (tokenInQuery && !string.IsNullOrEmpty(token)) url += "&token=" + Uri.EscapeDataString(token);
            return new Uri(url);
        }

        // The server sends every chunk when since is omitted; it reads since=0 as "changed
        // after version 0", which on an uncarved bone is nothing.
        private static string SinceParameter(ulong? since)
        {
            return since.HasValue ? "since=" + since.Value.ToString(CultureInfo.InvariantCulture) + "&" : "";
        }

        public void Dispose() { http.Dispose(); }
    }
}
