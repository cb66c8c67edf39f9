"""Bones and what comes out of sessions: phantoms, the library, uploads, load jobs, exports,
brick deltas, snapshots and recordings, and the storage they take (``storage``)."""

from __future__ import annotations

import re
from pathlib import Path as FilePath
from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from starlette.background import BackgroundTask

from ...proto.bricks import encode_delta
from ..bone import PHANTOMS
from ..bone.deltas import MAX_BRICKS_LIMIT, brick_delta
from ..bone.export import VOLUME_MEDIA_TYPES, write_volume
from ..bone.loaders import write_bone
from ..bone.mesh import MESH_FORMATS, surface_mesh
from ..bone.phantoms import PHANTOM_VOXEL_MM
from ..record import RecordingError
from ..report import report_from_recording
from .archive import TAR_MEDIA_TYPE
from .deps import PlaneDep, SessionPath, wait_for
from .errors import Conflict, Invalid, NotFound, TooLarge
from .generation import bone_generation
from .models import (
    MAX_BONE_VERSION,
    Deleted,
    ExportEntry,
    JobView,
    PhantomEntry,
    PrintableText,
    RecordingEntry,
    RecordingStart,
    RestoreRequest,
    SnapshotEntry,
    SnapshotListed,
    SnapshotRequest,
    StorageReport,
    Uploaded,
    UploadEntry,
)
from .report_http import REPORT_RESPONSES, ReportFormat, ReportThreshold, report_response
from .sources import library_entries

router = APIRouter()
UPLOAD_SUFFIX = re.compile(r"(\.bone\.npz|\.seg\.nrrd|\.nii\.gz|\.[A-Za-z0-9]{1,5})$")
DELTA_MEDIA_TYPE = "application/x-msgpack"
#: The burrforce bone file a volume export's ``format=bone`` writes (``save_bone``).
BONE_MEDIA_TYPE = ("application/octet-stream", ".bone.npz")
#: Response headers naming the bone state an export holds (an npy file cannot say it).
GENERATION_HEADER = "X-Burrforce-Bone-Generation"
VERSION_HEADER = "X-Burrforce-Bone-Version"
#: The most an npy export's header takes (format 1.0 pads it to a multiple of 64; a 3-D
#: uint8 array's fits in 128).
NPY_HEADER_BYTES = 128
#: A binary STL: an 80-byte header and a facet count, then 50 bytes a facet.
STL_HEADER_BYTES, STL_FACET_BYTES = 84, 50


# -- bones ------------------------------------------------------------------------------------
DELETE_FORCE = ("delete it even though a session's bone came from it (the session keeps its "
                "bone, but its reset, and resuming it after a crash or restart, will fail)")

@router.get("/phantoms", tags=["bones"], response_model=list[PhantomEntry])
def phantoms() -> list[dict]:
    """Built-in bones: ``phantom:NAME`` sources."""
    return [{"source": f"phantom:{name}", "description": text,
             "default_voxel_mm": PHANTOM_VOXEL_MM[name]} for name, text in PHANTOMS.items()]


@router.get("/library", tags=["bones"])
def library(plane: PlaneDep) -> list[dict]:
    """Bone files and series folders in the configured library (``library:PATH`` sources)."""
    return library_entries(plane.roots.library)


@router.post("/uploads", status_code=201, tags=["bones"], response_model=Uploaded,
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string",
                                                         "format": "binary"}}}}})
async def upload(request: Request, plane: PlaneDep,
                 filename: Annotated[PrintableText, Query(
                     min_length=1, max_length=200,
                     description="the file's name; its suffix tells the format (.nrrd, "
                                 ".nii.gz, .npy, …); no control characters")]) -> dict:
    """Upload one bone file as the raw request body (``curl --data-binary @ct.nrrd``). DICOM
    series and PNG stacks are folders: put them in the bone library instead. The answer's
    ``source`` loads it into a session."""
    match = UPLOAD_SUFFIX.search(FilePath(filename).name)
    if match is None:
        raise Invalid(f"{filename!r} has no file suffix to tell its format")
    limit = plane.config.upload_max_bytes
    declared = request.headers.get("content-length")
    declared_bytes = int(declared) if declared is not None and declared.isdigit() else None
    if declared_bytes is not None and declared_bytes > limit:
        raise TooLarge(f"the upload is {declared_bytes:,} bytes; the limit is {limit:,} "
                       "(serve's upload_max_mb)")
    upload_id, size = await plane.storage.receive_upload(
        request.stream(), match.group(1).lower(), limit, declared_bytes)
    return {"id": upload_id, "source": f"upload:{upload_id}", "bytes": size,
            "filename": FilePath(filename).name}


UploadName = Path(description="the upload's id (``upload:ID`` without ``upload:``)")


