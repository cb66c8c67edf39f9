"""The REST client's calls on what a server stores: uploads, snapshots, recordings and
their reports, exports, and the data budget (``GET /v1/storage``). :class:`StoredData` is
mixed into :class:`burrforce.client.rest.BurrRest`, whose plumbing (``_json``, ``_send``,
``_download``) its methods use."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .rest_paths import API_PREFIX, CHUNK_BYTES, bare_upload_id, flag, quoted, snapshot_name


class StoredData:
    """Uploads, snapshots, recordings, reports, exports and storage (see :class:`BurrRest`)."""

    def upload(self, path: str | Path, filename: str | None = None) -> str:
        """Upload one bone file (streamed; its suffix tells the format) and return its source
        (``upload:ID``) for :meth:`create_session` or :meth:`load_bone`.

        Raises:
            RestError: 413 over the server's limit, 422 without a known suffix or empty.
        """
        path = Path(path)
        size = path.stat().st_size

        def chunks() -> Iterator[bytes]:
            with open(path, "rb") as f:
                while chunk := f.read(CHUNK_BYTES):
                    yield chunk

        answer = self._json("POST", "/uploads", params={"filename": filename or path.name},
                            content=chunks(),
                            headers={"Content-Type": "application/octet-stream",
                                     "Content-Length": str(size)})
        return answer["source"]

    # -- snapshots ------------------------------------------------------------------------------
    def snapshot(self, session_id: int, name: str | None = None) -> dict:
        """Save the session's bone as it is now; returns ``name``, ``source``
        (``snapshot:NAME``), ``bytes``, ``created``."""
        return self._json("POST", f"/sessions/{int(session_id)}/snapshot",
                          json={"name": name} if name is not None else {})

    def snapshots(self) -> list[dict]:
        """The saved snapshots."""
        return self._json("GET", "/snapshots")

    def download_snapshot(self, name: str, path: str | Path) -> Path:
        """Download snapshot ``name`` (a ``.bone.npz``) to ``path``."""
        return self._download(f"/snapshots/{quoted(snapshot_name(name))}", {}, path)

    def delete_snapshot(self, name: str, force: bool = False) -> dict:
        """Delete snapshot ``name`` (``NAME`` or ``snapshot:NAME``). Returns ``deleted``,
        ``bytes`` freed, ``in_use_by`` (sessions whose bone came from it: they keep it, but
        their reset, and their resume after a restart, would fail) and a ``note`` saying so.
        Such a file is deleted only with ``force`` (else 409).

        Raises:
            RestError: 404 when there is no such snapshot, 400 for a name that is not a plain
                name, 409 while a bone load reads it.
        """
        query = "?force=true" if force else ""
        return self._json("DELETE", f"/snapshots/{quoted(snapshot_name(name))}{query}")

    def restore(self, session_id: int, snapshot: str, wait: bool = True) -> dict:
        """Load snapshot ``snapshot`` (``NAME`` or ``snapshot:NAME``) into the session, its
        carving included. Returns the load job."""
        return self._json("POST", f"/sessions/{int(session_id)}/restore",
                          json={"snapshot": snapshot_name(snapshot)},
                          params={"wait": flag(wait)}, wait=wait)

    # -- recordings -----------------------------------------------------------------------------
    def start_recording(self, session_id: int, name: str | None = None,
                        max_mb: float | None = None) -> dict:
        """Record the session's stream from now on (``burrforce replay`` re-runs it); it stops
        at ``max_mb`` MB (server default 2048). Returns ``name``, ``path``, …"""
        body: dict[str, Any] = {}
        if name is not None:
            body["name"] = name
        if max_mb is not None:
            body["max_mb"] = float(max_mb)
        return self._json("POST", f"/sessions/{int(session_id)}/recording", json=body)

    def recording(self, session_id: int) -> dict:
        """The running recording's status (404 when the session is not recording)."""
        return self._json("GET", f"/sessions/{int(session_id)}/recording")

    def stop_recording(self, session_id: int) -> dict:
        """Stop recording; returns what was recorded."""
        return self._json("DELETE", f"/sessions/{int(session_id)}/recording")

    def recordings(self) -> list[dict]:
        """The recordings on the server: ``name``, ``bytes``, ``files``, ``created``,
        ``modified`` (Unix s), ``complete``, ``recording_session`` (the session writing it,
        or None) and ``replay``."""
        return self._json("GET", "/recordings")

    def download_recording(self, name: str, path: str | Path) -> Path:
        """Download recording ``name`` (``NAME`` or ``NAME.burrrec``) to ``path`` as one
        uncompressed tar archive of its ``NAME.burrrec/`` directory (unpack it with
        ``tarfile`` or ``tar xf``, then ``burrforce replay``).

        Raises:
            RestError: 404 when there is no such recording, 409 while a session writes it.
        """
        return self._download(f"/recordings/{quoted(name)}", {}, path)

    def recording_report(self, name: str, threshold_n: float | None = None) -> dict:
        """The session report of recording ``name``: ``duration_s``, ``cutting_s``,
        ``removed_mm3_by_material``, ``forbidden_contacts`` (``time_s``, ``material``,
        ``position_mm``), ``hand_force_peak_N``, ``hand_force_mean_N``,
        ``time_above_threshold_s`` for ``threshold_n`` (server default 2 N), the plotted
        ``series``, … (the server replays the recording: about as long as it lasted).

        Raises:
            RestError: 404 when there is no such recording, 422 for a bad threshold.
        """
        params = {} if threshold_n is None else {"threshold_n": float(threshold_n)}
        return self._json("GET", f"/recordings/{quoted(name)}/report", params=params,
                          wait=True)

    def session_report(self, session_id: int, format: str = "json",
                       threshold_n: float | None = None) -> dict | str:
        """Live session ``session_id``'s report, as :meth:`recording_report`'s (a dict), or
        with ``format="html"`` the self-contained page (str). The hand force and cutting
        time come from the server's 100 Hz sampling of the session (its ``notes`` say so).

        Raises:
            RestError: 404 when there is no such session, 409 while it is not ready, 422
                for a bad threshold or format, 503 without live telemetry on the server.
        """
        params: dict[str, Any] = {"format": format}
        if threshold_n is not None:
            params["threshold_n"] = float(threshold_n)
        path = f"/sessions/{int(session_id)}/report"
        if format == "html":
            return self._send("GET", API_PREFIX + path, params=params).text
        return self._json("GET", path, params=params)

    def download_recording_report(self, name: str, path: str | Path,
                                  threshold_n: float | None = None) -> Path:
        """Write recording ``name``'s report as a self-contained HTML page to ``path``."""
        params: dict[str, Any] = {"format": "html"}
        if threshold_n is not None:
            params["threshold_n"] = float(threshold_n)
        return self._download(f"/recordings/{quoted(name)}/report", params, path)

    def delete_recording(self, name: str) -> dict:
        """Delete recording ``name``; returns ``deleted`` and ``bytes`` freed.

        Raises:
            RestError: 404 when there is no such recording, 409 while a session writes it
                (:meth:`stop_recording` first).
        """
        return self._json("DELETE", f"/recordings/{quoted(name)}")

    # -- storage --------------------------------------------------------------------------------
    def storage(self) -> dict:
        """The data directory's usage: ``budget_bytes`` (0: no limit), ``used_bytes``,
        ``reserved_bytes`` (room running recordings may still fill), ``free_bytes`` (the room
        a write has: the smaller of the budget's and the disk's), ``disk_free_bytes`` and
        ``kinds``: per kind (uploads, snapshots, recordings, exports, journal) its ``bytes``,
        ``items`` and whether it is ``counted`` against the budget. Writes that do not fit
        are refused (RestError 413 for an upload over the budget, 507 for a full disk and
        for a snapshot, export or recording over the budget)."""
        return self._json("GET", "/storage")

    def exports(self) -> list[dict]:
        """Export files still on the server (a download that was cut off leaves one until
        the server restarts): ``name``, ``bytes``, ``created`` (Unix s)."""
        return self._json("GET", "/exports")

    def delete_export(self, name: str) -> dict:
        """Delete export ``name`` (as :meth:`exports` lists it); returns ``deleted`` and
        ``bytes`` freed.

        Raises:
            RestError: 404 when there is no such export.
        """
        return self._json("DELETE", f"/exports/{quoted(name)}")

    def uploads(self) -> list[dict]:
        """Uploaded bone files: ``id``, ``source`` (``upload:ID``), ``file``, ``bytes``,
        ``created`` (Unix s), ``in_use_by`` (sessions whose bone came from it)."""
        return self._json("GET", "/uploads")

    def download_upload(self, upload_id: str, path: str | Path) -> Path:
        """Download upload ``upload_id`` (``ID`` or ``upload:ID``) to ``path``, as it was sent.

        Raises:
            RestError: 404 when there is no such upload, 400 for an id this server does not
                issue.
        """
        return self._download(f"/uploads/{quoted(bare_upload_id(upload_id))}", {}, path)

    def delete_upload(self, upload_id: str, force: bool = False) -> dict:
        """Delete upload ``upload_id`` (``ID`` or ``upload:ID``). Returns ``deleted``,
        ``bytes`` freed, ``in_use_by`` (sessions whose bone came from it: they keep it, but
        their reset, and their resume after a restart, would fail) and a ``note`` saying so.
        Such a file is deleted only with ``force`` (else 409).

        Raises:
            RestError: 404 when there is no such upload, 409 while a bone load reads it.
        """
        query = "?force=true" if force else ""
        return self._json("DELETE", f"/uploads/{quoted(bare_upload_id(upload_id))}{query}")
