"""Cached kernels the round burr's tick calls, compiled on their own, without a bone: a first
start splits the tick's compile between two processes with them (``cli.compile_jobs``).

numba compiles a kernel's callees as it types the kernel, loading from its cache any that
another process compiled for the same argument types. The tick (``tick.bone_tick``) passes
these kernels its own arrays and plain numbers, so example values of those types, made here
without a bone, compile the very specializations the tick looks up. A kernel from the cache
may stay a call where one compiled in the same process would be inlined, so these are
kernels the tick calls once a tick (or only at the grid's edges): its outputs are the same to
the last bit (``tests/test_first_start.py``) and its instruction count the same within noise
(``benchmarks/tick_profile.py``).

- :func:`round_tick_first_parts`: what the tick reaches first (the carve). The tick's own
  process compiles it while the other process builds the bone the tick is then warmed on
  (its brick and phantom kernels), instead of waiting for that bone.
- :func:`round_tick_last_parts`: what the tick reaches last. The other process compiles
  them next, so they are cached before the tick gets there (any it reaches first it
  compiles itself, as it would alone).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import typeof

from ..model.kernels import N_ACC, N_OUT, finish
from .carve import N_TOUCH, carve_voxels
from .carve_hooks import SphereCarve
from .shaft import N_SHAFT, shaft_contact
from .voxels import gather_edge

#: A kernel and example arguments of the types the tick passes it (never run).
Part = tuple[Callable, tuple]

# The bone's arrays as the tick sees them: voxels (density, swept, labels, brick flags) are
# uint8, brick counts int32, brick versions and the coverage cache int64.
_VOXELS = np.zeros((2, 2, 2), dtype=np.uint8)
_COUNTS = np.zeros((1, 1, 1), dtype=np.int32)
_VERSIONS = np.zeros((1, 1, 1), dtype=np.int64)
_VECTOR = np.zeros(3)  # float64 (3,): spacing, centre, axis, the burr's last position
_PER_LABEL = np.zeros(256)  # float64 per label: Us tables, removal
_LABEL_FLAGS = np.zeros(256, dtype=np.uint8)  # forbidden labels


def round_tick_first_parts() -> list[Part]:
    """``carve.carve_voxels`` for the round burr (``carve_hooks.SphereCarve``)."""
    return [(carve_voxels, (SphereCarve(0.0, _VECTOR), _VOXELS, _VOXELS, _VOXELS,
                            _LABEL_FLAGS, _COUNTS, _COUNTS, _VERSIONS, _VOXELS, _VECTOR,
                            _VECTOR, True, 0, _PER_LABEL, np.zeros(N_TOUCH),
                            np.zeros((1, 4)), np.zeros((1, 1, 1), dtype=np.int64), 0))]


def round_tick_last_parts() -> list[Part]:
    """In the order the tick reaches them: ``voxels.gather_edge`` (a stencil leaving the
    grid), ``model.kernels.finish`` (the force's frame), ``shaft.shaft_contact``."""
    return [
        (gather_edge, (_VOXELS, _VOXELS, _VOXELS, _PER_LABEL, _PER_LABEL, 0, 0, 0, 0.0, 0.0,
                       0.0)),
        (finish, (np.zeros(N_ACC), *(0.0,) * 9, _VECTOR, np.zeros(N_OUT))),
        (shaft_contact, (_VOXELS, _VOXELS, _COUNTS, _VECTOR, _VECTOR, _VECTOR, 0.0, 0.0, 0.0,
                         0.0, np.zeros(N_SHAFT))),
    ]


def compile_parts(parts: list[Part]) -> None:
    """Compile (or load from the cache) each kernel of ``parts`` for its example's types."""
    for kernel, example in parts:
        kernel.compile(tuple(typeof(value) for value in example))