@router.get("/uploads", tags=["storage"], response_model=list[UploadEntry])
def uploads(plane: PlaneDep) -> list[dict]:
    """Uploaded bone files: ``id``, ``source``, ``file``, ``bytes``, ``created`` (Unix s) and
    ``in_use_by`` (sessions whose bone came from it)."""
    return plane.storage.list_uploads()


@router.get("/uploads/{name:path}", tags=["storage"], response_class=FileResponse)
def download_upload(plane: PlaneDep, name: str = UploadName) -> FileResponse:
    """The uploaded file as it was sent."""
    path = plane.storage.upload_file(name)
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.delete("/uploads/{name:path}", tags=["storage"], response_model=Deleted)
def delete_upload(plane: PlaneDep, name: str = UploadName,
                  force: bool = Query(False, description=DELETE_FORCE)) -> dict:
    """Delete an upload; 409 while a bone load reads it, and while a session's bone came
    from it unless ``force`` (those sessions keep their bone; ``in_use_by`` and ``note``
    say which, and that their reset and resume after a restart will fail)."""
    return plane.storage.delete_upload(name, force)


@router.get("/storage", tags=["storage"], response_model=StorageReport,
             response_model_exclude_unset=True)
def storage_usage(plane: PlaneDep) -> dict:
    """The data directory's usage: ``bytes`` and ``items`` per kind (uploads, snapshots,
    recordings, exports being served; the journal is shown but not ``counted``), the budget
    (``budget_bytes``, 0: none; serve's ``--data-budget``), ``used_bytes``, ``reserved_bytes``
    (room running recordings may still fill) and ``free_bytes``. A write that does not fit
    is refused: an upload with 413, a snapshot, export or recording start with 507."""
    return plane.storage.report()


@router.get("/jobs/{job_id}", tags=["bones"], response_model=JobView)
def job(plane: PlaneDep, job_id: str = Path(pattern=r"^[0-9a-f]{16}$")) -> dict:
    """A bone load's state: queued, running (with progress), done or failed (with why)."""
    found = plane.jobs.get(job_id)
    if found is None:
        raise NotFound(f"no job {job_id}")
    return found.public()


# -- exports ----------------------------------------------------------------------------------
def _file_response(path: FilePath, media_type: str, filename: str,
                   headers: dict[str, str] | None = None) -> FileResponse:
    return FileResponse(path, media_type=media_type, filename=filename, headers=headers,
                        background=BackgroundTask(path.unlink, missing_ok=True))


def _state_headers(generation: int | None, version: int) -> dict[str, str]:
    out = {VERSION_HEADER: str(int(version))}
    if generation is not None:
        out[GENERATION_HEADER] = str(int(generation))
    return out


@router.get("/sessions/{session_id}/export/volume", tags=["exports"],
            response_class=FileResponse)
def export_volume(plane: PlaneDep, session_id: int = SessionPath,
                  format: Literal["nrrd", "npy", "bone"] = Query(
                      "nrrd", description="nrrd, npy (one array each), or bone: the whole "
                                          "bone as a burrforce .bone.npz (density, carving, "
                                          "labels and the material table), which loads "
                                          "back as it was (upload it)"),
                  what: Literal["remaining", "labels", "swept", "density"] | None = Query(
                      None, description="nrrd and npy: remaining bone 0–255 (carving "
                                        "applied, the default), labels, swept, or the "
                                        "original density; bone holds them all")
                  ) -> FileResponse:
    """The carved volume as it is now (a consistent copy; the loop keeps running). NRRD
    carries the geometry (LPS mm); npy is the bare uint8 array; bone keeps everything,
    materials included. The headers X-Burrforce-Bone-Generation and -Version say which bone
    state it is (a client continues with deltas from them)."""
    if format == "bone" and what is not None:
        raise Invalid("format=bone holds every array (density, swept, labels): leave "
                      "what out")
    what = what or "remaining"
    generation = bone_generation(plane.ready(session_id))  # before the bone: generation.py
    bone = plane.snapshot_bone(session_id)
    headers = _state_headers(generation, bone.grid.version)
    if format == "bone":
        media, suffix = BONE_MEDIA_TYPE
        path = plane.storage.write_export(suffix, lambda f: write_bone(bone, f, generation))
        return _file_response(path, media, f"session-{session_id}-v{bone.grid.version}"
                                           f"{suffix}", headers)
    media, suffix = VOLUME_MEDIA_TYPES[format]
    # An npy file's size is known before it is written (its header and one byte a voxel):
    # a disk without room for it is told so before anything is written.
    needed = NPY_HEADER_BYTES + int(bone.grid.density.size) if format == "npy" else None
    path = plane.storage.write_export(
        suffix, lambda f: write_volume(bone.grid, f, format, what, generation=generation),
        needed)
    return _file_response(path, media, f"session-{session_id}-v{bone.grid.version}-{what}"
                                       f"{suffix}", headers)


