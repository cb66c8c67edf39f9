"""A small typed client of the REST control plane (``burrforce serve``'s ``/v1`` API).

Forces stream over UDP (:class:`burrforce.client.BurrClient`); this client configures what
they are computed from: sessions, bones, parameters, features, materials, and fetches what
comes out: state, exports, brick deltas, snapshots, recordings, metrics. ::

    from burrforce.client.rest import BurrRest

    with BurrRest.from_connection() as api:       # the file `burrforce serve` wrote
        s = api.create_session("phantom:workpiece", voxel_mm=0.25)
        # ... stream poses to s["udp"] with session s["id"] and key s["key"] ...
        api.set_parameters(s["id"], us_n_mm2=1610.0, k=0.5)
        api.export_mesh(s["id"], "bone.stl")

Units are in the names, as in the API: mm, N, rpm, N/mm², s. Every method raises
:class:`RestError` when the server refuses (with its status and its ``detail``) or cannot be
reached (status 0). Needs ``httpx`` (``pip install burrforce[test]`` or ``pip install httpx``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np

from ..proto.bricks import decode_delta
from . import connection
from .rest_paths import API_PREFIX, CHUNK_BYTES, flag
from .rest_storage import StoredData

#: How long a call that waits for a bone load may take, s (the server waits up to 600 s).
LOAD_TIMEOUT_S = 600.0

VolumeFormat = Literal["nrrd", "npy"]
VolumeWhat = Literal["remaining", "labels", "swept", "density"]
MeshFormat = Literal["stl", "ply", "obj"]
BoneKind = Literal["ct", "labels", "density"]


class RestError(Exception):
    """The server refused a request, or could not be reached.

    Attributes:
        status: the HTTP status (0: no answer: connection refused, timed out, reset).
        detail: the server's explanation as one readable line (for a request the API's
            validation rejected: ``"body.radius_mm: Input should be greater than 0.001"``,
            one such part per problem, joined by ``"; "``).
        errors: the validation problems as the server sent them (a list of
            ``{"loc", "msg", "type"}``), empty for other errors.
        method, url: the request.
    """

    def __init__(self, status: int, detail: str, errors: Sequence[Mapping[str, Any]] = (),
                 method: str = "", url: str = "") -> None:
        self.status = status
        self.detail = detail
        self.errors = list(errors)
        self.method = method
        self.url = url
        where = f" ({method} {url})" if method else ""
        super().__init__(f"{status}: {detail}{where}" if status else f"{detail}{where}")


def _readable(detail: object) -> tuple[str, list]:
    """The server's ``detail`` as one line, and the validation errors if it was a list."""
    if isinstance(detail, list):
        parts = []
        for e in detail:
            if isinstance(e, Mapping):
                loc = ".".join(str(x) for x in e.get("loc", ()))
                parts.append(f"{loc}: {e.get('msg', '')}" if loc else str(e.get("msg", "")))
            else:
                parts.append(str(e))
        return "; ".join(parts) or "invalid request", [e for e in detail
                                                        if isinstance(e, Mapping)]
    return str(detail), []


