"""An actuator that writes the synthesized vibration to a WAV file (tests, offline review).

Its timeline is the updates' ``t_ns``, not the wall clock, so a run replays to the same
samples: sample k of the file is at ``t_first + k / rate_hz``, where ``t_first`` is the first
update's ``t_ns``. Rendering mimics an audio callback on a fixed block grid: a block starting
at time s uses the parameters of the last update at or before s (the block granularity is the
writer's latency, as it is a sound card's); the watchdog ramps to silence in the last block that
ends within ``watchdog_ms`` of the last update, so the file is silent from then on.
"""

from __future__ import annotations

import os
import struct
import wave
from pathlib import Path

import numpy as np

from .base import Actuator
from .synth import Oscillator, Perceptual

SAMPLE_FORMATS = ("int16", "float32")


class _FloatWavWriter:
    """Mono IEEE-float WAV (format tag 3), written as it goes; sizes patched on close (the
    stdlib ``wave`` writes PCM only)."""

    def __init__(self, path: Path, rate_hz: int) -> None:
        self._file = open(path, "wb")  # closed in close()
        self._rate = rate_hz
        self._frames = 0
        self._file.write(self._header())

    def _header(self) -> bytes:
        data_bytes = 4 * self._frames
        fmt = struct.pack("<HHIIHHH", 3, 1, self._rate, 4 * self._rate, 4, 32, 0)
        return (b"RIFF" + struct.pack("<I", 4 + (8 + len(fmt)) + 12 + 8 + data_bytes) + b"WAVE"
                + b"fmt " + struct.pack("<I", len(fmt)) + fmt
                + b"fact" + struct.pack("<II", 4, self._frames)
                + b"data" + struct.pack("<I", data_bytes))

    def write(self, samples: np.ndarray) -> None:
        self._file.write(samples.astype("<f4").tobytes())
        self._frames += samples.shape[0]

    def close(self) -> None:
        self._file.seek(0)
        self._file.write(self._header())
        self._file.close()


class _PcmWavWriter:
    """Mono 16-bit PCM WAV through the stdlib ``wave``."""

    def __init__(self, path: Path, rate_hz: int) -> None:
        self._wave = wave.open(os.fspath(path), "wb")  # closed in close()
        self._wave.setnchannels(1)
        self._wave.setsampwidth(2)
        self._wave.setframerate(rate_hz)

    def write(self, samples: np.ndarray) -> None:
        pcm = np.clip(np.rint(samples * 32767.0), -32767, 32767).astype("<i2")
        self._wave.writeframes(pcm.tobytes())

    def close(self) -> None:
        self._wave.close()


class WavActuator(Actuator):
    """Writes the vibration waveform to ``path`` (mono WAV).

    Args:
        path: output file (overwritten).
        rate_hz: sample rate, Hz.
        sample_format: ``"int16"`` (PCM, full scale 32767) or ``"float32"`` (IEEE float,
            full scale 1.0).
        block_frames: the render block, samples (ramps span one block; 48 = 1 ms at 48 kHz).
        full_scale_N, watchdog_ms: see :class:`~.base.Actuator`.
        perceptual: the synthesizer's perceptual mode.
    """

    def __init__(self, path: str | os.PathLike, rate_hz: int = 48_000,
                 sample_format: str = "int16", block_frames: int = 48,
                 full_scale_N: float = 1.0, watchdog_ms: float = 50.0,
                 perceptual: Perceptual | str | None = None) -> None:
        super().__init__(full_scale_N, watchdog_ms)
        if sample_format not in SAMPLE_FORMATS:
            raise ValueError(f"sample_format must be one of {SAMPLE_FORMATS}, "
                             f"got {sample_format!r}")
        if int(rate_hz) != rate_hz or not 1000 <= rate_hz <= 384_000:
            raise ValueError(f"rate_hz must be an integer in 1000..384000, got {rate_hz}")
        if not 1 <= block_frames <= 8192:
            raise ValueError(f"block_frames must be 1..8192, got {block_frames}")
        self.path = Path(path)
        self.rate_hz = int(rate_hz)
        self.sample_format = sample_format
        self.block_frames = int(block_frames)
        self.perceptual = Perceptual.of(perceptual)
        self._writer: _FloatWavWriter | _PcmWavWriter | None = None
        self._osc: Oscillator | None = None
        self._block = np.zeros(self.block_frames, dtype=np.float32)
        self._t_first: int | None = None
        self._last_t = 0
        self._blocks_written = 0

    def _block_start_ns(self, index: int) -> int:
        assert self._t_first is not None
        return self._t_first + (index * self.block_frames * 1_000_000_000) // self.rate_hz

    def _open(self) -> None:
        writer = _FloatWavWriter if self.sample_format == "float32" else _PcmWavWriter
        self._writer = writer(self.path, self.rate_hz)
        self._osc = Oscillator(self.rate_hz, self.perceptual)
        self._t_first = None
        self._blocks_written = 0

    def _render_until(self, t_ns: int) -> None:
        """Write every block that starts before ``t_ns`` with the current target."""
        assert self._writer is not None and self._osc is not None
        if self._t_first is None:
            return
        block_ns = self.block_frames * 1_000_000_000 / self.rate_hz
        while self._block_start_ns(self._blocks_written) < t_ns:
            start = self._block_start_ns(self._blocks_written)
            # Ramp in the last block that still ends within the watchdog: silent by then.
            stale = start + 2 * block_ns - self._last_t > self.watchdog_ns
            if self._osc.render(self._block, stale):
                self.stats.watchdog_silences += 1
                self.stats.watchdog_silent_ns = self._block_start_ns(self._blocks_written + 1)
            self._writer.write(self._block)
            self._blocks_written += 1
            self.stats.blocks += 1

    def advance(self, t_ns: int) -> None:
        """Extend the file to ``t_ns`` without new parameters (the watchdog applies)."""
        if not self.is_open:
            raise RuntimeError("actuator is not open")
        if self._t_first is not None and t_ns < self._last_t:
            raise ValueError(f"t_ns went backwards: {t_ns} < {self._last_t}")
        self._render_until(int(t_ns))

    def _set(self, level: float, frequency_hz: float, t_ns: int, arrival_ns: int) -> None:
        assert self._osc is not None
        if self._t_first is None:
            self._t_first = t_ns
            self._last_t = t_ns
        if t_ns < self._last_t:
            raise ValueError(f"t_ns went backwards: {t_ns} < {self._last_t}")
        self._render_until(t_ns)
        self._last_t = t_ns
        self._osc.set_target(level, frequency_hz)

    def _close(self) -> None:
        if self._writer is None:  # _open failed before the file was open
            return
        try:
            # Ramp down whatever is still sounding, so the file never ends on a tone.
            if self._osc is not None and self._t_first is not None and not self._osc.silent:
                self._osc.render(self._block, stale=True)
                self._writer.write(self._block)
                self._blocks_written += 1
        finally:
            self._writer.close()
            self._writer = None
            self._osc = None


def read_wav(path: str | os.PathLike) -> tuple[int, np.ndarray]:
    """(rate Hz, samples as float32 in [-1, 1]) of a mono WAV written by :class:`WavActuator`
    (PCM 16-bit or IEEE float 32-bit)."""
    from scipy.io import wavfile

    rate, data = wavfile.read(os.fspath(path))
    if data.dtype == np.int16:
        return rate, (data.astype(np.float32) / 32767.0)
    if data.dtype == np.float32:
        return rate, data
    raise ValueError(f"{path}: unexpected sample type {data.dtype}")
