"""The REST API's request and response bodies (pydantic: validated, documented in OpenAPI).

Units are in the field names: mm, N, rpm, N/mm² (= N·mm per mm³ removed), s.
"""

from __future__ import annotations

import math
import unicodedata
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator

from ...proto.frames import FRAMES
from ..haptics.profiles import PROFILE_NAMES

FrameName = Literal[tuple(FRAMES)]  # type: ignore[valid-type]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = Annotated[tuple[Finite, Finite, Finite], Field(description="x, y, z")]
#: Burr radii of surgical burrs (0.5–10 mm in diameter), mm.
BURR_RADIUS_MIN_MM = 0.25
BURR_RADIUS_MAX_MM = 5.0
#: The longest cutting head a surgical burr has, mm (long fissure burrs: ~10 mm).
BURR_LENGTH_MAX_MM = 20.0
#: A bone version (``since`` of deltas and meshes) is an int64.
MAX_BONE_VERSION = (1 << 63) - 1
#: The longest shaft a handpiece reaches with, mm (burr centre to the handpiece's nose).
SHAFT_LENGTH_MAX_MM = 200.0
#: A coordinate a POSE can reach (SPEC 3.1: positions within ±1e9 engine units).
Coord = Annotated[float, Field(allow_inf_nan=False, ge=-1e9, le=1e9)]
Point = Annotated[tuple[Coord, Coord, Coord], Field(description="x, y, z")]
Quat = Annotated[tuple[Finite, Finite, Finite, Finite], Field(description="x, y, z, w")]
SessionId = Annotated[int, Field(ge=0, le=(1 << 32) - 1)]


def no_control_characters(text: str) -> str:
    """``text`` unless it holds a control character (NUL, newline, escape, U+007F–U+009F):
    in a name they cut it short in C, split log lines and hide in a terminal."""
    bad = sorted({c for c in text if unicodedata.category(c) == "Cc"})
    if bad:
        raise ValueError("a name must not hold control characters; this one holds "
                         + ", ".join(f"U+{ord(c):04X}" for c in bad))
    return text


#: A name the user gives (a material's, an upload's file name): printable characters only.
PrintableText = Annotated[str, AfterValidator(no_control_characters)]
DeviceName = Literal[(*PROFILE_NAMES, "none")]  # type: ignore[valid-type]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class BoneRequest(Strict):
    """Which bone to load."""

    source: str = Field("phantom:temporal", max_length=1024, examples=[
        "phantom:temporal", "library:patients/0042/ct.nrrd", "upload:9f86d081884c7d65",
        "snapshot:before-mastoid"],
        description="phantom:NAME, library:PATH (in the configured bone library), upload:ID "
                    "(from POST /v1/uploads) or snapshot:NAME")
    kind: Literal["ct", "labels", "density"] | None = Field(
        None, description="what the voxels are; required for npy, npz, NRRD, NIfTI and PNG "
                          "(their voxels could mean any of the three)")
    voxel_mm: float | None = Field(None, gt=0.001, le=10.0, allow_inf_nan=False,
                                   description="a phantom's voxel size, mm")
    spacing_mm: Vec3 | None = Field(None, description="voxel size for npy and PNG files, mm")


class Features(Strict):
    """What a session's scene uses. Off is skipped in the hot loop, not computed and
    discarded."""

    model: bool = Field(True, description="the bone stage (carving and force); off answers "
                                          "with zero force (protocol only)")
    carving: bool = Field(True, description="remove bone (off: forces from the bone as is)")
    vibration: bool = Field(True, description="vibration amplitude and frequency")
    shaft: bool = Field(True, description="contact of the burr's shaft with bone")
    deltas: bool = Field(True, description="publish the bone to the control plane while it is "
                                           "cut (exports, deltas and snapshots of a session "
                                           "being cut); two integer writes per carving tick")
    coupling: bool | None = Field(None, description=(
        "the coupled output: a burr proxy integrated implicitly and a virtual coupling to "
        "the device (stable on any device at any cutting damping; the reply carries the "
        "coupling model). false: the raw model force. null: coupled when a device profile "
        "is set (parameters.device), raw otherwise"))


