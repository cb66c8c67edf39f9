"""A session's journal record (``session.json``): what it takes to build the session again, and
the checks a record must pass before a restart trusts it.

Format 2 adds ``checksum``: the CRC-32 (8 hex digits) of the record's other keys as compact,
sorted JSON, so a byte changed on disk is caught even where the JSON still parses (a digit of
the key, say). Format 1, what earlier releases wrote, has no checksum and is read as it is.
"""

from __future__ import annotations

import json
import zlib
from pathlib import Path

from ...proto.tag import parse_key
from .sessions import ManagedSession
from .views import parameters_view

FORMAT = "burrforce-journal"
FORMAT_VERSION = 2
#: The versions a restart reads.
READABLE_VERSIONS = (1, 2)


class RecordError(ValueError):
    """A ``session.json`` that cannot be trusted (unreadable, damaged or incomplete)."""


def session_record(session: ManagedSession, stream: int | None) -> dict:
    """What it takes to build ``session`` again (JSON-ready, without its checksum)."""
    params = parameters_view(session)
    params.pop("burr_calibrated")  # follows from the burr
    params.pop("burr_profile_mm")  # likewise
    for name in ("us_n_mm2", "k", "primary_material_name"):  # in the material changes
        params.pop(name)
    source = session.source
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "id": session.id, "key_hex": session.key_hex,
        "source": {"source": source.source, "kind": source.kind,
                   "voxel_mm": source.voxel_mm,
                   "spacing_mm": list(source.spacing_mm) if source.spacing_mm else None,
                   "path": str(source.path) if source.path is not None else None},
        "parameters": params,
        "features": session.features.model_dump(),
        "primary_label": session.primary_label,
        # JSON keys are strings: None (the primary material, before a bone) is "primary".
        "overrides": {("primary" if k is None else str(k)): v
                      for k, v in session.overrides.items()},
        "calibrations": {str(k): v for k, v in session.calibrations.items()},
        "created": session.created_s,
        "next_stream": stream,
        # Its worker's UDP port is the one its engine streams to: resumed on the same one.
        "worker": session.worker,
        "bone_generation": (session.bone_info or {}).get("generation"),
    }


def _checksum(record: dict) -> str:
    body = json.dumps({k: v for k, v in record.items() if k != "checksum"},
                      sort_keys=True, separators=(",", ":"))
    return f"{zlib.crc32(body.encode()):08x}"


def sealed(record: dict) -> str:
    """``record`` with its checksum, as the text ``session.json`` holds."""
    return json.dumps({**record, "checksum": _checksum(record)}, indent=1, sort_keys=True)


_FIELDS = {"id": int, "source": dict, "parameters": dict, "features": dict,
           "overrides": dict, "calibrations": dict, "created": (int, float)}


def read_record(path: Path) -> dict:
    """The record in ``path``, checked: format, checksum (format 2), fields and key.

    Raises:
        RecordError: why it cannot be trusted.
    """
    try:
        record = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise RecordError(f"{path.name} is missing") from None
    except OSError as exc:
        raise RecordError(f"{path.name} cannot be read: {exc.strerror}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecordError(f"{path.name} is not JSON ({exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise RecordError(f"{path.name} is not a {FORMAT} record")
    version = record.get("format_version")
    if version not in READABLE_VERSIONS:
        raise RecordError(f"{path.name} is format {version!r}; this server reads "
                          f"{', '.join(map(str, READABLE_VERSIONS))}")
    if version >= 2 and record.get("checksum") != _checksum(record):
        raise RecordError(f"{path.name} fails its checksum: it was changed or damaged on disk")
    for name, kind in _FIELDS.items():
        if not isinstance(record.get(name), kind) or isinstance(record.get(name), bool):
            raise RecordError(f"{path.name} has no valid {name!r}")
    key = record.get("key_hex")
    if key is not None:
        try:
            if not isinstance(key, str):
                raise ValueError("not a string")
            parse_key(key)
        except ValueError as exc:
            raise RecordError(f"{path.name} holds an invalid key ({exc})") from None
    source = record["source"]
    if not isinstance(source.get("source"), str):
        raise RecordError(f"{path.name} has no valid bone source")
    return record
