"""Bones and what comes out of sessions: phantoms, the library, uploads, load jobs, exports,
brick deltas, snapshots and recordings."""

from __future__ import annotations

import os
import re
import secrets
import tempfile
from pathlib import Path as FilePath
from typing import Literal

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from ...proto.bricks import encode_delta
from ..bone import PHANTOMS
from ..bone.deltas import MAX_BRICKS_LIMIT, brick_delta
from ..bone.export import VOLUME_MEDIA_TYPES, write_volume
from ..bone.mesh import MESH_FORMATS, surface_mesh
from ..bone.phantoms import PHANTOM_VOXEL_MM
from .manager import ApiError, ControlPlane
from .models import RecordingStart, RestoreRequest, SnapshotRequest
from .routes_sessions import SessionPath, _plane, wait_for
from .sources import snapshot_path

router = APIRouter()
UPLOAD_SUFFIX = re.compile(r"(\.bone\.npz|\.seg\.nrrd|\.nii\.gz|\.[A-Za-z0-9]{1,5})$")
DELTA_MEDIA_TYPE = "application/x-msgpack"


# -- bones ------------------------------------------------------------------------------------
@router.get("/phantoms", tags=["bones"])
def phantoms() -> list[dict]:
    """Built-in bones: ``phantom:NAME`` sources."""
    return [{"source": f"phantom:{name}", "description": text,
             "default_voxel_mm": PHANTOM_VOXEL_MM[name]} for name, text in PHANTOMS.items()]


@router.get("/library", tags=["bones"])
def library(request: Request) -> list[dict]:
    """Bone files and series folders in the configured library (``library:PATH`` sources)."""
    from .sources import library_entries

    return library_entries(_plane(request).roots.library)


@router.post("/uploads", status_code=201, tags=["bones"],
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string",
                                                         "format": "binary"}}}}})
async def upload(request: Request,
                 filename: str = Query(..., min_length=1, max_length=200,
                                       description="the file's name; its suffix tells the "
                                                   "format (.nrrd, .nii.gz, .npy, …)")) -> dict:
    """Upload one bone file as the raw request body (``curl --data-binary @ct.nrrd``). DICOM
    series and PNG stacks are folders: put them in the bone library instead. The answer's
    ``source`` loads it into a session."""
    plane = _plane(request)
    match = UPLOAD_SUFFIX.search(FilePath(filename).name)
    if match is None:
        raise ApiError(422, f"{filename!r} has no file suffix to tell its format")
    limit = plane.config.upload_max_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(413, f"the upload is {int(declared):,} bytes; the limit is {limit:,} "
                            "(serve's upload_max_mb)")
    upload_id = secrets.token_hex(8)
    final = plane.roots.uploads / (upload_id + match.group(1).lower())
    fd, tmp = tempfile.mkstemp(prefix=".upload-", dir=plane.roots.uploads)
    size = 0
    try:
        with os.fdopen(fd, "wb") as f:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise ApiError(413, f"the upload exceeds the limit of {limit:,} bytes "
                                        "(serve's upload_max_mb)")
                f.write(chunk)
        if size == 0:
            raise ApiError(422, "the upload is empty")
        os.replace(tmp, final)
    finally:
        FilePath(tmp).unlink(missing_ok=True)
    return {"id": upload_id, "source": f"upload:{upload_id}", "bytes": size,
            "filename": FilePath(filename).name}


@router.get("/jobs/{job_id}", tags=["bones"])
def job(request: Request, job_id: str = Path(pattern=r"^[0-9a-f]{16}$")) -> dict:
    """A bone load's state: queued, running (with progress), done or failed (with why)."""
    plane = _plane(request)
    found = plane.jobs.get(job_id)
    if found is None:
        raise ApiError(404, f"no job {job_id}")
    return found.public()


# -- exports ----------------------------------------------------------------------------------
def _file_response(path: FilePath, media_type: str, filename: str) -> FileResponse:
    return FileResponse(path, media_type=media_type, filename=filename,
                        background=BackgroundTask(path.unlink, missing_ok=True))


def _export_file(plane: ControlPlane, suffix: str) -> FilePath:
    fd, name = tempfile.mkstemp(prefix="export-", suffix=suffix,
                                dir=plane.data_dir / "exports")
    os.close(fd)
    return FilePath(name)


@router.get("/sessions/{session_id}/export/volume", tags=["exports"],
            response_class=FileResponse)
def export_volume(request: Request, session_id: int = SessionPath,
                  format: Literal["nrrd", "npy"] = Query("nrrd"),
                  what: Literal["remaining", "labels", "swept", "density"] = Query(
                      "remaining", description="remaining bone 0–255 (carving applied), "
                                               "labels, swept, or the original density")
                  ) -> FileResponse:
    """The carved volume as it is now (a consistent copy; the loop keeps running). NRRD
    carries the geometry (LPS mm); npy is the bare uint8 array."""
    plane = _plane(request)
    bone = plane.snapshot_bone(session_id)
    media, suffix = VOLUME_MEDIA_TYPES[format]
    path = _export_file(plane, suffix)
    with open(path, "wb") as f:
        write_volume(bone.grid, f, format, what)
    return _file_response(path, media, f"session-{session_id}-v{bone.grid.version}-{what}"
                                       f"{suffix}")


