"""What ``burrforce compile`` runs to fill numba's cache: jobs, each the code path a command
takes on first use, so exactly the signatures the server asks for are compiled.

Jobs are independent unless one names another in ``after`` (it then loads what that one
compiled instead of compiling it too), so ``compile_run`` runs them in parallel processes.
:data:`FIRST_START` is what a hot loop needs before it serves a round burr: ``serve``
compiles those first and the rest behind the running server.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Job:
    """One group of kernels: ``run`` compiles (or loads) them; ``kernels`` is about how many
    numba compiles on an empty cache (``numba:compile`` events, nested ones included: the
    progress bar's scale; ``tests/test_compile_cache.py`` checks it); ``after``: jobs whose
    kernels this one calls; ``longest``: the job a first start waits for, the others fitting
    beside it (``compile_run`` runs them at a lower priority)."""

    name: str
    run: Callable[[], None]
    kernels: int
    after: tuple[str, ...] = ()
    longest: bool = False


@contextmanager
def _shared_workpiece() -> Iterator[object]:
    """A reference to a small bone in shared memory, as the control plane hands one to a
    hot loop (the tick's arrays then have the types they have there)."""
    from ..bone import phantom
    from ..bone.shared import publish, run_directory

    folder = run_directory()
    try:
        yield publish(phantom("workpiece", 0.5), folder, "compile")
    finally:  # the map outlives the file: unlinking it now is safe
        shutil.rmtree(folder, ignore_errors=True)


def _tick(params) -> None:
    from ..hotloop.spec import SessionSpec, build_session

    with _shared_workpiece() as ref:
        build_session(SessionSpec(bone=ref, params=params)).engine.warm_up(every_burr=False)


def _tick_round() -> None:
    """The bone tick for the round abrasive burr (the default session's): its carve first,
    which needs no bone, while :data:`TICK_ROUND_PARTS` builds the bone in another process
    (``bone.tick_parts``)."""
    from ..bone.tick_parts import compile_parts, round_tick_first_parts
    from ..model.params import CuttingParams

    compile_parts(round_tick_first_parts())
    _tick(CuttingParams())


def _tick_round_parts() -> None:
    """Beside :data:`TICK_ROUND`, which loads what this compiles: the bone it warms the tick
    on (a session on the shared workpiece, without a tick), then the kernels the tick
    reaches last (``bone.tick_parts``)."""
    from ..bone.tick_parts import compile_parts, round_tick_last_parts
    from ..hotloop.spec import SessionSpec, build_session
    from ..model.params import CuttingParams

    with _shared_workpiece() as ref:
        build_session(SessionSpec(bone=ref, params=CuttingParams()))
    compile_parts(round_tick_last_parts())


def _tick_other_burrs() -> None:
    """The bone tick for every other burr (one set of types for all of them)."""
    from ..model.params import CuttingParams
    from ..model.shapes import Burr, Fluted, Sphere

    params = CuttingParams()
    _tick(params.with_(burr=Burr(Sphere(params.radius_mm), Fluted(n_flutes=6))))


def _packet_path() -> None:
    """The packet codec and the haptic stage: what a hot loop runs around the tick."""
    from ..haptics.stage import warm_up as warm_haptics
    from ..hotloop import wire

    wire.warm_up()
    warm_haptics()


def _sessions() -> None:
    """A hot loop's session on a bone in shared memory: every path of a packet but the tick
    (decode, tag, the stages around the tick, encode), which :data:`TICK_ROUND` compiles in
    another process meanwhile (the model is off, so no packet ticks); and the control plane's
    reads of that bone (status, snapshots for exports and the journal)."""
    from ..bone.shared import SharedBone
    from ..hotloop.dispatch import Dispatcher
    from ..hotloop.session_config import SessionConfig
    from ..hotloop.spec import SessionSpec, build_session

    with _shared_workpiece() as ref:
        dispatcher = Dispatcher()
        session = build_session(SessionSpec(bone=ref, config=SessionConfig(model=False)))
        dispatcher.add(session)
        dispatcher.warm_up(ticks=False)
        # Called after a tick that removed bone, by Python, not by the tick: compiled here,
        # where there is time to spare, the tick's job finds it in the cache (~1 s less).
        session.engine.removed_this_tick_mm3()
        del dispatcher, session
        reader = SharedBone(ref)
        reader.snapshot().grid.bone_volume_by_label_mm3()
        reader.close()


def _phantoms() -> None:
    from ..bone import PHANTOMS, phantom

    for name in PHANTOMS:
        phantom(name)


def _meshes() -> None:
    from ..bone import phantom
    from ..bone.mesh import surface_mesh

    grid = phantom("workpiece", 0.5).grid
    surface_mesh(grid, step=2)
    surface_mesh(grid, step=1, labels=[1])


def _bone_files() -> None:
    """CT (int16 HU), label (uint8) and density (float32) volumes, as the loaders read them."""
    from ..bone import LoadOptions, load_bone

    rng = np.random.default_rng(0)
    volumes = {"ct": rng.integers(-1000, 2000, (12, 12, 12)).astype(np.int16),
               "labels": rng.integers(0, 3, (12, 12, 12)).astype(np.uint8),
               "density": rng.random((12, 12, 12)).astype(np.float32)}
    with tempfile.TemporaryDirectory(prefix="burrforce-compile-") as folder:
        for kind, volume in volumes.items():
            path = Path(folder) / f"{kind}.npy"
            np.save(path, volume)
            load_bone(path, LoadOptions(kind=kind, spacing_mm=(0.2, 0.2, 0.2)))


def _model() -> None:
    """The cutting model alone (``experiment``, ``bench model``), round and other burrs."""
    from ..model import CuttingModel, CuttingParams
    from ..model.revolved import RevolvedModel
    from ..model.shapes import Burr, Cylinder, Fluted

    centre, axis = np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.0, 1.0])
    feed = np.array([1.0, 0.0, 0.0])
    CuttingModel(CuttingParams()).evaluate(centre, axis, feed, 80_000.0)
    RevolvedModel(Burr(Cylinder(1.0, 4.0), Fluted(6))).evaluate(centre, axis, feed, 80_000.0)


