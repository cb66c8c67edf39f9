// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;
using System.IO;

namespace Burrforce
{
    /// <summary>The connection file `burrforce serve` writes for local tools (SPEC.md §6.4):
    /// UDP endpoint, session, key, frame, REST URL and token.</summary>
    public sealed class ConnectionInfo
    {
        public string Host;
        public int UdpPort;
        public uint Session;
        public string KeyHex;
        public string Frame;
        public string HttpUrl;
        public string Token;

        /// <summary>Reads the file at path, or (null) where the server puts it by default:
        /// $BURRFORCE_CONNECTION, $XDG_RUNTIME_DIR/burrforce/connection.json, then
        /// ~/.cache/burrforce/connection.json.</summary>
        public static ConnectionInfo Read(string path = null)
        {
            string p = path ?? DefaultPath();
            var o = Json.AsObject(Json.Parse(File.ReadAllText(p)), p);
            var c = new ConnectionInfo
            {
                Host = Json.GetString(o, "host"),
                UdpPort = (int)Json.GetLong(o, "udp_port"),
                Session = checked((uint)Json.GetLong(o, "session")),
                KeyHex = Json.GetString(o, "key_hex"),
            };
            object v;
            if (o.TryGetValue("frame", out v)) c.Frame = v as string;
            if (o.TryGetValue("http_url", out v)) c.HttpUrl = v as string;
            if (o.TryGetValue("token", out v)) c.Token = v as string;
            c.Host = BurrRest.ReachableHost(c.Host, c.HttpUrl);
            return c;
        }

        public static string DefaultPath()
        {
            string env = Environment.GetEnvironmentVariable("BURRFORCE_CONNECTION");
            if (!string.IsNullOrEmpty(env)) return env;
            string xdg = Environment.GetEnvironmentVariable("XDG_RUNTIME_DIR");
            if (!string.IsNullOrEmpty(xdg)) return Path.Combine(xdg, "burrforce", "connection.json");
            string home = Environment.GetFolderPath(Environment.SpecialFolder.UserProfile);
            return Path.Combine(home, ".cache", "burrforce", "connection.json");
        }
    }
}