@router.get("/sessions/{session_id}/export/mesh", tags=["exports"],
            response_class=FileResponse)
def export_mesh(request: Request, session_id: int = SessionPath,
                format: Literal["stl", "ply", "obj"] = Query("stl"),
                level: float = Query(0.5, gt=0.0, lt=1.0,
                                     description="iso-level of the bone fraction"),
                step: int = Query(1, ge=1, le=16, description="marching-cubes step, voxels"),
                material: list[int] | None = Query(None, description="only these labels"),
                ) -> FileResponse:
    """The carved bone's surface by marching cubes, in the bone's world frame (mm)."""
    plane = _plane(request)
    bone = plane.snapshot_bone(session_id)
    try:
        mesh = surface_mesh(bone.grid, level=level, step=step, labels=material)
    except ValueError as exc:
        raise ApiError(422, str(exc)) from None
    writer, media, suffix = MESH_FORMATS[format]
    path = _export_file(plane, suffix)
    with open(path, "wb") as f:
        writer(mesh, f)
    return _file_response(path, media, f"session-{session_id}-v{bone.grid.version}{suffix}")


@router.get("/sessions/{session_id}/deltas", tags=["exports"],
            responses={200: {"content": {DELTA_MEDIA_TYPE: {}}}})
def deltas(request: Request, session_id: int = SessionPath,
           since: int = Query(..., ge=0, description="the bone version the client has"),
           max_bricks: int = Query(4096, ge=1, le=MAX_BRICKS_LIMIT)) -> Response:
    """The 8³ bricks changed since bone version ``since``, with their remaining density
    (msgpack; format in ``burrforce.server.bone.deltas``), so an engine can update its own
    mesh of the bone."""
    plane = _plane(request)
    session = plane.ready(session_id)
    if not session.features.deltas:
        raise ApiError(409, "the session has deltas off")
    reader = session.reader
    assert reader is not None
    try:
        d = reader.read_published(lambda grid: brick_delta(grid, since, max_bricks))
    except ValueError as exc:
        raise ApiError(422, str(exc)) from None
    except TimeoutError as exc:
        raise ApiError(503, str(exc)) from None
    return Response(encode_delta(d), media_type=DELTA_MEDIA_TYPE)


# -- snapshots ------------------------------------------------------------------------------
@router.post("/sessions/{session_id}/snapshot", status_code=201, tags=["snapshots"])
def snapshot(request: Request, body: SnapshotRequest | None = None,
             session_id: int = SessionPath) -> dict:
    """Save the session's bone as it is now (``.bone.npz``, with what was carved); restore it
    into any session with ``snapshot:NAME``."""
    return _plane(request).save_snapshot(session_id, body.name if body else None)


@router.get("/snapshots", tags=["snapshots"])
def snapshots(request: Request) -> list[dict]:
    return _plane(request).list_snapshots()


@router.get("/snapshots/{name}", tags=["snapshots"], response_class=FileResponse)
def download_snapshot(request: Request,
                      name: str = Path(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
                      ) -> FileResponse:
    plane = _plane(request)
    path = snapshot_path(plane.roots.snapshots, name)
    if not path.is_file():
        raise ApiError(404, f"no snapshot {name!r}")
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.post("/sessions/{session_id}/restore", status_code=202, tags=["snapshots"])
def restore(body: RestoreRequest, request: Request, session_id: int = SessionPath,
            wait: bool = Query(True)) -> dict:
    """Load a snapshot into the session (its carving included)."""
    plane = _plane(request)
    source = plane.resolve(f"snapshot:{body.snapshot}")
    job = plane.load_bone(session_id, source, "restore")
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


# -- recordings -----------------------------------------------------------------------------
@router.post("/sessions/{session_id}/recording", status_code=201, tags=["recordings"])
def start_recording(request: Request, body: RecordingStart | None = None,
                    session_id: int = SessionPath) -> dict:
    """Record the session's stream (poses, engine inputs, forces, removals) from now on;
    ``burrforce replay`` re-runs it offline."""
    body = body or RecordingStart()
    return _plane(request).start_recording(session_id, body.name,
                                           int(body.max_mb * (1 << 20)))


@router.get("/sessions/{session_id}/recording", tags=["recordings"])
def recording_status(request: Request, session_id: int = SessionPath) -> dict:
    status = _plane(request).recording_status(session_id)
    if status is None:
        raise ApiError(404, f"session {session_id} is not recording")
    return status


@router.delete("/sessions/{session_id}/recording", tags=["recordings"])
def stop_recording(request: Request, session_id: int = SessionPath) -> dict:
    return _plane(request).stop_recording(session_id)


@router.get("/recordings", tags=["recordings"])
def recordings(request: Request) -> list[dict]:
    return _plane(request).list_recordings()
