// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System;
using System.Collections.Concurrent;
using System.Collections.Generic;
using System.Threading.Tasks;
using UnityEngine;

namespace Burrforce.Unity
{
    /// <summary>One burrforce session: streams the tool's pose at a fixed rate on a background
    /// thread and exposes what the hand should feel. Properties and events are for the main
    /// thread; events are raised in Update.</summary>
    [AddComponentMenu("Burrforce/Burrforce Session")]
    [DefaultExecutionOrder(-100)]
    public sealed class BurrforceSession : MonoBehaviour
    {
        public enum ConnectMode
        {
            /// <summary>The file `burrforce serve` writes (empty path: its default place).</summary>
            ConnectionFile,
            /// <summary>Host, UDP port, session id and key as `burrforce serve` prints them.</summary>
            Manual,
            /// <summary>A new `unity`-frame session created over REST (URL + token), deleted on disable.</summary>
            CreateOverRest,
        }

        [Header("Connection")]
        public ConnectMode mode = ConnectMode.ConnectionFile;
        [Tooltip("Empty: $BURRFORCE_CONNECTION, $XDG_RUNTIME_DIR/burrforce/connection.json or ~/.cache/burrforce/connection.json")]
        public string connectionFile = "";
        public string host = "127.0.0.1";
        public int udpPort = 47810;
        public long sessionId = 1;
        [Tooltip("Hex key; empty for a session without one (loopback development only)")]
        public string keyHex = "";
        [Tooltip("REST root without /v1, e.g. http://127.0.0.1:8080 (needed for CreateOverRest and for the bone mesh)")]
        public string restUrl = "";
        public string token = "";
        [Tooltip("CreateOverRest: the bone to load, e.g. phantom:workpiece")]
        public string boneSource = "phantom:workpiece";

        [Header("Tool")]
        [Tooltip("The burr centre; its rotation turns the local tool axis (+Y, toward the handle)")]
        public Transform tool;
        public float rpm = 60000f;
        public bool spindleOn = true;
        [Tooltip("Evaluate forces without removing bone")]
        public bool noCarve;

        [Header("Stream")]
        [Range(100f, 2000f)] public float rateHz = 1000f;
        public PoseSmoothing smoothing = PoseSmoothing.Interpolate;

        /// <summary>Newest render state (zero force when stale or after an error REPLY).</summary>
        public ForceState State { get; private set; }
        /// <summary>Force of the bone on the tool, N, Unity axes.</summary>
        public Vector3 Force { get { return State.Force.ToUnity(); } }
        /// <summary>N·m, Unity axes.</summary>
        public Vector3 Torque { get { return State.Torque.ToUnity(); } }
        public float VibrationAmplitude { get { return (float)State.VibrationAmplitudeN; } }
        public float VibrationFrequency { get { return (float)State.VibrationFrequencyHz; } }
        public Vector3 VibrationAxis { get { return State.VibrationAxis.ToUnity(); } }
        public uint Status { get { return State.Status; } }
        public bool Cutting { get { return State.Cutting; } }
        public ulong BoneVersion { get { return State.BoneVersion; } }
        public bool Streaming { get { return streamer != null && streamer.Running; } }
        public StreamerCounters Counters { get { return streamer != null ? streamer.Counters : new StreamerCounters(); } }

        /// <summary>The REST client (null without a REST URL) and the session's id once connected.</summary>
        public BurrRest Rest { get; private set; }
        public uint SessionId { get; private set; }
        /// <summary>Set once the streamer runs; the bone mesh waits for it.</summary>
        public bool Ready { get; private set; }

        /// <summary>Each Update with the newest state.</summary>
        public event Action<ForceState> ForceUpdated;
        public event Action<uint> StatusChanged;
        public event Action<ulong> BoneVersionChanged;
        /// <summary>A NOTICE (diagnostic: wrong key, unknown session...), with its error code;
        /// also NEW_STREAM and WRONG_STREAM when the streamer took or lost a stream.</summary>
        public event Action<int> NoticeReceived;

        private Streamer streamer;
        private OwnedSession owned;
        private bool failureLogged;
        private uint lastStatus;
        private ulong lastBoneVersion;
        private readonly ConcurrentQueue<int> notices = new ConcurrentQueue<int>();

        private void OnEnable()
        {
            Ready = false;
            ConnectAsync();
        }