def _device_loop() -> None:
    from ..devices.falcon.device import _commands_for_force, _sense
    from ..devices.render import CouplingRenderer
    from ..haptics.profiles import PROFILES

    CouplingRenderer(PROFILES["generic"]).warm_up()
    grip_m = np.array([0.0, 0.0, 0.11])  # near the Falcon's workspace centre
    _sense(np.zeros(3), grip_m.copy())
    _commands_for_force(grip_m, np.zeros(3))


def _recordings() -> None:
    """A replay and a report of a short recording (``burrforce replay``, ``report``, the
    REST report): the tick there runs on a bone loaded from the recording's snapshot, whose
    arrays numba types apart from a hot loop's shared ones; every burr's tick on it."""
    from ...proto.messages import Pose
    from ..bone import BoneEngine, phantom
    from ..hotloop import Session
    from ..record import start_recording
    from ..report import report_from_recording

    bone = phantom("workpiece", 0.5)
    session = Session(1, BoneEngine(bone.grid, bone.materials))
    with tempfile.TemporaryDirectory(prefix="burrforce-compile-") as folder:
        recorder = start_recording(session, Path(folder) / "compile")
        for seq in range(1, 4):  # 0.5 mm into the workpiece's top face (z = 0), cutting
            pose = Pose(1, seq, seq * 1000, (5.0 + 0.02 * seq, 0.0, -0.5),
                        (0.0, 0.0, 0.0, 1.0), 60_000.0, True, None, 0)
            session.admit(pose.seq)
            session.respond(pose, seq * 1_000_000)
        recorder.close()
        report_from_recording(recorder.path)
        BoneEngine(bone.grid, bone.materials).warm_up(every_burr=True)


TICK_ROUND = "tick, round burr"
TICK_ROUND_PARTS = "tick, round burr: its bone and last parts"
PACKET_PATH = "packets and haptics"
SESSIONS = "sessions"
RECORDINGS = "recordings and reports"
BUILT_IN_PHANTOMS = "phantoms"

#: In the order a server needs them (a free process takes the first job ready). The round
#: tick's bone and last parts come second, to be cached before the tick needs them; the
#: phantoms next, so that ``serve`` loads their kernels while the tick still compiles.
JOBS: tuple[Job, ...] = (
    Job(TICK_ROUND, _tick_round, 88, longest=True),
    Job(TICK_ROUND_PARTS, _tick_round_parts, 29),
    Job(BUILT_IN_PHANTOMS, _phantoms, 6),
    Job(PACKET_PATH, _packet_path, 31),
    Job(SESSIONS, _sessions, 21, after=(PACKET_PATH,)),
    Job("tick, other burrs", _tick_other_burrs, 40, after=(TICK_ROUND,)),
    Job("surface meshes", _meshes, 1),
    Job("bone files", _bone_files, 9),
    Job("cutting model", _model, 24),
    Job("device loop", _device_loop, 55),
    Job(RECORDINGS, _recordings, 156),
)
#: What a first ``serve`` compiles before it is ready: a hot loop serving a round burr, and
#: the built-in phantoms (the default bone is one). The round tick takes longest; on two
#: cores the others follow one another in a second process meanwhile, in this order (a free
#: process takes the first one ready): the tick's bone and last parts first (the tick loads
#: them: they balance the two processes), then as in :data:`JOBS`.
FIRST_START: tuple[str, ...] = (TICK_ROUND, TICK_ROUND_PARTS, BUILT_IN_PHANTOMS, PACKET_PATH,
                                SESSIONS)
