// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using UnityEngine;

namespace Burrforce.Unity
{
    /// <summary>Unity's types ↔ the core's. A session in the `unity` frame takes Unity's world
    /// coordinates as they are (metres, left-handed, y up) and its quaternion components
    /// unchanged: no axis swapping here, the server converts at its edge.</summary>
    public static class UnityConversions
    {
        public static Vec3 ToBurr(this Vector3 v) { return new Vec3(v.x, v.y, v.z); }

        public static Quat ToBurr(this Quaternion q) { return new Quat(q.x, q.y, q.z, q.w); }

        public static Vector3 ToUnity(this Vec3 v) { return new Vector3((float)v.X, (float)v.Y, (float)v.Z); }
    }
}
