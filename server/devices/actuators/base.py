"""What a vibration actuator is: it takes the burr's vibration parameters and renders them.

The server sends ``vibration_amplitude`` (N) and ``vibration_frequency_hz`` per REPLY
(proto/SPEC.md §7.4) at up to the servo rate; an actuator synthesizes the waveform itself
(``synth``) and is responsible for its own silence: when the parameter stream stops it goes
quiet within :attr:`Actuator.watchdog_ns` (50 ms by default) of the last update, enforced
where the waveform is produced (the audio callback, the board's TTL, the wav writer's
timeline), not by the caller.
"""

from __future__ import annotations

import math
import time
from abc import abstractmethod
from dataclasses import dataclass

from ..base import SafeOutput

WATCHDOG_DEFAULT_MS = 50.0


@dataclass(frozen=True)
class AmplitudeMap:
    """Maps the server's vibration amplitude (N) to an output level (0..1 of full scale).

    Attributes:
        full_scale_N: the amplitude, N, that drives the actuator at full scale (level 1).
            Calibrate per rig: the force the voice coil delivers at full drive, or the
            amplitude at which the cue should saturate. Default 1 N (twice the model's
            illustrative free-spinning 0.5 N).
    """

    full_scale_N: float = 1.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.full_scale_N) or self.full_scale_N <= 0.0:
            raise ValueError(f"full_scale_N must be finite and > 0, got {self.full_scale_N}")

    def level(self, amplitude_N: float) -> float:
        """Output level in [0, 1]: ``amplitude_N / full_scale_N`` clamped (negative → 0)."""
        return min(max(amplitude_N / self.full_scale_N, 0.0), 1.0)


def check_parameters(amplitude_N: float, frequency_hz: float) -> None:
    """ValueError unless both are finite and ≥ 0."""
    if not math.isfinite(amplitude_N) or amplitude_N < 0.0:
        raise ValueError(f"vibration amplitude must be finite and ≥ 0 N, got {amplitude_N}")
    if not math.isfinite(frequency_hz) or frequency_hz < 0.0:
        raise ValueError(f"vibration frequency must be finite and ≥ 0 Hz, got {frequency_hz}")


@dataclass
class ActuatorStats:
    """Counters an actuator keeps (all since :meth:`Actuator.open`).

    Attributes:
        updates: update() calls accepted.
        blocks: waveform blocks produced (audio callbacks, wav blocks) or frames sent (board).
        underruns: output underruns (audio: PortAudio output underflow; board: its DAC's).
        watchdog_silences: times the watchdog silenced a stale stream.
        watchdog_silent_ns: when the watchdog's ramp to silence last ended: the stream time
            (audio: ``time.monotonic_ns()`` when that block was produced, wav: its timeline).
        last_update_ns: ``time.monotonic_ns()`` of the last update's arrival (0: none yet).
        last_t_ns: the ``t_ns`` the last update carried.
    """

    updates: int = 0
    blocks: int = 0
    underruns: int = 0
    watchdog_silences: int = 0
    watchdog_silent_ns: int = 0
    last_update_ns: int = 0
    last_t_ns: int = 0


class Actuator(SafeOutput):
    """A vibration actuator. Use as a context manager: ``close`` always leaves it silent.

    Subclasses implement :meth:`_open`, :meth:`_set` (store the new target: cheap, never
    blocking), :meth:`_close` (may block briefly to let the ramp to silence play out), and
    enforce the watchdog where they produce the waveform.
    """

    def __init__(self, full_scale_N: float = 1.0,
                 watchdog_ms: float = WATCHDOG_DEFAULT_MS) -> None:
        if not math.isfinite(watchdog_ms) or not 0.0 < watchdog_ms <= 1000.0:
            raise ValueError(f"watchdog_ms must be in (0, 1000], got {watchdog_ms}")
        self.amplitude_map = AmplitudeMap(full_scale_N)
        self.watchdog_ns = int(watchdog_ms * 1e6)
        self.stats = ActuatorStats()
        super().__init__()

    def open(self) -> None:
        """Start the output, silent (raises the DeviceError family with what to do)."""
        if not self.is_open:
            self.stats = ActuatorStats()
        super().open()

    def update(self, amplitude_N: float, frequency_hz: float, t_ns: int | None = None) -> None:
        """Render ``amplitude_N`` (N) at ``frequency_hz`` (Hz) from now on.

        Called by the device loop at up to servo rate: cheap and never blocks. ``t_ns`` is
        when the parameters hold, on the loop's clock (``time.monotonic_ns()`` when None);
        real-time actuators time their watchdog from the update's arrival, the wav writer uses
        ``t_ns`` as its timeline. Bad values (non-finite, negative) silence the actuator and
        raise ValueError; so does an update on a closed actuator (RuntimeError).
        """
        if not self.is_open:
            raise RuntimeError("actuator is not open")
        try:
            check_parameters(amplitude_N, frequency_hz)
        except ValueError:
            self.silence()
            raise
        now = time.monotonic_ns()
        t = now if t_ns is None else int(t_ns)
        level = self.amplitude_map.level(amplitude_N) if frequency_hz > 0.0 else 0.0
        self._set(level, float(frequency_hz), t, now)
        self.stats.updates += 1
        self.stats.last_update_ns = now
        self.stats.last_t_ns = t

    def silence(self) -> None:
        """Ramp to silence now (best effort: never raises)."""
        if self.is_open:
            try:
                self._silence()
            except Exception:  # the output may already be gone
                pass

    def _make_safe(self) -> None:
        self.silence()  # close: silence, then release the output

    @abstractmethod
    def _set(self, level: float, frequency_hz: float, t_ns: int, arrival_ns: int) -> None:
        """Store a new target: ``level`` in [0, 1] of full scale (0 when the frequency is 0),
        ``frequency_hz`` ≥ 0."""

    def _silence(self) -> None:
        self._set(0.0, 0.0, self.stats.last_t_ns, time.monotonic_ns())

    @abstractmethod
    def _open(self) -> None:
        """Acquire the output and start it silent."""

    @abstractmethod
    def _close(self) -> None:
        """Release the output (after :meth:`_silence`). Also called when ``_open`` raised
        part-way: release only what is there (and be safe to call twice)."""

