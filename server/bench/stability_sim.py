"""The closed loop of ``burrforce bench stability``: a simulated device and hand, a simulated
network, and the real hot loop answering real POSE datagrams, in simulated time.

``bench.stability`` explains the method and the tolerances; this module holds the pieces:
:class:`Scenario` (one run's settings), :class:`Link` (the socket to the hot loop),
:func:`simulate` (one run) and the measures (:func:`oscillation_rms`).

Units: mm, s, N (mass N·s²/mm = kg/1000, stiffness N/mm, damping N·s/mm), energy N·mm = mJ.
"""

from __future__ import annotations

import math
import socket
import time
import zlib
from dataclasses import asdict, dataclass, replace

import numpy as np

from ...proto.codec import decode_server_message, encode_pose
from ...proto.messages import (
    NEW_STREAM,
    OK,
    STATUS_CLAMPED,
    STATUS_CUTTING,
    Notice,
    Pose,
    Reply,
)
from ...proto.tag import Tagger
from ..devices.render import CouplingRenderer
from ..devices.sim import SimMechanism
from ..haptics.profiles import DeviceProfile
from ..haptics.velocity import DeviceVelocity

# -- the scene: the thesis's groove on the workpiece block (bone.phantoms) -------------------
RADIUS_MM = 2.0
ALPHA_DEG = 60.0  # tool axis (−cos α, 0, sin α): tilted back against the +x feed
TOP_Z_MM = 0.0  # the block's top face; x ∈ [0, 26], y ∈ [−8, 8], z ∈ [−8, 0]
GRID_X_MAX_MM = 29.0  # the block plus its 3 mm margin of air: the grid ends here
#: Where the device's workspace centre lies in the server frame (the block's top centre).
WORKSPACE_CENTRE_MM = (13.0, 0.0, 0.0)

# -- the hand: a spring-damper (devices.sim) pulling the device toward the target path --------
#: The path: above the bone at x = 3 mm, down in APPROACH_S until the burr centre is
#: CENTRE_DEPTH_MM below the top face (the burr's bottom 3 mm deep: the hand presses, with up to
#: 0.9 N), then along +x at the feed speed until X_END_MM, then held there.
X_START_MM = 3.0
X_END_MM = 23.0
Z_ABOVE_MM = RADIUS_MM + 4.0
CENTRE_DEPTH_MM = 1.0
APPROACH_S = 0.2
#: Events: the target jumps up TELEPORT_MM at TELEPORT_S and back down TELEPORT_BACK_S later.
TELEPORT_MM = 30.0
TELEPORT_S = 0.6
TELEPORT_BACK_S = 0.8
#: NaN poses: a burst of NAN_BURST_S from NAN_S, and single ones at NAN_SINGLE_S.
NAN_S = 0.5
NAN_BURST_S = 0.02
NAN_SINGLE_S = (0.75, 0.9)
#: Starting inside bone: the burr's centre this deep, fully embedded (the shaft in bone too).
INSIDE_Z_MM = -3.0
#: Leaving the grid: fed at LEAVE_FEED_MM_S past the block to x = LEAVE_X_MM, outside the grid.
LEAVE_X_MM = 45.0
LEAVE_FEED_MM_S = 50.0
EVENTS = ("", "teleport", "nan", "inside", "leave_grid")

# -- the client ------------------------------------------------------------------------------
#: SPEC 7.6: no good reply for this long → render zero force.
STALE_FORCE_S = 0.05
#: Real (wall) time to wait for an expected reply before counting it lost.
REPLY_TIMEOUT_S = 1.0
#: Device integration: at least this many substeps per packet interval, none longer than
#: MAX_SUBSTEP_S (also the sampling of the applied force for the oscillation measure).
MIN_SUBSTEPS = 10
MAX_SUBSTEP_S = 1e-4
#: Coupled output: how the device renders replies. ``servo``: the device loop's renderer
#: (devices.render) re-renders the newest coupling model every servo tick (1/rated_hz);
#: ``hold``: each reply's force held until the next (what the bench measured before the
#: device loop existed).
RENDERS = ("servo", "hold")
#: The oscillation measure: the applied force minus its moving average over this window.
OSC_WINDOW_S = 0.025
OSC_SAMPLE_S = 1e-4
#: The server's stream gap (SessionConfig.gap_s, default): intervals are capped at it.
SERVER_GAP_S = 0.05


