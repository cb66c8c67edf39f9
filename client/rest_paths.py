"""What the REST client's calls share: the API's prefix, the transfer chunk size, and how a
name or a flag goes into a URL."""

from __future__ import annotations

from urllib.parse import quote

API_PREFIX = "/v1"
#: Download and upload chunk size, bytes.
CHUNK_BYTES = 1 << 20


def quoted(name: str) -> str:
    """One path segment: a '/' in a name stays in the name (the server refuses it) instead
    of reaching another route."""
    return quote(name, safe="")


def flag(value: bool) -> str:
    """A boolean query parameter as the API reads it."""
    return "true" if value else "false"


def snapshot_name(name: str) -> str:
    """A snapshot's name, with or without its ``snapshot:`` source prefix."""
    return name[len("snapshot:"):] if name.startswith("snapshot:") else name


def bare_upload_id(upload: str) -> str:
    """An upload's id, with or without its ``upload:`` source prefix."""
    return upload[len("upload:"):] if upload.startswith("upload:") else upload
