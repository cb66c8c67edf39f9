"""An emulated Novint Falcon: its FTDI bridge, bootloader, I/O firmware and mechanism.

The host sees what a real Falcon shows over USB (``falcon.protocol`` for every constant):
0403:cb48, an FT232BM-class bridge (``ftdi``), and behind its serial line a microcontroller:

- **bootloader** (after power-on, and after each DTR low→high edge, which resets the
  microcontroller): answers the probe ``0A 43 0D`` with ``0A 44 2C 0D`` when the line runs
  at 9600 Bd 8N1; then, at the upload rate (divisor 0x15), echoes ``'A'`` and every image
  byte. The uploaded image starts once the host leaves the upload rate (the emulation's stand-
  in for the real bootloader's end-of-image check; the image is counted and hashed, never
  run). Bytes at any other rate are garbled and dropped.
- **firmware** (at 1.5 MBd): for each 16-byte command packet, one 16-byte status packet:
  encoders of the simulated grip (``mechanism``), the grip buttons, the per-axis homed flags.
  Malformed packets are counted and skipped (resynchronizing on ``'<'``).
- **homing**: while the host sets the homing bit, each axis whose true encoder count has
  swept ``homing_travel_counts`` becomes homed; until then its encoder reads relative to where
  it was at power-on (the real encoders are incremental until they find their index).

Every I/O cycle is logged with its arrival time (``time.monotonic_ns``, comparable across
processes), the motor commands and the encoders sent, so a test can read back what the
driver commanded and when (e.g. "force zero within 50 ms").
"""

from __future__ import annotations

import hashlib
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from burrforce.server.devices.falcon import protocol as fp
from burrforce.server.devices.falcon.kinematics import commands_to_torques, end_effector_force
from burrforce.server.devices.sim import HAND_B_N_S_MM, HAND_K_N_MM

from .ftdi import EmulatedFtdi, same_baud
from .mechanism import FalconMechanism, warm_up

#: Log columns, one row per I/O cycle.
LOG_FIELDS = ("t_ns", "motor0", "motor1", "motor2", "enc0", "enc1", "enc2", "flags",
              "status")
DEFAULT_HOMING_TRAVEL_COUNTS = 400
DEFAULT_LOG_ROWS = 200_000


def _bad_waypoint(waypoint: Any) -> bool:
    raise ValueError(f"a waypoint is [t_s, x_mm, y_mm, z_mm], got {waypoint!r}")