class DeviceLimits(Strict):
    """A custom device profile's limits (any subset; the rest from the base profile)."""

    max_force_N: Finite | None = Field(None, gt=0.0, le=1e4)
    max_stiffness_N_mm: Finite | None = Field(None, gt=0.0, le=1e4)
    max_damping_N_s_mm: Finite | None = Field(None, gt=0.0, le=100.0)
    max_slew_N_s: Finite | None = Field(None, gt=0.0, le=1e7)
    rated_hz: Finite | None = Field(None, gt=0.0, le=1e5, description=(
        "the update rate the stiffness is rated at"))
    resolution_mm: Finite | None = Field(None, gt=0.0, le=10.0, description=(
        "position resolution: the velocity estimator's noise bound"))


class Parameters(Strict):
    """A session's model, burr and engine parameters (PATCH: any subset)."""

    us_n_mm2: Finite | None = Field(None, ge=0.0, le=1e7, description=(
        "specific cutting energy Us of the session's primary material, N/mm²"))
    k: Finite | None = Field(None, ge=0.0, le=100.0, description=(
        "normal/tangential force ratio K of the primary material"))
    primary_material: int | None = Field(None, ge=1, le=255, description=(
        "the material label us_n_mm2 and k apply to (default: label 1 if the bone has it, "
        "else its first non-forbidden material)"))
    fd_N: Finite | None = Field(None, ge=0.0, le=1e3, description="vibration amplitude "
                                                                  "spinning free, N")
    g: Finite | None = Field(None, ge=0.0, le=1e3, description="vibration gain on |F_r|")
    harmonic: Finite | None = Field(None, gt=0.0, le=1e3, description=(
        "vibration frequency multiple of the rotation rate (1: grinding burr; flutes)"))
    radius_mm: Finite | None = Field(None, ge=BURR_RADIUS_MIN_MM, le=BURR_RADIUS_MAX_MM,
                                     description=(
        f"burr radius R, mm: {BURR_RADIUS_MIN_MM}–{BURR_RADIUS_MAX_MM}, the surgical burrs' "
        "0.5–10 mm diameters (a larger sphere would sweep away whole bones in one tick)"))
    burr: dict[str, Any] | None = Field(None, description=(
        "the burr's shape and cutter, e.g. {\"shape\": {\"kind\": \"cylinder\", "
        "\"radius_mm\": 1.0, \"length_mm\": 4.0, \"end\": \"round\"}, \"cutter\": "
        "{\"kind\": \"fluted\", \"n_flutes\": 6, \"helix_deg\": 20, \"rake_deg\": 0}}. "
        "Shapes: sphere (radius_mm), cylinder (radius_mm, length_mm, end flat|round), barrel "
        "(equator_radius_mm, end_radius_mm, length_mm); cutters: abrasive (default) or "
        "fluted (n_flutes, helix_deg, rake_deg, friction_deg — not calibrated against "
        "measurements). Changing it mid-stream is a tool change: the stream goes on. "
        "radius_mm follows the shape's largest radius; a fluted cutter sets the vibration "
        "harmonic to its flute count unless harmonic is given"))
    spin: Literal["forward", "reverse"] | None = None
    min_cutting_rpm: Finite | None = Field(None, ge=1.0, le=1e7, description=(
        "below this spindle speed the burr does not cut, rpm"))
    shaft_radius_mm: Finite | None = Field(None, ge=0.0, le=BURR_RADIUS_MAX_MM, description=(
        "shaft radius, mm; thinner than the burr"))
    shaft_length_mm: Finite | None = Field(None, ge=0.0, le=SHAFT_LENGTH_MAX_MM, description=(
        f"shaft length from the burr centre, mm (0: no shaft); a handpiece's reach is at "
        f"most {SHAFT_LENGTH_MAX_MM:g} mm"))
    shaft_stiffness_n_mm3: Finite | None = Field(None, ge=0.0, le=1e6)
    frame: FrameName | None = Field(None, description="the engine's frame and units")
    tool_axis: Vec3 | None = Field(None, description=(
        "tool axis (burr → handle) in the tool's local frame, engine axes"))
    placement_position: Point | None = Field(None, description=(
        "where the bone's world origin is in the engine's world, engine units (within ±1e9, "
        "the range of a POSE's position)"))
    placement_orientation: Quat | None = None
    device: DeviceName | None = Field(None, description=(
        "the haptic device the force is for: its force, stiffness and damping limits "
        "(generic, touch, falcon, omega3; custom: device_limits over the current profile or "
        "generic; none: no device, the raw force unlimited)"))
    device_limits: DeviceLimits | None = Field(None, description=(
        "custom limits (makes the profile custom)"))

    @field_validator("burr")
    @classmethod
    def _burr(cls, v):
        if v is not None:
            from ..model.shapes import Burr, profile_points
            shape = Burr.from_dict(v).shape  # ValueError: what is wrong with it
            if not BURR_RADIUS_MIN_MM <= shape.max_radius_mm <= BURR_RADIUS_MAX_MM:
                raise ValueError(
                    f"the burr's largest radius must be in [{BURR_RADIUS_MIN_MM}, "
                    f"{BURR_RADIUS_MAX_MM}] mm (the surgical burrs' sizes), got "
                    f"{shape.max_radius_mm:g}")
            z = profile_points(shape.profile())[:, 1]
            if z.max() - z.min() > BURR_LENGTH_MAX_MM:
                raise ValueError(f"the burr must be at most {BURR_LENGTH_MAX_MM:g} mm long, "
                                 f"got {z.max() - z.min():g}")
        return v

    @field_validator("tool_axis")
    @classmethod
    def _nonzero(cls, v):
        if v is not None and math.hypot(*v) < 1e-6:
            raise ValueError("tool_axis must not be zero")
        if v is not None and not math.isfinite(math.hypot(*v)):
            raise ValueError("tool_axis must be a direction whose length is finite (it is "
                             "normalized): scale it down")
        return v

    @field_validator("placement_orientation")
    @classmethod
    def _unit(cls, v):
        norm = None if v is None else math.hypot(*v)
        if norm is not None and norm < 1e-6:
            raise ValueError("placement_orientation must not be a zero quaternion")
        if norm is not None and not math.isfinite(norm):
            raise ValueError("placement_orientation must have a finite norm (it is "
                             "normalized): scale it down")
        return v


