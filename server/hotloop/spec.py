"""What a hot-loop worker is asked to run: its sessions (``SessionSpec``) and its socket
(``HotLoopConfig``), and how a spec becomes a live ``Session`` (``build_session``).

Both specs are frozen values the control plane builds and pickles across the pipe to the loop
process (``handle``); the child (``child``) and the command table (``commands``) build the
sessions. Nothing here touches a process or a socket.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..bone import Bone, BoneEngine, MaterialTable, ShaftParams, load_bone, phantom
from ..bone.loaders import LoadOptions
from ..bone.shared import SharedBone, SharedBoneRef
from ..model.params import CuttingParams
from .session import Session
from .session_config import SessionConfig
from .telemetry import TelemetrySlot

PHANTOM_PREFIX = "phantom:"
#: The bone ``burrforce serve`` loads when none is named.
DEFAULT_BONE = "phantom:temporal"


@dataclass(frozen=True)
class SessionSpec:
    """A session to create: which bone, which burr, which engine conventions, which key.

    Attributes:
        session_id: unsigned 32-bit id the client puts in every datagram.
        bone: ``phantom:NAME`` (``bone.PHANTOMS``), a bone file's path, or a bone the
            control plane has loaded into shared memory (``bone.shared.SharedBoneRef``).
        voxel_mm: a phantom's voxel size, mm (None: the phantom's default).
        key: the session key; None only for loopback development (no tags).
        config: frame, tool axis, features (``SessionConfig``).
        params: burr radius, spin, minimum cutting speed.
        shaft: the shaft's geometry.
        materials: the material table (None: the bone's own).
        publish: for a shared bone, keep the counters that let the control plane read it
            while it is cut.
        next_stream: the first stream number the session offers (None: a random one).
        telemetry: a telemetry file the control plane created and reads
            (``hotloop.telemetry``): the session's per-packet state lives in it. None:
            private memory.
    """

    session_id: int = 1
    bone: str | SharedBoneRef = DEFAULT_BONE
    voxel_mm: float | None = None
    key: bytes | None = None
    config: SessionConfig = field(default_factory=SessionConfig)
    params: CuttingParams = field(default_factory=CuttingParams)
    shaft: ShaftParams = field(default_factory=ShaftParams)
    materials: MaterialTable | None = None
    publish: bool = True
    next_stream: int | None = None
    telemetry: str | None = None


def load_session_bone(spec: SessionSpec) -> Bone:
    """The bone ``spec`` names: a shared bone mapped writable, a phantom, or a bone file.

    Raises:
        ValueError: ``voxel_mm`` given for a file, or a bad phantom name or bone file.
    """
    if isinstance(spec.bone, SharedBoneRef):
        return SharedBone(spec.bone, writable=True).bone()
    if spec.bone.startswith(PHANTOM_PREFIX):
        return phantom(spec.bone[len(PHANTOM_PREFIX):], spec.voxel_mm)
    if spec.voxel_mm is not None:
        raise ValueError("voxel_mm sets a phantom's voxel size, not a file's")
    return load_bone(Path(spec.bone), LoadOptions())


def build_session(spec: SessionSpec) -> Session:
    """A session as ``spec`` says, not yet serving: a loop installs it (and then calls
    ``Session.publish_telemetry``).

    Raises:
        ValueError: a bad bone, burr, key or stream number.
    """
    if isinstance(spec.bone, SharedBoneRef):
        # The shared bone's own tally: removal and contacts survive this loop.
        shared = SharedBone(spec.bone, writable=True)
        bone, tally = shared.bone(), shared.tally
    else:
        bone, tally = load_session_bone(spec), None
    materials = spec.materials if spec.materials is not None else bone.materials
    engine = BoneEngine(bone.grid, materials, spec.params, spec.shaft, tally=tally)
    telemetry = TelemetrySlot(spec.telemetry) if spec.telemetry is not None else None
    session = Session(spec.session_id, engine, spec.config, spec.key,
                      next_stream=spec.next_stream, telemetry=telemetry)
    session.publish_bone(spec.publish)
    return session


def bone_info(session: Session) -> dict:
    """What a client may want to know of a session's bone: its voxel size, mm."""
    return {"voxel_mm": float(min(session.engine.grid.spacing_mm))}
