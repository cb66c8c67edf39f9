"""How much memory one load may take, and the error for a load that would take more.

A load holds the bone it makes — ``density`` and ``labels`` while converting, then the three
bytes a voxel of the shared bone takes (``bone.shared``) — plus what it reads with: a slab of
the file's values at a time (``slabs.SLAB_BYTES``), never the whole source, and what a reader
must keep whole (an ASCII NRRD's values; a colour PNG stack's, when they fit). The budget is
checked from the header, before any voxel is read: a float64 source is never held whole, so
its width does not count, only the bone's.
"""

from __future__ import annotations

from pathlib import Path

from ..bricks import LABEL_WORDS, brick_shape
from .errors import BoneFileError

#: What a load may take beyond the bone it makes, by default: bytes.
DEFAULT_WORK_BYTES = 512 << 20
#: What the conversion holds besides the bone: a slab of source values (``slabs.SLAB_BYTES``),
#: its native and scaled copies, the slab's two uint8 outputs and the decompressor's buffers,
#: with room for the allocator's slack: bytes.
STREAM_WORK_BYTES = 64 << 20


def bone_bytes(shape: tuple[int, ...]) -> int:
    """The bytes a bone of ``shape`` voxels takes: three per voxel (``density``, ``labels``,
    ``swept``) and its brick arrays — the size of its shared file, page rounding aside."""
    n = 1
    for s in shape:
        n *= int(s)
    bricks = 1
    for s in brick_shape(tuple(int(s) for s in shape)):
        bricks *= int(s)
    return 3 * n + bricks * (8 + 4 + 4 + 8 * LABEL_WORDS)


def budget_bytes(shape: tuple[int, ...], limit_bytes: int | None) -> int:
    """The budget of a load of ``shape`` voxels: ``limit_bytes`` when set (a server's
    ``load_budget_bytes``), else the bone's bytes plus :data:`DEFAULT_WORK_BYTES`."""
    if limit_bytes:
        return int(limit_bytes)
    return bone_bytes(shape) + DEFAULT_WORK_BYTES


class BoneTooLarge(BoneFileError):
    """A bone file whose load would take more memory than the load budget. Raised from the
    header, before the voxels are read.

    Attributes:
        need_bytes: what the load would take.
        budget_bytes: what it may take.
    """

    def __init__(self, path: str | Path, problem: str, need_bytes: int,
                 budget_bytes: int) -> None:
        super().__init__(path, problem)
        self.need_bytes = need_bytes
        self.budget_bytes = budget_bytes


def require(path: str | Path, shape: tuple[int, ...], limit_bytes: int | None,
            held_bytes: int = 0, what: str = "") -> None:
    """Refuse a load of a ``shape`` bone that also holds ``held_bytes`` of whole volumes
    (``what`` they are) when it would not fit its budget.

    Raises:
        BoneTooLarge: naming what it needs and the budget.
    """
    budget = budget_bytes(shape, limit_bytes)
    need = bone_bytes(shape) + STREAM_WORK_BYTES + int(held_bytes)
    if need <= budget:
        return
    dims = "×".join(str(int(s)) for s in shape)
    held = f" and {_mib(held_bytes)} for {what}" if held_bytes else ""
    source = ("the server's load_budget_bytes" if limit_bytes
              else f"the bone's {_mib(bone_bytes(shape))} + {_mib(DEFAULT_WORK_BYTES)}")
    raise BoneTooLarge(path, f"loading it needs {_mib(need)} of memory (a {dims} bone takes "
                             f"{_mib(bone_bytes(shape))}{held}), more than the load budget of "
                             f"{_mib(budget)} ({source}): crop or downsample it",
                       need, budget)


def _mib(n: int) -> str:
    return f"{n / (1 << 20):,.0f} MiB"