class SessionCreate(Strict):
    """A new session."""

    id: SessionId | None = Field(None, description="default: the lowest free id from 1")
    bone: BoneRequest = Field(default_factory=BoneRequest)
    authenticated: bool = Field(True, description=(
        "give the session a key (datagrams are tagged); false only for loopback development"))
    parameters: Parameters = Field(default_factory=Parameters)
    features: Features = Field(default_factory=Features)


class MaterialBody(Strict):
    name: PrintableText = Field(min_length=1, max_length=64)
    us_n_mm2: Finite = Field(ge=0.0, le=1e7)
    k: Finite = Field(ge=0.0, le=100.0)
    forbidden: bool = False


class MaterialPatch(Strict):
    name: PrintableText | None = Field(None, min_length=1, max_length=64)
    us_n_mm2: Finite | None = Field(None, ge=0.0, le=1e7)
    k: Finite | None = Field(None, ge=0.0, le=100.0)
    forbidden: bool | None = None


class RecordingStart(Strict):
    name: str | None = Field(None, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$",
                             description="default: session-ID-TIME")
    max_mb: float = Field(2048.0, gt=0.0, le=1 << 20, description="stop at this size, MB")


class SnapshotRequest(Strict):
    name: str | None = Field(None, pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,70}$",
                             description="default: session-ID-vVERSION-TIME")


class RestoreRequest(Strict):
    snapshot: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")


class CaseRowBody(Strict):
    """One replicate of the case table (docs/calibration.md): the case's geometry (model.md)
    and its mean force components on the burr."""

    orientation: Literal["parallel", "perpendicular", "diagonal"]
    angle_deg: Finite = Field(gt=0.0, le=90.0)
    depth_mm: Finite = Field(gt=0.0, le=200.0)
    feed_mm_s: Finite = Field(gt=0.0, le=1e5)
    rpm: Finite = Field(gt=0.0, le=1e7)
    radius_mm: Finite = Field(gt=0.0, le=100.0)
    feed_N: Finite = Field(ge=-1e4, le=1e4)
    lateral_N: Finite = Field(ge=-1e4, le=1e4)
    normal_N: Finite = Field(ge=-1e4, le=1e4)
    source: str | None = Field(None, max_length=256)


Component = Literal["feed", "lateral", "normal"]


