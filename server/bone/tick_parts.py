"""Cached kernels the round burr's tick calls, compiled on their own: a first start compiles
them in a second process while the tick compiles the rest (``cli.compile_jobs``).

numba compiles a kernel's callees as it types the kernel, loading from its cache any that
another process compiled for the same argument types. The tick (``tick.bone_tick``) passes
these kernels its own arrays and plain numbers, so example values of those types, made here
without a bone, compile the very specializations the tick looks up. Compiled first in another
process, they come from the cache when the tick reaches them: the tick's code is the same
(a cached kernel keeps its bitcode for the caller to link and inline, as a fresh one), and a
first start waits for a shorter tick. The kernels are those the tick reaches last, so they
are cached before it gets there; any it reaches first it compiles itself, as before.
"""

from __future__ import annotations

import numpy as np
from numba import typeof

from ..model.kernels import N_ACC, N_OUT, finish
from .history import BurrPath, history_record
from .shaft import N_SHAFT, shaft_contact
from .voxels import gather_edge


def round_tick_parts() -> list[tuple[object, tuple]]:
    """(kernel, example arguments) for each kernel, in the order the tick reaches them:
    ``voxels.gather_edge`` (a stencil leaving the grid), ``model.kernels.finish`` (the
    force's frame), ``shaft.shaft_contact``, ``history.history_record`` (the burr's path).
    The arguments have the types the tick passes (uint8 voxels, int32 brick counts, float64
    vectors and numbers, the path's own arrays) and are never run."""
    voxels = np.zeros((2, 2, 2), dtype=np.uint8)  # density, swept, labels
    bricks = np.zeros((1, 1, 1), dtype=np.int32)
    table = np.zeros(256)  # Us, Us·K per label
    vector = np.zeros(3)
    path = BurrPath((np.zeros(3), np.ones(3)), carved_before=False)
    return [
        (gather_edge, (voxels, voxels, voxels, table, table, 0, 0, 0, 0.0, 0.0, 0.0)),
        (finish, (np.zeros(N_ACC), *(0.0,) * 9, vector, np.zeros(N_OUT))),
        (shaft_contact, (voxels, voxels, bricks, vector, vector, vector, 0.0, 0.0, 0.0, 0.0,
                         np.zeros(N_SHAFT))),
        (history_record, (path.ring, path.meta, 0.0, 0.0, 0.0, 0.0, True, 0.0)),
    ]


def compile_round_tick_parts() -> None:
    """Compile (or load from the cache) every kernel of :func:`round_tick_parts`."""
    for kernel, example in round_tick_parts():
        kernel.compile(tuple(typeof(value) for value in example))
