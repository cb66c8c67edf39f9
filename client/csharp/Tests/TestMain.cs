// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Generic;

namespace Burrforce.Tests
{
    /// <summary>The C# SDK's test program, driven by tests/sdk/test_csharp.py. Each command
    /// prints its result as one JSON line (the last line of stdout).</summary>
    public static class TestMain
    {
        public static int Main(string[] args)
        {
            if (args.Length == 0)
            {
                Console.Error.WriteLine("usage: BurrforceTests.exe vectors|selftest|groove|errors|mesh|publish|stall|lifecycle|handshake [--name value ...]");
                return 2;
            }
            var opts = Options(args);
            Dictionary<string, object> result;
            switch (args[0])
            {
                case "vectors": result = VectorsTest.Run(opts["vectors"]); break;
                case "selftest": result = SelfTest.Run(); break;
                case "groove": result = GrooveTest.Run(opts); break;
                case "errors": result = ErrorsTest.Run(opts); break;
                case "mesh": result = MeshTest.Run(opts); break;
                case "publish": result = PublishTest.Run(opts); break;
                case "stall": result = StallTest.Run(); break;
                case "lifecycle": result = LifecycleTest.Run(opts); break;
                case "handshake": result = HandshakeTest.Run(opts); break;
                default:
                    Console.Error.WriteLine("unknown command " + args[0]);
                    return 2;
            }
            Console.WriteLine(Json.Write(result));
            return 0;
        }

        private static Dictionary<string, string> Options(string[] args)
        {
            var d = new Dictionary<string, string>();
            for (int i = 1; i + 1 < args.Length; i += 2)
            {
                if (!args[i].StartsWith("--", StringComparison.Ordinal)) throw new ArgumentException("expected --name value, got " + args[i]);
                d[args[i].Substring(2)] = args[i + 1];
            }
            return d;
        }
    }

    /// <summary>Collects failed checks instead of stopping at the first.</summary>
    public sealed class Checks
    {
        public readonly List<object> Failures = new List<object>();
        public int Passed;

        public void That(bool ok, string what)
        {
            if (ok) Passed++;
            else Failures.Add(what);
        }
    }
}
