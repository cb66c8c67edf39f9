"""A vibration actuator on a sound card: PortAudio (sounddevice) line out → amplifier → voice
coil (Haptuator class).

The waveform is synthesized in PortAudio's callback, block by block; :meth:`update` only swaps
the target (one tuple, atomic under the GIL), so the device loop never waits on audio. The
callback is also where the watchdog lives: when the last update is about to be older than
``watchdog_ms`` it ramps to silence within that block and stays silent, so the stream is silent
by ``watchdog_ms`` after the last update, plus the device's output latency.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from ..base import DeviceError, DeviceNotFound, VendorLibraryMissing
from .base import Actuator
from .synth import Oscillator, Perceptual

DEFAULT_RATE_HZ = 48_000
DEFAULT_BLOCKSIZE = 64


def import_sounddevice() -> Any:
    """The ``sounddevice`` module; VendorLibraryMissing saying what to install when it or the
    PortAudio library is missing."""
    try:
        import sounddevice
    except ImportError as exc:
        raise VendorLibraryMissing(
            "the audio actuator needs the 'sounddevice' package: pip install sounddevice"
        ) from exc
    except OSError as exc:  # sounddevice raises OSError when libportaudio is absent
        raise VendorLibraryMissing(
            f"PortAudio library not found ({exc}); on Debian/Ubuntu: "
            "apt-get install libportaudio2"
        ) from exc
    return sounddevice


def output_devices() -> list[str]:
    """``"index: name (host API)"`` of every output device PortAudio sees."""
    sd = import_sounddevice()
    apis = sd.query_hostapis()
    return [f"{d['index']}: {d['name']} ({apis[d['hostapi']]['name']})"
            for d in sd.query_devices() if d["max_output_channels"] > 0]


class AudioActuator(Actuator):
    """Vibration on a sound card output channel.

    Args:
        device: PortAudio output device: index, or a (sub)string of its name as
            ``sounddevice`` matches it (e.g. ``"burrfile"``, ``"USB Audio"``); None: default.
        rate_hz: sample rate, Hz (48 kHz: ≥ 40 samples per period up to 1.2 kHz).
        blocksize: frames per callback (64–128 keep the added latency at 1.3–2.7 ms).
        channel: the output channel carrying the waveform (0-based); other channels of the
            stream are written silent.
        channels: channels to open (default ``channel + 1``).
        full_scale_N, watchdog_ms: see :class:`~.base.Actuator`.
        perceptual: the synthesizer's perceptual mode.
        latency: PortAudio's suggested latency (``"low"``, ``"high"`` or seconds).
    """

    def __init__(self, device: int | str | None = None, *, rate_hz: int = DEFAULT_RATE_HZ,
                 blocksize: int = DEFAULT_BLOCKSIZE, channel: int = 0,
                 channels: int | None = None, full_scale_N: float = 1.0,
                 watchdog_ms: float = 50.0, perceptual: Perceptual | str | None = None,
                 latency: str | float = "low") -> None:
        super().__init__(full_scale_N, watchdog_ms)
        if not 8 <= blocksize <= 4096:
            raise ValueError(f"blocksize must be 8..4096 frames, got {blocksize}")
        if channel < 0:
            raise ValueError(f"channel must be ≥ 0, got {channel}")
        channels = channel + 1 if channels is None else channels
        if channels <= channel:
            raise ValueError(f"channel {channel} needs ≥ {channel + 1} channels, got {channels}")
        self.device = device
        self.rate_hz = int(rate_hz)
        self.blocksize = int(blocksize)
        self.channel = int(channel)
        self.channels = int(channels)
        self.latency = latency
        self.perceptual = Perceptual.of(perceptual)
        self._block_ns = self.blocksize * 1_000_000_000 // self.rate_hz
        self._osc = Oscillator(self.rate_hz, self.perceptual)
        self._mono = np.zeros(self.blocksize, dtype=np.float32)
        self._stream: Any = None
        self._last_arrival_ns = 0
        self._silent_event = threading.Event()
        #: the callback's last exception (it must not raise into PortAudio)
        self.callback_error: BaseException | None = None
        self.output_latency_s = 0.0

    # -- the audio thread ---------------------------------------------------------------------
    def _callback(self, outdata: np.ndarray, frames: int, time_info: Any, status: Any) -> None:
        try:
            if status.output_underflow:
                self.stats.underruns += 1
            now = time.monotonic_ns()
            stale = now + 2 * self._block_ns - self._last_arrival_ns > self.watchdog_ns
            mono = self._mono if frames == self._mono.shape[0] else np.zeros(frames, np.float32)
            if self._osc.render(mono, stale):
                self.stats.watchdog_silences += 1
                self.stats.watchdog_silent_ns = now + frames * 1_000_000_000 // self.rate_hz
            if self.channels > 1:
                outdata.fill(0.0)
            outdata[:, self.channel] = mono
            self.stats.blocks += 1
            if self._osc.silent:
                self._silent_event.set()
        except BaseException as exc:  # never raise into PortAudio: output silence instead
            self.callback_error = exc
            outdata.fill(0.0)

    # -- the caller's thread ------------------------------------------------------------------
    def _set(self, level: float, frequency_hz: float, t_ns: int, arrival_ns: int) -> None:
        # Arrival first: a callback in between then sees a fresh stream with the old target,
        # never the new target with a stale arrival (which would latch silence).
        self._last_arrival_ns = arrival_ns
        self._osc.set_target(level, frequency_hz)
        if level > 0.0:
            self._silent_event.clear()

    def _open(self) -> None:
        sd = import_sounddevice()
        try:
            info = sd.query_devices(self.device, "output")
        except ValueError as exc:
            raise DeviceNotFound(
                f"audio output device {self.device!r} not found ({exc}); outputs: "
                f"{'; '.join(output_devices()) or 'none'}") from exc
        if info["max_output_channels"] < self.channels:
            raise DeviceError(f"audio device {info['name']!r} has "
                              f"{info['max_output_channels']} output channels, "
                              f"{self.channels} needed")
        self._osc = Oscillator(self.rate_hz, self.perceptual)
        # Load the compiled kernel here, not in the first callback (that would underrun).
        self._osc.render(self._mono, stale=True)
        self._last_arrival_ns = 0
        self._silent_event.set()
        self.callback_error = None
        try:
            self._stream = sd.OutputStream(
                samplerate=self.rate_hz, blocksize=self.blocksize, device=info["index"],
                channels=self.channels, dtype="float32", latency=self.latency,
                callback=self._callback)
            self._stream.start()
        except sd.PortAudioError as exc:  # _close closes a stream that was made, not started
            raise DeviceError(f"cannot start audio output on {info['name']!r} at "
                              f"{self.rate_hz} Hz, {self.channels} ch: {exc}") from exc
        self.output_latency_s = float(self._stream.latency)

    def _close(self) -> None:
        stream, self._stream = self._stream, None
        if stream is None:
            return
        try:
            # Let the ramp to silence reach the stream before stopping it (a stopped stream
            # would otherwise end on whatever the last block held).
            self._silent_event.wait(timeout=max(0.1, 4 * self._block_ns / 1e9))
            stream.stop()
        finally:
            stream.close()

    @property
    def callbacks(self) -> int:
        """Callbacks run since :meth:`open`."""
        return self.stats.blocks

    @property
    def underruns(self) -> int:
        """Output underflows PortAudio reported since :meth:`open`."""
        return self.stats.underruns