@dataclass(frozen=True)
class Scenario:
    """One run's settings. ``case`` names the swept factor, ``value`` its value.

    Attributes:
        rpm: spindle speed (on whenever rpm > 0).  feed_mm_s: the target's feed along +x.
        us_scale: cortical Us × this (805.1 N/mm² × us_scale).  k: the material's K.
        dt_ms: the client's packet interval (simulated).
        delay_ms: from a pose's sampling to its reply's arrival (simulated round trip).
        jitter_ms: each interval is dt + U(−j, j) (at least dt/10) and each reply arrives up to
            j later than the delay (U(0, j)).
        loss: probability that a request is lost, and (independently) that its reply is.
        duplicate: probability that a datagram is sent twice (the server drops the copy).
        reorder: probability that a datagram is held and sent after the next one (the server
            answers only the newer).
        event: "", "teleport", "nan", "inside" or "leave_grid" (module constants).
        duration_s: simulated length of the run.
    """

    case: str
    value: float | None = None
    rpm: float = 60_000.0
    feed_mm_s: float = 10.0
    us_scale: float = 1.0
    k: float = 1.3
    dt_ms: float = 1.0
    delay_ms: float = 0.3
    jitter_ms: float = 0.0
    loss: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    event: str = ""
    duration_s: float = 1.2

    def __post_init__(self) -> None:
        if self.event not in EVENTS:
            raise ValueError(f"unknown event {self.event!r}")

    def with_(self, **changes: object) -> Scenario:
        return replace(self, **changes)  # type: ignore[arg-type]


# -- the target path --------------------------------------------------------------------------
class TargetPath:
    """Where the hand wants the burr centre at time t (server frame, mm) and how fast."""

    def __init__(self, sc: Scenario) -> None:
        self.event = sc.event
        self.feed = LEAVE_FEED_MM_S if sc.event == "leave_grid" else sc.feed_mm_s
        self.x_end = LEAVE_X_MM if sc.event == "leave_grid" else X_END_MM
        self.z_cut = INSIDE_Z_MM if sc.event == "inside" else TOP_Z_MM - CENTRE_DEPTH_MM
        self.x_start = X_START_MM + (5.0 if sc.event == "inside" else 0.0)
        self.t_feed_end = APPROACH_S + (self.x_end - self.x_start) / max(self.feed, 1e-9)

    def at(self, t: float) -> tuple[float, float, float, float, float, float]:
        """(x, y, z, vx, vy, vz)."""
        if t < APPROACH_S:
            if self.event == "inside":
                x, z, vz = self.x_start, self.z_cut, 0.0
            else:
                vz = (self.z_cut - Z_ABOVE_MM) / APPROACH_S
                x, z = self.x_start, Z_ABOVE_MM + vz * t
            vx = 0.0
        elif t < self.t_feed_end:
            x, z, vx, vz = self.x_start + self.feed * (t - APPROACH_S), self.z_cut, self.feed, 0.0
        else:
            x, z, vx, vz = self.x_end, self.z_cut, 0.0, 0.0
        if self.event == "teleport" and TELEPORT_S <= t < TELEPORT_BACK_S:
            z += TELEPORT_MM
        return x, 0.0, z, vx, 0.0, vz

    def start(self) -> tuple[float, float, float]:
        x, y, z, _, _, _ = self.at(0.0)
        return x, y, z


def is_nan_tick(event: str, t: float, dt: float) -> bool:
    """A NaN pose at sample time t: inside the burst, or the first sample at a single's time."""
    if event != "nan":
        return False
    if NAN_S <= t < NAN_S + NAN_BURST_S:
        return True
    return any(s <= t < s + dt for s in NAN_SINGLE_S)


def tool_orientation() -> tuple[float, float, float, float]:
    """The quaternion taking the session's tool axis (+z, si_mm) to (−cos α, 0, sin α)."""
    beta = math.radians(ALPHA_DEG - 90.0)
    return (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))


