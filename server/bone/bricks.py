"""Brick summary of a voxel grid: 8³-voxel bricks that let a tick skip empty space.

Per brick the grid keeps two counts, kept exact by the carving kernel as it goes:
``bone``, voxels that still hold bone (original density > 0 and not fully swept), and
``full``, voxels of pristine full density (255, never swept). A brick with ``bone == 0`` is
empty; one with ``full`` equal to its voxel count is full; anything else is mixed.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BRICK_SHIFT = 3
BRICK = 1 << BRICK_SHIFT  # voxels per brick edge
BRICK_MASK = BRICK - 1

EMPTY = 0
MIXED = 1
FULL = 2


def brick_shape(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple((n + BRICK - 1) >> BRICK_SHIFT for n in shape)  # type: ignore[return-value]


@njit(cache=True, nogil=True)
def count_bricks(density, swept, bone, full):
    """Fill ``bone`` and ``full`` (int32, brick shape) from ``density`` and ``swept`` (uint8,
    voxel shape)."""
    bone[:] = 0
    full[:] = 0
    nx, ny, nz = density.shape
    for i in range(nx):
        bi = i >> BRICK_SHIFT
        for j in range(ny):
            bj = j >> BRICK_SHIFT
            for k in range(nz):
                d = density[i, j, k]
                if d == 0:
                    continue
                c = swept[i, j, k]
                bk = k >> BRICK_SHIFT
                if c < 255:
                    bone[bi, bj, bk] += 1
                if d == 255 and c == 0:
                    full[bi, bj, bk] += 1


@njit(cache=True, nogil=True)
def voxels_per_brick(shape, out):
    """Number of grid voxels inside each brick (edge bricks may be partial)."""
    nbx, nby, nbz = out.shape
    for bi in range(nbx):
        sx = min(BRICK, shape[0] - bi * BRICK)
        for bj in range(nby):
            sy = min(BRICK, shape[1] - bj * BRICK)
            for bk in range(nbz):
                out[bi, bj, bk] = sx * sy * min(BRICK, shape[2] - bk * BRICK)


@njit(cache=True, nogil=True)
def bone_by_label(density, swept, labels, out):
    """Σ density·(255 − swept) per label into ``out`` (float64, (256,)), in units of 255²
    voxel volumes. No temporaries, so a 125 M-voxel grid costs nothing extra."""
    out[:] = 0.0
    nx, ny, nz = density.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                d = density[i, j, k]
                if d != 0:
                    out[labels[i, j, k]] += float(d) * float(255 - swept[i, j, k])


@njit(cache=True, nogil=True)
def forbidden_bricks(density, labels, forbidden, out):
    """``out`` (uint8, brick shape) = 1 where a voxel with bone carries a forbidden label."""
    out[:] = 0
    nx, ny, nz = density.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if density[i, j, k] != 0 and forbidden[labels[i, j, k]] != 0:
                    out[i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT] = 1


#: uint64 words per brick in a label mask: one bit per label (``materials.N_LABELS`` = 256).
LABEL_WORDS = 4


@njit(cache=True, nogil=True)
def brick_labels(density, labels, out):
    """``out`` (uint64, brick shape + (LABEL_WORDS,)): bit ``l`` set where the brick holds a
    voxel with bone (density > 0) labelled ``l``. Kept in a shared bone's file so a session's
    forbidden bricks, for any material table, cost a pass over the bricks, not the voxels."""
    out[:] = 0
    nx, ny, nz = density.shape
    for i in range(nx):
        bi = i >> BRICK_SHIFT
        for j in range(ny):
            bj = j >> BRICK_SHIFT
            for k in range(nz):
                if density[i, j, k] != 0:
                    label = labels[i, j, k]
                    out[bi, bj, k >> BRICK_SHIFT, label >> 6] |= np.uint64(1) << np.uint64(
                        label & 63)


@njit(cache=True, nogil=True)
def forbidden_from_labels(label_mask, forbidden, out):
    """``forbidden_bricks`` from a brick label mask (``brick_labels``): same result, bricks
    only."""
    words = np.zeros(LABEL_WORDS, dtype=np.uint64)
    for label in range(forbidden.shape[0]):
        if forbidden[label] != 0:
            words[label >> 6] |= np.uint64(1) << np.uint64(label & 63)
    nbx, nby, nbz, nw = label_mask.shape
    for bi in range(nbx):
        for bj in range(nby):
            for bk in range(nbz):
                hit = 0
                for w in range(nw):
                    if label_mask[bi, bj, bk, w] & words[w] != 0:
                        hit = 1
                out[bi, bj, bk] = hit