class EmulatedFalcon(EmulatedFtdi):
    """The emulated Falcon (options are the emulator's ``--options`` keys).

    Args:
        firmware_loaded: start with the I/O firmware running (skip the upload).
        homed: start with all three axes homed (absolute encoders); needs
            ``firmware_loaded`` (homing is the firmware's state: a reset loses it).
        start_mm: where the grip starts, mm from the workspace centre (kinematics frame).
        hand: whether the scripted hand holds the grip (at ``start_mm``) from the start.
        hand_k_N_mm, hand_b_N_s_mm: the hand's spring and damper.
        homing_travel_counts: encoder counts each axis must sweep in homing mode.
        buttons: grip button bits reported (low nibble).
        latency: emulate the FTDI latency timer on data (see ``ftdi``).
        log_rows: I/O cycles kept in the log (oldest dropped first).
        serial: the USB serial-number string.
    """

    vendor_id = fp.VID
    product_id = fp.PID
    manufacturer = "Novint (emulated)"
    product = "Falcon (emulated)"

    def __init__(self, firmware_loaded: bool = False, homed: bool = False,
                 start_mm=(0.0, 0.0, 0.0), hand: bool = True,
                 hand_k_N_mm: float = HAND_K_N_MM, hand_b_N_s_mm: float = HAND_B_N_S_MM,
                 homing_travel_counts: int = DEFAULT_HOMING_TRAVEL_COUNTS, buttons: int = 0,
                 latency: bool = False, log_rows: int = DEFAULT_LOG_ROWS,
                 serial: str = "EMU00001",
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(latency=latency, clock=clock)
        warm_up()
        if homed and not firmware_loaded:
            raise ValueError("homed needs firmware_loaded: homing is lost with the firmware")
        if not 1 <= int(homing_travel_counts) <= 4000:
            raise ValueError(f"homing_travel_counts must be 1..4000, got {homing_travel_counts}")
        if not 100 <= int(log_rows) <= 10_000_000:
            raise ValueError(f"log_rows must be 100..10 000 000, got {log_rows}")
        self.serial = serial
        self.homing_travel_counts = int(homing_travel_counts)
        self.mechanism = FalconMechanism(self.clock(), start_mm, hand_k_N_mm, hand_b_N_s_mm,
                                         hand_on=hand)
        self.buttons = 0
        self._set_buttons(buttons)
        self.log: deque[tuple[int, ...]] = deque(maxlen=int(log_rows))
        self.cycles = 0
        self.bad_packets = 0
        self.garbled_bytes = 0
        self.leds = 0
        self.homing_mode = False
        self.last_motor = (0, 0, 0)
        self.last_command_ns: int | None = None
        self._rx = bytearray()
        self._power_on(firmware_loaded, homed)

    # -- microcontroller state ---------------------------------------------------------

    def _power_on(self, firmware_loaded: bool, homed: bool) -> None:
        self.upload_bytes = 0
        self._upload_hash = hashlib.sha256()
        self.uploads = 0
        self.probes_answered = 0
        self._reset_microcontroller(firmware_loaded, homed)

    def _reset_microcontroller(self, keep_firmware: bool = False, homed: bool = False) -> None:
        # The firmware lives in RAM, and the encoder counters and homing in the
        # microcontroller: a reset returns to the bootloader, unhomed, counting from here.
        self.mode = "firmware" if keep_firmware else "bootloader"
        self.firmware_loaded = keep_firmware
        # A power-on leaves the bootloader waiting for its reset (DTR low → high); then it
        # answers the probe, waits for the upload start, and echoes the upload.
        self._boot_stage = "probe" if keep_firmware else "reset"
        self._rx.clear()
        now = self.clock()
        self.mechanism.command(now, (0, 0, 0))
        counts = self.mechanism.encoder_counts()
        self.homed = [bool(homed)] * 3
        self._power_on_counts = counts.copy()
        self._sweep_min = counts.copy()
        self._sweep_max = counts.copy()

    def on_dtr(self, level: bool) -> None:
        if level:
            self._reset_microcontroller()
            self._boot_stage = "probe"

    def on_purge_tx(self) -> None:
        self._rx.clear()

    def control(self, request_type: int, request: int, value: int, index: int,
                data_or_length: bytes | int) -> bytes | int | None:
        answer = super().control(request_type, request, value, index, data_or_length)
        if request == fp.SIO_SET_BAUD_RATE and request_type == fp.FTDI_REQUEST_OUT \
                and self.mode == "bootloader" and self._boot_stage == "upload" \
                and not same_baud(self.baud_divisor, fp.BAUD_DIVISOR_FIRMWARE):
            self._start_firmware()
        return answer

    def _start_firmware(self) -> None:
        self.mode = "firmware"
        self.firmware_loaded = True
        self.uploads += 1
        self._rx.clear()

    def serial_from_host(self, data: bytes) -> None:
        if self.line != fp.LINE_8N1:
            self.garbled_bytes += len(data)
            return
        if self.mode == "firmware":
            if not same_baud(self.baud_divisor, fp.BAUD_DIVISOR_NORMAL):
                self.garbled_bytes += len(data)
                return
            self._rx += data
            self._parse_packets()
        else:
            self._bootloader(data)

    def _bootloader(self, data: bytes) -> None:
        if self._boot_stage == "reset":
            self.garbled_bytes += len(data)   # held in reset until DTR is toggled
            return
        if self._boot_stage == "probe":
            if not same_baud(self.baud_divisor, fp.BAUD_DIVISOR_9600):
                self.garbled_bytes += len(data)
                return
            self._rx += data
            if fp.FIRMWARE_PROBE in self._rx:
                self._rx.clear()
                self.probes_answered += 1
                # The bootloader answers, then listens at the upload rate only.
                self._boot_stage = "start"
                self.serial_to_host(fp.FIRMWARE_PROBE_REPLY)
            del self._rx[:-len(fp.FIRMWARE_PROBE)]
            return
        if not same_baud(self.baud_divisor, fp.BAUD_DIVISOR_FIRMWARE):
            self.garbled_bytes += len(data)
            return
        if self._boot_stage == "start":
            if data[:1] != fp.FIRMWARE_UPLOAD_START:
                self.garbled_bytes += len(data)
                return
            self._boot_stage = "upload"
            self.upload_bytes = 0
            self._upload_hash = hashlib.sha256()
            self.serial_to_host(data[:1])
            data = data[1:]
        if data:
            self.upload_bytes += len(data)
            self._upload_hash.update(data)
            self.serial_to_host(data)

    def _parse_packets(self) -> None:
        for command in fp.split_packets(self._rx, fp.decode_command):
            if command is None:
                self.bad_packets += 1
            else:
                self._io_cycle(*command)

    def _io_cycle(self, motor: tuple[int, int, int], leds: int, homing: bool) -> None:
        now = self.clock()
        self.mechanism.command(now, motor)
        counts = self.mechanism.encoder_counts()
        self.homing_mode = homing
        if homing:
            np.minimum(self._sweep_min, counts, out=self._sweep_min)
            np.maximum(self._sweep_max, counts, out=self._sweep_max)
            for axis in range(3):
                if self._sweep_max[axis] - self._sweep_min[axis] >= self.homing_travel_counts:
                    self.homed[axis] = True
        sent = [int(c) if self.homed[axis] else int(c - self._power_on_counts[axis])
                for axis, c in enumerate(counts)]
        sent = [min(max(c, fp.INT16_MIN), fp.INT16_MAX) for c in sent]
        status = fp.encode_status(sent, self.buttons, tuple(self.homed))
        self.leds = leds
        self.last_motor = motor
        self.last_command_ns = now
        self.cycles += 1
        flags = leds | (fp.HOMING_BIT if homing else 0)
        status_bits = status[13] - fp.NIBBLE_OFFSET
        self.log.append((now, *motor, *sent, flags, status_bits))
        self.serial_to_host(status)

    # -- control channel ---------------------------------------------------------------

    def _set_buttons(self, buttons: int) -> int:
        buttons = int(buttons)
        if buttons & ~fp.BUTTON_MASK:
            raise ValueError(f"button bits must be within {fp.BUTTON_MASK:#x}, got {buttons:#x}")
        self.buttons = buttons
        return buttons

    def _state(self) -> dict[str, Any]:
        now = self.clock()
        m = self.mechanism
        m.advance(now)
        counts = m.encoder_counts()
        return {
            "t_ns": now, "mode": self.mode, "firmware_loaded": self.firmware_loaded,
            "cycles": self.cycles, "bad_packets": self.bad_packets,
            "garbled_bytes": self.garbled_bytes, "probes_answered": self.probes_answered,
            "upload_bytes": self.upload_bytes, "uploads": self.uploads,
            "upload_sha256": self._upload_hash.hexdigest(),
            "homed": list(self.homed), "homing_mode": self.homing_mode, "leds": self.leds,
            "buttons": self.buttons, "motor_command": list(self.last_motor),
            "last_command_ns": self.last_command_ns,
            "motor_force_N": m.motor_force_N().tolist(),
            "position_mm": m.position_mm().tolist(), "position_m": m.p.tolist(),
            "velocity_m_s": m.v.tolist(), "encoders_true": counts.tolist(),
            "hand_target_mm": m.hand_target_mm(now),
            "encoders_sent": list(self.log[-1][4:7]) if self.log else None,
            "ftdi": self.ftdi_state(),
        }

    def _log(self, since_ns: int = 0, limit: int | None = None) -> dict[str, Any]:
        rows = [list(r) for r in self.log if r[0] > since_ns]
        if limit is not None:
            rows = rows[-int(limit):]
        return {"fields": list(LOG_FIELDS), "rows": rows}

    def _set_hand(self, target_mm=None, path=None, stiffness_N_mm: float | None = None,
                  damping_N_s_mm: float | None = None, release: bool = False) -> bool:
        now = self.clock()
        m = self.mechanism
        if stiffness_N_mm is not None or damping_N_s_mm is not None:
            m.advance(now)
            m.set_hand_gains(m.hand_k * 1e-3 if stiffness_N_mm is None else float(stiffness_N_mm),
                             m.hand_b * 1e-3 if damping_N_s_mm is None else float(damping_N_s_mm))
        if release:
            if target_mm is not None or path is not None:
                raise ValueError("release takes no target or path")
            m.release_hand(now)
        elif target_mm is not None and path is not None:
            raise ValueError("give a target_mm or a path, not both")
        elif target_mm is not None:
            m.set_path(now, [(0.0, target_mm)])
        elif path is not None:
            try:
                waypoints = [(float(w[0]), [float(c) for c in w[1:4]]) for w in path
                             if len(w) == 4 or _bad_waypoint(w)]
            except (TypeError, ValueError):
                raise ValueError("a hand path is a list of [t_s, x_mm, y_mm, z_mm] "
                                 "waypoints") from None
            m.set_path(now, waypoints)
        return True

    def _place(self, position_mm) -> bool:
        self.mechanism.place(self.clock(), position_mm)
        return True

    def _home_now(self) -> list[bool]:
        self.homed = [True, True, True]
        return self.homed

    def power_off(self) -> None:
        self.mechanism.command(self.clock(), (0, 0, 0))   # unpowered motors hold no torque

    def power_cycle(self) -> None:
        self._power_cycle()

    def _power_cycle(self, firmware_loaded: bool = False, homed: bool = False) -> bool:
        super().power_cycle()
        self._power_on(firmware_loaded, homed)
        return True

    def _force_at(self, motor) -> list[float]:
        """The force (N) motor commands ``motor`` would exert at the grip's position now."""
        tau = commands_to_torques(np.asarray(motor, dtype=float))
        self.mechanism.advance(self.clock())
        return end_effector_force(self.mechanism.p, tau).tolist()

    def commands(self) -> dict[str, Callable[..., Any]]:
        return {"state": self._state, "log": self._log, "set_hand": self._set_hand,
                "place": self._place, "set_buttons": self._set_buttons,
                "home_now": self._home_now, "power_cycle": self._power_cycle,
                "force_at": self._force_at, "clear_log": self.log.clear}