# -- the link to the real hot loop ------------------------------------------------------------
class Link:
    """A UDP socket to the hot loop, with the session key's tagger."""

    def __init__(self, address: tuple[str, int], key: bytes | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(address)
        self.sock.settimeout(REPLY_TIMEOUT_S)
        self.tagger = Tagger(key) if key is not None else None

    def close(self) -> None:
        self.sock.close()

    def exchange(self, datagrams: list[bytes], expected: set[int]) -> tuple[list, int]:
        """Send ``datagrams`` in order, then receive until every sequence number in
        ``expected`` has its reply (REPLY or NOTICE) or the timeout passes.

        Returns:
            (messages received for ``expected``, in arrival order; how many never came).
        """
        for d in datagrams:
            self.sock.send(d)
        got: list = []
        waiting = set(expected)
        while waiting:
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                break
            msg = decode_server_message(data)
            if msg.seq in waiting:
                waiting.discard(msg.seq)
                got.append(msg)
        return got, len(waiting)


# -- measures ---------------------------------------------------------------------------------
def oscillation_rms(t: np.ndarray, force: np.ndarray, t_from: float, t_to: float) -> float:
    """RMS (N) over [t_from, t_to) of the applied force (piecewise constant: ``force[i]``
    (n, 3) from ``t[i]`` on) minus its centred OSC_WINDOW_S moving average, on a uniform
    OSC_SAMPLE_S grid. A steady or slowly varying force gives ~0; a buzz or limit cycle with
    a period under the window gives about its RMS amplitude."""
    if len(t) == 0 or t_to <= t_from:
        return 0.0
    half = OSC_WINDOW_S / 2.0
    grid = np.arange(max(t_from - half, t[0]), t_to + half, OSC_SAMPLE_S)
    idx = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 1)
    f = force[idx]
    n = max(1, round(OSC_WINDOW_S / OSC_SAMPLE_S))
    if len(f) <= n:
        return 0.0
    kernel = np.ones(n) / n
    avg = np.stack([np.convolve(f[:, i], kernel, mode="same") for i in range(3)], axis=1)
    keep = (grid >= t_from) & (grid < t_to) & (grid >= grid[0] + half) \
        & (grid <= grid[-1] - half)
    if not keep.any():
        return 0.0
    d = f[keep] - avg[keep]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _finite_reply(r: Reply) -> bool:
    values = (*r.force, *r.resistive, *r.torque, r.power_w, r.vibration_amplitude,
              r.vibration_frequency_hz, *r.vibration_axis, *r.proxy_position,
              *r.proxy_velocity, r.coupling_stiffness, r.coupling_damping, r.removed_mm3,
              *r.feed_velocity)
    return all(math.isfinite(x) for x in values)


def run_seed(seed: int, profile: str, mode: str, sc: Scenario) -> int:
    """A reproducible per-run seed from the run's identity."""
    text = f"{seed}|{profile}|{mode}|{sc.case}|{sc.value}|{sc.us_scale}|{sc.dt_ms}"
    return zlib.crc32(text.encode())