class BurrRest(StoredData):
    """A client of one server's REST API.

    Args:
        url: the server's base URL, e.g. ``http://127.0.0.1:47811`` (a trailing ``/v1`` is
            accepted).
        token: the bearer token ``burrforce serve`` printed (or kept in DATA_DIR/token).
        timeout_s: connect, read and write timeout of one request, s.
        load_timeout_s: the read timeout of calls that wait for a bone load (create a
            session, load a bone, reset, restore with ``wait=True``), s.
        transport: an httpx transport (tests: ``httpx.ASGITransport(app)``); default: HTTP.
    """

    def __init__(self, url: str, token: str, timeout_s: float = 30.0, *,
                 load_timeout_s: float = LOAD_TIMEOUT_S,
                 transport: httpx.BaseTransport | None = None) -> None:
        base = url.rstrip("/")
        if base.endswith(API_PREFIX):
            base = base[: -len(API_PREFIX)]
        self.url = base
        self.timeout_s = float(timeout_s)
        self.load_timeout_s = float(load_timeout_s)
        self._http = httpx.Client(base_url=base, transport=transport,
                                  headers={"Authorization": f"Bearer {token}",
                                           "Accept": "application/json"},
                                  timeout=httpx.Timeout(self.timeout_s))

    @classmethod
    def from_connection(cls, path: str | Path | None = None,
                        timeout_s: float = 30.0) -> BurrRest:
        """The server a connection file describes (default: the one a local
        ``burrforce serve`` wrote; see :func:`burrforce.client.connection.default_path`).

        Raises:
            ValueError: no connection file, or one without a REST URL and token.
        """
        c = connection.read(Path(path) if path is not None else None)
        if not c.http_url or not c.token:
            raise ValueError("the connection file has no REST URL and token (written by an "
                             "older server?): give BurrRest(url, token)")
        return cls(c.http_url, c.token, timeout_s)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> BurrRest:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"BurrRest({self.url!r})"

    # -- plumbing -------------------------------------------------------------------------------
    def _send(self, method: str, path: str, *, stream: bool = False, wait: bool = False,
              **kwargs: Any) -> httpx.Response:
        """One request; non-2xx answers and transport failures become RestError. A streamed
        response must be closed by the caller."""
        if wait:
            kwargs["timeout"] = httpx.Timeout(self.timeout_s, read=max(self.timeout_s,
                                                                       self.load_timeout_s))
        request = self._http.build_request(method, path, **kwargs)
        try:
            response = self._http.send(request, stream=stream)
        except httpx.TimeoutException as exc:
            raise RestError(0, f"no answer from {self.url} in time ({type(exc).__name__})",
                            method=method, url=str(request.url)) from exc
        except httpx.TransportError as exc:
            raise RestError(0, f"cannot reach {self.url}: {exc}", method=method,
                            url=str(request.url)) from exc
        if response.is_success:
            return response
        try:
            response.read()
            body = response.json()
            detail = body["detail"] if isinstance(body, dict) and "detail" in body else body
        except (ValueError, httpx.HTTPError):
            detail = response.text.strip() or response.reason_phrase
        finally:
            response.close()
        text, errors = _readable(detail)
        raise RestError(response.status_code, text, errors, method, str(request.url))

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        response = self._send(method, API_PREFIX + path, **kwargs)
        if response.status_code == 204 or not response.content:
            return None
        return response.json()

    def _download(self, path: str, params: dict, target: str | Path) -> Path:
        """Stream a file answer to ``target`` (through ``target.part``, so a failed download
        leaves no partial file)."""
        target = Path(target)
        part = target.with_name(target.name + ".part")
        response = self._send("GET", API_PREFIX + path, params=params, stream=True)
        try:
            with open(part, "wb") as f:
                for chunk in response.iter_bytes(CHUNK_BYTES):
                    f.write(chunk)
            os.replace(part, target)
        except httpx.HTTPError as exc:
            raise RestError(0, f"the download from {self.url} broke off: {exc}", method="GET",
                            url=str(response.request.url)) from exc
        finally:
            response.close()
            part.unlink(missing_ok=True)
        return target

    # -- system ---------------------------------------------------------------------------------
    def health(self) -> dict:
        """Liveness (needs no token): ``status``, ``hot_loop``, ``version``, ``sessions``,
        ``udp`` {host, port}, ``packets_received``."""
        return self._json("GET", "/health")

    def metrics_text(self) -> str:
        """The Prometheus exposition text (packets by outcome, tick-time histogram in s,
        per-session counters, bone versions, removed volume in mm³)."""
        return self._send("GET", "/metrics").text

    # -- sessions -------------------------------------------------------------------------------
    def create_session(self, bone: str = "phantom:temporal", kind: BoneKind | None = None,
                       voxel_mm: float | None = None, parameters: Mapping[str, Any] | None = None,
                       features: Mapping[str, bool] | None = None, authenticated: bool = True,
                       wait: bool = True, *, id: int | None = None,
                       spacing_mm: Sequence[float] | None = None) -> dict:
        """Create a session on a bone.

        Args:
            bone: ``phantom:NAME``, ``library:PATH``, ``upload:ID`` (see :meth:`upload`) or
                ``snapshot:NAME``.
            kind: what a file's voxels are (``ct``, ``labels``, ``density``); required for
                npy, npz, NRRD, NIfTI and PNG.
            voxel_mm: a phantom's voxel size, mm.
            parameters: initial parameters (the fields of :meth:`set_parameters`).
            features: initial features (the fields of :meth:`set_features`).
            authenticated: give the session a key (datagrams are tagged); False only for
                loopback development.
            wait: answer when the bone is loaded (else at once, state ``loading``; follow
                ``job`` with :meth:`wait_for_job`).
            id: the session id (default: the lowest free one from 1).
            spacing_mm: voxel size of npy and PNG files (x, y, z), mm.

        Returns:
            The session: ``id``, ``key`` (hex; shown only here), ``udp`` {host, port},
            ``state``, ``job``, ``bone`` (shape, spacing_mm, origin_mm, …), ``features``, …

        Raises:
            RestError: 404 when the source does not exist, 400 for a library path outside
                the library, 422 when the request is invalid or the bone cannot be loaded,
                409 when ``id`` is taken.
        """
        body: dict[str, Any] = {"bone": _bone_request(bone, kind, voxel_mm, spacing_mm),
                                "authenticated": authenticated,
                                "parameters": _jsonable(dict(parameters or {})),
                                "features": dict(features or {})}
        if id is not None:
            body["id"] = id
        return self._json("POST", "/sessions", json=body, params={"wait": flag(wait)},
                          wait=wait)

    def sessions(self) -> list[dict]:
        """Every session (without keys), by id."""
        return self._json("GET", "/sessions")

    def session(self, session_id: int) -> dict:
        """One session: state, bone, features, UDP endpoint, recording."""
        return self._json("GET", f"/sessions/{int(session_id)}")

    def delete_session(self, session_id: int) -> None:
        """Remove the session (its datagrams then get UNKNOWN_SESSION notices)."""
        self._json("DELETE", f"/sessions/{int(session_id)}")

    def reset(self, session_id: int, wait: bool = True) -> dict:
        """Reload the bone from its source (uncarved; Us and K set here are kept) and start a
        new stream. Returns the load job (see :meth:`job`)."""
        return self._json("POST", f"/sessions/{int(session_id)}/reset",
                          params={"wait": flag(wait)}, wait=wait)

    def restart_stream(self, session_id: int) -> None:
        """Forget the stream's sequence and velocity: the next datagram starts a new stream."""
        self._json("POST", f"/sessions/{int(session_id)}/restart-stream")

    def load_bone(self, session_id: int, source: str, kind: BoneKind | None = None,
                  voxel_mm: float | None = None, spacing_mm: Sequence[float] | None = None,
                  wait: bool = True) -> dict:
        """Load another bone into the session (the stream continues on it). Arguments as in
        :meth:`create_session`. Returns the load job; a failed load leaves the old bone (the
        job's ``state`` is ``failed``, its ``error`` says why)."""
        return self._json("PUT", f"/sessions/{int(session_id)}/bone",
                          json=_bone_request(source, kind, voxel_mm, spacing_mm),
                          params={"wait": flag(wait)}, wait=wait)

    def job(self, job_id: str) -> dict:
        """A bone load: ``state`` (queued, running, done, failed), ``error``, ``progress``
        {stage, done, total}."""
        return self._json("GET", f"/jobs/{job_id}")

    def wait_for_job(self, job_id: str, timeout_s: float = LOAD_TIMEOUT_S,
                     poll_s: float = 0.05) -> dict:
        """Poll :meth:`job` until it is done or failed (at most ``timeout_s``, s).

        Raises:
            TimeoutError: still queued or running after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            j = self.job(job_id)
            if j["state"] not in ("queued", "running"):
                return j
            if time.monotonic() >= deadline:
                raise TimeoutError(f"job {job_id} is still {j['state']} after {timeout_s} s "
                                   f"({j['progress']})")
            time.sleep(poll_s)

    # -- parameters, features, materials --------------------------------------------------------
    def parameters(self, session_id: int) -> dict:
        """The session's parameters: ``us_n_mm2`` (N/mm²) and ``k`` of the primary material,
        ``fd_N``, ``g``, ``harmonic``, ``radius_mm``, ``spin``, ``min_cutting_rpm``,
        ``shaft_radius_mm``, ``shaft_length_mm``, ``shaft_stiffness_n_mm3``, ``frame``,
        ``tool_axis``, ``placement_position`` (engine units), ``placement_orientation``
        (x, y, z, w)."""
        return self._json("GET", f"/sessions/{int(session_id)}/parameters")

    def set_parameters(self, session_id: int, **fields: Any) -> dict:
        """Change any subset of :meth:`parameters` (e.g. ``us_n_mm2=1610.0, k=0.5``); all or
        nothing. Returns the parameters after the change.

        Raises:
            RestError: 422 for a value out of range or an unknown field (``detail`` names
                it).
        """
        return self._json("PATCH", f"/sessions/{int(session_id)}/parameters",
                          json=_jsonable(fields))

    def features(self, session_id: int) -> dict:
        """What the session's scene uses: ``model``, ``carving``, ``vibration``, ``shaft``,
        ``deltas``, ``coupling`` (booleans)."""
        return self._json("GET", f"/sessions/{int(session_id)}/features")

    def set_features(self, session_id: int, **fields: bool) -> dict:
        """Turn features on or off (e.g. ``vibration=False``); the others keep their state
        (read first, then written whole: not atomic against another writer). Returns the
        features after the change."""
        current = self.features(session_id)
        return self._json("PUT", f"/sessions/{int(session_id)}/features",
                          json={**current, **fields})

    # -- devices on the server's machine ------------------------------------------------------
    def devices(self) -> list[dict]:
        """Every supported haptic device and actuator back-end, whether it is ready, and the
        units detected on the server's machine (docs/devices.md)."""
        return self._json("GET", "/devices")

    def attach_device(self, session_id: int, device: str, **fields: Any) -> dict:
        """Drive ``device`` (``NAME[:key=value,...]``) from the session; ``fields``:
        ``actuator``, ``placement_mm``, ``rotation``, ``workspace_scale``, ``rpm``,
        ``spindle``, ``home``, ``stale_ms``. Returns the device loop's status.

        Raises:
            RestError: 409 when the session already drives a device, 422 for a bad spec or
                a device this machine cannot open (``detail`` says why).
        """
        return self._json("PUT", f"/sessions/{int(session_id)}/device",
                          json=_jsonable({"device": device, **fields}))

    def device_status(self, session_id: int) -> dict:
        """The device loop's state, counters, measured rates and recent events."""
        return self._json("GET", f"/sessions/{int(session_id)}/device")

    def detach_device(self, session_id: int) -> dict:
        """Stop the device loop (zero force, device released); its final status."""
        return self._json("DELETE", f"/sessions/{int(session_id)}/device")

    def materials(self, session_id: int) -> list[dict]:
        """The material table: ``label``, ``name``, ``us_n_mm2`` (N/mm²), ``k``,
        ``forbidden``."""
        return self._json("GET", f"/sessions/{int(session_id)}/materials")

    def set_material(self, session_id: int, label: int, *, name: str | None = None,
                     us_n_mm2: float | None = None, k: float | None = None,
                     forbidden: bool | None = None, replace: bool = False) -> dict:
        """Change material ``label`` (1..255): the fields given (PATCH), or with
        ``replace=True`` set it whole (PUT: ``name``, ``us_n_mm2`` and ``k`` required; adds a
        label the bone lacks). Returns the material."""
        fields = {k_: v for k_, v in (("name", name), ("us_n_mm2", us_n_mm2), ("k", k),
                                      ("forbidden", forbidden)) if v is not None}
        return self._json("PUT" if replace else "PATCH",
                          f"/sessions/{int(session_id)}/materials/{int(label)}", json=fields)

    def fit_calibration(self, cases: Sequence[Mapping[str, Any]], *, fit: str = "us,k",
                        k: float | None = None, components: Sequence[str] | None = None,
                        confidence: float = 0.95, intervals: str = "replicate",
                        spin: str = "forward") -> dict:
        """Fit Us (and K) to a case table on the server (``POST /v1/calibration/fit``):
        ``cases`` are rows with orientation, angle_deg, depth_mm, feed_mm_s, rpm, radius_mm,
        feed_N, lateral_N, normal_N; ``intervals`` "replicate" (robust to whole-run scatter) or
        "ols"; ``spin`` the drill's in the experiment. Returns what ``burrforce calibrate
        --json`` prints."""
        return self._json("POST", "/calibration/fit", json=_fit_body(
            cases, fit, k, components, confidence, intervals, spin))

    def apply_calibration(self, session_id: int, *, label: int | None = None,
                          us_n_mm2: float | None = None, k: float | None = None,
                          cases: Sequence[Mapping[str, Any]] | None = None,
                          fit: str = "us,k",
                          provenance: Mapping[str, Any] | None = None,
                          components: Sequence[str] | None = None, confidence: float = 0.95,
                          intervals: str = "replicate", spin: str = "forward") -> dict:
        """Set a material's Us and K from a calibration (``POST
        /v1/sessions/{id}/calibration``): values fitted elsewhere (``us_n_mm2``, ``k``, with
        ``provenance`` kept beside them, e.g. the fit's CI and RMSE), or ``cases`` to fit on the
        server (``fit`` = "us" or "us,k"; ``k`` then is the K held fixed by "us"; the other
        options as :meth:`fit_calibration`). ``label`` defaults to the primary material."""
        body: dict[str, Any] = {"label": label}
        if cases is not None:
            body["fit"] = _fit_body(cases, fit, k, components, confidence, intervals, spin)
        else:
            body.update(us_n_mm2=us_n_mm2, k=k, provenance=provenance)
        return self._json("POST", f"/sessions/{int(session_id)}/calibration",
                          json=_jsonable({k_: v for k_, v in body.items() if v is not None}))

    def calibrations(self, session_id: int) -> dict:
        """The calibrations applied to a session, by material label."""
        return self._json("GET", f"/sessions/{int(session_id)}/calibration")

    def state(self, session_id: int, max_events: int = 100) -> dict:
        """Bone version, removed volume per material (mm³), the latest ``max_events``
        forbidden-contact events, counters, tick-time quantiles (µs)."""
        return self._json("GET", f"/sessions/{int(session_id)}/state",
                          params={"max_events": int(max_events)})

    # -- exports --------------------------------------------------------------------------------
    def export_volume(self, session_id: int, path: str | Path, format: VolumeFormat = "nrrd",
                      what: VolumeWhat = "remaining") -> Path:
        """Download the carved volume to ``path`` (streamed): ``remaining`` bone 0–255,
        ``labels``, ``swept`` or the original ``density``. NRRD carries the geometry (LPS,
        mm) and the bone version; npy is the bare uint8 array. Returns ``path``."""
        return self._download(f"/sessions/{int(session_id)}/export/volume",
                              {"format": format, "what": what}, path)

    def export_mesh(self, session_id: int, path: str | Path, format: MeshFormat = "stl",
                    step: int = 1, level: float = 0.5,
                    materials: Sequence[int] | None = None) -> Path:
        """Download the carved bone's surface (marching cubes at iso-level ``level`` of the
        bone fraction, every ``step`` voxels, only ``materials`` labels if given) in the
        bone's world frame, mm. Returns ``path``."""
        params: dict[str, Any] = {"format": format, "step": int(step), "level": float(level)}
        if materials is not None:
            params["material"] = [int(m) for m in materials]
        return self._download(f"/sessions/{int(session_id)}/export/mesh", params, path)

    def deltas(self, session_id: int, since: int | None = None, max_bricks: int = 4096,
               generation: int | None = None) -> dict:
        """The 8³-voxel bricks changed since bone version ``since`` of bone ``generation``
        (``since`` None: every brick with bone, ``full``).

        Returns the message of ``burrforce.server.bone.deltas`` (format
        ``burrforce-bricks`` 1) with ``bricks`` as int32 (count, 3) brick indices and
        ``remaining`` as uint8 (count, 8, 8, 8) remaining densities: brick (a, b, c) covers
        voxels [8a:8a+8, 8b:8b+8, 8c:8c+8]. Ask next with ``since=next_since`` and
        ``generation=`` the message's ``generation``. When ``full`` is set (the bone was
        replaced: a reset, load or restore) set the whole copy to 0 first (of
        ``grid_shape``) — ``deltas.apply_delta`` does — and keep the new generation; on
        ``reload`` fetch the whole volume (:meth:`export_volume`).

        Raises:
            RestError: 409 when the session has deltas off; status 0 for an answer that is
                not such a message.
        """
        params = {"max_bricks": int(max_bricks)}
        if since is not None:
            params["since"] = int(since)
        if generation is not None:
            params["generation"] = int(generation)
        response = self._send("GET", f"{API_PREFIX}/sessions/{int(session_id)}/deltas",
                              params=params)
        try:
            return decode_delta(response.content)
        except ValueError as exc:
            raise RestError(0, str(exc), method="GET", url=str(response.request.url)) from None

    def mesh_chunks(self, session_id: int, **query: Any) -> bytes:
        """One page of the carved bone's chunk meshes (proto/MESH.md; decode it with
        ``burrforce.proto.mesh_chunks.decode``, or keep a copy with
        ``burrforce.client.mesh.sync_rest``). ``query``: since, chunk_bricks, frame,
        winding, cursor, max_bytes.

        Raises:
            RestError: 409 when the session is not ready or has deltas off, 422 for a bad
                parameter.
        """
        return self._send("GET", f"{API_PREFIX}/sessions/{int(session_id)}/mesh",
                          params=query).content

    # -- bones ----------------------------------------------------------------------------------
    def phantoms(self) -> list[dict]:
        """Built-in bones: ``source`` (``phantom:NAME``), ``description``,
        ``default_voxel_mm``."""
        return self._json("GET", "/phantoms")

    def library(self) -> list[dict]:
        """Bone files in the server's library: ``source`` (``library:PATH``), ``format``,
        ``folder``, ``bytes``, ``needs_kind``."""
        return self._json("GET", "/library")



def _fit_body(cases: Sequence[Mapping[str, Any]], fit: str, k: float | None,
              components: Sequence[str] | None, confidence: float, intervals: str,
              spin: str) -> dict:
    body: dict[str, Any] = {"cases": [dict(c) for c in cases], "fit": fit,
                            "confidence": confidence, "intervals": intervals, "spin": spin}
    if k is not None:
        body["k"] = k
    if components is not None:
        body["components"] = list(components)
    return _jsonable(body)


def _bone_request(source: str, kind: str | None, voxel_mm: float | None,
                  spacing_mm: Sequence[float] | None) -> dict:
    body: dict[str, Any] = {"source": source}
    if kind is not None:
        body["kind"] = kind
    if voxel_mm is not None:
        body["voxel_mm"] = float(voxel_mm)
    if spacing_mm is not None:
        body["spacing_mm"] = [float(x) for x in spacing_mm]
    return body


def _jsonable(value: Any) -> Any:
    """Tuples and numpy values as JSON types (a pose or axis may come as a numpy array)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


__all__ = ["BurrRest", "RestError"]