@router.get("/sessions/{session_id}/export/mesh", tags=["exports"],
            response_class=FileResponse)
def export_mesh(plane: PlaneDep, session_id: int = SessionPath,
                format: Literal["stl", "ply", "obj"] = Query("stl"),
                level: float = Query(0.5, gt=0.0, lt=1.0,
                                     description="iso-level of the bone fraction"),
                step: int = Query(1, ge=1, le=16, description="marching-cubes step, voxels"),
                material: list[int] | None = Query(None, description="only these labels"),
                ) -> FileResponse:
    """The carved bone's surface by marching cubes, in the bone's world frame (mm)."""
    bone = plane.snapshot_bone(session_id)
    try:
        mesh = surface_mesh(bone.grid, level=level, step=step, labels=material)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    writer, media, suffix = MESH_FORMATS[format]
    needed = STL_HEADER_BYTES + STL_FACET_BYTES * mesh.n_faces if format == "stl" else None
    path = plane.storage.write_export(suffix, lambda f: writer(mesh, f), needed)
    return _file_response(path, media, f"session-{session_id}-v{bone.grid.version}{suffix}")


@router.get("/exports", tags=["exports", "storage"], response_model=list[ExportEntry])
def exports(plane: PlaneDep) -> list[dict]:
    """Export files still in the data directory: ``name``, ``bytes``, ``created`` (Unix s).
    An export is deleted once it was sent; one whose download was cut off stays (until the
    server restarts) and is deleted here."""
    return plane.storage.list_exports()


@router.delete("/exports/{name:path}", tags=["exports", "storage"], response_model=Deleted)
def delete_export(plane: PlaneDep, name: str = Path(description="the export's name, as "
                                                                "``GET /v1/exports`` lists it"
                                                    )) -> dict:
    """Delete an export file (one still being downloaded goes on being sent)."""
    return plane.storage.delete_export(name)


@router.get("/sessions/{session_id}/deltas", tags=["exports"],
            responses={200: {"content": {DELTA_MEDIA_TYPE: {}}}})
def deltas(plane: PlaneDep, session_id: int = SessionPath,
           since: int | None = Query(None, ge=0, le=MAX_BONE_VERSION,
                                     description="the bone version the client "
                                                             "has; omitted: every brick "
                                                             "(full)"),
           generation: int | None = Query(None, ge=0, le=(1 << 63) - 1,
                                          description="the bone generation the client's "
                                                      "copy is of; another one than the "
                                                      "bone's: every brick (full)"),
           max_bricks: int = Query(4096, ge=1, le=MAX_BRICKS_LIMIT)) -> Response:
    """The 8³ bricks changed since bone version ``since`` of bone ``generation``, with their
    remaining density (msgpack; format in ``burrforce.server.bone.deltas``), so an engine can
    update its own mesh of the bone. A copy of another generation (the bone was reset,
    reloaded or restored) gets a full answer: clear the copy and start over."""
    session = plane.ready(session_id)
    if not session.features.deltas:
        raise Conflict("the session has deltas off")
    current = bone_generation(session)  # before the reader: generation.py
    d = session.read_bone(lambda grid: brick_delta(grid, since, max_bricks, current,
                                                   generation))
    return Response(encode_delta(d), media_type=DELTA_MEDIA_TYPE)


# -- snapshots ------------------------------------------------------------------------------
@router.post("/sessions/{session_id}/snapshot", status_code=201, tags=["snapshots"],
             response_model=SnapshotEntry)
def snapshot(plane: PlaneDep, body: SnapshotRequest | None = None,
             session_id: int = SessionPath) -> dict:
    """Save the session's bone as it is now (``.bone.npz``, with what was carved); restore it
    into any session with ``snapshot:NAME``."""
    return plane.save_snapshot(session_id, body.name if body else None)


SnapshotName = Path(description="the snapshot's name (``.bone.npz`` may be left off)")


@router.get("/snapshots", tags=["snapshots", "storage"],
            response_model=list[SnapshotListed])
def snapshots(plane: PlaneDep) -> list[dict]:
    """Saved snapshots: ``name``, ``source``, ``bytes``, ``created`` (Unix s) and
    ``in_use_by`` (sessions whose bone came from it)."""
    return plane.storage.list_snapshots()


@router.get("/snapshots/{name:path}", tags=["snapshots", "storage"],
            response_class=FileResponse)
def download_snapshot(plane: PlaneDep, name: str = SnapshotName) -> FileResponse:
    """The snapshot's ``.bone.npz`` file."""
    path = plane.storage.snapshot_file(name)
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.delete("/snapshots/{name:path}", tags=["snapshots", "storage"],
               response_model=Deleted)
