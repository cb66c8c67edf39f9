"""Recording a session's stream to a file, and replaying it offline (``burrforce replay``).

- :class:`Recorder` writes one row per tick (pose, engine inputs and outputs, reply force and
  torque, removal) to a ``NAME.burrrec/`` directory beside a snapshot of the bone at the start;
  :func:`start_recording` snapshots a session's bone and attaches a recorder to it.
- :func:`read_recording` reads one back (torn chunks reported, not fatal).
- :func:`replay` re-runs it through a fresh engine: exactly, or with other materials.
"""

from .format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    REC_CARVE_RESET,
    ROW_DTYPE,
    SUFFIX,
    Recording,
    RecordingError,
    read_recording,
    recording_path,
)
from .recorder import Recorder, session_meta, start_recording
from .replay import CSV_COLUMNS, ReplayReport, replay

__all__ = [
    "CSV_COLUMNS",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "REC_CARVE_RESET",
    "ROW_DTYPE",
    "SUFFIX",
    "Recorder",
    "Recording",
    "RecordingError",
    "ReplayReport",
    "read_recording",
    "recording_path",
    "replay",
    "session_meta",
    "start_recording",
]