# -- one run ----------------------------------------------------------------------------------
def simulate(link: Link, session_id: int, profile: DeviceProfile, mode: str, sc: Scenario,
             seed: int, energy_tol_J: float, osc_fraction: float,
             force_rel_tol: float = 1e-9, force_abs_tol_N: float = 1e-9,
             render: str = "servo") -> dict:
    """One closed-loop run against session ``session_id`` (fresh, this profile and mode);
    ``render`` (RENDERS) says how a coupled output reaches the device.

    Returns the row dict (``bench.stability`` documents the keys)."""
    if render not in RENDERS:
        raise ValueError(f"render must be one of {RENDERS}, got {render!r}")
    rng = np.random.default_rng(run_seed(seed, profile.name, mode, sc))
    wall0 = time.perf_counter()
    path = TargetPath(sc)
    q = tool_orientation()
    rpm = sc.rpm
    spindle_on = rpm > 0.0
    dt = sc.dt_ms * 1e-3
    jitter = sc.jitter_ms * 1e-3
    delay = sc.delay_ms * 1e-3
    half_ws = profile.sim_workspace_mm
    cx, cy, cz = WORKSPACE_CENTRE_MM
    max_f = profile.max_force_N
    max_f_ok = max_f * (1.0 + force_rel_tol) + force_abs_tol_N
    k_ok = profile.max_stiffness_N_mm * (1.0 + force_rel_tol)
    b_ok = profile.max_damping_N_s_mm * (1.0 + force_rel_tol)
    coupled = mode == "coupled"
    servo = coupled and render == "servo"
    renderer = CouplingRenderer(profile) if servo else None
    velocity = DeviceVelocity(profile.resolution_mm)
    servo_period = 1.0 / profile.rated_hz
    next_servo = 0.0
    f_servo = (0.0, 0.0, 0.0)

    # Device state (server frame, mm, mm/s).
    mech = SimMechanism(profile, path.start())
    x, v = mech.x, mech.v
    t = 0.0
    energy_max = 0.0  # of ∫ F_applied · v dt, N·mm (mech.work_mJ)
    f_hold = (0.0, 0.0, 0.0)
    newest_used = -1  # seq of the newest reply applied
    last_good_arrival = -math.inf
    first_arrival = math.inf
    pending: list[tuple[float, int, Reply | None]] = []  # (arrival, seq, good reply or None)
    f_t: list[float] = []
    f_xyz: list[tuple[float, float, float]] = []

    counts = {"nonfinite": 0, "force_over": 0, "slew_over": 0, "k_over": 0, "b_over": 0,
              "lost_requests": 0, "lost_replies": 0, "timeouts": 0, "duplicates": 0,
              "reordered": 0, "nan_poses": 0, "error_replies": 0, "notices": 0, "replies": 0,
              "clamped": 0, "cutting": 0}
    removed = 0.0
    max_server_force = 0.0
    max_depth = -math.inf
    left_workspace = False
    # The server's output stream, for the slew check (bench.stability docstring).
    ref_force = (0.0, 0.0, 0.0)
    ref_good_t_us: int | None = None
    # The stream handshake (SPEC 5.2): hellos until the server's NEW_STREAM notice arrives
    # (simulated time); the POSEs of the stream sent before its first reply arrived may each
    # be the one that opens it on the server (loss, reordering), its tick restarting the
    # haptic stage.
    stream = 0
    offer: tuple[float, int] | None = None  # (arrival, stream) of the first NEW_STREAM
    new_stream_seqs: set[int] = set()
    seq = 1
    t_us = 0
    held: tuple[int, bytes, float] | None = None  # a datagram held back (reordering)
    max_seq_at_server = 0
    stopped = False

    def advance(t_to: float) -> None:
        """Integrate the device from t to t_to under the rendered force, the hand and friction."""
        nonlocal t, energy_max, f_hold, newest_used, last_good_arrival, max_depth
        nonlocal left_workspace, next_servo, f_servo
        span = t_to - t
        if span <= 0.0:
            return
        n = max(MIN_SUBSTEPS, math.ceil(span / MAX_SUBSTEP_S - 1e-9))
        h = span / n
        for i in range(n):
            ts = t + i * h
            while pending and pending[0][0] <= ts:
                _, s, msg = pending.pop(0)
                if s > newest_used:
                    newest_used = s
                    if renderer is not None:
                        if msg is None:
                            renderer.drop()
                        else:
                            renderer.accept(msg.t_client_us * 1e-6, ts, msg.proxy_position,
                                            msg.proxy_velocity, msg.coupling_stiffness,
                                            msg.coupling_damping, msg.force)
                    else:
                        f_hold = None if msg is None else tuple(msg.force)
                        if msg is not None:
                            last_good_arrival = ts
            if renderer is not None:
                if ts >= next_servo - 1e-12:  # a servo tick: read the encoder, render
                    reading = mech.reading()
                    f = renderer.render(np.array(reading), velocity.update(reading, ts), ts)
                    f_servo = (float(f[0]), float(f[1]), float(f[2]))
                    while next_servo <= ts + 1e-12:
                        next_servo += servo_period
                fa = f_servo
            elif f_hold is None or ts - last_good_arrival > STALE_FORCE_S:
                fa = (0.0, 0.0, 0.0)
            else:
                fa = f_hold
            f_t.append(ts)
            f_xyz.append(fa)
            p0, p1, p2, u0, u1, u2 = path.at(ts)
            mech.step(fa, (p0, p1, p2), (u0, u1, u2), h)
            if mech.work_mJ > energy_max:
                energy_max = mech.work_mJ
        t = t_to
        max_depth = max(max_depth, TOP_Z_MM - (x[2] - RADIUS_MM))
        if max(abs(x[0] - cx), abs(x[1] - cy), abs(x[2] - cz)) > half_ws:
            left_workspace = True

    def check(msg) -> None:
        """The server's output, reply by reply in sequence order: finite, within limits."""
        nonlocal ref_force, ref_good_t_us, removed, max_server_force
        counts["replies"] += 1
        if not isinstance(msg, Reply):
            counts["notices"] += 1
            return
        if not _finite_reply(msg):
            counts["nonfinite"] += 1
        if msg.error != OK:
            counts["error_replies"] += 1
            ref_force = (0.0, 0.0, 0.0)  # an error reply carries zero force (device released)
            return
        if msg.status & STATUS_CLAMPED:
            counts["clamped"] += 1
        if msg.status & STATUS_CUTTING:
            counts["cutting"] += 1
        removed += msg.removed_mm3 if math.isfinite(msg.removed_mm3) else 0.0
        f = msg.force
        mag = math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
        max_server_force = max(max_server_force, mag) if math.isfinite(mag) else max_server_force
        if not mag <= max_f_ok:
            counts["force_over"] += 1
        t_now = msg.t_client_us
        if ref_good_t_us is None or msg.seq in new_stream_seqs:
            step_s = 1e-3  # a stream's first tick counts the usual period (session._tick)
        else:
            step_s = min(max(t_now - ref_good_t_us, 0) * 1e-6, SERVER_GAP_S)
        allowed = profile.max_slew_N_s * step_s * (1.0 + force_rel_tol) + force_abs_tol_N
        step = math.sqrt(sum((f[i] - ref_force[i]) ** 2 for i in range(3)))
        if not step <= allowed:
            counts["slew_over"] += 1
        if coupled:
            if not msg.coupling_stiffness <= k_ok:
                counts["k_over"] += 1
            if not msg.coupling_damping <= b_ok:
                counts["b_over"] += 1
        ref_force = f
        ref_good_t_us = t_now

    n_ticks = 0
    while True:
        # The next sample time (client clock, integer µs as on the wire).
        if n_ticks > 0:
            interval = dt + (rng.uniform(-jitter, jitter) if jitter > 0.0 else 0.0)
            t_us += max(1, round(float(max(interval, 0.1 * dt)) * 1e6))
        t_sample = t_us * 1e-6
        if t_sample > sc.duration_s:
            break
        advance(t_sample)
        if not all(math.isfinite(c) for c in (*x, *v)):
            counts["nonfinite"] += 1
            stopped = True
            break
        n_ticks += 1
        # The pose: encoder-quantized, or NaN for the event.
        if is_nan_tick(sc.event, t_sample, dt):
            position = (math.nan, math.nan, math.nan)
            counts["nan_poses"] += 1
        else:
            position = mech.reading()
        if stream == 0 and offer is not None and offer[0] <= t_sample:
            stream = offer[1]
        data = encode_pose(Pose(session_id, seq, t_us, position, q, rpm, spindle_on, None, 0,
                                stream), link.tagger)
        if stream != 0 and first_arrival > t_sample:
            new_stream_seqs.add(seq)
        this = (seq, data, t_sample)
        seq += 1
        # The channel: which datagrams reach the server this tick, in which order.
        out: list[tuple[int, bytes, float]] = []
        if sc.loss > 0.0 and rng.random() < sc.loss:
            counts["lost_requests"] += 1
        elif held is None and sc.reorder > 0.0 and rng.random() < sc.reorder:
            held = this
            counts["reordered"] += 1
        else:
            out.append(this)
            if sc.duplicate > 0.0 and rng.random() < sc.duplicate:
                out.append(this)
                counts["duplicates"] += 1
        if held is not None and held is not this:
            out.append(held)
            held = None
        expected: set[int] = set()
        for s, _, _ in out:
            if s > max_seq_at_server:  # newest wins: older or equal ones are never answered
                max_seq_at_server = s
                expected.add(s)
        if out:
            msgs, missing = link.exchange([d for _, d, _ in out], expected)
        else:
            msgs, missing = [], 0
        counts["timeouts"] += missing
        for msg in sorted(msgs, key=lambda m: m.seq):
            handshake = isinstance(msg, Notice) and msg.error == NEW_STREAM
            if not handshake:  # a hello's answer is no output of the server's
                check(msg)
            if sc.loss > 0.0 and rng.random() < sc.loss:
                counts["lost_replies"] += 1
                continue
            arrival = t_sample + delay + (rng.uniform(0.0, jitter) if jitter > 0 else 0.0)
            if handshake:
                if offer is None or arrival < offer[0]:
                    offer = (arrival, msg.stream)
                continue  # a hello's answer: no force, nothing to render or drop
            first_arrival = min(first_arrival, arrival)
            good = isinstance(msg, Reply) and msg.error == OK
            pending.append((arrival, msg.seq, msg if good else None))
        pending.sort(key=lambda p: p[0])
    if not stopped:
        advance(sc.duration_s)
        if not all(math.isfinite(c) for c in (*x, *v)):
            counts["nonfinite"] += 1

    ft = np.array(f_t)
    fxyz = np.array(f_xyz).reshape(-1, 3)
    mags = np.linalg.norm(fxyz, axis=1) if len(fxyz) else np.zeros(1)
    osc = oscillation_rms(ft, fxyz, sc.duration_s / 2.0, sc.duration_s)
    osc_tail = oscillation_rms(ft, fxyz, 0.75 * sc.duration_s, sc.duration_s)
    violations = counts["force_over"] + counts["slew_over"] + counts["k_over"] \
        + counts["b_over"]
    if len(ft) > 1:  # time-weighted mean of the applied force's magnitude
        w = np.diff(np.append(ft, sc.duration_s))
        mean_force = float(np.sum(mags * w) / max(np.sum(w), 1e-12))
    else:
        mean_force = 0.0
    energy_J = energy_max * 1e-3
    oscillating = bool(osc > osc_fraction * max_f)
    answered = max(counts["replies"] - counts["notices"], 1)
    row = {
        "profile": profile.name,
        "mode": mode,
        "render": render if coupled else "hold",
        "case": sc.case,
        "value": sc.value,
        "nonfinite": counts["nonfinite"],
        "limit_violations": violations,
        "energy_generated_J": energy_J,
        "oscillation": oscillating,
        "oscillation_N": osc,
        "oscillation_tail_N": osc_tail,
        "stable": False,
        "mean_force_N": mean_force,
        "max_force_N": float(mags.max()),
        "max_server_force_N": max_server_force,
        "removed_mm3": removed,
        "max_depth_mm": max_depth,
        "ticks": n_ticks,
        "replies": counts["replies"],
        "replies_lost": counts["lost_requests"] + counts["lost_replies"] + counts["timeouts"],
        "timeouts": counts["timeouts"],
        "error_replies": counts["error_replies"],
        "clamped_fraction": counts["clamped"] / answered,
        "cutting_fraction": counts["cutting"] / answered,
        "force_over": counts["force_over"],
        "slew_over": counts["slew_over"],
        "k_over": counts["k_over"],
        "b_over": counts["b_over"],
        "left_workspace": left_workspace,
        "wall_s": time.perf_counter() - wall0,
        "seed": run_seed(seed, profile.name, mode, sc),
        **{f"sc_{k}": v for k, v in asdict(sc).items() if k not in ("case", "value")},
    }
    row["stable"] = bool(row["nonfinite"] == 0 and violations == 0
                         and energy_J <= energy_tol_J and not oscillating)
    return row