def delete_snapshot(plane: PlaneDep, name: str = SnapshotName,
                    force: bool = Query(False, description=DELETE_FORCE)) -> dict:
    """Delete a snapshot; 409 while a restore or load reads it, and while a session's bone
    came from it unless ``force`` (as for uploads)."""
    return plane.storage.delete_snapshot(name, force)


@router.post("/sessions/{session_id}/restore", status_code=202, tags=["snapshots"],
             response_model=JobView)
def restore(body: RestoreRequest, plane: PlaneDep, session_id: int = SessionPath,
            wait: bool = Query(True)) -> dict:
    """Load a snapshot into the session (its carving included)."""
    source = plane.resolve(f"snapshot:{body.snapshot}")
    job = plane.load_bone(session_id, source, "restore")
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


# -- recordings -----------------------------------------------------------------------------
@router.post("/sessions/{session_id}/recording", status_code=201, tags=["recordings"])
def start_recording(plane: PlaneDep, body: RecordingStart | None = None,
                    session_id: int = SessionPath) -> dict:
    """Record the session's stream (poses, engine inputs, forces, removals) from now on;
    ``burrforce replay`` re-runs it offline."""
    body = body or RecordingStart()
    return plane.start_recording(session_id, body.name,
                                           int(body.max_mb * (1 << 20)))


@router.get("/sessions/{session_id}/recording", tags=["recordings"])
def recording_status(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    status = plane.recording_status(session_id)
    if status is None:
        raise NotFound(f"session {session_id} is not recording")
    return status


@router.delete("/sessions/{session_id}/recording", tags=["recordings"])
def stop_recording(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    return plane.stop_recording(session_id)


RecordingName = Path(description="the recording's name (``.burrrec`` may be left off)")


@router.get("/recordings", tags=["recordings", "storage"],
            response_model=list[RecordingEntry])
def recordings(plane: PlaneDep) -> list[dict]:
    """Recordings: ``name``, ``bytes``, ``files``, ``created``, ``modified`` (Unix s),
    ``complete`` (it has its summary), ``recording_session`` (the session writing it, or
    null) and the ``replay`` command."""
    return plane.storage.list_recordings()


# Before the download route, whose ``{name:path}`` would take ``NAME/report`` as a name.
@router.get("/recordings/{name}/report", tags=["recordings"], responses=REPORT_RESPONSES)
def recording_report(plane: PlaneDep, name: str = RecordingName,
                     format: Literal["json", "html"] = ReportFormat,
                     threshold_n: float = ReportThreshold) -> Response:
    """A session report of the recording: duration, time cutting, bone removed per material,
    forbidden contacts (time, structure, position), the hand force (peak, mean in contact,
    time above ``threshold_n``) and its plot. The recording is replayed for the volumes and
    contacts, on a worker thread: about as much CPU time as the session took to compute (a
    10 s groove at 1 kHz: 2.5–3.3 s on a shared 2-core machine; other routes stay served).
    A recording still being written is reported as far as it goes (``complete`` false).
    404: no such recording; 422: a bad threshold, or a recording that cannot be replayed."""
    path = plane.storage.recording_dir(name)
    try:
        report = report_from_recording(path, threshold_n)
    except RecordingError as exc:
        raise Invalid(f"recording {path.name!r}: {exc.problem}") from None
    return report_response(report, format)


@router.get("/recordings/{name:path}", tags=["recordings", "storage"],
            response_class=StreamingResponse,
            responses={200: {"description": "the recording's directory as one uncompressed "
                                            "tar archive (members ``NAME.burrrec/...``; "
                                            "``tar xf`` it, then ``burrforce replay``)",
                             "content": {TAR_MEDIA_TYPE: {"schema": {
                                 "type": "string", "format": "binary"}}}},
                       409: {"description": "a session is still writing it"}})
def download_recording(plane: PlaneDep, name: str = RecordingName) -> StreamingResponse:
    """A recording (a ``.burrrec`` directory) as one **tar** archive, streamed: its rows
    hardly compress, and a tar's length is known before it is sent. 409 while a session
    writes it: stop that recording first."""
    archive = plane.storage.recording_archive(name)
    return StreamingResponse(archive.chunks(), media_type=TAR_MEDIA_TYPE, headers={
        "Content-Length": str(archive.size_bytes),
        "Content-Disposition": f'attachment; filename="{archive.filename}"'})


@router.delete("/recordings/{name:path}", tags=["recordings", "storage"],
               response_model=Deleted)
def delete_recording(plane: PlaneDep, name: str = RecordingName) -> dict:
    """Delete a recording; 409 while a session writes it (stop it first with ``DELETE
    /v1/sessions/ID/recording``)."""
    return plane.storage.delete_recording(name)
