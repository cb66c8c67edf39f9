"""The device loop: a haptic device and an actuator driven from a session, at the device's
servo rate, in a process of its own.

It is a device host as SPEC 7.5 describes one, speaking the ordinary UDP protocol to the hot
loop (nothing in the hot loop knows it is there). Each servo cycle:

1. one I/O cycle with the device: send the force computed last cycle, read the state;
2. map the state into the server frame (``devices.mapping``);
3. send this cycle's POSE (every ``packet_divider`` cycles), stamped with the reading's time;
4. take replies until the one answering that POSE arrives or the period ends: the newest good
   reply's coupling model goes to the renderer, its vibration parameters to the actuator; an
   error reply drops the model;
5. render the force from the newest coupling model at the device's position and velocity
   (``devices.render``: extrapolated, delay-limited, passivity-controlled, limited);
6. sleep to the end of the period (a device whose I/O blocks, like the Falcon, paces itself).

With a server that answers within the period, a pose's force reaches the device one period
after the pose was read.

Watchdog: the renderer zeroes the force when the newest model is older than ``stale_s``
(30 ms: no replies because the stream stopped, the hot loop died or the network failed), and
the next cycle sends that zero. The actuator silences itself on its own watchdog (50 ms
without an update), and is silenced at once when the model goes stale. A USB error or an
unplugged device ends the loop (state ``failed``, the reason in the events); SIGTERM, SIGINT
(also while opening or homing), the server process's death (checked every cycle) and any
exception end it too, always through ``device.close()``, which commands zero force. What
software cannot cover: SIGKILL of this process (or the OOM killer) leaves the device with its
last command, and whether a device then holds it is up to its firmware.
"""

from __future__ import annotations

import gc
import math
import os
import select
import signal
import socket
import time
from dataclasses import dataclass, field

import numpy as np

from ...client.udp import SessionRules
from ...proto.codec import ProtocolError
from ...proto.frames import Transform, frame
from ...proto.messages import ERROR_NAMES, MAX_REPLY_BYTES, NEW_STREAM, OK, Notice
from ..realtime import DEVICE_LOOP_PRIORITY, enter_realtime
from . import stats as st
from .base import DeviceDisconnected, DeviceError
from .mapping import WorkspaceMap
from .registry import create_actuator, create_device
from .render import C_PASSIVITY, C_SATURATED, C_TRIPS, M_T_ARRIVAL, STALE_S, CouplingRenderer

SPINDLE_MODES = ("on", "off", "button")
#: This many non-finite readings in a row end the loop (the device is failing).
BAD_READINGS_LIMIT = 50


class StopRequested(Exception):
    """SIGTERM or SIGINT while the device was being opened or homed."""


