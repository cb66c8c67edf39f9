"""The demo client: find the bone's surface and cut a groove in a running server (the command
``burrforce client demo`` is ``burrforce.server.cli.client_demo``).

Plans in the server's frame (mm, z up) and speaks the session's frame on the wire, as an
engine would: the probe descends with the spindle off until the server reports contact, then
the spinning burr plunges to depth, tilted back against the feed, and feeds along +x at a
steady speed while the forces are printed (and plotted with --plot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..proto import frames
from ..proto.messages import (
    FLAG_RESET_VELOCITY,
    STATUS_CONTACT,
    STATUS_CUTTING,
    STATUS_FORBIDDEN,
)
from .trajectory import Waypoint, line, stream
from .udp import BurrClient, Result

PROBE_SPEED_MM_S = 10.0
PLUNGE_SPEED_MM_S = 1.0
PROBE_FLOOR_MM = -60.0


@dataclass
class DemoRun:
    """What the demo measured. Per-tick arrays cover the cut (plunge and feed)."""

    surface_z_mm: float
    t_s: list[float] = field(default_factory=list)
    x_mm: list[float] = field(default_factory=list)
    force_N: list[tuple[float, float, float]] = field(default_factory=list)
    components_N: list[tuple[float, float, float]] = field(default_factory=list)
    status: list[int] = field(default_factory=list)
    removed_mm3: float = 0.0
    rtt_us: list[float] = field(default_factory=list)
    lost: int = 0
    feeding: list[bool] = field(default_factory=list)
    #: The session renders the coupled output (the replies carry a coupling model).
    coupled: bool = False
    #: Times the server ended this client's stream (another client's hello took it, or the
    #: server restarted): each costs a hello and the packets in flight.
    streams_ended: int = 0


def shortest_arc(a: frames.Vec3, b: frames.Vec3) -> frames.Quat:
    """The quaternion (x, y, z, w) rotating unit vector ``a`` onto unit vector ``b``."""
    ax, ay, az = a
    bx, by, bz = b
    dot = ax * bx + ay * by + az * bz
    if dot < -1.0 + 1e-12:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, (1.0, 0.0, 0.0) if abs(ax) < 0.9 else (0.0, 1.0, 0.0))
        axis /= np.linalg.norm(axis)
        return (float(axis[0]), float(axis[1]), float(axis[2]), 0.0)
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    w = 1.0 + dot
    n = math.sqrt(cx * cx + cy * cy + cz * cz + w * w)
    return (cx / n, cy / n, cz / n, w / n)


class _Planner:
    """Server-frame plans → the session frame's waypoints."""

    def __init__(self, frame_name: str) -> None:
        self.frame = frames.frame(frame_name)
        self.tf = frames.Transform(self.frame)

    def orientation(self, axis_server: frames.Vec3) -> frames.Quat:
        return shortest_arc(self.frame.tool_axis, self.tf.direction_out(axis_server))

    def waypoints(self, points_mm, axis_server, rpm: float, spindle_on: bool):
        q = self.orientation(axis_server)
        for w in points_mm:
            yield Waypoint(self.tf.point_out(w.position), q, rpm, spindle_on)