        private async void ConnectAsync()
        {
            try
            {
                string h = host, key = keyHex;
                int port = udpPort;
                uint id = checked((uint)sessionId);
                if (mode == ConnectMode.ConnectionFile)
                {
                    ConnectionInfo c = ConnectionInfo.Read(string.IsNullOrEmpty(connectionFile) ? null : connectionFile);
                    h = c.Host; port = c.UdpPort; id = c.Session; key = c.KeyHex;
                    if (!string.IsNullOrEmpty(c.HttpUrl)) Rest = new BurrRest(c.HttpUrl, c.Token);
                    if (c.Frame != "unity")
                        Debug.LogWarning("burrforce: session " + id + " is in frame '" + c.Frame + "', not 'unity': start the server with --frame unity");
                }
                else if (!string.IsNullOrEmpty(restUrl))
                {
                    Rest = new BurrRest(restUrl, token);
                }
                if (mode == ConnectMode.CreateOverRest)
                {
                    if (Rest == null) throw new InvalidOperationException("CreateOverRest needs a REST URL and token");
                    // Its own client: disabling during the bone's load disposes Rest, and the
                    // session must still be created to be deleted (OnDisable releases it).
                    var mine = OwnedSession.Create(Rest.HttpUrl, Rest.Token, boneSource,
                                                   new Dictionary<string, object> { { "frame", "unity" } });
                    owned = mine;
                    SessionInfo s = await mine.Created;
                    if (owned != mine || !isActiveAndEnabled) return; // released by OnDisable
                    h = s.UdpHost; port = s.UdpPort; id = s.Id; key = s.KeyHex;
                }
                if (!isActiveAndEnabled) return; // disabled while connecting
                SessionId = id;
                var options = new StreamerOptions { RateHz = rateHz, Smoothing = smoothing };
                streamer = new Streamer(h, port, id, key, options);
                streamer.NoticeReceived += n => notices.Enqueue(n.Error);
                Publish();
                streamer.Start();
                Ready = true;
                Debug.Log("burrforce: streaming to " + h + ":" + port + ", session " + id);
            }
            catch (Exception e)
            {
                Debug.LogError("burrforce: cannot connect: " + e.Message);
            }
        }

        private void Update()
        {
            if (streamer == null) return;
            if (streamer.Failure != null && !failureLogged)
            {
                failureLogged = true;
                Debug.LogError("burrforce: the streamer stopped: " + streamer.Failure);
            }
            ForceState s = streamer.State;
            State = s;
            int code;
            while (notices.TryDequeue(out code))
            {
                // The stream handshake is routine (start, REST restart-stream, server restart):
                // the streamer follows it by itself.
                if (code == Protocol.ErrorBadVersion)
                    Debug.LogWarning("burrforce: the server speaks another wire protocol version: update the package or the server");
                else if (code != Protocol.ErrorNewStream && code != Protocol.ErrorWrongStream)
                    Debug.LogWarning("burrforce: the server refused a POSE: " + Protocol.ErrorName(code));
                var nh = NoticeReceived;
                if (nh != null) nh(code);
            }
            var fh = ForceUpdated;
            if (fh != null) fh(s);
            if (s.Status != lastStatus)
            {
                lastStatus = s.Status;
                var sh = StatusChanged;
                if (sh != null) sh(s.Status);
            }
            if (s.BoneVersion != lastBoneVersion)
            {
                lastBoneVersion = s.BoneVersion;
                var bh = BoneVersionChanged;
                if (bh != null) bh(s.BoneVersion);
            }
        }

        // After every Update has moved the tool (animation, XR input, scripts).
        private void LateUpdate() { Publish(); }

        private void Publish()
        {
            if (streamer == null || tool == null) return;
            var p = new ToolPose(tool.position.ToBurr(), tool.rotation.ToBurr(), rpm, spindleOn);
            if (noCarve) p.Flags |= Protocol.FlagNoCarve;
            streamer.Publish(p);
        }

        /// <summary>Gives up the stream and takes a new one from the server, whose first tick
        /// starts velocity afresh. Never needed to follow the server: after a REST
        /// restart-stream or a server restart the streamer takes a new stream by itself.</summary>
        public void RestartStream()
        {
            if (streamer != null) streamer.RestartStream();
        }

        private void OnDisable()
        {
            Ready = false;
            if (streamer != null)
            {
                streamer.Dispose();
                streamer = null;
            }
            State = default(ForceState);
            if (owned != null)
            {
                // Never blocks the main thread: deletes once the session exists.
                owned.Release().ContinueWith(t => Debug.LogWarning("burrforce: cannot delete the session: " + t.Exception.GetBaseException().Message),
                                             TaskContinuationOptions.OnlyOnFaulted);
                owned = null;
            }
            if (Rest != null) Rest.Dispose();
            Rest = null;
        }
    }
}
