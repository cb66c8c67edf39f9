"""``burrforce serve --demo``: the client demo's grooves against the server just started,
one at once and then one every few seconds, giving way to any other client."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

from .client_demo import EXIT_GAVE_WAY
from .invocation import burrforce_command


def demo_start_mm(bone_info: dict | None, length_mm: float = 10.0) -> tuple[float, float]:
    """Where the demo's groove starts (x, y, server frame, mm): centred on the bone's
    footprint, so it finds bone whichever phantom or file is loaded."""
    if not bone_info:
        return -5.0, 0.0
    import numpy as np

    shape = np.asarray(bone_info["shape"], dtype=np.float64)
    spacing = np.asarray(bone_info["spacing_mm"], dtype=np.float64)
    rot = np.asarray(bone_info["direction"], dtype=np.float64).reshape(3, 3)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    world = np.asarray(bone_info["origin_mm"]) + (corners * (shape - 1) * spacing) @ rot.T
    centre = (world.min(axis=0) + world.max(axis=0)) / 2
    return round(float(centre[0]) - length_mm / 2, 2), round(float(centre[1]), 2)


#: After its first groove, --demo cuts another beside it this often (s), so the live view
#: has a groove being cut whenever someone opens it.
DEMO_EVERY_S = 6.0
#: Lanes of the later grooves, mm from the first (y); the bone is reset after the last.
DEMO_LANES_MM = (3.0, -3.0, 6.0, -6.0)


def run_demo(say, conn_path: Path, done: threading.Event, bone_info: dict | None,
              url: str, plane, session_id: int, after_first=lambda: None) -> None:
    """The demo's grooves on ``session_id``: one at once, then one every ``DEMO_EVERY_S``.
    They give the session's stream way to any other client (a person's `client demo`, an
    engine) and wait to go on until the session has had no other traffic for a whole
    interval: a session has one stream, and two clients taking it back and forth both lose
    their packets. ``after_first`` runs once the first groove's table is printed."""
    say(f"--demo: running `{burrforce_command()} client demo` against this server...")
    x_mm, y_mm = demo_start_mm(bone_info)
    code = _demo_groove(conn_path, done, x_mm, y_mm, quiet=False)
    after_first()
    if code is None:
        return
    say(f"--demo finished (exit {code}); the server keeps running.")
    say(f"--demo: watch it in the live view ({url}/ui/, the VIEW link above). A groove "
        f"beside the last every {DEMO_EVERY_S:.0f} s; the bone is reset after "
        f"{len(DEMO_LANES_MM) + 1} grooves. They give way to any other client on session "
        f"{session_id}.")
    paused = False

    def pause() -> None:
        nonlocal paused
        if not paused:
            say(f"--demo: another client streams on session {session_id}: the demo's grooves "
                f"wait until it has been quiet for {DEMO_EVERY_S:.0f} s")
        paused = True

    if code == EXIT_GAVE_WAY:
        pause()
    lane = 0
    seen = _session_traffic(plane, session_id)
    while not done.wait(DEMO_EVERY_S):
        now = _session_traffic(plane, session_id)
        if now is None or seen is None:
            # The session is (or was) being reloaded, its counters starting again: they say
            # nothing about this interval.
            seen = now
            continue
        if now != seen:  # someone else's packets while the demo waited
            seen = now
            pause()
            continue
        if paused:
            say(f"--demo: session {session_id} has been quiet for {DEMO_EVERY_S:.0f} s: the "
                "demo's grooves go on")
            paused = False
        if lane == len(DEMO_LANES_MM):
            lane = 0
            # As POST …/reset does: the bone reloaded from its source, uncarved.
            job = plane.reset(session_id)
            if not plane.wait(job, 60.0) or job.state != "done":
                say(f"--demo: stopped: could not reset the bone ({job.error or 'timed out'})")
                return
            code = _demo_groove(conn_path, done, x_mm, y_mm)
        else:
            code = _demo_groove(conn_path, done, x_mm, y_mm + DEMO_LANES_MM[lane])
            lane += 1
        if code is None:
            return
        if code == EXIT_GAVE_WAY:
            pause()
        elif code != 0:
            say(f"--demo: stopped: a groove failed (exit {code})")
            return
        seen = _session_traffic(plane, session_id)


def _session_traffic(plane, session_id: int) -> int | None:
    """The datagrams session ``session_id`` has taken so far (POSEs and hellos), or None
    while it cannot say (its bone being replaced)."""
    from ..api.errors import ApiError

    try:
        state = plane.session_state(session_id, max_events=0)
    except ApiError:  # while the session reloads: ask again next time
        return None
    return int(state["accepted"]) + int(state["hellos"])


def _demo_groove(conn_path: Path, done: threading.Event, x_mm: float, y_mm: float,
                 quiet: bool = True) -> int | None:
    """One `burrforce client demo` groove; its exit status, or None when the server stops."""
    env = dict(os.environ, BURRFORCE_CONNECTION=str(conn_path))
    out = subprocess.DEVNULL if quiet else None
    proc = subprocess.Popen([sys.executable, "-m", "burrforce.server.cli", "client", "demo",
                             "--x-mm", str(x_mm), "--y-mm", str(y_mm), "--give-way"],
                            env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=out)
    while proc.poll() is None:
        if done.wait(0.1):
            proc.terminate()
            proc.wait()
            return None
    # A signal to the whole process group (Ctrl-C in a terminal, `timeout`) ends the groove's
    # client before this process has set ``done``: a groove ended by the stop is no failure.
    if proc.returncode != 0 and done.wait(2.0):
        return None
    return proc.returncode