@dataclass(frozen=True)
class DeviceLoopConfig:
    """Everything the loop's process needs (picklable).

    Attributes:
        device: the haptic device spec (``registry``: ``NAME[:key=value,...]``).
        host, port, session, key_hex: the session's UDP endpoint and key.
        frame: the session's engine frame; placement_position (engine units) and
            placement_orientation: the session's placement, so poses land where the server
            puts them.
        workspace: where the device's workspace lies in the server frame.
        actuator: the vibration actuator's spec, or None.
        rpm: spindle speed sent with every pose.
        spindle: ``on`` (always), ``off``, or ``button`` (on while button 0 is held).
        orientation: the burr's orientation in every pose (engine quaternion x, y, z, w):
            identity keeps the session's tool axis.
        packet_divider: send a POSE every this many servo cycles (1: every cycle).
        stale_s: the watchdog's limit on the coupling model's age, ≤ 0.05 s.
        home: home the device before the loop; home_timeout_s: how long to wait for it.
        passivity: run the servo-rate passivity controller.
        realtime: ask for SCHED_FIFO (ignored where not permitted).
    """

    device: str
    host: str
    port: int
    session: int
    key_hex: str | None = None
    frame: str = "si_mm"
    placement_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    placement_orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    workspace: WorkspaceMap = field(default_factory=WorkspaceMap)
    actuator: str | None = None
    rpm: float = 60_000.0
    spindle: str = "on"
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    packet_divider: int = 1
    stale_s: float = STALE_S
    home: bool = True
    home_timeout_s: float = 60.0
    passivity: bool = True
    realtime: bool = True

    def __post_init__(self) -> None:
        frame(self.frame)
        if self.spindle not in SPINDLE_MODES:
            raise ValueError(f"spindle must be one of {SPINDLE_MODES}, got {self.spindle!r}")
        if not (math.isfinite(self.rpm) and abs(self.rpm) <= 1e6):
            raise ValueError(f"rpm must be a finite number within ±1e6, got {self.rpm!r}")
        if not 1 <= int(self.packet_divider) <= 1000:
            raise ValueError(f"packet_divider must be in [1, 1000], got {self.packet_divider}")
        if not 0.0 < self.stale_s <= 0.05:
            raise ValueError(f"stale_s must be in (0, 0.05] s, got {self.stale_s!r}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"bad UDP port {self.port}")


class DeviceLoop:
    """The loop itself (runs in the device process; :func:`run` is the process's entry).

    Args:
        config: what to drive and where to stream.
        stats: the shared statistics array (``devices.stats``: N_SLOTS float64).
        say: where events go (homing instructions, failures): one line each.
    """

    def __init__(self, config: DeviceLoopConfig, stats: np.ndarray, say) -> None:
        self.config = config
        self.stats = stats
        self.say = say
        self.stop_requested = False
        #: True while the device is opened and homed: a stop request unwinds that at once
        #: (later it ends the servo loop at the next cycle, or is moot while closing).
        self.opening = False
        #: The server that started this process: when it dies the loop stops (Linux's
        #: PR_SET_PDEATHSIG follows the starting *thread*, and REST workers come and go).
        self.parent_pid = os.getppid()
        self.device = None
        self.actuator = None
        self.sock: socket.socket | None = None

    # -- set-up ------------------------------------------------------------------------------
    def _check_stop(self) -> None:
        """Raise StopRequested if a stop was asked for. The signal handler raises it too,
        but where the signal lands inside a finalizer (a ``__del__`` run by the garbage
        collector) Python prints the exception and drops it: only the flag is sure."""
        if self.stop_requested:
            raise StopRequested

    def open(self) -> None:
        """Open (and home) the device and the actuator, then the stream's socket. Raises
        StopRequested when asked to stop meanwhile."""
        c = self.config
        self.device = create_device(c.device)
        self.device.open()
        self._check_stop()
        info = self.device.info
        self.say(f"device: {info.model} ({info.backend}), servo {info.servo_rate_hz:g} Hz, max "
                 f"force {info.limits.max_force_N:g} N")
        if c.home:
            self.stats[st.ST_STATE] = st.STATES.index("homing")
            homed = self.device.home(c.home_timeout_s, progress=self.say,
                                     cancelled=lambda: self.stop_requested)
            self._check_stop()
            if not homed:
                raise DeviceError(f"the device did not home within {c.home_timeout_s:g} s: "
                                  "move the grip slowly through its whole range, then retry")
        if c.actuator:
            self.actuator = create_actuator(c.actuator)
            self.actuator.open()
            self._check_stop()
            self.say(f"actuator: {c.actuator}")
        self.renderer = CouplingRenderer(info.limits, c.workspace.scale, c.stale_s,
                                         passivity=c.passivity)
        self.renderer.warm_up()  # compiles or loads kernels: where a finalizer may run
        self._check_stop()
        self.device.cycle(np.zeros(3))  # the back-end's kernels load before the first period
        self.transform = Transform(frame(c.frame), c.placement_position,
                                   c.placement_orientation)
        self.rules = SessionRules(c.session, c.key_hex, int.from_bytes(os.urandom(4), "big"))
        family = socket.AF_INET6 if ":" in c.host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock.connect((c.host, c.port))
        self.sock.setblocking(False)

    # -- the servo loop ----------------------------------------------------------------------
    def run(self) -> None:
        """Serve until asked to stop or the device fails (raises what made it fail).

        One cycle: device I/O; this cycle's POSE; replies until the reply to that POSE or
        the next deadline, whichever is first (so a fast server's answer is rendered in the
        same cycle, one servo period after the pose was read); render; sleep to the deadline.
        """
        c = self.config
        s = self.stats
        device, renderer, transform, mapping = (self.device, self.renderer, self.transform,
                                                c.workspace)
        period = 1.0 / device.info.servo_rate_hz
        axes = np.asarray(device.info.axes, dtype=float)  # native → common device frame
        f_device = np.zeros(3)
        n = 0
        s[st.ST_STATE] = st.STATES.index("running")
        deadline = time.monotonic()
        s[st.ST_T_START] = deadline
        t_prev = None
        pushing = False  # whether the last force sent was not zero
        bad_run = 0  # non-finite readings in a row
        self.silenced = True
        self.fresh_sample = -1.0  # sample time of a reply whose force goes out next cycle
        self.waited = 0.0  # s this cycle spent waiting for the reply
        gc.collect()
        gc.freeze()
        while not self.stop_requested:
            if os.getppid() != self.parent_pid:
                self.say("the server process is gone: stopping")
                break
            if self.fresh_sample >= 0.0:
                st.hist_add(s, st.HIST_LATENCY, (time.monotonic() - self.fresh_sample) * 1e6)
                self.fresh_sample = -1.0
            t_io = time.monotonic()
            state = device.cycle(f_device)
            now_ns = time.monotonic_ns()
            st.hist_add(s, st.HIST_IO, (now_ns * 1e-9 - t_io) * 1e6)
            now = now_ns * 1e-9
            if pushing and not f_device.any():
                s[st.ST_T_DEVICE_ZERO] = now  # the watchdog's zero has reached the device
            pushing = bool(f_device.any())
            if not (np.isfinite(state.position_mm).all()
                    and np.isfinite(state.velocity_mm_s).all()):
                # A reading the back-end could not make sense of: nothing is rendered from
                # it (zero force this cycle), and a run of them is the device failing.
                s[st.ST_BAD_READINGS] += 1
                bad_run += 1
                if bad_run >= BAD_READINGS_LIMIT:
                    raise DeviceError(f"{bad_run} unusable readings in a row from the device")
                f_device = np.zeros(3)
                time.sleep(period)
                deadline = time.monotonic()
                continue
            bad_run = 0
            x = mapping.point(axes @ state.position_mm)
            v = mapping.vector(axes @ state.velocity_mm_s)
            awaited = -1
            if n % c.packet_divider == 0:
                spindle = (c.spindle == "on" or (c.spindle == "button" and state.buttons & 1))
                seq, datagram = self.rules.datagram(transform.point_out(tuple(x)), c.orientation,
                                                    c.rpm, bool(spindle), None, 0,
                                                    now_ns // 1000)
                try:
                    self.sock.send(datagram)
                    s[st.ST_SENT] += 1
                    awaited = seq
                except (BlockingIOError, ConnectionRefusedError):
                    s[st.ST_REFUSED] += 1
            deadline += period
            self.waited = 0.0
            self._receive(awaited, deadline)
            t_render = time.monotonic()
            f = renderer.render(x, v, t_render)
            live = renderer.live
            if not live and not self.silenced and self.actuator is not None:
                self.actuator.silence()  # never raises
                self.silenced = True
            f_device = axes.T @ mapping.force_to_device(f)
            # Statistics.
            n += 1
            s[st.ST_CYCLES] = n
            s[st.ST_T_LAST] = now
            s[st.ST_LIVE] = 1.0 if live else 0.0
            s[st.ST_POSITION:st.ST_POSITION + 3] = x
            s[st.ST_FORCE:st.ST_FORCE + 3] = f
            s[st.ST_BUTTONS] = state.buttons
            s[st.ST_MODEL_AGE] = t_render - renderer.model[M_T_ARRIVAL] if live else 0.0
            counters = renderer.counters
            s[st.ST_SATURATED] = counters[C_SATURATED]
            s[st.ST_TRIPS] = counters[C_TRIPS]
            s[st.ST_PASSIVITY] = counters[C_PASSIVITY]
            if t_prev is not None:
                st.hist_add(s, st.HIST_PERIOD, (now - t_prev) * 1e6)
            t_prev = now
            # The loop's own work this cycle: everything but the device's I/O and waiting.
            st.hist_add(s, st.HIST_WORK, (time.monotonic() - now - self.waited) * 1e6)
            # Pacing: sleep to the deadline; never try to catch up a burst.
            late = time.monotonic() - deadline
            if late > 0.5 * period:
                s[st.ST_OVERRUNS] += 1
                deadline = time.monotonic()
            elif late < 0.0:
                time.sleep(-late)

    def _receive(self, awaited: int, deadline: float) -> None:
        """Take replies until the one answering ``awaited`` (a seq; −1: none) has come or
        ``deadline`` (monotonic s) passes; then whatever else has already arrived."""
        sock = self.sock
        while True:
            got = self._take_replies(awaited)
            remaining = deadline - time.monotonic()
            if got or remaining <= 0.0 or awaited < 0:
                return
            t_wait = time.monotonic()
            select.select((sock,), (), (), remaining)
            self.waited += time.monotonic() - t_wait

    def _take_replies(self, awaited: int) -> bool:
        """Every datagram already arrived: the newest good reply's coupling model to the
        renderer, its vibration to the actuator. True if the reply to ``awaited`` came."""
        s = self.stats
        renderer, transform = self.renderer, self.transform
        mm_per_unit = transform.scale
        got = False
        while True:
            try:
                data = self.sock.recv(MAX_REPLY_BYTES + 1)
            except BlockingIOError:
                return got
            except ConnectionRefusedError:  # ICMP: nothing listens (the hot loop is gone)
                s[st.ST_REFUSED] += 1
                return got
            now_ns = time.monotonic_ns()
            now = now_ns * 1e-9
            try:
                item = self.rules.accept(data, now_ns // 1000)
            except ProtocolError:
                continue
            if item is None:  # forged, foreign, older than one already taken
                continue
            if isinstance(item, Notice):
                s[st.ST_NOTICES] += 1
                # NEW_STREAM is the handshake (SessionRules adopted the stream): not news.
                if int(s[st.ST_LAST_NOTICE]) != item.error and item.error != NEW_STREAM:
                    self.say(f"server notice: {ERROR_NAMES.get(item.error, item.error)}")
                s[st.ST_LAST_NOTICE] = item.error
                got = got or item.seq == awaited
                continue
            r = item.reply
            got = got or r.seq == awaited
            if r.error != OK:
                s[st.ST_ERROR_REPLIES] += 1
                renderer.drop()
                continue
            s[st.ST_REPLIES] += 1
            s[st.ST_T_LAST_REPLY] = now
            st.hist_add(s, st.HIST_RTT, item.rtt_us)
            self.fresh_sample = r.t_client_us * 1e-6
            renderer.accept(r.t_client_us * 1e-6, now, transform.point_in(r.proxy_position),
                            transform.vector_in(r.proxy_velocity),
                            r.coupling_stiffness / mm_per_unit, r.coupling_damping / mm_per_unit,
                            transform.direction_in(r.force))
            if self.actuator is not None:
                try:
                    self.actuator.update(r.vibration_amplitude, r.vibration_frequency_hz, now_ns)
                    self.silenced = False
                except ValueError:  # it silenced itself; the next good reply resumes
                    self.silenced = True
                except DeviceError as exc:  # the cue is lost, the force must not be
                    self.say(f"actuator failed, going on without it: {exc}")
                    self._drop_actuator()
            s[st.ST_VIB_AMPLITUDE] = r.vibration_amplitude
            s[st.ST_VIB_FREQUENCY] = r.vibration_frequency_hz

    def _drop_actuator(self) -> None:
        actuator, self.actuator = self.actuator, None
        try:
            actuator.close()
        except Exception:  # it is already broken; closing is best effort
            pass

    def close(self) -> None:
        """Zero the force, silence the actuator, release everything (never raises)."""
        for thing in (self.device, self.actuator):
            if thing is not None:
                try:
                    thing.close()
                except Exception as exc:  # a device that is gone cannot be zeroed
                    self.say(f"closing {type(thing).__name__}: {exc}")
        if self.sock is not None:
            self.sock.close()
        self.stats[st.ST_FORCE:st.ST_FORCE + 3] = 0.0
        self.stats[st.ST_LIVE] = 0.0


def run(config: DeviceLoopConfig, raw_stats, events) -> None:
    """The device process's entry: open, loop, and always close (zero force).

    Args:
        raw_stats: a ``multiprocessing.RawArray('d', stats.N_SLOTS)``.
        events: a multiprocessing queue for one-line events (or None: print them).
    """
    stats = np.frombuffer(raw_stats, dtype=np.float64)

    def say(text: str) -> None:
        if events is None:
            print(text, flush=True)
        else:
            events.put(text)

    loop = DeviceLoop(config, stats, say)

    def stop(signum, frame) -> None:
        loop.stop_requested = True
        if loop.opening:  # opening or homing: unwind now, through close()
            raise StopRequested

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    failed = False
    try:
        if config.realtime and enter_realtime(DEVICE_LOOP_PRIORITY):
            say("servo loop: SCHED_FIFO")
        loop.opening = True
        try:
            loop.open()
        finally:
            loop.opening = False
        loop.run()
    except StopRequested:
        say("stopped before the device was ready")
    except DeviceDisconnected as exc:
        failed = True
        say(f"failed: the device was disconnected ({exc})")
    except Exception as exc:  # any failure must still reach close() and be reported
        failed = True
        say(f"failed: {exc}")
    finally:
        loop.close()
        stats[st.ST_STATE] = st.STATES.index("failed" if failed else "stopped")