class FitRequest(Strict):
    """Fit Us (and K) to a case table by linear least squares."""

    cases: list[CaseRowBody] = Field(min_length=2, max_length=20_000)
    fit: Literal["us", "us,k"] = Field("us,k", description="Us alone (K held at k) or both")
    k: Finite | None = Field(None, ge=0.0, le=100.0,
                             description="K held fixed when fit = 'us' (default 1.3, or the "
                                         "material's K when applying to a session)")
    components: list[Component] = Field(["feed", "lateral", "normal"], min_length=1,
                                         max_length=3)
    confidence: Finite = Field(0.95, gt=0.5, lt=1.0)
    intervals: Literal["replicate", "ols"] = Field(
        "replicate", description="replicate: robust to whole-run scatter between replicates; "
                                 "ols: observations independent")
    spin: Literal["forward", "reverse"] = Field(
        "forward", description="the drill's spin in the experiment")

    @field_validator("components")
    @classmethod
    def _distinct(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("components must be distinct")
        return value


class CalibrationApply(Strict):
    """Apply a calibration to a session's material: either a table to fit here (``fit``) or
    values fitted elsewhere (``us_n_mm2``, optionally ``k``, e.g. from ``burrforce calibrate
    --json``)."""

    label: int | None = Field(None, ge=1, le=255,
                              description="the material label (default the primary material)")
    fit: FitRequest | None = None
    us_n_mm2: Finite | None = Field(None, gt=0.0, le=1e7)
    k: Finite | None = Field(None, ge=0.0, le=100.0,
                             description="with us_n_mm2: the K to set (default: keep the "
                                         "material's)")
    provenance: dict[str, bool | int | float | str | list[int | float | str] | None] | None = Field(
        None, description="what to keep with the values (CI, RMSE, source), shown by GET")

    @field_validator("provenance")
    @classmethod
    def _small(cls, value: dict | None) -> dict | None:
        if value is not None and len(value) > 64:
            raise ValueError("provenance holds at most 64 entries")
        return value


class DeviceAttach(Strict):
    """A haptic device (and optionally a vibration actuator) to drive from a session, on the
    server's machine (docs/devices.md)."""

    device: str = Field(..., min_length=1, max_length=512, examples=[
        "falcon:firmware=/opt/novint/nvent_firmware.bin", "sim:hand=groove", "forcedimension"],
        description="NAME[:key=value,...]: sim, falcon, forcedimension, openhaptics, haply")
    actuator: str | None = Field(None, max_length=512, examples=["audio", "wav:path=cue.wav"],
                                 description="NAME[:key=value,...]: audio, usb, wav")
    placement_mm: Vec3 | None = Field(
        None, description="where the device's workspace centre lies in the bone's frame, mm "
                          "(default: the top centre of the bone's bounding box)")
    rotation: Quat = Field((0.0, 0.0, 0.0, 1.0),
                           description="the device frame's orientation in the bone's frame")
    workspace_scale: float = Field(1.0, ge=0.01, le=100.0,
                                   description="bone mm per device mm")
    rpm: float = Field(60_000.0, ge=-1e6, le=1e6, allow_inf_nan=False,
                       description="spindle speed sent with each pose")
    spindle: Literal["on", "off", "button"] = Field(
        "on", description="on, off, or on while the device's first button is held")
    home: bool = Field(True, description="home the device before streaming")
    stale_ms: float = Field(30.0, gt=0.0, le=50.0,
                            description="the watchdog: zero force when the newest reply is "
                                        "older than this")

    @field_validator("rotation")
    @classmethod
    def _unit(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        n = math.sqrt(sum(c * c for c in q))
        if not 0.5 <= n <= 1.5:
            raise ValueError(f"rotation must be a unit quaternion (norm {n:.3g})")
        return q


# -- answers ------------------------------------------------------------------------------------
#: A number as the server computed it: an int stays an int in the JSON (a float field would
#: turn 1 into 1.0).
Number = int | float


class Answer(BaseModel):
    """A response body: every key declared (a key the route adds but the model lacks fails
    loudly instead of vanishing)."""

    model_config = ConfigDict(extra="forbid")


class Progress(Answer):
    stage: str = Field(description="reading, checking, replaying the journal, sharing, "
                                   "starting")
    done: int
    total: int


class JobView(Answer):
    """A bone load: queued, running (with progress), done or failed (with why)."""

    id: str
    kind: str = Field(description="create, load, reset or restore")
    session: int
    source: str
    state: Literal["queued", "running", "done", "failed"]
    error: str | None
    progress: Progress
    created: float = Field(description="Unix time, s")
    finished: float | None = Field(description="Unix time, s; null while it runs")


class Endpoint(Answer):
    host: str
    port: int


class JournalView(Answer):
    """A session's journal: whether the last pass wrote everything, and what the last
    restart lost if its journal was damaged or behind."""

    state: Literal["off", "ok", "degraded"] = Field(
        description="off (no journal), ok, or degraded: it cannot be written (a full disk), "
                    "so a restart now would lose the carving since failing_since")
    written: float | None = Field(description="when a pass last wrote everything, Unix time, s")
    failing_since: float | None = Field(description="when the passes began to fail, Unix "
                                                    "time, s")
    error: str | None
    recovery: dict[str, Any] | None = Field(
        description="what resuming this session lost (bricks, removed_mm3, contacts, "
                    "summary, the damaged files kept); null: nothing")


class SessionView(Answer):
    """A session: its state, UDP endpoint, bone and what it renders."""

    id: int
    state: Literal["loading", "ready", "failed"]
    error: str | None
    job: str | None = Field(description="its latest bone load")
    udp: Endpoint = Field(description="where its engine streams (its worker's endpoint)")
    worker: int
    authenticated: bool
    source: str
    bone: dict[str, Any] | None = Field(description="the loaded bone: name, format, shape, "
                                                    "spacing_mm, origin_mm, generation, …")
    frame: str
    features: Features
    output: str = Field(description="raw or coupled")
    device: str | None
    device_attached: bool
    recording: str | None
    created: float = Field(description="Unix time, s")
    journal: JournalView = Field(description="how its journal stands: ok, degraded (cannot "
                                             "be written) or off, and what a restart lost")


class SessionCreated(SessionView):
    """A new session, with its key (shown only here; null: unauthenticated)."""

    key: str | None


class MaterialView(Answer):
    label: int
    name: str
    us_n_mm2: Number
    k: Number
    forbidden: bool


class PhantomEntry(Answer):
    source: str
    description: str
    default_voxel_mm: Number


class Uploaded(Answer):
    id: str
    source: str
    bytes: int
    filename: str


class UploadEntry(Answer):
    id: str
    source: str
    file: str
    bytes: int
    created: float
    in_use_by: list[int] = Field(description="sessions whose bone came from it")


class SnapshotEntry(Answer):
    name: str
    source: str
    bytes: int
    created: float


class SnapshotListed(SnapshotEntry):
    in_use_by: list[int] = Field(description="sessions whose bone came from it")


class RecordingEntry(Answer):
    name: str
    bytes: int
    files: int
    created: float
    modified: float
    complete: bool
    recording_session: int | None
    replay: str


class ExportEntry(Answer):
    name: str
    bytes: int
    created: float


class Deleted(Answer):
    deleted: str
    kind: str
    bytes: int
    in_use_by: list[int]
    note: str | None


class KindUsage(Answer):
    bytes: int
    items: int
    counted: bool
    list: str | None = None


class StorageReport(Answer):
    data_dir: str
    budget_bytes: int
    used_bytes: int
    reserved_bytes: int
    free_bytes: int | None
    disk_free_bytes: int | None
    kinds: dict[str, KindUsage]


class ParametersView(Answer):
    """A session's parameters (``GET``/``PATCH /v1/sessions/ID/parameters``)."""

    us_n_mm2: Number | None = Field(description="the primary material's Us, N/mm²")
    k: Number | None = Field(description="the primary material's K")
    primary_material: int | None
    primary_material_name: str | None
    fd_N: Number
    g: Number
    harmonic: Number
    burr: dict[str, Any]
    burr_calibrated: bool
    burr_profile_mm: list[list[Number]] = Field(
        description="the burr's generatrix, tip to top, as (ρ, z) mm in the tool frame")
    radius_mm: Number
    spin: str
    min_cutting_rpm: Number
    shaft_radius_mm: Number
    shaft_length_mm: Number
    shaft_stiffness_n_mm3: Number
    frame: str
    tool_axis: list[Number] | None
    placement_position: list[Number]
    placement_orientation: list[Number]
    device: str | None
    device_limits: dict[str, Any] | None
