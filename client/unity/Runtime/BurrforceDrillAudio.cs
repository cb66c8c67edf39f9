// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using UnityEngine;

namespace Burrforce.Unity
{
    /// <summary>The drill's sound from the REPLY's vibration parameters (SPEC.md §7.4): a tone
    /// at vibration_frequency_hz (the spindle's rotation rate × harmonic) whose loudness
    /// follows vibration_amplitude. Phase-continuous when the frequency changes, and it fades
    /// to silence when the stream stops or goes stale. Put it on a GameObject with an
    /// AudioSource (no clip needed) that is playing.</summary>
    [AddComponentMenu("Burrforce/Burrforce Drill Audio")]
    [RequireComponent(typeof(AudioSource))]
    public sealed class BurrforceDrillAudio : MonoBehaviour
    {
        public BurrforceSession session;
        [Tooltip("Output level per newton of vibration amplitude")]
        public float gainPerNewton = 0.4f;
        [Range(0f, 1f)] public float maxLevel = 0.8f;
        [Tooltip("Time constant of loudness and pitch changes, s (also the fade-out)")]
        public float smoothingSeconds = 0.03f;
        [Tooltip("Second harmonic's share, for a harsher drill timbre")]
        [Range(0f, 1f)] public float harmonic2 = 0.25f;

        // Written on the main thread, read on the audio thread: single floats are atomic.
        private volatile float targetLevel;
        private volatile float targetFrequencyHz;
        private float level, frequencyHz;
        private double phase;
        private int sampleRate;

        private void Awake()
        {
            // Unity's API is off-limits on the audio thread: read it here.
            sampleRate = AudioSettings.outputSampleRate;
        }

        private void OnEnable()
        {
            AudioSource source = GetComponent<AudioSource>();
            if (!source.isPlaying) source.Play();
        }

        private void Update()
        {
            if (session == null || !session.Streaming)
            {
                targetLevel = 0f;
                return;
            }
            ForceState s = session.State;
            // State is zero when stale or after an error REPLY: the tone fades out by itself.
            targetLevel = Mathf.Min(maxLevel, (float)s.VibrationAmplitudeN * gainPerNewton);
            if (s.VibrationFrequencyHz > 0.0) targetFrequencyHz = (float)s.VibrationFrequencyHz;
        }

        private void OnDisable() { targetLevel = 0f; }

        private void OnAudioFilterRead(float[] data, int channels)
        {
            if (sampleRate <= 0) return;
            float goalLevel = targetLevel;
            float goalFrequency = targetFrequencyHz;
            float k = 1f - Mathf.Exp(-1f / (Mathf.Max(smoothingSeconds, 1e-4f) * sampleRate));
            double twoPi = 2.0 * System.Math.PI;
            for (int i = 0; i < data.Length; i += channels)
            {
                level += (goalLevel - level) * k;
                frequencyHz += (goalFrequency - frequencyHz) * k;
                phase += twoPi * frequencyHz / sampleRate;
                if (phase > twoPi) phase -= twoPi;
                float sample = level * (float)(System.Math.Sin(phase) + harmonic2 * System.Math.Sin(2.0 * phase)) / (1f + harmonic2);
                for (int c = 0; c < channels; c++) data[i + c] += sample;
            }
        }
    }
}