def run_demo(client: BurrClient, frame_name: str, x_mm: float = -5.0, y_mm: float = 0.0,
             length_mm: float = 10.0, depth_mm: float = 0.5, feed_mm_s: float = 5.0,
             rpm: float = 60_000.0, angle_deg: float = 60.0, radius_mm: float = 2.0,
             rate_hz: float = 1000.0, voxel_mm: float | None = None,
             say=print) -> DemoRun:
    """Probe, plunge, feed; returns the per-tick record.

    The server reports contact where the burr meets interpolated density above zero, which
    begins half a voxel above the bone's surface (density's 0.5 level): given the voxel size,
    the probe corrects for it.

    Raises:
        RuntimeError: no bone under (x, y), or the server does not answer.
    """
    plan = _Planner(frame_name)
    up = (0.0, 0.0, 1.0)
    # 1. Probe: spindle off, straight down until the server reports contact.
    say(f"probing for the surface under x = {x_mm:g}, y = {y_mm:g} mm ...")
    surface = None
    z = 20.0
    q_up = plan.orientation(up)
    step = PROBE_SPEED_MM_S / rate_hz
    while z > PROBE_FLOOR_MM:
        r = client.exchange(plan.tf.point_out((x_mm, y_mm, z)), q_up, 0.0, False,
                            timeout_s=1.0)
        if r.reply.status & STATUS_CONTACT:
            surface = z - radius_mm - 0.5 * (voxel_mm or 0.0)
            break
        z -= step
    if surface is None:
        raise RuntimeError(f"no bone under x = {x_mm:g}, y = {y_mm:g} mm down to z = "
                           f"{PROBE_FLOOR_MM:g} mm: choose --x-mm/--y-mm over the bone")
    within = "± a quarter voxel" if voxel_mm else "to within a voxel"
    say(f"surface at z = {surface:.2f} mm ({within}); cutting {length_mm:g} mm along +x, "
        f"{depth_mm:g} mm deep, {feed_mm_s:g} mm/s, {rpm:g} rpm, tool tilted {angle_deg:g}°")
    # 2. Plunge (spinning, vertical feed) and 3. feed along +x, tilted back against the feed.
    alpha = math.radians(angle_deg)
    axis = (-math.cos(alpha), 0.0, math.sin(alpha))
    cut_z = surface + radius_mm - depth_mm
    above = (x_mm, y_mm, surface + radius_mm + 0.5)
    at_depth = (x_mm, y_mm, cut_z)
    end = (x_mm + length_mm, y_mm, cut_z)
    plunge = list(plan.waypoints(line(above, at_depth, PLUNGE_SPEED_MM_S, rate_hz), axis,
                                 rpm, True))
    feed = list(plan.waypoints(line(at_depth, end, feed_mm_s, rate_hz), axis, rpm, True))
    first = plunge[0]
    plunge[0] = first._replace(flags=FLAG_RESET_VELOCITY)  # from the probe: not a motion
    waypoints = plunge + feed
    run = DemoRun(surface)
    report_every = max(1, round(rate_hz / 4))
    say(f"{'t s':>6} {'x mm':>7} {'|F| N':>7} {'feed N':>7} {'lat N':>7} {'norm N':>7} "
        f"{'rtt µs':>7}  status")

    def on_result(i: int, result: Result) -> None:
        if i % report_every == 0:
            rep = result.reply
            f = math.sqrt(sum(c * c for c in rep.force))
            names = ",".join(rep.status_names()) or "-"
            say(f"{i / rate_hz:6.2f} {_server_x(plan, waypoints[i]):7.2f} {f:7.3f} "
                f"{rep.resistive[0]:7.3f} {rep.resistive[1]:7.3f} {rep.resistive[2]:7.3f} "
                f"{result.rtt_us:7.0f}  {names}")

    def on_outage(gone: bool, i: int) -> None:
        if gone:
            say(f"{i / rate_hz:6.2f} the server is gone (is `burrforce serve` still running?); "
                "sending on until it is back")
        else:
            say(f"{i / rate_hz:6.2f} the server is back: a new stream, cutting resumes")

    out = stream(client, waypoints, rate_hz, on_result, on_outage=on_outage)
    for i, result in enumerate(out.results):
        if result is None:
            run.lost += 1
            continue
        rep = result.reply
        run.t_s.append(i / rate_hz)
        run.x_mm.append(_server_x(plan, waypoints[i]))
        run.force_N.append(plan.tf.direction_in(rep.force))
        run.components_N.append(rep.resistive)
        run.status.append(rep.status)
        run.removed_mm3 += rep.removed_mm3
        run.coupled = run.coupled or rep.coupling_stiffness > 0.0
        run.rtt_us.append(result.rtt_us)
        run.feeding.append(i >= len(plunge) + round(rate_hz * min(1.0, 0.2 * length_mm
                                                                   / feed_mm_s)))
    # Retract with the spindle off, so the session is left with no force.
    top = plan.tf.point_out((x_mm + length_mm, y_mm, surface + radius_mm + 5.0))
    client.exchange(top, plan.orientation(up), 0.0, False, flags=FLAG_RESET_VELOCITY,
                    timeout_s=1.0)
    run.streams_ended = client.counters["wrong_stream"]
    return run


def _server_x(plan: _Planner, w: Waypoint) -> float:
    return plan.tf.point_in(w.position)[0]


def summary(run: DemoRun) -> dict:
    """Means over the steady part of the feed, and totals."""
    steady = np.array(run.feeding, dtype=bool)
    status = np.array(run.status, dtype=np.int64)
    comps = np.array(run.components_N).reshape(-1, 3)
    force = np.array(run.force_N).reshape(-1, 3)
    rtt = np.array(run.rtt_us)
    sel = steady & (status & STATUS_CUTTING > 0) if len(status) else steady
    mean = comps[sel].mean(axis=0) if sel.any() else np.zeros(3)
    return {
        "surface_z_mm": run.surface_z_mm,
        "ticks": len(run.t_s),
        "lost": run.lost,
        "streams_ended": run.streams_ended,
        "cutting_ticks": int((status & STATUS_CUTTING > 0).sum()),
        "forbidden_ticks": int((status & STATUS_FORBIDDEN > 0).sum()),
        "steady_feed_N": float(mean[0]),
        "steady_lateral_N": float(mean[1]),
        "steady_normal_N": float(mean[2]),
        "steady_force_N": float(np.linalg.norm(force[sel], axis=1).mean()) if sel.any()
        else 0.0,
        "removed_mm3": run.removed_mm3,
        "coupled": run.coupled,
        "rtt_p50_us": float(np.median(rtt)) if len(rtt) else None,
        "rtt_p99_us": float(np.percentile(rtt, 99)) if len(rtt) else None,
    }


def plot(run: DemoRun, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    comps = np.array(run.components_N).reshape(-1, 3)
    t = np.array(run.t_s)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6.5),
                                   gridspec_kw={"height_ratios": [2, 1]})
    for k, name in enumerate(("feed", "lateral", "normal")):
        ax1.plot(t, comps[:, k], lw=0.8, label=name)
    ax1.plot(t, np.linalg.norm(np.array(run.force_N).reshape(-1, 3), axis=1), "k", lw=0.8,
             label="|F| (hand)")
    ax1.set_xlabel("time since the plunge began, s")
    ax1.set_ylabel("force, N")
    ax1.set_title("burrforce client demo: plunge, then feed along +x")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(alpha=0.3)
    rtt = np.array(run.rtt_us)
    ax2.hist(rtt, bins=60, range=(0.0, float(np.percentile(rtt, 99.5))), color="0.4")
    ax2.set_xlabel("round trip from the pose's sample time, µs (up to p99.5)")
    ax2.set_ylabel("packets")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
